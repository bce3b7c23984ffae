"""Camera rotation refinement against the Manhattan frame (paper §3.1, supplement §2, Eq. 1) in GTSAM.

Cost (supplement Eq. 1), with R = world_from_camera (the paper's R_i^T):

    sum_i sum_j (v_ij . R_i n_ij)^2  +  lambda sum_(i,j) |R_i^T R_j - R_i0^T R_j0|_F^2

n_ij is the unit camera-frame interpretation-plane normal of segment j,
v_ij its Manhattan direction. For a small rotation error theta,
|A - B|_F^2 = 4 (1 - cos theta) ~= 2 theta^2, and a ``BetweenFactorRot3``
with isotropic sigma adds theta^2 / (2 sigma^2) to GTSAM's error
0.5 * sum r^2 (data sigma 1). Matching the ratio, 1/(2 sigma^2) = lambda,
so sigma_imu = 1 / sqrt(2 lambda) rad (2.24 rad for lambda = 0.1).
"""
from __future__ import annotations

import logging
from functools import partial

import gtsam
import numpy as np
from scipy.spatial import cKDTree

from ..config import Config, RotationConfig
from ..data import ManhattanFrame, Segments
from ..geometry import interpretation_normals, rotation_angle_deg

log = logging.getLogger("panosfm.lines")

GAUGE_SIGMA_RAD = 100.0  # weak prior towards the IMU on every frame: keeps each frame determined


def _rotation_config(config: Config | RotationConfig) -> RotationConfig:
    return config.rotation if isinstance(config, Config) else config


def skew(v: np.ndarray) -> np.ndarray:
    """Returns (..., 3, 3) cross-product matrices [v]x."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def manhattan_residuals(
    R: np.ndarray, normals_cam: np.ndarray, directions: np.ndarray, huber: float = 0.0, weights: np.ndarray | None = None
):
    """Returns (residuals (N,), Jacobian (N, 3) w.r.t. the right tangent of R) of supplement Eq. 1's data term.

    r_j = v_j . (R n_j) (sine of the angle between plane and vanishing
    direction); d r_j / d omega = (n_j x R^T v_j)^T for R exp([omega]x).
    With ``huber > 0`` the residuals are robustified exactly: e = sign(r)
    sqrt(2 rho(r)) with Huber's rho (threshold ``huber``), so that
    0.5 * sum e^2 = sum rho(r).
    """
    u = directions @ R  # rows R^T v_j
    r = np.einsum("ij,ij->i", directions, normals_cam @ R.T)
    J = np.cross(normals_cam, u)
    if weights is not None:
        r = r * weights
        J = J * weights[:, None]
    if huber > 0:
        a = np.abs(r)
        big = a > huber
        e = r.copy()
        scale = np.ones_like(r)
        e[big] = np.sign(r[big]) * np.sqrt(2.0 * huber * a[big] - huber * huber)
        scale[big] = huber / np.abs(e[big])  # de/dr = psi(r) / e = huber * sign(r) / e
        return e, J * scale[:, None]
    return r, J


def _frame_error(normals_cam, directions, huber, weights, this: gtsam.CustomFactor, values: gtsam.Values, H):
    """Error of one frame's stacked Manhattan residuals (supplement Eq. 1, data term)."""
    R = values.atRot3(this.keys()[0]).matrix()
    r, J = manhattan_residuals(R, normals_cam, directions, huber, weights)
    if H is not None:
        H[0] = J
    return r


def manhattan_factor(
    key: int, normals_cam: np.ndarray, directions: np.ndarray, huber: float = 0.0, weights: np.ndarray | None = None
):
    """Returns a ``gtsam.CustomFactor`` on Rot3 ``key`` stacking one frame's Manhattan residuals (sigma 1)."""
    noise = gtsam.noiseModel.Unit.Create(len(normals_cam))
    w = None if weights is None else np.ascontiguousarray(weights, dtype=np.float64)
    fn = partial(_frame_error, np.ascontiguousarray(normals_cam), np.ascontiguousarray(directions), huber, w)
    return gtsam.CustomFactor(noise, [key], fn)


