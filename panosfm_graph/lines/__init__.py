"""Preprocessing (paper §3.1, supplement §1-3): line segments, Manhattan frame, rotations, tracks.

``preprocess(capture, config)`` detects segments, then alternates Manhattan
frame extraction, Manhattan labelling and rotation refinement
``config.manhattan.iterations`` times; ``track_lines(capture, pre, config)``
chains the Manhattan segments into tracks.
"""
from __future__ import annotations

import logging

import numpy as np

from ..config import Config
from ..data import UNLABELLED, Capture, ManhattanFrame, Preprocessed, Segments, Tracks
from ..errors import OnlyVerticalEdgesError
from .detect import detect_segments
from .manhattan import check_enough_manhattan, gravity_aligned, horizontal_counts, label_segments, manhattan_frame, \
    refined_manhattan_frame
from .rotations import heading_drift, refine_rotations, rotate_heading
from .tracking import loop_pairs, track_lines as _track_lines

log = logging.getLogger("panosfm.lines")

__all__ = [
    "detect_segments", "manhattan_frame", "label_segments", "refine_rotations",
    "refine_manhattan_and_rotations", "refine_warm", "preprocess", "track_lines", "vertical_only",
]


def refine_manhattan_and_rotations(segments: Segments, capture: Capture, config: Config) -> Preprocessed:
    """Returns the Manhattan frame, segment labels and refined rotations (paper §3.1, supplement §1-2).

    Frames that show vertical edges only (a bare room) give :func:`vertical_only` where point tracks may place
    the frames (``points.enabled`` and ``graph.motion_model``); otherwise :class:`OnlyVerticalEdgesError`.
    """
    try:
        return _refine_manhattan_and_rotations(segments, capture, config)
    except OnlyVerticalEdgesError as e:
        if not (config.points.enabled and config.graph.motion_model):
            raise
        log.warning("%s; the IMU's rotations are kept and the point tracks place the frames", e)
        return vertical_only(segments, capture, config)


def vertical_only(segments: Segments, capture: Capture, config: Config) -> Preprocessed:
    """Returns the preprocessing of frames that show vertical edges only (our addition; issue #40).

    No horizontal Manhattan direction is seen, so the Manhattan frame is the IMU's world axes (the vertical is
    gravity, the heading the IMU's), the rotations are the IMU's (the vertical edges alone leave them as they are,
    measured on a bare room: 0.742 deg median before and after) and only the vertical segments are labelled. No
    frame is fixed by lines; :func:`panosfm_graph.graph.place_by_motion_model` places them by point tracks.
    """
    R_imu = np.asarray(capture.R_wc_imu, dtype=np.float64)
    mf = ManhattanFrame(directions=np.eye(3))
    labels = label_segments(segments, capture.camera.K, R_imu, mf, config.manhattan)
    labels = np.where(labels == 2, 2, UNLABELLED).astype(np.int8)
    return Preprocessed(segments=segments, manhattan=mf, labels=labels, R_wc=np.ascontiguousarray(R_imu),
                        R_wc_imu=R_imu)


def _refine_manhattan_and_rotations(segments: Segments, capture: Capture, config: Config) -> Preprocessed:
    """Returns the Manhattan frame, segment labels and refined rotations (paper §3.1, supplement §1-2).

    Starting from the IMU rotations, repeats ``config.manhattan.iterations``
    times: Manhattan frame extraction (axes kept consistent with the
    previous round), Manhattan labelling (85 degree rule), rotation
    refinement (Eq. 1, warm-started, against the raw IMU's relative rotations:
    the heading-drift fit must not see its own previous estimate); the last
    refinement uses the drift-corrected IMU; the final labels use the final
    rotations. Raises :class:`TooFewLinesError` when the scene has too few
    Manhattan segments.
    """
    if config.rotation.drift_weights not in ("frames", "length"):
        raise ValueError(f"rotation.drift_weights must be 'frames' or 'length', not {config.rotation.drift_weights!r}")
    K = capture.camera.K
    R_imu = np.asarray(capture.R_wc_imu, dtype=np.float64)
    R = R_imu.copy()
    R_prior = R_imu  # the IMU with its estimated heading drift removed (config.rotation.drift_degree)
    mf = None
    for it in range(max(1, config.manhattan.iterations)):
        mf = manhattan_frame(segments, K, R, config.manhattan, reference=mf)
        labels = label_segments(segments, K, R, mf, config.manhattan)
        check_enough_manhattan(labels, config.manhattan)
        # with drift_feedback off the loop's refinements keep the raw IMU's relative rotations, so the drift fit
        # never sees its own previous estimate in frames whose lines do not fix their heading
        R = refine_rotations(segments, labels, K, R_prior if config.rotation.drift_feedback else R_imu, mf,
                             config.rotation, R_wc_init=R)
        if config.rotation.drift_degree >= 0:
            R_prior = _drift_corrected(segments, labels, R, capture, mf, config)
        log.info("preprocess iteration %d: %d Manhattan segments of %d", it + 1, int(np.sum(labels >= 0)), segments.n)
    if config.rotation.drift_degree >= 0:  # the last rotations against the last drift estimate
        R = refine_rotations(segments, labels, K, R_prior, mf, config.rotation, R_wc_init=R,
                             prior_weight=config.rotation.heading_weight)
    mf = manhattan_frame(segments, K, R, config.manhattan, reference=mf)
    labels = label_segments(segments, K, R, mf, config.manhattan)
    check_enough_manhattan(labels, config.manhattan)
    # contiguous as the stage cache returns it: a strided R_wc gives other last bits downstream (BLAS), so a
    # resumed run would not repeat the uninterrupted one exactly
    return Preprocessed(segments=segments, manhattan=mf, labels=labels, R_wc=np.ascontiguousarray(R), R_wc_imu=R_imu)


