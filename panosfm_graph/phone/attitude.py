"""The camera's attitude at every frame from raw gyroscope and accelerometer samples: a GTSAM AHRS smoother.

One ``Rot3`` per frame (the phone's attitude, world_from_device, at the
frame's time on the sensor clock) and one gyroscope bias: GTSAM's
``AHRSFactor`` between consecutive frames (its ``PreintegratedAhrsMeasurements``
integrate the gyroscope samples between them, bias-corrected to first order),
an ``AttitudeFactorRot3`` per frame from the accelerometer averaged over
+- :data:`UP_WINDOW_S` (the specific force points up, world +z, at rest and
on average while a person turns on the spot), a prior on the bias from the
phone's still moments (:func:`still_bias`), and a loose prior on the first
frame's attitude for the arbitrary heading. The camera's attitude is the
phone's times ``camera_from_device^T``.

A person turning on the spot swings the phone on an arm: its accelerometer
also feels ``omega x (omega x l) + omega' x l`` (``l`` the lever from the
turning axis to the phone, fixed in the phone's axes), which tilts the
measured up by ~5 degrees in a 4-second turn. :func:`smooth_attitude` solves
once, fits ``l`` by least squares against the smoothed attitude
(:func:`_lever_arm`), removes its acceleration from the samples and solves
again.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from ..errors import InputError
from ..geometry import slerp_rotations
from .logs import G, RawSensors

log = logging.getLogger("panosfm.phone")

UP_WINDOW_S = 0.25  # the accelerometer is averaged over +- this around each frame
UP_SIGMA_DEG = 2.0  # per frame: a person's hand accelerates the phone
STILL_WINDOW_S = 0.25
STILL_STD_RAD_S = 0.01  # a window whose gyroscope std (every axis) is below this is still
STILL_MEAN_RAD_S = 0.05  # ... and whose mean rate is below this
BIAS_SIGMA_RAD_S = 0.005  # the bias prior without still moments (a calibrated phone gyroscope's residual)
GYRO_NOISE_RAD_S = 0.005  # per-sample gyroscope noise when no still moment measures it


@dataclass(frozen=True)
class Attitude:
    """The smoothed camera attitude at the frames and what the smoother learnt on the way."""

    R_wc: np.ndarray  # (F, 3, 3) world_from_camera, world +z up, heading arbitrary
    gyro_bias: np.ndarray  # (3,) rad/s, device axes
    still_s: float  # seconds of still samples that measured the bias (0: prior only)
    up_residual_deg: float  # median angle between each frame's measured up (lever removed) and the smoothed one
    gyro_noise: float  # per-sample gyroscope noise used (rad/s)
    lever_arm_m: np.ndarray  # (3,) device axes: from the turning axis to the phone (zeros when not fitted)


def still_bias(sensors: RawSensors) -> tuple[np.ndarray | None, float, float]:
    """Returns (bias (3,) or None, seconds of still samples, per-sample noise rad/s) from the still windows."""
    t, w = sensors.t_gyro, sensors.gyro
    n = max(int(round(STILL_WINDOW_S * sensors.gyro_rate_hz)), 5)
    m = len(t) // n
    if m == 0:
        return None, 0.0, GYRO_NOISE_RAD_S
    win = w[: m * n].reshape(m, n, 3)
    std, mean = win.std(axis=1), win.mean(axis=1)
    still = np.all(std < STILL_STD_RAD_S, axis=1) & (np.linalg.norm(mean, axis=1) < STILL_MEAN_RAD_S)
    if not still.any():
        return None, 0.0, GYRO_NOISE_RAD_S
    samples = win[still].reshape(-1, 3)
    return samples.mean(axis=0), float(len(samples) / sensors.gyro_rate_hz), float(np.median(std[still]))


def _up_at(t_up: np.ndarray, up: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Returns (F, 3) unit "up" directions (device axes): the accelerometer's mean over +- UP_WINDOW_S."""
    c = np.vstack([np.zeros((1, 3)), np.cumsum(up, axis=0)])
    a = np.searchsorted(t_up, t - UP_WINDOW_S)
    b = np.maximum(np.searchsorted(t_up, t + UP_WINDOW_S), a + 1)
    b = np.minimum(b, len(t_up))
    a = np.minimum(a, b - 1)
    m = (c[b] - c[a]) / (b - a)[:, None]
    return m / np.linalg.norm(m, axis=1, keepdims=True)


def _preintegrate(params, sensors: RawSensors, ta: float, tb: float, bias: np.ndarray):
    """Returns the PreintegratedAhrsMeasurements of the gyroscope over [ta, tb] (rate held per sample interval)."""
    t, w = sensors.t_gyro, sensors.gyro
    pim = gtsam.PreintegratedAhrsMeasurements(params, bias)
    i0, i1 = np.searchsorted(t, ta, side="right"), np.searchsorted(t, tb, side="left")
    knots = np.concatenate([[ta], t[i0:i1], [tb]])
    mid = 0.5 * (knots[1:] + knots[:-1])
    rates = np.column_stack([np.interp(mid, t, w[:, j]) for j in range(3)])
    for r, dt in zip(rates, np.diff(knots)):
        if dt > 0:
            pim.integrateMeasurement(r, float(dt))
    return pim


