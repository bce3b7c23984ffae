"""Point tracks (points/tracking.py, issue #40): corners followed by optical flow, the loop closed a turn apart.

On a small synthetic hand-held spin (true poses known) the tracks must be pure
(each one the same 3D point: triangulated with the true poses it reprojects
within a pixel), and frames a turn apart must share tracks (loop closure).
"""
from __future__ import annotations

import numpy as np
import pytest

from factors import project_points
from panosfm_graph.config import PointsConfig
from panosfm_graph.geometry import project, triangulate_dlt
from panosfm_graph.points import loop_pairs, rotation_homography, track_points
from panosfm_graph.synth import synthesize

FRAMES, SIZE = 120, (480, 270)  # synthesize may add frames past the turn: spin.n_frames counts them


@pytest.fixture(scope="module")
def spin(tmp_path_factory):
    from panosfm_graph.capture import load_capture

    root = synthesize(tmp_path_factory.mktemp("points") / "bedroom", "bedroom", FRAMES, SIZE, seed=2, gt_maps=False,
                      sway_m=0.05)
    return load_capture(root)


def test_rotation_homography_maps_a_pure_turn_exactly():
    from scipy.spatial.transform import Rotation

    K = np.array([[400.0, 0, 240], [0, 400.0, 135], [0, 0, 1]])
    R_i, R_j = Rotation.from_rotvec([[0.1, -0.2, 0.05], [0.05, 0.1, -0.1]]).as_matrix()
    P = np.array([[0.3, -0.2, 3.0], [-1.0, 0.5, 4.0]]) @ R_i.T  # in front of frame i, seen from the origin
    uv_i, _ = project(K, R_i, np.zeros(3), P)
    uv_j, _ = project(K, R_j, np.zeros(3), P)
    H = rotation_homography(K, R_i, R_j)
    q = np.c_[uv_i, np.ones(2)] @ H.T
    np.testing.assert_allclose(q[:, :2] / q[:, 2:], uv_j, atol=1e-9)


def test_tracks_are_pure_and_close_the_loop(spin):
    gt, K = spin.ground_truth, spin.camera.K
    R_imu = spin.R_wc_imu  # the IMU predicts where corners move: its drift is what LK must absorb
    pts = track_points(spin, R_imu, PointsConfig())
    assert pts.n >= 200 and np.all(np.diff(pts.frame) >= 0)
    n = spin.n_frames
    per_frame = np.bincount(pts.frame, minlength=n)
    assert np.median(per_frame) >= 50
    f, t, uv = pts.frame, pts.track, pts.xy.astype(np.float64)
    xn = (uv - K[:2, 2]) / np.diag(K)[:2]
    Xh = triangulate_dlt(gt.R_wc, gt.centers, t, f, xn, pts.n)
    proj, _ = project_points(gt.R_wc[f], gt.centers[f], Xh[t, :3] / Xh[t, 3:], K)
    err = np.hypot(*(proj - uv).T)
    assert np.median(err) < 0.3 and np.mean(err < 1.0) >= 0.95, (np.median(err), np.mean(err < 1.0))
    # loop closure: tracks seen both in the last frames and a turn earlier
    pairs = loop_pairs(R_imu, PointsConfig())
    assert pairs and all(i - j > n // 2 for i, j in pairs)
    first, last = np.full(pts.n, n), np.zeros(pts.n, int)
    np.minimum.at(first, t, f)
    np.maximum.at(last, t, f)
    assert np.sum(last - first > 0.75 * n) >= 20


def test_coarse_shift_finds_a_loop_drift_lk_alone_misses():
    """A faint, smooth wall texture shifted 120 px (the rotations' drift over a turn): the coarse correlation finds
    the shift within its quarter-resolution step; an image without texture gives none."""
    import cv2

    from panosfm_graph.points.tracking import _coarse_shift

    rng = np.random.default_rng(0)
    wall = cv2.GaussianBlur(rng.normal(128, 40, (700, 1200)).astype(np.float32), (0, 0), 6)
    wall = np.clip(wall, 0, 255).astype(np.uint8)
    g_i, g_j = wall[80:620, 100:1060], wall[60:600, 220:1180]  # content moves by (-120, +20) px from i to j
    np.testing.assert_allclose(_coarse_shift(g_i, g_j, np.eye(3)), [-120, 20], atol=4)
    flat = np.full((540, 960), 100, np.uint8)
    np.testing.assert_array_equal(_coarse_shift(flat, flat, np.eye(3)), [0, 0])


def test_a_fast_spin_is_tracked_in_every_frame(tmp_path):
    """60 frames per turn at 960x540 (6-degree steps): on a 0.3 m arm a wall 1 m away moves 24 px off the rotation's
    prediction per step, past the 20 px a 300-frame spin allows; the allowance grows with the spin's step
    (``points.parallax_ref_step_deg``), so every frame keeps its tracks (measured on this capture: 11 frames had
    none before) and they stay pure."""
    from panosfm_graph.capture import load_capture

    cap = load_capture(synthesize(tmp_path / "fast", "bedroom", 60, (960, 540), seed=21, gt_maps=False))
    gt, K = cap.ground_truth, cap.camera.K
    pts = track_points(cap, cap.R_wc_imu, PointsConfig())
    per_frame = np.bincount(pts.frame, minlength=cap.n_frames)
    assert per_frame.min() >= 6, np.flatnonzero(per_frame < 6)
    f, t, uv = pts.frame, pts.track, pts.xy.astype(np.float64)
    Xh = triangulate_dlt(gt.R_wc, gt.centers, t, f, (uv - K[:2, 2]) / np.diag(K)[:2], pts.n)
    proj, _ = project_points(gt.R_wc[f], gt.centers[f], Xh[t, :3] / Xh[t, 3:], K)
    err = np.hypot(*(proj - uv).T)
    assert np.median(err) < 0.3 and np.mean(err < 1.0) >= 0.95, (np.median(err), np.mean(err < 1.0))
