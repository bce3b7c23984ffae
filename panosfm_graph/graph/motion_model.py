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
* for each frame to place, its observations of the adjusted 3D lines (held):
  a frame whose lines fix its centre along one axis keeps that, the motion
  model supplies the rest;
* with point tracks (:mod:`panosfm_graph.points`), each track seen by these
  frames as a 3D point (triangulated from the current centres) and its
  observations (:class:`factors.PointProjectionSet`); the frames to place then
  get their rotation as a variable too, tied to their neighbours' by the
  refined rotations' relative rotation (``points.relative_sigma_deg``), so the
  points correct the rotation drift of a stretch no line holds; frames whose
  horizontal lines fix their heading are then held to their vanishing-point
  rotations where the tracks fit that as well (:func:`_held_to_vanishing_points`);

solves it, and reads each placed centre's marginal covariance. Without line-fixed frames
(a bare room: vertical edges only) the point tracks place every frame in a gauge of
their own, each centre's std taken with the similarity projected out; with them, the
points alone place the spin too (the line-fixed frames' rotations as anchors), and
where the line-fixed centres disagree with the points' the points' poses are kept
and the lines triangulated again at them (:func:`_lines_or_points`). A frame whose
largest std is at most ``graph.motion_max_sigma_rel`` of the spin's diameter
gets that pose (source "points" when at least ``MIN_POINT_OBS`` point
observations hold it, else "motion model"); the others stay without one, with
the reason. ``graph.motion_model`` False (``panosfm run --strict``): only
line-fixed frames, as before.
"""
from __future__ import annotations

import dataclasses
import logging
import time

import gtsam
import numpy as np
from scipy.spatial.distance import pdist

import factors

from ..config import GraphConfig
from ..config import PointsConfig
from ..data import PointTracks, Preprocessed, Relations, Solution, Tracks
from ..geometry import triangulate_dlt, turned_degrees
from .factor_graph import reprojection_kernel
from .held_poses import adjust_lines_at_poses
from .lm import levenberg_marquardt
from .placement_rotations import add_rotations, heading_by_lines
from .readout import lines_at_poses
from .problem import ARM_KEY, center_key, line_key, point_key, rotation_key, stand_key
from .spin import fit_spin

log = logging.getLogger("panosfm.graph")

HOLD_SIGMA = 1e-4  # solution units: the line-fixed centres and the lines are held
MIN_FIXED = 6  # fewer line-fixed frames: no motion model
MIN_POINT_OBS = 6  # a placed frame with this many point observations is placed by "points"
# the weak priors (diameters) on the points that make the marginals' system determinate, tried in turn: a point
# seen along nearly one ray leaves its depth free (measured, procedural room 5: 100 diameters not enough)
WEAK_POINT_PRIORS = (100.0, 1.0, 0.1)


def place_by_motion_model(pre: Preprocessed, tracks: Tracks, sol: Solution, config: GraphConfig,
                          points: PointTracks | None = None, points_config: PointsConfig = PointsConfig(),
                          relations: Relations | None = None, free: Solution | None = None) -> Solution:
    """Returns ``sol`` with the frames the motion model places within its sigma bound registered (module docstring).

    ``residuals["frame_source"]`` (per frame: "lines", "steady circle" where the steady style placed it,
    "points", "motion model" or None),
    ``residuals["frame_sigma_rel"]`` (per frame: the placed centre's largest std over the spin's diameter;
    None for line-fixed and unplaced frames) and ``residuals["motion_model"]`` (counts, bound, seconds).

    With point tracks and fewer than ``MIN_FIXED`` line-fixed frames the points alone place every frame
    (anchor-free). With enough, the spin is also placed by the points alone and compared with the line-fixed
    frames (:func:`_lines_or_points`): where the two disagree, the lines' solution is wrong and the points'
    is kept. Lines triangulated at the points' poses are then adjusted with the poses held, with ``relations``
    where given and ``graph.lines_held_poses`` (:func:`~.held_poses.adjust_lines_at_poses`). ``free``: that
    anchor-free placement of ``sol`` made before (:func:`place_by_points_alone`), not made again.
    """
    has_points = _has_points(points, points_config)
    points = points if has_points else None
    if int(sol.registered.sum()) < MIN_FIXED:
        out = _place(pre, tracks, sol, config, points, points_config, anchor_free=has_points)
        if out.residuals.get("motion_model", {}).get("anchor_free"):  # no line was held: the tracks the placed
            out = dataclasses.replace(out, lines=lines_at_poses(pre, tracks, out))  # frames see, at their poses
            out.residuals["lines_at_poses"] = int(out.lines.valid.sum())
            out = _adjust_lines(pre, tracks, relations, out, config)
        return out
    compare = has_points and config.motion_lines_points_max_rel > 0
    # the points alone first: where they place every frame and disagree with the lines, the anchored placement
    # would be thrown away (measured, a streamed bedroom batch: 50 iterations, 11 s; docs/decisions.md#points-first)
    if free is None:
        free = place_by_points_alone(pre, tracks, sol, config, points, points_config)
    if free is not None and free.registered.all():
        out = _lines_or_points(pre, tracks, sol, None, free, config, points)
        if out is not None:
            return _adjust_lines(pre, tracks, relations, out, config)
    anchored = _place(pre, tracks, sol, config, points, points_config, anchor_free=False)
    if not compare or "motion_model" not in anchored.residuals:
        return anchored
    if free is None:
        free = _place(pre, tracks, sol, config, points, points_config, anchor_free=True)
    out = _lines_or_points(pre, tracks, sol, anchored, free, config, points)
    replaced = out.residuals.get("motion_model", {}).get("lines_replaced", False)
    return _adjust_lines(pre, tracks, relations, out, config) if replaced else out


def place_by_points_alone(pre: Preprocessed, tracks: Tracks, sol: Solution, config: GraphConfig,
                          points: PointTracks | None, points_config: PointsConfig, always: bool = False
                          ) -> Solution | None:
    """Returns every frame placed by the point tracks alone, in a gauge of their own (:func:`place_by_motion_model`'s
    first step where it compares the points with the lines), or None where it would not compare them (no point
    tracks, no frame left to place, too few line-fixed frames, ``graph.motion_lines_points_max_rel`` 0).
    ``always``: placed wherever there are point tracks (the reliability check's independent solution,
    :mod:`.reliability`), the line-fixed frames' rotations its anchors; None where that fails."""
    if not _has_points(points, points_config):
        return None
    if always:
        F = len(sol.registered)
        # every frame line-fixed: their rotations anchor the placement and all but one are placed (all are)
        base = dataclasses.replace(sol, registered=np.arange(F) > 0) if sol.registered.all() else sol
        try:
            out = _place(pre, tracks, base, dataclasses.replace(config, motion_model=True), points, points_config,
                         anchor_free=True)
        except (RuntimeError, np.linalg.LinAlgError) as e:
            log.warning("points alone: not placed (%s)", str(e).strip().splitlines()[0] if str(e) else type(e).__name__)
            return None
        return out if out.registered.any() else None
    if not compares_points(sol, config):
        return None
    return _place(pre, tracks, sol, config, points, points_config, anchor_free=True)


def compares_points(sol: Solution, config: GraphConfig) -> bool:
    """Returns whether :func:`place_by_motion_model` compares the points' own placement of ``sol`` with its lines:
    some frames but not all line-fixed (at least ``MIN_FIXED``), the motion model and the comparison on."""
    return bool(config.motion_model and config.motion_lines_points_max_rel > 0 and not sol.registered.all()
                and int(sol.registered.sum()) >= MIN_FIXED)


def points_replace_lines(sol: Solution, free: Solution, config: GraphConfig, points: PointTracks | None = None
                         ) -> bool:
    """Returns whether :func:`place_by_motion_model` takes ``free`` (:func:`place_by_points_alone` of ``sol``) over
    the lines: it places every frame, puts the line-fixed frames more than ``graph.motion_lines_points_max_rel``
    of the diameter from the lines' and (with ``points``) the lines' poses fit the point tracks worse than its own
    (:func:`_lines_or_points`, :func:`lines_fit_points`)."""
    if not free.registered.all():
        return False
    gap = _lines_points_gap(sol, free)
    if gap is None or gap[0] <= config.motion_lines_points_max_rel:
        return False
    return points is None or not lines_fit_points(sol, free, points, config)[0]


def point_fit_px(R_wc: np.ndarray, centers: np.ndarray, frames: np.ndarray, points: PointTracks, K: np.ndarray
                 ) -> float:
    """Returns the median px distance of the point tracks' corners in ``frames`` from their projections, each track
    seen twice or more there triangulated at these poses (a corner behind a camera counts 50 px); NaN without any."""
    sel = np.isin(points.frame, frames)
    f, t, uv = points.frame[sel], points.track[sel], points.xy[sel].astype(np.float64)
    if not len(f):
        return float("nan")
    _, t = np.unique(t, return_inverse=True)
    keep = np.bincount(t)[t] >= 2
    f, t, uv = f[keep], t[keep], uv[keep]
    if not len(f):
        return float("nan")
    ids, t = np.unique(t, return_inverse=True)
    xn = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1]], axis=1)
    Xh = triangulate_dlt(R_wc, centers, t, f, xn, len(ids))
    X = Xh[:, :3] / np.where(np.abs(Xh[:, 3:]) > 1e-12, Xh[:, 3:], 1e-12)
    proj, depth = factors.project_points(R_wc[f], centers[f], X[t], K)
    return float(np.median(np.where(depth > 0, np.linalg.norm(proj - uv, axis=1), 50.0)))


