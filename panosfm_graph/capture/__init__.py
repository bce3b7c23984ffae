"""Read and validate a capture directory (``capture-format.md``): camera, frames, timestamps, IMU, ground truth.

:func:`load_capture` returns a :class:`~panosfm_graph.data.Capture` whose
frames are read lazily (never all held at once), downscaled by
``CaptureConfig.scale`` and, for the OPENCV model, undistorted: the pipeline
works in undistorted pinhole coordinates, so ``Capture.camera`` is then the
PINHOLE camera of the undistorted images (same K). The IMU attitude is
slerped to every frame's timestamp (paper supplement §2 uses it as the
initial rotation and as a relative-rotation prior).

Every problem with the input raises :class:`~panosfm_graph.errors.InputError`
with one line naming the file. :func:`inspect_capture` describes a capture
(also one whose IMU does not cover its frames) and :func:`format_inspection`
prints that as a table. :func:`capture_warnings` checks a loaded capture as a
spin to reconstruct (IMU turn span, dropped frames); the pipeline calls it.

One module per part of the capture directory:

* :mod:`.load`: :func:`load_capture` (start reading here) and :func:`capture_warnings`;
* :mod:`.camera`: ``camera.json``, the working camera, (un)distortion, raw -> working image;
* :mod:`.frames`: the frames (``frames/`` or ``video.<ext>``) and their timestamps (``frames.csv``);
* :mod:`.images`: ``frames/`` PNG / JPEG files; :mod:`.video`: ``video.<ext>``;
* :mod:`.imu`: ``imu.csv``, its coverage and rate, slerped to the frames, turn span;
* :mod:`.ground_truth`: ``ground_truth/``;
* :mod:`.inspection`: :func:`inspect_capture`, :func:`format_inspection`;
* :mod:`.validate`: the one-line errors the readers share (CSV files, numbers, config).
"""
from __future__ import annotations

from .camera import FOCAL_RANGE_FRAC, N_PARAMS, distort_points, read_camera, undistort_points, working_camera
from .frames import DEFAULT_FPS, FRAMES_CSV_HEADER
from .ground_truth import AXIS_LABELS
from .images import IMAGE_EXTS, JPEG_TAIL_BYTES, PNG_END
from .imu import (IMU_HEADER, QUAT_NORM_TOL, TIME_TOL_S, check_imu_rate, imu_at_frames, imu_coverage, read_imu,
                  turn_span_deg)
from .inspection import format_inspection, inspect_capture
from .load import capture_warnings, load_capture
from .video import SEEK_AHEAD_FRAMES

__all__ = [
    "load_capture", "capture_warnings", "inspect_capture", "format_inspection",
    "read_camera", "working_camera", "undistort_points", "distort_points", "read_imu", "imu_coverage",
    "imu_at_frames", "check_imu_rate", "turn_span_deg",
    "N_PARAMS", "FOCAL_RANGE_FRAC", "IMAGE_EXTS", "PNG_END", "JPEG_TAIL_BYTES", "SEEK_AHEAD_FRAMES",
    "FRAMES_CSV_HEADER", "DEFAULT_FPS", "IMU_HEADER", "QUAT_NORM_TOL", "TIME_TOL_S", "AXIS_LABELS",
]
