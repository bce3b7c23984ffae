"""Bundle adjustment as a GTSAM factor graph (paper §3.4), solved in three phases.

Variables (keys made by :func:`center_key`, :func:`rotation_key`, ...):

* ``c<i>``  ``gtsam.Point3`` centre of registered frame i (world, m) — every
  registered frame that observes at least one optimised line;
* ``r<i>``  ``gtsam.Rot3`` R_wc of registered frame i (phases >= 2; in phase 1
  the rotations are constants bound into the reprojection factors);
* ``l<t>``  ``gtsam.Point3`` Taylor vector Lambda_t of track t (valid tracks
  seen in >= 2 registered frames);
* ``h0``    1-vector floor height (the floor plane is ``z . X = h``), present
  when floor relations are used;
* ``f0``    1-vector focal length fx in pixels (phase 3; fy keeps the aspect);
* ``s<j>``  ``gtsam.Point3`` stand-point knot j, ``a0`` 2-vector arm (the spin prior, below);
* ``d0``    1-vector heading-drift slope (rad over the capture) of the rotation prior (phases >= 2, optional, below).

Factors (``factors`` package), switched by :class:`GraphConfig`:
line reprojection (one factor per chunk of a track's observations, sigma
``reprojection_sigma_px``; our addition: a Geman-McClure kernel on each observation,
``reprojection_robust``, graduated over the phases by ``reprojection_robust_k``, so that a track
that jumps between two edges fits the one most of its segments follow), colinearity and
coplanarity/floor (sigma ``reprojection_sigma_px / sqrt(relation_weight)``: the paper's weights 1 and
1e4; coplanarity and floor additionally divided by sqrt(support) when
``support_weighting`` and robustified with ``robust`` — Geman-McClure by default:
measured on synthetic problems with 10 % injected false relations, Huber lets
them drag weakly observed line depths by metres; Cauchy's cost still grows with a
false relation's residual, and on the pipeline's output (a quarter of the
relations false) their sum made a collapsed sweep cheaper than the true one;
Geman-McClure caps each at ``k^2 / 2``), IMU relative
rotations between consecutive registered frames (``imu_sigma_deg``, scaled by
sqrt of the frame gap).

Rotation prior (ours, phases >= 2, ``rotation_prior_sigma_deg``): each frame held to its preprocessed
(vanishing-point) rotation; optionally (``heading_drift_sigma_deg`` > 0, off by default) turned about up
by ``d0 * tau`` (``factors.heading_drift``; ``tau`` the frame's time in [-1/2, 1/2]), ``d0`` with a prior
of that sigma: the drift fit of the preprocessing can leave part of the IMU's heading drift where few
horizontal lines fix the heading, a ramp per-frame priors hold. Measured: on one bedroom spin its
-0.14 .. +0.16 degree ramp goes (rotation error 0.115 -> 0.072 degrees), on another a -0.57 degree ramp
comes in (0.070 -> 0.170): the lines do not determine the slope reliably (``config.py``).

Spin prior (our addition, ``spin_sigma_m``; ``factors.spin_prior``): every centre lies on the circle
the phone describes about the person's stand point (knots ``s<j>`` every ``spin_knot_deg`` of turn, a
random walk of ``spin_walk_sigma_m`` between them) with one arm ``a0`` (2-vector) for the whole sweep,
Huber-robust. Without it, tracks of a few frames leave the parts of a sweep free to take their own
scale, which reprojection cannot see (measured: from a linear solve 0.5 % off, 3-frame tracks drift to
48 % of the trajectory's diameter; with it 0.6 %).
Which frames stay registered (:func:`determinacy`) counts the prior only where asked: ``spin_height``
(the height) or ``spin_position`` (every coordinate: a steady spin, ``config.SPIN_STYLES``, whose frames
between two that their lines fix the linear solve placed on the circle).

Gauge: a tight prior holds the first registered camera centre at its initial
position; the world orientation is fixed by the Manhattan directions of the
lines. Scale: the distance of the best-observed line from the first camera
centre (along its initial normal) is held (``scale_line_gauge``; False: a tight
prior on the floor height ``h``, which a floor made of robustly down-weighted
furniture tops does not hold); with floor relations the result is then rescaled
about the origin so the MEAN camera-to-floor distance equals the initial one (a
metric initial solution stays metric even when its first frame is misplaced). Phase 3 adds a weak prior (10 % of the calibrated focal) on the
focal length.

Floor relations are used only where the linear solve's scale rests on them (:func:`floor_held_scale`):
where it dropped every one of them (no floor verified), so does the bundle adjustment.

Relations checked against the tracks (our addition, ``verify_relations``, off by default: measured
better on the captures it was developed on, worse on kept-back office captures): phase 1 is first solved
without any coplanarity; coplanarities whose lines that solve puts further apart than
``verify_sigma`` of their std are dropped, and the phases start from that solve when it fixes at
least ``verify_start_share`` of the frames (:func:`_verify_relations`).

Solver: our own Levenberg-Marquardt loop over ``graph.linearize`` /
``GaussianFactorGraph.optimize`` / ``Values.retract`` with isotropic damping
(``notes/gtsam-python-performance.md``: GTSAM's optimizers are slow with many
Python factors). The line reprojection terms, most of the cost, are linearised by one vectorised
call (:class:`factors.LineReprojectionSet`: the same residuals and Jacobians as the factors, one
``JacobianFactor`` per observation) instead of one Python callback per factor; the factors
themselves remain where a graph must hold them (phase 3 with the focal length free, the focal's
marginal). Measured (``tools/bench_ba.py --frames 300 --clutter 60 --fragment 6``, 2,287-2,774
tracks): 23.1/22.5/18.5 s -> 10.3/11.4/9.8 s for living/bedroom/office, results equal to 1e-5.
After the last phase relations whose whitened residual
exceeds ``reject_sigma`` are dropped and the last phase is solved again
(up to 3 rounds).
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Callable

import gtsam
import numpy as np

import factors

from .config import SPIN_STYLES, GraphConfig, LinearConfig
from .data import FLOOR, JUNCTION, ORTHOGONAL, PARALLEL, Camera, LineModel, Preprocessed, Relations, Solution, Tracks
from .geometry import closest_on_lines, turned_degrees, world_rays
from .linear import solve_linear

log = logging.getLogger("panosfm.graph")

CHUNK_OBS = 8  # observations per reprojection factor (bounds the zero blocks of stacked Jacobians)
GAUGE_SIGMA = 1e-4  # m: priors fixing the first centre and the scale
FOCAL_PRIOR_FRAC = 0.1  # phase 3: weak prior on the focal length, sigma = this * calibrated focal
MAX_REJECT_ROUNDS = 3


def center_key(i: int) -> int:
    """Returns the gtsam key of frame i's centre (Point3)."""
    return gtsam.symbol("c", int(i))


def rotation_key(i: int) -> int:
    """Returns the gtsam key of frame i's R_wc (Rot3)."""
    return gtsam.symbol("r", int(i))


def line_key(t: int) -> int:
    """Returns the gtsam key of track t's Taylor vector Lambda_t (Point3)."""
    return gtsam.symbol("l", int(t))


