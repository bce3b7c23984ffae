"""The focal length a spin's point tracks give (our addition; issue #41 item 5).

A panorama stitcher finds the focal length of a camera turned about its optical centre from its feature tracks
alone: over a whole turn the frames' rotations must close, and only the true focal length maps each corner's
image motion onto those rotations. :func:`stitched_focal` fits it the same way: a ``Rot3`` per frame (tied to its
neighbour by the IMU's relative rotation, loosely, and held towards the IMU's attitude only as a gauge), each point
track a bearing (a ``Point3`` at unit distance with a weak prior), one focal length (a 1-vector), the corners seen
through :class:`factors.PointProjectionSet` (Huber) from one fixed centre. Where the spin has parallax (a phone on
an arm) no focal length makes the bearings fit, and the fit's reprojection distances say so: the focal length
is taken only where 90 % of them are at most ``focal.stitch_max_p90_px`` (a percentile, not the RMS: a few stray
corners in a large hall put the RMS of a true fit over 1 px, its 90th percentile at 0.5).

A phone on an arm moves its centre sideways as it turns, so the image moves more per radian than the rotation
alone explains and the bearings' focal length comes out long (+15 to +22 % on synthetic arm spins). :func:`arm_focal`
then fits the same tracks with the camera on the spin's circle: a centre per frame on the spin prior of the bundle
adjustment (:mod:`factors.spin_prior`: stand-point knots a random walk apart, one arm, its forward length fixed as
the scale's gauge), each track a 3D point (started at a room's distance along its mean ray), the rotations and
the focal length as above; taken within the same bound
(docs/decisions.md#focal-on-an-arm). The Manhattan vanishing points (:mod:`panosfm_graph.lines.focal`) start
both: their estimate is biased where a room's furniture and floor boards do not follow its walls
(docs/decisions.md#stitched-focal-length).
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import gtsam
import numpy as np

import factors

from ..config import GraphConfig, PointsConfig
from ..data import Capture, PointTracks

GAUGE_SIGMA_DEG = 5.0  # each frame held towards the IMU's attitude this loosely: the gauge and the IMU's drift
IMU_SIGMA_DEG = 1.0  # the IMU's relative rotation between neighbours, loosely: the corners decide
FOCAL_PRIOR_FRAC = 0.25  # the focal's weak prior about its start (sigma, share of it)
POINT_PRIOR = 1.0  # a bearing's weak prior (at graph.rotation_only.ASSUMED_DISTANCE, 1: about a radian)
MAX_FRAMES = 90  # the spin's frames are taken every k-th, at most this many: a turn's closure fixes the focal length
ROOM_DEPTH = 2.5  # arm_focal: each point starts this far along its mean ray (m, as the arm's length is)


@dataclass(frozen=True)
class StitchedFocal:
    """The focal length fitted to the point tracks as bearings, and how well a turn about the centre explains them."""

    focal_px: float
    start_px: float  # where the fit started (the vanishing points' estimate)
    rms_px: float  # RMS reprojection distance of the corners after the fit
    p90_px: float  # ... and its 90th percentile, which decides (a few stray corners do not)
    tracks: int
    observations: int
    accepted: bool  # p90_px within the bound: the model explains the spin and the focal length is used
    seconds: float
    model: str = "centre"  # "centre": bearings about one centre (stitched_focal); "arm": on the spin's circle
    centre_p90_px: float | None = None  # model "arm": the bearings' p90_px about one centre, which did not fit


def stitched_focal(points: PointTracks, R_wc_imu: np.ndarray, K: np.ndarray, config: PointsConfig,
                   max_p90_px: float, iterations: int = 30) -> StitchedFocal | None:
    """Returns the focal length (fx; fy keeps K's aspect) the point tracks give as bearings about one centre
    (module docstring), started from ``K``'s; None without point tracks seen in ``config.min_frames`` frames."""
    from ..graph.problem import FOCAL_KEY, center_key
    from ..graph.rotation_only import bearing_set

    t0 = time.perf_counter()
    values, graph = gtsam.Values(), gtsam.NonlinearFactorGraph()
    obs = bearing_set(points, R_wc_imu, K, config, graph, values, gtsam.noiseModel.Isotropic.Sigma(3, POINT_PRIOR),
                      FOCAL_KEY)
    if obs is None:
        return None
    values.insert(center_key(0), np.zeros(3))
    graph.add(gtsam.PriorFactorPoint3(center_key(0), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    return _fit(graph, values, obs, R_wc_imu, K, max_p90_px, iterations, t0, "centre")


def _fit(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, obs: factors.PointProjectionSet, R_wc: np.ndarray,
         K: np.ndarray, max_p90_px: float, iterations: int, t0: float, model: str) -> StitchedFocal:
    """Adds the rotations (IMU gauge and relative rotations) and the focal length (weak prior at ``K``'s) to the
    graph, solves it and returns the fit."""
    from ..graph.lm import levenberg_marquardt
    from ..graph.problem import FOCAL_KEY, rotation_key

    gauge = gtsam.noiseModel.Isotropic.Sigma(3, np.radians(GAUGE_SIGMA_DEG))
    for i in range(len(R_wc)):
        values.insert(rotation_key(i), gtsam.Rot3(R_wc[i]))
        graph.add(gtsam.PriorFactorRot3(rotation_key(i), gtsam.Rot3(R_wc[i]), gauge))
    imu = factors.imu_noise(IMU_SIGMA_DEG)
    for i in range(len(R_wc) - 1):
        graph.add(factors.imu_rotation_factor(rotation_key(i), rotation_key(i + 1), R_wc[i], R_wc[i + 1], imu))
    f0 = float(K[0, 0])
    values.insert(FOCAL_KEY, np.array([f0]))
    graph.add(gtsam.PriorFactorVector(FOCAL_KEY, np.array([f0]), gtsam.noiseModel.Isotropic.Sigma(
        1, FOCAL_PRIOR_FRAC * f0)))
    values, _ = levenberg_marquardt(graph, values, iterations, batches=[obs])
    r = np.linalg.norm(obs.residuals(values), axis=1)
    p90 = float(np.percentile(r, 90))
    fx = float(values.atVector(FOCAL_KEY)[0])
    return StitchedFocal(focal_px=fx, start_px=f0, rms_px=float(np.sqrt(np.mean(r ** 2))), p90_px=p90,
                         tracks=len(set(obs.point_keys)), observations=len(obs), accepted=bool(p90 <= max_p90_px),
                         seconds=round(time.perf_counter() - t0, 3), model=model)


def arm_focal(points: PointTracks, R_wc_imu: np.ndarray, K: np.ndarray, config: PointsConfig,
              graph_config: GraphConfig, max_p90_px: float, iterations: int = 40) -> StitchedFocal | None:
    """Returns the focal length the point tracks give with the camera on the spin's circle (module docstring), started
    from ``K``'s; None without point tracks seen in ``config.min_frames`` frames."""
    from ..geometry import turned_degrees
    from ..graph.problem import ARM_KEY, FOCAL_KEY, center_key, stand_key
    from ..graph.rotation_only import bearing_set

    t0 = time.perf_counter()
    F, g = len(R_wc_imu), graph_config
    arm = np.array([g.metric_arm_fallback_m, 0.0])  # the scale's gauge: the arm's forward length (not metric)
    M = np.eye(3)  # the spin prior's horizontal axes and up (+z, the IMU's gravity-aligned world)
    j, alpha, n_knots = factors.spin_knots(turned_degrees(R_wc_imu), g.spin_knot_deg)
    C0 = np.concatenate([arm[0] * factors.horizontal_direction(M, R_wc_imu[:, :, 2]), np.zeros((F, 1))], axis=1)
    values, graph = gtsam.Values(), gtsam.NonlinearFactorGraph()
    obs = bearing_set(points, R_wc_imu, K, config, graph, values, None, FOCAL_KEY, centers=C0, depth=ROOM_DEPTH)
    if obs is None:
        return None
    hold = gtsam.noiseModel.Isotropic.Sigma(3, 1e-4)
    for k in range(n_knots):
        values.insert(stand_key(k), np.zeros(3))
        if k:
            graph.add(gtsam.BetweenFactorPoint3(stand_key(k - 1), stand_key(k), np.zeros(3),
                                                gtsam.noiseModel.Isotropic.Sigma(3, g.spin_walk_sigma_m)))
    graph.add(gtsam.PriorFactorPoint3(stand_key(0), np.zeros(3), hold))
    values.insert(ARM_KEY, arm)
    graph.add(gtsam.PriorFactorVector(ARM_KEY, arm, gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-4, 10.0 * arm[0]]))))
    noise = factors.spin_noise(g.spin_sigma_m, g.spin_sigma_m * g.spin_vertical_ratio)
    for i in range(F):
        values.insert(center_key(i), C0[i])
        graph.add(factors.spin_prior_factor(center_key(i), (stand_key(j[i]), stand_key(min(j[i] + 1, n_knots - 1))),
                                            alpha[i], ARM_KEY, M, R_wc_imu[i][:, 2], noise))
    return _fit(graph, values, obs, R_wc_imu, K, max_p90_px, iterations, t0, "arm")


