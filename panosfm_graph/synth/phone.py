"""A synthetic capture re-expressed as a phone recording: a video and raw gyroscope / accelerometer logs.

:func:`phone_recording` reads a capture written by :func:`~.writer.synthesize`
and writes what a phone would give for the same motion (the input of
``panosfm import``, issue #41 item 4):

    <out>/video.mp4         the capture's frames, encoded at its frame rate
    <out>/sensors/gyro.csv  timestamp_s,x,y,z  rad/s    (generic layout, docs/import.md)
    <out>/sensors/accel.csv timestamp_s,x,y,z  m/s², gravity included
    <out>/truth.json        time offset, camera_from_device, gyroscope bias

The samples come from the spin's true continuous motion
(:func:`~.trajectory.spin_pose`, differentiated numerically): the
gyroscope measures the body rate, the accelerometer the specific force
``R^T (a + g z)``, both in the phone's axes (a landscape phone's,
:data:`LANDSCAPE_CAMERA_FROM_DEVICE`), with white noise and a constant
gyroscope bias. The sensor clock runs ``offset_s`` ahead of the video's and
starts ``lead_s`` early, the phone held still until the spin begins (a ramp
of ``RAMP_S``), as when one starts the logger and then the camera.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from .scenes import make_scene
from .trajectory import spin_params, spin_pose
from .writer import atomic_capture_dir

G = 9.80665
RAMP_S = 0.5  # the spin accelerates from rest over this long before the video starts
# A phone in landscape (top to the left, as the camera looks): device x = camera -y, device y = camera -x,
# device z (out of the screen) = camera -z (the back camera looks away from the screen).
LANDSCAPE_CAMERA_FROM_DEVICE = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def _video_time(t: np.ndarray) -> np.ndarray:
    """Returns the spin's time at video time ``t``: ``t`` from 0 on; before, a ramp from rest (C1 at 0)."""
    t = np.asarray(t, dtype=np.float64)
    u = np.clip(t + RAMP_S, 0.0, RAMP_S)
    return np.where(t >= 0, t, u * u / (2 * RAMP_S) - RAMP_S / 2)


def true_motion(p, t: np.ndarray, h: float = 1e-3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (R_wc (N, 3, 3), body rate in the camera frame (N, 3) rad/s, specific force in the camera frame
    (N, 3) m/s²) of spin ``p`` at video times ``t`` (central differences with step ``h``)."""
    R0, c0 = spin_pose(p, _video_time(t))
    Rm, cm = spin_pose(p, _video_time(t - h))
    Rp, cp = spin_pose(p, _video_time(t + h))
    omega = Rotation.from_matrix(np.einsum("nji,njk->nik", Rm, Rp)).as_rotvec() / (2 * h)
    acc = (cp - 2 * c0 + cm) / (h * h)
    f_world = acc + np.array([0.0, 0.0, G])
    return R0, omega, np.einsum("nji,nj->ni", R0, f_world)


def phone_recording(capture: str | Path, out: str | Path, offset_s: float = 0.237, rate_hz: float = 200.0,
                    lead_s: float = 1.5, tail_s: float = 0.5, gyro_noise: float = 0.002, accel_noise: float = 0.05,
                    gyro_bias=(0.003, -0.002, 0.002), seed: int = 0,
                    camera_from_device: np.ndarray = LANDSCAPE_CAMERA_FROM_DEVICE) -> Path:
    """Writes the phone recording (video + raw sensor logs) of synthetic ``capture`` to ``out``; returns ``out``.

    ``gyro_noise`` rad/s and ``accel_noise`` m/s² per sample (white),
    ``gyro_bias`` rad/s (constant, device axes); ``offset_s``: sensor clock
    minus video clock.
    """
    capture, out = Path(capture), Path(out)
    meta_path = capture / "ground_truth" / "synth.json"
    if not meta_path.is_file():
        raise InputError("not a synthetic capture (no ground_truth/synth.json)", capture)
    meta = json.loads(meta_path.read_text())
    if meta.get("generator") != "panosfm_graph.synth" or "scene" not in meta:
        raise InputError("only box-room captures of panosfm synth can be re-expressed", meta_path)
    if out.exists() and any(out.iterdir()):
        raise InputError("exists and is not empty", out)
    fps, n = float(meta["fps"]), int(meta["n_frames"])
    p = spin_params(make_scene(meta["scene"], int(meta["seed"])), n, int(meta["seed"]), float(meta["turn_deg"]), fps,
                    float(meta.get("sway_m", 0.0)), meta.get("arm_m"), float(meta.get("tremor_deg", 0.0)))
    rng = np.random.default_rng([int(seed), 777])
    t_video_end = (n - 1) / fps
    t_sensor = np.arange(offset_s - lead_s, offset_s + t_video_end + tail_s, 1.0 / rate_hz)
    _, omega_c, f_c = true_motion(p, t_sensor - offset_s)
    R_dc = np.asarray(camera_from_device).T
    gyro = omega_c @ R_dc.T + np.asarray(gyro_bias) + rng.normal(0, gyro_noise, omega_c.shape)
    accel = f_c @ R_dc.T + rng.normal(0, accel_noise, f_c.shape)
    frames = sorted((capture / "frames").iterdir())
    with atomic_capture_dir(out) as tmp:
        (tmp / "sensors").mkdir()
        first = cv2.imread(str(frames[0]))
        writer = cv2.VideoWriter(str(tmp / "video.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                 (first.shape[1], first.shape[0]))
        if not writer.isOpened():
            raise InputError("OpenCV cannot write an mp4v video here", out / "video.mp4")
        try:
            for f in frames:
                writer.write(cv2.imread(str(f)))
        finally:
            writer.release()
        for name, v in (("gyro.csv", gyro), ("accel.csv", accel)):
            rows = "".join(f"{t:.6f},{x:.7g},{y:.7g},{z:.7g}\n" for t, (x, y, z) in zip(t_sensor, v))
            (tmp / "sensors" / name).write_text("timestamp_s,x,y,z\n" + rows)
        (tmp / "truth.json").write_text(json.dumps(
            {"capture": str(capture), "offset_s": offset_s,
             "camera_from_device": np.asarray(camera_from_device).tolist(),
             "gyro_bias_rad_s": list(map(float, gyro_bias)), "rate_hz": rate_hz}, indent=1) + "\n")
    return out
