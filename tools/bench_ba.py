"""Benchmark of the factor-graph bundle adjustment (paper §3.4) on synthetic problems.

For each scene: build an image-free problem (``synth.problem.make_problem``),
an initial solution (the linear solve when ``--init linear`` and
``panosfm_graph.linear`` exists; else ground truth perturbed: centres and
lines with Gaussian noise, rotations = the problem's noisy preprocessed
rotations), run ``bundle_adjust`` and report, before and after BA:

* registered ratio;
* camera-centre error after a similarity alignment of the centres to ground
  truth (Umeyama, as evo's ``--align --correct_scale``), median, in % of the
  ground-truth trajectory diameter (largest distance between two centres);
* rotation error (median angle of R_gt^T R, degrees; no alignment);
* line-to-surface distance: median distance (m) from the reconstructed line
  segments' endpoints and midpoints, after the same alignment, to the
  nearest scene surface (shell or box face);
* seconds per phase and in total, peak RSS of the process (an upper bound:
  includes problem generation).

``--clutter N`` hangs N thin wall panels in the room (more edges) and
``--fragment L`` cuts tracks into pieces of L observations (as real tracking
breaks them) to reach the size of a real 300-frame capture (~3,000 tracks).

    python tools/bench_ba.py --frames 300 --clutter 60 --fragment 6 --cache /tmp/bench_ba --scenes living bedroom office

``--real DIR`` benchmarks BA on REAL pipeline output instead: each scene is
synthesised as a capture under DIR (once), run through the pipeline up to the
linear solve (``run_pipeline(..., stop_after="linear", resume=True)``, cached
under DIR), then ``bundle_adjust`` (or ``bundle_adjust_incremental`` with
``--incremental N``) is timed on that output. The linear and the BA solutions
are both written with ``export.export_reconstruction`` and measured with
``evaluate.evaluate_reconstruction``: exactly ``panosfm eval``'s metrics.

    python tools/bench_ba.py --real /tmp/bench_ba_real --frames 300 --size 960 540 --normals oracle
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import sys
import time

import numpy as np

import factors
from panosfm_graph.config import GraphConfig
from panosfm_graph.data import Solution
from panosfm_graph.geometry import rotation_angle_deg
from panosfm_graph.graph import bundle_adjust, bundle_adjust_incremental, steady_or_hand_held
from panosfm_graph.evaluate import umeyama


def add_clutter(scene, n: int, seed: int = 0):
    """Returns ``scene`` with ``n`` thin rectangular panels (2 cm deep) added on its four walls."""
    if n <= 0:
        return scene
    rng = np.random.default_rng(seed)
    W, D, H = np.asarray(scene.room_max) - np.asarray(scene.room_min)
    lo0 = np.asarray(scene.room_min, float)
    wall = rng.integers(0, 4, n)
    width = rng.uniform(0.15, 0.5, n)
    height = rng.uniform(0.15, 0.5, n)
    z0 = rng.uniform(0.3, H - 0.6, n)
    along = np.where(wall < 2, W, D)
    u0 = rng.uniform(0.05, 1.0, n) * np.maximum(along - width - 0.05, 0.0)
    t = 0.02
    mins = np.zeros((n, 3))
    maxs = np.zeros((n, 3))
    # walls 0: -y, 1: +y (panel spans x), 2: -x, 3: +x (panel spans y)
    mins[:, 2], maxs[:, 2] = z0, z0 + height
    sx = wall < 2
    mins[sx, 0], maxs[sx, 0] = u0[sx], u0[sx] + width[sx]
    mins[sx, 1] = np.where(wall[sx] == 0, 0.0, D - t)
    maxs[sx, 1] = mins[sx, 1] + t
    mins[~sx, 1], maxs[~sx, 1] = u0[~sx], u0[~sx] + width[~sx]
    mins[~sx, 0] = np.where(wall[~sx] == 2, 0.0, W - t)
    maxs[~sx, 0] = mins[~sx, 0] + t
    mins += lo0
    maxs += lo0
    return dataclasses.replace(
        scene,
        boxes_min=np.vstack([scene.boxes_min.reshape(-1, 3), mins]),
        boxes_max=np.vstack([scene.boxes_max.reshape(-1, 3), maxs]),
        box_names=tuple(scene.box_names) + tuple(f"panel_{i}" for i in range(n)),
        box_kinds=tuple(scene.box_kinds) + ("poster",) * n,
        box_colors=np.vstack([scene.box_colors.reshape(-1, 3), rng.uniform(0.2, 0.9, (n, 3))]),
    )


def fragment_tracks(p, max_obs: int):
    """Returns ``p`` with every track cut into pieces of at most ``max_obs`` consecutive observations.

    Real line tracking breaks tracks; this reaches a real capture's track
    count. A relation (a, b) is kept for every piece of a, paired with the
    piece of b nearest in time (FLOOR: every piece of a).
    """
    from panosfm_graph.data import FLOOR, Relations, Tracks

    if max_obs <= 0:
        return p
    tr = p.tracks.track_of
    seg = np.flatnonzero(tr >= 0)
    seg = seg[np.lexsort((p.preprocessed.segments.frame[seg], tr[seg]))]
    t = tr[seg]
    first = np.r_[0, np.flatnonzero(np.diff(t)) + 1]
    rank = np.arange(len(seg)) - np.repeat(first, np.diff(np.r_[first, len(seg)]))
    piece = rank // max_obs
    key = t.astype(np.int64) * 100000 + piece
    uniq, new_id = np.unique(key, return_inverse=True)
    parent = (uniq // 100000).astype(int)
    track_of = np.full_like(tr, -1)
    track_of[seg] = new_id
    frames = p.preprocessed.segments.frame[seg]
    mid_frame = np.bincount(new_id, weights=frames) / np.bincount(new_id)
    tracks = Tracks(track_of.astype(np.int32), p.tracks.axis[parent].astype(np.int8))
    rel = p.relations
    pieces_of = [np.flatnonzero(parent == k) for k in range(p.tracks.n)]
    ka, kb, kk, kn, ks, ktrue = [], [], [], [], [], []
    for r in range(rel.n):
        for a in pieces_of[rel.track_a[r]]:
            if rel.kind[r] == FLOOR:
                b = -1
            else:
                cand = pieces_of[rel.track_b[r]]
                b = cand[np.argmin(np.abs(mid_frame[cand] - mid_frame[a]))]
            ka.append(a), kb.append(b), kk.append(rel.kind[r]), kn.append(rel.normal_axis[r]), ks.append(rel.support[r])
            ktrue.append(True if p.relation_true is None else p.relation_true[r])
    relations = Relations(np.array(kk, np.int8), np.array(ka, np.int32), np.array(kb, np.int32),
                          np.array(kn, np.int8), np.array(ks, np.int32))
    return dataclasses.replace(p, tracks=tracks, relations=relations, gt_track_lines=p.gt_track_lines[parent],
                               relation_true=np.array(ktrue, bool))


def perturbed_solution(p, seed: int = 0, center_sigma_m: float = 0.03, line_sigma_m: float = 0.05) -> Solution:
    """Returns GT with noisy centres/lines (first centre exact) and the problem's noisy rotations."""
    rng = np.random.default_rng(seed)
    g = p.gt_solution()
    lam = factors.taylor_from_point_direction(g.lines.taylor + rng.normal(size=g.lines.taylor.shape) * line_sigma_m,
                                              g.lines.direction)
    c = g.centers + rng.normal(size=g.centers.shape) * center_sigma_m
    c[0] = g.centers[0]
    return dataclasses.replace(g, R_wc=p.preprocessed.R_wc.copy(), centers=c,
                               lines=dataclasses.replace(g.lines, taylor=lam))


