"""Capture reader (capture-format.md): bad input, IMU slerp, frame selection, video, distortion, inspect."""
from __future__ import annotations

import json
import pickle
import shutil

import cv2
import numpy as np
import pytest

from panosfm_graph.capture import (distort_points, format_inspection, inspect_capture, load_capture,
                                   undistort_points)
from panosfm_graph.config import CaptureConfig
from panosfm_graph.data import Camera
from panosfm_graph.errors import InputError
from panosfm_graph.geometry import rotation_angle_deg


def _edit_json(path, **changes):
    data = json.loads(path.read_text())
    for k, v in changes.items():
        if v is None:
            data.pop(k, None)
        else:
            data[k] = v
    path.write_text(json.dumps(data))


def _imu_lines(root):
    return (root / "imu.csv").read_text().splitlines()


def _set_imu(root, lines):
    (root / "imu.csv").write_text("\n".join(lines) + "\n")


def _set_imu_row(root, k, row):
    lines = _imu_lines(root)
    lines[k] = row
    _set_imu(root, lines)


def _bad_png(root):
    (root / "frames" / "000002.png").write_bytes(b"this is not an image")


def _small_frame(root):
    p = root / "frames" / "000001.png"
    cv2.imwrite(str(p), cv2.resize(cv2.imread(str(p)), (80, 60)))


def _frames_csv_edit(root, fn):
    lines = (root / "frames.csv").read_text().splitlines()
    (root / "frames.csv").write_text("\n".join(fn(lines)) + "\n")


# (name, capture kwargs, mutation, the file the message must name, a word the message must hold)
BAD_CASES = [
    ("no camera.json", {}, lambda r: (r / "camera.json").unlink(), "camera.json", "missing"),
    ("no imu.csv", {}, lambda r: (r / "imu.csv").unlink(), "imu.csv", "missing"),
    ("camera.json not json", {}, lambda r: (r / "camera.json").write_text("{model: PINHOLE"), "camera.json", "JSON"),
    ("unknown model", {}, lambda r: _edit_json(r / "camera.json", model="FISHEYE"), "camera.json", "FISHEYE"),
    ("param count", {}, lambda r: _edit_json(r / "camera.json", params=[100, 100, 80]), "camera.json", "4 params"),
    ("param count opencv", {"model": "OPENCV"},
     lambda r: _edit_json(r / "camera.json", params=[100, 100, 80, 60]), "camera.json", "8 params"),
    ("negative focal", {}, lambda r: _edit_json(r / "camera.json", params=[-100, 100, 80, 60]), "camera.json",
     "positive"),
    ("zero cx", {"model": "SIMPLE_PINHOLE"}, lambda r: _edit_json(r / "camera.json", params=[100, 0, 60]),
     "camera.json", "positive"),
    ("nan focal", {}, lambda r: (r / "camera.json").write_text(
        '{"model": "PINHOLE", "width": 160, "height": 120, "params": [NaN, 96, 79.5, 59.5]}'), "camera.json",
     "finite"),
    ("no width", {}, lambda r: _edit_json(r / "camera.json", width=None), "camera.json", "width"),
    ("no height", {}, lambda r: _edit_json(r / "camera.json", height=None), "camera.json", "height"),
    ("bad fps", {}, lambda r: _edit_json(r / "camera.json", fps=-3), "camera.json", "fps"),
    ("empty frames", {}, lambda r: [p.unlink() for p in (r / "frames").iterdir()], "frames", "no PNG"),
    ("no frames no video", {}, lambda r: shutil.rmtree(r / "frames"), "capture", "no frames/"),
    ("unreadable frame", {}, _bad_png, "000002.png", "image"),
    ("frame size", {}, _small_frame, "000001.png", "80x60"),
    ("camera size vs frames", {}, lambda r: _edit_json(r / "camera.json", width=200), "000000.png", "200x120"),
    ("video unopenable", {"video": True}, lambda r: (r / "video.mp4").write_bytes(b"\x00" * 4096), "video.mp4",
     "cannot"),
    ("video size", {"video": True}, lambda r: _edit_json(r / "camera.json", height=100), "video.mp4", "160x100"),
    ("imu header", {}, lambda r: _set_imu_row(r, 0, "t,qw,qx,qy,qz"), "imu.csv", "header"),
    ("imu nan", {}, lambda r: _set_imu_row(r, 5, "0.05,nan,0,0,0"), "imu.csv", "NaN"),
    ("imu text", {}, lambda r: _set_imu_row(r, 5, "0.05,one,0,0,0"), "imu.csv", "not a number"),
    ("imu short row", {}, lambda r: _set_imu_row(r, 5, "0.05,1,0,0"), "imu.csv", "expected 5"),
    ("imu not unit", {}, lambda r: _set_imu_row(r, 5, "-0.0095,0.9,0,0,0.1"), "imu.csv", "norm"),
    ("imu one row", {}, lambda r: _set_imu(r, _imu_lines(r)[:2]), "imu.csv", "at least 2"),
    ("imu empty", {}, lambda r: (r / "imu.csv").write_text(""), "imu.csv", "empty"),
    ("imu time repeats", {}, lambda r: _set_imu(r, _imu_lines(r)[:4] + _imu_lines(r)[3:]), "imu.csv",
     "strictly increasing"),
    ("imu too short", {}, lambda r: _set_imu(r, _imu_lines(r)[:30]), "imu.csv", "outside the IMU time span"),
    ("frames.csv row missing", {"frames_csv": True}, lambda r: _frames_csv_edit(r, lambda ls: ls[:-1]),
     "frames.csv", "rows"),
    ("frames.csv unknown file", {"frames_csv": True},
     lambda r: _frames_csv_edit(r, lambda ls: ls[:-1] + ["000099.png,0.5"]), "frames.csv", "000099.png"),
    ("frames.csv duplicate", {"frames_csv": True},
     lambda r: _frames_csv_edit(r, lambda ls: ls[:-1] + [ls[-2]]), "frames.csv", "twice"),
    ("frames.csv order", {"frames_csv": True},
     lambda r: _frames_csv_edit(r, lambda ls: ls[:2] + ["000001.png,0.45"] + ls[3:]), "frames.csv", "increase"),
    ("frames.csv header", {"frames_csv": True},
     lambda r: _frames_csv_edit(r, lambda ls: ["name,time"] + ls[1:]), "frames.csv", "header"),
    ("frames.csv video rows", {"frames_csv": True, "video": True},
     lambda r: _frames_csv_edit(r, lambda ls: ls[:-2]), "frames.csv", "video.mp4"),
]


