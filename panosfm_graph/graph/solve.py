"""The bundle adjustment (paper §3.4): the three phases, the relation rejection rounds, the scale checks.

:func:`bundle_adjust` solves one problem from an initial solution (lines + centres, then +
rotations, then + focal), solved once more at the final scale where the scale checks rescaled it
(:func:`_resolve_at_scale`); :func:`bundle_adjust_incremental` solves as frames arrive in batches.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from typing import Callable

import gtsam
import numpy as np

import factors

from ..config import GraphConfig
from ..data import Preprocessed, Relations, Solution, Tracks
from ..geometry import turned_degrees
from .determinacy import _mark_undetermined, _verify_relations, focal_sigma
from .factor_graph import _build_graph
from .lm import levenberg_marquardt
from .problem import (ARM_KEY, DRIFT_KEY, FLOOR_KEY, FOCAL_KEY, _select, initial_values, line_key,
                      relation_residuals, relation_sigmas, rotation_key, stand_key)
from .readout import _camera_with_focal, _read_points, _reprojection_rms, _solution
from .scale import _floor_below_lines, _gauge, _keep_camera_height, _scaled
from .spin import _check_arm, _check_steady, fit_spin, spin_arm_length

log = logging.getLogger("panosfm.graph")

MAX_REJECT_ROUNDS = 3


def bundle_adjust(pre: Preprocessed, tracks: Tracks, relations: Relations, initial: Solution,
                  config: GraphConfig = GraphConfig(), resolve: bool = True) -> Solution:
    """Returns the bundle-adjusted Solution (paper §3.4): lines + centres, then + rotations, then + focal.

    ``initial`` (e.g. from the linear solve) gives the registered frames, the
    valid tracks and the starting values. ``residuals`` of the result holds,
    per phase, cost before/after (0.5 * sum of whitened squared residuals),
    iterations and seconds; factor counts; relations rejected; the final
    RMS reprojection distance (px) and the camera's focal length.

    Solved at the final scale (our addition, ``resolve_scale_ratio``): the scale checks after the
    solve (:func:`_keep_camera_height`, :func:`_floor_below_lines`, :func:`_check_arm`) may rescale
    the model, and the sigmas in metres (spin prior, coplanarities, determinacy) were then applied
    at the wrong scale (measured: ``tools/bench_ba.py --real`` office, the floor's scale 3.2 times too
    small, 4.9 % centre error and 2.1 px; solved again at the arm's scale, 0.6 % and 0.73 px). Where the
    result ended more than that ratio away from ``initial``'s scale, the problem is solved once more
    from ``initial`` rescaled by that factor, and the first solve's scale decision (metric or not, floor
    height, the scale residuals and warnings) is kept: the second solve changes the shape, not the
    scale (where the arm gave the scale, the arm is set to ``metric_arm_fallback_m`` again). The
    second solve is kept only where it fits the images no worse (RMS reprojection; measured on a
    swaying living capture: 0.69 -> 0.74 px with its centre error 0.6 -> 2.0 %).
    ``residuals["scale_vs_initial"]``: the result's scale relative to ``initial`` (the incremental
    mode brings each batch back to it); ``residuals["resolved_at_scale"]``: the factor, the seconds,
    whether the second solve was kept, and both solves' RMS reprojection and registered frames (first, second).
    With ``resolve`` False that second solve is left to :func:`solve_at_final_scale` (the pipeline: only where
    the auto spin style keeps this solution, :func:`~panosfm_graph.graph.steady_or_hand_held`).
    """
    sol = _bundle_adjust_once(pre, tracks, relations, initial, config)
    return solve_at_final_scale(pre, tracks, relations, initial, config, sol) if resolve else sol


def solve_at_final_scale(pre: Preprocessed, tracks: Tracks, relations: Relations, initial: Solution,
                         config: GraphConfig, sol: Solution) -> Solution:
    """Returns ``sol`` (from ``bundle_adjust(..., resolve=False)`` of ``initial``) solved again at its final scale
    where the scale checks moved it (:func:`bundle_adjust`), with the steadiness check made; what ``sol``'s
    residuals say of the spin style stays."""
    style = {k: sol.residuals[k] for k in _STYLE_KEYS if k in sol.residuals}
    sol = _resolve_at_scale(pre, tracks, relations, initial, config, sol)
    sol.residuals.update(style)
    _check_steady(sol, pre.manhattan.directions, config)
    return sol


# what steady_or_hand_held adds to a solution's residuals: a second solve at the final scale keeps them
_STYLE_KEYS = ("spin_style", "steady_check", "linear_steady", "frame_source")


def _resolve_at_scale(pre: Preprocessed, tracks: Tracks, relations: Relations, initial: Solution,
                      config: GraphConfig, sol: Solution) -> Solution:
    """Returns ``sol``, or the problem solved again from ``initial`` at ``sol``'s scale (:func:`bundle_adjust`)."""
    f = float(sol.residuals["scale_vs_initial"])
    ratio = config.resolve_scale_ratio
    if not (ratio > 1.0 and np.isfinite(f) and f > 0 and abs(np.log(f)) > np.log(ratio)):
        return sol
    t0 = time.perf_counter()
    res0 = dict(initial.residuals) if isinstance(initial.residuals, dict) else {}
    if res0.get("floor_height") is not None:
        res0["floor_height"] = float(res0["floor_height"]) * f
    start = dataclasses.replace(_scaled(initial, f), residuals=res0)
    again = _bundle_adjust_once(pre, tracks, relations, start, config, scale_checks=False)
    first, r = sol.residuals, again.residuals
    rms0, rms1 = first.get("reprojection_rms_px"), r.get("reprojection_rms_px")
    # the arm of both solves (the first's after its scale checks; each solve measured it): a second solve whose arm
    # shrank past the ratio collapsed the spin (measured: a 60-frame swaying spin, 0.29 m -> 1 mm, one point)
    arms = [first.get("spin_arm_m"), r.get("spin_arm_m")]
    collapsed = arms[0] is not None and arms[0] > 0 and (arms[1] is None or arms[1] < arms[0] / ratio)
    kept = not collapsed and (rms0 is None or (rms1 is not None and rms1 <= rms0))
    record = {"factor": f, "seconds": round(time.perf_counter() - t0, 3), "kept": bool(kept),
              "reprojection_rms_px": [rms0, rms1], "registered": [int(sol.registered.sum()), int(again.registered.sum())],
              "arm": arms}
    if not kept:  # the second solve fits the images worse or lost the spin's arm: it went elsewhere, the first stands
        first["resolved_at_scale"] = record
        log.info("BA: solved again at %.3g x the scale, it fits worse (RMS reprojection %.3f -> %.3f px, arm %s -> "
                 "%s): the first solve kept", f, rms0 or 0.0, rms1 or 0.0, *arms)
        return sol
    for key in _SCALE_DECISION:
        r.pop(key, None)
        if key in first:
            r[key] = first[key]
    r["warnings"] = list(first.get("warnings", [])) + list(r.get("warnings", []))
    arm = r.get("spin_arm_m")
    if "scale_from_arm" in first and arm:  # the arm gave the scale: it is the fallback arm again
        g = config.metric_arm_fallback_m / float(arm)
        again = _scaled(again, g)
        r["floor_height"] = None if r.get("floor_height") is None else float(r["floor_height"]) * g
        r["scale_vs_initial"] = f * g
        r["spin_arm_m"] = float(config.metric_arm_fallback_m)
    r["resolved_at_scale"] = record
    log.info("BA: the scale checks rescaled the result by %.3g; solved again at that scale (%.2f s): RMS reprojection "
             "%.3f -> %.3f px, %d -> %d frames", f, record["seconds"], rms0, rms1, *record["registered"])
    return dataclasses.replace(again, metric=sol.metric)


