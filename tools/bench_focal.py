"""Benchmark of the focal length estimated without camera.json's (issue #41 item 5), on synthetic spins.

For each scene, horizontal field of view, spin kind and seed: a synthetic capture (``synthesize``; kinds: ``circle``
on an arm, ``sway`` a hand-held spin whose stand point wanders ``--sway`` m, ``tripod`` about the camera), its
``camera.json`` written without ``params``, and the pipeline run up to its preprocessing (the focal length is
estimated before it: ``lines/focal.py``, then ``points/stitch.py``). Printed per capture and written as JSON: the
error of the vanishing points' estimate, which point-track model fitted ("centre": bearings about one centre;
"arm": the camera on the spin's circle), its corners' 90th-percentile distance (and the bearings' where the arm was
fitted), whether it was
taken, and the error of the focal length the rest of the pipeline starts from; seconds of the focal stage.

    python tools/bench_focal.py --scenes living,bedroom,office --hfov 50,64,80 --kinds circle,sway,tripod \\
        --seeds 1 --out OUT [--json OUT/bench_focal.json]
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from panosfm_graph.config import Config
from panosfm_graph.pipeline import run_pipeline
from panosfm_graph.synth import synthesize

KINDS = {"circle": {}, "sway": {"sway_m": None}, "tripod": {"arm_m": 0.0}}


def without_focal(capture: Path) -> float:
    """Rewrites ``capture/camera.json`` without its ``params``; returns the true fx."""
    path = capture / "camera.json"
    cam = json.loads(path.read_text())
    true = float(cam.pop("params")[0])
    path.write_text(json.dumps(cam, indent=2))
    return true


def one(cap: Path, out: Path, true: float, config: Config) -> dict:
    """Returns the focal-length figures of one capture without its focal length (module docstring)."""
    t0 = time.perf_counter()
    res = run_pipeline(cap, out, config, rerun=False, views=False, stop_after="preprocess")
    secs = time.perf_counter() - t0
    est, st = res.focal, res.focal_stitched
    err = lambda f: 100.0 * (f / true - 1.0)  # noqa: E731
    return {"true_px": true, "vp_err_pct": err(est.focal_px),
            "fit": None if st is None else {"model": st.model, "err_pct": err(st.focal_px), "rms_px": st.rms_px,
                                            "p90_px": st.p90_px, "centre_p90_px": st.centre_p90_px,
                                            "accepted": st.accepted, "tracks": st.tracks, "seconds": st.seconds},
            # the focal length the rest of the pipeline goes on with: the capture's camera after the focal stage
            "used_err_pct": err(float(res.capture.camera.K[0, 0])),
            "focal_stage_s": round(res.summary["seconds"].get("focal", float("nan")), 2),
            "run_s": round(secs, 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="living,bedroom,office")
    ap.add_argument("--hfov", default="50,64,80", help="horizontal fields of view (deg)")
    ap.add_argument("--kinds", default="circle,sway,tripod", help=f"spin kinds: {', '.join(KINDS)}")
    ap.add_argument("--sway", type=float, default=0.05, help="stand point wander of the sway kind (m RMS)")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--size", default="640x360")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--seeds", type=int, default=1, help="captures per scene, hfov and kind (seed + 10 j)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    config, rows = Config(), []
    for scene in args.scenes.split(","):
        for hfov in (float(h) for h in args.hfov.split(",")):
            for kind in args.kinds.split(","):
                for j in range(args.seeds):
                    seed = args.seed + 10 * j
                    name = f"{scene}-hfov{hfov:g}-{kind}-s{seed}"
                    cap, out = args.out / "captures" / name, args.out / "runs" / name
                    shutil.rmtree(cap, ignore_errors=True)
                    extra = {k: (args.sway if v is None else v) for k, v in KINDS[kind].items()}
                    synthesize(cap, scene=scene, n_frames=args.frames, size=size, seed=seed, gt_maps=False,
                               hfov_deg=hfov, **extra)
                    row = {"capture": name, "scene": scene, "hfov_deg": hfov, "kind": kind, "seed": seed,
                           **one(cap, out, without_focal(cap), config)}
                    shutil.rmtree(cap, ignore_errors=True)
                    rows.append(row)
                    fit = row["fit"] or {}
                    print(f"{name:32s} vp {row['vp_err_pct']:+6.2f} %  {fit.get('model', '-'):6s} "
                          f"{fit.get('err_pct', float('nan')):+6.2f} % p90 {fit.get('p90_px', float('nan')):.2f} px"
                          f" ({'taken' if fit.get('accepted') else 'not taken'})  used {row['used_err_pct']:+6.2f} %"
                          f"  focal stage {row['focal_stage_s']:.1f} s", flush=True)
    used = np.abs([r["used_err_pct"] for r in rows])
    summary = {"captures": len(rows), "used_abs_err_pct": {"median": float(np.median(used)), "max": float(used.max())},
               "within_1pct": int(np.sum(used <= 1.0)), "rows": rows}
    print(f"used focal length: |error| median {summary['used_abs_err_pct']['median']:.2f} %, max "
          f"{summary['used_abs_err_pct']['max']:.2f} %; within 1 %: {summary['within_1pct']} of {len(rows)}")
    path = args.json or args.out / "bench_focal.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
