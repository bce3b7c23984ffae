"""iSAM2 against warm-started re-solves (issue 42) on the bundle adjustment's first phase, a small image-free problem.

    python tools/bench_isam2.py [--frames 60] [--batch 15] [--seed 1] [--extra-updates 2] [--relinearize 1e-3]
                                [--json bench_isam2.json]

The problem is :func:`panosfm_graph.synth.make_problem` (living, 480x270, 0.5 px noise) started from its linear
solve; the graph is the BA's phase 1 (lines and centres, rotations fixed: ``graph._build_graph`` with
CustomFactor reprojection terms, no spin prior, no floor). Frames arrive ``--batch`` at a time; a
variable arrives with its frame (a centre) or with the second frame that sees it (a line), a factor with the
last of its variables. Per batch, three ways to the estimate of the frames so far:

* ``isam2``: ``gtsam.ISAM2.update(new factors, new values)`` (GTSAM's relinearisation, checked at every update,
  of the variables whose step exceeds ``--relinearize``), then ``--extra-updates`` empty updates;
* ``resolve``: the project's Levenberg-Marquardt loop (``graph.lm``) over all factors so far, warm-started
  from the last batch's estimate (new variables from the linear solve), on the CustomFactor graph;
* ``resolve_batched``: the same with the reprojection terms vectorised (``LineReprojectionSet``), as the
  pipeline's bundle adjustment solves.

Prints and records each batch's seconds and the last batch's largest centre difference between the three
(m; the room is about 5 m across).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gtsam
import numpy as np


def _problem(frames: int, seed: int):
    from panosfm_graph.config import LinearConfig
    from panosfm_graph.linear import solve_linear
    from panosfm_graph.synth.problem import make_problem

    p = make_problem("living", frames, size=(480, 270), seed=seed, pixel_noise_px=0.5, rot_noise_deg=0.3,
                     imu_drift_deg=0.4)
    return p, solve_linear(p.preprocessed, p.tracks, p.relations, p.camera, LinearConfig())


def _setup(p, initial, config):
    """Returns (graph of BA phase 1 without the reprojection terms, initial values, problem, gauge)."""
    import dataclasses

    from panosfm_graph.graph.factor_graph import _build_graph
    from panosfm_graph.graph.problem import _select, center_key, line_key
    from panosfm_graph.graph.scale import _gauge

    pre = p.preprocessed
    prob = _select(pre, p.tracks, p.relations, initial, config)
    values = gtsam.Values()
    for i in prob.frames:
        values.insert(center_key(i), np.asarray(initial.centers[i], np.float64))
    for t in prob.lines:
        values.insert(line_key(t), np.asarray(initial.lines.taylor[t], np.float64))
    gauge = _gauge(p.relations, prob, initial, pre.manhattan.directions)
    gauge["use_floor"] = False
    mask = np.ones(len(prob.rel_idx), bool)
    other, _, _ = _build_graph(pre, p.relations, prob, 1, initial.R_wc, initial.camera.K, mask,
                               dataclasses.replace(config, reprojection=False), gauge)
    return other, values, prob, gauge


def _reprojection(p, initial, prob, obs: np.ndarray, config, gauge):
    """Returns the phase-1 reprojection terms of the observations ``obs`` (indices into the problem's)."""
    import factors
    from panosfm_graph.graph.factor_graph import reprojection_kernel
    from panosfm_graph.graph.problem import center_key, line_key

    robust, k = reprojection_kernel(config, 1, gauge.get("reprojection_rms_initial", 0.0))
    tr, fr = prob.obs_track[obs], prob.obs_frame[obs]
    ep = p.preprocessed.segments.endpoints.astype(np.float64)[prob.obs_seg[obs]]
    return factors.LineReprojectionSet([line_key(t) for t in tr], [center_key(i) for i in fr], ep,
                                       prob.directions[tr], initial.camera.K, config.reprojection_sigma_px,
                                       R_wc_fixed=initial.R_wc[fr], robust=robust, k=k)


def _arrival(prob, batch: int) -> tuple[dict[int, int], np.ndarray]:
    """Returns key -> the batch it arrives in (a centre with its frame, a line with its second observation) and
    each observation's batch (its frame's, or its line's if later)."""
    from panosfm_graph.graph.problem import center_key, line_key

    arrive = {center_key(int(i)): int(i) // batch for i in prob.frames}
    order = np.lexsort((prob.obs_frame, prob.obs_track))
    tr, fr = prob.obs_track[order], prob.obs_frame[order]
    first = np.flatnonzero(np.r_[True, tr[1:] != tr[:-1]])
    line_batch = {int(tr[a]): int(fr[a + 1]) // batch for a in first}  # every selected track has >= 2
    arrive.update({line_key(t): b for t, b in line_batch.items()})
    obs_batch = np.maximum(prob.obs_frame // batch, [line_batch[int(t)] for t in prob.obs_track])
    return arrive, obs_batch


def _subgraph(graph: gtsam.NonlinearFactorGraph, idx, extra=()) -> gtsam.NonlinearFactorGraph:
    g = gtsam.NonlinearFactorGraph()
    for i in idx:
        g.add(graph.at(int(i)))
    for f in extra:
        g.add(f)
    return g


def _centres(values: gtsam.Values, prob, upto: int, batch: int) -> np.ndarray:
    from panosfm_graph.graph.problem import center_key

    return np.array([values.atPoint3(center_key(int(i))) for i in prob.frames if int(i) // batch <= upto])


def run(frames: int = 60, batch: int = 15, seed: int = 1, extra_updates: int = 2, relinearize: float = 1e-3) -> dict:
    """Returns per-batch seconds of the three ways (module docstring) and their last batch's centre differences."""
    from panosfm_graph.config import GraphConfig
    from panosfm_graph.graph import CHUNK_OBS
    from panosfm_graph.graph.lm import levenberg_marquardt

    config = GraphConfig(spin_sigma_m=0.0, coplanarity_floor=False)
    p, initial = _problem(frames, seed)
    other, init, prob, gauge = _setup(p, initial, config)
    arrive, obs_batch = _arrival(prob, batch)
    fb = np.array([max(arrive.get(k, 0) for k in other.at(i).keys()) for i in range(other.size())], np.int64)
    n_batches = int(max(arrive.values())) + 1
    params = gtsam.ISAM2Params()
    params.relinearizeSkip = 1  # default 10: with a handful of batches it would never relinearise
    params.setRelinearizeThreshold(relinearize)  # default 0.1: 10 cm or so, more than most variables move
    isam = gtsam.ISAM2(params)
    est = {"resolve": gtsam.Values(), "resolve_batched": gtsam.Values()}
    rec: dict = {"frames": frames, "batch": batch, "seed": seed, "extra_updates": extra_updates,
                 "relinearize": relinearize,
                 "observations": int(len(obs_batch)), "other_factors": int(other.size()), "variables": int(init.size()),
                 "seconds": {"isam2": [], "resolve": [], "resolve_batched": []}}
    for b in range(n_batches):
        new_values = gtsam.Values()
        for k in [k for k, a in arrive.items() if a == b]:
            new_values.insert(k, init.atPoint3(k))
        new_obs = np.flatnonzero(obs_batch == b)
        t0 = time.perf_counter()
        rep = _reprojection(p, initial, prob, new_obs, config, gauge).factors(CHUNK_OBS) if len(new_obs) else []
        isam.update(_subgraph(other, np.flatnonzero(fb == b), rep), new_values)
        for _ in range(extra_updates):  # more Gauss-Newton steps on the affected part (relinearised as needed)
            isam.update()
        isam_est = isam.calculateEstimate()
        rec["seconds"]["isam2"].append(round(time.perf_counter() - t0, 3))
        so_far = np.flatnonzero(obs_batch <= b)
        for name in ("resolve", "resolve_batched"):
            v = gtsam.Values(est[name])
            v.insert(new_values)
            t0 = time.perf_counter()
            rep = _reprojection(p, initial, prob, so_far, config, gauge)
            if name == "resolve":
                est[name], _ = levenberg_marquardt(_subgraph(other, np.flatnonzero(fb <= b), rep.factors(CHUNK_OBS)),
                                                   v, config.max_iterations)
            else:
                est[name], _ = levenberg_marquardt(_subgraph(other, np.flatnonzero(fb <= b)), v,
                                                   config.max_iterations, batches=[rep])
            rec["seconds"][name].append(round(time.perf_counter() - t0, 3))
    last = n_batches - 1
    c = {name: _centres(v, prob, last, batch) for name, v in (("isam2", isam_est), *est.items())}
    rec["max_centre_diff_m"] = {"isam2_vs_resolve": float(np.abs(c["isam2"] - c["resolve"]).max()),
                                "resolve_batched_vs_resolve": float(np.abs(c["resolve_batched"] - c["resolve"]).max())}
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--batch", type=int, default=15)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--extra-updates", type=int, default=2, help="empty iSAM2 updates after each batch's")
    ap.add_argument("--relinearize", type=float, default=1e-3, help="iSAM2's relinearisation threshold")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    rec = run(args.frames, args.batch, args.seed, args.extra_updates, args.relinearize)
    print(f"{rec['frames']} frames in batches of {rec['batch']}: {rec['variables']} variables, "
          f"{rec['observations']} observations, "
          f"{rec['other_factors']} other factors")
    for name, secs in rec["seconds"].items():
        print(f"  {name:16s} per batch {secs}  total {sum(secs):.2f} s")
    print(f"  last batch, largest centre difference (m): {rec['max_centre_diff_m']}")
    if args.json:
        args.json.write_text(json.dumps(rec, indent=2))


if __name__ == "__main__":
    main()