@pytest.mark.parametrize("name,kwargs,mutate,file,word", BAD_CASES, ids=[c[0] for c in BAD_CASES])
def test_bad_input_raises_one_line_naming_the_file(tiny_capture, name, kwargs, mutate, file, word):
    root = tiny_capture(ground_truth=False, **kwargs)
    mutate(root)
    with pytest.raises(InputError) as err:
        load_capture(root)
    msg = str(err.value)
    assert "\n" not in msg
    assert file in msg, msg
    assert word in msg, msg


def test_bad_inputs_also_stop_inspect(tiny_capture):
    root = tiny_capture(ground_truth=False)
    _set_imu_row(root, 0, "time,qw,qx,qy,qz")
    with pytest.raises(InputError, match="imu.csv"):
        inspect_capture(root)
    with pytest.raises(InputError, match="does not exist"):
        load_capture(root / "nowhere")


def test_frames_outside_imu_span_message(tiny_capture):
    root = tiny_capture(n_frames=6, imu_rate=100.0, ground_truth=False)
    lines = _imu_lines(root)
    _set_imu(root, [lines[0]] + [ln for ln in lines[1:] if float(ln.split(",")[0]) <= 0.32])
    with pytest.raises(InputError) as err:
        load_capture(root)
    msg = str(err.value)
    assert "2 of 6 frames" in msg and "0.400..0.500 s" in msg and "-0.050..0.320 s" in msg, msg
    # the frames that are covered load fine
    cap = load_capture(root, CaptureConfig(max_frames=4))
    assert cap.n_frames == 4
    info = inspect_capture(root)
    assert info["imu"]["coverage"]["frames_outside"] == 2 and len(info["problems"]) == 1