FLOOR_KEY = gtsam.symbol("h", 0)
FOCAL_KEY = gtsam.symbol("f", 0)
ARM_KEY = gtsam.symbol("a", 0)  # spin prior: the arm (a, b) (2-vector)
DRIFT_KEY = gtsam.symbol("d", 0)  # rotation prior: the heading-drift slope left in the prior (1-vector, rad)


def stand_key(j: int) -> int:
    """Returns the gtsam key of the spin prior's stand-point knot j (Point3)."""
    return gtsam.symbol("s", int(j))

_KIND_SWITCH = {ORTHOGONAL: "coplanarity_orthogonal", PARALLEL: "coplanarity_parallel",
                JUNCTION: "coplanarity_junction", FLOOR: "coplanarity_floor"}


@dataclass(frozen=True)
class _Problem:
    """The selected variables and observations of one BA problem (internal)."""

    frames: np.ndarray  # registered frames with a centre variable (sorted)
    rot_frames: np.ndarray  # registered frames (rotation variables in phases >= 2)
    lines: np.ndarray  # optimised tracks (sorted)
    obs_seg: np.ndarray  # observations (segment ids), sorted by track then frame
    obs_track: np.ndarray
    obs_frame: np.ndarray
    directions: np.ndarray  # (T, 3) unit world direction per track
    rel_idx: np.ndarray  # relations usable (both tracks optimised, type switched on)


def _select(pre: Preprocessed, tracks: Tracks, relations: Relations, initial: Solution, config: GraphConfig) -> _Problem:
    """Returns the problem's variables and observations: valid tracks seen in >= 2 registered frames."""
    seg = pre.segments
    tr = tracks.track_of
    valid_track = initial.lines.valid.copy() if len(initial.lines.valid) == tracks.n else np.ones(tracks.n, bool)
    s = np.flatnonzero(tr >= 0)
    s = s[initial.registered[seg.frame[s]] & valid_track[tr[s]]]
    n_obs = np.bincount(tr[s], minlength=tracks.n)
    line_ok = valid_track & (n_obs >= 2) & np.all(np.isfinite(initial.lines.taylor), axis=1)
    s = s[line_ok[tr[s]]]
    order = np.lexsort((seg.frame[s], tr[s]))
    s = s[order]
    directions = pre.manhattan.directions[np.clip(tracks.axis, 0, 2)]
    keep = np.zeros(relations.n, bool)
    for kind, switch in _KIND_SWITCH.items():
        if getattr(config, switch):
            keep |= relations.kind == kind
    if not floor_held_scale(initial):  # the linear solve found them no floor (or had none): neither is the BA's
        keep &= relations.kind != FLOOR
    if len(initial.relations_kept) == relations.n:  # nor those it rejected (floor lines above the floor, IRLS outliers)
        keep &= initial.relations_kept
    rel_idx = np.flatnonzero(keep & relations.between(line_ok)) if relations.n else np.zeros(0, int)
    frames = np.unique(seg.frame[s])
    if config.spin_position and config.spin_sigma_m > 0 and len(frames):
        # a steady spin: the frames the linear solve placed on the circle without a line in view (a blank wall)
        # stay variables, held by the spin prior alone
        frames = np.union1d(frames, np.flatnonzero(initial.registered))
    return _Problem(frames=frames, rot_frames=np.flatnonzero(initial.registered),
                    lines=np.flatnonzero(line_ok), obs_seg=s, obs_track=tr[s], obs_frame=seg.frame[s].astype(np.int64),
                    directions=directions, rel_idx=rel_idx)


def floor_held_scale(initial: Solution) -> bool:
    """Returns whether ``initial``'s scale rests on floor relations (metric or camera-to-floor = 1).

    Where the linear solve dropped every floor relation (none verified, or fewer floor lines than
    ``min_floor_lines``: ``linear.floor_verified``) its scale is arbitrary, and the bundle adjustment
    leaves the floor out too rather than bring back what was found to be no floor. A solution without
    a recorded scale mode (a hand-made initial solution) keeps its floor relations.
    """
    mode = initial.residuals.get("scale") if isinstance(initial.residuals, dict) else None
    return mode not in ("mean_depth", "spin_arm")


def _relation_sigma(config: GraphConfig) -> float:
    """Returns the colinearity / coplanarity sigma: weight ``relation_weight`` relative to reprojection (paper §3.4)."""
    return factors.sigma_from_weight(config.relation_weight, config.reprojection_sigma_px)


def relation_sigmas(relations: Relations, config: GraphConfig) -> np.ndarray:
    """Returns (R,) per-relation sigmas: the relation sigma divided by sqrt(support) when ``support_weighting``.

    A relation detected in k frames counts as k detections (the paper's
    per-frame constraints, deduplicated here), so a sporadic false detection
    cannot outweigh a relation seen in many frames.
    """
    sigma = np.full(relations.n, _relation_sigma(config))
    if config.support_weighting:
        sigma /= np.sqrt(np.maximum(relations.support, 1))
    return sigma