def pose_fits_px(R_a: np.ndarray, c_a: np.ndarray, R_b: np.ndarray, c_b: np.ndarray, common: np.ndarray,
                 points: PointTracks, K: np.ndarray) -> tuple[float, float]:
    """Returns the point tracks' median px residual (:func:`point_fit_px`) at two solutions' poses on the frames
    both place (``common``, (F,) bool)."""
    frames = np.flatnonzero(common)
    return (point_fit_px(R_a, np.where(common[:, None], c_a, 0.0), frames, points, K),
            point_fit_px(R_b, np.where(common[:, None], c_b, 0.0), frames, points, K))


def lines_fit_points(sol: Solution, free: Solution, points: PointTracks, config: GraphConfig
                     ) -> tuple[bool, float, float]:
    """Returns (whether the line-fixed frames' poses fit the point tracks about as well as the points' own
    placement does on the same frames, their median px residual, the points' own): within
    ``graph.motion_lines_points_fit_ratio`` times the points' residual or ``motion_lines_points_fit_slack_px`` more.

    The point tracks alone leave a flat valley of trajectories a few % of the diameter apart that fit them equally
    well (an open chain, a small arm in a big room); a line-fixed frame's pose that the tracks confirm is then
    the better one. Measured on 19 procedural rooms whose lines and points were both placed: the rule kept the
    better of the two in 15 and in every case where they differed by more than 1 % of the diameter
    (docs/decisions.md#lines-checked-by-the-points)."""
    r_lines, r_points = pose_fits_px(sol.R_wc, sol.centers, free.R_wc, free.centers, sol.registered & free.registered,
                                     points, sol.camera.K)
    if not (np.isfinite(r_lines) and np.isfinite(r_points)):
        return False, r_lines, r_points
    ok = r_lines <= max(config.motion_lines_points_fit_ratio * r_points,
                        r_points + config.motion_lines_points_fit_slack_px)
    return bool(ok), r_lines, r_points


