"""A person's spin: camera poses over time and a drifting IMU attitude stream.

The person stands at ``scene.stand_point`` (not the room centre) and turns
once around: the camera centre moves on a circle of radius 0.30-0.40 m about
that point at about 1.5 m height with a ~1 cm bob, the optical axis points
outwards (nearly horizontal), yaw sweeps ``turn_deg`` degrees, and pitch and
roll vary smoothly by a few degrees. Rotations are ``R_wc`` (world_from_camera,
OpenCV camera frame: x right, y down, z forward).

With ``sway_m`` > 0 the spin is less ideal, as a person's is: the stand point
wanders (smooth, RMS ``sway_m``, not returning to where it started), the arm
length varies (RMS ``sway_m / 2``) and so does the angle between the arm and
the optical axis (RMS ``2 deg * sway_m / 0.05 m``). ``sway_m = 0`` (the
default) gives exactly the circle above, identical to earlier versions.
``arm_m`` sets the circle's radius instead of the seeded 0.30-0.40 m; ``arm_m = 0``
is a tripod spin (one optical centre, no bob): zero baseline.

The IMU attitude is the true attitude with a heading drift that grows
linearly in time from 0 at the first frame to ``imu_drift_deg`` at the last
(a rotation about world +z applied on the left) and ~0.1 deg white noise,
sampled at 100 Hz over a span covering every frame timestamp.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from .scenes import Scene


@dataclass(frozen=True)
class SpinParams:
    """The seeded parameters of one spin (angles in degrees, lengths in metres, times in seconds)."""

    stand_world: np.ndarray  # (3,) floor point the person stands on
    radius_m: float
    height_m: float
    bob_m: float
    bob_hz: float
    bob_phase: float
    yaw0_deg: float
    turn_deg: float
    yaw_wobble: float  # relative speed variation of the turn
    view_offset_deg: float  # optical axis yaw relative to the outward radial direction
    pitch_deg: tuple[float, float, float, float]  # offset, amplitude, cycles per sweep, phase
    roll_deg: tuple[float, float, float, float]
    duration_s: float  # time of the last frame
    sway_m: float = 0.0  # how far from an ideal circle the spin is (module docstring)
    sway: tuple = ()  # (amplitudes (4, 3), phases (4, 3)): three harmonics of stand x, stand y, arm length, arm angle
    tremor_deg: float = 0.0  # RMS angle of the hand's rotational tremor (module docstring)
    tremor: tuple = ()  # (frequencies Hz (3, 3), amplitudes (3, 3), phases (3, 3)): per camera axis, three sinusoids


_SWAY_CYCLES = np.array([0.55, 1.35, 2.2])  # cycles per sweep of the sway's three harmonics (not periodic)


def spin_params(scene: Scene, n_frames: int, seed: int = 0, turn_deg: float = 380.0, fps: float = 30.0,
                sway_m: float = 0.0, arm_m: float | None = None, tremor_deg: float = 0.0) -> SpinParams:
    """Returns the seeded spin parameters for ``scene`` (the same seed gives the same spin).

    ``arm_m``: the circle's radius (None: seeded); 0 also stops the bob (a tripod).
    """
    rng = np.random.default_rng([int(seed), 4242])
    sway_rng = np.random.default_rng([int(seed), 4243])  # its own stream: sway_m = 0 leaves the rest unchanged
    amp = sway_rng.normal(size=(4, 3)) / np.arange(1, 4)[None]
    phase = sway_rng.uniform(0, 2 * np.pi, (4, 3))
    tremor_rng = np.random.default_rng([int(seed), 4244])
    tremor = (tremor_rng.uniform(2.0, 7.0, (3, 3)), tremor_rng.uniform(0.5, 1.0, (3, 3)),
              tremor_rng.uniform(0, 2 * np.pi, (3, 3)))
    p = SpinParams(
        tremor_deg=float(tremor_deg),
        tremor=tremor,
        sway_m=float(sway_m),
        sway=(amp, phase),
        stand_world=scene.stand_point_world.astype(np.float64),
        radius_m=float(rng.uniform(0.30, 0.40)),
        height_m=float(rng.uniform(1.45, 1.55)),
        bob_m=float(rng.uniform(0.008, 0.012)),
        bob_hz=float(rng.uniform(0.6, 1.0)),
        bob_phase=float(rng.uniform(0, 2 * np.pi)),
        yaw0_deg=float(rng.uniform(-180.0, 180.0)),
        turn_deg=float(turn_deg),
        yaw_wobble=float(rng.uniform(0.01, 0.03)),
        view_offset_deg=float(rng.uniform(-6.0, 6.0)),
        pitch_deg=(float(rng.uniform(-8.0, -4.0)), float(rng.uniform(1.5, 3.0)), float(rng.uniform(1.0, 2.5)), float(rng.uniform(0, 2 * np.pi))),
        roll_deg=(float(rng.uniform(-1.0, 1.0)), float(rng.uniform(1.0, 2.0)), float(rng.uniform(1.0, 2.5)), float(rng.uniform(0, 2 * np.pi))),
        duration_s=max(n_frames - 1, 1) / float(fps),
    )
    if arm_m is None:
        return p
    return replace(p, radius_m=float(arm_m), bob_m=p.bob_m if arm_m > 0 else 0.0)


def spin_pose(p: SpinParams, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns (R_wc (N, 3, 3), centres (N, 3)) of the spin at times ``t`` (s)."""
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    s = t / p.duration_s  # 0 at the first frame, 1 at the last
    yaw = np.radians(p.yaw0_deg + p.turn_deg * (s + p.yaw_wobble * np.sin(2 * np.pi * s) / (2 * np.pi)))
    radial = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=1)
    z = p.height_m + p.bob_m * np.sin(2 * np.pi * p.bob_hz * t + p.bob_phase)
    sway = _sway(p, s)  # (N, 4): stand x, stand y (m), arm length (m), arm angle (deg); zeros without sway
    centers = p.stand_world[None] + (p.radius_m + sway[:, 2:3]) * radial
    centers[:, :2] += sway[:, :2]
    centers[:, 2] = z
    look = yaw + np.radians(p.view_offset_deg + sway[:, 3])
    f = np.stack([np.cos(look), np.sin(look), np.zeros_like(look)], axis=1)  # camera z (forward)
    down = np.broadcast_to(np.array([0.0, 0.0, -1.0]), f.shape)  # camera y
    right = np.cross(down, f)  # camera x = y x z
    R_level = np.stack([right, down, f], axis=2)  # columns = camera axes in the world
    pitch = np.radians(p.pitch_deg[0] + p.pitch_deg[1] * np.sin(2 * np.pi * p.pitch_deg[2] * s + p.pitch_deg[3]))
    roll = np.radians(p.roll_deg[0] + p.roll_deg[1] * np.sin(2 * np.pi * p.roll_deg[2] * s + p.roll_deg[3]))
    # pitch about the camera x axis (positive looks up), then roll about the optical axis
    R_local = Rotation.from_euler("XZ", np.stack([pitch, roll], axis=1)).as_matrix()
    if p.tremor_deg > 0:
        R_local = R_local @ Rotation.from_rotvec(_tremor(p, t)).as_matrix()
    return R_level @ R_local, centers