def smooth_attitude(sensors: RawSensors, t_frames_sensor: np.ndarray, camera_from_device: np.ndarray,
                    up_sigma_deg: float = UP_SIGMA_DEG, lever_arm: bool = True) -> Attitude:
    """Returns the :class:`Attitude` at frame times ``t_frames_sensor`` (on the sensor clock); with ``lever_arm``
    the arm's acceleration is fitted and removed (module docstring).

    InputError if the frames are not all inside both sensor streams.
    """
    t = np.asarray(t_frames_sensor, dtype=np.float64)
    lo, hi = sensors.span
    if t[0] < lo or t[-1] > hi:
        raise InputError(f"the sensor logs ({lo:.3f}..{hi:.3f} s on their clock) do not cover the video's frames "
                         f"({t[0]:.3f}..{t[-1]:.3f} s after the time offset)")
    bias0, still_s, noise = still_bias(sensors)
    bias_sigma = BIAS_SIGMA_RAD_S if bias0 is None else max(noise / np.sqrt(still_s * sensors.gyro_rate_hz), 1e-5)
    bias0 = np.zeros(3) if bias0 is None else bias0
    R_dc = np.asarray(camera_from_device, dtype=np.float64).T
    lever = np.zeros(3)
    R_wd, bias, resid = _solve(sensors, sensors.up, t, R_dc, bias0, bias_sigma, noise, up_sigma_deg)
    if lever_arm:
        lever, arm_acc = _lever_arm(sensors, bias, t, R_wd)
        R_wd, bias, resid = _solve(sensors, sensors.up - arm_acc, t, R_dc, bias0, bias_sigma, noise, up_sigma_deg)
    return Attitude(R_wc=R_wd @ R_dc, gyro_bias=bias, still_s=still_s, up_residual_deg=resid,
                    gyro_noise=float(noise), lever_arm_m=lever)


def _solve(sensors: RawSensors, up_samples: np.ndarray, t: np.ndarray, R_dc: np.ndarray, bias0: np.ndarray,
           bias_sigma: float, noise: float, up_sigma_deg: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Returns (world_from_device (F, 3, 3), gyroscope bias (3,), median up residual in degrees): one smoothing."""
    params = gtsam.PreintegratedRotationParams()
    params.setGyroscopeCovariance(np.eye(3) * noise ** 2 / sensors.gyro_rate_hz)  # continuous-time density
    up = _up_at(sensors.t_up, up_samples, t)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    B = gtsam.symbol("b", 0)
    X = [gtsam.symbol("r", k) for k in range(len(t))]
    R0 = _level(up[0], R_dc)  # the measured up onto +z, the optical axis heading along world +x
    values.insert(B, bias0)
    values.insert(X[0], gtsam.Rot3(R0))
    graph.add(gtsam.PriorFactorVector(B, bias0, gtsam.noiseModel.Isotropic.Sigma(3, bias_sigma)))
    graph.add(gtsam.PriorFactorRot3(X[0], gtsam.Rot3(R0), gtsam.noiseModel.Isotropic.Sigma(3, 1.0)))
    up_noise = gtsam.noiseModel.Isotropic.Sigma(2, np.radians(up_sigma_deg))
    z = gtsam.Unit3(np.array([0.0, 0.0, 1.0]))
    R = gtsam.Rot3(R0)
    for k in range(len(t)):
        graph.add(gtsam.AttitudeFactorRot3(X[k], z, up_noise, gtsam.Unit3(up[k])))
        if k + 1 < len(t):
            pim = _preintegrate(params, sensors, t[k], t[k + 1], bias0)
            graph.add(gtsam.AHRSFactor(X[k], X[k + 1], B, pim))
            R = R.compose(pim.deltaRij())
            values.insert(X[k + 1], R)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
    R_wd = np.array([result.atRot3(x).matrix() for x in X])
    fitted_up = R_wd[:, 2, :]  # world +z in device axes
    resid = np.degrees(np.arccos(np.clip(np.sum(fitted_up * up, axis=1), -1, 1)))
    return R_wd, np.asarray(result.atVector(B)), float(np.median(resid))


def _skew(v: np.ndarray) -> np.ndarray:
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


def _lever_arm(sensors: RawSensors, bias: np.ndarray, t: np.ndarray, R_wd: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Returns (lever l (3,) m, its acceleration at every accelerometer sample (M, 3)): ``l`` fitted by least
    squares to the accelerometer minus gravity over the frames' span, the phone's attitude slerped from ``R_wd``."""
    tu = sensors.t_up
    w = np.column_stack([np.interp(tu, sensors.t_gyro, sensors.gyro[:, j]) for j in range(3)]) - bias
    # the angular acceleration, smoothed over ~50 ms (gyroscope noise differentiates badly)
    k = max(int(round(0.05 * sensors.gyro_rate_hz)), 1)
    ws = np.column_stack([np.convolve(sensors.gyro[:, j], np.ones(k) / k, mode="same") for j in range(3)])
    dw = np.column_stack([np.interp(tu, sensors.t_gyro, np.gradient(ws[:, j], sensors.t_gyro)) for j in range(3)])
    W = _skew(w)
    A = W @ W + _skew(dw)  # (M, 3, 3): acceleration = A l
    inside = (tu >= t[0]) & (tu <= t[-1])
    R = slerp_rotations(t, R_wd, tu[inside])
    y = sensors.up[inside] - G * R[:, 2, :]  # minus gravity's specific force in device axes
    lever = np.linalg.lstsq(A[inside].reshape(-1, 3), y.reshape(-1), rcond=None)[0]
    return lever, A @ lever


def _level(up_device: np.ndarray, R_dc: np.ndarray) -> np.ndarray:
    """Returns world_from_device with ``up_device`` on world +z and the camera's optical axis heading along +x."""
    zc = np.array([0.0, 0.0, 1.0])
    fwd = R_dc @ zc  # optical axis in device axes
    u = up_device / np.linalg.norm(up_device)
    h = fwd - u * (fwd @ u)
    if np.linalg.norm(h) < 1e-6:  # looking straight up or down: any heading
        h = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    h /= np.linalg.norm(h)
    y = np.cross(u, h)
    return np.stack([h, y, u])  # rows: world x, y, z in device axes