def _has_points(points: PointTracks | None, points_config: PointsConfig) -> bool:
    return points is not None and len(points.frame) > 0 and points_config.enabled


def _adjust_lines(pre: Preprocessed, tracks: Tracks, relations: Relations | None, sol: Solution,
                  config: GraphConfig) -> Solution:
    """Returns ``sol`` with its lines adjusted at its poses (:func:`~.held_poses.adjust_lines_at_poses`) where
    ``relations`` are given and ``graph.lines_held_poses`` is on."""
    if relations is None or not config.lines_held_poses:
        return sol
    return adjust_lines_at_poses(pre, tracks, relations, sol, config)


def _lines_or_points(pre: Preprocessed, tracks: Tracks, sol: Solution, anchored: Solution | None, free: Solution,
                     config: GraphConfig, points: PointTracks | None = None) -> Solution | None:
    """Returns ``anchored`` (line-fixed frames kept, the rest placed by the points) unless the points alone
    (``free``: the line-fixed frames' rotations its anchors) place at least as many frames and put the line-fixed
    frames' centres, after a scale and a shift, more than ``graph.motion_lines_points_max_rel`` of the diameter
    (median) from the lines'; then ``free``
    moved onto the line-fixed frames by a scale and a shift (both are in the refined rotations' world), every line
    triangulated again at its poses (:func:`lines_at_poses`). Measured, hall seed 12 swaying: the lines'
    frames 6-7 % off the truth, 172 of 300 accurate; the points' 300 (docs/decisions.md#lines-or-points).
    ``anchored`` None (not placed yet; ``free`` places every frame): None wherever ``anchored`` would be returned,
    but with ``graph.motion_anchored`` off (a streamed preview) ``free`` moved onto the line-fixed frames then too."""
    if anchored is not None and free.registered.sum() < anchored.registered.sum():
        return anchored
    gap_centers = _lines_points_gap(sol, free)
    if gap_centers is None:
        return anchored
    gap, centers = gap_centers
    res = dict(anchored.residuals) if anchored is not None else {}
    res["motion_model"] = {**res.get("motion_model", {}), "lines_vs_points_rel": gap}
    agree = gap <= config.motion_lines_points_max_rel
    if not agree and points is not None and config.motion_lines_points_fit_ratio > 0:
        fit, r_lines, r_points = lines_fit_points(sol, free, points, config)
        res["motion_model"].update(lines_point_fit_px=r_lines, points_point_fit_px=r_points, lines_fit_points=fit)
        if fit:
            log.info("the line-fixed frames lie %.1f %% of the spin's diameter from the point tracks' own poses, but the "
                     "tracks fit them as well (median %.2f px against %.2f px): the lines' poses kept", 100 * gap,
                     r_lines, r_points)
            agree = True
    if agree and (anchored is not None or config.motion_anchored):
        return None if anchored is None else dataclasses.replace(anchored, residuals=res)
    if agree:  # graph.motion_anchored off (a streamed preview): the points' placement stands
        log.info("motion model: the point tracks place every frame, the line-fixed frames %.1f %% of the spin's "
                 "diameter from them; not placed again anchored by them", 100 * gap)
    else:
        log.warning("the line-fixed frames lie %.1f %% of the spin's diameter from where the point tracks alone put "
                    "them (at most %.1f %%): the point tracks place every frame and the lines are triangulated again",
                    100 * gap, 100 * config.motion_lines_points_max_rel)
    res = dict(free.residuals)
    res["motion_model"] = {**res["motion_model"], "lines_vs_points_rel": gap, "lines_replaced": True,
                           "anchored": False}
    res.pop("spin_arm_m", None)
    out = dataclasses.replace(free, centers=centers, metric=sol.metric, residuals=res)
    out = dataclasses.replace(out, lines=lines_at_poses(pre, tracks, out, only_missing=False))
    res["lines_at_poses"] = int(out.lines.valid.sum())
    return out


