"""Issue #41 item 5: camera.json may omit the focal length; the pipeline estimates it from the Manhattan vanishing
points (synthetic captures with a known focal length)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

FRAMES = 60
SIZE = (640, 360)


def _without_focal(capture: Path) -> float:
    """Removes ``params`` from the capture's camera.json; returns the true focal length (px)."""
    path = capture / "camera.json"
    data = json.loads(path.read_text())
    focal = float(data.pop("params")[0])
    path.write_text(json.dumps(data))
    return focal


@pytest.fixture(scope="module")
def wide(tmp_path_factory) -> tuple[Path, float]:
    from panosfm_graph.synth import synthesize

    cap = synthesize(tmp_path_factory.mktemp("focal") / "wide", "living", FRAMES, SIZE, seed=0, gt_maps=False,
                     hfov_deg=80.0)
    return cap, _without_focal(cap)


def test_capture_without_focal_loads_with_a_provisional_one(wide):
    from panosfm_graph.capture import load_capture
    from panosfm_graph.capture.camera import PROVISIONAL_HFOV_DEG, hfov_deg

    cap = load_capture(wide[0])
    assert not cap.focal_given
    assert hfov_deg(cap.camera.K[0, 0], cap.camera.width) == pytest.approx(PROVISIONAL_HFOV_DEG)
    assert cap.camera.K[0, 2] == pytest.approx((SIZE[0] - 1) / 2)


@pytest.mark.parametrize("start", [0.8, 1.25])
def test_focal_from_the_vanishing_points_within_one_percent(wide, start):
    """From 20 % too short or 25 % too long a starting focal length, the estimate lands within 1 % of the truth
    (measured +0.43 %); the cost rises away from it."""
    from panosfm_graph.capture import load_capture
    from panosfm_graph.capture.camera import with_focal
    from panosfm_graph.config import Config
    from panosfm_graph.lines import detect_segments
    from panosfm_graph.lines.focal import estimate_focal

    cap, truth = load_capture(wide[0]), wide[1]
    cfg = Config()
    segments = detect_segments(cap, cfg.detect)
    est = estimate_focal(segments, cap.R_wc_imu, with_focal(cap.camera, start * truth), cfg.focal, cfg.manhattan)
    assert abs(est.focal_px / truth - 1.0) < 0.01
    assert est.sharpness > 1.05 and est.frames == FRAMES


def test_run_reports_and_writes_the_estimated_focal(wide, tmp_path):
    from panosfm_graph.pipeline import run_pipeline

    res = run_pipeline(wide[0], tmp_path / "out", rerun=False, views=False)
    foc = res.summary["focal"]
    assert foc["given"] is False and abs(foc["estimated"]["focal_px"] / wide[1] - 1.0) < 0.01
    assert "focal       estimated" in res.report()
    cam_line = [ln for ln in (tmp_path / "out" / "sparse" / "cameras.txt").read_text().splitlines()
                if ln and not ln.startswith("#")][0].split()
    assert abs(float(cam_line[4]) / wide[1] - 1.0) < 0.01  # PINHOLE w h fx fy cx cy
    assert res.summary["frames"]["registered"] >= 0.9 * FRAMES


def test_opencv_without_params_is_an_input_error(tmp_path):
    cap = tmp_path / "c"
    cap.mkdir()
    (cap / "camera.json").write_text(json.dumps({"model": "OPENCV", "width": 64, "height": 48}))
    r = subprocess.run([sys.executable, "-m", "panosfm_graph", "inspect", str(cap)], capture_output=True, text=True)
    assert r.returncode == 2 and "OPENCV needs its 'params'" in r.stderr


def test_inspect_says_the_focal_is_unknown(wide):
    r = subprocess.run([sys.executable, "-m", "panosfm_graph", "inspect", str(wide[0])], capture_output=True,
                       text=True)
    assert r.returncode == 0 and "focal length unknown" in r.stdout and "nan" not in r.stdout.lower()


def test_estimate_focal_flag_overrides_a_given_one(tmp_path):
    from panosfm_graph.cli import build_parser, config_from_args

    args = build_parser().parse_args(["run", "CAP", "OUT", "--estimate-focal"])
    assert config_from_args(args).focal.estimate is True
    assert config_from_args(build_parser().parse_args(["run", "CAP", "OUT"])).focal.estimate is False
