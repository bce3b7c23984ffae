"""Small shared geometry helpers: quaternions (qw, qx, qy, qz, Hamilton), angles, rays.

Vectorised over leading dimensions; built on ``scipy.spatial.transform``.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


def quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    """Returns (..., 3, 3) rotation matrices from (..., 4) unit quaternions qw, qx, qy, qz."""
    q = np.asarray(q, dtype=np.float64)
    flat = q.reshape(-1, 4)
    R = Rotation.from_quat(flat[:, [1, 2, 3, 0]]).as_matrix()
    return R.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Returns (..., 4) unit quaternions qw, qx, qy, qz (qw >= 0) from (..., 3, 3) rotations."""
    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    q = Rotation.from_matrix(flat).as_quat()[:, [3, 0, 1, 2]]
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(R.shape[:-2] + (4,))


def slerp_rotations(t_src: np.ndarray, R_src: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """Returns (N, 3, 3) rotations slerped from samples ``R_src`` at times ``t_src`` to ``t_query``.

    ``t_src`` must be strictly increasing and cover ``t_query``.
    """
    if len(t_src) == 1:
        return np.repeat(R_src[:1], len(t_query), axis=0)
    return Slerp(t_src, Rotation.from_matrix(R_src))(t_query).as_matrix()


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Returns the angles in degrees of ``R_a^T R_b`` for (..., 3, 3) stacks (atan2 form: exact near 0)."""
    M = np.einsum("...ji,...jk->...ik", R_a, R_b)
    sin2 = np.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], axis=-1)
    cos2 = np.trace(M, axis1=-2, axis2=-1) - 1.0
    return np.degrees(np.arctan2(np.linalg.norm(sin2, axis=-1), cos2))


def heading_aligned_errors_deg(R_est: np.ndarray, R_true: np.ndarray) -> np.ndarray:
    """Returns (N,) the angles in degrees between ``R_est`` and ``R_true`` (N, 3, 3 world_from_camera) after the
    best rotation of ``R_est`` about world z (an attitude's heading is arbitrary)."""
    M = np.einsum("nij,nkj->ik", R_true, R_est)  # sum R_true R_est^T
    yaw = np.arctan2(M[1, 0] - M[0, 1], M[0, 0] + M[1, 1])
    c, s = np.cos(yaw), np.sin(yaw)
    return rotation_angle_deg(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R_est, R_true)


def turned_degrees(R_wc: np.ndarray) -> np.ndarray:
    """Returns (F,) the cumulative angle (degrees) the camera has turned since the first frame."""
    R = np.asarray(R_wc, dtype=np.float64)
    if len(R) < 2:
        return np.zeros(len(R))
    return np.concatenate([[0.0], np.cumsum(rotation_angle_deg(R[:-1], R[1:]))])


def angle_between_deg(a: np.ndarray, b: np.ndarray, unsigned: bool = False) -> np.ndarray:
    """Returns angles in degrees between vectors (last axis); ``unsigned`` treats v and -v alike."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    c = np.sum(a * b, axis=-1)
    if unsigned:
        c = np.abs(c)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def pixel_rays(K: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Returns (..., 3) unit camera-frame rays through pixels ``pts`` (..., 2)."""
    pts = np.asarray(pts, dtype=np.float64)
    x = (pts[..., 0] - K[0, 2]) / K[0, 0]
    y = (pts[..., 1] - K[1, 2]) / K[1, 1]
    d = np.stack([x, y, np.ones_like(x)], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def world_rays(K: np.ndarray, R_wc: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Returns (N, 3) unit WORLD viewing rays ``R_wc K^-1 x~`` through pixels ``pts`` (N, 2) of cameras ``R_wc`` (N, 3, 3)."""
    return np.einsum("nij,nj->ni", R_wc, pixel_rays(K, pts))


def closest_on_lines(points: np.ndarray, directions: np.ndarray, origins: np.ndarray, rays: np.ndarray,
                     min_sin2: float = 1e-9) -> np.ndarray:
    """Returns (N,) the parameters s of the points ``points + s directions`` of 3D lines nearest to rays.

    Row n: the line through ``points[n]`` along the unit ``directions[n]`` and the ray from
    ``origins[n]`` along the unit ``rays[n]``; NaN where the ray is parallel to its line (squared
    sine of their angle at most ``min_sin2``).
    """
    w0 = points - origins
    b = np.sum(directions * rays, axis=1)
    d = np.sum(directions * w0, axis=1)
    e = np.sum(rays * w0, axis=1)
    den = 1.0 - b ** 2
    ok = den > min_sin2
    return np.where(ok, (b * e - d) / np.where(ok, den, 1.0), np.nan)


def interpretation_normals(K: np.ndarray, endpoints: np.ndarray) -> np.ndarray:
    """Returns (N, 3) unit camera-frame normals of the segments' interpretation planes.

    The plane through the camera centre and segment (x1, y1, x2, y2); supplement §1.
    """
    a = pixel_rays(K, endpoints[:, :2])
    b = pixel_rays(K, endpoints[:, 2:])
    n = np.cross(a, b)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def project(K: np.ndarray, R_wc: np.ndarray, center: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns pixels (N, 2) and depths (N,) of world points ``X`` (N, 3) in one camera."""
    Xc = (X - center) @ R_wc  # = R_wc^T (X - c) for each row
    z = Xc[:, 2]
    uv = Xc[:, :2] / z[:, None]
    uv = uv * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])
    return uv, z


def triangulate_dlt(R_wc: np.ndarray, centers: np.ndarray, point_idx: np.ndarray, frame_idx: np.ndarray,
                    xn: np.ndarray, n_points: int) -> np.ndarray:
    """Returns (P, 4) homogeneous points triangulated by linear DLT from all their observations.

    Observation k: point ``point_idx[k]`` seen in camera ``frame_idx[k]`` at normalised
    coordinates ``xn[k]``; rows ``x P3 - P1`` and ``y P3 - P2`` with ``P = [R_cw | -R_cw c]``,
    accumulated as A^T A per point and solved by its smallest eigenvector.
    """
    R_cw = np.transpose(R_wc[frame_idx], (0, 2, 1))
    P = np.concatenate([R_cw, -np.einsum("kij,kj->ki", R_cw, centers[frame_idx])[..., None]], axis=2)  # (K, 3, 4)
    r1 = xn[:, :1] * P[:, 2] - P[:, 0]
    r2 = xn[:, 1:] * P[:, 2] - P[:, 1]
    outer = np.einsum("ki,kj->kij", r1, r1) + np.einsum("ki,kj->kij", r2, r2)
    M = np.zeros((n_points, 4, 4))
    np.add.at(M, point_idx, outer)
    _, vecs = np.linalg.eigh(M)
    X = vecs[:, :, 0]
    return X / np.linalg.norm(X, axis=1, keepdims=True)


def rotation_homography(K: np.ndarray, R_wc_i: np.ndarray, R_wc_j: np.ndarray) -> np.ndarray:
    """Returns the 3x3 homography H = K R_j^T R_i K^-1 mapping pixels of frame i to frame j (pure rotation)."""
    return K @ R_wc_j.T @ R_wc_i @ np.linalg.inv(K)


def rotation_alignment(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """Returns the rotation A minimising sum ||A R_est_i - R_gt_i||_F (chordal mean of R_gt R_est^T)."""
    M = np.einsum("nij,nkj->ik", R_gt, R_est)
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0]) @ Vt


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Returns (s, R, t) minimising sum ||dst - (s R src + t)||^2 (Umeyama 1991), for (N, 3) point sets."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    U, D, Vt = np.linalg.svd(xd.T @ xs / len(src))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0])
    R = U @ S @ Vt
    var_s = np.mean(np.sum(xs * xs, axis=1))
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale and var_s > 0 else 1.0
    if with_scale and var_s <= 0:
        s = 0.0
    return s, R, mu_d - s * R @ mu_s
