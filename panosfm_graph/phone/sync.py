"""The video-to-sensor time offset and the camera's axes in the phone's, from the images (issue #41 item 4).

The gyroscope's turn over each frame interval, ``log(Q(t_k + o)^-1 Q(t_k+1 + o))``
with ``Q`` the integrated gyroscope attitude, must equal the camera's turn seen
in the images (:mod:`.video_rotation`) once rotated into the camera's axes
and scaled (parallax and a provisional focal length stretch the image turn).
:func:`estimate_sync` scores every offset ``o`` on a grid by the correlation
of the two sets of turn vectors (scale free), the gyroscope's turned by each
of the 24 axis permutations (a phone's camera is mounted along the phone's
axes), and keeps the best permutation and offset where the best free
rotation (Kabsch) at that offset lies within :data:`SNAP_DEG` of it, else
the free rotation's best offset (a free rotation absorbs part of a timing
error: 16 degrees off the axes at a wrong offset on a smooth spin, 332 ms
off on a fast one in a bare room), and refines ``o`` below a millisecond on
the turns' components off the spin axis (the wobble in pitch and roll
carries the timing; the turn about the spin axis is nearly constant and
biased by parallax).

A hand trembles (2-12 Hz); parallax, the stand point's bob and the slow
wobble do not. :func:`tremor_band` times the video once more on the turns
less their moving mean over :data:`TREMOR_HIGHPASS_S`: where the
gyroscope's turns explain most of the images' there
(:data:`MIN_TREMOR_SHARE`), that offset is kept, with a sigma from its
residuals that the smooth errors no longer inflate
(docs/decisions.md#tremor-band).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation, Slerp

from ..errors import InputError
from .logs import RawSensors

SNAP_DEG = 30.0  # the 24 axis permutations lie 90 deg apart: within 30 deg of one is unambiguous
GRID_STEP_S = 0.005
TRIM = 0.9  # the fine fit keeps this share of the intervals with the smallest residuals
TREMOR_HIGHPASS_S = 0.3  # the tremor band: each turn less its mean over this long (passes ~3 Hz and up)
TREMOR_SEARCH_S = 0.1  # the tremor band's offset is searched this far around the whole band's
TREMOR_STEP_S = 0.002
MIN_TREMOR_SHARE = 0.8  # the gyroscope's turns explain this share of the images' tremor band: it times the video


@dataclass(frozen=True)
class Sync:
    """How the video's clock and the camera's axes relate to the sensors': ``t_sensor = t_video + offset_s``,
    ``omega_camera = camera_from_device @ omega_device``."""

    offset_s: float
    offset_sigma_s: float  # whole band: curvature and residual over independent intervals; tremor band: score_sigma
    camera_from_device: np.ndarray  # (3, 3)
    axes_snapped: bool  # camera_from_device is an axis permutation (else the fitted rotation)
    scale: float  # image turn / gyroscope turn (parallax, focal length error)
    residual_deg: float  # RMS of the off-axis turn residual per interval after the fit
    correlation: float  # the grid score at the chosen offset (1 = the turns agree up to a rotation and scale)
    intervals: int
    band: str = "full"  # which turns gave the offset: "tremor" (the tremor band) or "full" (every frequency)
    tremor_share: float = 0.0  # the share of the images' tremor-band turns the gyroscope's explain (0..1)


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


def _grid_correlations(Q: Slerp, ta: np.ndarray, tb: np.ndarray, img: np.ndarray, grid: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Returns, for each offset of ``grid``, the correlation ``H = sum img g^T`` (n, 3, 3) of the image turns
    ``img`` (M, 3) with the gyroscope's over the same intervals and ``sum |g|^2`` (n,)."""
    H, gg = np.empty((len(grid), 3, 3)), np.empty(len(grid))
    for c0 in range(0, len(grid), 256):  # bounded memory
        g = gyro_turns(Q, ta[None] + grid[c0:c0 + 256, None], tb[None] + grid[c0:c0 + 256, None])  # (n, M, 3)
        H[c0:c0 + 256] = np.einsum("mi,nmj->nij", img, g)
        gg[c0:c0 + 256] = np.sum(g ** 2, axis=(1, 2))
    return H, gg


