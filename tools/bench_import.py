"""Benchmark of ``panosfm import`` (issue #41 item 4): phone recordings of synthetic spins, imported and reconstructed.

For each room and seed: a synthetic capture with hand tremor (``synthesize(tremor_deg=...)``),
its phone recording (``synth.phone_recording``: mp4 video, raw gyroscope and accelerometer with
noise, bias, a landscape phone's axes and a known time offset), imported twice (with the true
focal length and without one), and the three captures reconstructed and scored against the
ground truth. Printed as a table; ``--json`` writes every figure.

    python tools/bench_import.py --scenes living,bedroom,office --seeds 0 --frames 300 --out OUT

Figures per capture: the time offset's error (ms; and the images' turns' own where the lines
re-timed a smooth spin), the camera axes found, the gyroscope bias
error, the imported attitude's rotation error before any refinement (after the best heading;
median and max, degrees), the focal length the pipeline estimates, and for the original and
the imported captures: registered and accurate frames, rotation error (rotation-only alignment)
and the clicked-corner reprojection (px; only comparable where the focal length is given).
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from panosfm_graph.capture import load_capture, read_imu
from panosfm_graph.config import Config
from panosfm_graph.evaluate import evaluate_reconstruction
from panosfm_graph.geometry import heading_aligned_errors_deg
from panosfm_graph.phone import import_capture
from panosfm_graph.pipeline import run_pipeline
from panosfm_graph.synth import phone_recording, synthesize
from panosfm_graph.synth.phone import LANDSCAPE_CAMERA_FROM_DEVICE


def _scores(capture: Path, out: Path) -> dict:
    res = run_pipeline(capture, out, Config(), rerun=False, views=False)
    m = evaluate_reconstruction(capture, out)
    rp = m.get("reprojection_px") or {}
    ba = res.summary.get("residuals", {}).get("bundle_adjust") or {}
    return {"frames": m["frames"], "registered": m["registered"], "accurate": m["accurate"],
            "rotation_deg": m["rotation_error_rotalign_deg"].get("median"),
            "centre_rel_median": m["center_error_rel"].get("median"), "corners_px": rp.get("median"),
            "focal_px": ba.get("focal_px"), "seconds": res.summary.get("seconds", {}).get("total")}


def one(root: Path, scene: str, seed: int, frames: int, size: tuple[int, int], tremor: float, offset: float,
        sway: float = 0.0) -> dict:
    cap = synthesize(root / "capture", scene=scene, n_frames=frames, size=size, seed=seed, gt_maps=False,
                     tremor_deg=tremor, sway_m=sway)
    rec = phone_recording(cap, root / "phone", offset_s=offset, seed=seed)
    truth = json.loads((rec / "truth.json").read_text())
    gt = load_capture(cap).ground_truth
    f_true = float(json.loads((cap / "camera.json").read_text())["params"][0])
    row = {"scene": scene, "seed": seed, "frames": frames, "size": f"{size[0]}x{size[1]}", "tremor_deg": tremor,
           "sway_m": sway}
    for label, focal in (("focal_given", f_true), ("focal_unknown", None)):
        t0 = time.perf_counter()
        imp = import_capture(rec / "video.mp4", rec / "sensors", root / f"import_{label}", focal_px=focal)
        secs = time.perf_counter() - t0
        _, R_imu = read_imu(imp.path / "imu.csv")
        err = heading_aligned_errors_deg(R_imu, gt.R_wc)
        shutil.copytree(cap / "ground_truth", imp.path / "ground_truth")
        row[label] = {"import_s": round(secs, 2), "offset_err_ms": 1e3 * (imp.offset_s - truth["offset_s"]),
                      "offset_sigma_ms": 1e3 * imp.offset_sigma_s,
                      "offset_from": "lines" if imp.line_timing else f"turns ({imp.sync.band} band)",
                      "tremor_share": imp.sync.tremor_share,
                      "turns_offset_err_ms": 1e3 * (imp.sync.offset_s - truth["offset_s"]),
                      "turns_offset_sigma_ms": 1e3 * imp.sync.offset_sigma_s,
                      "axes_ok": bool(np.array_equal(imp.sync.camera_from_device, LANDSCAPE_CAMERA_FROM_DEVICE)),
                      "bias_err_deg_s": float(np.degrees(np.linalg.norm(imp.attitude.gyro_bias
                                                                        - truth["gyro_bias_rad_s"]))),
                      "attitude_median_deg": float(np.median(err)), "attitude_max_deg": float(err.max()),
                      "lever_arm_m": float(np.linalg.norm(imp.attitude.lever_arm_m)),
                      "run": _scores(imp.path, root / f"out_{label}")}
    row["original"] = {"run": _scores(cap, root / "out_original")}
    row["true_focal_px"] = f_true
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="living,bedroom,office")
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--size", default="960x540")
    ap.add_argument("--tremor", type=float, default=0.2)
    ap.add_argument("--offset", type=float, default=0.237)
    ap.add_argument("--sway", type=float, default=0.0, help="stand point sway, m RMS (a hand-held spin)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    out = Path(args.out)
    rows = []
    for scene in args.scenes.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            root = out / f"{scene}_s{seed}"
            if root.exists():
                shutil.rmtree(root)
            rows.append(one(root, scene, seed, args.frames, size, args.tremor, args.offset, args.sway))
            r = rows[-1]
            for label in ("focal_given", "focal_unknown"):
                g = r[label]
                print(f"{scene} s{seed} {label:13s} offset {g['offset_err_ms']:+.2f} ms +- {g['offset_sigma_ms']:.2f} "
                      f"({g['offset_from']}; turns {g['turns_offset_err_ms']:+.2f} +- {g['turns_offset_sigma_ms']:.2f}), axes "
                      f"{'ok' if g['axes_ok'] else 'WRONG'}, bias err {g['bias_err_deg_s']:.4f} deg/s, attitude "
                      f"{g['attitude_median_deg']:.3f}/{g['attitude_max_deg']:.3f} deg, import {g['import_s']} s; run: "
                      f"{g['run']}", flush=True)
            print(f"{scene} s{seed} original      run: {r['original']['run']}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