def _build_graph(pre: Preprocessed, relations: Relations, prob: _Problem, phase: int, R_fixed: np.ndarray,
                 K: np.ndarray, rel_mask: np.ndarray, config: GraphConfig, gauge: dict,
                 batched: bool = False) -> tuple[gtsam.NonlinearFactorGraph, dict, list]:
    """Returns (graph, factor counts by type, batches) for one phase (relations of ``prob.rel_idx[rel_mask]``).

    With ``batched`` the line reprojection terms come as a
    :class:`factors.LineReprojectionSet` in ``batches`` (for
    :func:`levenberg_marquardt`, which linearises them in one vectorised call)
    instead of as CustomFactors in the graph, unless the focal length is a
    variable; ``counts["reprojection"]`` is the number of CustomFactors either
    way.
    """
    graph = gtsam.NonlinearFactorGraph()
    counts = {"reprojection": 0, "colinearity": 0, "orthogonal": 0, "parallel": 0, "junction": 0, "floor": 0,
              "imu": 0, "rotation_prior": 0, "prior": 0, "spin": 0}
    ep = pre.segments.endpoints.astype(np.float64)
    rel_sigma = _relation_sigma(config)
    batches = []
    ks = tuple(config.reprojection_robust_k) or (0.0,)
    rep_k = float(ks[min(phase, len(ks)) - 1])
    if phase == 1 and rep_k > 0:  # graduated: at first as wide as the initial residuals
        wide = config.reprojection_robust_widen * gauge.get("reprojection_rms_initial", 0.0)
        wide /= config.reprojection_sigma_px
        if np.isfinite(wide):
            rep_k = float(np.clip(wide, rep_k, max(rep_k, config.reprojection_robust_k_max)))
    rep_robust = config.reprojection_robust if rep_k > 0 else "none"
    if config.reprojection and len(prob.obs_seg):
        fr = prob.obs_frame
        rep = factors.LineReprojectionSet(
            [line_key(t) for t in prob.obs_track], [center_key(i) for i in fr], ep[prob.obs_seg],
            prob.directions[prob.obs_track], K, config.reprojection_sigma_px,
            rotation_keys=[rotation_key(i) for i in fr] if phase >= 2 else None,
            R_wc_fixed=R_fixed[fr] if phase < 2 else None, robust=rep_robust, k=rep_k)
        with_focal = phase >= 3 and gauge.get("focal_free", True)
        if with_focal or not batched:
            for f in rep.factors(CHUNK_OBS, FOCAL_KEY if with_focal else None):
                graph.add(f)
        else:
            batches.append(rep)
        counts["reprojection"] = len(rep.runs(CHUNK_OBS))
    if config.colinearity:
        for t in prob.lines:
            graph.add(factors.colinearity_factor_builtin(line_key(t), prob.directions[t], rel_sigma))
        counts["colinearity"] = len(prob.lines)
    dirs = pre.manhattan.directions
    sig = relation_sigmas(relations, config)
    for r in prob.rel_idx[rel_mask]:
        kind = int(relations.kind[r])
        normal = dirs[int(relations.normal_axis[r])]
        if kind == FLOOR:
            graph.add(factors.floor_factor(line_key(relations.track_a[r]), FLOOR_KEY, normal,
                                           factors.noise_model(1, sig[r], config.robust, config.robust_k)))
        else:
            graph.add(factors.coplanarity_factor_builtin(line_key(relations.track_a[r]), line_key(relations.track_b[r]),
                                                         normal, sig[r], config.robust, config.robust_k))
        counts[("orthogonal", "parallel", "junction", "floor")[kind]] += 1
    if phase >= 2 and config.rotation_prior_sigma_deg > 0 and "R_prior" in gauge:
        noise = gtsam.noiseModel.Isotropic.Sigma(3, float(np.radians(config.rotation_prior_sigma_deg)))
        tau = gauge.get("drift_tau")  # with a drift slope (heading_drift_sigma_deg): factors.drift_prior_factor
        up = pre.manhattan.directions[2]
        for i in prob.rot_frames:
            if tau is None:
                graph.add(gtsam.PriorFactorRot3(rotation_key(i), gauge["R_prior"][i], noise))
            else:
                graph.add(factors.drift_prior_factor(rotation_key(i), DRIFT_KEY, gauge["R_prior"][i].matrix(), up,
                                                     tau[i], noise))
            counts["rotation_prior"] += 1
        if tau is not None:
            graph.add(gtsam.PriorFactorVector(DRIFT_KEY, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(
                1, float(np.radians(config.heading_drift_sigma_deg)))))
            counts["prior"] += 1
    if phase >= 2 and config.imu_prior and len(prob.rot_frames) > 1:
        fr = prob.rot_frames
        for i, j in zip(fr[:-1], fr[1:]):
            noise = factors.imu_noise(config.imu_sigma_deg * np.sqrt(j - i))
            graph.add(factors.imu_rotation_factor(rotation_key(i), rotation_key(j), pre.R_wc_imu[i], pre.R_wc_imu[j], noise))
            counts["imu"] += 1
    if "spin" in gauge:
        M = pre.manhattan.directions
        noise = factors.spin_noise(config.spin_sigma_m, config.spin_sigma_m * config.spin_vertical_ratio,
                                   config.spin_robust, config.robust_k)
        j, alpha, n_knots = gauge["spin"]
        for i, jj, al in zip(prob.frames, j, alpha):
            knots = (stand_key(jj), stand_key(min(jj + 1, n_knots - 1)))
            graph.add(factors.spin_prior_factor(center_key(i), knots, al, ARM_KEY, M, R_fixed[i][:, 2], noise))
        walk = gtsam.noiseModel.Isotropic.Sigma(3, config.spin_walk_sigma_m)
        for jj in range(n_knots - 1):
            graph.add(gtsam.BetweenFactorPoint3(stand_key(jj), stand_key(jj + 1), np.zeros(3), walk))
        counts["spin"] = len(prob.frames)
    # gauge: first centre, scale
    tight = lambda d: gtsam.noiseModel.Isotropic.Sigma(d, GAUGE_SIGMA)  # noqa: E731
    graph.add(gtsam.PriorFactorPoint3(center_key(gauge["first"]), gauge["first_center"], tight(3)))
    counts["prior"] += 1
    if gauge["use_floor"] and not config.scale_line_gauge:
        graph.add(gtsam.PriorFactorVector(FLOOR_KEY, np.array([gauge["floor_h"]]), tight(1)))
    else:
        graph.add(factors.plane_offset_factor(line_key(gauge["scale_line"]), center_key(gauge["first"]),
                                              gauge["scale_normal"], gauge["scale_offset"], tight(1)))
    counts["prior"] += 1
    if phase >= 3 and gauge.get("focal_free", True):
        graph.add(gtsam.PriorFactorVector(FOCAL_KEY, np.array([K[0, 0]]),
                                          gtsam.noiseModel.Isotropic.Sigma(1, FOCAL_PRIOR_FRAC * K[0, 0])))
        counts["prior"] += 1
    return graph, counts, batches


def fit_spin(centers: np.ndarray, view_dirs: np.ndarray, manhattan: np.ndarray, j: np.ndarray, alpha: np.ndarray,
             n_knots: int, walk_weight: float = 1.0) -> tuple[np.ndarray, np.ndarray, float]:
    """Returns (stand-point knots (K, 3) world, arm (a, b), RMS): the least-squares spin circle through the centres.

    The rows of :func:`factors.spin_prior.spin_model_rows` (knots ``j``/``alpha``
    from :func:`factors.spin_prior.spin_knots`) with the centres given;
    neighbouring knots are tied with ``walk_weight`` (relative to a centre).
    RMS: the horizontal distance of the centres from the fitted circle.
    """
    M = np.asarray(manhattan, dtype=np.float64)
    cm = (np.asarray(centers, dtype=np.float64) @ M.T).ravel()  # 3 i + k, as the rows' centre index
    kind, centre, cols, vals = factors.spin_model_rows(factors.horizontal_direction(M, view_dirs), j, alpha, n_knots)
    w = np.where(kind == 2, walk_weight, 1.0)
    A = np.zeros((len(kind), 3 * int(n_knots) + 2))
    np.add.at(A, (np.repeat(np.arange(len(kind)), cols.shape[1]), cols.ravel()), (vals * w[:, None]).ravel())
    b = np.where(centre >= 0, cm[np.maximum(centre, 0)], 0.0)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    r = (b - A @ x)[kind == 0]  # two horizontal rows per centre
    rms = float(np.sqrt(2.0 * np.mean(r ** 2))) if len(r) else 0.0
    return x[:3 * n_knots].reshape(-1, 3) @ M, x[3 * n_knots:].copy(), rms


def _dims(values: gtsam.Values) -> list[tuple[int, int]]:
    """Returns (key, tangent dimension) of every variable."""
    out = []
    for k in values.keys():
        ch = chr(gtsam.Symbol(k).chr())
        out.append((k, 1 if ch in "hfd" else 2 if ch == "a" else 3))
    return out