# the scale checks' residuals: a second solve at the final scale keeps the first solve's (bundle_adjust)
_SCALE_DECISION = ("floor_height", "height_rescale", "floor_lowered_by", "floor_from_line", "spin_arm_m_from_floor",
                   "scale_from_arm", "scale_vs_initial")


def _bundle_adjust_once(pre: Preprocessed, tracks: Tracks, relations: Relations, initial: Solution,
                        config: GraphConfig, scale_checks: bool = True) -> Solution:
    """Returns one bundle adjustment from ``initial`` (:func:`bundle_adjust`); ``scale_checks`` False: at its scale."""
    prob = _select(pre, tracks, relations, initial, config)
    camera = initial.camera
    K = camera.K
    R_wc = np.where(initial.registered[:, None, None], initial.R_wc, np.nan)
    if not np.all(np.isfinite(initial.R_wc[initial.registered])):
        raise ValueError("initial solution has non-finite rotations for registered frames")
    values = initial_values(prob, initial)
    gauge = _gauge(relations, prob, initial, pre.manhattan.directions)
    _insert_spin(pre, prob, initial.centers, R_wc, config, values, gauge)
    gauge["R_prior"] = {int(i): gtsam.Rot3(_orthonormal(R_wc[i])) for i in prob.rot_frames}
    residuals: dict = {"phases": {}, "factors": {}}
    rel_mask = np.ones(len(prob.rel_idx), bool)
    if gauge["use_floor"]:
        values.insert(FLOOR_KEY, np.array([gauge["floor_h"]]))
    residuals["reprojection_rms_px_initial"] = _reprojection_rms(pre, prob, initial.lines.taylor, initial.R_wc,
                                                                 initial.centers, K)
    gauge["reprojection_rms_initial"] = residuals["reprojection_rms_px_initial"]
    phases = sorted(set(config.phases)) or [1]
    last = phases[-1]
    n_rejected = 0
    rejected: list[int] = []
    if config.verify_relations and len(prob.rel_idx):
        values, rel_mask = _verify_relations(pre, relations, prob, R_wc, K, config, gauge, values, residuals)
        rejected.extend(int(r) for r in prob.rel_idx[~rel_mask])
        residuals["relations_unverified"] = int(np.sum(~rel_mask))
    for phase in phases:
        if phase >= 2:
            for i in prob.rot_frames:
                if not values.exists(rotation_key(i)):
                    values.insert(rotation_key(i), gtsam.Rot3(_orthonormal(R_wc[i])))
            if (config.heading_drift_sigma_deg > 0 and config.rotation_prior_sigma_deg > 0 and len(prob.rot_frames) > 1
                    and not values.exists(DRIFT_KEY)):
                values.insert(DRIFT_KEY, np.zeros(1))
                gauge["drift_tau"] = factors.drift_times(np.arange(len(R_wc)), len(R_wc))
        if phase >= 3 and not values.exists(FOCAL_KEY) and "focal_free" not in gauge:
            values.insert(FOCAL_KEY, np.array([K[0, 0]]))
            sigma_f = focal_sigma(pre, relations, prob, R_wc, K, rel_mask, config, gauge, values)
            gauge["focal_free"] = bool(sigma_f <= config.focal_max_sigma_frac * K[0, 0])
            residuals["focal_sigma_px"] = float(sigma_f)
            residuals["focal_refined"] = gauge["focal_free"]
            if not gauge["focal_free"]:
                log.info("BA phase 3: focal length not determined (std %.3g px): kept at %.1f px", sigma_f, K[0, 0])
                values.erase(FOCAL_KEY)
        rounds = MAX_REJECT_ROUNDS if phase == last else 0
        for rnd in range(rounds + 1):
            graph, counts, batches = _build_graph(pre, relations, prob, phase, R_wc, K, rel_mask, config, gauge,
                                                  batched=True)
            values, info = levenberg_marquardt(graph, values, config.max_iterations, batches=batches)
            info["factors"] = counts
            name = f"phase{phase}" if rnd == 0 else f"phase{phase}_reject{rnd}"
            residuals["phases"][name] = info
            residuals["factors"] = counts
            log.info("BA %s: cost %.4g -> %.4g in %d iterations (%.2f s)", name, info["cost_before"],
                     info["cost_after"], info["iterations"], info["seconds"])
            if rnd == rounds or len(prob.rel_idx) == 0:
                break
            taylor_now = _read_points(values, line_key, prob.lines, initial.lines.taylor)
            h = values.atVector(FLOOR_KEY)[0] if values.exists(FLOOR_KEY) else 0.0
            sub = relations.subset(prob.rel_idx)
            white = np.abs(relation_residuals(sub, pre.manhattan.directions, taylor_now, h)) / relation_sigmas(sub, config)
            drop = rel_mask & (white > config.reject_sigma)
            if not drop.any():
                break
            rel_mask &= ~drop
            n_rejected += int(drop.sum())
            rejected.extend(int(r) for r in prob.rel_idx[drop])
        if phase >= 2:
            for i in prob.rot_frames:
                R_wc[i] = values.atRot3(rotation_key(i)).matrix()
        if phase >= 3 and values.exists(FOCAL_KEY):
            camera = _camera_with_focal(initial.camera, values.atVector(FOCAL_KEY)[0])
            K = camera.K
    residuals["relations_used"] = int(rel_mask.sum())
    residuals["relations_rejected"] = n_rejected + residuals.get("relations_unverified", 0)  # both ways
    residuals["rejected_relations"] = sorted(rejected)
    residuals["focal_px"] = float(camera.K[0, 0])
    sol = _solution(pre, tracks, initial, prob, values, R_wc, camera, residuals)
    used = np.zeros(relations.n, bool)
    used[prob.rel_idx[rel_mask]] = True
    sol = dataclasses.replace(sol, relations_kept=used)
    residuals["reprojection_rms_px"] = _reprojection_rms(pre, prob, sol.lines.taylor, sol.R_wc, sol.centers, camera.K)
    sol = _mark_undetermined(pre, relations, prob, rel_mask, sol, config, values)
    residuals = sol.residuals  # _mark_undetermined returns a copy
    if values.exists(FLOOR_KEY):
        residuals["floor_height"] = float(values.atVector(FLOOR_KEY)[0])
    if values.exists(DRIFT_KEY):  # the heading drift the BA took out of the rotation prior, over the capture
        residuals["heading_drift_deg"] = float(np.degrees(values.atVector(DRIFT_KEY)[0]))
    if not scale_checks:
        sol.residuals["spin_arm_m"] = spin_arm_length(sol.centers, sol.R_wc, pre.manhattan.directions,
                                                      config.spin_knot_deg, config.metric_arm_min_turn_deg)
        return sol
    if values.exists(FLOOR_KEY):
        sol = _keep_camera_height(sol, initial, relations, prob, pre.manhattan.directions, residuals)
        if config.floor_below_lines_min_obs > 0:
            sol = _floor_below_lines(sol, relations, prob, pre.manhattan.directions, residuals,
                                     config.floor_below_lines_min_obs)
    sol = _check_arm(sol, pre.manhattan.directions, config)
    r = sol.residuals
    r["scale_vs_initial"] = (float(r.get("height_rescale", 1.0)) / float(r.get("floor_lowered_by", 1.0))
                             * float(r.get("scale_from_arm", 1.0)))
    return sol


