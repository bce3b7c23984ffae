"""The time offset from the lines' rotations (``phone/line_timing.py``): a smooth spin the images' turns cannot time.

The cost is checked on the spin's true rotations and gyroscope (no images),
then the whole import on a rendered spin without tremor, against the
recording's known offset.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from panosfm_graph.capture import load_capture, read_imu
from panosfm_graph.cli import main
from panosfm_graph.geometry import heading_aligned_errors_deg
from panosfm_graph.phone import import_capture, read_sensors
from panosfm_graph.phone.line_timing import OffsetCost, axis_weights, line_offset
from panosfm_graph.phone.sync import covering_offsets, gyro_orientation, independent_samples
from panosfm_graph.synth import phone_recording, spin_params, spin_pose, synthesize
from panosfm_graph.synth.phone import LANDSCAPE_CAMERA_FROM_DEVICE, true_motion
from panosfm_graph.synth.scenes import make_scene

OFFSET = 0.237
C = LANDSCAPE_CAMERA_FROM_DEVICE


def _true_gyro(n_frames: int = 300, seed: int = 0):
    """Returns (spin params, frame times, gyroscope Slerp on the sensor clock) of a smooth spin, noise-free."""
    p = spin_params(make_scene("living", seed), n_frames, seed)
    t_frames = np.arange(n_frames) / 30.0
    tau = np.arange(-1.0 + OFFSET, t_frames[-1] + 1.0 + OFFSET, 0.005)  # sensor clock
    _, omega_cam, _ = true_motion(p, tau - OFFSET)
    return p, t_frames, tau, gyro_orientation(tau, omega_cam @ C)  # omega_device = C^T omega_camera


def test_offset_cost_times_the_true_rotations_and_a_shifted_copy():
    p, t, tau, Q = _true_gyro()
    lo, hi = tau[0] - t[0], tau[-1] - t[-1]
    R_true = spin_pose(p, t)[0]
    o, sigma = line_offset(OffsetCost(R_true, np.ones((len(t), 3)), Q, C, t), lo, hi)
    assert abs(o - OFFSET) < 0.002 and sigma < 0.005, (o, sigma)
    # rotations 40 ms late on the video's clock: the sensor clock is 40 ms less ahead
    R_late = spin_pose(p, t - 0.04)[0]
    o_late, _ = line_offset(OffsetCost(R_late, np.ones((len(t), 3)), Q, C, t), lo, hi)
    assert abs(o_late - (OFFSET - 0.04)) < 0.002, o_late


def test_frames_without_lines_do_not_count():
    p, t, tau, Q = _true_gyro()
    lo, hi = tau[0] - t[0], tau[-1] - t[-1]
    R = spin_pose(p, t)[0].copy()
    weights = np.ones((len(t), 3))
    rng = np.random.default_rng(0)
    bad = rng.random(len(t)) < 0.3
    R[bad] = spin_pose(p, t[bad] + rng.uniform(-0.5, 0.5, bad.sum()))[0]  # wildly mistimed
    weights[bad] = 0.0
    o, _ = line_offset(OffsetCost(R, weights, Q, C, t), lo, hi)
    assert abs(o - OFFSET) < 0.002, o


def test_axis_weights_count_the_segments_that_fix_each_axis():
    class Seg:
        frame = np.array([0, 0, 0, 1, 1, 2])

    labels = np.array([0, 1, 2, 2, 2, -1])  # frame 0: two horizontal, one vertical; frame 1: two vertical
    w = axis_weights(Seg(), labels, 3)
    np.testing.assert_allclose(w[0], [0.5, 0.5, 0.6])
    np.testing.assert_allclose(w[1], [0.0, 0.0, 0.5])
    np.testing.assert_allclose(w[2], [0.0, 0.0, 0.0])


def test_independent_samples_counts_smooth_errors_as_few():
    rng = np.random.default_rng(1)
    white = rng.normal(size=(600, 2))
    assert 450 < independent_samples(white) <= 600
    smooth = np.stack([np.convolve(white[:, j], np.ones(30) / 30, mode="same") for j in range(2)], axis=1)
    assert independent_samples(smooth) < 60


@pytest.fixture(scope="module")
def smooth_recording(tmp_path_factory):
    root = tmp_path_factory.mktemp("smooth")
    cap = synthesize(root / "capture", n_frames=120, size=(480, 270), seed=2, gt_maps=False)  # no tremor
    return cap, phone_recording(cap, root / "phone", offset_s=OFFSET, seed=2)


def _attitude_error(imported_dir, cap) -> float:
    _, R = read_imu(imported_dir / "imu.csv")
    return float(np.median(heading_aligned_errors_deg(R, load_capture(cap).ground_truth.R_wc)))


def test_a_smooth_spin_is_timed_by_its_lines(smooth_recording, tmp_path):
    cap, rec = smooth_recording
    res = import_capture(rec / "video.mp4", rec / "sensors", tmp_path / "lines")
    turns = import_capture(rec / "video.mp4", rec / "sensors", tmp_path / "turns", line_timing=False)
    assert turns.sync.offset_sigma_s > 0.005 and turns.line_timing is None  # the turns leave it loose
    assert turns.sync.band == "full"  # no tremor to time it by
    lt = res.line_timing
    assert lt is not None and len(lt.offsets_s) == 3
    err = abs(res.offset_s - OFFSET)
    assert err < 0.015 and err < 3 * lt.offset_sigma_s, (res.offset_s, lt.offset_sigma_s)
    assert err < abs(turns.offset_s - OFFSET)
    assert _attitude_error(res.path, cap) < _attitude_error(turns.path, cap)
    report = json.loads((res.path / "import.json").read_text())
    assert report["time_offset_from"] == "lines' rotations" and report["line_timing"]["used"]
    assert report["time_offset_s"] == pytest.approx(res.offset_s)
    assert report["turns_time_offset_s"] == pytest.approx(turns.offset_s)
    lo, hi = covering_offsets(np.arange(120) / 30.0, read_sensors(rec / "sensors"))
    assert lo <= res.offset_s <= hi


def test_import_cli_can_skip_the_line_timing(smooth_recording, tmp_path, capsys):
    _, rec = smooth_recording
    assert main(["import", str(rec / "video.mp4"), str(rec / "sensors"), str(tmp_path / "c"), "--no-line-timing"]) == 0
    out = capsys.readouterr().out
    assert "from the images' turns" in out and "loose" in out
    assert json.loads((tmp_path / "c" / "import.json").read_text())["line_timing"] is None


def test_snapped_axes_search_the_offset_again(smooth_recording):
    """A free rotation absorbs part of a smooth spin's timing error: once the axes snap to the phone's, the
    offset is searched with them fixed, as if they had been given."""
    from panosfm_graph.capture.camera import focal_from_hfov
    from panosfm_graph.phone import estimate_sync, frame_rotations

    _, rec = smooth_recording
    f = focal_from_hfov(65.0, 480)
    theta = frame_rotations(rec / "video.mp4", np.array([[f, 0.0, 239.5], [0.0, f, 134.5], [0.0, 0.0, 1.0]]))
    t = np.arange(len(theta) + 1) / 30.0
    sensors = read_sensors(rec / "sensors")
    free = estimate_sync(t, theta, sensors)
    given = estimate_sync(t, theta, sensors, camera_from_device=C)
    assert free.axes_snapped
    np.testing.assert_array_equal(free.camera_from_device, C)
    assert free.offset_s == pytest.approx(given.offset_s, abs=1e-6)


def test_looser_lines_leave_the_turns_offset_written(tmp_path):
    """A bare room's few lines time its smooth spin more loosely than the turns do: the turns' offset is written,
    the lines' attempt reported beside it."""
    cap = synthesize(tmp_path / "capture", scene="bare", n_frames=90, size=(480, 270), seed=3, gt_maps=False)
    rec = phone_recording(cap, tmp_path / "phone", offset_s=OFFSET, seed=3)
    res = import_capture(rec / "video.mp4", rec / "sensors", tmp_path / "imported")
    report = json.loads((res.path / "import.json").read_text())
    tried = report["line_timing"]
    assert tried is not None and not tried["used"] and tried["offset_sigma_s"] > res.sync.offset_sigma_s
    assert res.line_timing is None and res.offset_s == res.sync.offset_s == report["time_offset_s"]
    assert report["time_offset_from"] == "images' turns"
    assert any("loose" in w for w in res.warnings)


def test_timings_that_disagree_are_warned_about():
    from panosfm_graph.phone.importer import timings_disagree

    # office seed 7 swaying without tremor: the turns -56.7 +- 22.6 ms off, the lines +44.6 +- 13.3 ms
    msg = timings_disagree(0.237 - 0.0567, 0.0226, 0.237 + 0.0446, 0.0133)
    assert msg is not None and "101 ms apart" in msg and "3.9 sigma" in msg
    assert timings_disagree(0.285, 0.028, 0.256, 0.010) is None  # living seed 1: 1 sigma apart
    assert timings_disagree(0.3, float("inf"), 0.24, 0.01) is None  # a loose turns' offset says nothing
