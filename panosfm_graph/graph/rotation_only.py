"""Bundle adjustment of a zero-baseline spin (our addition to paper §3.4): rotations and lines, one fixed centre.

With no parallax (:mod:`..linear.baseline`) the centres are not solved, but the rotations still are: each
tracked line lies on ONE plane through the shared centre, seen in every frame of its track, so the line
reprojection factors of §3.4 tie the frames' rotations together across the spin exactly as in the full
bundle adjustment. The graph: ``r<i>`` ``Rot3`` for every frame, ``l<t>`` ``Point3`` Taylor vector for each
track seen in >= 2 frames, one centre ``c0`` held at the origin by a tight prior (every observation's
centre); factors: line reprojection (:class:`factors.LineReprojectionSet`, Geman-McClure, its threshold
graduated from the initial residuals to ``reprojection_robust_k`` as in phase 1 and 2), IMU relative
rotations between consecutive frames, the rotation prior to the preprocessed (vanishing-point) rotations.
A line's distance from the centre is not observable: every line starts at ``ASSUMED_DISTANCE`` (1 unit)
towards its segments' mean viewing ray, a weak isotropic prior (sigma 1 unit: about a radian across the
line) holds that distance and the point along the line, and the lines are drawn at that distance (on a
cylinder about the centre, as directions; ``residuals["assumed_line_distance"]``).

With point tracks (:mod:`panosfm_graph.points`, ``points.zero_baseline``) each texture corner tracked over
``points.min_frames`` frames joins as a bearing: a ``Point3`` ``p<k>`` at the assumed distance with the same weak
prior, seen through :class:`factors.PointProjectionSet` (Huber) from the fixed centre, as a panorama stitcher ties
its frames. The lines hold the rotations to the Manhattan directions, and a real room's walls depart from them by a
fraction of a degree, wall by wall; the corners tie neighbouring frames to each other whatever the walls do
(docs/decisions.md#zero-baseline-points).

Not worse than its input by its own measure: when the RMS reprojection distance over every observation (lines, and
points where they joined) ends higher than with the preprocessed rotations, those are kept and
``residuals["kept_preprocessed"]`` says so. Measured (docs/decisions.md#zero-baseline-rotations): real panorama
cuts move 0.1 degrees (median), the worst frames most.
"""
from __future__ import annotations

import dataclasses
import logging
import time

import gtsam
import numpy as np

import factors

from ..config import GraphConfig, PointsConfig
from ..data import LineModel, PointTracks, Preprocessed, Solution, Tracks
from ..geometry import rotation_angle_deg, world_rays
from .factor_graph import FOCAL_PRIOR_FRAC, GAUGE_SIGMA, widened_robust_k
from .lm import levenberg_marquardt
from .problem import FOCAL_KEY, center_key, line_key, point_key, rotation_key
from .readout import _camera_with_focal, line_extents, track_extents

log = logging.getLogger("panosfm.graph")

ASSUMED_DISTANCE = 1.0  # a line's distance from the centre, unobservable: each is drawn this far (model units)
MAX_EXTENT = 3.0  # ... and at most this far along itself from its closest point (75 degrees off the perpendicular)


def _initial_taylor(pre: Preprocessed, tracks: Tracks, K: np.ndarray, obs_seg: np.ndarray,
                    obs_track: np.ndarray) -> np.ndarray:
    """Returns (T, 3) Lambda at ``ASSUMED_DISTANCE`` from the centre, towards the mean viewing ray of each track's
    segments (0 for tracks without observations)."""
    M = np.asarray(pre.manhattan.directions, dtype=np.float64)
    A = M[tracks.axis.astype(int)]
    ep = pre.segments.endpoints[obs_seg].astype(np.float64)
    ray = world_rays(K, pre.R_wc[pre.segments.frame[obs_seg]], 0.5 * (ep[:, :2] + ep[:, 2:]))
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    mean = np.stack([np.bincount(obs_track, ray[:, k], minlength=tracks.n) for k in range(3)], axis=1)
    mean -= np.sum(mean * A, axis=1, keepdims=True) * A  # on the constraint manifold A . Lambda = 0
    return ASSUMED_DISTANCE * mean / np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)


