"""Linear SfM (paper §3.3): :func:`solve_linear` as a sequence of named steps, and its two outer variants.

* Floor verification* (``floor_verify_ratio`` > 0): the floor relations are checked against a first
  solve without them, and those above the floor (furniture tops) dropped (:func:`floor_verified`).
* Tracks first* (``tracks_first``, off by default: measured worse on the bedroom): the solve uses
  the tracks (colinearity, the body-motion prior) and the floor alone, and the coplanarity rows
  only when that registers fewer than ``tracks_first_share`` of the frames they register. A false
  coplanarity is satisfied here by shrinking the camera motion that would show the depth
  difference, so it leaves no residual to find it by (measured: parts of the sweep collapsed onto
  a point); the bundle adjustment brings the coplanarities in with a redescending kernel.

* Zero baseline* (``zero_baseline_px`` > 0): a spin whose tracked lines show no parallax
  (:func:`.baseline.parallax_px`) has no translation to solve for: it is solved as the paper's
  zero-translation baseline, every frame registered at one shared centre, and said so
  (``residuals["zero_baseline"]``, a warning) instead of fitting translations to noise; the bundle
  adjustment then refines only the rotations (``graph.rotation_bundle_adjust``).

(* marks a deviation from the paper.)
"""
from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from ..config import LinearConfig
from ..data import FLOOR, Camera, Preprocessed, Relations, Solution, Tracks
from .baseline import parallax_px
from .registration import determinable_frames
from .result import camera_centres, line_model, residual_report
from .robust import solve_constrained
from .scale import choose_gauge, normalise_scale
from .system import VERTICAL, build_system, lay_out_unknowns, system_members, tracked_observations, usable_relations

log = logging.getLogger("panosfm.linear")


def solve_linear(pre: Preprocessed, tracks: Tracks, relations: Relations, camera: Camera,
                 config: LinearConfig = LinearConfig()) -> Solution:
    """Returns the linear SfM solution (paper §3.3): camera centres and one 3D line per track.

    Solves colinearity + coplanarity + floor constraints for the translations and the line depths
    (``lambda >= min_depth_m``) of the registered frames. The steps, each in its module (whose
    docstring says the formulation and its deviations from the paper):

    1. :func:`.system.tracked_observations` -- the tracked segments' viewing rays (§3.3 "Model");
    2. :func:`.system.usable_relations` -- the coplanarity and floor relations the solve can use;
    3. :func:`.registration.determinable_frames` -- the frames whose translation the lines determine;
    4. :func:`.system.system_members`, :func:`.system.lay_out_unknowns` -- the observations, relations
       and tracks of those frames, and the unknowns ``tau``, ``u``, ``h`` (+ the spin model's);
    5. :func:`.scale.choose_gauge` -- the origin, and the floor height or one depth fixed;
    6. :func:`.system.build_system` -- the rows: colinearity, coplanarity, floor, priors (§3.3);
    7. :func:`.robust.solve_constrained` -- least squares with the depth bound, relations reweighted;
    8. :func:`.scale.normalise_scale` -- metric, camera-to-floor, mean-depth or spin-arm units;
    9. :func:`.result.camera_centres`, :func:`.result.line_model`, :func:`.result.residual_report`.

    Lines: direction = the track's Manhattan direction, position = the median of its observations'
    points (orthogonal to the direction), extent = the closest points on the line to its segments'
    end-point rays. ``R_wc`` is ``pre.R_wc`` passed through.
    With ``floor_verify_ratio`` > 0 the floor relations are verified first (:func:`floor_verified`);
    ``relations_kept`` of the result: all relations but the floor relations it found above the floor
    and those the robust solve left below ``reject_weight`` (the bundle adjustment leaves them out:
    :func:`~panosfm_graph.graph.bundle_adjust`).
    """
    if config.zero_baseline_px > 0 and not config.zero_translation:
        return _zero_baseline_or_not(pre, tracks, relations, camera, config)
    if config.tracks_first and config.coplanarity_weight > 0:
        return _tracks_first(pre, tracks, relations, camera, config)
    if config.floor_verify_ratio > 0 and np.any(relations.kind == FLOOR):
        return _with_verified_floor(pre, tracks, relations, camera, config)
    t_start = time.perf_counter()
    M = np.asarray(pre.manhattan.directions, dtype=np.float64)  # rows N_0, N_1, N_2
    axis = tracks.axis.astype(int)
    obs = tracked_observations(pre, tracks, camera, M)
    rels = usable_relations(relations, axis, config)
    registered, reasons = determinable_frames(pre, obs, rels, M, axis, config)
    members = system_members(registered, obs, rels, tracks.n)
    unknowns, priors = lay_out_unknowns(pre, M, registered, members.in_sys, axis, config)
    gauge = choose_gauge(unknowns, members, obs, config)
    system = build_system(obs, rels, members, unknowns, priors, gauge.fixed_val, gauge.ref_obs, config)
    est = solve_constrained(system, camera, gauge.h0, config)
    scaled = normalise_scale(est, unknowns, gauge, config)
    centers = camera_centres(scaled.x, unknowns, len(pre.R_wc), M)
    lines = line_model(pre, camera, tracks, obs, members, centers, scaled.depths, M)
    res = residual_report(scaled, est, registered, reasons, rels, members, unknowns, system, gauge.use_floor)
    res["seconds"] = time.perf_counter() - t_start
    log.info("linear: registered %d / %d frames, %d lines, colinearity rms %.3g (%s scale) in %.2f s",
             int(registered.sum()), len(registered), int(lines.valid.sum()), res["colinearity_rms"] or 0.0,
             scaled.mode, res["seconds"])
    kept = np.ones(relations.n, bool)
    kept[est.rejected] = False
    return Solution(R_wc=np.asarray(pre.R_wc, dtype=np.float64).copy(), centers=centers, registered=registered,
                    lines=lines, camera=camera, metric=scaled.mode == "metric", residuals=res, relations_kept=kept)