def surface_distance(scene, pts_world: np.ndarray) -> np.ndarray:
    """Returns (N,) distance (m) of world points to the nearest face of the scene's shell and boxes."""
    mins, maxs = scene.all_boxes()
    P = scene.to_room(pts_world)
    best = np.full(len(P), np.inf)
    for k in range(3):
        for side in (mins, maxs):
            lo, hi = mins.copy(), maxs.copy()
            lo[:, k] = hi[:, k] = side[:, k]
            q = np.clip(P[:, None, :], lo[None], hi[None])
            best = np.minimum(best, np.min(np.linalg.norm(P[:, None, :] - q, axis=2), axis=1))
    return best


def metrics(p, sol: Solution) -> dict:
    """Returns the benchmark's metrics of ``sol`` against the problem's ground truth (module docstring)."""
    reg = sol.registered & np.all(np.isfinite(sol.centers), axis=1)
    gt_c = p.gt_centers[reg]
    diam = float(np.max(np.linalg.norm(p.gt_centers[:, None] - p.gt_centers[None], axis=2)))
    s, R, t = umeyama(sol.centers[reg], gt_c)
    c_al = (s * sol.centers[reg] @ R.T) + t
    cerr = np.linalg.norm(c_al - gt_c, axis=1)
    rot = rotation_angle_deg(p.gt_R_wc[reg], sol.R_wc[reg])
    ok = sol.lines.valid
    ep = sol.lines.endpoints[ok]
    pts = np.concatenate([ep[:, :3], ep[:, 3:], 0.5 * (ep[:, :3] + ep[:, 3:])])
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    pts_al = (s * pts @ R.T) + t
    surf = surface_distance(p.scene, pts_al) if len(pts_al) else np.array([np.nan])
    return {"registered_ratio": float(reg.mean()), "center_err_pct_diam": float(100 * np.median(cerr) / diam),
            "center_err_m": float(np.median(cerr)), "trajectory_diameter_m": diam,
            "rot_err_deg": float(np.median(rot)), "line_surface_m": float(np.median(surf))}