def bearing_set(points: PointTracks, R_wc: np.ndarray, K: np.ndarray, config: PointsConfig,
                 graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, prior, focal_key: int | None = None,
                 centers: np.ndarray | None = None, depth: float = ASSUMED_DISTANCE
                 ) -> factors.PointProjectionSet | None:
    """Returns the observations of the point tracks seen in ``config.min_frames`` frames as bearings
    (module docstring), each point inserted into ``values`` ``depth`` (``ASSUMED_DISTANCE``) along the mean viewing ray
    of its observations at ``R_wc`` with the weak ``prior`` in ``graph``, each frame's rotation ``r<i>`` and the
    one centre ``c0`` variables (and the focal length ``focal_key`` where given); None where no track is that long
    (also :func:`panosfm_graph.points.stitched_focal`'s). With ``centers`` (F, 3) each frame is seen from its own
    centre ``c<i>`` instead, each point starts ``depth`` along its mean ray from the mean of its frames' centres,
    and ``prior`` may be None (no prior: :func:`panosfm_graph.points.arm_focal`'s)."""
    t = points.track.astype(np.int64)
    n_obs = np.bincount(t, minlength=points.n)
    keep = n_obs[t] >= config.min_frames
    if not keep.any():
        return None
    ray = world_rays(K, R_wc[points.frame], points.xy.astype(np.float64))
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    mean = np.stack([np.bincount(t, ray[:, k], minlength=points.n) for k in range(3)], axis=1)
    bearing = depth * mean / np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    if centers is not None:
        C = np.asarray(centers, dtype=np.float64)[points.frame]
        bearing += np.stack([np.bincount(t, C[:, k], minlength=points.n) for k in range(3)], axis=1) / np.maximum(
            n_obs, 1)[:, None]
    pt, pf = t[keep], points.frame[keep].astype(np.int64)
    for p in np.unique(pt):
        values.insert(point_key(int(p)), bearing[p])
        if prior is not None:
            graph.add(gtsam.PriorFactorPoint3(point_key(int(p)), bearing[p], prior))
    center_keys = [center_key(0)] * len(pt) if centers is None else [center_key(int(i)) for i in pf]
    return factors.PointProjectionSet(center_keys, [point_key(int(p)) for p in pt],
                                      points.xy[keep].astype(np.float64), K, config.sigma_px, R_wc[pf],
                                      rotation_keys=[rotation_key(int(i)) for i in pf], robust="huber",
                                      k=config.robust_k, focal_key=focal_key)


def _rotation_graph(pre: Preprocessed, R0: np.ndarray, taylor0: np.ndarray, lines: np.ndarray, config: GraphConfig
                    ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, gtsam.noiseModel.Base]:
    """Returns (graph, values, the lines' weak prior): a Rot3 per frame at ``R0``, the fixed centre, the lines at
    ``taylor0`` with their weak priors, the rotation prior and the IMU's relative rotations (module docstring)."""
    F = len(R0)
    values = gtsam.Values()
    for i in range(F):
        values.insert(rotation_key(i), gtsam.Rot3(R0[i]))
    values.insert(center_key(0), np.zeros(3))
    for t in lines:
        values.insert(line_key(int(t)), taylor0[t])
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPoint3(center_key(0), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, GAUGE_SIGMA)))
    line_prior = gtsam.noiseModel.Isotropic.Sigma(3, ASSUMED_DISTANCE)  # about a radian across the line
    for t in lines:
        graph.add(gtsam.PriorFactorPoint3(line_key(int(t)), taylor0[t], line_prior))
    if config.rotation_prior_sigma_deg > 0:
        noise = gtsam.noiseModel.Isotropic.Sigma(3, float(np.radians(config.rotation_prior_sigma_deg)))
        for i in range(F):
            graph.add(gtsam.PriorFactorRot3(rotation_key(i), gtsam.Rot3(R0[i]), noise))
    if config.imu_prior:
        noise = factors.imu_noise(config.imu_sigma_deg)
        for i in range(F - 1):
            graph.add(factors.imu_rotation_factor(rotation_key(i), rotation_key(i + 1), pre.R_wc_imu[i],
                                                  pre.R_wc_imu[i + 1], noise))
    return graph, values, line_prior


