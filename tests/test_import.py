"""panosfm import: a synthetic capture re-expressed as a phone video + raw gyroscope/accelerometer, imported back.

The phone recording's samples come from the spin's true motion with noise, a
gyroscope bias, a landscape phone's axes and a known time offset
(``synth.phone_recording``); the import must find them and the attitude.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from panosfm_graph.capture import load_capture, read_imu
from panosfm_graph.cli import FORMAT_CHOICES, main
from panosfm_graph.errors import InputError
from panosfm_graph.geometry import heading_aligned_errors_deg, rotation_angle_deg
from panosfm_graph.phone import FORMATS, import_capture, read_sensors
from panosfm_graph.synth import phone_recording, spin_params, spin_pose, synthesize
from panosfm_graph.synth.phone import LANDSCAPE_CAMERA_FROM_DEVICE
from panosfm_graph.synth.scenes import make_scene

N, SIZE, OFFSET = 120, (480, 270), 0.237


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    root = tmp_path_factory.mktemp("phone")
    cap = synthesize(root / "capture", n_frames=N, size=SIZE, seed=1, gt_maps=False, tremor_deg=0.2)
    rec = phone_recording(cap, root / "phone", offset_s=OFFSET, seed=1)
    return cap, rec


@pytest.fixture(scope="module")
def imported(recording, tmp_path_factory):
    cap, rec = recording
    out = tmp_path_factory.mktemp("imported") / "capture"
    return import_capture(rec / "video.mp4", rec / "sensors", out)


def test_import_finds_offset_axes_bias_and_attitude(recording, imported):
    cap, rec = recording
    truth = json.loads((rec / "truth.json").read_text())
    assert abs(imported.sync.offset_s - OFFSET) < 0.005
    # the hand's tremor times it, far inside the 5 ms, with a sigma that says so (not loose: no line timing)
    assert imported.sync.band == "tremor" and imported.line_timing is None
    assert abs(imported.sync.offset_s - OFFSET) < 0.001 and imported.sync.offset_sigma_s < 0.001
    assert imported.sync.axes_snapped
    np.testing.assert_array_equal(imported.sync.camera_from_device, LANDSCAPE_CAMERA_FROM_DEVICE)
    np.testing.assert_allclose(imported.attitude.gyro_bias, truth["gyro_bias_rad_s"], atol=3e-4)
    t, R_imu = read_imu(imported.path / "imu.csv")
    gt = load_capture(cap).ground_truth
    err = heading_aligned_errors_deg(R_imu, gt.R_wc)
    assert np.median(err) < 0.5 and err.max() < 1.0, (np.median(err), err.max())


def test_imported_capture_loads_with_unknown_focal(imported):
    cap = load_capture(imported.path)
    assert cap.n_frames == N and not cap.focal_given
    assert (cap.camera.width, cap.camera.height) == SIZE
    report = json.loads((imported.path / "import.json").read_text())
    assert abs(report["time_offset_s"] - OFFSET) < 0.005
    assert report["turns_band"] == "tremor" and report["tremor_share"] > 0.5 and not report["warnings"]


def test_import_without_tremor_or_lever_fit_is_worse_but_sound(recording, tmp_path):
    """The lever-arm fit matters on a fast turn: without it the tilt is several tenths of a degree worse."""
    from panosfm_graph.phone.attitude import smooth_attitude

    cap, rec = recording
    sensors = read_sensors(rec / "sensors")
    t = np.arange(N) / 30.0 + OFFSET
    gt = load_capture(cap).ground_truth
    e_fit = np.median(heading_aligned_errors_deg(
        smooth_attitude(sensors, t, LANDSCAPE_CAMERA_FROM_DEVICE).R_wc, gt.R_wc))
    e_raw = np.median(heading_aligned_errors_deg(
        smooth_attitude(sensors, t, LANDSCAPE_CAMERA_FROM_DEVICE, lever_arm=False).R_wc, gt.R_wc))
    assert e_fit < e_raw


def test_tremor_has_its_rms_and_zero_leaves_the_spin():
    sc = make_scene("living", 0)
    t = np.linspace(0, 10, 3001)
    R0, c0 = spin_pose(spin_params(sc, 300, 0), t)
    R1, c1 = spin_pose(spin_params(sc, 300, 0, tremor_deg=0.3), t)
    np.testing.assert_array_equal(c0, c1)
    ang = rotation_angle_deg(R0, R1)
    assert 0.2 < np.sqrt(np.mean(ang ** 2)) < 0.4


def _write(path: Path, header: str, t: np.ndarray, v: np.ndarray) -> None:
    path.write_text(header + "\n" + "".join(
        f"{float(a)!r},{float(x)!r},{float(y)!r},{float(z)!r}\n" for a, (x, y, z) in zip(t, v)))


def test_sensor_logger_and_phyphox_layouts_read_the_same(recording, tmp_path):
    _, rec = recording
    ref = read_sensors(rec / "sensors")
    # Sensor Logger (iOS): time in ns since the epoch, columns z,y,x, gravity pointing down
    sl = tmp_path / "sl"
    sl.mkdir()
    epoch = 1_700_000_000_000_000_000
    for name, t, v in (("Gyroscope.csv", ref.t_gyro, ref.gyro), ("Gravity.csv", ref.t_up, -ref.up)):
        ns = epoch + np.round((t - ref.t_gyro[0]) * 1e9).astype(np.int64)
        (sl / name).write_text("time,seconds_elapsed,z,y,x\n" + "".join(
            f"{n},{float(n - epoch) * 1e-9!r},{float(z)!r},{float(y)!r},{float(x)!r}\n" for n, (x, y, z) in zip(ns, v)))
    (sl / "metadata.csv").write_text("version,device name,recording time,platform\n3,phone,2026-12-06,ios\n")
    got = read_sensors(sl)
    assert got.source.startswith("sensor-logger (ios)")
    np.testing.assert_allclose(got.gyro, ref.gyro)
    np.testing.assert_allclose(got.up, ref.up)
    np.testing.assert_allclose(got.t_gyro, ref.t_gyro - ref.t_gyro[0], atol=1e-6)
    assert got.epoch_s == pytest.approx(epoch * 1e-9)
    # zipped, too
    shutil.make_archive(str(tmp_path / "sl"), "zip", sl)
    np.testing.assert_allclose(read_sensors(tmp_path / "sl.zip").gyro, ref.gyro)
    # phyphox
    ph = tmp_path / "ph"
    ph.mkdir()
    _write(ph / "Gyroscope.csv", '"Time (s)","Gyroscope x (rad/s)","Gyroscope y (rad/s)","Gyroscope z (rad/s)"',
           ref.t_gyro, ref.gyro)
    _write(ph / "Accelerometer.csv", '"Time (s)","Acceleration x (m/s^2)","Acceleration y (m/s^2)",'
                                     '"Acceleration z (m/s^2)"', ref.t_up, ref.up)
    got = read_sensors(ph)
    assert got.source.startswith("phyphox")
    np.testing.assert_allclose(got.gyro, ref.gyro)
    np.testing.assert_allclose(got.up, ref.up)
    assert FORMATS == FORMAT_CHOICES


def _broken_log(rec: Path, dst: Path, fn) -> Path:
    shutil.copytree(rec / "sensors", dst)
    for name in ("gyro.csv", "accel.csv"):
        lines = (dst / name).read_text().splitlines()
        header, rows = lines[0], np.array([[float(c) for c in r.split(",")] for r in lines[1:]])
        rows = fn(name, rows)
        (dst / name).write_text(header + "\n" + "".join(",".join(repr(float(c)) for c in r) + "\n" for r in rows))
    return dst


BAD_LOGS = {
    "deg/s": (lambda n, r: np.column_stack([r[:, 0], np.degrees(r[:, 1:])]) if n == "gyro.csv" else r, "deg/s"),
    "in g": (lambda n, r: np.column_stack([r[:, 0], r[:, 1:] / 9.80665]) if n == "accel.csv" else r, "in g"),
    "unsorted": (lambda n, r: r[np.r_[0:50, 51, 50, 52:len(r)]] if n == "gyro.csv" else r, "must increase"),
    "gap": (lambda n, r: np.delete(r, np.s_[300:360], axis=0) if n == "gyro.csv" else r, "gap of"),
    "short": (lambda n, r: r[: len(r) // 2], "does not cover"),
    "nan": (lambda n, r: np.where(np.arange(len(r))[:, None] == 7, np.nan, r) if n == "accel.csv" else r, "line 9"),
}


@pytest.mark.parametrize("kind", list(BAD_LOGS))
def test_bad_sensor_logs_give_one_line_and_exit_2(recording, tmp_path, capsys, kind):
    _, rec = recording
    fn, needle = BAD_LOGS[kind]
    log_dir = _broken_log(rec, tmp_path / "sensors", fn)
    out = tmp_path / "out"
    assert main(["import", str(rec / "video.mp4"), str(log_dir), str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err, err
    assert not out.exists()


def test_import_cli_refuses_missing_files_and_a_full_out(recording, tmp_path, capsys):
    _, rec = recording
    full, odd = tmp_path / "full", tmp_path / "odd"
    full.mkdir()
    odd.mkdir()
    (odd / "readings.csv").write_text("t,a\n0,1\n")
    (full / "keep.txt").write_text("mine")
    for args in ([str(rec / "video.mp4"), str(rec / "sensors"), str(full)],
                 [str(tmp_path / "none.mp4"), str(rec / "sensors"), str(tmp_path / "o1")],
                 [str(rec / "video.mp4"), str(tmp_path / "nolog"), str(tmp_path / "o2")],
                 [str(rec / "video.mp4"), str(odd), str(tmp_path / "o3")]):  # no sensor log layout there
        assert main(["import", *args]) == 2
        assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert (full / "keep.txt").read_text() == "mine" and len(list(full.iterdir())) == 1
    with pytest.raises(InputError, match="not both"):
        import_capture(rec / "video.mp4", rec / "sensors", tmp_path / "o4", focal_px=500.0, hfov_deg=60.0)


def test_synth_phone_cli_writes_a_recording_that_imports(tmp_path, capsys):
    cap, phone, out = tmp_path / "c", tmp_path / "p", tmp_path / "i"
    assert main(["synth", str(cap), "--frames", "60", "--size", "320x180", "--tremor", "0.2", "--no-gt-maps",
                 "--phone", str(phone), "--seed", "2"]) == 0
    assert (phone / "video.mp4").is_file() and (phone / "sensors" / "gyro.csv").is_file()
    assert main(["import", str(phone / "video.mp4"), str(phone / "sensors"), str(out), "--hfov", "64"]) == 0
    report = capsys.readouterr().out
    assert "time offset" in report and "camera axes" in report
    cam = json.loads((out / "camera.json").read_text())
    assert cam["params"][0] == pytest.approx(0.5 * 320 / np.tan(np.radians(32)))


def test_a_perfectly_steady_turn_leaves_the_offset_loose_and_says_so():
    """A constant turn rate looks the same at every offset: the fit must report that, not a precise offset."""
    from panosfm_graph.phone import RawSensors, estimate_sync

    rng = np.random.default_rng(0)
    t = np.arange(0.0, 12.0, 0.005)
    gyro = np.tile([0.0, 0.0, 0.6], (len(t), 1)) + rng.normal(0, 1e-3, (len(t), 3))
    sensors = RawSensors(t, gyro, t, np.tile([9.81, 0.0, 0.0], (len(t), 1)), "test")
    tf = np.arange(240) / 30.0 + 1.0
    theta = np.tile(LANDSCAPE_CAMERA_FROM_DEVICE @ [0.0, 0.0, 0.6 / 30.0], (239, 1)) + rng.normal(0, 1e-4, (239, 3))
    sync = estimate_sync(tf, theta, sensors, guess_s=0.0, max_offset_s=0.5)
    assert sync.offset_sigma_s > 0.005
