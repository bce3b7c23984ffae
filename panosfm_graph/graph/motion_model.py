"""Frames the lines do not fix, placed by the spin's motion model with their uncertainty (our addition; issue #40).

After the bundle adjustment some frames have no pose: their lines do not
determine their centre (a blank wall, lines along one axis only). A person's
spin still tells where they were: the phone on the arm about a stand point
that wanders smoothly (:mod:`factors.spin_prior`). :func:`place_by_motion_model`
builds one GTSAM graph of

* the line-fixed frames' centres, held where the bundle adjustment put them
  (a tight prior each);
* the spin model over every frame: stand-point knots a fixed turn apart tied
  by a random walk, one arm; each centre on the circle within
  ``graph.spin_sigma_m`` (robust for the line-fixed ones, Gaussian for the
  frames to place);
* for each frame to place, its observations of the adjusted 3D lines (held)
  at its refined rotation: a frame whose lines fix its centre along one axis
  keeps that, the motion model supplies the rest;

solves it, and reads each placed centre's marginal covariance. A frame whose
largest std is at most ``graph.motion_max_sigma_rel`` of the spin's diameter
gets that pose (source "motion model"); the others stay without one, with
the reason. ``graph.motion_model`` False (``panosfm run --strict``): only
line-fixed frames, as before.
"""
from __future__ import annotations

import dataclasses
import logging
import time

import gtsam
import numpy as np

import factors

from ..config import GraphConfig
from ..data import Preprocessed, Solution, Tracks
from ..geometry import turned_degrees
from .factor_graph import reprojection_kernel
from .problem import ARM_KEY, center_key, line_key, stand_key
from .spin import fit_spin

log = logging.getLogger("panosfm.graph")

HOLD_SIGMA = 1e-4  # solution units: the line-fixed centres and the lines are held
MIN_FIXED = 6  # fewer line-fixed frames: no motion model


def place_by_motion_model(pre: Preprocessed, tracks: Tracks, sol: Solution, config: GraphConfig) -> Solution:
    """Returns ``sol`` with the frames the motion model places within its sigma bound registered (module docstring).

    ``residuals["frame_source"]`` (per frame: "lines", "steady circle" where the steady style placed it,
    "motion model" or None),
    ``residuals["frame_sigma_rel"]`` (per frame: the placed centre's largest std over the spin's diameter;
    None for line-fixed and unplaced frames) and ``residuals["motion_model"]`` (counts, bound, seconds).
    """
    F = len(sol.registered)
    res = dict(sol.residuals)
    given = res.get("frame_source")  # the steady style's (graph.style): "lines" or "steady circle"
    source = list(given) if given is not None and len(given) == F else np.where(sol.registered, "lines", None).tolist()
    source = [s if r else None for s, r in zip(source, sol.registered)]
    res["frame_source"], res["frame_sigma_rel"] = source, [None] * F
    fixed = np.flatnonzero(sol.registered)
    todo = np.flatnonzero(~sol.registered & np.all(np.isfinite(pre.R_wc), axis=(1, 2)))
    if not config.motion_model or not len(todo) or len(fixed) < MIN_FIXED:
        return dataclasses.replace(sol, residuals=res)
    t0 = time.perf_counter()
    M = pre.manhattan.directions
    R = np.where(sol.registered[:, None, None], sol.R_wc, pre.R_wc)
    j, alpha, n_knots = factors.spin_knots(turned_degrees(R), config.spin_knot_deg)
    stand, arm, _ = fit_spin(sol.centers[fixed], R[fixed][:, :, 2], M, j[fixed], alpha[fixed], n_knots,
                               walk_weight=config.spin_sigma_m / config.spin_walk_sigma_m)
    diameter = 2.0 * float(np.hypot(*arm))
    if not np.isfinite(diameter) or diameter <= 0:
        return dataclasses.replace(sol, residuals=res)
    # a placed frame is off the model by the BA's spin prior std (measured: its error over that std was 0.96 / 1.09 on
    # two captures swaying 5 cm; the line-fixed frames' own RMS about the model, alone or cross-validated, put it
    # 1.7x too small on one and 1.3x too large on the other: docs/decisions.md#motion-model-placement)
    model_sigma = config.spin_sigma_m

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    hold = gtsam.noiseModel.Isotropic.Sigma(3, HOLD_SIGMA)
    vertical = model_sigma * config.spin_vertical_ratio
    fixed_noise = factors.spin_noise(model_sigma, vertical, config.spin_robust, config.robust_k)
    free_noise = factors.spin_noise(model_sigma, vertical)
    for k in range(n_knots):
        values.insert(stand_key(k), stand[k])
        if k:
            graph.add(gtsam.BetweenFactorPoint3(stand_key(k - 1), stand_key(k), np.zeros(3),
                                                gtsam.noiseModel.Isotropic.Sigma(3, config.spin_walk_sigma_m)))
    values.insert(ARM_KEY, arm)
    for i in np.concatenate([fixed, todo]):
        free = not sol.registered[i]
        if free:
            values.insert(center_key(i), _predict(stand, arm, M, R[i][None, :, 2], j[i:i + 1], alpha[i:i + 1])[0])
        else:
            values.insert(center_key(i), sol.centers[i])
            graph.add(gtsam.PriorFactorPoint3(center_key(i), sol.centers[i], hold))
        knots = (stand_key(j[i]), stand_key(min(j[i] + 1, n_knots - 1)))
        graph.add(factors.spin_prior_factor(center_key(i), knots, alpha[i], ARM_KEY, M, R[i][:, 2],
                                            free_noise if free else fixed_noise))
    n_obs = _add_line_observations(graph, values, pre, tracks, sol, todo, R, config, hold)
    try:
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
        marginals = gtsam.Marginals(graph, result)
        sig = np.array([np.sqrt(np.linalg.eigvalsh(marginals.marginalCovariance(center_key(i)))[-1]) for i in todo])
    except RuntimeError as e:  # an indeterminate system: leave the frames out rather than guess
        log.warning("motion model: not solved (%s); frames left without a pose", str(e).splitlines()[0])
        res["motion_model"] = {"placed": 0, "error": str(e).splitlines()[0]}
        return dataclasses.replace(sol, residuals=res)
    rel = sig / diameter
    ok = rel <= config.motion_max_sigma_rel
    centers, registered, R_out = sol.centers.copy(), sol.registered.copy(), sol.R_wc.copy()
    for i, s_rel, good in zip(todo, rel, ok):
        res["frame_sigma_rel"][i] = float(s_rel)
        if good:
            centers[i] = result.atPoint3(center_key(i))
            R_out[i] = pre.R_wc[i]
            registered[i] = True
            source[i] = "motion model"
    res["motion_model"] = {"placed": int(ok.sum()), "left_out": int((~ok).sum()), "line_fixed": int(len(fixed)),
                           "model_sigma_rel": model_sigma / diameter,
                           "max_sigma_rel": config.motion_max_sigma_rel, "observations": n_obs,
                           "sigma_rel_median": float(np.median(rel)), "seconds": round(time.perf_counter() - t0, 3)}
    log.info("motion model: %d of %d frames placed (std <= %.1f %% of the spin's diameter), %d left out",
             int(ok.sum()), len(todo), 100 * config.motion_max_sigma_rel, int((~ok).sum()))
    return dataclasses.replace(sol, centers=centers, registered=registered, R_wc=R_out, residuals=res)