def spin_focal(capture: Capture, config: PointsConfig, max_p90_px: float, max_frames: int = MAX_FRAMES,
               graph_config: GraphConfig | None = None) -> StitchedFocal | None:
    """Returns :func:`stitched_focal` of the capture's point tracks (predicted by its IMU attitude, from its camera's
    focal length), every k-th frame taken so that at most ``max_frames`` are (the tracker's allowance grows with
    the step: points/tracking.py). Where the bearings do not fit and ``graph_config`` is given, :func:`arm_focal`
    of the same tracks instead (its ``centre_p90_px`` the bearings')."""
    from .tracking import track_points

    k = max(1, int(np.ceil(capture.n_frames / max_frames)))
    if k > 1:
        reader = capture.reader
        capture = dataclasses.replace(capture, frame_names=capture.frame_names[::k], timestamps=capture.timestamps[::k],
                                      R_wc_imu=capture.R_wc_imu[::k], reader=lambda i: reader(k * i), ground_truth=None)
    points = track_points(capture, capture.R_wc_imu, config)
    centre = stitched_focal(points, capture.R_wc_imu, capture.camera.K, config, max_p90_px)
    if centre is None or centre.accepted or graph_config is None:
        return centre
    arm = arm_focal(points, capture.R_wc_imu, capture.camera.K, config, graph_config, max_p90_px)
    if arm is None:
        return centre
    return dataclasses.replace(arm, centre_p90_px=centre.p90_px, seconds=round(centre.seconds + arm.seconds, 3))
