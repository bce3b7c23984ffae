"""The bundle adjustment with the point tracks joined (graph/joint_points.py, issue #40).

On a synthetic spin with ground truth: the poses the lines alone give are solved again with the corners tracked
over the spin; they must come closer to the truth (centres and rotations, after the orientations' alignment), the
corners must then fit within a fraction of a pixel, and the solution keep its scale. Where the lines would fit
worse than the bound allows, the solution is kept as it was.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from panosfm_graph.config import Config
from panosfm_graph.evaluate import orientation_alignment
from panosfm_graph.geometry import rotation_angle_deg
from panosfm_graph.synth import synthesize

FRAMES, SIZE = 100, (640, 360)


@pytest.fixture(scope="module")
def lines_only(tmp_path_factory):
    """The pipeline's result on a 100-frame bedroom spin with the point tracks kept out of the bundle adjustment."""
    from panosfm_graph.pipeline import run_pipeline

    root = tmp_path_factory.mktemp("joint")
    cap = synthesize(root / "bedroom", "bedroom", FRAMES, SIZE, seed=21, gt_maps=False)
    cfg = Config()
    cfg = dataclasses.replace(cfg, graph=dataclasses.replace(cfg.graph, points_joint_max_line_rms_ratio=0.0))
    res = run_pipeline(cap, root / "out", cfg, rerun=False, views=False)
    assert "points_in_ba" not in res.solution.residuals
    return res, cfg


def _errors(sol, gt):
    """Returns (centre errors over the true trajectory's diameter, rotation errors in deg) of the registered frames
    after the orientations' alignment (as tools/bench.py scores them)."""
    use = np.flatnonzero(sol.registered)
    al = orientation_alignment(sol.centers[use], gt.centers[use], sol.R_wc[use], gt.R_wc[use])
    diam = float(np.max(np.linalg.norm(gt.centers[:, None] - gt.centers[None], axis=2)))
    c = np.linalg.norm(al["scale"] * sol.centers[use] @ al["R"].T + al["t"] - gt.centers[use], axis=1) / diam
    return c, rotation_angle_deg(np.einsum("ij,njk->nik", al["R"], sol.R_wc[use]), gt.R_wc[use])


def _spread(c):
    return float(np.sqrt(np.mean(np.sum((c - c.mean(axis=0)) ** 2, axis=1))))


def test_points_bring_the_poses_closer_to_the_truth(lines_only):
    from panosfm_graph.graph import adjust_with_points
    from panosfm_graph.points import track_points

    res, cfg = lines_only
    sol, gt = res.solution, res.capture.ground_truth
    points = track_points(res.capture, res.preprocessed.R_wc, cfg.points)
    joint_cfg = dataclasses.replace(cfg.graph, points_joint_max_line_rms_ratio=2.0)
    out = adjust_with_points(res.preprocessed, res.tracks, res.relations, sol, points, joint_cfg, cfg.points)
    rec = out.residuals["points_in_ba"]
    assert rec["kept"] and rec["observations"] > 1000, rec
    assert rec["point_rms_px"][1] < 0.5 < rec["point_rms_px"][0], rec  # the corners now fit, before they did not
    c0, r0 = _errors(sol, gt)
    c1, r1 = _errors(out, gt)
    assert np.array_equal(out.registered, sol.registered)
    assert np.median(c1) < 0.7 * np.median(c0) and np.max(c1) < 0.05, (np.median(c0), np.median(c1), np.max(c1))
    assert np.median(r1) <= np.median(r0) + 0.01, (np.median(r0), np.median(r1))
    reg = sol.registered
    assert _spread(out.centers[reg]) == pytest.approx(_spread(sol.centers[reg]), rel=1e-9)  # the scale as it was


def test_lines_that_would_fit_worse_keep_the_solution(lines_only, monkeypatch):
    import panosfm_graph.graph.joint_points as jp
    from panosfm_graph.points import track_points

    res, cfg = lines_only
    sol = res.solution
    points = track_points(res.capture, res.preprocessed.R_wc, cfg.points)
    # the lines must end 0.1 px better: more than the joint solve gives them (measured 0.56 -> 0.55 px)
    monkeypatch.setattr(jp, "MIN_LINE_RMS_SLACK_PX", -0.1)
    strict = dataclasses.replace(cfg.graph, points_joint_max_line_rms_ratio=0.5)
    out = jp.adjust_with_points(res.preprocessed, res.tracks, res.relations, sol, points, strict, cfg.points)
    rec = out.residuals["points_in_ba"]
    assert not rec["kept"] and rec["line_rms_px"][1] > rec["line_rms_px"][0] - 0.1, rec
    assert np.array_equal(out.centers, sol.centers, equal_nan=True) and np.array_equal(out.R_wc, sol.R_wc, equal_nan=True)


def test_every_point_observation_joins(lines_only):
    """The joint solve sees every observation of the tracks (points.per_frame_joint 0), not the motion model's few
    per frame, and its poses come closer to the truth than with the cap (measured: rotations 0.038 -> 0.025 deg,
    centres 0.23 -> 0.16 % of the diameter, medians)."""
    from panosfm_graph.graph import adjust_with_points
    from panosfm_graph.points import track_points

    res, cfg = lines_only
    sol, gt = res.solution, res.capture.ground_truth
    points = track_points(res.capture, res.preprocessed.R_wc, cfg.points)
    joint_cfg = dataclasses.replace(cfg.graph, points_joint_max_line_rms_ratio=3.0)
    capped = dataclasses.replace(cfg.points, per_frame_joint=cfg.points.per_frame_graph)
    out_all = adjust_with_points(res.preprocessed, res.tracks, res.relations, sol, points, joint_cfg, cfg.points)
    out_cap = adjust_with_points(res.preprocessed, res.tracks, res.relations, sol, points, joint_cfg, capped)
    n_all, n_cap = out_all.residuals["points_in_ba"]["observations"], out_cap.residuals["points_in_ba"]["observations"]
    seen = np.isin(points.frame, np.flatnonzero(sol.registered))
    assert n_cap <= cfg.points.per_frame_graph * int(sol.registered.sum()) < n_all <= int(seen.sum()), (n_cap, n_all)
    c_all, r_all = _errors(out_all, gt)
    c_cap, r_cap = _errors(out_cap, gt)
    assert np.median(r_all) < 0.85 * np.median(r_cap), (np.median(r_cap), np.median(r_all))
    assert np.median(c_all) < 0.85 * np.median(c_cap), (np.median(c_cap), np.median(c_all))