def levenberg_marquardt(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, max_iterations: int = 30,
                        rel_tol: float = 1e-4, lam0: float = 1e-4, batches=()) -> tuple[gtsam.Values, dict]:
    """Returns (optimised values, info) from a Levenberg-Marquardt loop driven from Python.

    Damping ``lam * I`` per variable is added as unit JacobianFactors before
    the sparse multifrontal solve; a step is accepted if it lowers the error;
    an indeterminate linear system (a direction no factor constrains, e.g.
    Lambda along A without colinearity) raises the damping, and the damping
    never goes below the smallest that solved since (measured, 300 frames: every
    other solve had failed so, each at about half a solve's time). ``batches``
    (e.g. :class:`factors.LineReprojectionSet`) are more terms of the cost,
    each with ``error(values)`` and ``linearize(values)``. ``info``:
    cost_before, cost_after, iterations, seconds.
    """
    t0 = time.perf_counter()
    dims = _dims(values)

    def total_error(v):
        return graph.error(v) + sum(b.error(v) for b in batches)

    err0 = err = total_error(values)
    lam = lam0
    lam_floor = 1e-12  # raised above a damping whose system was indeterminate
    it = 0
    unit = {d: gtsam.noiseModel.Unit.Create(d) for d in (1, 2, 3)}
    eyes = {d: np.eye(d) for d in (1, 2, 3)}
    zeros = {d: np.zeros(d) for d in (1, 2, 3)}
    for it in range(1, max_iterations + 1):
        gfg = graph.linearize(values)
        for b in batches:
            gfg.push_back(b.linearize(values))
        accepted = False
        while lam < 1e12:
            damped = gtsam.GaussianFactorGraph()
            damped.push_back(gfg)
            s = np.sqrt(lam)
            for k, d in dims:
                damped.push_back(gtsam.JacobianFactor(k, s * eyes[d], zeros[d], unit[d]))
            try:
                delta = damped.optimize()
            except RuntimeError:  # indeterminate (a null direction, damping too weak): damp more
                lam *= 10.0
                lam_floor = max(lam_floor, lam)
                continue
            cand = values.retract(delta)
            new_err = total_error(cand)
            if np.isfinite(new_err) and new_err <= err:
                accepted = True
                break
            lam *= 10.0
        if not accepted:
            break
        decrease = err - new_err
        values, err = cand, new_err
        lam = max(lam / 10.0, lam_floor)
        if decrease <= rel_tol * max(err, 1e-30) or err < 1e-20:
            break
    return values, {"cost_before": float(err0), "cost_after": float(err), "iterations": it,
                    "seconds": time.perf_counter() - t0}