def _scores(H: np.ndarray, gg: np.ndarray, img: np.ndarray, R: np.ndarray | None) -> np.ndarray:
    """Returns each offset's score from :func:`_grid_correlations`: the squared correlation of the image turns with
    the gyroscope's turned by the best rotation (Kabsch; ``R`` None) or by ``R``, signed."""
    R = kabsch(H) if R is None else np.broadcast_to(R, H.shape)
    tr = np.einsum("nij,nij->n", R, H)
    return np.sign(tr) * tr ** 2 / (np.sum(img ** 2) * gg)


def _trimmed(r: np.ndarray) -> tuple[float, np.ndarray]:
    """Returns (the mean squared norm of the rows of ``r`` (M, k) kept, the kept rows' mask): the :data:`TRIM` share
    with the smallest norms."""
    e = np.sum(r * r, axis=1)
    keep = e <= np.quantile(e, TRIM)
    return float(np.mean(e[keep])), keep


def high_pass(x: np.ndarray, idx: np.ndarray, n: int) -> np.ndarray:
    """Returns ``x`` (M, k), samples at the sorted integer positions ``idx``, less its mean over the ``n``
    positions around each (missing positions left out of the mean)."""
    full = np.zeros((int(idx[-1]) + 1, x.shape[1]))
    have = np.zeros(len(full))
    full[idx], have[idx] = x, 1.0
    count = uniform_filter1d(have, n, mode="constant")
    return x - (uniform_filter1d(full, n, axis=0, mode="constant") / np.maximum(count, 1e-12)[:, None])[idx]


