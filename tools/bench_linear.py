"""Benchmark of the linear SfM solve (paper §3.3) on image-free synthetic problems.

For each scene: ``make_problem`` (GT segments + pixel noise, GT rotations + rotation noise,
GT tracks and relations), ``solve_linear`` with the true mean camera height (metric), then

* ``registered``: fraction of frames registered;
* ``center_err_sim_*``: camera-centre error (m) after a similarity (Umeyama) alignment of the
  registered centres to the ground truth, and relative to the trajectory diameter;
* ``center_err_metric_*``: the same after a translation-only alignment (centroids), i.e. the
  metric scale is tested too;
* ``line_surface_*``: distance (m) of 5 sample points on each valid 3D line to the nearest GT
  surface (``Scene.distance_to_surfaces``) after the translation-only alignment (the similarity
  one when the solution is not metric: no floor relation was available);
* ``seconds``: the solve alone.

Run: ``python tools/bench_linear.py --frames 300 --json out.json`` (``--spin steady``: the steady style)
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from panosfm_graph.cli import section_settings
from panosfm_graph.config import SPIN_STYLES, LinearConfig
from panosfm_graph.errors import InputError
from panosfm_graph.linear import solve_linear
from panosfm_graph.synth.problem import make_problem
from panosfm_graph.evaluate import umeyama


def evaluate(problem, sol) -> dict:
    """Returns the metrics of one solution against the problem's ground truth (module docstring)."""
    reg = sol.registered
    gt = problem.gt_centers
    X, Y = sol.centers[reg], gt[reg]
    diameter = float(np.max(np.linalg.norm(gt[:, None] - gt[None], axis=2)))
    s, R, t = umeyama(X, Y)
    e_sim = np.linalg.norm((s * (R @ X.T)).T + t - Y, axis=1)
    shift = Y.mean(0) - X.mean(0)
    e_met = np.linalg.norm(X + shift - Y, axis=1)
    L = sol.lines
    v = L.valid
    ends = L.endpoints[v]
    fr = np.linspace(0.0, 1.0, 5)[None, :, None]
    pts = (ends[:, None, :3] * (1 - fr) + ends[:, None, 3:] * fr).reshape(-1, 3)
    # metric: translation only; arbitrary scale: the similarity found from the camera centres
    pts = pts + shift if sol.metric else (s * (R @ pts.T)).T + t
    d = problem.scene.distance_to_surfaces(pts) if len(pts) else np.zeros(0)
    return {
        "frames": int(len(reg)),
        "registered": float(reg.mean()),
        "center_err_sim_median_m": float(np.median(e_sim)),
        "center_err_sim_max_m": float(np.max(e_sim)),
        "center_err_sim_rel": float(np.median(e_sim) / diameter),
        "sim_scale": s,
        "center_err_metric_median_m": float(np.median(e_met)),
        "lines_valid": int(v.sum()),
        "lines": int(len(v)),
        "line_surface_median_m": float(np.median(d)) if len(d) else None,
        "line_surface_p90_m": float(np.quantile(d, 0.9)) if len(d) else None,
        "trajectory_diameter_m": diameter,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["living", "bedroom", "office", "random"])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--size", type=int, nargs=2, default=(960, 540))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pixel-noise", type=float, default=0.5, help="px, per endpoint coordinate")
    ap.add_argument("--rot-noise", type=float, default=0.1, help="deg, per frame")
    ap.add_argument("--false-relations", type=float, default=0.0, help="ratio of injected wrong coplanarities")
    ap.add_argument("--no-height", action="store_true", help="solve without the camera height (arbitrary scale)")
    ap.add_argument("--motion-weight", type=float, default=LinearConfig.motion_weight, help="body-motion prior (0: paper)")
    ap.add_argument("--bridge-deg", type=float, default=LinearConfig.motion_bridge_deg,
                    help="motion_bridge_deg: anchor frames this close in turn are linked by the motion prior")
    ap.add_argument("--tracks-first", action="store_true",
                    help="solve from the tracks alone unless the coplanarities are needed to register (option)")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="a LinearConfig setting, e.g. spin_links=true (repeatable)")
    ap.add_argument("--spin", choices=["hand-held", "steady"], default="hand-held",
                    help="the spin style's linear settings (config.SPIN_STYLES; the pipeline's default, auto, keeps "
                         "the steady solve where the bundle adjustment finds the centres on one circle)")
    ap.add_argument("--json", default=None, help="write the results here")
    args = ap.parse_args(argv)
    try:
        sets = section_settings(LinearConfig(), args.set, "linear")
    except InputError as exc:
        ap.error(str(exc))

    results = {}
    for name in args.scenes:
        p = make_problem(name, args.frames, tuple(args.size), args.seed, pixel_noise_px=args.pixel_noise,
                         rot_noise_deg=args.rot_noise, false_relation_ratio=args.false_relations)
        floor_z = p.scene.to_world(np.zeros(3))[2]
        height = None if args.no_height else float(p.gt_centers[:, 2].mean() - floor_z)
        t0 = time.perf_counter()
        settings = {"camera_height_m": height, "motion_weight": args.motion_weight,
                    "tracks_first": args.tracks_first, "motion_bridge_deg": args.bridge_deg,
                    **SPIN_STYLES[args.spin].get("linear", {}), **sets}
        sol = solve_linear(p.preprocessed, p.tracks, p.relations, p.camera, LinearConfig(**settings))
        dt = time.perf_counter() - t0
        r = evaluate(p, sol)
        r["seconds"] = dt
        r["relations"] = p.relations.counts()
        r["tracks"] = int(p.tracks.n)
        r["metric"] = bool(sol.metric)
        results[name] = r
        print(f"{name:8s} reg {r['registered']:.3f}  centre err (sim) {r['center_err_sim_median_m'] * 100:.2f} cm "
              f"({r['center_err_sim_rel'] * 100:.2f} % of {r['trajectory_diameter_m']:.2f} m)  metric "
              f"{r['center_err_metric_median_m'] * 100:.2f} cm  scale {r['sim_scale']:.3f}  "
              f"lines {r['lines_valid']}/{r['lines']} surface med {(r['line_surface_median_m'] or 0) * 100:.2f} cm "
              f"p90 {(r['line_surface_p90_m'] or 0) * 100:.2f} cm  {'metric' if r['metric'] else 'no-scale'}  {dt:.2f} s")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": vars(args), "results": results}, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