def _zero_baseline_or_not(pre: Preprocessed, tracks: Tracks, relations: Relations, camera: Camera,
                          config: LinearConfig) -> Solution:
    """Returns the zero-translation solve when the spin shows no parallax, else the solve; both record the test."""
    median, p90, n = parallax_px(pre, tracks, camera, config.zero_baseline_min_turn_deg)
    # a big room seen at low resolution: most lines far, the median drift under the threshold; the near lines' drift
    # (the 90th percentile) still shows the arm (docs/decisions.md#zero-baseline-by-the-near-lines)
    detected = bool(n > 0 and median < config.zero_baseline_px and not p90 >= config.zero_baseline_p90_px)
    test = {"parallax_px": None if n == 0 else round(median, 3), "parallax_p90_px": None if n == 0 else round(p90, 3),
            "tracks": n, "threshold_px": config.zero_baseline_px, "threshold_p90_px": config.zero_baseline_p90_px,
            "detected": detected}
    rest = dataclasses.replace(config, zero_baseline_px=0.0, zero_translation=detected)
    sol = solve_linear(pre, tracks, relations, camera, rest)
    sol.residuals["zero_baseline"] = test
    if detected:  # one shared centre is known for every frame, with or without lines of its own
        F = len(sol.registered)
        sol.residuals.update(registered=F, unregistered_reason_codes=[0] * F)
        sol = dataclasses.replace(sol, registered=np.ones(F, bool), centers=np.zeros((F, 3)))
        log.warning("zero baseline: tracked lines drift %.2f px (median of %d tracks) off their plane through the "
                    "camera, under %.1f px: no measurable parallax, every frame output with one shared centre",
                    median, n, config.zero_baseline_px)
    else:
        log.info("linear: parallax %s px (median of %d tracks)", "n/a" if n == 0 else f"{median:.2f}", n)
    return sol


def _tracks_first(pre: Preprocessed, tracks: Tracks, relations: Relations, camera: Camera,
                  config: LinearConfig) -> Solution:
    """Returns the solve from the tracks alone, or with the coplanarities when that registers too few frames."""
    paper = dataclasses.replace(config, tracks_first=False)
    with_rel = solve_linear(pre, tracks, relations, camera, paper)
    alone = solve_linear(pre, tracks, relations, camera, dataclasses.replace(paper, coplanarity_weight=0.0))
    use_alone = alone.registered.sum() >= config.tracks_first_share * with_rel.registered.sum()
    sol = alone if use_alone else with_rel
    sol.residuals["coplanarities_in_linear"] = not use_alone
    log.info("linear: %s (tracks alone register %d frames, with the coplanarities %d)",
             "from the tracks alone" if use_alone else "with the coplanarities",
             int(alone.registered.sum()), int(with_rel.registered.sum()))
    return sol


