"""Evaluation against ground truth on a hand-made box room: perfect, similar, noisy and partial reconstructions."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from panosfm_graph.data import Camera, Capture, GroundTruth
from panosfm_graph.evaluate import (
    distance_to_boxes,
    edge_coverage,
    evaluate_reconstruction,
    format_metrics,
    scene_boxes,
    segments_blocked,
    umeyama,
)
from panosfm_graph.export import write_colmap_text, write_lines_ply

N_CAMS = 36
CAM = Camera("PINHOLE", 320, 240, np.array([160.0, 160.0, 159.5, 119.5]))
YAW = np.radians(20.0)
R_WR = np.array([[np.cos(YAW), -np.sin(YAW), 0], [np.sin(YAW), np.cos(YAW), 0], [0, 0, 1]])
T_WR = np.array([-2.0, -3.0, 0.1])
ROOM = ([0, 0, 0], [6, 5, 3])
BOXES = [([3.8, 1.0, 0.0], [4.8, 2.0, 0.75]), ([0.3, 3.5, 0.0], [0.9, 4.5, 1.8])]


def _box_edges(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    E, lab = [], []
    for a in range(3):
        b, c = [k for k in range(3) if k != a]
        for vb in (lo[b], hi[b]):
            for vc in (lo[c], hi[c]):
                p, q = lo.copy(), hi.copy()
                p[b] = q[b] = vb
                p[c] = q[c] = vc
                E.append(np.concatenate([p, q]))
                lab.append(a)
    return np.array(E), np.array(lab, np.int8)


def _to_world(p):
    return p @ R_WR.T + T_WR


def _scene():
    return {"version": 1, "frame": "room", "R_world_room": R_WR.tolist(), "t_world_room": T_WR.tolist(),
            "room": {"min": ROOM[0], "max": ROOM[1]},
            "boxes": [{"name": f"b{i}", "min": lo, "max": hi} for i, (lo, hi) in enumerate(BOXES)]}


def _gt_lines():
    parts = [_box_edges(*ROOM)] + [_box_edges(lo, hi) for lo, hi in BOXES]
    E = np.concatenate([p[0] for p in parts])
    lab = np.concatenate([p[1] for p in parts])
    return np.concatenate([_to_world(E[:, :3]), _to_world(E[:, 3:])], axis=1), lab


def _gt_poses(n=N_CAMS):
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    stand = np.array([3.0, 2.5, 1.5])
    c_room = stand + 0.35 * np.stack([np.cos(th), np.sin(th), 0.02 * np.sin(3 * th)], axis=1)
    pitch = np.radians(5.0) * np.sin(2 * th)
    fwd = np.stack([np.cos(th) * np.cos(pitch), np.sin(th) * np.cos(pitch), np.sin(pitch)], axis=1)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(fwd, right)
    R_room = np.stack([right, down, fwd], axis=2)  # columns: camera axes in the room frame
    return np.einsum("ij,njk->nik", R_WR, R_room), _to_world(c_room)


def _capture(root, depth=None, n=N_CAMS):
    R, c = _gt_poses(n)
    lines, lab = _gt_lines()
    gt = GroundTruth(R_wc=R, centers=c, lines=lines, line_labels=lab, scene=_scene(),
                     depth=depth or (lambda i: None), has_depth=depth is not None)
    names = tuple(f"{i:06d}.png" for i in range(n))
    return Capture(root=root, camera=CAM, frame_names=names, timestamps=np.arange(n) / 30.0, R_wc_imu=R,
                   ground_truth=gt, reader=lambda i: np.zeros((CAM.height, CAM.width, 3), np.uint8))


def _write(out, cap, R, c, reg=None, lines=None, labels=None, camera=CAM):
    reg = np.ones(len(R), bool) if reg is None else reg
    write_colmap_text(out / "sparse", camera, cap.frame_names, R, c, reg)
    if lines is not None:
        write_lines_ply(out / "lines.ply", lines, labels)
    return out


def _similar(s, A, t, R, c, lines):
    R2 = np.einsum("ij,njk->nik", A, R)
    c2 = s * c @ A.T + t
    L2 = np.concatenate([s * lines[:, :3] @ A.T + t, s * lines[:, 3:] @ A.T + t], axis=1)
    return R2, c2, L2


@pytest.fixture
def cap(tmp_path):
    return _capture(tmp_path)


def test_perfect_reconstruction_has_zero_error(tmp_path, cap):
    gt = cap.ground_truth
    out = _write(tmp_path / "rec", cap, gt.R_wc, gt.centers, lines=gt.lines, labels=gt.line_labels)
    m = evaluate_reconstruction(cap, out)
    assert m["registered"] == N_CAMS and m["registered_ratio"] == 1.0
    assert "umeyama" in m["alignment"]["method"]
    assert abs(m["alignment"]["scale"] - 1) < 1e-9
    assert m["center_error_m"]["max"] < 1e-6 and m["rotation_error_deg"]["max"] < 1e-6
    rp = m["reprojection_px"]
    assert rp["points"] >= 12 and rp["occlusion"] == "scene boxes"
    assert 0.2 < rp["mean"] < 0.9 and rp["max"] < 3.0  # 0.5 px click noise, 2D, less the DLT's 3 dof
    ln = m["lines"]
    assert ln["distance_m"]["median"] < 1e-6 and ln["recovered_share"] == 1.0
    assert ln["gt_edges"] == 36
    table = format_metrics(m)
    assert "umeyama" in table and "px @ 320x240" in table
    json.dumps(m, default=lambda o: o.tolist())  # plain data

    m0 = evaluate_reconstruction(cap, out, click_noise_px=0.0)
    assert m0["reprojection_px"]["max"] < 1e-6 and m0["reprojection_px"]["corner_error_m"]["median"] < 1e-6


def test_similarity_transformed_reconstruction_still_zero(tmp_path, cap):
    gt = cap.ground_truth
    s, A, t = 3.0, Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix(), np.array([10.0, -4.0, 2.5])
    R2, c2, L2 = _similar(s, A, t, gt.R_wc, gt.centers, gt.lines)
    out = _write(tmp_path / "rec", cap, R2, c2, lines=L2, labels=gt.line_labels)
    m = evaluate_reconstruction(cap, out)
    ref = evaluate_reconstruction(cap, _write(tmp_path / "ref", cap, gt.R_wc, gt.centers))
    assert abs(m["alignment"]["scale"] - 1 / s) < 1e-9
    assert m["center_error_m"]["max"] < 1e-6 and m["rotation_error_deg"]["max"] < 1e-6
    assert abs(m["reprojection_px"]["mean"] - ref["reprojection_px"]["mean"]) < 1e-6
    assert m["lines"]["distance_m"]["median"] < 1e-6 and m["lines"]["recovered_share"] == 1.0


def test_centre_noise_gives_expected_error(tmp_path, cap):
    gt = cap.ground_truth
    sigma = 0.01
    c = gt.centers + np.random.default_rng(3).normal(0.0, sigma, gt.centers.shape)
    m = evaluate_reconstruction(cap, _write(tmp_path / "rec", cap, gt.R_wc, c))
    # a 7-dof similarity fitted to 3n coordinates leaves sigma^2 (3n - 7) of squared error
    expected = sigma * np.sqrt((3 * N_CAMS - 7) / N_CAMS)
    assert 0.8 < m["center_error_m"]["rmse"] / expected < 1.2
    diam = m["trajectory_diameter_m"]
    assert abs(diam - 0.70) < 0.01
    assert abs(m["center_error_rel"]["mean"] - m["center_error_m"]["mean"] / diam) < 1e-12
    assert m["reprojection_px"]["mean"] > 0.9  # centimetre pose errors show in the reprojection
    err_rel = np.linalg.norm(c - gt.centers, axis=1) / diam  # the similarity barely moves noisy centres
    assert abs(m["accurate"] - int(np.sum(err_rel <= 0.05))) <= 1  # 5 % of 0.70 m: 3.5 sigma


def test_one_rotated_frame_gives_its_angle(tmp_path, cap):
    gt = cap.ground_truth
    R = gt.R_wc.copy()
    R[5] = Rotation.from_rotvec(np.radians(2.0) * np.array([0.6, 0.0, 0.8])).as_matrix() @ R[5]
    m = evaluate_reconstruction(cap, _write(tmp_path / "rec", cap, R, gt.centers))
    assert abs(m["rotation_error_deg"]["max"] - 2.0) < 1e-6  # centres exact: the similarity is the identity
    assert m["accurate"] == N_CAMS - 1  # the frame turned by 2 degrees (more than 1) is not accurate
    assert "frames accurate" in format_metrics(m)
    assert m["rotation_error_deg"]["median"] < 1e-6
    assert abs(m["rotation_error_rotalign_deg"]["max"] - 2.0) < 0.1


def test_accurate_frames_aligned_by_the_orientations(tmp_path, cap):
    """Exact rotations, centres turned by 2 degrees about the circle's centre (1.2 cm along it): the centres'
    similarity carries the 2 degrees into every rotation (no frame accurate by it), the orientations' alignment
    leaves the centres 1.7 % of the diameter off and every frame accurate."""
    gt = cap.ground_truth
    mid = gt.centers.mean(axis=0)
    up = np.linalg.svd(gt.centers - mid)[2][2]  # the circle's axis
    turn = Rotation.from_rotvec(np.radians(2.0) * up).as_matrix()
    c = (gt.centers - mid) @ turn.T + mid
    m = evaluate_reconstruction(cap, _write(tmp_path / "rec", cap, gt.R_wc, c))
    assert m["accurate_sim3"] == 0
    assert m["accurate"] == N_CAMS
    assert m["rotation_error_rotalign_deg"]["max"] < 1e-6


def test_few_frames_and_no_lines(tmp_path, cap):
    gt = cap.ground_truth
    reg = np.zeros(N_CAMS, bool)
    reg[[3, 4]] = True
    c = gt.centers.copy()
    c[~reg] = np.nan
    out = _write(tmp_path / "rec", cap, gt.R_wc, c, reg=reg)
    (out / "summary.json").write_text(json.dumps({"frames": 18}))  # e.g. a run on every 2nd frame
    m = evaluate_reconstruction(cap, out)
    assert m["run_frames"] == 18 and "the run took 18 frames" in format_metrics(m)
    (out / "summary.json").write_text(json.dumps({"frames": {"total": 18, "registered": 2}}))  # as runs write it
    assert evaluate_reconstruction(cap, out)["run_frames"] == 18
    assert m["registered"] == 2 and abs(m["registered_ratio"] - 2 / N_CAMS) < 1e-12
    assert "orientations" in m["alignment"]["method"]
    assert m["center_error_m"]["max"] < 1e-6 and m["rotation_error_deg"]["max"] < 1e-6
    assert m["reprojection_px"]["points"] == 0 and m["reprojection_px"]["mean"] is None
    assert m["lines"] is None
    assert "no lines.ply" in format_metrics(m)

    reg[:] = False  # nothing registered at all
    m = evaluate_reconstruction(cap, _write(tmp_path / "none", cap, gt.R_wc, c, reg=reg))
    assert m["registered"] == 0 and m["alignment"] is None
    format_metrics(m)


def test_line_metrics_offset_and_partial(tmp_path, cap):
    gt = cap.ground_truth
    shifted = gt.lines + np.tile(0.08 * np.ones(3) / np.sqrt(3), 2)
    m = evaluate_reconstruction(cap, _write(tmp_path / "a", cap, gt.R_wc, gt.centers, lines=shifted))
    assert m["lines"]["recovered"] == 0
    half = gt.lines[::2]
    m = evaluate_reconstruction(cap, _write(tmp_path / "b", cap, gt.R_wc, gt.centers, lines=half))
    assert m["lines"]["recovered"] == len(half) and abs(m["lines"]["recovered_share"] - 0.5) < 1e-12

    edge = np.array([[0.0, 0, 0, 2, 0, 0]])
    part = lambda f, off: np.array([[0.0, off, 0, 2 * f, off, 0]])  # noqa: E731
    # covered: 60 % plus the 4 cm beyond its end that are still within 5 cm of a line 3 cm away
    assert abs(edge_coverage(edge, part(0.6, 0.03), 0.05, 3.0)[0] - 0.62) < 0.006
    assert edge_coverage(edge, part(0.6, 0.07), 0.05, 3.0)[0] == 0.0
    tilted = np.array([[0.0, 0, 0, 2 * np.cos(0.1), 2 * np.sin(0.1), 0]])  # 5.7 deg: rejected
    assert edge_coverage(edge, tilted, 0.05, 3.0)[0] == 0.0


def test_surface_distance_and_occlusion():
    boxes = scene_boxes(_scene())
    p_room = np.array([[2.5, 2.5, 1.0],  # mid-room: nearest is the floor at 1.0
                       [4.3, 1.5, 0.7],  # inside the table, 5 cm below its top
                       [4.3, 1.5, 0.95],  # 20 cm above the table
                       [6.5, 2.5, 1.5]])  # outside the room, 0.5 m beyond the +x wall
    d = distance_to_boxes(_to_world(p_room), boxes)
    np.testing.assert_allclose(d, [1.0, 0.05, 0.2, 0.5], atol=1e-9)
    a = _to_world(np.array([[3.0, 1.5, 0.5], [3.0, 1.5, 0.5], [4.3, 1.5, 1.5]]))
    b = _to_world(np.array([[5.5, 1.5, 0.5], [3.8, 1.0, 0.75], [4.3, 1.5, 0.75]]))
    # through the table; to the table's own corner; straight down onto its top
    assert segments_blocked(a, b, boxes).tolist() == [True, False, False]


def test_depth_occlusion_path(tmp_path):
    far = _capture(tmp_path, depth=lambda i: np.full((CAM.height, CAM.width), 100.0, np.float32))
    near = _capture(tmp_path, depth=lambda i: np.full((CAM.height, CAM.width), 0.3, np.float32))
    gt = far.ground_truth
    out = _write(tmp_path / "rec", far, gt.R_wc, gt.centers)
    m = evaluate_reconstruction(far, out)
    assert m["reprojection_px"]["occlusion"] == "ground-truth depth" and m["reprojection_px"]["points"] >= 15
    assert evaluate_reconstruction(near, out)["reprojection_px"]["points"] == 0


def test_distorted_camera_clicks_in_raw_image(tmp_path):
    (tmp_path / "camera.json").write_text(json.dumps(
        {"model": "OPENCV", "width": 320, "height": 240, "params": [160, 160, 159.5, 119.5, -0.1, 0.02, 0.001, 0]}))
    cap = _capture(tmp_path)
    gt = cap.ground_truth
    rec_cam = Camera("OPENCV", 640, 480, np.array([320, 320, 319.5, 239.5, -0.1, 0.02, 0.001, 0]))  # 2x size
    out = _write(tmp_path / "rec", cap, gt.R_wc, gt.centers, camera=rec_cam)
    m = evaluate_reconstruction(cap, out, click_noise_px=0.0)
    assert m["reprojection_px"]["image"] == "320x240" and m["reprojection_px"]["max"] < 1e-6
    wrong = Camera("PINHOLE", 640, 480, np.array([320, 320, 319.5, 239.5]))
    m = evaluate_reconstruction(cap, _write(tmp_path / "w", cap, gt.R_wc, gt.centers, camera=wrong),
                                click_noise_px=0.0)
    assert m["reprojection_px"]["max"] < 1e-6  # a pinhole model describes the undistorted working image


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(20, 3))
    A = Rotation.random(random_state=1).as_matrix()
    s, R, t = umeyama(X, 2.5 * X @ A.T + [1, 2, 3])
    assert abs(s - 2.5) < 1e-12 and np.allclose(R, A, atol=1e-12) and np.allclose(t, [1, 2, 3], atol=1e-12)