def _lines_points_gap(sol: Solution, free: Solution) -> tuple[float, np.ndarray] | None:
    """Returns (the line-fixed frames' median distance from ``free``'s over the diameter, ``free``'s centres moved
    onto the line-fixed frames by a scale and a shift), or None with fewer than ``MIN_FIXED`` frames in both."""
    fixed = sol.registered & free.registered
    if fixed.sum() < MIN_FIXED:
        return None
    # both in the refined rotations' world (the points' gauge holds one of them): only a scale and a shift apart
    src, dst = free.centers[fixed], sol.centers[fixed]
    xs, xd = src - src.mean(axis=0), dst - dst.mean(axis=0)
    s = float(np.sum(xs * xd) / max(np.sum(xs * xs), 1e-300))
    if s <= 0:  # the lines' frames turned half round from the points' (wrong lines): their spread sets the scale,
        # never a reflection (measured: procedural room 37, every frame 47 % off)
        s = float(np.sqrt(np.sum(xd * xd) / max(np.sum(xs * xs), 1e-300)))
    centers = s * (free.centers - src.mean(axis=0)) + dst.mean(axis=0)
    diameter = float(np.max(pdist(centers[free.registered])))
    return float(np.median(np.linalg.norm(centers[fixed] - sol.centers[fixed], axis=1)) / diameter), centers


