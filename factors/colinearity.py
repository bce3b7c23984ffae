"""Colinearity factor (paper §3.4): ``A_l . Lambda_l = 0`` for a line with fixed Manhattan direction A_l.

It keeps Lambda_l the point of the line closest to the origin; the paper
weights it 1e4 relative to reprojection (sigma = 0.01 in reprojection units).
"""
from __future__ import annotations

import functools

import gtsam
import numpy as np


def colinearity_error(direction: np.ndarray, this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
    """Returns the 1-vector ``A . Lambda`` (m); Jacobian ``A^T`` w.r.t. the Point3 Lambda."""
    lam = values.atPoint3(this.keys()[0])
    if jacobians is not None:
        jacobians[0] = direction.reshape(1, 3)
    return np.array([direction @ lam])


def colinearity_factor(line_key: int, direction: np.ndarray, noise) -> gtsam.CustomFactor:
    """Returns a CustomFactor on the Point3 ``line_key`` enforcing ``A . Lambda = 0`` (noise: 1-dim)."""
    a = np.asarray(direction, dtype=np.float64).reshape(3)
    return gtsam.CustomFactor(noise, [line_key], functools.partial(colinearity_error, a))


def colinearity_factor_builtin(line_key: int, direction: np.ndarray, sigma: float) -> gtsam.PriorFactorPoint3:
    """Returns the same constraint as :func:`colinearity_factor` as a C++ ``PriorFactorPoint3`` (no Python callback).

    Prior at the origin with a rank-one noise model (``robust.projection_noise``):
    whitened error ``[A . Lambda / sigma, 0, 0]``.
    """
    from factors.robust import projection_noise

    return gtsam.PriorFactorPoint3(line_key, np.zeros(3), projection_noise(direction, sigma))
