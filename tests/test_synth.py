"""Tests of the synthetic capture generator (panosfm_graph.synth): geometry, rendering, files."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from panosfm_graph.errors import InputError
from panosfm_graph.geometry import project, quat_wxyz_to_matrix, slerp_rotations
from panosfm_graph.synth import (
    SCENES, intrinsics, make_scene, render_frame, scene_from_json, spin_params, spin_trajectory, synthesize,
)

SIZE = (160, 90)
N = 12
DRIFT = 3.0


def _read_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    return rows[0], rows[1:]


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "cap"
    return synthesize(out, "living", N, SIZE, seed=3, imu_drift_deg=DRIFT, workers=1)


def _gt(capture: Path):
    _, rows = _read_csv(capture / "ground_truth" / "poses.csv")
    q = np.array([[float(x) for x in r[1:5]] for r in rows])
    c = np.array([[float(x) for x in r[5:8]] for r in rows])
    return [r[0] for r in rows], quat_wxyz_to_matrix(q), c


def test_files_parse_per_format(capture):
    cam = json.loads((capture / "camera.json").read_text())
    assert cam["model"] == "PINHOLE" and (cam["width"], cam["height"]) == SIZE and cam["fps"] == 30
    np.testing.assert_allclose(cam["params"], [0.8 * 160, 0.8 * 160, 79.5, 44.5])

    frames = sorted(p.name for p in (capture / "frames").iterdir())
    assert frames == [f"{i:06d}.png" for i in range(N)]
    img = cv2.imread(str(capture / "frames" / frames[0]), cv2.IMREAD_UNCHANGED)
    assert img.shape == (SIZE[1], SIZE[0], 3) and img.dtype == np.uint8

    head, rows = _read_csv(capture / "frames.csv")
    assert head == ["file", "timestamp_s"] and [r[0] for r in rows] == frames
    np.testing.assert_allclose([float(r[1]) for r in rows], np.arange(N) / 30.0, atol=1e-9)

    head, rows = _read_csv(capture / "imu.csv")
    assert head == ["timestamp_s", "qw", "qx", "qy", "qz"]
    imu = np.array(rows, dtype=np.float64)
    assert imu[0, 0] <= 0.0 and imu[-1, 0] >= (N - 1) / 30.0
    np.testing.assert_allclose(np.diff(imu[:, 0]), 0.01, atol=1e-6)  # 100 Hz
    np.testing.assert_allclose(np.linalg.norm(imu[:, 1:], axis=1), 1.0, atol=1e-6)

    head, rows = _read_csv(capture / "ground_truth" / "poses.csv")
    assert head == ["file", "qw", "qx", "qy", "qz", "tx", "ty", "tz"] and [r[0] for r in rows] == frames
    q = np.array([r[1:5] for r in rows], dtype=np.float64)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)

    scene = json.loads((capture / "ground_truth" / "scene.json").read_text())
    R_wr = np.array(scene["R_world_room"])
    np.testing.assert_allclose(R_wr @ R_wr.T, np.eye(3), atol=1e-9)
    assert np.degrees(np.arctan2(R_wr[1, 0], R_wr[0, 0])) == pytest.approx(scene["room_yaw_deg"])
    assert len(scene["boxes"]) > 5 and all(np.all(np.array(b["max"]) > np.array(b["min"])) for b in scene["boxes"])

    head, rows = _read_csv(capture / "ground_truth" / "lines.csv")
    assert head == ["x1", "y1", "z1", "x2", "y2", "z2", "label"]
    L = np.array([r[:6] for r in rows], dtype=np.float64)
    lab = np.array([int(r[6]) for r in rows])
    assert set(lab) == {0, 1, 2}
    d = L[:, 3:] - L[:, :3]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # each line runs along its labelled room axis, expressed in the world frame
    np.testing.assert_allclose(np.abs(np.sum(d * R_wr[:, lab].T, axis=1)), 1.0, atol=1e-6)
    assert np.all(np.abs(d[lab == 2, 2]) > 0.999999)  # axis 2 is vertical

    for i in (0, N - 1):
        n = np.load(capture / "ground_truth" / "normals" / f"{i:06d}.npy")
        z = np.load(capture / "ground_truth" / "depth" / f"{i:06d}.npy")
        assert n.shape == (SIZE[1], SIZE[0], 3) and n.dtype == np.float16
        assert z.shape == (SIZE[1], SIZE[0]) and z.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(n.astype(np.float32), axis=2), 1.0, atol=2e-3)
        assert np.all(z > 0.1) and np.all(z < 15.0)  # closed room: every pixel sees a surface


def test_poses_match_trajectory_and_spin_shape(capture):
    names, R, c = _gt(capture)
    scene = make_scene("living", 3)
    R2, c2, ts = spin_trajectory(scene, N, seed=3)
    np.testing.assert_allclose(R, R2, atol=1e-7)
    np.testing.assert_allclose(c, c2, atol=1e-7)
    # the person stands away from the room centre; the camera circles at 0.30-0.40 m, ~1.5 m high
    stand = scene.stand_point_world
    room_centre = scene.to_world((scene.room_min + scene.room_max) / 2)
    assert np.linalg.norm((stand - room_centre)[:2]) > 0.5
    r = np.linalg.norm(c2[:, :2] - stand[:2], axis=1)
    assert 0.3 <= r.min() and r.max() <= 0.4 and np.ptp(r) < 1e-9
    p = spin_params(scene, N, seed=3)
    assert abs(c2[:, 2] - p.height_m).max() <= 0.0125 and 1.4 < p.height_m < 1.6
    # the optical axis points outwards, nearly horizontally
    fwd = R2[:, :, 2]
    radial = (c2 - stand)[:, :2] / r[:, None]
    assert np.all(np.sum(fwd[:, :2] * radial, axis=1) > 0.95)
    assert np.all(np.abs(np.degrees(np.arcsin(fwd[:, 2]))) < 12.0)


@pytest.mark.parametrize("sway", [0.05, 0.1])
def test_sway_departs_from_the_circle_by_its_size(sway):
    """``sway_m`` moves the stand point (not back to its start), the arm length and its angle, smoothly; 0 changes nothing."""
    scene = make_scene("office", 2)
    R0, c0, _ = spin_trajectory(scene, 300, seed=2)
    R1, c1, _ = spin_trajectory(scene, 300, seed=2, sway_m=0.0)
    np.testing.assert_array_equal(c0, c1)
    np.testing.assert_array_equal(R0, R1)
    R, c, _ = spin_trajectory(scene, 300, seed=2, sway_m=sway)
    off = np.linalg.norm((c - c0)[:, :2], axis=1)
    assert 0.7 * sway < np.sqrt(np.mean(off**2)) < 2.0 * sway  # stand point RMS sway, plus the arm's share
    assert off.max() < 4 * sway
    assert np.linalg.norm(np.diff(c, axis=0), axis=1).max() < 0.03  # smooth: under 3 cm a frame
    np.testing.assert_allclose(c[:, 2], c0[:, 2])  # the height (and its bob) stays
    heading = np.degrees(np.arctan2(R[:, 1, 2], R[:, 0, 2]) - np.arctan2(R0[:, 1, 2], R0[:, 0, 2]))
    heading = (heading + 180) % 360 - 180
    assert 0.2 * sway / 0.05 < np.std(heading) < 6.0 * sway / 0.05  # the arm's angle varies (2 deg RMS at 5 cm)


@pytest.mark.parametrize("turn", [380.0, 200.0])
def test_turn_angle(turn):
    scene = make_scene("office")
    R, _, _ = spin_trajectory(scene, 90, seed=1, turn_deg=turn)
    heading = np.unwrap(np.arctan2(R[:, 1, 2], R[:, 0, 2]))
    assert np.degrees(heading[-1] - heading[0]) == pytest.approx(turn, abs=0.5)
    assert np.all(np.diff(heading) > 0)  # turns one way


def test_edges_project_onto_strong_gradients(capture):
    names, R, c = _gt(capture)
    K = intrinsics(SIZE)
    scene = scene_from_json(json.loads((capture / "ground_truth" / "scene.json").read_text()))
    lines, _ = scene.edges(min_length_m=0.1)
    s = np.linspace(0.02, 0.98, 40)
    pts = (lines[:, None, :3] * (1 - s)[None, :, None] + lines[:, None, 3:] * s[None, :, None]).reshape(-1, 3)
    rng = np.random.default_rng(0)
    on_edge, at_random = [], []
    for i, name in enumerate(names):
        gray = cv2.cvtColor(cv2.imread(str(capture / "frames" / name)), cv2.COLOR_BGR2GRAY).astype(np.float32)
        g = np.hypot(cv2.Sobel(gray, cv2.CV_32F, 1, 0), cv2.Sobel(gray, cv2.CV_32F, 0, 1))
        g = cv2.dilate(g, np.ones((3, 3), np.uint8))  # strongest gradient within 1 px
        depth = np.load(capture / "ground_truth" / "depth" / f"{Path(name).stem}.npy")
        uv, z = project(K, R[i], c[i], pts)
        ok = (z > 0.2) & np.all((uv >= 2) & (uv <= np.array(SIZE) - 3), axis=1)
        ui, vi = np.rint(uv[ok]).astype(int).T
        # visible: some pixel within 1 px sees the point's depth (not occluded)
        dz = np.min([np.abs(depth[vi + dv, ui + du] - z[ok]) for du in (-1, 0, 1) for dv in (-1, 0, 1)], axis=0)
        vis = dz < 0.02 * z[ok] + 0.01
        on_edge.append(g[vi[vis], ui[vis]])
        at_random.append(g[rng.integers(0, SIZE[1], 500), rng.integers(0, SIZE[0], 500)])
    on_edge, at_random = np.concatenate(on_edge), np.concatenate(at_random)
    assert len(on_edge) > 500
    assert np.median(on_edge) > 4.0 * np.median(at_random)
    assert np.mean(on_edge) > 2.0 * np.mean(at_random)


def test_normals_agree_with_depth_and_scene(capture):
    names, R, c = _gt(capture)
    K = intrinsics(SIZE)
    scene = scene_from_json(json.loads((capture / "ground_truth" / "scene.json").read_text()))
    u, v = np.meshgrid(np.arange(SIZE[0]), np.arange(SIZE[1]))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], axis=2)
    angles, dist = [], []
    for i in range(0, N, 3):
        stem = Path(names[i]).stem
        n = np.load(capture / "ground_truth" / "normals" / f"{stem}.npy").astype(np.float64)
        X = rays * np.load(capture / "ground_truth" / "depth" / f"{stem}.npy")[..., None].astype(np.float64)
        assert np.all(np.sum(n * X, axis=2) < 0)  # towards the camera
        dXu = X[1:-1, 2:] - X[1:-1, :-2]
        dXv = X[2:, 1:-1] - X[:-2, 1:-1]
        fd = np.cross(dXu, dXv)
        fd /= np.linalg.norm(fd, axis=2, keepdims=True)
        fd *= -np.sign(np.sum(fd * X[1:-1, 1:-1], axis=2))[..., None]
        # pixels whose 3x3 neighbourhood lies on one face (same stored normal)
        nn = n[1:-1, 1:-1] / np.linalg.norm(n[1:-1, 1:-1], axis=2, keepdims=True)  # float16 storage
        same = np.ones(nn.shape[:2], bool)
        for dv in (-1, 0, 1):
            for du in (-1, 0, 1):
                same &= np.all(np.abs(n[1 + dv:n.shape[0] - 1 + dv, 1 + du:n.shape[1] - 1 + du] - nn) < 1e-3, axis=2)
        cosang = np.clip(np.sum(fd * nn, axis=2)[same], -1, 1)
        angles.append(np.degrees(np.arccos(cosang)))
        # back-projected depth lies on the scene's surfaces (scene.json consumer path)
        Xw = X.reshape(-1, 3)[::7] @ R[i].T + c[i]
        dist.append(scene.distance_to_surfaces(Xw))
    angles = np.concatenate(angles)
    assert np.median(angles) < 0.5 and np.percentile(angles, 95) < 3.0
    assert np.max(np.concatenate(dist)) < 2e-3


def test_imu_drift_and_tilt(capture):
    names, R, c = _gt(capture)
    _, rows = _read_csv(capture / "imu.csv")
    imu = np.array(rows, dtype=np.float64)
    ts = np.arange(N) / 30.0
    R_imu = slerp_rotations(imu[:, 0], quat_wxyz_to_matrix(imu[:, 1:]), ts)
    E = R_imu @ np.transpose(R, (0, 2, 1))  # world-side error rotation
    yaw = np.degrees(np.arctan2(E[:, 1, 0], E[:, 0, 0]))
    assert abs(yaw[0]) < 0.4
    assert yaw[-1] == pytest.approx(DRIFT, abs=0.4)
    np.testing.assert_allclose(yaw, DRIFT * ts / ts[-1], atol=0.4)  # grows steadily
    # gravity in the camera frame: the IMU's tilt is nearly exact
    tilt = np.degrees(np.arccos(np.clip(np.sum(R_imu[:, 2, :] * R[:, 2, :], axis=1), -1, 1)))
    assert np.all(tilt < 0.4)


def test_deterministic_for_a_seed_also_with_workers(tmp_path, capture):
    a = synthesize(tmp_path / "a", "living", N, SIZE, seed=3, imu_drift_deg=DRIFT, workers=2, gt_maps=False)
    for rel in ["imu.csv", "frames.csv", "ground_truth/poses.csv", "ground_truth/lines.csv",
                "ground_truth/scene.json", "frames/000000.png", f"frames/{N - 1:06d}.png"]:
        assert (a / rel).read_bytes() == (capture / rel).read_bytes(), rel
    assert not (a / "ground_truth" / "normals").exists()
    b = synthesize(tmp_path / "b", "living", N, SIZE, seed=4, workers=1, gt_maps=False)
    assert (a / "ground_truth/poses.csv").read_bytes() != (b / "ground_truth/poses.csv").read_bytes()


def test_presets_differ_and_leave_room_to_spin():
    from panosfm_graph.synth.scenes import random_box_room

    # the procedural rooms (--scene random) have tests of their own (test_procedural.py)
    scenes = [make_scene(n, 0) for n in SCENES if n != "random"] + [random_box_room(s) for s in (1, 2, 3)]
    sizes = {tuple(np.round(s.room_max, 3)) for s in scenes}
    yaws = {round(s.yaw_deg, 3) for s in scenes}
    assert len(sizes) == len(scenes) and len(yaws) == len(scenes)
    K = intrinsics(SIZE)
    first = []
    for s in scenes:
        assert s.n_boxes >= (4 if s.name == "bare" else 5)  # the bare room: one door (leaf and trim)
        assert len(s.edges()[0]) == 12 * (s.n_boxes + 1) and s.faces().n == 6 * (s.n_boxes + 1)
        R, c, _ = spin_trajectory(s, 60, seed=0)
        assert s.distance_to_surfaces(c).min() > 0.5  # cameras are well clear of every surface
        assert np.all(c[:, 2] < s.room_max[2] - 0.5)
        centre = s.to_world((s.room_min + s.room_max) / 2)
        assert np.linalg.norm((s.stand_point_world - centre)[:2]) > 0.2
        first.append(render_frame(s, K, R[0], c[0], SIZE)[0].astype(np.float32))
    for i in range(len(first)):
        for j in range(i):
            assert np.abs(first[i] - first[j]).mean() > 5.0


def test_texture_blur_noise_options():
    s = make_scene("bedroom")
    R, c, _ = spin_trajectory(s, 30)
    K = intrinsics(SIZE)
    plain, depth, normals = render_frame(s, K, R[5], c[5], SIZE, texture=0.0)
    tex = render_frame(s, K, R[5], c[5], SIZE, texture=1.0)[0]
    # inside faces (normal constant over 5x5), textureless images are flat, textured ones are not
    flat = cv2.erode((np.abs(cv2.Laplacian(depth, cv2.CV_32F)) < 1e-3).astype(np.uint8), np.ones((5, 5), np.uint8))
    lap = lambda im: np.abs(cv2.Laplacian(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY).astype(np.float32), cv2.CV_32F))  # noqa: E731
    assert flat.sum() > 1000
    assert lap(plain)[flat > 0].mean() < 0.5 < lap(tex)[flat > 0].mean()
    noisy = render_frame(s, K, R[5], c[5], SIZE, texture=0.0, noise=4.0, seed=1)[0].astype(np.float32)
    assert np.std(noisy - plain) == pytest.approx(4.0, rel=0.15)
    blurred = render_frame(s, K, R[5], c[5], SIZE, texture=1.0, blur=6.0)[0]
    gx = lambda im: np.abs(cv2.Sobel(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY), cv2.CV_32F, 1, 0)).mean()  # noqa: E731
    assert gx(blurred) < 0.7 * gx(tex)


def test_refuses_non_empty_out_dir_and_bad_settings(tmp_path):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="not an empty directory"):
        synthesize(out, "living", 4, SIZE)
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    with pytest.raises(InputError, match="unknown scene"):
        synthesize(tmp_path / "x", "castle", 4, SIZE)
    with pytest.raises(InputError):
        make_scene("castle")
    with pytest.raises(InputError):
        synthesize(tmp_path / "y", "living", 1, SIZE)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["busy"]  # no temp dirs left behind
    empty = tmp_path / "empty"
    empty.mkdir()
    assert synthesize(empty, "office", 3, SIZE, gt_maps=False, workers=1) == empty
    assert len(list((empty / "frames").iterdir())) == 3


def test_faces_edges_and_json_round_trip():
    s = make_scene("office")
    f = s.faces()
    # a face's centre lies on the scene's surfaces, its outward normal points into free space
    centre = np.zeros((f.n, 3))
    for a in range(3):
        m = f.axis == a
        oth = [b for b in range(3) if b != a]
        centre[m, a] = f.offset[m]
        centre[np.ix_(m, oth)] = (f.lo[m] + f.hi[m]) / 2
    assert s.distance_to_surfaces(s.to_world(centre)).max() < 1e-9
    assert np.all(f.surface[:6] == np.arange(6)) and np.all(f.sign[[0, 2, 4]] == 1)
    # every face corner is an endpoint of a GT edge (room frame)
    L, _ = s.edges(frame="room")
    ends = np.unique(np.round(np.vstack([L[:, :3], L[:, 3:]]), 9), axis=0)
    corners = centre.copy()
    for a in range(3):
        m = f.axis == a
        oth = [b for b in range(3) if b != a]
        corners[np.ix_(m, oth)] = f.lo[m]
    assert np.all(np.isin(np.round(corners, 9).view([("", float)] * 3), ends.view([("", float)] * 3)))
    s2 = scene_from_json(json.loads(json.dumps(s.to_json())))
    np.testing.assert_allclose(s2.edges()[0], s.edges()[0], atol=1e-5)
    assert s2.box_names == s.box_names and s.to_json()["room_yaw_deg"] == 50.0


def test_exposure_blurs_by_the_angular_speed(tmp_path):
    """motion_blur_px is exposure x angular speed x focal length: 380 deg in 30 frames at 30 fps turn at 380 deg/s,
    1/100 s moves the centre 3.8 deg; a capture with that exposure is blurrier than a sharp one of the same seed."""
    from panosfm_graph.synth.writer import motion_blur_px

    s = make_scene("living")
    R, _, ts = spin_trajectory(s, 30, turn_deg=380.0, fps=30.0)
    K = intrinsics(SIZE)
    px = motion_blur_px(K, R, ts, 0.01)
    assert np.median(px) == pytest.approx(np.radians(3.8) * K[0, 0], rel=0.06)  # plus the wobble
    assert np.all(motion_blur_px(K, R, ts, 0.0) == 0)
    sharp = synthesize(tmp_path / "sharp", "living", 4, SIZE, seed=2, gt_maps=False, workers=1, turn_deg=60.0, fps=4.0)
    blurred = synthesize(tmp_path / "blur", "living", 4, SIZE, seed=2, gt_maps=False, workers=1, turn_deg=60.0, fps=4.0,
                         exposure_s=0.1)  # 60 deg in 0.75 s: 8 deg, 9 px at 65 deg HFOV and 160 px
    gx = lambda p: np.abs(cv2.Sobel(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), cv2.CV_32F, 1, 0)).mean()  # noqa: E731
    assert gx(blurred / "frames" / "000001.png") < 0.7 * gx(sharp / "frames" / "000001.png")
    assert json.loads((blurred / "ground_truth" / "synth.json").read_text())["exposure_s"] == 0.1


def test_a_bare_room_seen_level_shows_only_vertical_edges_and_the_point_tracks_place_it(tmp_path, capsys):
    """The bare room (issue #40): walls, one door; a level 65-degree view sees no floor or ceiling edge. The
    point tracks on its painted walls place every frame (after the similarity alignment within the accuracy
    bar, rotations better than the IMU's); the lines alone (no motion model) stop with one line saying why."""
    from panosfm_graph.cli import main
    from panosfm_graph.evaluate import evaluate_reconstruction

    cap = synthesize(tmp_path / "bare", "bare", 40, (480, 270), seed=0, workers=1, gt_maps=False)
    assert main(["run", str(cap), str(tmp_path / "strict"), "--no-rerun", "--set", "graph.motion_model=False"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "only vertical edges" in err
    assert main(["run", str(cap), str(tmp_path / "out"), "--no-rerun"]) == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    # every frame placed by the points; the reliability check may leave a few doubtful ones out of a trusted run
    assert set(summary["frames"]["source"]) <= {"points", None} and "point tracks" in summary["scale"]
    assert summary["frames"]["registered"] >= 0.85 * summary["frames"]["total"]
    assert summary["verdict"]["status"] in ("trusted", "doubtful")
    ev = evaluate_reconstruction(cap, tmp_path / "out")
    # measured: 36 output (4 doubtful frames left out), all 36 accurate; before the check 40 of 40
    assert ev["accurate"] >= 34 and ev["accurate"] == ev["registered"], ev["accurate"]
    assert ev["rotation_error_rotalign_deg"]["median"] < 0.3  # measured 0.11 (the IMU 0.76)
