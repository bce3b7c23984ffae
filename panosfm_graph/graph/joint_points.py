"""The bundle adjustment with the point tracks joined (paper §3.4's cost plus texture corners; our addition, issue #40).

The paper's bundle adjustment sees lines only. A line constrains a camera's centre only across itself, and a
room's lines are few and long: where a frame sees the lines of one wall, or the spin's two ends see the same
corner from the start and the end of the turn, the poses the lines give disagree with the images' texture by
pixels (measured: the corners tracked over a 100-frame bedroom spin sat 2.1-6.1 px RMS off the BA's poses, and a
room corner clicked in the first and last frames reprojected 20-28 px off). :func:`adjust_with_points` solves the
bundle adjustment's phase-2 cost (line reprojection, colinearity, the coplanarities it kept, IMU relative
rotations, rotation prior, spin prior; rotations, centres and lines free) once more from its solution with the
point tracks (:mod:`panosfm_graph.points`) joined, after the motion model placed the frames the lines leave
without a pose (the points then tie every frame, not only the line-fixed ones): each track a 3D point triangulated
at the current poses, its corners seen through :class:`factors.PointProjectionSet` (Huber; every observation, not
the motion model's few per frame: ``points.per_frame_joint``, docs/decisions.md#every-point-in-the-joint-solve),
the tracks that stay more than ``points.reject_px`` off dropped and the graph solved again (as the motion model
does). Every registered frame gets a centre variable (the spin prior holds those that see no line). The scale is a
gauge the points do not fix: the result is scaled back to the solution's own spread of centres. Where the points had placed the frames
(the lines adjusted at held poses, :mod:`.held_poses`), the lines are adjusted at the new poses once more: on a
plain room swaying (seed 11) the joint solve left its few lines 18.3 cm from the surfaces, 10.7 cm after.

Not worse than its input by its own measure: where the lines' RMS reprojection distance ends more than
``graph.points_joint_max_line_rms_ratio`` times theirs before (and 0.5 px more), the spin's spread of centres
changes more than twofold (the points pull a poorly held spin towards one centre), or the system is singular,
the solution is kept as it was and ``residuals["points_in_ba"]["kept"]`` says so
(docs/decisions.md#points-in-the-bundle-adjustment).
"""
from __future__ import annotations

import dataclasses
import logging
import time

import gtsam
import numpy as np

from ..config import GraphConfig, PointsConfig
from ..data import PointTracks, Preprocessed, Relations, Solution, Tracks
from .factor_graph import _build_graph
from .held_poses import adjust_lines_at_poses
from .motion_model import MIN_FIXED, _point_observations, _solve_rejecting_points
from .problem import FLOOR_KEY, _select, initial_values, rotation_key
from .readout import _reprojection_rms, _solution
from .scale import _gauge, _scaled
from .solve import _insert_spin

log = logging.getLogger("panosfm.graph")

MIN_LINE_RMS_SLACK_PX = 0.5  # the lines' RMS may grow by this much whatever the ratio (a sub-pixel fit loosening)
MIN_SCALE_CHANGE = 0.5  # the joint solve's spread of centres within this factor of its input's, else it is not kept


def _spread(centers: np.ndarray) -> float:
    """Returns the RMS distance of the centres from their mean."""
    return float(np.sqrt(np.mean(np.sum((centers - centers.mean(axis=0)) ** 2, axis=1))))


