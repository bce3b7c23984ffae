"""Noise-model helpers: isotropic Gaussian noise, optionally wrapped in a robust kernel.

A weight ``w`` in the paper's cost (§3.4: 1 for reprojection, 1e4 for colinearity
and coplanarity) corresponds to ``sigma = 1 / sqrt(w)`` in the whitened cost.
"""
from __future__ import annotations

import gtsam
import numpy as np

ROBUST_KERNELS = ("none", "huber", "cauchy", "geman_mcclure")


def sigma_from_weight(weight: float, unit_sigma: float = 1.0) -> float:
    """Returns the standard deviation equivalent to a least-squares ``weight`` (sigma = unit / sqrt(w))."""
    if weight <= 0:
        raise ValueError(f"weight must be positive, got {weight}")
    return float(unit_sigma) / float(np.sqrt(weight))


def robust_kernel(name: str, k: float):
    """Returns the gtsam m-estimator for ``name`` ("huber" | "cauchy" | "geman_mcclure") with threshold ``k``
    (whitened units), or None for "none". Geman-McClure redescends: a residual far outside the noise costs
    at most ``k^2 / 2``, where Cauchy's cost keeps growing with its logarithm."""
    name = name.lower()
    if name == "none":
        return None
    if name == "huber":
        return gtsam.noiseModel.mEstimator.Huber.Create(float(k))
    if name == "cauchy":
        return gtsam.noiseModel.mEstimator.Cauchy.Create(float(k))
    if name == "geman_mcclure":
        return gtsam.noiseModel.mEstimator.GemanMcClure.Create(float(k))
    raise ValueError(f"unknown robust kernel {name!r}; expected one of {ROBUST_KERNELS}")


def noise_model(dim: int, sigma: float, robust: str = "none", k: float = 1.345):
    """Returns an isotropic noise model of dimension ``dim`` and std ``sigma``, robustified when ``robust`` != "none"."""
    base = gtsam.noiseModel.Isotropic.Sigma(int(dim), float(sigma))
    kernel = robust_kernel(robust, k)
    if kernel is None:
        return base
    return gtsam.noiseModel.Robust.Create(kernel, base)


def robust_weight(whitened: np.ndarray, robust: str = "none", k: float = 1.345) -> np.ndarray:
    """Returns the IRLS weights of the kernel at whitened residual norms (1 for "none"); vectorised."""
    r = np.abs(np.asarray(whitened, dtype=np.float64))
    name = robust.lower()
    if name == "none":
        return np.ones_like(r)
    if name == "huber":
        return np.where(r <= k, 1.0, k / np.maximum(r, 1e-300))
    if name == "cauchy":
        return 1.0 / (1.0 + (r / k) ** 2)
    if name == "geman_mcclure":
        return k**4 / (k**2 + r**2) ** 2
    raise ValueError(f"unknown robust kernel {robust!r}; expected one of {ROBUST_KERNELS}")


def robust_loss(whitened: np.ndarray, robust: str = "none", k: float = 1.345) -> np.ndarray:
    """Returns the kernel's cost at whitened residual norms (0.5 r^2 for "none"), as gtsam's m-estimators'
    ``loss``; vectorised."""
    r = np.abs(np.asarray(whitened, dtype=np.float64))
    name = robust.lower()
    if name == "none":
        return 0.5 * r**2
    if name == "huber":
        return np.where(r <= k, 0.5 * r**2, k * r - 0.5 * k**2)
    if name == "cauchy":
        return 0.5 * k**2 * np.log1p((r / k) ** 2)
    if name == "geman_mcclure":
        return 0.5 * k**2 * r**2 / (k**2 + r**2)
    raise ValueError(f"unknown robust kernel {robust!r}; expected one of {ROBUST_KERNELS}")


def projection_noise(normal: np.ndarray, sigma: float, robust: str = "none", k: float = 1.345):
    """Returns a 3-dim Gaussian noise model that whitens a 3-vector v to ``[n . v / sigma, 0, 0]``.

    A rank-one square-root information matrix: lets GTSAM's built-in C++
    factors on Point3 (``BetweenFactorPoint3``, ``PriorFactorPoint3``) express
    a scalar residual along ``normal`` (unit) without a Python callback.
    """
    R = np.zeros((3, 3))
    R[0] = np.asarray(normal, dtype=np.float64).reshape(3) / float(sigma)
    base = gtsam.noiseModel.Gaussian.SqrtInformation(R, False)
    kernel = robust_kernel(robust, k)
    return base if kernel is None else gtsam.noiseModel.Robust.Create(kernel, base)