def _with_verified_floor(pre: Preprocessed, tracks: Tracks, relations: Relations, camera: Camera,
                         config: LinearConfig) -> Solution:
    """Returns the solve with the floor relations :func:`floor_verified` keeps (``relations_kept``: of all)."""
    keep = floor_verified(pre, tracks, relations, camera, config)
    sol = solve_linear(pre, tracks, relations.subset(keep), camera, dataclasses.replace(config, floor_verify_ratio=0.0))
    sol.residuals["floor_relations_rejected"] = int(np.sum(~keep))
    kept = keep.copy()
    kept[np.flatnonzero(keep)] = sol.relations_kept  # and of the verified ones, those the solve kept
    return dataclasses.replace(sol, relations_kept=kept)


def floor_verified(pre: Preprocessed, tracks: Tracks, relations: Relations, camera: Camera,
                   config: LinearConfig) -> np.ndarray:
    """Returns (R,) bool: every relation but the floor relations that are not on the floor.

    A deviation from the paper: surface normals cannot tell the floor from the tops of tables,
    beds and sofa seats (all horizontal), and one furniture top taken for the floor makes the
    metric scale wrong. The floor is the LOWEST horizontal plane, which a first solve without the
    floor relations shows: each floor candidate line's depth below the mean camera height is
    compared with the deepest horizontal lines' (the 90th percentile, or the deepest candidate when it
    lies deeper: with little floor in view most lines below the cameras are furniture); lines less than
    ``floor_verify_ratio`` of that deep (a desk top 0.7 m below a 1.45 m camera: 0.48) are no floor.
    With fewer than 5 horizontal lines below the cameras the candidates are compared among
    themselves, and with fewer than 3 candidates nothing can be verified: all are dropped (the
    scale is then reported arbitrary rather than metric on a guess), as are candidates whose line
    the first solve does not determine.
    """
    is_floor = relations.kind == FLOOR
    first = solve_linear(pre, tracks, relations.subset(~is_floor), camera,
                         dataclasses.replace(config, floor_verify_ratio=0.0, camera_height_m=None))
    up = pre.manhattan.directions[VERTICAL]
    reg = first.registered
    cand = np.flatnonzero(is_floor)
    t = relations.track_a[cand].astype(int)
    known = first.lines.valid[t] & np.any(reg)  # the others cannot be checked: they are dropped too
    if not np.any(known):
        log.info("linear: none of the %d floor relations can be verified, dropped", len(cand))
        return ~is_floor
    cam_h = float(np.mean(first.centers[reg] @ up))
    depth = cam_h - first.lines.taylor[t[known]] @ up  # how far below the cameras each candidate line lies
    # the reference: the deepest horizontal lines of the model (floor candidates or not: a floor-wall
    # line need not have been detected as floor), or the candidates when fewer than 5 lie below
    horizontal = first.lines.valid & (tracks.axis != VERTICAL)
    below = cam_h - first.lines.taylor[horizontal] @ up
    below = below[below > 0]
    if len(below) >= 5:
        # the floor is the lowest plane: a candidate deeper than most horizontal lines (when few floor
        # lines are in view, most lines below the cameras are furniture) raises the reference. Known
        # weakness: one misplaced deep candidate (living capture 0: 2.2x the others) then leaves the
        # scale on that single line (summary.json says how many floor lines hold it)
        ref = float(max(np.percentile(below, 90), depth.max()))
    elif len(depth) >= 3:
        ref = float(np.percentile(depth, 90))
    else:  # nothing to compare with: one or two floor lines may as well be a bed top; the scale stays arbitrary
        ref = np.inf
    drop = np.concatenate([cand[~known], cand[known][~(depth >= config.floor_verify_ratio * ref)]])
    kept = np.setdiff1d(cand, drop)
    if len(np.unique(relations.track_a[kept])) < config.min_floor_lines:
        drop = cand  # too few floor lines to hold the scale: arbitrary rather than wrong
    keep = np.ones(relations.n, bool)
    keep[drop] = False
    log.info("linear: %d of %d floor relations are above the floor (furniture tops), dropped", len(drop), len(cand))
    return keep