def _drift_corrected(segments: Segments, labels: np.ndarray, R: np.ndarray, capture: Capture, mf: ManhattanFrame,
                     config: Config) -> np.ndarray:
    """Returns the IMU rotations with the heading drift fitted to the corrections ``R`` made removed."""
    R_imu = np.asarray(capture.R_wc_imu, dtype=np.float64)
    weight = horizontal_counts(segments, labels, capture.n_frames, segments.lengths)
    count = horizontal_counts(segments, labels, capture.n_frames)
    weight[count < config.rotation.drift_min_horizontal] = 0.0  # too few to fix the frame's heading
    if config.rotation.drift_weights == "frames":  # each frame with horizontal lines counts once
        weight = (weight > 0).astype(np.float64)
    ends = loop_pairs(R, config.rotation.drift_loop_deg)  # a turn apart, looking the same way
    drift = heading_drift(R, R_imu, capture.timestamps, weight, config.rotation.drift_degree, mf.directions[2],
                          ends, config.rotation.drift_loop_weight)
    log.info("IMU heading drift over the capture: %.2f deg", np.degrees(drift[-1] - drift[0]))
    return rotate_heading(R_imu, drift, mf.directions[2])


def refine_warm(segments: Segments, capture: Capture, config: Config, previous: Preprocessed) -> Preprocessed:
    """Returns the preprocessing of a capture that grew by some frames (streaming; paper §3.1).

    Warm-started from ``previous`` (its first frames are the capture's first): its refined
    rotations start the old frames, the new ones start from the last refined one carried by the
    IMU's relative rotations; the Manhattan frame is extracted again from all frames, its axes
    matched to ``previous``'s (kept from the first batch, the later lines came out 6.6 times further
    from the true surfaces: docs/decisions.md#streaming-preprocessing). One round of labelling,
    refinement, drift fit and refinement against the drift-corrected IMU replaces
    :func:`refine_manhattan_and_rotations`'s iterations.
    """
    K = capture.camera.K
    R_imu = np.asarray(capture.R_wc_imu, dtype=np.float64)
    old = len(previous.R_wc)
    R = R_imu.copy()
    R[:old] = previous.R_wc
    if old:  # R_new = R_last R_imu,last^T R_imu,new: the IMU's motion since the last refined frame
        R[old:] = previous.R_wc[old - 1] @ R_imu[old - 1].T @ R_imu[old:]
    mf = _warm_manhattan_frame(segments, K, R, config, previous.manhattan)
    labels = label_segments(segments, K, R, mf, config.manhattan)
    check_enough_manhattan(labels, config.manhattan)
    # against the raw IMU's relative rotations first: the drift fit must see the new frames' own corrections
    R = refine_rotations(segments, labels, K, R_imu, mf, config.rotation, R_wc_init=R)
    if config.rotation.drift_degree >= 0:
        R_prior = _drift_corrected(segments, labels, R, capture, mf, config)
        R = refine_rotations(segments, labels, K, R_prior, mf, config.rotation, R_wc_init=R,
                             prior_weight=config.rotation.heading_weight)
    labels = label_segments(segments, K, R, mf, config.manhattan)
    check_enough_manhattan(labels, config.manhattan)
    return Preprocessed(segments=segments, manhattan=mf, labels=labels, R_wc=np.ascontiguousarray(R), R_wc_imu=R_imu)


def _warm_manhattan_frame(segments: Segments, K: np.ndarray, R: np.ndarray, config: Config,
                          previous: ManhattanFrame) -> ManhattanFrame:
    """Returns the Manhattan frame of a warm start (paper §3.1), its vertical taken from gravity where the lines put
    it more than ``manhattan.warm_vertical_max_deg`` off. Refined against relative rotations only, the warm
    rotations hold no absolute tilt: a vertical the lines pull off gravity (slanted lines) tilts the rotations,
    which tilt the next batch's vertical further (measured, bedroom seed 1: 0.09, 0.20, 0.32, 0.48, 0.80 deg over
    five batches, the rotations 1.36 deg off at 300 frames against 0.27 from the IMU; docs/decisions.md#warm-vertical)."""
    mf = refined_manhattan_frame(segments, K, R, previous, config.manhattan)
    g = np.array([0.0, 0.0, 1.0])
    tilt = float(np.degrees(np.arccos(np.clip(mf.directions[2] @ g, -1.0, 1.0))))
    limit = config.manhattan.warm_vertical_max_deg
    if limit > 0 and tilt > limit:
        log.info("warm start: the Manhattan vertical %.2f deg off gravity (at most %.2f); taken from gravity", tilt, limit)
        mf = ManhattanFrame(directions=gravity_aligned(mf.directions, g))
    return mf


def preprocess(capture: Capture, config: Config, segments: Segments | None = None) -> Preprocessed:
    """Returns the preprocessed capture: segments, Manhattan frame, labels, refined rotations (paper §3.1).

    ``segments`` skips detection when given (e.g. from a cache).
    """
    if segments is None:
        segments = detect_segments(capture, config.detect)
    return refine_manhattan_and_rotations(segments, capture, config)


def track_lines(capture: Capture, pre: Preprocessed, config: Config) -> Tracks:
    """Returns the line tracks of a preprocessed capture (supplement §3)."""
    cam = capture.camera
    return _track_lines(
        pre.segments, pre.labels, cam.K, pre.R_wc, config.tracking, image_size=(cam.width, cam.height),
        directions=pre.manhattan.directions,
    )