def run_scene(name: str, args) -> dict:
    """Returns the benchmark record of one scene."""
    from panosfm_graph.synth import make_scene
    from panosfm_graph.synth.problem import make_problem

    import pickle
    from pathlib import Path

    t0 = time.perf_counter()
    tag = f"{name}-{args.frames}-{args.size[0]}x{args.size[1]}-c{args.clutter}-s{args.seed}-n{args.pixel_noise}-r{args.rot_noise}-f{args.false_ratio}"
    cached = Path(args.cache) / f"{tag}.pkl" if args.cache else None
    if cached is not None and cached.exists():
        p = pickle.loads(cached.read_bytes())
    else:
        scene = add_clutter(make_scene(name, args.seed), args.clutter, args.seed)
        p = make_problem(scene, args.frames, size=tuple(args.size), seed=args.seed, pixel_noise_px=args.pixel_noise,
                         rot_noise_deg=args.rot_noise, false_relation_ratio=args.false_ratio)
        if cached is not None:
            cached.parent.mkdir(parents=True, exist_ok=True)
            cached.write_bytes(pickle.dumps(p))
    p = fragment_tracks(p, args.fragment)
    t_make = time.perf_counter() - t0
    initial = None
    if args.init == "linear":
        from panosfm_graph.config import LinearConfig
        from panosfm_graph.linear import solve_linear
        initial = solve_linear(p.preprocessed, p.tracks, p.relations, p.camera, LinearConfig())
    else:
        initial = perturbed_solution(p, args.seed)
    cfg = GraphConfig(max_iterations=args.iters)
    t0 = time.perf_counter()
    if args.incremental:
        sol = bundle_adjust_incremental(p.preprocessed, p.tracks, p.relations, initial, cfg, batch_frames=args.incremental)[-1]
    else:
        sol = bundle_adjust(p.preprocessed, p.tracks, p.relations, initial, cfg)
    t_ba = time.perf_counter() - t0
    rec = {
        "scene": name, "frames": p.n_frames, "tracks": p.tracks.n, "observations": int(np.sum(p.tracks.track_of >= 0)),
        "relations": p.relations.counts(), "seconds_make": round(t_make, 2), "seconds_ba": round(t_ba, 2),
        "seconds_per_phase": {k: round(v["seconds"], 2) for k, v in sol.residuals["phases"].items()},
        "before": metrics(p, initial), "after": metrics(p, sol),
        "relations_rejected": sol.residuals["relations_rejected"],
        "reprojection_rms_px": [round(sol.residuals["reprojection_rms_px_initial"], 3),
                                round(sol.residuals["reprojection_rms_px"], 3)],
        "focal_px": [float(p.camera.K[0, 0]), round(sol.residuals["focal_px"], 3)],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }
    if p.relation_true is not None and args.false_ratio > 0:
        rej = np.array(sol.residuals["rejected_relations"], int)
        rec["rejected_false"] = int(np.sum(~p.relation_true[rej])) if len(rej) else 0
        rec["false_injected"] = int(np.sum(~p.relation_true))
    return rec


