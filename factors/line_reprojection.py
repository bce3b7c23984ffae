"""Line reprojection factor (paper §3.4): segment-averaged pixel distance to the projected 3D line.

The 3D line ``l`` is ``{Lambda_l + s A_l}`` (``taylor_line``); in frame ``i``
with ``R_wc_i`` and centre ``c_i`` it projects to the image line ``K^-T n``
with ``n = R_wc_i^T ((Lambda_l - c_i) x A_l)``. For an observed segment with
endpoints x1, x2 let d1, d2 be their signed pixel distances to that line.
The paper averages the (squared) distance over all points of the segment
(Taylor & Kriegman): along the segment the distance is linear, so the mean
squared distance is ``(d1² + d1 d2 + d2²) / 3``. Each observation gives the
2-vector

    r = [ (d1 + d2) / 2,  (d1 - d2) / (2 sqrt 3) ],   ||r||² = (d1² + d1 d2 + d2²) / 3.

One factor holds several observations of ONE line (a track or a chunk of it),
residuals stacked, which keeps the number of Python callbacks low (see
``notes/gtsam-python-performance.md``). Keys, in order:
``[line, centre_1..centre_n, (rotation_1..rotation_n), (focal)]``.

* line: ``gtsam.Point3`` Lambda_l;
* centres: ``gtsam.Point3`` camera centres (world, m);
* rotations: ``gtsam.Rot3`` R_wc (right perturbation ``R Exp(w)``). When the
  rotations are not variables (phase 1) they are constants bound in the factor;
* focal: a 1-vector ``f`` = fx in pixels; fy = f * fy0 / fx0 keeps the aspect
  of the base ``K``; the principal point is fixed. Absent: ``K`` is constant.
"""
from __future__ import annotations

import functools

import gtsam
import numpy as np