def test_bad_config_raises(tiny_capture):
    root = tiny_capture(ground_truth=False)
    for cfg in (CaptureConfig(every_k=0), CaptureConfig(max_frames=0), CaptureConfig(scale=0.0),
                CaptureConfig(scale=1.5)):
        with pytest.raises(InputError):
            load_capture(root, cfg)


def test_imu_slerp_matches_smooth_rotation(tiny_capture):
    # 100 Hz IMU, frames at 7 fps starting off the IMU grid: slerp error well under 0.01 deg
    root = tiny_capture(n_frames=12, fps=7.0, t0=0.0137, frames_csv=True, imu_rate=100.0, ground_truth=False)
    cap = load_capture(root)
    t_true = 0.0137 + np.arange(12) / 7.0
    np.testing.assert_allclose(cap.timestamps, t_true, atol=1e-9)
    err = rotation_angle_deg(cap.R_wc_imu, tiny_capture.rotation(t_true))
    assert err.max() < 0.01, err
    # and the slerp really interpolates: the IMU rows nearest in time are off by much more
    nearest = np.round(t_true * 100) / 100
    assert rotation_angle_deg(tiny_capture.rotation(nearest), tiny_capture.rotation(t_true)).max() > 0.05


def test_imu_one_row_per_frame(tiny_capture):
    root = tiny_capture(n_frames=5, imu_rate=None, ground_truth=False)
    cap = load_capture(root)
    assert rotation_angle_deg(cap.R_wc_imu, tiny_capture.rotation(cap.timestamps)).max() < 1e-4


def test_every_k_max_frames(tiny_capture):
    root = tiny_capture(n_frames=10, fps=10.0)
    full = load_capture(root)
    cap = load_capture(root, CaptureConfig(every_k=3, max_frames=3))
    assert cap.frame_names == ("000000.png", "000003.png", "000006.png")
    np.testing.assert_allclose(cap.timestamps, [0.0, 0.3, 0.6], atol=1e-12)
    np.testing.assert_array_equal(cap.R_wc_imu, full.R_wc_imu[[0, 3, 6]])
    for j, i in enumerate((0, 3, 6)):
        np.testing.assert_array_equal(cap.frame(j), full.frame(i))
    gt = cap.ground_truth
    assert rotation_angle_deg(gt.R_wc, tiny_capture.rotation(cap.timestamps)).max() < 1e-4  # arccos resolution
    np.testing.assert_allclose(gt.centers, tiny_capture.center(cap.timestamps), atol=1e-8)
    assert len(list(cap.frames())) == 3


@pytest.mark.parametrize("model", ["PINHOLE", "SIMPLE_PINHOLE"])
def test_scale_keeps_images_and_intrinsics_consistent(tiny_capture, model):
    root = tiny_capture(n_frames=3, size=(160, 120), model=model)
    cap = load_capture(root, CaptureConfig(scale=0.5))
    assert (cap.camera.width, cap.camera.height) == (80, 60)
    K = cap.camera.K
    np.testing.assert_allclose(K, [[48, 0, 39.5], [0, 48, 29.5], [0, 0, 1]])  # f*s, (c+0.5)*s-0.5
    assert cap.camera.model == model
    t = cap.timestamps
    for i in range(3):
        img = cap.frame(i)
        assert img.shape == (60, 80, 3) and img.dtype == np.uint8
        ref = tiny_capture.render(K, tiny_capture.rotation(t)[i], tiny_capture.center(t)[i], (80, 60))[0]
        assert np.abs(img.astype(float) - ref).mean() < 2.0  # grey levels; edges are where they should be
    depth = cap.ground_truth.depth(1)
    normals = cap.ground_truth.normals(1)
    assert depth.shape == (60, 80) and normals.shape == (60, 80, 3) and normals.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(normals, axis=2), 1.0, atol=1e-5)
    ref_depth = tiny_capture.render(K, tiny_capture.rotation(t)[1], tiny_capture.center(t)[1], (80, 60))[1]
    assert np.median(np.abs(depth - ref_depth)) < 0.02


def test_jpeg_frames_and_pickled_capture(tiny_capture):
    root = tiny_capture(n_frames=4, ext=".jpg", ground_truth=False)
    cap = load_capture(root)
    assert cap.frame_names[-1] == "000003.jpg"
    clone = pickle.loads(pickle.dumps(cap))  # readers travel to worker processes
    np.testing.assert_array_equal(clone.frame(2), cap.frame(2))