def adjust_with_points(pre: Preprocessed, tracks: Tracks, relations: Relations, sol: Solution, points: PointTracks,
                       config: GraphConfig, points_config: PointsConfig) -> Solution:
    """Returns ``sol`` bundle-adjusted again with the point tracks joined (module docstring);
    ``residuals["points_in_ba"]``: observations, points, tracks dropped, the lines' and the points' RMS
    reprojection before and after (px), whether the result was kept, seconds. ``sol`` as it was where fewer than
    ``MIN_FIXED`` frames are registered or no point track is seen twice."""
    t0 = time.perf_counter()
    if (config.points_joint_max_line_rms_ratio <= 0 or int(sol.registered.sum()) < MIN_FIXED or points is None
            or not len(points.frame)):
        return sol
    cfg = dataclasses.replace(config, spin_position=True)  # every registered frame a centre variable
    prob = _select(pre, tracks, relations, sol, cfg)
    frames = np.intersect1d(prob.frames, prob.rot_frames)
    K = sol.camera.K
    pset, n_pts, point_init = _point_observations(sol.centers, points, frames, sol.registered, sol.R_wc, K,
                                                  points_config, per_frame=points_config.per_frame_joint)
    if pset is None or not len(prob.lines):
        return sol
    values = initial_values(prob, sol)
    for key, X in point_init.items():
        values.insert(key, X)
    gauge = _gauge(relations, prob, sol, pre.manhattan.directions)
    R_wc = np.where(sol.registered[:, None, None], sol.R_wc, np.nan)
    _insert_spin(pre, prob, sol.centers, R_wc, config, values, gauge)
    gauge["R_prior"] = {int(i): gtsam.Rot3(R_wc[i]) for i in prob.rot_frames}
    if gauge["use_floor"]:
        values.insert(FLOOR_KEY, np.array([gauge["floor_h"]]))
    for i in prob.rot_frames:
        values.insert(rotation_key(int(i)), gtsam.Rot3(R_wc[i]))
    line_rms0 = _reprojection_rms(pre, prob, sol.lines.taylor, sol.R_wc, sol.centers, K)
    point_rms0 = float(np.sqrt(np.mean(np.sum(pset.residuals(values) ** 2, axis=1))))
    rel_mask = np.ones(len(prob.rel_idx), bool)  # the relations the bundle adjustment kept (_select)
    graph, _, batches = _build_graph(pre, relations, prob, 2, R_wc, K, rel_mask, cfg, gauge, batched=True)
    record = {"observations": len(pset), "points": len(point_init), "line_rms_px": [line_rms0, None],
              "point_rms_px": [point_rms0, None], "kept": False}
    try:
        values, kept_sets, _, dropped = _solve_rejecting_points(graph, values, [pset], n_pts, points_config,
                                                                extra=batches)
    except RuntimeError as e:  # an indeterminate system: the bundle adjustment's solution stands
        record.update(error=str(e).strip().splitlines()[0], seconds=round(time.perf_counter() - t0, 3))
        log.warning("bundle adjustment with the point tracks: not solved (%s); kept without them", record["error"])
        return dataclasses.replace(sol, residuals={**sol.residuals, "points_in_ba": record})
    R_out = sol.R_wc.copy()
    for i in prob.rot_frames:
        R_out[i] = values.atRot3(rotation_key(int(i))).matrix()
    out = _solution(pre, tracks, sol, prob, values, R_out, sol.camera, dict(sol.residuals))
    line_rms1 = _reprojection_rms(pre, prob, out.lines.taylor, out.R_wc, out.centers, K)
    record["line_rms_px"][1] = line_rms1
    record["point_rms_px"][1] = (float(np.sqrt(np.mean(np.sum(kept_sets[0].residuals(values) ** 2, axis=1))))
                                 if kept_sets else None)
    record["tracks_dropped"] = dropped
    record["seconds"] = round(time.perf_counter() - t0, 3)
    bound = max(config.points_joint_max_line_rms_ratio * line_rms0, line_rms0 + MIN_LINE_RMS_SLACK_PX)
    if not kept_sets or not np.isfinite(line_rms1) or line_rms1 > bound:
        log.warning("bundle adjustment with the point tracks: the lines fit worse (RMS %.2f -> %.2f px, at most "
                    "%.2f): kept without them", line_rms0, line_rms1, bound)
        return dataclasses.replace(sol, residuals={**sol.residuals, "points_in_ba": record})
    reg = sol.registered
    scale = _spread(sol.centers[reg]) / max(_spread(out.centers[reg]), 1e-300)  # the scale's gauge, as it was
    record["scale"] = scale
    if not MIN_SCALE_CHANGE <= scale <= 1.0 / MIN_SCALE_CHANGE:
        # the spin shrank towards one point (or blew up): the points fit a rotation-only spin better than a real one
        # (measured, procedural room 28: points 0.81 -> 0.17 px with the centres 62 times closer, then 16.6 % off)
        log.warning("bundle adjustment with the point tracks: the spin's spread changed %.1f times: kept without them",
                    scale if scale >= 1 else 1 / scale)
        return dataclasses.replace(sol, residuals={**sol.residuals, "points_in_ba": record})
    record["kept"] = True
    out = _scaled(out, scale)
    if values.exists(FLOOR_KEY):
        out.residuals["floor_height"] = scale * float(values.atVector(FLOOR_KEY)[0])
    out.residuals["points_in_ba"] = record
    if "lines_held_poses" in sol.residuals:  # the points placed the frames: the lines adjusted at them again
        out = adjust_lines_at_poses(pre, tracks, relations, out, config)
    log.info("bundle adjustment with %d point tracks (%d observations, %d dropped): lines RMS %.3f -> %.3f px, "
             "points %.2f -> %.3f px (%.2f s)", record["points"], record["observations"], dropped, line_rms0,
             line_rms1, point_rms0, record["point_rms_px"][1] or float("nan"), record["seconds"])
    return out