def neighbour_pairs(R_wc: np.ndarray, angle_deg: float, max_neighbours: int) -> np.ndarray:
    """Returns (P, 2) frame pairs i < j whose optical axes are within ``angle_deg`` (supplement §2 'N').

    The IMU is "fairly accurate locally" (supplement §2), so a pair is also
    required to be local in time: the camera turned less than ``angle_deg``
    in total between the two frames (the sum of frame-to-frame rotation
    angles). This excludes the start/end overlap of a >360 degree spin,
    whose IMU relative rotation carries the whole sweep's drift. Consecutive
    frames are always neighbours (a gap-free chain). Each frame
    keeps its ``max_neighbours`` nearest in time; a pair is kept when it is
    among the nearest of either frame.
    """
    F = len(R_wc)
    if F < 2:
        return np.zeros((0, 2), dtype=np.int64)
    axes = R_wc[:, :, 2]
    chord = 2.0 * np.sin(np.radians(angle_deg) / 2.0)
    pairs = cKDTree(axes).query_pairs(chord, output_type="ndarray").reshape(-1, 2)
    step = np.concatenate([[0.0], rotation_angle_deg(R_wc[:-1], R_wc[1:])])
    path = np.cumsum(step)  # degrees turned since the first frame
    pairs = np.sort(pairs, axis=1)
    pairs = pairs[path[pairs[:, 1]] - path[pairs[:, 0]] < angle_deg]
    # consecutive frames are always neighbours: the IMU is most accurate there,
    # and a chain without gaps keeps frames with few (or one-axis) lines determined
    consecutive = np.stack([np.arange(F - 1), np.arange(1, F)], axis=1)
    pairs = np.unique(np.concatenate([pairs.reshape(-1, 2), consecutive]), axis=0)
    if max_neighbours <= 0:
        return consecutive.astype(np.int64)
    gap = pairs[:, 1] - pairs[:, 0]
    keep = np.zeros(len(pairs), dtype=bool)
    for col in (0, 1):  # rank each pair among its frame's pairs by time gap
        order = np.lexsort((gap, pairs[:, col]))
        f = pairs[order, col]
        first = np.searchsorted(f, f, side="left")
        rank = np.arange(len(f)) - first
        keep[order[rank < max_neighbours]] = True
    return pairs[keep].astype(np.int64)