def score_sigma(r: np.ndarray, J: np.ndarray) -> float:
    """Returns the sigma of an offset fitted by least squares to residuals ``r`` (N, k) in time order, with
    ``J = dr/d offset``: ``sum_l sum_n J_n^T C(l) J_n+l / (sum |J|^2)^2``, ``C(l)`` the residuals' autocovariance
    up to their first lag without correlation. Residuals that are smooth where ``J`` is not (parallax against
    tremor) do not inflate it, as they do :func:`independent_samples`."""
    r = r - r.mean(axis=0)
    N, jj = len(r), float(np.sum(J * J))
    if N < 2 or jj <= 0:
        return float("inf")
    total = float(np.einsum("ni,ij,nj->", J, r.T @ r / N, J))
    for lag in range(1, N // 2):
        C = r[:-lag].T @ r[lag:] / N
        if np.trace(C) <= 0:
            break
        total += 2.0 * float(np.einsum("ni,ij,nj->", J[:-lag], C, J[lag:]))
    return float(np.sqrt(max(total, 0.0)) / jj)


def tremor_band(Q: Slerp, ta: np.ndarray, tb: np.ndarray, img: np.ndarray, idx: np.ndarray,
                camera_from_device: np.ndarray, around: float, lo: float, hi: float) -> tuple[float, float, float]:
    """Returns (offset, sigma, share) timing the image turns ``img`` (M, 3) of the intervals ``ta..tb`` (positions
    ``idx`` among the video's intervals) by their tremor band (:func:`high_pass` over :data:`TREMOR_HIGHPASS_S`),
    within :data:`TREMOR_SEARCH_S` of ``around`` and ``[lo, hi]``; ``share``: how much of the images'
    tremor-band turns the gyroscope's explain at that offset (1 - residual / total, the kept intervals)."""
    rate = 1.0 / max(float(np.median(tb - ta)), 1e-6)
    n = max(3, int(round(TREMOR_HIGHPASS_S * rate)) | 1)
    band = high_pass(img, idx, n)
    R = np.asarray(camera_from_device, dtype=np.float64)

    def resid(o: float) -> np.ndarray:
        g = high_pass(gyro_turns(Q, ta + o, tb + o) @ R.T, idx, n)
        return band - float(np.sum(band * g) / max(np.sum(g * g), 1e-30)) * g

    def cost(o: float) -> float:
        return _trimmed(resid(o))[0]

    grid = np.arange(max(lo, around - TREMOR_SEARCH_S), min(hi, around + TREMOR_SEARCH_S) + 1e-9, TREMOR_STEP_S)
    if len(grid) < 3:
        return around, float("inf"), 0.0
    k = int(np.clip(np.argmin([cost(o) for o in grid]), 1, len(grid) - 2))
    o = float(minimize_scalar(cost, bounds=(grid[k - 1], grid[k + 1]), method="bounded",
                              options={"xatol": 1e-6}).x)
    r = resid(o)
    keep = _trimmed(r)[1]
    share = 1.0 - float(np.sum(r[keep] ** 2) / max(np.sum(band[keep] ** 2), 1e-30))
    h = 1e-3
    if o - h < lo or o + h > hi:
        return o, float("inf"), share
    J = (resid(o + h) - resid(o - h)) / (2 * h)
    return o, score_sigma(r[keep], J[keep]), share


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
    H, gg = _grid_correlations(Q, ta, tb, img, grid)
    if camera_from_device is None:
        # every axis permutation's best offset: a free rotation absorbs part of a timing error (16 deg off the
        # axes at a wrong offset on a smooth spin), so the phone's axes are tried first, kept where the free fit
        # at their best offset lies within SNAP_DEG of them
        perm = np.stack([_scores(H, gg, img, P) for P in AXIS_ROTATIONS])  # (24, n)
        p, k = np.unravel_index(int(np.argmax(perm)), perm.shape)
        snapped = bool(Rotation.from_matrix(AXIS_ROTATIONS[p].T @ kabsch(H[k])).magnitude() < np.radians(SNAP_DEG))
        if snapped:
            R, score = AXIS_ROTATIONS[p], perm[p]
        else:
            score = _scores(H, gg, img, None)
            k = int(np.argmax(score))
            R = kabsch(H[k])
    else:
        R, snapped = np.asarray(camera_from_device, dtype=np.float64), True
        score = _scores(H, gg, img, R)
        k = int(np.argmax(score))
    o_c = float(grid[k])
    axis = np.mean(img, axis=0)
    axis /= max(np.linalg.norm(axis), 1e-12)
    P = np.eye(3) - np.outer(axis, axis)

    def cost(o: float) -> tuple[float, float, np.ndarray, np.ndarray]:
        """Returns (the kept intervals' mean squared off-axis residual, the scale, the residuals (M, 3), the kept
        intervals' mask)."""
        gc = gyro_turns(Q, ta + o, tb + o) @ R.T
        s = float(np.sum(img * gc) / max(np.sum(gc * gc), 1e-30))
        r = (img - s * gc) @ P
        c, keep = _trimmed(r)
        return c, s, r, keep

    lo_f, hi_f = max(o_c - 2 * GRID_STEP_S, lo), min(o_c + 2 * GRID_STEP_S, hi)
    res = minimize_scalar(lambda o: cost(o)[0], bounds=(lo_f, hi_f), method="bounded", options={"xatol": 1e-5})
    o_f = float(res.x)
    c, s, r, keep = cost(o_f)
    h = 1e-3
    # the best offset at the end of the log's cover is no minimum: no curvature there
    curv = (cost(o_f + h)[0] - 2 * c + cost(o_f - h)[0]) / (h * h) if lo <= o_f - h and o_f + h <= hi else 0.0
    n = independent_samples(r[keep])
    sigma = float(np.sqrt(2 * c / (n * curv))) if curv > 0 else float("inf")
    o_t, sigma_t, share = tremor_band(Q, ta, tb, img, np.flatnonzero(ok), R, o_f, lo, hi)
    band = "tremor" if share >= MIN_TREMOR_SHARE and np.isfinite(sigma_t) else "full"
    if band == "tremor":
        o_f, sigma = o_t, sigma_t
    return Sync(offset_s=o_f, offset_sigma_s=sigma, camera_from_device=R, axes_snapped=snapped, scale=s,
                residual_deg=float(np.degrees(np.sqrt(c))), correlation=float(score[k]), intervals=int(ok.sum()),
                band=band, tremor_share=share)