def _insert_spin(pre: Preprocessed, prob, centers: np.ndarray, R_wc: np.ndarray, config: GraphConfig,
                 values: gtsam.Values, gauge: dict) -> None:
    """Inserts the spin prior's stand-point knots and arm, fitted to ``centers`` of the problem's frames, into
    ``values`` and its knots into ``gauge["spin"]`` (``graph.spin_sigma_m`` > 0 and at least 3 frames)."""
    if config.spin_sigma_m > 0 and len(prob.frames) >= 3:
        knots = factors.spin_knots(turned_degrees(pre.R_wc)[prob.frames], config.spin_knot_deg)
        stand, arm, _ = fit_spin(centers[prob.frames], R_wc[prob.frames][:, :, 2], pre.manhattan.directions,
                                 *knots, walk_weight=config.spin_sigma_m / config.spin_walk_sigma_m)
        for jj, p in enumerate(stand):
            values.insert(stand_key(jj), p)
        values.insert(ARM_KEY, arm)
        gauge["spin"] = knots


def _orthonormal(R: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(R)
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


def bundle_adjust_incremental(pre: Preprocessed, tracks: Tracks, relations: Relations, initial: Solution,
                              config: GraphConfig = GraphConfig(), batch_frames: int | None = None,
                              on_batch: Callable[[int, Solution], None] | None = None) -> list[Solution]:
    """Returns the per-batch bundle-adjusted Solutions (the last is the final one) as frames arrive in batches.

    Registered frames are added in time order, ``batch_frames`` at a time
    (default ``config.incremental_batch``, else 50). Each batch is a
    warm-started batch solve (:func:`bundle_adjust`, all phases) over the
    frames so far: frames and lines already estimated start from the previous
    batch's estimate, new ones from ``initial`` (the warm re-solve against iSAM2:
    ``tools/bench_isam2.py``, docs/decisions.md#isam2-for-the-streamed-ba). In a batch's Solution only the
    frames so far are registered and only lines seen in >= 2 of them are valid.
    With ``incremental_final_solve`` (default) one more, final, Solution
    follows the last batch: the whole problem solved from ``initial``, equal
    to the one-shot :func:`bundle_adjust`. ``on_batch(k, solution)`` is
    called after each batch and for the final solve.
    """
    n = int(batch_frames or config.incremental_batch or 50)
    if n < 1:
        raise ValueError("batch_frames must be >= 1")
    reg = np.flatnonzero(initial.registered)
    seg_frame = pre.segments.frame
    tr = tracks.track_of
    current = initial
    out: list[Solution] = []
    for k, end in enumerate(range(n, len(reg) + n, n)):
        mask = np.zeros_like(initial.registered)
        mask[reg[:end]] = True
        s = np.flatnonzero((tr >= 0) & mask[seg_frame])
        seen = np.bincount(tr[s], minlength=tracks.n) >= 2
        start = dataclasses.replace(current, registered=mask,
                                    lines=dataclasses.replace(current.lines, valid=initial.lines.valid & seen))
        t0 = time.perf_counter()
        sol = bundle_adjust(pre, tracks, relations, start, config)
        sol.residuals["batch_seconds"] = time.perf_counter() - t0
        out.append(sol)
        if on_batch is not None:
            on_batch(k, sol)
        # next start: this batch's estimates where they exist, the initial values elsewhere
        done = sol.registered  # frames this batch determined (undetermined ones restart from ``initial``)
        f = 1.0 / float(sol.residuals.get("scale_vs_initial", 1.0))  # back to ``initial``'s scale (scale checks)
        centers = np.where(done[:, None], sol.centers * f, initial.centers)
        R_wc = np.where(done[:, None, None], sol.R_wc, initial.R_wc)
        taylor = np.where((seen & sol.lines.valid)[:, None], sol.lines.taylor * f, initial.lines.taylor)
        current = dataclasses.replace(initial, R_wc=R_wc, centers=centers, camera=sol.camera,
                                      lines=dataclasses.replace(initial.lines, taylor=taylor))
    if config.incremental_final_solve and len(out) > 1:
        # the chain of warm starts drifts where a batch is weakly constrained (measured, living 300
        # frames in batches of 50: 39.8 % vs 12.6 % centre error), so once every frame is in, the
        # whole problem is solved once from the linear solution, as the one-shot batch solve does
        t0 = time.perf_counter()
        final = bundle_adjust(pre, tracks, relations, initial, config)
        final.residuals["batch_seconds"] = time.perf_counter() - t0
        final.residuals["incremental_batches"] = len(out)
        out.append(final)
        if on_batch is not None:
            on_batch(len(out) - 1, final)
    return out
