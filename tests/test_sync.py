"""The video's time offset and the camera's axes from the images' turns (phone/sync.py): the phone's axes tried
first, and the tremor band timing a trembling spin past the smooth errors of the turns."""
from __future__ import annotations

import numpy as np
import pytest

from panosfm_graph.phone import RawSensors, estimate_sync
from panosfm_graph.phone import sync as sync_mod
from panosfm_graph.phone.sync import gyro_orientation, gyro_turns, high_pass, score_sigma
from panosfm_graph.synth.phone import LANDSCAPE_CAMERA_FROM_DEVICE

OFFSET, FPS = 0.137, 30.0


def _spin(tremor_rad: float, seed: int = 0):
    """A 12 s spin's gyroscope (200 Hz) and its video's turns (30 fps), the latter with a smooth error as large as
    the wobble's turn (what parallax does) and white noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 12.0, 0.005)
    gyro = np.zeros((len(t), 3))
    gyro[:, 2] = 0.6
    for ax, (f, a) in enumerate([(0.31, 0.05), (0.23, 0.04)]):  # the slow wobble in two axes
        gyro[:, ax] += a * np.sin(2 * np.pi * f * t + ax)
    for ax in range(3):  # the hand's tremor: a few sinusoids at 3-7 Hz
        for f in rng.uniform(3.0, 7.0, 3):
            gyro[:, ax] += tremor_rad * 2 * np.pi * f * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    sensors = RawSensors(t, gyro + rng.normal(0.0, 2e-3, gyro.shape), t, np.tile([9.81, 0.0, 0.0], (len(t), 1)),
                         "test")  # the sensor's noise is not the camera's motion
    tf = np.arange(300) / FPS + 1.0
    Q = gyro_orientation(t, gyro)
    theta = gyro_turns(Q, tf[:-1] + OFFSET, tf[1:] + OFFSET) @ LANDSCAPE_CAMERA_FROM_DEVICE.T
    theta[:, 0] += 1.5e-3 * np.sin(2 * np.pi * 0.27 * tf[:-1])  # smooth, off the spin axis
    theta[:, 1] += 1.0e-3 * np.cos(2 * np.pi * 0.19 * tf[:-1])
    theta += rng.normal(0.0, 1e-4, theta.shape)
    return tf, theta, sensors


def test_the_tremor_band_times_past_the_smooth_errors(monkeypatch):
    tf, theta, sensors = _spin(tremor_rad=np.radians(0.05))
    sync = estimate_sync(tf, theta, sensors, max_offset_s=0.5, camera_from_device=LANDSCAPE_CAMERA_FROM_DEVICE)
    assert sync.band == "tremor" and sync.tremor_share > 0.9
    err = abs(sync.offset_s - OFFSET)
    assert err < 3e-4 and err < 4 * sync.offset_sigma_s + 1e-5, (err, sync.offset_sigma_s)
    monkeypatch.setattr(sync_mod, "MIN_TREMOR_SHARE", 2.0)  # the whole band alone, as before
    whole = estimate_sync(tf, theta, sensors, max_offset_s=0.5, camera_from_device=LANDSCAPE_CAMERA_FROM_DEVICE)
    assert whole.band == "full" and abs(whole.offset_s - OFFSET) > 5 * err, (whole.offset_s, sync.offset_s)
    # ... and the smooth errors make the whole band's sigma say "loose" (over the 5 ms that starts the line timing)
    assert whole.offset_sigma_s > 0.005 > 50 * sync.offset_sigma_s


def test_a_spin_without_tremor_keeps_the_whole_band():
    tf, theta, sensors = _spin(tremor_rad=0.0)
    sync = estimate_sync(tf, theta, sensors, max_offset_s=0.5, camera_from_device=LANDSCAPE_CAMERA_FROM_DEVICE)
    assert sync.band == "full" and sync.tremor_share < sync_mod.MIN_TREMOR_SHARE


def test_high_pass_removes_slow_signals_and_skips_gaps():
    idx = np.delete(np.arange(200), [50, 51, 120])
    slow = np.column_stack([np.linspace(0, 1, 200), np.full(200, 3.0)])[idx]
    out = high_pass(slow, idx, 9)
    assert np.abs(out[:, 1]).max() < 1e-12  # a constant, gaps and ends included
    assert np.abs(out[10:40, 0]).max() < 1e-12  # a line less its centred mean, away from the gaps and ends
    fast = np.column_stack([np.cos(np.pi * np.arange(200)), np.zeros(200)])[idx]  # alternating: kept
    assert np.abs(high_pass(fast, idx, 9)[20:40, 0]).min() > 0.8


@pytest.mark.parametrize("smooth", [False, True])
def test_score_sigma_matches_the_scatter_of_fitted_offsets(smooth):
    """Many least-squares offsets r = J * (o - o_true) + e: the score sigma predicts their scatter; smooth residuals
    against a white J are worth as much as white ones (independent_samples would count them as few)."""
    rng = np.random.default_rng(3)
    N, trials = 400, 300
    J = rng.normal(0.0, 1.0, (N, 2))
    est, sig = [], []
    for _ in range(trials):
        e = rng.normal(0.0, 0.1, (N + 20, 2))
        if smooth:
            e = np.cumsum(e, axis=0)[20:] * 0.1 - np.cumsum(e, axis=0)[:-20] * 0.1  # a 20-sample moving sum
        else:
            e = e[:N]
        o = -np.sum(J * e) / np.sum(J * J)  # the least-squares offset (truth 0)
        est.append(o)
        sig.append(score_sigma(e + J * o, J))
    ratio = np.std(est) / np.median(sig)
    assert 0.8 < ratio < 1.25, ratio


def test_the_phones_axes_are_tried_before_a_free_rotation(tmp_path):
    """A fast, smooth spin in a bare room: the free rotation's best offset was 332 ms off with axes 30+ deg off the
    phone's (kept unsnapped); the best of the 24 axis permutations finds the axes and an offset near the truth."""
    from panosfm_graph.capture.camera import focal_from_hfov
    from panosfm_graph.phone import frame_rotations, read_sensors
    from panosfm_graph.synth import phone_recording, synthesize

    cap = synthesize(tmp_path / "capture", scene="bare", n_frames=90, size=(480, 270), seed=9, gt_maps=False)
    rec = phone_recording(cap, tmp_path / "phone", offset_s=0.237, seed=9)
    f = focal_from_hfov(65.0, 480)
    theta = frame_rotations(rec / "video.mp4", np.array([[f, 0.0, 239.5], [0.0, f, 134.5], [0.0, 0.0, 1.0]]))
    sync = estimate_sync(np.arange(90) / 30.0, theta, read_sensors(rec / "sensors"))
    assert sync.axes_snapped
    np.testing.assert_array_equal(sync.camera_from_device, LANDSCAPE_CAMERA_FROM_DEVICE)
    assert abs(sync.offset_s - 0.237) < 0.06 and abs(sync.offset_s - 0.237) < 3 * sync.offset_sigma_s