def _tremor(p: SpinParams, t: np.ndarray) -> np.ndarray:
    """Returns (N, 3) the tremor's rotation vectors (rad, camera axes) at times ``t``: RMS angle ``p.tremor_deg``."""
    freq, amp, phase = p.tremor
    waves = amp[None] * np.sin(2 * np.pi * freq[None] * t[:, None, None] + phase[None])  # (N, axis, sinusoid)
    rms = np.sqrt(np.sum(amp ** 2) / 2)  # of the angle: sinusoids of distinct frequencies add in power
    return np.radians(p.tremor_deg) * waves.sum(axis=2) / rms


def _sway(p: SpinParams, s: np.ndarray) -> np.ndarray:
    """Returns (N, 4) the sway at sweep fractions ``s``: stand point x, y (m), arm length (m), arm angle (deg)."""
    if p.sway_m <= 0:
        return np.zeros((len(s), 4))
    amp, phase = p.sway
    grid = np.linspace(0.0, 1.0, 512)

    def wave(x):  # (len(x), 4): a sum of three harmonics per component
        return np.sum(amp[None] * np.cos(2 * np.pi * x[:, None, None] * _SWAY_CYCLES[None, None] + phase[None]), axis=2)

    g = wave(grid)
    mu, sd = g.mean(axis=0), np.maximum(g.std(axis=0), 1e-9)
    scale = np.array([p.sway_m / np.sqrt(2), p.sway_m / np.sqrt(2), 0.5 * p.sway_m, 2.0 * p.sway_m / 0.05])
    return (wave(np.asarray(s, dtype=np.float64)) - mu) / sd * scale


