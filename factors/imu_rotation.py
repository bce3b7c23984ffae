"""IMU relative-rotation prior (paper §3.4, supplement §2): GTSAM's built-in ``BetweenFactorRot3``.

Rotation variables are ``R_wc`` (world_from_camera) as ``gtsam.Rot3``. The
measurement between frames i and j is ``R_wc_i^T R_wc_j`` from the IMU; the
error is ``Log(measured^-1 R_i^-1 R_j)`` (rad, right-perturbation tangent).
Noise: isotropic, ``sigma_deg`` per axis — the drift the IMU accumulates
between two neighbouring frames, not its absolute error.
"""
from __future__ import annotations

import gtsam
import numpy as np


def imu_noise(sigma_deg: float):
    """Returns the isotropic 3-dim noise model with std ``sigma_deg`` (converted to radians) per axis."""
    return gtsam.noiseModel.Isotropic.Sigma(3, float(np.radians(sigma_deg)))


def imu_rotation_factor(key_i: int, key_j: int, R_wc_i: np.ndarray, R_wc_j: np.ndarray, noise) -> gtsam.BetweenFactorRot3:
    """Returns a BetweenFactorRot3 holding ``R_i^T R_j`` at the IMU's relative rotation between frames i and j."""
    rel = np.asarray(R_wc_i, dtype=np.float64).T @ np.asarray(R_wc_j, dtype=np.float64)
    return gtsam.BetweenFactorRot3(key_i, key_j, gtsam.Rot3(rel), noise)