def refine_rotations(
    segments: Segments,
    labels: np.ndarray,
    K: np.ndarray,
    R_wc_imu: np.ndarray,
    mf: ManhattanFrame,
    config: Config | RotationConfig,
    R_wc_init: np.ndarray | None = None,
    prior_weight: float = 0.0,
) -> np.ndarray:
    """Returns (F, 3, 3) refined world_from_camera rotations minimising supplement Eq. 1.

    One ``CustomFactor`` per frame stacks its Manhattan segments' residuals,
    each weighted by its length over the median length (a plane normal's
    noise shrinks with the segment's length; short texture and broken-edge
    segments would otherwise dominate) and robustified with Huber
    (``huber_deg``);
    ``BetweenFactorRot3`` keeps the IMU's relative rotations between
    neighbouring frames (sigma = 1/sqrt(2 lambda), see the module docstring);
    ``AttitudeFactorRot3`` keeps each frame's up direction near the IMU's
    gravity (``gravity_sigma_deg``; not in the paper: a phone's tilt comes
    from the accelerometer and does not drift, its heading does); a weak
    prior (``GAUGE_SIGMA_RAD``) towards the IMU keeps every frame determined. Levenberg-Marquardt iterations are driven from Python
    (linearize + optimize + retract). ``R_wc_init`` is the starting point
    (default: the IMU rotations). ``prior_weight`` > 0: each frame is held to ``R_wc_imu`` with
    that weight (``PriorFactorRot3``, sigma as the IMU term's) in place of the weak prior: pass the IMU
    with its heading drift removed.
    """
    cfg = _rotation_config(config)
    F = len(R_wc_imu)
    R0 = R_wc_imu if R_wc_init is None else R_wc_init
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    keys = [gtsam.symbol("r", i) for i in range(F)]
    for i in range(F):
        values.insert(keys[i], gtsam.Rot3(R0[i]))
    prior = gtsam.noiseModel.Isotropic.Sigma(3, 1.0 / np.sqrt(2.0 * prior_weight) if prior_weight > 0 else GAUGE_SIGMA_RAD)
    for i in range(F):
        graph.add(gtsam.PriorFactorRot3(keys[i], gtsam.Rot3(R_wc_imu[i]), prior))

    sel = labels >= 0
    if np.any(sel):
        n_cam = interpretation_normals(K, segments.endpoints[sel].astype(np.float64))
        v = mf.directions[labels[sel].astype(np.int64)]
        fr = segments.frame[sel]
        bounds = np.searchsorted(fr, np.arange(F + 1))
        huber = np.sin(np.radians(cfg.huber_deg)) if cfg.huber_deg > 0 else 0.0
        length = segments.lengths[sel].astype(np.float64)
        w = length / np.median(length)  # sigma_j ~ 1 / length_j (normal noise ~ px noise / length)
        for i in range(F):
            a, b = bounds[i], bounds[i + 1]
            if b > a:
                graph.add(manhattan_factor(keys[i], n_cam[a:b], v[a:b], huber, w[a:b]))

    if cfg.gravity_sigma_deg > 0:  # the IMU's gravity (tilt) is absolute and does not drift; only its heading does
        up = gtsam.Unit3(np.array([0.0, 0.0, 1.0]))
        g_noise = gtsam.noiseModel.Isotropic.Sigma(2, np.radians(cfg.gravity_sigma_deg))
        up_cam = R_wc_imu[:, 2, :]  # R_imu^T z: the world's up in each camera frame
        for i in range(F):
            graph.add(gtsam.AttitudeFactorRot3(keys[i], up, g_noise, gtsam.Unit3(up_cam[i])))

    pairs = neighbour_pairs(R_wc_imu, cfg.neighbour_angle_deg, cfg.max_neighbours)
    if cfg.imu_weight > 0 and len(pairs):
        imu_noise = gtsam.noiseModel.Isotropic.Sigma(3, 1.0 / np.sqrt(2.0 * cfg.imu_weight))
        rel = np.einsum("pji,pjk->pik", R_wc_imu[pairs[:, 0]], R_wc_imu[pairs[:, 1]])  # R_i^T R_j
        for (i, j), Rij in zip(pairs, rel):
            graph.add(gtsam.BetweenFactorRot3(keys[i], keys[j], gtsam.Rot3(Rij), imu_noise))

    values = levenberg_marquardt(graph, values, keys, cfg.max_iterations)
    return np.stack([values.atRot3(k).matrix() for k in keys])


