"""The time offset from the lines' rotations, where the images' turns cannot time a smooth spin (issue #41 item 4).

:func:`.sync.estimate_sync` times the video by the camera's turn between
consecutive frames. A spin without hand tremor turns at a nearly constant
rate; what times it is its slow wobble in pitch and roll, and between two
frames that wobble is as small as the error parallax puts into the images'
turns, so the offset comes out tens to hundreds of milliseconds off and is
reported loose. The Manhattan lines give every frame's absolute rotation
instead (the pipeline's own preprocessing, paper §3.1 and supplement §2),
where the wobble (1-3 degrees) is seen whole, not differentiated.

:func:`line_offset` scores each offset by how well the gyroscope's attitude
at the frames' sensor times (bias removed), turned by one rotation per
window of :data:`WINDOW_S` (the gyroscope's heading drifts; a constant turn
rate's time shift is a turn about the vertical and is absorbed too), matches
the lines' rotations, each frame's axes weighted by the Manhattan segments
that fix them (:func:`axis_weights`), robustly (Huber). The rotation
refinement holds the frames to the attitude's relative rotations, which carry
the old offset's error in part, so :func:`retime_by_lines` repeats
refinement, offset and attitude (:data:`ITERATIONS`); it holds no frame to
the attitude's tilt or heading, which carry that error whole. The importer
writes the tighter of the turns' and the lines' offsets
(docs/decisions.md#time-offset-from-the-lines).
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation, Slerp

from ..config import Config
from ..data import Capture, Segments
from ..errors import InputError
from .attitude import Attitude, smooth_attitude
from .logs import RawSensors
from .sync import kabsch, gyro_orientation, independent_samples

log = logging.getLogger("panosfm.phone")

WINDOW_S = 2.0  # one free rotation per window: the gyroscope's drift within it is small against the wobble
COARSE_STEP_S = 0.02  # the first search's grid over the whole range, then refined within +- one step
FINE_STEP_S = 0.005
FINE_HALF_S = 0.06  # later searches: this far around the previous offset
ITERATIONS = 3  # rounds of refinement, offset, attitude (the third moved it 0-8 ms on seven smooth spins)
HUBER_DEG = 0.5  # a frame's residual angle beyond this counts linearly (a frame whose lines mislead it)
MIN_FRAMES = 20  # fewer frames with Manhattan segments: no timing from the lines


@dataclass(frozen=True)
class LineTiming:
    """The offset the lines' rotations give and how it got there."""

    offset_s: float  # sensor clock minus video clock
    offset_sigma_s: float  # from the cost's curvature and the residuals' independent frames
    offsets_s: tuple[float, ...]  # the offset after each iteration
    frames: int  # frames with Manhattan segments
    seconds: float


def axis_weights(segments: Segments, labels: np.ndarray, n_frames: int) -> np.ndarray:
    """Returns (F, 3) how well each frame's lines fix its rotation about the camera's x, y, z axes (0..1).

    Horizontal Manhattan segments fix the pitch (x) and the heading (y, about the nearly vertical camera y);
    every Manhattan segment fixes the roll (z). ``n / (n + 2)``: two segments count half.
    """
    horizontal = (labels == 0) | (labels == 1)
    nh = np.bincount(segments.frame[horizontal], minlength=n_frames).astype(np.float64)
    na = nh + np.bincount(segments.frame[labels == 2], minlength=n_frames)
    return np.column_stack([nh / (nh + 2.0), nh / (nh + 2.0), na / (na + 2.0)])


class OffsetCost:
    """``cost(offset)``: the weighted mean Huber cost (rad²) of the angle between the lines' rotations ``R_lines``
    (F, 3, 3) and the gyroscope's camera attitude ``Q(t + offset) camera_from_device^T``, each window of
    ``window_s`` (default :data:`WINDOW_S`) turned by its best rotation."""

    def __init__(self, R_lines: np.ndarray, weights: np.ndarray, Q: Slerp, camera_from_device: np.ndarray,
                 t_frames: np.ndarray, window_s: float | None = None):
        t_frames = np.asarray(t_frames, dtype=np.float64)
        self.R_lines, self.weights, self.Q, self.t = R_lines, weights, Q, t_frames
        self.window = np.floor((t_frames - t_frames[0]) / (window_s or WINDOW_S)).astype(int)
        self.frame_w = weights.mean(axis=1)
        self.C_t = np.asarray(camera_from_device, dtype=np.float64).T

    def residuals(self, offset: float) -> np.ndarray:
        """Returns (F, 3) each frame's angle (rad, camera axes) from the gyroscope's attitude at ``offset``."""
        G = self.Q(self.t + offset).as_matrix() @ self.C_t  # world_gyro from camera
        M = np.zeros((int(self.window.max()) + 1, 3, 3))
        np.add.at(M, self.window, self.frame_w[:, None, None] * np.einsum("nij,nkj->nik", self.R_lines, G))
        A = kabsch(M)  # world_lines from world_gyro, per window
        return Rotation.from_matrix(np.einsum("nji,njk->nik", self.R_lines, A[self.window] @ G)).as_rotvec()

    def __call__(self, offset: float) -> float:
        e = self.residuals(offset)
        fw = self.frame_w
        r2 = np.sum(self.weights * e * e, axis=1) / np.maximum(fw, 1e-12)  # the frame's weighted angle²
        r, k = np.sqrt(r2), np.radians(HUBER_DEG)
        return float(np.sum(fw * np.where(r <= k, r2, 2 * k * r - k * k)) / max(fw.sum(), 1e-12))

    def independent_frames(self, offset: float) -> float:
        """Returns how many independent frames the residuals at ``offset`` are worth (:func:`.sync.independent_samples`:
        a scene's lines mislead neighbouring frames alike)."""
        use = self.frame_w > 0
        return independent_samples(self.residuals(offset)[use] * np.sqrt(self.weights[use]))