def test_video_reads_the_same_frames_in_order(tiny_capture):
    n = 12
    png = load_capture(tiny_capture(n_frames=n, ground_truth=False, name="png"))
    vid = load_capture(tiny_capture(n_frames=n, video=True, name="vid"))
    assert vid.frame_names[3] == "video.mp4#000003"
    np.testing.assert_allclose(vid.timestamps, png.timestamps, atol=1e-6)
    np.testing.assert_allclose(vid.R_wc_imu, png.R_wc_imu, atol=1e-9)
    ref = np.stack([png.frame(i).astype(np.float32) for i in range(n)])
    seq = [vid.frame(i) for i in range(n)]
    dist = np.array([[np.abs(f.astype(np.float32) - r).mean() for r in ref] for f in seq])
    np.testing.assert_array_equal(dist.argmin(axis=1), np.arange(n))  # each decoded frame is its own PNG
    assert dist.diagonal().max() < 6.0  # mp4v compression only
    # random access (backward jumps, repeats) returns exactly the sequential frames
    for i in (9, 2, 2, 11, 0, 5, 6, 1):
        np.testing.assert_array_equal(vid.frame(i), seq[i])
    # every_k on video, and ground truth matched by stem ("000004.png" <-> "video.mp4#000004")
    sub = load_capture(vid.root, CaptureConfig(every_k=4))
    assert sub.frame_names == ("video.mp4#000000", "video.mp4#000004", "video.mp4#000008")
    for j in range(3):
        np.testing.assert_array_equal(sub.frame(j), seq[4 * j])
    assert rotation_angle_deg(sub.ground_truth.R_wc, tiny_capture.rotation(sub.timestamps)).max() < 1e-4  # arccos resolution


def test_opencv_points_round_trip():
    K = np.array([[500.0, 0, 320], [0, 480, 240], [0, 0, 1]])
    dist = np.array([-0.25, 0.08, 0.002, -0.001])
    cam = Camera("OPENCV", 640, 480, np.r_[500, 480, 320, 240, dist])
    rng = np.random.default_rng(3)
    X = np.c_[rng.uniform(-0.55, 0.55, 200), rng.uniform(-0.45, 0.45, 200), np.ones(200)]
    distorted, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, dist)
    ideal = X[:, :2] * [500, 480] + [320, 240]
    assert np.abs(distorted.reshape(-1, 2) - ideal).max() > 5  # the distortion is not negligible
    np.testing.assert_allclose(undistort_points(cam, distorted.reshape(-1, 2)), ideal, atol=1e-4)
    np.testing.assert_allclose(distort_points(cam, ideal), distorted.reshape(-1, 2), atol=1e-6)
    pin = Camera("PINHOLE", 640, 480, np.array([500.0, 480, 320, 240]))
    np.testing.assert_array_equal(undistort_points(pin, ideal), ideal)


@pytest.mark.parametrize("video", [False, True])
def test_opencv_frames_are_undistorted(tiny_capture, video):
    root = tiny_capture(n_frames=3, model="OPENCV", video=video)
    cap = load_capture(root)
    assert cap.camera.model == "PINHOLE"
    np.testing.assert_allclose(cap.camera.K, tiny_capture.K((160, 120)))
    t = cap.timestamps
    R, C = tiny_capture.rotation(t), tiny_capture.center(t)
    inner = (slice(8, -8), slice(8, -8))  # the undistorted image's border samples outside the raw frame
    raw = cv2.imread(str(root / "frames" / "000001.png")) if not video else None
    for i in range(3):
        ref = tiny_capture.render(cap.camera.K, R[i], C[i], (160, 120))[0].astype(float)
        err = np.abs(cap.frame(i).astype(float) - ref)[inner]
        assert err.mean() < (4.0 if video else 1.0), err.mean()
        if raw is not None and i == 1:  # while the raw (distorted) frame is clearly different
            assert np.abs(raw.astype(float) - ref)[inner].mean() > 2 * err.mean()
    # ground-truth maps go through the same undistortion
    d = cap.ground_truth.depth(0)
    ref_d = tiny_capture.render(cap.camera.K, R[0], C[0], (160, 120))[1]
    assert np.median(np.abs(d - ref_d)[inner]) < 0.01