def spin_trajectory(scene: Scene, n_frames: int, seed: int = 0, turn_deg: float = 380.0,
                    fps: float = 30.0, sway_m: float = 0.0, arm_m: float | None = None, tremor_deg: float = 0.0
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (R_wc (F, 3, 3), centres (F, 3), timestamps (F,)) of a person's spin at ``fps``.

    Ground-truth poses of a synthetic capture of the paper's input (§3: a
    person turns once around holding the phone, so the camera centre moves on
    a small circle): world_from_camera rotations, camera centres in metres,
    timestamps ``i / fps`` seconds.
    """
    p = spin_params(scene, n_frames, seed, turn_deg, fps, sway_m, arm_m, tremor_deg)
    ts = np.arange(n_frames, dtype=np.float64) / float(fps)
    R, c = spin_pose(p, ts)
    return R, c, ts


def imu_stream(scene: Scene, n_frames: int, seed: int = 0, turn_deg: float = 380.0, fps: float = 30.0,
               imu_drift_deg: float = 3.0, noise_deg: float = 0.1, rate_hz: float = 100.0, sway_m: float = 0.0,
               arm_m: float | None = None, tremor_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Returns (timestamps (N,), R_wc (N, 3, 3)): the drifting IMU attitude at ``rate_hz`` of the scene's spin
    (:func:`imu_attitude`)."""
    p = spin_params(scene, n_frames, seed, turn_deg, fps, sway_m, arm_m, tremor_deg)
    return imu_attitude(p, n_frames, fps, seed, imu_drift_deg, noise_deg, rate_hz)


def imu_attitude(p: SpinParams, n_frames: int, fps: float = 30.0, seed: int = 0, imu_drift_deg: float = 3.0,
                 noise_deg: float = 0.1, rate_hz: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """Returns (timestamps (N,), R_wc (N, 3, 3)): the IMU attitude of spin ``p`` at ``rate_hz``.

    Attitude = Rz(drift(t)) @ R_wc_true(t) @ noise, with drift growing
    linearly from 0 at the first frame to ``imu_drift_deg`` at the last frame
    and white rotation noise of ``noise_deg`` RMS angle. The stream starts
    0.05 s before the first frame and ends at least 0.05 s after the last.
    """
    t_last = (n_frames - 1) / float(fps)
    dt = 1.0 / rate_hz
    ts = np.arange(-0.05, t_last + 0.05 + dt, dt)
    R_true, _ = spin_pose(p, ts)
    drift = np.radians(imu_drift_deg) * ts / p.duration_s
    R_drift = Rotation.from_euler("z", drift[:, None]).as_matrix()
    rng = np.random.default_rng([int(seed), 777])
    rotvec = rng.normal(0.0, np.radians(noise_deg) / np.sqrt(3.0), (len(ts), 3))
    R_noise = Rotation.from_rotvec(rotvec).as_matrix()
    return ts, R_drift @ R_true @ R_noise