def _predict(stand: np.ndarray, arm: np.ndarray, M: np.ndarray, view_dirs: np.ndarray, j: np.ndarray,
             alpha: np.ndarray) -> np.ndarray:
    """Returns (N, 3) the spin model's centres (``factors.spin_prior``) for frames with these view directions."""
    h = factors.horizontal_direction(M, view_dirs)
    S = (1 - alpha)[:, None] * stand[j] + alpha[:, None] * stand[np.minimum(j + 1, len(stand) - 1)]
    off = arm[0] * h + arm[1] * np.stack([-h[:, 1], h[:, 0]], axis=1)
    return S + off @ M[:2]


def _add_line_observations(graph, values, pre: Preprocessed, tracks: Tracks, sol: Solution, frames: np.ndarray,
                           R: np.ndarray, config: GraphConfig, hold) -> int:
    """Adds the frames' observations of the solution's valid lines (held) at rotations ``R``; returns their number."""
    seg = pre.segments
    tr = tracks.track_of
    valid = sol.lines.valid if len(sol.lines.valid) == tracks.n else np.zeros(tracks.n, bool)
    s = np.flatnonzero(np.isin(seg.frame, frames) & (tr >= 0))
    s = s[valid[tr[s]] & np.all(np.isfinite(sol.lines.taylor[tr[s]]), axis=1)]
    if not len(s):
        return 0
    K = sol.camera.K
    dirs = pre.manhattan.directions[np.clip(tracks.axis, 0, 2)]
    noise = factors.noise_model(2, config.reprojection_sigma_px, *reprojection_kernel(config, 3))  # the BA's last
    for t in np.unique(tr[s]):
        values.insert(line_key(t), sol.lines.taylor[t])
        graph.add(gtsam.PriorFactorPoint3(line_key(t), sol.lines.taylor[t], hold))
    for k in s:
        f, t = int(seg.frame[k]), int(tr[k])
        graph.add(factors.line_reprojection_factor(line_key(t), [center_key(f)], seg.endpoints[k], dirs[t], K, noise,
                                                   R_wc_fixed=R[f][None]))
    return int(len(s))