def line_extents(taylor: np.ndarray, direction: np.ndarray, endpoints: np.ndarray, R_wc: np.ndarray,
                 centers: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Returns (N, 2) line coordinates s of the points of the 3D lines closest to the endpoints' viewing rays.

    Rows are observations: ``taylor``/``direction`` (N, 3), ``endpoints`` (N, 4) pixels,
    ``R_wc`` (N, 3, 3), ``centers`` (N, 3). NaN where a ray is parallel to its line.
    """
    out = np.empty((len(endpoints), 2))
    for e in range(2):
        D = world_rays(K, R_wc, endpoints[:, 2 * e:2 * e + 2])
        out[:, e] = closest_on_lines(taylor, direction, centers, D, min_sin2=1e-6)
    return out


def _solution(pre: Preprocessed, tracks: Tracks, initial: Solution, prob: _Problem, values: gtsam.Values,
              R_wc: np.ndarray, camera: Camera, residuals: dict) -> Solution:
    """Returns the Solution read from ``values`` (Lambda projected onto its direction's normal plane, extents from observations)."""
    centers = _read_points(values, center_key, prob.frames, initial.centers)
    taylor = initial.lines.taylor.copy()
    raw = np.array([values.atPoint3(line_key(t)) for t in prob.lines]).reshape(-1, 3)
    A = prob.directions[prob.lines]
    taylor[prob.lines] = factors.taylor_from_point_direction(raw, A)
    direction = initial.lines.direction.copy()
    direction[prob.lines] = A
    extent = initial.lines.extent.copy()
    if len(prob.obs_seg):
        t = prob.obs_track
        s = line_extents(taylor[t], prob.directions[t], pre.segments.endpoints[prob.obs_seg].astype(np.float64),
                         R_wc[prob.obs_frame], centers[prob.obs_frame], camera.K)
        s = np.where(np.isfinite(s), s, np.nan)
        lo = np.full(tracks.n, np.inf)
        hi = np.full(tracks.n, -np.inf)
        np.minimum.at(lo, t, np.nanmin(s, axis=1, initial=np.inf))
        np.maximum.at(hi, t, np.nanmax(s, axis=1, initial=-np.inf))
        ok = np.isfinite(lo) & np.isfinite(hi)
        extent[ok] = np.c_[lo[ok], hi[ok]]
    valid = initial.lines.valid.copy()
    residuals["colinearity_rms_m"] = float(np.sqrt(np.mean(np.sum(raw * A, axis=1) ** 2))) if len(raw) else 0.0
    lines = LineModel(taylor=taylor, direction=direction, axis=tracks.axis.copy(), extent=extent, valid=valid)
    centers[~initial.registered] = np.nan
    return Solution(R_wc=R_wc, centers=centers, registered=initial.registered.copy(), lines=lines, camera=camera,
                    metric=initial.metric, residuals=residuals)


def _read_points(values: gtsam.Values, key: Callable[[int], int], ids: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Returns a copy of ``base`` (N, 3) with rows ``ids`` read from the Point3 variables ``key(id)``."""
    out = np.array(base, dtype=np.float64, copy=True)
    for i in ids:
        out[i] = values.atPoint3(key(i))
    return out


def _camera_with_focal(camera: Camera, fx: float) -> Camera:
    """Returns ``camera`` with fx set to ``fx`` and fy scaled by the same factor (principal point kept)."""
    p = np.array(camera.params, dtype=np.float64)
    if camera.model == "SIMPLE_PINHOLE":
        p[0] = fx
    else:
        scale = fx / p[0]
        p[0] = fx
        p[1] = p[1] * scale
    return dataclasses.replace(camera, params=p)


def _reprojection_rms(pre: Preprocessed, prob: _Problem, taylor: np.ndarray, R_wc: np.ndarray, centers: np.ndarray,
                      K: np.ndarray) -> float:
    """Returns the RMS segment-averaged reprojection distance (pixels) over all observations."""
    if len(prob.obs_seg) == 0:
        return 0.0
    t, f = prob.obs_track, prob.obs_frame
    r = factors.reprojection_terms(pre.segments.endpoints[prob.obs_seg].astype(np.float64), prob.directions[t],
                                   taylor[t], centers[f], R_wc[f], K)
    return float(np.sqrt(np.mean(np.sum(r**2, axis=1))))


def relation_residuals(relations: Relations, directions: np.ndarray, taylor: np.ndarray, floor_h: float) -> np.ndarray:
    """Returns (R,) coplanarity residuals (m): ``(Lambda_a - Lambda_b) . n`` or, for floor, ``Lambda_a . n - h``."""
    n = directions[relations.normal_axis.astype(int)]
    a = taylor[relations.track_a]
    b = taylor[np.clip(relations.track_b, 0, None)]
    pair = np.sum((a - b) * n, axis=1)
    floor = np.sum(a * n, axis=1) - floor_h
    return np.where(relations.kind == FLOOR, floor, pair)


def bundle_adjust(pre: Preprocessed, tracks: Tracks, relations: Relations, initial: Solution,
                  config: GraphConfig = GraphConfig()) -> Solution:
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
    """
    sol = _resolve_at_scale(pre, tracks, relations, initial, config,
                            _bundle_adjust_once(pre, tracks, relations, initial, config))
    _check_steady(sol, pre.manhattan.directions, config)
    return sol


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
    kept = rms0 is None or (rms1 is not None and rms1 <= rms0)
    record = {"factor": f, "seconds": round(time.perf_counter() - t0, 3), "kept": bool(kept),
              "reprojection_rms_px": [rms0, rms1], "registered": [int(sol.registered.sum()), int(again.registered.sum())]}
    if not kept:  # the second solve fits the images worse: it went elsewhere, the first stands
        first["resolved_at_scale"] = record
        log.info("BA: solved again at %.3g x the scale, it fits worse (RMS reprojection %.3f -> %.3f px): the "
                 "first solve kept", f, rms0, rms1)
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
    values = gtsam.Values()
    for i in prob.frames:
        values.insert(center_key(i), np.asarray(initial.centers[i], dtype=np.float64))
    for t in prob.lines:
        values.insert(line_key(t), np.asarray(initial.lines.taylor[t], dtype=np.float64))
    gauge = _gauge(relations, prob, initial, pre.manhattan.directions)
    if config.spin_sigma_m > 0 and len(prob.frames) >= 3:
        knots = factors.spin_knots(turned_degrees(pre.R_wc)[prob.frames], config.spin_knot_deg)
        stand, arm, _ = fit_spin(initial.centers[prob.frames], R_wc[prob.frames][:, :, 2], pre.manhattan.directions,
                              *knots, walk_weight=config.spin_sigma_m / config.spin_walk_sigma_m)
        for jj, p in enumerate(stand):
            values.insert(stand_key(jj), p)
        values.insert(ARM_KEY, arm)
        gauge["spin"] = knots
    gauge["R_prior"] = {int(i): gtsam.Rot3(_orthonormal(R_wc[i])) for i in prob.rot_frames}
    residuals: dict = {"phases": {}, "factors": {}}
    rel_mask = np.ones(len(prob.rel_idx), bool)
    floor_used = bool(np.any(relations.kind[prob.rel_idx] == FLOOR))
    gauge["use_floor"] = floor_used
    if floor_used:
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


def steady_or_hand_held(pre: Preprocessed, tracks: Tracks, relations: Relations, camera: Camera,
                        linear_config: LinearConfig, config: GraphConfig,
                        hand_held: Solution) -> tuple[Solution, Solution | None]:
    """Returns (the steady-spin solution, its linear solve) where the capture was steady, else (``hand_held``, None).

    Our addition. ``config.steady_auto``: where the hand-held solution (``hand_held``, solved with ``linear_config``
    and ``config``) left frames unregistered, the capture is solved again in the steady style
    (``config.SPIN_STYLES['steady']``: one stand point; the frames between two that their lines fix
    placed on its circle) and that solution kept when its centres lie within ``steady_max_rms_arm``
    of one circle (RMS, a share of the arm: :func:`spin_fit`) and it registers more frames. The
    steady style alone (measured, README): ideal circles 97/23/85 -> 100/96/100 % registered, but a
    spin swaying 5 cm put 43 % centre error where 1.2 % was; its centres lay 2.4 % of the arm and
    more off one circle on all 15 swaying captures, 2.2 % and less on 28 of 30 ideal ones.
    ``camera``: the capture's (the linear solve's) camera. ``residuals["spin_style"]`` says which
    result this is; ``residuals["steady_check"]`` what the steady solve gave; a kept steady result
    carries its linear solve's residuals as ``residuals["linear_steady"]`` too (what a cached result keeps).
    """
    res = dict(hand_held.residuals)
    res["spin_style"] = "steady" if config.spin_position else "hand-held"
    reg = hand_held.registered
    if not config.steady_auto or config.spin_position or reg.all() or not reg.any():
        return dataclasses.replace(hand_held, residuals=res), None
    t0 = time.perf_counter()
    style = SPIN_STYLES["steady"]
    linear = solve_linear(pre, tracks, relations, camera, dataclasses.replace(linear_config, **style["linear"]))
    # the circle test is made here (a rejected steady solve is no result to warn about: _check_steady)
    trial = dataclasses.replace(config, **style["graph"], steady_max_rms_arm=float("inf"))
    steady = bundle_adjust(pre, tracks, relations, linear, trial) if linear.registered.any() else linear
    rms = steady.residuals.get("spin_circle_rms_arm")
    n_steady, n_hand = int(steady.registered.sum()), int(reg.sum())
    kept = rms is not None and rms <= config.steady_max_rms_arm and n_steady > n_hand
    check = {"rms_arm": rms, "max_rms_arm": config.steady_max_rms_arm, "registered": n_steady,
             "registered_hand_held": n_hand, "kept": bool(kept), "seconds": round(time.perf_counter() - t0, 3)}
    log.info("auto spin style: steady solve registers %d frames (hand-held %d), centres %s of the arm off one "
             "circle (at most %.1f %%): %s", n_steady, n_hand, "n/a" if rms is None else f"{100 * rms:.1f} %",
             100 * config.steady_max_rms_arm, "steady kept" if kept else "hand-held kept")
    if not kept:
        res["steady_check"] = check
        return dataclasses.replace(hand_held, residuals=res), None
    out = dict(steady.residuals)
    out.update(spin_style="steady (auto)", steady_check=check, linear_steady=dict(linear.residuals))
    return dataclasses.replace(steady, residuals=out), linear


def spin_arm_length(centers: np.ndarray, R_wc: np.ndarray, manhattan: np.ndarray, knot_deg: float,
                    min_turn_deg: float = 0.0) -> float | None:
    """Returns the length of the spin's arm (:func:`fit_spin`) through the finite centres, in their units.

    None with fewer than 3 centres or where they span less than ``min_turn_deg`` of turn (on a short
    arc the arm and the stand point trade off).
    """
    fit = spin_fit(centers, R_wc, manhattan, knot_deg, min_turn_deg)
    return None if fit is None else fit[0]


def spin_fit(centers: np.ndarray, R_wc: np.ndarray, manhattan: np.ndarray, knot_deg: float,
             min_turn_deg: float = 0.0) -> tuple[float, float] | None:
    """Returns (arm length, RMS horizontal distance of the centres from the circle): :func:`fit_spin` on the finite centres.

    None as :func:`spin_arm_length`. With ``knot_deg`` 0 (one stand point) the RMS says how
    steady the spin was (the steady style's BA centres: 0.9-2.6 % of the arm on 29 of the
    project's 30 ideal circles; 2.4 % and more on the 15 spins that sway 5 cm, at the 0.1-degree
    rotation prior).
    """
    ok = np.all(np.isfinite(centers), axis=1) & np.all(np.isfinite(R_wc), axis=(1, 2))
    if ok.sum() < 3:
        return None
    turned = turned_degrees(R_wc[ok])
    if float(np.ptp(turned)) < min_turn_deg:
        return None
    j, alpha, n = factors.spin_knots(turned, knot_deg)
    _, arm, rms = fit_spin(centers[ok], R_wc[ok][:, :, 2], manhattan, j, alpha, n)
    return float(np.hypot(*arm)), rms


def _check_steady(sol: Solution, manhattan: np.ndarray, config: GraphConfig) -> None:
    """Warns where a run set for a steady spin (``spin_position``) finds the centres off one circle.

    ``residuals["spin_circle_rms_arm"]``: the RMS horizontal distance of the centres from one
    stand point's circle, as a share of the arm (:func:`spin_fit`), on every run that turned far
    enough. Above ``steady_max_rms_arm`` with ``spin_position`` on, the spin was likely hand-held
    (measured: the steady style's worst capture 46 % centre error on spins swaying 5 cm).
    """
    fit = spin_fit(sol.centers, sol.R_wc, manhattan, 0.0, config.metric_arm_min_turn_deg)
    rel = None if fit is None or fit[0] <= 0 else fit[1] / fit[0]
    sol.residuals["spin_circle_rms_arm"] = rel
    if config.spin_position and rel is not None and rel > config.steady_max_rms_arm:
        _warn(sol.residuals, f"the camera centres lie {100 * rel:.1f} % of the arm off one circle (a steady spin: "
                             f"under {100 * config.steady_max_rms_arm:.1f} %): the spin looks hand-held; compare "
                             f"with a run without --spin steady")


def _warn(residuals: dict, msg: str) -> None:
    """Logs ``msg`` and adds it to ``residuals["warnings"]`` (the run's summary.json ``warnings``)."""
    log.warning("BA: %s", msg)
    residuals.setdefault("warnings", []).append(msg)


def _check_arm(sol: Solution, manhattan: np.ndarray, config: GraphConfig) -> Solution:
    """Returns ``sol``, rescaled and marked not metric where its metric scale puts the spin's arm out of range.

    Our addition. The metric scale rests on the floor (camera height), and the floor is rarely in
    view (39 degrees of vertical field at 1.5 m see it only beyond 4 m): where only furniture tops
    were taken for it the model came out 1.7-2.3 times too large. The phone's distance from the
    body's axis is known to a few tens of percent (``metric_arm_range_m``); an arm outside that
    range means the floor's scale is wrong, and the arm (``metric_arm_fallback_m``) is the better
    one. Only over ``metric_arm_min_turn_deg`` of turn (not on the early batches of an incremental
    solve). ``residuals``: ``spin_arm_m`` (after any rescale; None on a shorter turn), and
    ``spin_arm_m_from_floor`` with the factor ``scale_from_arm`` when rescaled.
    """
    res = sol.residuals
    arm = spin_arm_length(sol.centers, sol.R_wc, manhattan, config.spin_knot_deg, config.metric_arm_min_turn_deg)
    res["spin_arm_m"] = arm
    lo, hi = config.metric_arm_range_m
    if arm is None or arm <= 0 or not sol.metric or lo <= arm <= hi:
        return sol
    s = config.metric_arm_fallback_m / arm
    _warn(res, f"the metric scale puts the spin's arm at {arm:.2f} m (outside {lo:g}-{hi:g} m): the floor lines "
               f"were likely not the floor; scaled by {s:.3g} so that the arm is {config.metric_arm_fallback_m:g} m, "
               f"scale reported arbitrary")
    res["spin_arm_m_from_floor"] = arm
    res["scale_from_arm"] = float(s)
    res["spin_arm_m"] = float(config.metric_arm_fallback_m)
    if "floor_height" in res:
        res["floor_height"] = float(res["floor_height"]) * s
    return dataclasses.replace(_scaled(sol, s), metric=False)


def _floor_below_lines(sol: Solution, relations: Relations, prob: _Problem, manhattan: np.ndarray, residuals: dict,
                       min_obs: int) -> Solution:
    """Returns ``sol`` scaled about the origin so that no well-observed horizontal line lies below the floor.

    Our addition to the metric gauge. The floor relations that survive verification are often
    the tops of furniture (the floor is rarely in view of a 39-degree vertical field of view at
    1.5 m), and the floor put ``camera height`` below the cameras on a desk top makes the whole
    model too large. Nothing lies below the floor, so where a horizontal line seen in at least
    ``min_obs`` frames lies deeper below the mean camera height than the floor, the floor is
    moved down to it: the model is scaled by (camera-to-floor distance / that line's depth), which
    keeps the camera height the distance from the cameras to the floor. ``residuals``:
    ``floor_lowered_by`` (the factor, 1 when no line lies below), ``floor_from_line`` (its track).
    """
    up = _floor_normal(relations, prob, manhattan)
    reg = sol.registered
    h = residuals.get("floor_height")
    residuals["floor_lowered_by"] = 1.0
    if up is None or h is None or not np.any(reg):
        return sol
    cam = float(np.mean(sol.centers[reg] @ up))
    d_floor = cam - float(h)
    n_obs = np.bincount(prob.obs_track, minlength=len(sol.lines.valid))
    ok = sol.lines.valid & (np.abs(sol.lines.direction @ up) < 0.5) & (n_obs >= min_obs)
    ok &= np.all(np.isfinite(sol.lines.taylor), axis=1)
    if not np.any(ok) or d_floor <= 0:
        return sol
    depth = cam - sol.lines.taylor[ok] @ up
    k = int(np.argmax(depth))
    if depth[k] <= d_floor:
        return sol
    f = d_floor / float(depth[k])
    residuals["floor_lowered_by"] = float(1.0 / f)
    residuals["floor_from_line"] = int(np.flatnonzero(ok)[k])
    residuals["floor_height"] = float(cam * f - d_floor)
    return _scaled(sol, f)


def _verify_relations(pre: Preprocessed, relations: Relations, prob: _Problem, R_wc: np.ndarray, K: np.ndarray,
                      config: GraphConfig, gauge: dict, values: gtsam.Values,
                      residuals: dict) -> tuple[gtsam.Values, np.ndarray]:
    """Returns (values, relation mask over ``prob.rel_idx``): coplanarities checked against the tracks.

    Our addition to paper §3.4. Phase 1 is solved first without any coplanarity (reprojection
    and colinearity only); a pair coplanarity whose two lines that solve determines
    (:func:`determinacy`) but puts further apart along its normal than ``verify_sigma`` of their
    combined std plus ``verify_tolerance`` of the median camera-to-line distance is dropped
    before the three phases. A false coplanarity (a wall and a sofa
    arm 1.5 m in front of it, with normals alike) is otherwise satisfied by shrinking the camera
    motion that shows their depth difference: parallax is small in a spin, so the shrunken sweep
    costs little reprojection (measured, office capture 2: 0.37 px without coplanarities at
    1.1 % centre error, 0.44 px with them at 20 %). Floor relations and relations of lines the
    tracks alone do not determine are kept. The phases start from that solve when it determines
    at least ``verify_start_share`` of the frames (else from ``values``: with too few frames fixed
    by their tracks alone the relation-free solve wanders, e.g. 40 frames 9 degrees apart).
    """
    mask = np.zeros(len(prob.rel_idx), bool)
    graph, _, batches = _build_graph(pre, relations, prob, 1, R_wc, K, mask, config, gauge, batched=True)
    free, info = levenberg_marquardt(graph, values, config.max_iterations, batches=batches)
    residuals["phases"]["phase1_without_relations"] = info
    taylor = _read_points(free, line_key, prob.lines, np.full((len(prob.directions), 3), np.nan))
    centers = _read_points(free, center_key, prob.frames, np.full((len(R_wc), 3), np.nan))
    line_sig, _ = determinacy(pre, relations, prob, mask, taylor, R_wc, centers, K, config)
    seen = line_sig[prob.obs_track] <= config.max_line_sigma_m  # as _mark_undetermined: determined lines only
    fixed = dataclasses.replace(prob, obs_seg=prob.obs_seg[seen], obs_track=prob.obs_track[seen],
                                obs_frame=prob.obs_frame[seen])
    _, center_sig = determinacy(pre, relations, fixed, mask, taylor, R_wc, centers, K, config)
    share = float(np.mean(center_sig[prob.frames] <= config.max_center_sigma_m)) if len(prob.frames) else 0.0
    residuals["relation_free_share"] = share
    sub = relations.subset(prob.rel_idx)
    pair = sub.kind != FLOOR
    res = np.abs(relation_residuals(sub, pre.manhattan.directions, taylor, 0.0))
    sa = line_sig[sub.track_a]
    sb = np.where(pair, line_sig[np.maximum(sub.track_b, 0)], 0.0)
    known = pair & (sa <= config.max_line_sigma_m) & (sb <= config.max_line_sigma_m)
    t, f = prob.obs_track, prob.obs_frame
    dist = np.linalg.norm(np.cross(taylor[t] - centers[f], prob.directions[t]), axis=1)
    tol = config.verify_tolerance * float(np.nanmedian(dist)) if len(dist) else 0.0
    false = known & (res > config.verify_sigma * np.hypot(sa, sb) + tol)
    log.info("BA: %d of %d coplanarities contradict the tracks' own solve and are dropped (%d checked)",
             int(false.sum()), len(false), int(known.sum()))
    return (free if share >= config.verify_start_share else values), ~false


def _keep_camera_height(sol: Solution, initial: Solution, relations: Relations, prob: _Problem,
                        manhattan: np.ndarray, residuals: dict) -> Solution:
    """Returns ``sol`` scaled about the origin so the MEAN camera-to-floor distance is the initial one.

    The floor prior (gauge) holds the floor height relative to the FIRST camera, whose centre is
    fixed; where the initial solution placed that camera badly (measured: living, linear: 3.56 m
    above the floor against a 1.45 m mean), every other camera ends at the first one's height and
    the metric scale inflates by that ratio. Scale is a gauge freedom of the relation and
    reprojection costs, so rescaling restores the linear solve's metric definition (the floor
    ``camera_height_m`` below the mean camera height) exactly.
    """
    up = _floor_normal(relations, prob, manhattan)
    h1 = residuals.get("floor_height")
    h0 = initial.residuals.get("floor_height") if isinstance(initial.residuals, dict) else None
    reg = sol.registered
    if up is None or h1 is None or h0 is None or not np.any(reg):
        return sol
    d0 = float(np.mean(initial.centers[initial.registered] @ up)) - float(h0)
    d1 = float(np.mean(sol.centers[reg] @ up)) - float(h1)
    s = d0 / d1 if d1 > 0 and d0 > 0 else 1.0
    residuals["height_rescale"] = float(s)
    if not np.isfinite(s) or abs(s - 1.0) < 1e-9:
        return sol
    residuals["floor_height"] = float(h1) * s
    return _scaled(sol, s)


def _floor_normal(relations: Relations, prob: _Problem, manhattan: np.ndarray) -> np.ndarray | None:
    """Returns the floor relations' (majority) normal, the up direction, or None without floor relations."""
    fl = prob.rel_idx[relations.kind[prob.rel_idx] == FLOOR]
    return manhattan[int(np.bincount(relations.normal_axis[fl].astype(int)).argmax())] if len(fl) else None


def _scaled(sol: Solution, s: float) -> Solution:
    """Returns ``sol`` with centres and lines scaled by ``s`` about the origin (a change of the scale gauge)."""
    lines = dataclasses.replace(sol.lines, taylor=sol.lines.taylor * s, extent=sol.lines.extent * s)
    return dataclasses.replace(sol, centers=sol.centers * s, lines=lines)


def focal_sigma(pre: Preprocessed, relations: Relations, prob: _Problem, R_wc: np.ndarray, K: np.ndarray,
                rel_mask: np.ndarray, config: GraphConfig, gauge: dict, values: gtsam.Values) -> float:
    """Returns the marginal std (px) of the focal length in the phase-3 graph at ``values`` (inf if indeterminate).

    The focal is refined (paper §3.4, phase 3) only where the images determine
    it (reprojection, colinearity, IMU and priors; relations are left out: with
    their weight 1e4 they pin it to whatever the possibly wrong structure says): a spin seen by a level camera barely constrains it (the vertical
    vanishing point is at infinity and the focal trades off against the
    rotation angles), and an undetermined focal drifts with the smallest bias
    (measured: 512 -> 520 px, lines 3 cm -> 23 cm from the true surfaces).
    The reprojection terms are taken without their kernel here (information, not fit).
    Weak priors (10 m, 1 rad) on every other variable keep the marginal
    computable when some line is undetermined; they do not change the focal's.
    """
    g = dict(gauge, focal_free=True)
    plain = dataclasses.replace(config, reprojection_robust="none")  # a kernel would make one factor per observation
    graph, _, _ = _build_graph(pre, relations, prob, 3, R_wc, K, np.zeros_like(rel_mask), plain, g)
    weak3 = gtsam.noiseModel.Isotropic.Sigma(3, 10.0)
    weak_r = gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
    for k in values.keys():
        ch = chr(gtsam.Symbol(k).chr())
        if ch in "cl":
            graph.add(gtsam.PriorFactorPoint3(k, values.atPoint3(k), weak3))
        elif ch == "r":
            graph.add(gtsam.PriorFactorRot3(k, values.atRot3(k), weak_r))
    try:
        cov = gtsam.Marginals(graph, values).marginalCovariance(FOCAL_KEY)
    except RuntimeError:
        return float("inf")
    return float(np.sqrt(max(cov[0, 0], 0.0)))


def determinacy(pre: Preprocessed, relations: Relations, prob: _Problem, rel_used: np.ndarray, taylor: np.ndarray,
                R_wc: np.ndarray, centers: np.ndarray, K: np.ndarray, config: GraphConfig,
                floor_h: float = 0.0, center_prior: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Returns (line std (T,) m, centre std (F,) m): how well each line's position and each centre are determined.

    Gauss-Newton information of one variable with all others held: a
    reprojected line moved by delta along the unit normal u of its
    interpretation plane moves by ``f delta / d`` pixels (d: camera-to-line
    distance), so each observation adds ``(f / d / sigma_px)^2 u u^T`` to the
    line's and to the frame centre's 3x3 information; each used relation
    (robust weight at its residual) adds ``n n^T / sigma^2`` to its lines.
    The std is ``1 / sqrt`` of the smallest eigenvalue (for lines, in the plane
    normal to the line's direction: the position along it is not a quantity).
    ``center_prior`` (3, 3), when given, is added to the information of every frame
    of ``prob.frames`` (the spin prior's hold on the height, or on the whole centre
    of a steady spin). Other frames without observations get inf.
    """
    T, F = len(prob.directions), len(centers)
    H_l = np.zeros((T, 3, 3))
    H_c = np.zeros((F, 3, 3))
    if len(prob.obs_seg):
        t, f = prob.obs_track, prob.obs_frame
        w = np.cross(taylor[t] - centers[f], prob.directions[t])
        d = np.linalg.norm(w, axis=1)
        ok = np.isfinite(d) & (d > 1e-9)
        u = w[ok] / d[ok, None]
        g = (K[0, 0] / d[ok] / config.reprojection_sigma_px) ** 2
        outer = g[:, None, None] * u[:, :, None] * u[:, None, :]
        np.add.at(H_l, t[ok], outer)
        np.add.at(H_c, f[ok], outer)
    r = prob.rel_idx[rel_used]
    if len(r):
        sub = relations.subset(r)
        sig = relation_sigmas(sub, config)
        white = np.abs(relation_residuals(sub, pre.manhattan.directions, taylor, floor_h)) / sig
        wgt = factors.robust_weight(white, config.robust, config.robust_k) / sig**2
        n = pre.manhattan.directions[sub.normal_axis.astype(int)]
        outer = wgt[:, None, None] * n[:, :, None] * n[:, None, :]
        np.add.at(H_l, sub.track_a, outer)
        pair = sub.kind != FLOOR
        np.add.at(H_l, sub.track_b[pair], outer[pair])
    A = prob.directions
    e1 = np.cross(A, np.where(np.abs(A[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]]))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    B = np.stack([e1, np.cross(A, e1)], axis=2)  # (T, 3, 2) basis of the plane normal to A
    lam_l = np.linalg.eigvalsh(np.einsum("tia,tij,tjb->tab", B, H_l, B))[:, 0]
    if center_prior is not None:
        seen_f = np.zeros(F, bool)
        seen_f[prob.frames] = True  # every centre variable (a steady spin's also those that see no line: _select)
        H_c[seen_f] += center_prior
    lam_c = np.linalg.eigvalsh(H_c)[:, 0]
    with np.errstate(divide="ignore"):
        return 1.0 / np.sqrt(np.maximum(lam_l, 0.0)), 1.0 / np.sqrt(np.maximum(lam_c, 0.0))


def _mark_undetermined(pre: Preprocessed, relations: Relations, prob: _Problem, rel_mask: np.ndarray, sol: Solution,
                       config: GraphConfig, values: gtsam.Values) -> Solution:
    """Returns ``sol`` with undetermined lines invalid and undetermined frames unregistered (:func:`determinacy`).

    A frame is kept only if its centre was a BA variable and its observations
    of the kept lines determine it within ``max_center_sigma_m``; a line only
    if within ``max_line_sigma_m``. Their counts go to ``residuals``.
    """
    h = values.atVector(FLOOR_KEY)[0] if values.exists(FLOOR_KEY) else 0.0
    seen = prob if config.reprojection else dataclasses.replace(prob, obs_seg=prob.obs_seg[:0],
                                                                 obs_track=prob.obs_track[:0], obs_frame=prob.obs_frame[:0])
    line_sig, _ = determinacy(pre, relations, seen, rel_mask, sol.lines.taylor, sol.R_wc, sol.centers,
                              sol.camera.K, config, h)
    line_ok = np.zeros(len(line_sig), bool)
    line_ok[prob.lines] = line_sig[prob.lines] <= config.max_line_sigma_m
    keep = line_ok[prob.obs_track] & config.reprojection  # without reprojection factors no centre is determined
    sub = dataclasses.replace(prob, obs_seg=prob.obs_seg[keep], obs_track=prob.obs_track[keep],
                              obs_frame=prob.obs_frame[keep])
    prior = None
    if config.spin_sigma_m > 0 and (config.spin_height or config.spin_position):  # the spin prior holds the height
        up = pre.manhattan.directions[2]
        prior = np.outer(up, up) / (config.spin_sigma_m * config.spin_vertical_ratio) ** 2
        if config.spin_position:  # ... and the horizontal position (a steady spin: config.SPIN_STYLES)
            prior = prior + (np.eye(3) - np.outer(up, up)) / config.spin_sigma_m ** 2
    _, center_sig = determinacy(pre, relations, sub, np.zeros(len(rel_mask), bool), sol.lines.taylor, sol.R_wc,
                                sol.centers, sol.camera.K, config, h, center_prior=prior)
    frame_ok = np.zeros(len(center_sig), bool)
    frame_ok[prob.frames] = center_sig[prob.frames] <= config.max_center_sigma_m
    registered = sol.registered & frame_ok
    valid = sol.lines.valid.copy()
    valid[prob.lines] &= line_ok[prob.lines]
    centers = np.where(registered[:, None], sol.centers, np.nan)
    R = np.where(registered[:, None, None], sol.R_wc, np.nan)
    res = dict(sol.residuals)
    res["lines_undetermined"] = int(np.sum(sol.lines.valid[prob.lines] & ~line_ok[prob.lines]))
    res["frames_undetermined"] = int(np.sum(sol.registered & ~registered))
    return dataclasses.replace(sol, registered=registered, centers=centers, R_wc=R,
                               lines=dataclasses.replace(sol.lines, valid=valid), residuals=res)


def _orthonormal(R: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(R)
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


def _gauge(relations: Relations, prob: _Problem, initial: Solution, manhattan: np.ndarray) -> dict:
    """Returns the gauge constants: first centre, floor height, and the fallback scale line."""
    # the first frame that sees a line (a steady spin's problem also holds frames that see none: _select)
    first = int(prob.obs_frame.min()) if len(prob.obs_frame) else int(np.flatnonzero(initial.registered)[0])
    c0 = np.asarray(initial.centers[first], dtype=np.float64)
    fl = prob.rel_idx[relations.kind[prob.rel_idx] == FLOOR]
    floor_h = 0.0
    if len(fl):
        n = manhattan[relations.normal_axis[fl].astype(int)]
        floor_h = float(np.median(np.sum(initial.lines.taylor[relations.track_a[fl]] * n, axis=1)))
    counts = np.bincount(prob.obs_track, minlength=len(prob.directions)) if len(prob.obs_track) else np.zeros(1, int)
    best = int(np.argmax(counts)) if len(prob.lines) else 0
    lam = np.asarray(initial.lines.taylor[best], dtype=np.float64)
    A = prob.directions[best]
    v = lam - c0
    v = v - (v @ A) * A
    dist = float(np.linalg.norm(v))
    normal = v / dist if dist > 1e-9 else np.cross(A, [0.0, 0.0, 1.0] if abs(A[2]) < 0.9 else [1.0, 0.0, 0.0])
    normal = normal / np.linalg.norm(normal)
    return {"first": first, "first_center": c0, "floor_h": floor_h, "scale_line": best,
            "scale_normal": normal, "scale_offset": float(normal @ (lam - c0))}


def bundle_adjust_incremental(pre: Preprocessed, tracks: Tracks, relations: Relations, initial: Solution,
                              config: GraphConfig = GraphConfig(), batch_frames: int | None = None,
                              on_batch: Callable[[int, Solution], None] | None = None) -> list[Solution]:
    """Returns the per-batch bundle-adjusted Solutions (the last is the final one) as frames arrive in batches.

    Registered frames are added in time order, ``batch_frames`` at a time
    (default ``config.incremental_batch``, else 50). Each batch is a
    warm-started batch solve (:func:`bundle_adjust`, all phases) over the
    frames so far: frames and lines already estimated start from the previous
    batch's estimate, new ones from ``initial``. (Measured against iSAM2 in
    ``tools/bench_ba.py``: see the report.) In a batch's Solution only the
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
