"""Rotation prior with a heading-drift slope (our addition to paper §3.4).

The bundle adjustment holds each frame's rotation to its preprocessed
(vanishing-point) rotation ``R_p`` (``graph.rotation_prior_sigma_deg``).
Those rotations keep part of the IMU's heading drift where few horizontal
lines fix the heading (supplement §2 and our drift fit,
:func:`panosfm_graph.lines.rotations.heading_drift`): a ramp in time,
e.g. -0.14 to +0.16 degrees over a bedroom spin whose two ends see one
horizontal segment each. Per-frame priors hold every frame on that ramp;
one shared slope ``s`` (rad over the capture) lets the lines the whole spin
sees (the spin's two ends look at the same ones) turn it away:

    e = Log((Exp(s tau up) R_p)^T R)    (3-vector, rad)

``tau`` is the frame's time in [-1/2, 1/2] over the capture, ``up`` the
world's vertical (unit). Variables: ``R`` a Rot3 (R_wc), ``s`` a 1-vector.
With ``s`` = 0 this is GTSAM's ``PriorFactorRot3`` at ``R_p``.
"""
from __future__ import annotations

import functools

import gtsam
import numpy as np


def _exp(w: np.ndarray) -> np.ndarray:
    return gtsam.Rot3.Expmap(np.asarray(w, dtype=np.float64)).matrix()


def drift_prior_error(R_prior: np.ndarray, up: np.ndarray, tau: float, this: gtsam.CustomFactor,
                      values: gtsam.Values, jacobians) -> np.ndarray:
    """Returns ``Log((Exp(s tau up) R_prior)^T R)`` (rad): the frame's rotation off its drift-corrected prior.

    Keys: R (Rot3), s (1-vector). Jacobians in GTSAM's right-perturbation tangent
    (R Exp(xi)): d/dxi = J_r^-1(e); d/ds = -tau J_r^-1(e) R^T up, since
    Exp(ds tau up) commutes with Exp(s tau up) and Exp(a) R = R Exp(R^T a).
    """
    keys = this.keys()
    R = values.atRot3(keys[0]).matrix()
    s = float(values.atVector(keys[1])[0])
    Rp = _exp(s * tau * up) @ R_prior
    e = gtsam.Rot3.Logmap(gtsam.Rot3(Rp.T @ R))
    if jacobians is not None:
        Jinv = gtsam.Rot3.LogmapDerivative(e)
        jacobians[0] = Jinv
        jacobians[1] = (-tau * Jinv @ (R.T @ up)).reshape(3, 1)
    return e


def drift_prior_factor(rotation_key: int, slope_key: int, R_prior: np.ndarray, up: np.ndarray, tau: float,
                       noise) -> gtsam.CustomFactor:
    """Returns a CustomFactor on (Rot3 R, 1-vector s) holding R at ``Exp(s tau up) R_prior`` (:func:`drift_prior_error`).

    ``noise`` is 3-dimensional (rad), as the plain rotation prior's.
    """
    u = np.asarray(up, dtype=np.float64).reshape(3)
    u = u / np.linalg.norm(u)
    return gtsam.CustomFactor(noise, [rotation_key, slope_key],
                              functools.partial(drift_prior_error, np.asarray(R_prior, dtype=np.float64).reshape(3, 3),
                                                u, float(tau)))


def drift_times(frames: np.ndarray, n_frames: int) -> np.ndarray:
    """Returns ``tau`` of each frame index in ``frames``: its time in [-1/2, 1/2] over a capture of ``n_frames``."""
    return np.asarray(frames, dtype=np.float64) / max(n_frames - 1, 1) - 0.5