def _place(pre: Preprocessed, tracks: Tracks, sol: Solution, config: GraphConfig, points: PointTracks | None,
           points_config: PointsConfig, anchor_free: bool) -> Solution:
    """Returns ``sol`` with the frames the motion model places (:func:`place_by_motion_model`; ``points`` None or
    non-empty, its lines as they were); ``anchor_free``:
    every frame placed by the point tracks alone in a gauge of their own (a stand point at the origin, the arm's
    forward length ``graph.metric_arm_fallback_m``, one frame's rotation)."""
    F = len(sol.registered)
    res = dict(sol.residuals)
    given = res.get("frame_source")  # the steady style's (graph.style): "lines" or "steady circle"
    source = list(given) if given is not None and len(given) == F else np.where(sol.registered, "lines", None).tolist()
    source = [s if r else None for s, r in zip(source, sol.registered)]
    res["frame_source"], res["frame_sigma_rel"] = source, [None] * F
    fixed = np.flatnonzero(sol.registered)
    todo = np.flatnonzero(~sol.registered & np.all(np.isfinite(pre.R_wc), axis=(1, 2)))
    has_points = points is not None
    if not config.motion_model or not len(todo) or (len(fixed) < MIN_FIXED and not anchor_free):
        return dataclasses.replace(sol, residuals=res)
    t0 = time.perf_counter()
    M = pre.manhattan.directions
    given_sol = sol
    R = np.where(sol.registered[:, None, None], sol.R_wc, pre.R_wc)
    if anchor_free:  # the line-fixed frames keep only their rotations, as anchors (the lines fix them best)
        fixed = np.zeros(0, np.int64)
        todo = np.flatnonzero(np.all(np.isfinite(pre.R_wc), axis=(1, 2)))
        rotation_anchors = np.flatnonzero(sol.registered) if sol.registered.any() else todo[:1]
        sol = dataclasses.replace(sol, registered=np.zeros(F, bool))
        source = [None] * F
    j, alpha, n_knots = factors.spin_knots(turned_degrees(R), config.spin_knot_deg)
    if anchor_free:  # the scale's gauge: the arm's length (not metric), the stand point at the origin
        stand, arm = np.zeros((n_knots, 3)), np.array([config.metric_arm_fallback_m, 0.0])
    else:
        stand, arm, _ = fit_spin(sol.centers[fixed], R[fixed][:, :, 2], M, j[fixed], alpha[fixed], n_knots,
                                 walk_weight=config.spin_sigma_m / config.spin_walk_sigma_m)
    diameter = 2.0 * float(np.hypot(*arm))
    if not np.isfinite(diameter) or diameter <= 0:
        return dataclasses.replace(sol, residuals=res)
    # a placed frame is off the model by the BA's spin prior std (measured: its error over that std was 0.96 / 1.09 on
    # two captures swaying 5 cm; the line-fixed frames' own RMS about the model, alone or cross-validated, put it
    # 1.7x too small on one and 1.3x too large on the other: docs/decisions.md#motion-model-placement)
    model_sigma = config.spin_sigma_m

    centers0 = sol.centers.copy()
    centers0[todo] = _predict(stand, arm, M, R[todo][:, :, 2], j[todo], alpha[todo])
    n_pts, batches, point_init = np.zeros(F, np.int64), [], {}
    if has_points:
        pset, n_pts, point_init = _point_observations(centers0, points, np.concatenate([fixed, todo]), sol.registered,
                                                      R, sol.camera.K, points_config)
        if pset is not None:
            batches.append(pset)
    if anchor_free and not batches:
        return dataclasses.replace(given_sol, residuals=res)
    # with points the line-fixed frames are anchors, not held: the points fix the frames' relative poses far better
    # than the lines (measured, office seed 2 swaying: held, the placed stretch 6-7 % of the diameter off and turned
    # 0.6-1.0 deg; the line-fixed frames held at their true poses instead, 0.4 %: docs/decisions.md#point-tracks)
    fixed_sigma = points_config.anchor_sigma_rel * diameter if batches else HOLD_SIGMA
    graph, values = _spin_graph(sol, centers0, fixed, todo, stand, arm, M, R, j, alpha, n_knots, config, fixed_sigma)
    for key, X in point_init.items():
        values.insert(key, X)
    if batches:
        add_rotations(graph, values, fixed, todo, R, pre.R_wc, points_config)
    if anchor_free:
        _add_gauge(graph, rotation_anchors, R, config.metric_arm_fallback_m, points_config)
    hold = gtsam.noiseModel.Isotropic.Sigma(3, HOLD_SIGMA)
    free_rot = len(batches) > 0
    n_obs = 0 if anchor_free else _add_line_observations(graph, values, pre, tracks, sol, todo, R, config, hold,
                                                         free_rot)
    try:
        result, batches, n_pts, dropped = _solve_rejecting_points(graph, values, batches, n_pts, points_config)
        sig = _largest_center_std(graph, batches, result, todo, diameter, gauge_free=anchor_free)
        held = todo[heading_by_lines(pre, F, points_config.vp_min_horizontal)[todo]]
        result, vp = _held_to_vanishing_points(graph, result, batches, np.concatenate([fixed, todo]), held, pre.R_wc,
                                               sol.camera.K, points, points_config, free_rot)
    except RuntimeError as e:  # an indeterminate system: leave the frames out rather than guess
        log.warning("motion model: not solved (%s); frames left without a pose", str(e).strip().splitlines()[0])
        res["motion_model"] = {"placed": 0, "error": str(e).strip().splitlines()[0]}
        return dataclasses.replace(given_sol, residuals=res)
    if anchor_free:  # the solved arm sets the spin's diameter; no anchor's error to inherit
        diameter = 2.0 * float(np.hypot(*result.atVector(ARM_KEY)))
        anchored = np.zeros(len(todo))
    else:  # a frame the points place inherits the anchors' own error, which the anchors share rather than average out
        anchored = np.where(n_pts[todo] >= MIN_POINT_OBS, points_config.anchor_sigma_rel * diameter, 0.0)
    rel = np.hypot(sig, anchored) / diameter
    ok = rel <= config.motion_max_sigma_rel
    res["frame_source"] = source
    centers, registered, R_out = sol.centers.copy(), sol.registered.copy(), sol.R_wc.copy()
    for i, s_rel, good in zip(todo, rel, ok):
        res["frame_sigma_rel"][i] = float(s_rel)
        if good:
            centers[i] = result.atPoint3(center_key(i))
            R_out[i] = result.atRot3(rotation_key(i)).matrix() if free_rot else pre.R_wc[i]
            registered[i] = True
            source[i] = "points" if n_pts[i] >= MIN_POINT_OBS else "motion model"
    res["motion_model"] = {"placed": int(ok.sum()), "left_out": int((~ok).sum()), "line_fixed": int(len(fixed)),
                           "anchor_free": anchor_free, "model_sigma_rel": model_sigma / diameter,
                           "max_sigma_rel": config.motion_max_sigma_rel, "observations": n_obs,
                           "point_observations": int(n_pts.sum()), "point_tracks_rejected": dropped,
                           "sigma_rel_median": float(np.median(rel)), "vanishing_point_rotations": vp,
                           "seconds": round(time.perf_counter() - t0, 3)}
    if anchor_free:
        res["spin_arm_m"] = float(np.hypot(*result.atVector(ARM_KEY)))
    log.info("motion model: %d of %d frames placed (std <= %.1f %% of the spin's diameter), %d left out%s",
             int(ok.sum()), len(todo), 100 * config.motion_max_sigma_rel, int((~ok).sum()),
             " (by point tracks alone)" if anchor_free else "")
    return dataclasses.replace(sol, centers=centers, registered=registered, R_wc=R_out, residuals=res,
                               metric=sol.metric and not anchor_free)


