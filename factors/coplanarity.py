"""Coplanarity factors (paper §3.4): ``(Lambda_l - Lambda_m) . A_lm = 0`` and the floor variant.

Floor (our choice, documented): one scalar variable ``h`` (a 1-vector
``gtsam`` Vector value: the floor plane is ``z . X = h``) and, per floor
line, ``Lambda_l . n - h = 0`` with ``n`` the vertical Manhattan direction.
Fixing ``h`` with a prior fixes the reconstruction's scale once the first
camera centre is fixed (see ``panosfm_graph.graph``).
``plane_offset_factor`` is the same residual measured from a camera centre
against a constant, usable as a one-degree-of-freedom scale gauge.
"""
from __future__ import annotations

import functools

import gtsam
import numpy as np


def coplanarity_error(normal: np.ndarray, this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
    """Returns the 1-vector ``(Lambda_l - Lambda_m) . A_lm`` (m): the distance between the two lines along the plane normal."""
    keys = this.keys()
    d = values.atPoint3(keys[0]) - values.atPoint3(keys[1])
    if jacobians is not None:
        jacobians[0] = normal.reshape(1, 3)
        jacobians[1] = -normal.reshape(1, 3)
    return np.array([normal @ d])


def coplanarity_factor(line_key_l: int, line_key_m: int, normal: np.ndarray, noise) -> gtsam.CustomFactor:
    """Returns a CustomFactor on Point3s (Lambda_l, Lambda_m) enforcing coplanarity along unit ``normal``."""
    n = np.asarray(normal, dtype=np.float64).reshape(3)
    return gtsam.CustomFactor(noise, [line_key_l, line_key_m], functools.partial(coplanarity_error, n))


def floor_error(normal: np.ndarray, this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
    """Returns the 1-vector ``Lambda_l . n - h`` (m): the line's offset from the plane ``n . X = h``."""
    keys = this.keys()
    lam = values.atPoint3(keys[0])
    h = values.atVector(keys[1])[0]
    if jacobians is not None:
        jacobians[0] = normal.reshape(1, 3)
        jacobians[1] = np.array([[-1.0]])
    return np.array([normal @ lam - h])


def floor_factor(line_key: int, height_key: int, normal: np.ndarray, noise) -> gtsam.CustomFactor:
    """Returns a CustomFactor on (Point3 Lambda_l, 1-vector h) putting the line on the plane ``n . X = h``."""
    n = np.asarray(normal, dtype=np.float64).reshape(3)
    return gtsam.CustomFactor(noise, [line_key, height_key], functools.partial(floor_error, n))


def plane_offset_error(normal: np.ndarray, offset: float, this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
    """Returns the 1-vector ``(Lambda_l - c) . n - offset`` (m): the line's distance from camera centre c along n, minus a constant."""
    keys = this.keys()
    d = values.atPoint3(keys[0]) - values.atPoint3(keys[1])
    if jacobians is not None:
        jacobians[0] = normal.reshape(1, 3)
        jacobians[1] = -normal.reshape(1, 3)
    return np.array([normal @ d - offset])


def plane_offset_factor(line_key: int, center_key: int, normal: np.ndarray, offset: float, noise) -> gtsam.CustomFactor:
    """Returns a CustomFactor on Point3s (Lambda_l, c) holding ``(Lambda_l - c) . n`` at ``offset``."""
    n = np.asarray(normal, dtype=np.float64).reshape(3)
    return gtsam.CustomFactor(noise, [line_key, center_key], functools.partial(plane_offset_error, n, float(offset)))


def coplanarity_factor_builtin(line_key_l: int, line_key_m: int, normal: np.ndarray, sigma: float,
                               robust: str = "none", k: float = 1.345) -> gtsam.BetweenFactorPoint3:
    """Returns the same constraint as :func:`coplanarity_factor` as a C++ ``BetweenFactorPoint3`` (no Python callback).

    ``BetweenFactorPoint3(m, l, 0)`` has error ``Lambda_l - Lambda_m``; the
    rank-one noise model (``robust.projection_noise``) whitens it to
    ``[(Lambda_l - Lambda_m) . n / sigma, 0, 0]``, robustified by ``robust``.
    """
    from factors.robust import projection_noise

    return gtsam.BetweenFactorPoint3(line_key_m, line_key_l, np.zeros(3), projection_noise(normal, sigma, robust, k))