def test_frames_csv_timestamps_are_used(tiny_capture):
    root = tiny_capture(n_frames=5, frames_csv=True, t0=12.5, fps=5.0, ground_truth=False)
    cap = load_capture(root)
    np.testing.assert_allclose(cap.timestamps, 12.5 + np.arange(5) / 5.0, atol=1e-9)
    assert rotation_angle_deg(cap.R_wc_imu, tiny_capture.rotation(cap.timestamps)).max() < 0.01


def test_ground_truth_contents(tiny_capture):
    cap = load_capture(tiny_capture(n_frames=3))
    gt = cap.ground_truth
    segs, labels = tiny_capture.lines()
    np.testing.assert_allclose(gt.lines, segs, atol=1e-6)
    np.testing.assert_array_equal(gt.line_labels, labels)
    assert gt.scene["boxes"][0]["inside"] and gt.has_normals and gt.has_depth
    # normals point towards the camera: negative dot product with the viewing ray
    n = gt.normals(2)
    K = cap.camera.K
    v, u = np.mgrid[0:120, 0:160]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1)
    assert np.all(np.sum(n * rays, axis=2) < 0)
    assert load_capture(tiny_capture(n_frames=2, ground_truth=False)).ground_truth is None


def test_inspect_frames_capture(tiny_capture):
    root = tiny_capture(n_frames=8, fps=10.0, imu_rate=100.0)
    info = inspect_capture(root)
    assert info["frames"] == 8 and info["source"] == "frames" and info["resolution"] == [160, 120]
    assert info["camera_model"] == "PINHOLE" and info["timestamps_from"] == "fps"
    assert info["fps"] == pytest.approx(10.0) and info["duration_s"] == pytest.approx(0.7)
    assert info["imu"]["rows"] == 81 and info["imu"]["rate_hz"] == pytest.approx(100.0, rel=1e-3)
    assert info["imu"]["time_span_s"] == pytest.approx([-0.05, 0.75])
    assert info["imu"]["coverage"]["fraction"] == 1.0 and info["problems"] == []
    assert info["ground_truth"] == {"poses": 8, "lines": 40, "scene": True, "normals": 8, "depth": 8}
    text = format_inspection(info)
    assert "8 from frames" in text and "100 Hz" in text and "8 of 8 frames (100.0%)" in text
    json.dumps(info)  # the CLI's --json


def test_inspect_video_capture(tiny_capture):
    root = tiny_capture(n_frames=9, video=True, model="OPENCV", fps=15.0, imu_rate=None, ground_truth=False)
    info = inspect_capture(root)
    assert info["frames"] == 9 and info["source"] == "video.mp4" and info["timestamps_from"] == "video"
    assert info["camera_model"] == "OPENCV" and len(info["params"]) == 8
    assert info["fps"] == pytest.approx(15.0, rel=1e-3) and info["duration_s"] == pytest.approx(8 / 15, abs=1e-3)
    assert info["imu"]["rows"] == 9 and info["ground_truth"] is None
    text = format_inspection(info)
    assert "9 from video.mp4" in text and "undistorted" in text and "ground truth  none" in text


def test_other_tools_formatting_is_accepted(tiny_capture):
    # CRLF line ends, a BOM, spaces after commas, an extra IMU column, frames.csv paths with folder,
    # a lower-case model name: all still the format
    root = tiny_capture(n_frames=4, frames_csv=True, ground_truth=False)
    imu = _imu_lines(root)
    rows = ["timestamp_s, qw, qx, qy, qz, accuracy"] + [ln.replace(",", ", ") + ", 0.5" for ln in imu[1:]]
    (root / "imu.csv").write_bytes(("\ufeff" + "\r\n".join(rows) + "\r\n").encode("utf-8"))
    _frames_csv_edit(root, lambda ls: [ls[0]] + ["frames/" + ln for ln in ls[1:]])
    _edit_json(root / "camera.json", model="pinhole")
    cap = load_capture(root)
    assert cap.n_frames == 4 and cap.camera.model == "PINHOLE"
    assert rotation_angle_deg(cap.R_wc_imu, tiny_capture.rotation(cap.timestamps)).max() < 0.01