def _largest_center_std(graph, batches: list, result: gtsam.Values, todo: np.ndarray, diameter: float,
                        gauge_free: bool = False) -> np.ndarray:
    """Returns (len(todo),) the largest std of each frame's centre from the graph's marginals at ``result``.

    A point seen along nearly one ray (its frames a few mm apart) leaves its depth free, which makes the
    system indeterminate for the marginals; each point gets a weak prior (100 diameters, or 1 and then 0.1 where
    that is not enough: :data:`WEAK_POINT_PRIORS`) at its solved value, which changes no centre's std measurably. ``gauge_free``: the std of the centre relative to the others
    (:func:`gauge_free_covariance`), not to the graph's gauge priors."""
    for weak_sigma in WEAK_POINT_PRIORS:  # a point seen along nearly one ray: held ever more firmly where needed
        gfg = graph.linearize(result)
        for b in batches:
            gfg.push_back(b.linearize(result))
            weak = gtsam.noiseModel.Isotropic.Sigma(3, weak_sigma * diameter)
            for key in set(b.point_keys):
                gfg.push_back(gtsam.PriorFactorPoint3(key, result.atPoint3(key), weak).linearize(result))
        try:
            marginals = gtsam.Marginals(gfg, result)
            break
        except RuntimeError:
            if weak_sigma == WEAK_POINT_PRIORS[-1] or not batches:
                raise
    if gauge_free:
        keys = gtsam.KeyVector([center_key(int(i)) for i in todo])
        C = gauge_free_covariance(marginals.jointMarginalCovariance(keys).fullMatrix(),
                                  np.array([result.atPoint3(center_key(int(i))) for i in todo]))
        blocks = np.stack([C[3 * k:3 * k + 3, 3 * k:3 * k + 3] for k in range(len(todo))])
        return np.sqrt(np.maximum(np.linalg.eigvalsh(blocks)[:, -1], 0.0))
    return np.array([np.sqrt(np.linalg.eigvalsh(marginals.marginalCovariance(center_key(i)))[-1]) for i in todo])


def gauge_free_covariance(C: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """Returns the (3N, 3N) covariance ``C`` of the centres (N, 3) with the similarity gauge projected out.

    A graph without line-fixed frames is held by gauge priors (a stand point, the arm, one rotation); a centre's
    marginal then grows with its distance along the chain from them, though the evaluation (and any user) aligns
    the whole trajectory first. The centres' deviations from the best similarity (translation, rotation, scale,
    linearised about ``centers``) are P c with P = I - J J^+, so their covariance is P C P^T."""
    d = centers - centers.mean(axis=0)
    n = len(d)
    J = np.zeros((3 * n, 7))
    J[:, :3] = np.tile(np.eye(3), (n, 1))
    for a in range(3):  # an infinitesimal rotation about axis a moves c by e_a x c
        J[:, 3 + a] = np.cross(np.eye(3)[a], d).ravel()
    J[:, 6] = d.ravel()
    P = np.eye(3 * n) - J @ np.linalg.pinv(J)
    return P @ C @ P.T


def _add_gauge(graph, rotation_anchors: np.ndarray, R: np.ndarray, arm_m: float, config: PointsConfig) -> None:
    """Adds the gauge of a graph without line-fixed centres: the first stand-point knot at the origin, the arm's
    forward length ``arm_m`` (the scale; not metric) and the rotations of ``rotation_anchors`` (the line-fixed
    frames', or one frame's: the heading about gravity) within ``points.anchor_sigma_deg``."""
    graph.add(gtsam.PriorFactorPoint3(stand_key(0), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, HOLD_SIGMA)))
    graph.add(gtsam.PriorFactorVector(ARM_KEY, np.array([arm_m, 0.0]),
                                      gtsam.noiseModel.Diagonal.Sigmas(np.array([HOLD_SIGMA, 10.0 * arm_m]))))
    hold = gtsam.noiseModel.Isotropic.Sigma(3, np.deg2rad(config.anchor_sigma_deg))
    for i in rotation_anchors:
        graph.add(gtsam.PriorFactorRot3(rotation_key(int(i)), gtsam.Rot3(R[i]), hold))


