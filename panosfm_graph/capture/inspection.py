"""inspect_capture / format_inspection: describe a capture (``panosfm inspect``), also one the IMU does not cover."""
from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from .camera import read_camera
from .frames import _read_source, _timestamps
from .imu import TIME_TOL_S, imu_coverage, read_imu, turn_span_deg
from .validate import _root


def inspect_capture(path: str | Path) -> dict[str, Any]:
    """Returns a description of a capture: frames, resolution, camera, fps, duration, IMU coverage, ground truth.

    Structural problems (a missing or malformed file) raise :class:`InputError`
    as in :func:`load_capture`; frames outside the IMU span are reported in
    ``imu.coverage`` and ``problems`` instead.
    """
    root = _root(path)
    camera_json = root / "camera.json"
    camera, fps = read_camera(camera_json)
    t_imu, R_imu = read_imu(root / "imu.csv")
    source = _read_source(root, camera, camera_json)
    t, t_from, rate = _timestamps(root, source, fps)
    inside = imu_coverage(t_imu, t)
    problems = []
    during = (t_imu >= t[0] - TIME_TOL_S) & (t_imu <= t[-1] + TIME_TOL_S) if len(t) else np.zeros(0, bool)
    turn = turn_span_deg(R_imu[during]) if during.sum() >= 2 else turn_span_deg(R_imu)
    if not inside.all():
        out = t[~inside]
        problems.append(f"imu.csv: {int((~inside).sum())} of {len(t)} frames (times {out.min():.3f}.."
                        f"{out.max():.3f} s) lie outside the IMU time span {t_imu[0]:.3f}..{t_imu[-1]:.3f} s")
    gt_dir = root / "ground_truth"
    gt = None
    if gt_dir.is_dir():
        def count(sub: str) -> int:
            d = gt_dir / sub
            return sum(1 for s in source.stems if (d / f"{s}.npy").is_file()) if d.is_dir() else 0

        def rows(name: str) -> int | None:
            p = gt_dir / name
            if not p.is_file():
                return None
            with open(p, newline="", encoding="utf-8-sig") as f:
                return max(0, sum(1 for r in csv.reader(f) if r and any(c.strip() for c in r)) - 1)

        gt = {"poses": rows("poses.csv"), "lines": rows("lines.csv"), "scene": (gt_dir / "scene.json").is_file(),
              "normals": count("normals"), "depth": count("depth")}
    duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    imu_span = float(t_imu[-1] - t_imu[0])
    return {
        "path": str(root),
        "source": source.kind if source.kind == "frames" else source.paths[0].name,
        "frames": len(source.names),
        "resolution": [camera.width, camera.height],
        "camera_model": camera.model,
        "params": [float(p) for p in camera.params],
        "fps": round(rate, 4),
        "timestamps_from": t_from,
        "time_span_s": [float(t[0]), float(t[-1])] if len(t) else None,
        "duration_s": round(duration, 4),
        "imu": {
            "rows": len(t_imu),
            "rate_hz": round((len(t_imu) - 1) / imu_span, 3),
            "time_span_s": [float(t_imu[0]), float(t_imu[-1])],
            "turn_deg": round(turn, 2),
            "coverage": {"frames_inside": int(inside.sum()), "frames_outside": int((~inside).sum()),
                         "fraction": float(inside.mean()) if len(inside) else 0.0},
        },
        "ground_truth": gt,
        "problems": problems,
    }


def format_inspection(info: dict[str, Any]) -> str:
    """Returns :func:`inspect_capture`'s description as a readable multi-line table."""
    imu = info["imu"]
    cov = imu["coverage"]
    span = info["time_span_s"] or [0.0, 0.0]
    model = info["camera_model"]
    params = ", ".join("?" if p != p else f"{p:g}" for p in info["params"])  # NaN: the focal length is not given
    if any(p != p for p in info["params"]):
        params += "; focal length unknown: panosfm run estimates it"
    rows = [
        ("capture", info["path"]),
        ("frames", f"{info['frames']} from {info['source']}"),
        ("resolution", f"{info['resolution'][0]} x {info['resolution'][1]}"),
        ("camera", f"{model} [{params}]" + (" (frames are undistorted on load)" if model == "OPENCV" else "")),
        ("fps", f"{info['fps']:g} (timestamps from {info['timestamps_from']})"),
        ("duration", f"{info['duration_s']:.3f} s  ({span[0]:.3f} .. {span[1]:.3f} s)"),
        ("IMU", f"{imu['rows']} rows, {imu['rate_hz']:g} Hz, {imu['time_span_s'][0]:.3f} .. "
                f"{imu['time_span_s'][1]:.3f} s, heading turns {imu.get('turn_deg', 0.0):g} deg"),
        ("IMU coverage", f"{cov['frames_inside']} of {info['frames']} frames ({100 * cov['fraction']:.1f}%)"),
    ]
    gt = info["ground_truth"]
    if gt is None:
        rows.append(("ground truth", "none"))
    else:
        parts = []
        if gt["poses"] is not None:
            parts.append(f"poses ({gt['poses']})")
        if gt["lines"] is not None:
            parts.append(f"lines ({gt['lines']})")
        if gt["scene"]:
            parts.append("scene.json")
        if gt["normals"]:
            parts.append(f"normals ({gt['normals']} frames)")
        if gt["depth"]:
            parts.append(f"depth ({gt['depth']} frames)")
        rows.append(("ground truth", ", ".join(parts) or "empty folder"))
    for p in info["problems"]:
        rows.append(("PROBLEM", p))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
