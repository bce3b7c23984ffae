"""The Manhattan vertical against the IMU's gravity (paper §3.1; the fallback is ours, issue #41)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from panosfm_graph.config import Config, with_overrides
from panosfm_graph.lines.detect import detect_segments
from panosfm_graph.lines.manhattan import gravity_aligned, manhattan_frame
from test_preprocess import make_capture


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


def test_gravity_aligned_keeps_the_heading():
    D = Rotation.from_euler("xz", [12.0, 30.0], degrees=True).as_matrix().T  # rows: a tilted Manhattan frame
    g = np.array([0.0, 0.0, 1.0])
    A = gravity_aligned(D, g)
    np.testing.assert_allclose(A @ A.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(A) == pytest.approx(1.0)
    np.testing.assert_allclose(A[2], g)
    heading = lambda v: np.degrees(np.arctan2(v[1], v[0]))  # noqa: E731
    assert heading(A[0]) == pytest.approx(heading(D[0]), abs=1e-9)  # x made horizontal, not turned


@pytest.mark.parametrize("tilt_deg,replaced", [(8.0, True), (2.0, False)])
def test_a_vertical_far_from_gravity_is_replaced_by_it(tilt_deg, replaced):
    """Rotations that disagree with the lines by a tilt (slanted lines, a wrong vanishing direction): the lines'
    vertical lies ``tilt_deg`` off gravity. Beyond manhattan.vertical_max_deg (5) gravity is taken instead; below
    it, and with the check off, the lines' vertical is kept."""
    cap = make_capture(n_frames=6, sweep_deg=60.0)
    cfg = with_overrides(Config(), detect={"workers": 1})
    segments = detect_segments(cap, cfg.detect)
    tilt = Rotation.from_euler("x", tilt_deg, degrees=True).as_matrix()
    R = np.einsum("ij,njk->nik", tilt, cap.R_wc_imu)
    g = np.array([0.0, 0.0, 1.0])
    lines_vertical = tilt @ g
    on = manhattan_frame(segments, cap.camera.K, R, cfg.manhattan).directions[2]
    off = manhattan_frame(segments, cap.camera.K, R,
                          with_overrides(cfg, manhattan={"vertical_max_deg": 0.0}).manhattan).directions[2]
    assert _angle_deg(off, lines_vertical) < 0.5
    if replaced:
        assert _angle_deg(on, g) < 1e-9
    else:
        np.testing.assert_allclose(on, off)