def _fit_rms(line_rms: float, n_lines: int, bearings: factors.PointProjectionSet | None, values: gtsam.Values,
             res: dict, key: str) -> float:
    """Returns the RMS reprojection distance (px) over the line observations (``line_rms`` over ``n_lines``) and the
    bearings' at ``values``; the bearings' own RMS goes into ``res[key]``."""
    if bearings is None:
        return line_rms
    sq = np.sum(bearings.residuals(values) ** 2, axis=1)
    res[key] = float(np.sqrt(np.mean(sq)))
    return float(np.sqrt((n_lines * line_rms ** 2 + np.sum(sq)) / (n_lines + len(sq))))


def rotation_bundle_adjust(pre: Preprocessed, tracks: Tracks, initial: Solution, config: GraphConfig,
                           points: PointTracks | None = None, points_config: PointsConfig = PointsConfig(),
                           focal_free: bool = False) -> Solution:
    """Returns the zero-baseline solution with rotations refined by the lines (module docstring), centres at 0.

    ``initial``: the linear zero-translation solve (every frame registered, centres 0). The result keeps its
    registration and centres; ``residuals`` record the reprojection RMS before and after and how far the
    rotations moved (from the preprocessed ones, degrees). ``focal_free`` with point tracks: the focal length is a
    variable too (the bearings of a whole turn fix it; ``residuals["focal_px"]`` before and after).
    """
    t0 = time.perf_counter()
    F = len(pre.R_wc)
    K = initial.camera.K
    seg, offsets = tracks.members()
    frames_of_track = np.diff(offsets)
    keep = frames_of_track[tracks.track_of[seg]] >= 2
    obs_seg = seg[keep]
    obs_track = tracks.track_of[obs_seg].astype(np.int64)
    obs_frame = pre.segments.frame[obs_seg].astype(np.int64)
    lines = np.unique(obs_track)
    res: dict = {"zero_baseline": True, "assumed_line_distance": ASSUMED_DISTANCE, "frames": F, "lines": int(len(lines)), "observations": int(len(obs_seg))}
    if len(lines) < 3:
        log.warning("zero baseline: %d lines seen in >= 2 frames, too few to refine the rotations", len(lines))
        res["skipped"] = "too few lines"
        return _with(initial, res)
    M = np.asarray(pre.manhattan.directions, dtype=np.float64)
    A = M[tracks.axis.astype(int)]
    taylor0 = _initial_taylor(pre, tracks, K, obs_seg, obs_track)
    R0 = np.asarray(pre.R_wc, dtype=np.float64)
    ep = pre.segments.endpoints[obs_seg].astype(np.float64)
    zeros = np.zeros((len(obs_seg), 3))

    def rms(taylor: np.ndarray, R: np.ndarray, K: np.ndarray = K) -> float:  # RMS segment-averaged distance (px)
        r = factors.reprojection_terms(ep, A[obs_track], taylor[obs_track], zeros, R[obs_frame], K)
        return float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))

    rms0 = rms(taylor0, R0)

    graph, values, line_prior = _rotation_graph(pre, R0, taylor0, lines, config)
    bearings = (bearing_set(points, R0, K, points_config, graph, values, line_prior,
                             FOCAL_KEY if focal_free else None) if points is not None else None)
    focal = focal_free and bearings is not None
    if focal:  # the focal length refined with the rotations (weak prior, as the bundle adjustment's phase 3)
        values.insert(FOCAL_KEY, np.array([K[0, 0]]))
        graph.add(gtsam.PriorFactorVector(FOCAL_KEY, np.array([K[0, 0]]),
                                          gtsam.noiseModel.Isotropic.Sigma(1, FOCAL_PRIOR_FRAC * K[0, 0])))
    batches = [] if bearings is None else [bearings]
    if bearings is not None:
        res["point_tracks"], res["point_observations"] = len(set(bearings.point_keys)), len(bearings)
    fit0 = _fit_rms(rms0, len(obs_seg), bearings, values, res, "point_rms_initial")
    ks = tuple(config.reprojection_robust_k) or (0.0,)
    k_final = float(ks[-1])
    k_first = widened_robust_k(config, k_final, rms0) if k_final > 0 else 0.0
    info = {}
    for k in (k_first, k_final):  # graduated: as wide as the initial residuals, then k
        robust = config.reprojection_robust if k > 0 else "none"
        rep = factors.LineReprojectionSet([line_key(int(t)) for t in obs_track], [center_key(0)] * len(obs_seg), ep,
                                          A[obs_track], K, config.reprojection_sigma_px,
                                          rotation_keys=[rotation_key(int(i)) for i in obs_frame], robust=robust,
                                          k=k if k > 0 else 1.345, focal_key=FOCAL_KEY if focal else None)
        values, info = levenberg_marquardt(graph, values, max_iterations=config.max_iterations,
                                           batches=[rep] + batches)
    R = np.array([values.atRot3(rotation_key(i)).matrix() for i in range(F)])
    raw = np.array([values.atPoint3(line_key(int(t))) for t in lines]).reshape(-1, 3)
    taylor = np.zeros((tracks.n, 3))
    raw = factors.taylor_from_point_direction(raw, A[lines])
    taylor[lines] = ASSUMED_DISTANCE * raw / np.maximum(np.linalg.norm(raw, axis=1, keepdims=True), 1e-12)
    camera = _camera_with_focal(initial.camera, values.atVector(FOCAL_KEY)[0]) if focal else initial.camera
    if focal:
        res["focal_px"] = [float(K[0, 0]), float(camera.K[0, 0])]  # before, after
    rms1 = rms(taylor, R, camera.K)
    fit1 = _fit_rms(rms1, len(obs_seg), bearings, values, res, "point_rms")  # every observation's, as fit0
    moved = rotation_angle_deg(R, R0)
    res.update(reprojection_rms_initial=rms0, reprojection_rms=rms1, iterations=int(info.get("iterations", 0)),
               rotation_change_deg={"median": float(np.median(moved)), "max": float(np.max(moved))},
               seconds=time.perf_counter() - t0)
    if not fit1 <= fit0:  # the lines (and points) fit worse: keep the preprocessed rotations (never silently worse)
        log.warning("zero baseline: the rotation refinement fits the %s worse (%.2f -> %.2f px): kept the "
                    "preprocessed rotations", "lines and points" if batches else "lines", fit0, fit1)
        res["kept_preprocessed"] = True
        return _with(initial, res)
    extent = np.zeros((tracks.n, 2))
    s = np.clip(line_extents(taylor[obs_track], A[obs_track], ep, R[obs_frame], zeros, camera.K), -MAX_EXTENT,
                MAX_EXTENT)
    lo_hi, ok = track_extents(s, obs_track, tracks.n)
    extent[ok] = lo_hi[ok]
    valid = np.zeros(tracks.n, bool)
    valid[lines] = True
    valid &= ok
    line_model = LineModel(taylor=taylor, direction=A.copy(), axis=tracks.axis.copy(), extent=extent, valid=valid)
    log.info("zero baseline: rotations refined by %d lines, reprojection %.2f -> %.2f px, moved %.2f deg "
             "(median) in %.1f s", len(lines), rms0, rms1, res["rotation_change_deg"]["median"], res["seconds"])
    return Solution(R_wc=R, centers=np.zeros((F, 3)), registered=np.ones(F, bool), lines=line_model,
                    camera=camera, metric=False, residuals=res, relations_kept=initial.relations_kept)


def _with(initial: Solution, res: dict) -> Solution:
    """Returns ``initial`` with the zero-baseline BA's residuals (nothing refined)."""
    return dataclasses.replace(initial, residuals=res)
