"""The video-to-sensor time offset and the camera's axes in the phone's, from the images (issue #41 item 4).

The gyroscope's turn over each frame interval, ``log(Q(t_k + o)^-1 Q(t_k+1 + o))``
with ``Q`` the integrated gyroscope attitude, must equal the camera's turn seen
in the images (:mod:`.video_rotation`) once rotated into the camera's axes
and scaled (parallax and a provisional focal length stretch the image turn).
:func:`estimate_sync` scores every offset ``o`` on a grid by the best
rotation between the two sets of turns (Kabsch, scale free: a correlation of
the vectors), snaps that rotation to the nearest of the 24 axis permutations
when it lies within :data:`SNAP_DEG` (a phone's camera is mounted along the
phone's axes; the offset is then searched again with the axes fixed: at a
wrong offset a free rotation fits 16 degrees off them on a smooth spin),
and refines ``o`` below a millisecond on the turns' components
off the spin axis (the wobble in pitch and roll carries the timing; the turn
about the spin axis is nearly constant and biased by parallax).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation, Slerp

from ..errors import InputError
from .logs import RawSensors

SNAP_DEG = 30.0  # the 24 axis permutations lie 90 deg apart: within 30 deg of one is unambiguous
GRID_STEP_S = 0.005
TRIM = 0.9  # the fine fit keeps this share of the intervals with the smallest residuals


@dataclass(frozen=True)
class Sync:
    """How the video's clock and the camera's axes relate to the sensors': ``t_sensor = t_video + offset_s``,
    ``omega_camera = camera_from_device @ omega_device``."""

    offset_s: float
    offset_sigma_s: float  # from the fit's curvature and residual, over the residuals' independent intervals
    camera_from_device: np.ndarray  # (3, 3)
    axes_snapped: bool  # camera_from_device is an axis permutation (else the fitted rotation)
    scale: float  # image turn / gyroscope turn (parallax, focal length error)
    residual_deg: float  # RMS of the off-axis turn residual per interval after the fit
    correlation: float  # the grid score at the chosen offset (1 = the turns agree up to a rotation and scale)
    intervals: int


def gyro_orientation(t: np.ndarray, omega: np.ndarray) -> Slerp:
    """Returns the gyroscope's integrated attitude (device frame, identity at ``t[0]``) as a slerp over ``t``;
    trapezoidal rate per sample interval."""
    w = 0.5 * (omega[1:] + omega[:-1]) * np.diff(t)[:, None]
    steps = Rotation.from_rotvec(w).as_quat()
    q = np.empty((len(t), 4))
    q[0] = (0, 0, 0, 1)
    acc = Rotation.identity()
    for k, s in enumerate(steps):  # the cumulative product is sequential; Rotation ops are cheap
        acc = acc * Rotation.from_quat(s)
        q[k + 1] = acc.as_quat()
    return Slerp(t, Rotation.from_quat(q))


def gyro_turns(Q: Slerp, t_a: np.ndarray, t_b: np.ndarray) -> np.ndarray:
    """Returns (..., 3) rotation vectors of ``Q(t_a)^-1 Q(t_b)`` (device frame)."""
    shape = np.shape(t_a)
    a, b = Q(np.ravel(t_a)), Q(np.ravel(t_b))
    return (a.inv() * b).as_rotvec().reshape(*shape, 3)


def _axis_rotations() -> np.ndarray:
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            M = np.zeros((3, 3))
            M[np.arange(3), perm] = signs
            if np.linalg.det(M) > 0:
                out.append(M)
    return np.array(out)


AXIS_ROTATIONS = _axis_rotations()  # (24, 3, 3)


def kabsch(H: np.ndarray) -> np.ndarray:
    """Returns the rotations R (..., 3, 3) maximising trace(R^T H) for correlation matrices H = sum img gyro^T."""
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.zeros_like(H)
    D[..., 0, 0] = D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    return U @ D @ Vt


def covering_offsets(t_frames: np.ndarray, sensors: RawSensors, guess_s: float = 0.0,
                     max_offset_s: float = np.inf) -> tuple[float, float]:
    """Returns (lo, hi): the offsets within ``guess_s +- max_offset_s`` at which the gyroscope log covers every
    frame (lo > hi where none does)."""
    lo, hi = sensors.t_gyro[0] - t_frames[0], sensors.t_gyro[-1] - t_frames[-1]
    return max(lo, guess_s - max_offset_s), min(hi, guess_s + max_offset_s)


def independent_samples(e: np.ndarray) -> float:
    """Returns how many independent samples the residual vectors ``e`` (N, k), in time order, are worth:
    ``N / (1 + 2 sum rho_j)``, their autocorrelation summed up to its first non-positive lag. Systematic errors
    (parallax, a scene's lines) mislead neighbouring frames alike; counting them as independent made the
    offset's sigma 5-10 times too small (docs/decisions.md#time-offset-from-the-lines)."""
    e = np.asarray(e, dtype=np.float64)
    e = e - e.mean(axis=0)
    var = float(np.sum(e * e))
    if len(e) < 2 or var <= 0:
        return float(len(e))
    tau = 1.0
    for lag in range(1, len(e) // 2):
        rho = float(np.sum(e[lag:] * e[:-lag])) / var
        if rho <= 0:
            break
        tau += 2.0 * rho
    return len(e) / tau


def _grid_scores(Q: Slerp, ta: np.ndarray, tb: np.ndarray, img: np.ndarray, grid: np.ndarray,
                 camera_from_device: np.ndarray | None) -> np.ndarray:
    """Returns each offset's score: the squared correlation of the image turns ``img`` (M, 3) with the gyroscope's
    over the same intervals, turned by the best rotation (Kabsch) or by ``camera_from_device``, signed."""
    score = np.empty(len(grid))
    for c0 in range(0, len(grid), 256):  # bounded memory
        o = grid[c0:c0 + 256, None]
        g = gyro_turns(Q, ta[None] + o, tb[None] + o)  # (n, M, 3)
        H = np.einsum("mi,nmj->nij", img, g)
        R = kabsch(H) if camera_from_device is None else np.broadcast_to(camera_from_device, H.shape)
        tr = np.einsum("nij,nij->n", R, H)
        score[c0:c0 + 256] = np.sign(tr) * tr ** 2 / (np.sum(img ** 2) * np.sum(g ** 2, axis=(1, 2)))
    return score


def estimate_sync(t_frames: np.ndarray, theta_img: np.ndarray, sensors: RawSensors, guess_s: float = 0.0,
                  max_offset_s: float = 5.0, camera_from_device: np.ndarray | None = None) -> Sync:
    """Returns the :class:`Sync` of a video (frame times ``t_frames``, image turns ``theta_img`` (F-1, 3)) and
    its sensor log; offsets searched within ``guess_s +- max_offset_s``. ``camera_from_device`` given: only the
    offset is estimated. InputError when the log does not cover the video at any such offset or the images
    give too few turns."""
    t_frames = np.asarray(t_frames, dtype=np.float64)
    ok = np.all(np.isfinite(theta_img), axis=1)
    if ok.sum() < 10:
        raise InputError(f"only {int(ok.sum())} frame pairs with a measurable rotation (too dark, blank or blurred)")
    ta, tb, img = t_frames[:-1][ok], t_frames[1:][ok], theta_img[ok]
    Q = gyro_orientation(sensors.t_gyro, sensors.gyro)
    lo, hi = covering_offsets(t_frames, sensors)
    grid = np.arange(guess_s - max_offset_s, guess_s + max_offset_s + 1e-9, GRID_STEP_S)
    grid = grid[(grid >= lo) & (grid <= hi)]
    if not len(grid):
        raise InputError(f"the gyroscope log ({sensors.t_gyro[0]:.2f}..{sensors.t_gyro[-1]:.2f} s) does not cover the "
                         f"video ({t_frames[-1] - t_frames[0]:.2f} s) at any offset within {guess_s:+.2f} +- "
                         f"{max_offset_s:g} s (give --offset-guess or a longer log)")
    score = _grid_scores(Q, ta, tb, img, grid, camera_from_device)
    k = int(np.argmax(score))
    o_c = float(grid[k])
    if camera_from_device is None:
        R = kabsch(np.einsum("mi,mj->ij", img, gyro_turns(Q, ta + o_c, tb + o_c)))
        angles = Rotation.from_matrix(np.einsum("kji,jl->kil", AXIS_ROTATIONS, R)).magnitude()
        snapped = bool(angles.min() < np.radians(SNAP_DEG))
        if snapped:  # the offset again with the axes fixed: a free rotation absorbs part of a timing error
            R = AXIS_ROTATIONS[int(np.argmin(angles))]
            score = _grid_scores(Q, ta, tb, img, grid, R)
            k = int(np.argmax(score))
            o_c = float(grid[k])
    else:
        R, snapped = np.asarray(camera_from_device, dtype=np.float64), True
    axis = np.mean(img, axis=0)
    axis /= max(np.linalg.norm(axis), 1e-12)
    P = np.eye(3) - np.outer(axis, axis)

    def cost(o: float, keep: float = TRIM) -> tuple[float, float, np.ndarray]:
        """Returns (the kept intervals' mean squared off-axis residual, the scale, the residuals (M, 3))."""
        gc = gyro_turns(Q, ta + o, tb + o) @ R.T
        s = float(np.sum(img * gc) / max(np.sum(gc * gc), 1e-30))
        r = (img - s * gc) @ P
        e = np.sum(r * r, axis=1)
        return float(np.mean(e[e <= np.quantile(e, keep)])), s, r

    lo_f, hi_f = max(o_c - 2 * GRID_STEP_S, lo), min(o_c + 2 * GRID_STEP_S, hi)
    res = minimize_scalar(lambda o: cost(o)[0], bounds=(lo_f, hi_f), method="bounded", options={"xatol": 1e-5})
    o_f = float(res.x)
    c, s, r = cost(o_f)
    h = 1e-3
    # the best offset at the end of the log's cover is no minimum: no curvature there
    curv = (cost(o_f + h)[0] - 2 * c + cost(o_f - h)[0]) / (h * h) if lo <= o_f - h and o_f + h <= hi else 0.0
    e = np.sum(r * r, axis=1)
    n = independent_samples(r[e <= np.quantile(e, TRIM)])
    sigma = float(np.sqrt(2 * c / (n * curv))) if curv > 0 else float("inf")
    return Sync(offset_s=o_f, offset_sigma_s=sigma, camera_from_device=R, axes_snapped=snapped, scale=s,
                residual_deg=float(np.degrees(np.sqrt(c))), correlation=float(score[k]), intervals=int(ok.sum()))
