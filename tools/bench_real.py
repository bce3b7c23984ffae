"""Benchmark on real images (issue #41): spins cut from real panoramas, with and without a focal length.

For each panorama and seed: ``panosfm synth --panorama`` cuts a zero-baseline spin (exact rotations, an IMU with
heading drift and noise), run once with the focal length given and once with ``camera.json``'s ``params``
deleted (the pipeline estimates it). Printed per capture and written as JSON: the rotation error median over all
frames (rotation-only alignment) of the IMU, the preprocessed and the final rotations; the windows of
``--window`` frames whose final median is worse than the IMU's; whether the zero baseline was found; the centres'
spread; the focal length's error (vanishing points, stitched, final); seconds.

    python tools/bench_real.py --real ../shared/real --seeds 0,1,2 --out OUT [--json OUT/bench_real.json]

The panoramas are test data (``../shared/real``, see its README): never copied into the project.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from panosfm_graph.cache import load_stage
from panosfm_graph.capture import load_capture
from panosfm_graph.config import Config
from panosfm_graph.data import Preprocessed
from panosfm_graph.evaluate import rotation_alignment
from panosfm_graph.export import poses_for_frames, read_colmap_text
from panosfm_graph.geometry import rotation_angle_deg
from panosfm_graph.pipeline import run_pipeline
from panosfm_graph.synth import cut_spin

ROOMS = {"bedroom": None, "bathroom": "bathroom-layout.json"}


def rotation_errors(R: np.ndarray, R_true: np.ndarray) -> np.ndarray:
    """Returns per-frame rotation errors (deg) after the best rotation of all frames (NaN where ``R`` is)."""
    ok = np.all(np.isfinite(R), axis=(1, 2))
    out = np.full(len(R), np.nan)
    B = rotation_alignment(R[ok], R_true[ok])
    out[ok] = rotation_angle_deg(np.einsum("ij,njk->nik", B, R[ok]), R_true[ok])
    return out


def _windows(e: np.ndarray, n: int) -> np.ndarray:
    k = len(e) // n
    return np.array([np.nanmedian(e[i * n:(i + 1) * n]) for i in range(k)])


def score(capture: Path, out: Path, window: int) -> dict:
    """Returns the run's figures (module docstring); ``out`` a finished reconstruction of ``capture``."""
    cap = load_capture(capture)
    gt = cap.ground_truth.R_wc
    model = read_colmap_text(out / "sparse")
    R, C, ok = poses_for_frames(model, cap.frame_names)
    R = np.where(ok[:, None, None], R, np.nan)
    pre = load_stage(sorted((out / "cache").glob("preprocess-*.npz"))[0], Preprocessed)
    e_imu, e_pre, e_fin = rotation_errors(cap.R_wc_imu, gt), rotation_errors(pre.R_wc, gt), rotation_errors(R, gt)
    w_imu, w_fin = _windows(e_imu, window), _windows(e_fin, window)
    summary = json.loads((out / "summary.json").read_text())
    return {"frames": int(len(gt)), "output": int(ok.sum()),
            "zero_baseline": bool((summary.get("zero_baseline") or {}).get("detected")),
            "centre_spread": float(np.max(np.ptp(C[ok], axis=0))) if ok.any() else None,
            "rotation_deg": {"imu": float(np.nanmedian(e_imu)), "preprocessed": float(np.nanmedian(e_pre)),
                             "final": float(np.nanmedian(e_fin))},
            "windows_worse_than_imu": int(np.sum(w_fin > w_imu)), "windows": int(len(w_fin)),
            "focal": summary.get("focal")}


def one(real: Path, room: str, seed: int, root: Path, window: int) -> dict:
    """Cuts, runs and scores one spin, focal length given and not; returns {"given": ..., "estimated": ...}."""
    cap = root / f"{room}-s{seed}"
    if not (cap / "imu.csv").exists():
        layout = ROOMS[room]
        cut_spin(real / f"{room}.png", cap, seed=seed, layout=None if layout is None else real / layout)
    true_f = float(load_capture(cap).camera.K[0, 0])
    nf = root / f"{room}-s{seed}-nofocal"
    if not (nf / "imu.csv").exists():
        shutil.copytree(cap, nf)
        cam = json.loads((nf / "camera.json").read_text())
        cam.pop("params", None)
        (nf / "camera.json").write_text(json.dumps(cam, indent=1))
    res = {"true_focal_px": true_f}
    for name, c in (("given", cap), ("estimated", nf)):
        out = root / "runs" / f"{c.name}"
        t0 = time.perf_counter()
        run_pipeline(c, out, Config(), rerun=False, views=False)
        res[name] = score(c, out, window)
        res[name]["seconds"] = round(time.perf_counter() - t0, 1)
        foc = res[name]["focal"] or {}
        res[name]["focal_error_pct"] = {
            "vanishing_points": _pct((foc.get("estimated") or {}).get("focal_px"), true_f),
            "stitched": _pct((foc.get("stitched") or {}).get("focal_px"), true_f),
            "final": _pct(foc.get("focal_px"), true_f)}
    return res


def _pct(f, true_f: float):
    return None if f is None else round(100.0 * (float(f) / true_f - 1.0), 4)


def _row(name: str, r: dict) -> str:
    rot = r["rotation_deg"]
    fe = r["focal_error_pct"]
    focal = " / ".join("-" if v is None else f"{v:+.3f}" for v in (fe["vanishing_points"], fe["stitched"], fe["final"]))
    return (f"| {name} | {r['output']}/{r['frames']} | {'yes' if r['zero_baseline'] else 'NO'} | {rot['imu']:.3f} | "
            f"{rot['preprocessed']:.3f} | {rot['final']:.3f} | {r['windows_worse_than_imu']}/{r['windows']} | "
            f"{focal} | {r['seconds']:.0f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", default=str(Path(__file__).resolve().parents[2] / "shared" / "real"))
    ap.add_argument("--rooms", default="bedroom,bathroom")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--window", type=int, default=24, help="frames per window compared with the IMU")
    ap.add_argument("--out", required=True)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    real = Path(args.real)
    if not all((real / f"{r}.png").is_file() for r in args.rooms.split(",")):
        print(f"bench_real: no panoramas at {real}", file=sys.stderr)
        return 2
    root = Path(args.out)
    root.mkdir(parents=True, exist_ok=True)
    record = {}
    rows = ["| capture | output | zero baseline | IMU (deg) | preprocessed | final | windows worse than IMU | "
            "focal error % (VPs / stitched / final) | s |", "|---|---|---|---|---|---|---|---|---|"]
    for room in args.rooms.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            r = one(real, room, seed, root, args.window)
            record[f"{room}-s{seed}"] = r
            for name in ("given", "estimated"):
                rows.append(_row(f"{room} seed {seed}, focal {name}", r[name]))
                print(rows[-1], flush=True)
    print("\n".join(rows))
    (Path(args.json) if args.json else root / "bench_real.json").write_text(json.dumps(record, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