_S3 = 1.0 / (2.0 * np.sqrt(3.0))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Returns row-wise cross products of (N, 3) arrays (np.cross is slow on small arrays)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def segment_distances(endpoints: np.ndarray, taylor: np.ndarray, direction: np.ndarray, R_wc: np.ndarray,
                      centers: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns (d1, d2): signed pixel distances of the segments' endpoints to the projected lines; vectorised over (N,)."""
    n = np.einsum("nji,nj->ni", R_wc, np.cross(taylor - centers, direction))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    s = np.hypot(n[:, 0] / fx, n[:, 1] / fy)
    d1 = (n[:, 0] * (endpoints[:, 0] - cx) / fx + n[:, 1] * (endpoints[:, 1] - cy) / fy + n[:, 2]) / s
    d2 = (n[:, 0] * (endpoints[:, 2] - cx) / fx + n[:, 1] * (endpoints[:, 3] - cy) / fy + n[:, 2]) / s
    return d1, d2


def segment_residuals(d1: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """Returns (N, 2) residuals whose squared norms are the segment-averaged squared distances (d1² + d1 d2 + d2²) / 3."""
    return np.stack([0.5 * (d1 + d2), _S3 * (d1 - d2)], axis=-1)


def line_reprojection_error(endpoints: np.ndarray, direction: np.ndarray, K: np.ndarray, R_fixed: np.ndarray | None,
                            has_focal: bool, this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
    """Returns the stacked (2n,) segment-averaged reprojection residuals (pixels) of one line in n frames.

    ``endpoints`` (n, 4) pixels; ``direction`` A (3,); ``K`` base intrinsics;
    ``R_fixed`` (n, 3, 3) constant R_wc when rotations are not variables.
    Jacobians are analytic (module docstring for the keys' order).
    """
    keys = this.keys()
    nobs = len(endpoints)
    lam = values.atPoint3(keys[0])
    C = np.array([values.atPoint3(k) for k in keys[1:1 + nobs]])
    if R_fixed is None:
        R = np.array([values.atRot3(k).matrix() for k in keys[1 + nobs:1 + 2 * nobs]])
    else:
        R = R_fixed
    fx0, fy0, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if has_focal:
        fx = values.atVector(keys[-1])[0]
        fy = fx * fy0 / fx0
    else:
        fx, fy = fx0, fy0
    w = _cross(lam - C, direction)                         # (n, 3) world normal of the interpretation plane
    n = np.einsum("nji,nj->ni", R, w)                      # camera frame
    m1 = np.empty((nobs, 3))
    m2 = np.empty((nobs, 3))
    m1[:, 0] = (endpoints[:, 0] - cx) / fx
    m1[:, 1] = (endpoints[:, 1] - cy) / fy
    m2[:, 0] = (endpoints[:, 2] - cx) / fx
    m2[:, 1] = (endpoints[:, 3] - cy) / fy
    m1[:, 2] = m2[:, 2] = 1.0
    s = np.sqrt((n[:, 0] / fx) ** 2 + (n[:, 1] / fy) ** 2)
    d1 = (n * m1).sum(1) / s
    d2 = (n * m2).sum(1) / s
    r = np.empty(2 * nobs)
    r[0::2] = 0.5 * (d1 + d2)
    r[1::2] = _S3 * (d1 - d2)
    if jacobians is None:
        return r
    # d d_k / d n = (m_k - d_k q) / s with q = (n1 / fx², n2 / fy², 0) / s
    q = np.zeros((nobs, 3))
    q[:, 0] = n[:, 0] / (fx * fx * s)
    q[:, 1] = n[:, 1] / (fy * fy * s)
    g1 = (m1 - d1[:, None] * q) / s[:, None]
    g2 = (m2 - d2[:, None] * q) / s[:, None]
    ga = 0.5 * (g1 + g2)                                   # rows of residual a, w.r.t. n
    gb = _S3 * (g1 - g2)
    G = np.empty((2 * nobs, 3))
    G[0::2], G[1::2] = ga, gb
    Rrep = np.repeat(R, 2, axis=0)                         # (2n, 3, 3)
    v = np.einsum("kij,kj->ki", Rrep, G)                   # R g: gradient w.r.t. the world normal w
    J_c = _cross(v, direction)                           # d/dc = (R g) x A ; d/dLambda = -(R g) x A
    jacobians[0] = -J_c
    rows = np.arange(2 * nobs)
    blocks = np.zeros((nobs, 2 * nobs, 3))
    blocks[rows // 2, rows] = J_c
    for j in range(nobs):
        jacobians[1 + j] = blocks[j]
    if R_fixed is None:
        nrep = np.repeat(n, 2, axis=0)
        J_r = _cross(G, nrep)                            # d/dw_rot = g x n (right perturbation)
        blocks = np.zeros((nobs, 2 * nobs, 3))
        blocks[rows // 2, rows] = J_r
        for j in range(nobs):
            jacobians[1 + nobs + j] = blocks[j]
    if has_focal:
        df1 = n[:, 2] / (fx * s)                           # d d_k / d fx, equal for both endpoints
        J_f = np.empty((2 * nobs, 1))
        J_f[0::2, 0] = df1
        J_f[1::2, 0] = 0.0
        jacobians[len(keys) - 1] = J_f
    return r


def line_reprojection_factor(line_key: int, center_keys, endpoints: np.ndarray, direction: np.ndarray, K: np.ndarray,
                             noise, rotation_keys=None, R_wc_fixed: np.ndarray | None = None,
                             focal_key: int | None = None) -> gtsam.CustomFactor:
    """Returns one CustomFactor for the observations of one line in n frames (2n residuals, pixels).

    Give ``rotation_keys`` (Rot3 variables) or ``R_wc_fixed`` (n, 3, 3)
    constants; ``focal_key`` adds the focal length as a variable. ``noise``
    must have dimension 2n (e.g. ``robust.noise_model(2 * n, sigma_px)``).
    """
    ep = np.ascontiguousarray(endpoints, dtype=np.float64).reshape(-1, 4)
    nobs = len(ep)
    center_keys = [int(k) for k in center_keys]
    if len(center_keys) != nobs:
        raise ValueError("one centre key per observation expected")
    keys = [int(line_key)] + center_keys
    if rotation_keys is not None:
        rotation_keys = [int(k) for k in rotation_keys]
        if len(rotation_keys) != nobs:
            raise ValueError("one rotation key per observation expected")
        keys += rotation_keys
        R_fixed = None
    else:
        if R_wc_fixed is None:
            raise ValueError("give rotation_keys or R_wc_fixed")
        R_fixed = np.ascontiguousarray(R_wc_fixed, dtype=np.float64).reshape(nobs, 3, 3)
    if focal_key is not None:
        keys.append(int(focal_key))
    a = np.asarray(direction, dtype=np.float64).reshape(3)
    fn = functools.partial(line_reprojection_error, ep, a, np.asarray(K, dtype=np.float64), R_fixed, focal_key is not None)
    return gtsam.CustomFactor(noise, keys, fn)