def line_offset(cost: OffsetCost, lo: float, hi: float, around: float | None = None) -> tuple[float, float]:
    """Returns (offset, sigma) minimising ``cost`` within ``[lo, hi]``: a coarse grid over all of it (or a fine
    one within :data:`FINE_HALF_S` of ``around``), then a bounded scalar search; sigma from the curvature and
    the residuals' independent frames."""
    if around is None:
        grid = np.arange(lo, hi + 1e-9, COARSE_STEP_S)
    else:
        grid = np.arange(max(lo, around - FINE_HALF_S), min(hi, around + FINE_HALF_S) + 1e-9, FINE_STEP_S)
    if not len(grid):
        grid = np.array([min(max(around if around is not None else lo, lo), hi)])
    values = np.array([cost(o) for o in grid])
    k = int(np.argmin(values))
    step = COARSE_STEP_S if around is None else FINE_STEP_S
    a, b = max(lo, grid[k] - step), min(hi, grid[k] + step)
    o = float(minimize_scalar(cost, bounds=(a, b), method="bounded", options={"xatol": 1e-5}).x) if b > a else a
    h = 1e-3
    if o - h < lo or o + h > hi:  # the best offset at the end of the log's cover: no minimum there
        return o, float("inf")
    c = cost(o)
    curv = (cost(o + h) - 2 * c + cost(o - h)) / (h * h)
    n = max(cost.independent_frames(o), 1.0)
    sigma = float(np.sqrt(2 * c / (n * curv))) if curv > 0 else float("inf")
    return o, sigma


def retime_by_lines(capture: Capture, sensors: RawSensors, offset_s: float, camera_from_device: np.ndarray,
                    lo: float, hi: float, config: Config | None = None, iterations: int = ITERATIONS,
                    attitude: Attitude | None = None) -> tuple[LineTiming, Attitude]:
    """Returns the time offset the lines' rotations give and the attitude at it, starting from ``offset_s``.

    ``capture``: the imported capture (its ``imu.csv`` from ``offset_s``; a missing focal length is estimated
    as ``panosfm run`` does); ``lo, hi``: the offsets at which the log covers the video; ``attitude``: the
    attitude at ``offset_s`` where already smoothed. Raises
    :class:`~panosfm_graph.errors.InputError` (as the preprocessing does) on a scene with too few lines.
    """
    from ..capture.camera import with_focal
    from ..lines import detect_segments, refine_manhattan_and_rotations
    from ..lines.focal import estimate_focal
    from ..lines.rotations import refine_rotations

    t0 = time.perf_counter()
    config = config or Config()
    # held to the attitude's relative rotations only: its tilt and heading carry the old offset's error whole
    rotation = dataclasses.replace(config.rotation, gravity_sigma_deg=0.0, heading_weight=0.0)
    # no point tracks: a bare room's vertical edges alone raise instead of handing back the attitude's rotations
    config = dataclasses.replace(config, rotation=rotation, points=dataclasses.replace(config.points, enabled=False))
    segments = detect_segments(capture, config)
    if not capture.focal_given:
        est = estimate_focal(segments, capture.R_wc_imu, capture.camera, config.focal, config.manhattan)
        capture = dataclasses.replace(capture, camera=with_focal(capture.camera, est.focal_px))
    t = np.asarray(capture.timestamps, dtype=np.float64)
    C = np.asarray(camera_from_device, dtype=np.float64)
    att = attitude if attitude is not None else smooth_attitude(sensors, t + offset_s, C)
    pre = refine_manhattan_and_rotations(segments, dataclasses.replace(capture, R_wc_imu=att.R_wc), config)
    R = pre.R_wc
    weights = axis_weights(segments, pre.labels, capture.n_frames)
    frames = int(np.sum(weights[:, 2] > 0))
    if frames < MIN_FRAMES:
        raise InputError(f"only {frames} frames show Manhattan lines (at least {MIN_FRAMES})")
    offsets: list[float] = []
    o, sigma = offset_s, float("inf")
    for it in range(max(1, iterations)):
        if it:  # the frames held to the attitude re-timed by the last iteration
            R = refine_rotations(segments, pre.labels, capture.camera.K, att.R_wc, pre.manhattan, rotation, R_wc_init=R)
        Q = gyro_orientation(sensors.t_gyro, sensors.gyro - att.gyro_bias)
        o, sigma = line_offset(OffsetCost(R, weights, Q, C, t), lo, hi, around=o if it else None)
        offsets.append(o)
        att = smooth_attitude(sensors, t + o, C)
        log.info("line timing iteration %d: offset %+.4f s +- %.1f ms", it + 1, o, 1e3 * sigma)
    return LineTiming(o, sigma, tuple(offsets), frames, time.perf_counter() - t0), att
