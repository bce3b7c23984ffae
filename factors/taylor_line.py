"""Taylor's line parameterisation (paper §3.4): Lambda, the line's point closest to the origin.

A Manhattan line ``l`` has a fixed unit world direction ``A_l`` and a free
3-vector ``Lambda_l`` (a ``gtsam.Point3`` variable). The line is
``{Lambda_l + s A_l}``; on the constraint manifold ``A_l . Lambda_l = 0``
(colinearity factor) ``Lambda_l`` is the foot of the perpendicular from the
origin. All functions are vectorised over a leading dimension.

Camera convention (``panosfm_graph.data``): ``R_wc`` maps camera-frame
vectors to the world, ``c`` is the camera centre; the camera-frame point is
``R_wc^T (X - c)``.
"""
from __future__ import annotations

import numpy as np


def taylor_from_point_direction(point: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Returns (N, 3) Lambda: the points of lines (point, unit direction) closest to the origin."""
    p = np.asarray(point, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    return p - np.sum(p * d, axis=-1, keepdims=True) * d


def taylor_to_point_direction(taylor: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns (point closest to the origin, unit direction) of lines given by Lambda and A (Lambda projected onto A's normal plane)."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return taylor_from_point_direction(taylor, d), d


def line_extent(taylor: np.ndarray, direction: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Returns the line coordinates s of ``points`` projected on the lines: ``(points - Lambda) . A``."""
    return np.sum((np.asarray(points) - np.asarray(taylor)) * np.asarray(direction), axis=-1)


def plucker(taylor: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Returns (N, 6) Plücker coordinates (direction A, moment Lambda x A) of the lines."""
    t = np.asarray(taylor, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    return np.concatenate([np.broadcast_to(d, t.shape), np.cross(t, d)], axis=-1)


def interpretation_normal(taylor: np.ndarray, direction: np.ndarray, R_wc: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Returns (N, 3) camera-frame normals ``R_wc^T ((Lambda - c) x A)`` of the planes through the camera centre and the lines (not normalised)."""
    w = np.cross(np.asarray(taylor) - np.asarray(center), np.asarray(direction))
    return np.einsum("...ji,...j->...i", np.asarray(R_wc), w)


def project_line(taylor: np.ndarray, direction: np.ndarray, R_wc: np.ndarray, center: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Returns (N, 3) image lines (a, b, c) with a² + b² = 1: pixel x is on the projected line iff a u + b v + c = 0.

    The projected line is ``K^-T n`` with ``n`` the interpretation-plane normal;
    ``a u + b v + c`` is then the signed pixel distance to the line.
    """
    n = interpretation_normal(taylor, direction, R_wc, center)
    l = n @ np.linalg.inv(K)  # rows: K^-T n
    return l / np.linalg.norm(l[..., :2], axis=-1, keepdims=True)
