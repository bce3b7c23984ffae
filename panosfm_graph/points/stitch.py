"""The focal length a spin's point tracks give when the spin turns about the camera (our addition; issue #41 item 5).

A panorama stitcher finds the focal length of a camera turned about its optical centre from its feature tracks
alone: over a whole turn the frames' rotations must close, and only the true focal length maps each corner's
image motion onto those rotations. :func:`stitched_focal` fits it the same way: a ``Rot3`` per frame (tied to its
neighbour by the IMU's relative rotation, loosely, and held towards the IMU's attitude only as a gauge), each point
track a bearing (a ``Point3`` at unit distance with a weak prior), one focal length (a 1-vector), the corners seen
through :class:`factors.PointProjectionSet` (Huber) from one fixed centre. Where the spin has parallax (a phone on
an arm) no focal length makes the bearings fit, and the fit's RMS reprojection distance says so: the focal length
is taken only where that RMS is at most ``focal.stitch_max_rms_px``. The Manhattan vanishing points
(:mod:`panosfm_graph.lines.focal`) start it: their estimate is biased where a room's furniture and floor boards do
not follow its walls (docs/decisions.md#stitched-focal-length).
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import gtsam
import numpy as np

import factors

from ..config import PointsConfig
from ..data import Capture, PointTracks

GAUGE_SIGMA_DEG = 5.0  # each frame held towards the IMU's attitude this loosely: the gauge and the IMU's drift
IMU_SIGMA_DEG = 1.0  # the IMU's relative rotation between neighbours, loosely: the corners decide
FOCAL_PRIOR_FRAC = 0.25  # the focal's weak prior about its start (sigma, share of it)
POINT_PRIOR = 1.0  # a bearing's weak prior (at graph.rotation_only.ASSUMED_DISTANCE, 1: about a radian)
MAX_FRAMES = 90  # the spin's frames are taken every k-th, at most this many: a turn's closure fixes the focal length


@dataclass(frozen=True)
class StitchedFocal:
    """The focal length fitted to the point tracks as bearings, and how well a turn about the centre explains them."""

    focal_px: float
    start_px: float  # where the fit started (the vanishing points' estimate)
    rms_px: float  # RMS reprojection distance of the corners after the fit
    tracks: int
    observations: int
    accepted: bool  # rms_px within the bound: the spin turns about the camera and the focal length is used
    seconds: float


def stitched_focal(points: PointTracks, R_wc_imu: np.ndarray, K: np.ndarray, config: PointsConfig,
                   max_rms_px: float, iterations: int = 30) -> StitchedFocal | None:
    """Returns the focal length (fx; fy keeps K's aspect) the point tracks give as bearings about one centre
    (module docstring), started from ``K``'s; None without point tracks seen in ``config.min_frames`` frames."""
    from ..graph.lm import levenberg_marquardt
    from ..graph.problem import FOCAL_KEY, center_key, rotation_key
    from ..graph.rotation_only import bearing_set

    t0 = time.perf_counter()
    F = len(R_wc_imu)
    values, graph = gtsam.Values(), gtsam.NonlinearFactorGraph()
    obs = bearing_set(points, R_wc_imu, K, config, graph, values, gtsam.noiseModel.Isotropic.Sigma(3, POINT_PRIOR),
                      FOCAL_KEY)
    if obs is None:
        return None
    gauge = gtsam.noiseModel.Isotropic.Sigma(3, np.radians(GAUGE_SIGMA_DEG))
    for i in range(F):
        values.insert(rotation_key(i), gtsam.Rot3(R_wc_imu[i]))
        graph.add(gtsam.PriorFactorRot3(rotation_key(i), gtsam.Rot3(R_wc_imu[i]), gauge))
    imu = factors.imu_noise(IMU_SIGMA_DEG)
    for i in range(F - 1):
        graph.add(factors.imu_rotation_factor(rotation_key(i), rotation_key(i + 1), R_wc_imu[i], R_wc_imu[i + 1], imu))
    values.insert(center_key(0), np.zeros(3))
    graph.add(gtsam.PriorFactorPoint3(center_key(0), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    f0 = float(K[0, 0])
    values.insert(FOCAL_KEY, np.array([f0]))
    graph.add(gtsam.PriorFactorVector(FOCAL_KEY, np.array([f0]), gtsam.noiseModel.Isotropic.Sigma(
        1, FOCAL_PRIOR_FRAC * f0)))
    values, _ = levenberg_marquardt(graph, values, iterations, batches=[obs])
    rms = float(np.sqrt(np.mean(np.sum(obs.residuals(values) ** 2, axis=1))))
    fx = float(values.atVector(FOCAL_KEY)[0])
    return StitchedFocal(focal_px=fx, start_px=f0, rms_px=rms, tracks=len(set(obs.point_keys)),
                         observations=len(obs), accepted=bool(rms <= max_rms_px),
                         seconds=round(time.perf_counter() - t0, 3))


def spin_focal(capture: Capture, config: PointsConfig, max_rms_px: float, max_frames: int = MAX_FRAMES
               ) -> StitchedFocal | None:
    """Returns :func:`stitched_focal` of the capture's point tracks (predicted by its IMU attitude, from its camera's
    focal length), every k-th frame taken so that at most ``max_frames`` are (the tracker's allowance grows with
    the step: points/tracking.py)."""
    from .tracking import track_points

    k = max(1, int(np.ceil(capture.n_frames / max_frames)))
    if k > 1:
        reader = capture.reader
        capture = dataclasses.replace(capture, frame_names=capture.frame_names[::k], timestamps=capture.timestamps[::k],
                                      R_wc_imu=capture.R_wc_imu[::k], reader=lambda i: reader(k * i), ground_truth=None)
    return stitched_focal(track_points(capture, capture.R_wc_imu, config), capture.R_wc_imu, capture.camera.K, config,
                          max_rms_px)