def heading_drift(
    R_wc: np.ndarray,
    R_wc_imu: np.ndarray,
    timestamps: np.ndarray,
    weights: np.ndarray,
    degree: int,
    up: np.ndarray = np.array([0.0, 0.0, 1.0]),
    pairs: np.ndarray | None = None,
    pair_weight: float = 10.0,
) -> np.ndarray:
    """Returns (F,) the IMU's heading drift (rad) per frame: a polynomial in time fitted to the corrections.

    A phone's attitude filter takes tilt from the accelerometer (it does not
    drift) and heading from the integrated gyroscope, so a gyro bias makes
    the heading drift about ``up``, smoothly in time (linearly for a
    constant bias). The correction of frame i, the heading angle of
    R_i R_imu,i^T, is fitted by weighted least squares (``weights``: how
    well the frame's own horizontal Manhattan lines fix its heading) with a
    polynomial of ``degree``, in two rounds, the second without frames
    more than 3 robust sigmas off. Not in the paper: it lets the IMU's
    relative rotations (supplement Eq. 1, second term) carry frames with few
    horizontal lines without carrying the drift along.

    ``pairs`` (P, 2): frames a turn apart that look the same way (a spin's two ends): the
    difference of their corrections is the drift between them, whatever the lines both see
    bias the headings by, so each pair is a row ``p(t_j) - p(t_i)`` of weight ``pair_weight``
    (measured: a bedroom whose biased blocks tilted the fit, heading errors -0.13 at the start
    to +0.16 degrees at the end).
    """
    F = len(R_wc)
    if degree < 0 or F < degree + 2:
        return np.zeros(F)
    D = np.einsum("fij,fkj->fik", R_wc, R_wc_imu)  # world-frame correction R R_imu^T
    # heading angle about `up`: the rotation of a horizontal reference vector projected on the horizontal plane
    a = np.array([1.0, 0.0, 0.0]) - up[0] * up
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    Da = D @ a
    angle = np.arctan2(Da @ b, Da @ a)
    t = np.asarray(timestamps, dtype=np.float64)
    t = (t - t[0]) / max(t[-1] - t[0], 1e-9)  # in [0, 1]: a well-conditioned Vandermonde matrix
    w = np.asarray(weights, dtype=np.float64)
    keep = w > 0
    if np.sum(keep) < degree + 2:
        return np.zeros(F)
    V = np.vander(t, degree + 1)
    P = np.zeros((0, 2), np.int64) if pairs is None else np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    P = P[(w[P[:, 0]] > 0) & (w[P[:, 1]] > 0)]  # both frames see horizontal lines
    A = np.vstack([V, V[P[:, 1]] - V[P[:, 0]]])
    b = np.concatenate([angle, np.angle(np.exp(1j * (angle[P[:, 1]] - angle[P[:, 0]])))])
    w = np.concatenate([w, np.full(len(P), float(pair_weight))])
    keep = np.concatenate([keep, np.ones(len(P), bool)])
    for _ in range(2):
        sw = np.sqrt(w * keep)
        coef, *_ = np.linalg.lstsq(A * sw[:, None], b * sw, rcond=None)
        r = b - A @ coef
        mad = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep])))
        keep = keep & (np.abs(r) <= 3.0 * max(mad, 1e-5))
        if np.sum(keep[:F]) < degree + 2:
            break
    return V @ coef


def rotate_heading(R_wc: np.ndarray, angle: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """Returns (F, 3, 3) R_z(angle_i) R_i: each rotation turned about the world's ``up`` by its angle."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(angle)[:, None] * up[None]).as_matrix() @ R_wc


def levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    keys: list[int],
    max_iterations: int,
    dims: int = 3,
    rel_tol: float = 1e-9,
) -> gtsam.Values:
    """Returns the values after Levenberg-Marquardt on ``graph``, driven from Python.

    Recipe of ``notes/gtsam-python-performance.md``: linearize, add the
    damping rows sqrt(lambda) I per variable, optimize, retract; accept a
    step only when the error decreases.
    """
    err = graph.error(values)
    lam = 1e-6
    unit = gtsam.noiseModel.Unit.Create(dims)
    zeros = np.zeros(dims)
    for it in range(max_iterations):
        gfg = graph.linearize(values)
        while True:
            damped = gfg.clone()
            for k in keys:
                damped.add(gtsam.JacobianFactor(k, np.sqrt(lam) * np.eye(dims), zeros, unit))
            delta = damped.optimize()
            candidate = values.retract(delta)
            new_err = graph.error(candidate)
            if new_err <= err:
                break
            lam *= 10.0
            if lam > 1e8:
                log.debug("LM: no decrease at iteration %d (error %.6g)", it, err)
                return values
        values, prev, err = candidate, err, new_err
        lam = max(lam / 10.0, 1e-9)
        if prev - err <= rel_tol * max(prev, 1e-30):
            break
    log.debug("LM: %d iterations, error %.6g", it + 1, err)
    return values
