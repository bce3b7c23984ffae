"""``imu.csv``: the camera's attitude (world_from_camera), read, checked and slerped to the frames.

Paper supplement §2 uses it as each frame's initial rotation and as a
relative-rotation prior (``capture-format.md``: any rate, one row per frame
or a 100 Hz stream; frames outside its time span are rejected).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry import quat_wxyz_to_matrix, slerp_rotations
from .validate import _numbers, _read_csv

IMU_HEADER = ("timestamp_s", "qw", "qx", "qy", "qz")
QUAT_NORM_TOL = 1e-3  # |‖q‖ - 1| above this is rejected
TIME_TOL_S = 1e-6  # frames this close outside the IMU span still count as covered


def read_imu(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Returns (timestamps (N,) s, world_from_camera rotations (N, 3, 3)) of ``imu.csv``, validated."""
    path = Path(path)
    if not path.is_file():
        raise InputError("missing (every capture needs the IMU attitude, timestamp_s,qw,qx,qy,qz)", path)
    rows = _read_csv(path, IMU_HEADER)
    data = _numbers(path, rows, slice(0, 5))
    if len(data) < 2:
        raise InputError(f"needs at least 2 rows to interpolate, got {len(data)}", path)
    bad = ~np.all(np.isfinite(data), axis=1)
    if bad.any():
        raise InputError(f"line {int(np.argmax(bad)) + 2}: NaN or infinite value", path)
    t, q = data[:, 0], data[:, 1:]
    dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.argmax(dt <= 0))
        raise InputError(f"timestamps must be strictly increasing (line {k + 3}: {t[k + 1]} after {t[k]})", path)
    norm = np.linalg.norm(q, axis=1)
    bad = np.abs(norm - 1.0) > QUAT_NORM_TOL
    if bad.any():
        k = int(np.argmax(bad))
        raise InputError(f"line {k + 2}: quaternion norm {norm[k]:.6f} is not 1 (tolerance {QUAT_NORM_TOL})", path)
    return t, quat_wxyz_to_matrix(q / norm[:, None])


def imu_coverage(t_imu: np.ndarray, t_frames: np.ndarray) -> np.ndarray:
    """Returns a (F,) bool mask: frame timestamps inside the IMU span (within 1 µs)."""
    return (t_frames >= t_imu[0] - TIME_TOL_S) & (t_frames <= t_imu[-1] + TIME_TOL_S)


def imu_at_frames(imu_path: Path, t_imu: np.ndarray, R_imu: np.ndarray, t: np.ndarray, t_from: str) -> np.ndarray:
    """Returns (F, 3, 3) the IMU attitude slerped to frame times ``t``; InputError if a frame lies outside its span.

    ``t_from`` says where the frame times came from (for the message).
    """
    inside = imu_coverage(t_imu, t)
    if not inside.all():
        out = t[~inside]
        raise InputError(f"{int((~inside).sum())} of {len(t)} frames (times {out.min():.3f}..{out.max():.3f} s, "
                         f"from {t_from}) lie outside the IMU time span {t_imu[0]:.3f}..{t_imu[-1]:.3f} s",
                         imu_path)
    return slerp_rotations(t_imu, R_imu, np.clip(t, t_imu[0], t_imu[-1]))


def check_imu_rate(imu_path: Path, t_imu: np.ndarray, frame_rate_hz: float, min_rate_hz: float) -> float:
    """Returns the IMU's mean rate (Hz); InputError when it is below ``min_rate_hz`` and half the frame rate.

    One IMU row per frame is always accepted (capture-format.md allows it);
    a stream much sparser than the frames cannot give each frame its own
    attitude (paper supplement §2 uses it as every frame's initial rotation).
    """
    span = float(t_imu[-1] - t_imu[0])
    rate = (len(t_imu) - 1) / span if span > 0 else math.inf
    if rate < min_rate_hz and rate < 0.5 * frame_rate_hz:
        raise InputError(f"IMU rate {rate:.3g} Hz is far below the frame rate {frame_rate_hz:.3g} Hz "
                         f"(need >= {min_rate_hz:g} Hz or one row per frame)", imu_path)
    return rate


def turn_span_deg(R_wc: np.ndarray) -> float:
    """Returns the yaw span (degrees) swept by the optical axis: max - min of its unwrapped heading.

    The heading is the azimuth of the optical axis (``R_wc[:, :, 2]``)
    projected on the horizontal plane (world +z is up, capture-format.md);
    frames looking within ~12° of straight up or down carry no heading and
    are skipped.
    """
    z = np.asarray(R_wc, dtype=np.float64)[:, :, 2]
    ok = np.hypot(z[:, 0], z[:, 1]) > 0.2
    if ok.sum() < 2:
        return 0.0
    heading = np.unwrap(np.arctan2(z[ok, 1], z[ok, 0]))
    return float(np.degrees(np.ptp(heading)))