def _predict(stand: np.ndarray, arm: np.ndarray, M: np.ndarray, view_dirs: np.ndarray, j: np.ndarray,
             alpha: np.ndarray) -> np.ndarray:
    """Returns (N, 3) the spin model's centres (``factors.spin_prior``) for frames with these view directions."""
    h = factors.horizontal_direction(M, view_dirs)
    S = (1 - alpha)[:, None] * stand[j] + alpha[:, None] * stand[np.minimum(j + 1, len(stand) - 1)]
    off = arm[0] * h + arm[1] * np.stack([-h[:, 1], h[:, 0]], axis=1)
    return S + off @ M[:2]


def _spin_graph(sol: Solution, centers0: np.ndarray, fixed: np.ndarray, todo: np.ndarray, stand: np.ndarray,
                arm: np.ndarray, M: np.ndarray, R: np.ndarray, j: np.ndarray, alpha: np.ndarray, n_knots: int,
                config: GraphConfig, fixed_sigma: float = HOLD_SIGMA) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Returns the graph and initial values (``centers0``) of the spin model (module docstring): the line-fixed
    centres held (within ``fixed_sigma``), the frames to place on the fitted model within its std."""
    model_sigma = config.spin_sigma_m
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    hold = gtsam.noiseModel.Isotropic.Sigma(3, fixed_sigma)
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
        values.insert(center_key(i), centers0[i])
        if not free:
            graph.add(gtsam.PriorFactorPoint3(center_key(i), sol.centers[i], hold))
        knots = (stand_key(j[i]), stand_key(min(j[i] + 1, n_knots - 1)))
        graph.add(factors.spin_prior_factor(center_key(i), knots, alpha[i], ARM_KEY, M, R[i][:, 2],
                                            free_noise if free else fixed_noise))
    return graph, values


def _solve_rejecting_points(graph, values, batches: list, n_pts: np.ndarray, config: PointsConfig, extra: list = ()
                            ) -> tuple[gtsam.Values, list, np.ndarray, int]:
    """Returns (the solution, the batches and (F,) point observations per frame left, point tracks dropped);
    ``batches``: the point set or none, ``extra``: other batches solved with it (:func:`levenberg_marquardt`'s).

    Solves, then drops the point tracks whose RMS residual exceeds ``points.reject_px`` and solves again from there,
    at most ``points.reject_rounds`` times: a corner where a near edge crosses a far one (a T-junction) slides
    with the parallax and follows no 3D point; measured, office seed 2 swaying: 22 % of the observations of
    frames 75-104 over 1 px off with the true poses, and the placed stretch 7 % of the diameter off before
    (docs/decisions.md#point-tracks)."""
    result, _ = levenberg_marquardt(graph, values, max_iterations=50, batches=list(extra) + batches)
    dropped = 0
    for _ in range(config.reject_rounds if batches else 0):
        pset = batches[0]
        bad = pset.point_rms(result) > config.reject_px
        if not bad.any():
            break
        gone = set(np.asarray(pset.point_keys)[bad].tolist())
        dropped += len(gone)
        frame_of = np.array([gtsam.Symbol(k).index() for k in pset.center_keys])
        n_pts = n_pts - np.bincount(frame_of[bad], minlength=len(n_pts))
        pset = pset.subset(~bad)
        kept_points = set(pset.point_keys)
        for key in gone - kept_points:
            result.erase(key)
        batches = [pset] if len(pset) else []
        result, _ = levenberg_marquardt(graph, result, max_iterations=50, batches=list(extra) + batches)
    return result, batches, n_pts, dropped


def _held_to_vanishing_points(graph, result: gtsam.Values, batches: list, frames: np.ndarray, todo: np.ndarray,
                              R_vp: np.ndarray, K: np.ndarray, points: PointTracks | None, config: PointsConfig,
                              free_rot: bool) -> tuple[gtsam.Values, dict | None]:
    """Returns (result, record): the placement solved again with each frame of ``todo`` (those whose lines fix
    their heading, :func:`.placement_rotations.heading_by_lines`) held to its preprocessed (vanishing-point, paper §3.1) rotation
    ``R_vp`` within ``points.vp_sigma_deg``, where the point tracks fit it (median px over ``frames``,
    :func:`point_fit_px`) within ``points.vp_fit_ratio`` times the free placement's; else the free one as it was.

    Our addition (issue #63): the tracks fix the relative poses precisely but trade a rotation for a shift of the
    centres (measured, room 6: the free placement turned 1.3 deg and 2.3 % off where the vanishing points are right
    within 0.2 deg), while a heading drift the preprocessing failed to remove makes the tracks fit the held
    placement worse (room 1: 1.6 times; docs/decisions.md#vanishing-point-rotations-in-the-placement). The stds stay
    the free placement's (the held one's marginals were indeterminate in room 6). ``record``: {"kept", "fit_px":
    [free, held]}, None where not tried."""
    if config.vp_sigma_deg <= 0 or not free_rot or not batches or not len(todo) or points is None:
        return result, None
    held = gtsam.NonlinearFactorGraph()
    held.push_back(graph)
    noise = gtsam.noiseModel.Isotropic.Sigma(3, np.deg2rad(config.vp_sigma_deg))
    for i in todo:
        held.add(gtsam.PriorFactorRot3(rotation_key(int(i)), gtsam.Rot3(R_vp[i]), noise))
    try:
        alt, _ = levenberg_marquardt(held, result, max_iterations=50, batches=batches)
    except RuntimeError:
        return result, None
    F = len(R_vp)

    def fit(values: gtsam.Values) -> float:
        R, C = np.tile(np.eye(3), (F, 1, 1)), np.zeros((F, 3))
        for i in frames:
            R[i], C[i] = values.atRot3(rotation_key(int(i))).matrix(), values.atPoint3(center_key(int(i)))
        return point_fit_px(R, C, frames, points, K)

    fits = [fit(result), fit(alt)]
    kept = bool(np.isfinite(fits).all() and fits[1] <= config.vp_fit_ratio * fits[0])
    record = {"kept": kept, "fit_px": [round(float(f), 4) for f in fits]}
    return (alt if kept else result), record


def _point_observations(centers: np.ndarray, points: PointTracks, frames: np.ndarray, held: np.ndarray, R: np.ndarray,
                        K: np.ndarray, config: PointsConfig, per_frame: int | None = None
                        ) -> tuple[factors.PointProjectionSet | None, np.ndarray, dict[int, np.ndarray]]:
    """Returns (the observations of the point tracks seen by ``frames`` as one set, (F,) their number per frame,
    {point key: the point triangulated from ``centers`` (F, 3) at rotations ``R``}).

    A point behind a camera, or more than ``points.max_error_px`` off an observation by a line-fixed frame
    (``held``, (F,) bool; the others start from the spin model's guess), is dropped; each
    frame keeps its ``per_frame`` (default ``points.per_frame_graph``; 0: all) observations of the tracks spanning
    the most frames; a point needs two."""
    per_frame = config.per_frame_graph if per_frame is None else per_frame
    F = len(R)
    n_added = np.zeros(F, np.int64)
    sel = np.isin(points.frame, frames)
    f, t, uv = points.frame[sel], points.track[sel], points.xy[sel].astype(np.float64)
    if not len(f):
        return None, n_added, {}
    ids, t = np.unique(t, return_inverse=True)
    xn = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1]], axis=1)
    Xh = triangulate_dlt(R, centers, t, f, xn, len(ids))
    ok_pt = np.abs(Xh[:, 3]) > 1e-9
    X = Xh[:, :3] / np.where(ok_pt, Xh[:, 3], 1.0)[:, None]
    proj, depth = factors.project_points(R[f], centers[f], X[t], K)
    bad = (depth <= 0) | ((np.hypot(*(proj - uv).T) > config.max_error_px) & held[f])
    ok_pt &= np.bincount(t, weights=bad, minlength=len(ids)) == 0
    first, last = np.full(len(ids), np.iinfo(np.int64).max), np.full(len(ids), -1)
    np.minimum.at(first, t, f)
    np.maximum.at(last, t, f)
    span = last - first  # frames a track spans: a track that closes the loop spans a turn, and is kept first
    obs = np.flatnonzero(ok_pt[t])
    obs = obs[np.lexsort((-span[t[obs]], f[obs]))]  # by frame, the widest-spanning tracks first
    rank = np.arange(len(obs)) - np.searchsorted(f[obs], f[obs])
    if per_frame > 0:
        obs = obs[rank < per_frame]
    obs = obs[np.bincount(t[obs], minlength=len(ids))[t[obs]] >= 2]
    if not len(obs):
        return None, n_added, {}
    fo = f[obs]
    pset = factors.PointProjectionSet([center_key(int(i)) for i in fo], [point_key(int(p)) for p in t[obs]], uv[obs],
                                      K, config.sigma_px, R[fo], rotation_keys=[rotation_key(int(i)) for i in fo],
                                      robust="huber", k=config.robust_k)
    np.add.at(n_added, fo, 1)
    return pset, n_added, {point_key(int(p)): X[p] for p in np.unique(t[obs])}


def _add_line_observations(graph, values, pre: Preprocessed, tracks: Tracks, sol: Solution, frames: np.ndarray,
                           R: np.ndarray, config: GraphConfig, hold, free_rotation: bool = False) -> int:
    """Adds the frames' observations of the solution's valid lines (held) at rotations ``R`` (or, with
    ``free_rotation``, at their rotation variables); returns their number."""
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
        graph.add(factors.line_reprojection_factor(
            line_key(t), [center_key(f)], seg.endpoints[k], dirs[t], K, noise,
            rotation_keys=[rotation_key(f)] if free_rotation else None, R_wc_fixed=None if free_rotation else R[f][None]))
    return int(len(s))