REAL_METRICS = (  # (name, path in evaluate_reconstruction's dict, lower is better)
    ("registered_ratio", ("registered_ratio",), False),
    ("center_err_rel_median", ("center_error_rel", "median"), True),
    ("rot_err_deg_median", ("rotation_error_deg", "median"), True),
    ("rot_err_rotalign_deg_median", ("rotation_error_rotalign_deg", "median"), True),
    ("reproj_px_mean", ("reprojection_px", "mean"), True),
    ("reproj_px_median", ("reprojection_px", "median"), True),
    ("line_surface_m_median", ("lines", "distance_m", "median"), True),
    ("lines", ("lines", "lines"), False),
    ("edges_recovered", ("lines", "recovered"), False),
)


def _dig(d, path):
    for k in path:
        if d is None:
            return None
        d = d.get(k)
    return d


def real_metrics(capture, solution: Solution, workdir) -> dict:
    """Returns ``panosfm eval``'s headline metrics of ``solution`` (exported into ``workdir``, then evaluated)."""
    from panosfm_graph.evaluate import evaluate_reconstruction
    from panosfm_graph.export import export_reconstruction

    export_reconstruction(workdir, solution, capture.frame_names)
    m = evaluate_reconstruction(capture, workdir)
    return {name: _dig(m, path) for name, path, _ in REAL_METRICS}


def run_real_scene(name: str, args) -> dict:
    """Returns the benchmark record of one scene through the real pipeline (module docstring, ``--real``)."""
    import logging
    import tempfile
    from pathlib import Path

    from panosfm_graph.config import Config, with_overrides
    from panosfm_graph.pipeline import run_pipeline
    from panosfm_graph.synth.writer import synthesize

    logging.getLogger("panosfm").setLevel(logging.WARNING)
    root = Path(args.real)
    W, H = args.size
    cap = root / f"cap_{name}-{args.frames}-{W}x{H}-s{args.seed}"
    if not cap.exists():
        synthesize(cap, name, args.frames, (W, H), args.seed)
    overrides = {"linear": {"camera_height_m": args.camera_height}}
    if args.normals:
        overrides["normals"] = {"source": args.normals}
    config = with_overrides(Config(), **overrides)
    gcfg = dataclasses.replace(config.graph, max_iterations=args.iters)
    out = root / f"run_{cap.name}-{args.normals or 'default'}"
    t0 = time.perf_counter()
    res = run_pipeline(cap, out, config, resume=True, stop_after="linear", rerun=False, views=False)
    t_front = time.perf_counter() - t0
    pre, tracks, rel, lin = res.preprocessed, res.tracks, res.relations, res.linear
    t0 = time.perf_counter()
    per_batch = []
    if args.incremental:
        sols = bundle_adjust_incremental(pre, tracks, rel, lin, gcfg, batch_frames=args.incremental,
                                         on_batch=lambda k, s: per_batch.append(time.perf_counter()))
        sol = sols[-1]
    else:
        sol = bundle_adjust(pre, tracks, rel, lin, gcfg)
    if not args.incremental or gcfg.incremental_final_solve:
        # as the pipeline: the auto spin style (graph.steady_auto) may keep a steady solve instead
        sol, steady_linear = steady_or_hand_held(pre, tracks, rel, lin.camera, config.linear, gcfg, sol)
        lin = steady_linear or lin  # "before": the linear solve the result rests on
    t_ba = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        before = real_metrics(res.capture, lin, Path(tmp) / "linear")
        after = real_metrics(res.capture, sol, Path(tmp) / "ba")
    rec = {
        "scene": name, "frames": int(len(lin.registered)), "size": f"{W}x{H}", "normals": args.normals or "default",
        "spin_style": sol.residuals.get("spin_style"),
        "tracks": tracks.n, "observations": int(np.sum(tracks.track_of >= 0)), "relations": rel.counts(),
        "seconds_pipeline_to_linear": round(t_front, 2), "seconds_ba": round(t_ba, 2),
        "seconds_per_phase": {k: round(v["seconds"], 2) for k, v in sol.residuals.get("phases", {}).items()},
        "before": before, "after": after,
        "ba_factors": sol.residuals.get("factors"), "relations_rejected": sol.residuals.get("relations_rejected"),
        "reprojection_rms_px": [sol.residuals.get("reprojection_rms_px_initial"), sol.residuals.get("reprojection_rms_px")],
        "focal_px": [float(lin.camera.K[0, 0]), sol.residuals.get("focal_px")],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }
    if per_batch:
        rec["seconds_per_batch"] = list(np.round(np.diff(np.r_[t0, per_batch]), 2))
    return rec


def real_improves(rec: dict) -> bool:
    """Returns whether BA is no worse than the linear solve on every lower-is-better metric and keeps every frame."""
    b, a = rec["before"], rec["after"]
    ok = all(a[n] is not None and (b[n] is None or a[n] <= b[n]) for n, _, low in REAL_METRICS if low)
    return ok and a["registered_ratio"] >= b["registered_ratio"] - 1e-9


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["living", "bedroom", "office"])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--size", type=int, nargs=2, default=[640, 360])
    ap.add_argument("--clutter", type=int, default=0, help="thin wall panels added to each scene")
    ap.add_argument("--fragment", type=int, default=0, help="cut tracks into pieces of at most this many observations")
    ap.add_argument("--cache", default="", help="directory to keep generated problems in (pickle)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pixel-noise", type=float, default=0.5)
    ap.add_argument("--rot-noise", type=float, default=0.3)
    ap.add_argument("--false-ratio", type=float, default=0.0)
    ap.add_argument("--iters", type=int, default=30)
    ap.add_argument("--init", choices=["perturbed", "linear"], default="perturbed")
    ap.add_argument("--incremental", type=int, default=0, help="frames per batch (0: one batch solve)")
    ap.add_argument("--real", default="", help="directory for captures and pipeline runs: benchmark real pipeline output")
    ap.add_argument("--normals", choices=["model", "orientation-map", "oracle"], default=None,
                    help="--real: normals source (default: the Config's)")
    ap.add_argument("--camera-height", type=float, default=1.5, help="--real: camera height (m) for metric scale")
    args = ap.parse_args(argv)
    out = []
    if args.real:
        for name in args.scenes:
            rec = run_real_scene(name, args)
            out.append(rec)
            print(json.dumps(rec, default=float), flush=True)
        print(json.dumps({"ba_improves_every_metric": all(real_improves(r) for r in out)}))
        return 0
    for name in args.scenes:
        rec = run_scene(name, args)
        out.append(rec)
        print(json.dumps(rec), flush=True)
    ok = all(r["after"][k] <= r["before"][k] for r in out for k in ("center_err_pct_diam", "rot_err_deg", "line_surface_m"))
    print(json.dumps({"ba_improves_every_metric": ok}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
