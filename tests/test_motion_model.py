"""The spin's motion model places the frames the lines leave without a pose, with an honest std (issue #40).

A synthetic spin (true poses of ``synth.spin_pose``, swaying 2 cm on a 0.5 m arm) whose
centres the "lines" fix on some stretches only: the motion model must place
the frames between them within their std of the truth, leave out those it
cannot place within its bound (with the reason), never move a line-fixed
frame, and ``graph.motion_model=False`` (``--strict``) must give the input
unchanged.
"""
from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from panosfm_graph.config import GraphConfig, PointsConfig
from panosfm_graph.data import Camera, LineModel, Solution
from panosfm_graph.graph import place_by_motion_model
from panosfm_graph.synth import make_scene, spin_params, spin_pose

F = 300


def _spin(sway_m: float, arm_m: float = 0.5):
    p = spin_params(make_scene("living", 0), F, seed=3, sway_m=sway_m, arm_m=arm_m)
    return spin_pose(p, np.arange(F) / 30.0)


def _inputs(R, c, fixed):
    pre = SimpleNamespace(R_wc=R, manhattan=SimpleNamespace(directions=np.eye(3)),
                          segments=SimpleNamespace(frame=np.zeros(0, np.int64), endpoints=np.zeros((0, 4))))
    tracks = SimpleNamespace(track_of=np.zeros(0, np.int64), n=0, axis=np.zeros(0, np.int8))
    lines = LineModel(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int8), np.zeros((0, 2)), np.zeros(0, bool))
    cam = Camera("PINHOLE", 960, 540, np.array([768.0, 768.0, 479.5, 269.5]))
    sol = Solution(R_wc=np.where(fixed[:, None, None], R, np.nan), centers=np.where(fixed[:, None], c, np.nan),
                   registered=fixed.copy(), lines=lines, camera=cam, metric=True, residuals={})
    return pre, tracks, sol


def _fixed_mask() -> np.ndarray:
    """Line-fixed stretches with gaps of 4 to 40 frames between them (a blank wall every so often)."""
    fixed = np.ones(F, bool)
    for a, n in ((20, 4), (60, 10), (110, 20), (170, 40), (250, 12)):
        fixed[a:a + n] = False
    return fixed


def test_placed_frames_lie_within_their_std_of_the_truth():
    R, c = _spin(0.02)
    fixed = _fixed_mask()
    pre, tracks, sol = _inputs(R, c, fixed)
    out = place_by_motion_model(pre, tracks, sol, GraphConfig())
    src = np.array(out.residuals["frame_source"], dtype=object)
    sig = np.array([np.nan if v is None else v for v in out.residuals["frame_sigma_rel"]])
    placed = src == "motion model"
    diameter = 2 * np.hypot(*np.ptp(c[:, :2], axis=0)) / np.sqrt(2)
    assert placed.sum() >= 20  # near the line-fixed frames
    err = np.linalg.norm(out.centers[placed] - c[placed], axis=1) / diameter
    z = err / sig[placed]
    assert np.median(z) < 1.5 and np.all(z < 4), (np.median(z), z.max())
    assert np.all(err < 0.05)  # within the accuracy bar, as the std bound promises
    # the line-fixed frames are untouched and marked so; the rest say why they were left out
    np.testing.assert_array_equal(out.centers[fixed], c[fixed])
    assert set(src[fixed]) == {"lines"}
    left = ~fixed & ~placed
    assert np.all(sig[left] > GraphConfig().motion_max_sigma_rel)
    assert np.all(out.registered == (fixed | placed))
    # the long gap's middle is the least certain
    assert sig[190] > sig[171]


def test_strict_leaves_the_solution_as_it_was():
    R, c = _spin(0.02)
    fixed = _fixed_mask()
    pre, tracks, sol = _inputs(R, c, fixed)
    out = place_by_motion_model(pre, tracks, sol, dataclasses.replace(GraphConfig(), motion_model=False))
    np.testing.assert_array_equal(out.registered, sol.registered)
    np.testing.assert_array_equal(out.centers, sol.centers)
    assert out.residuals["frame_source"] == ["lines" if f else None for f in fixed]


def test_a_shorter_arm_places_fewer_frames():
    """The bound is a share of the spin's diameter: on a short arm the model's std (graph.spin_sigma_m) is a larger
    share, and fewer frames pass it (none at 0.3 m: 2 cm is 3.3 % of its 0.6 m diameter)."""
    counts = []
    for arm in (0.5, 0.3):
        R, c = _spin(0.02, arm)
        pre, tracks, sol = _inputs(R, c, _fixed_mask())
        counts.append(place_by_motion_model(pre, tracks, sol, GraphConfig()).residuals["motion_model"]["placed"])
    assert counts[0] > counts[1] == 0


def test_run_reports_each_frames_source_and_lines_only_keeps_line_fixed_frames(tmp_path):
    """summary.json: frames.source / sigma_rel per frame, by_source counts; without the motion model and the joint
    solve: only "lines", the same frames, no point tracks in the bundle adjustment (by default they join it);
    --strict: only frames an independent solution confirms, none doubtful."""
    import json

    from panosfm_graph.cli import main
    from panosfm_graph.synth import synthesize

    cap = synthesize(tmp_path / "cap", scene="bedroom", n_frames=150, size=(480, 270), seed=2, gt_maps=False,
                     sway_m=0.05)
    runs, joint = {}, {}
    lines_only = ["--set", "graph.motion_model=False", "--set", "graph.points_joint_max_line_rms_ratio=0",
                  "--set", "verify.enabled=False"]
    for name, extra in (("default", []), ("strict", lines_only), ("confirmed", ["--strict"])):
        out = tmp_path / name
        assert main(["run", str(cap), str(out), "--no-rerun", "--resume", *extra]) == 0
        summary = json.loads((out / "summary.json").read_text())
        runs[name] = summary["frames"]
        joint[name] = summary["residuals"]["bundle_adjust"].get("points_in_ba")
        assert summary["residuals"]["bundle_adjust"]["lines_beyond_room"] >= 0  # the room's bound was checked
    assert joint["strict"] is None and joint["default"]["kept"], joint
    confirmed = runs["confirmed"]
    assert 0 < confirmed["registered"] <= runs["default"]["registered"] and not any(confirmed["doubtful"])
    assert all(s is None or g is not None for s, g in zip(confirmed["source"], confirmed["evidence_gap_rel"]))
    for fr in runs.values():
        assert len(fr["source"]) == fr["total"] == len(fr["sigma_rel"])
        assert sum(fr["by_source"].values()) == fr["registered"]
        assert fr["registered"] + len(fr["unregistered"]) == fr["total"]
    strict, default = runs["strict"], runs["default"]
    assert set(strict["by_source"]) <= {"lines"} and all(v is None for v in strict["sigma_rel"])
    assert default["by_source"].get("lines", 0) == strict["registered"]  # the motion model only adds frames
    placed = [i for i, s in enumerate(default["source"]) if s in ("motion model", "points")]
    assert all(default["model_sigma_rel"][i] <= 0.025 for i in placed)  # the motion model's own bound
    assert all(v is not None for v, r in zip(default["sigma_rel"], default["source"]) if r)  # every output frame


def _point_tracks(R, c, n_points=4000, noise_px=0.1, seed=0):
    """Texture corners on the walls of a 6 x 5 m room about the spin (z up), seen wherever they project into a frame;
    one track per point (its observations of every frame that sees it), ``noise_px`` Gaussian noise."""
    from panosfm_graph.data import PointTracks

    rng = np.random.default_rng(seed)
    K = np.array([[768.0, 0, 479.5], [0, 768.0, 269.5], [0, 0, 1]])
    side = rng.integers(0, 4, n_points)
    u = rng.uniform(-1, 1, n_points)
    P = np.stack([np.where(side < 2, np.where(side == 0, -3.0, 3.0), 3.0 * u),
                  np.where(side >= 2, np.where(side == 2, -2.5, 2.5), 2.5 * u),
                  rng.uniform(-1.2, 1.2, n_points)], axis=1)
    X = np.einsum("fji,fpj->fpi", R, P[None] - c[:, None])  # (F, P, 3) camera frame
    uv = X[..., :2] / X[..., 2:] * 768.0 + K[:2, 2]
    seen = (X[..., 2] > 0.5) & (uv[..., 0] > 0) & (uv[..., 0] < 959) & (uv[..., 1] > 0) & (uv[..., 1] < 539)
    f, p = np.nonzero(seen)
    xy = uv[f, p] + rng.normal(0, noise_px, (len(f), 2))
    return PointTracks(frame=f.astype(np.int32), track=p.astype(np.int32), xy=xy.astype(np.float32))


def test_point_tracks_place_a_long_stretch_and_correct_its_rotation_drift():
    """Lines fix the first third of a swaying spin; the rest is a blank stretch whose refined rotations drift
    0.8 deg in heading. With point tracks every frame is placed (source "points") within the accuracy bar, and
    their rotations are corrected: the points, not only the spin model, carry them."""
    from scipy.spatial.transform import Rotation

    from panosfm_graph.geometry import rotation_angle_deg

    R, c = _spin(0.05)
    fixed = np.arange(F) < 100
    drift = Rotation.from_rotvec(np.outer(np.clip(np.arange(F) - 100, 0, None) / (F - 100), [0, 0, np.deg2rad(0.8)]))
    R_drift = np.einsum("nij,njk->nik", drift.as_matrix(), R)
    pre, tracks, sol = _inputs(R, c, fixed)
    pre.R_wc = R_drift
    pts = _point_tracks(R, c)
    out = place_by_motion_model(pre, tracks, sol, GraphConfig(), points=pts)
    src = np.array(out.residuals["frame_source"], dtype=object)
    assert set(src[~fixed]) == {"points"} and out.registered.all()
    diameter = 2 * np.hypot(*np.ptp(c[:, :2], axis=0)) / np.sqrt(2)
    err = np.linalg.norm(out.centers - c, axis=1) / diameter
    assert err[~fixed].max() < 0.02, err[~fixed].max()
    sig = np.array([np.nan if v is None else v for v in out.residuals["frame_sigma_rel"]])[~fixed]
    z = err[~fixed] / sig  # the std is honest here (measured: median 0.65, max 1.17)
    assert np.median(z) < 1.5 and z.max() < 3, (np.median(z), z.max())
    rot_in = rotation_angle_deg(R_drift[~fixed], R[~fixed])
    rot_out = rotation_angle_deg(out.R_wc[~fixed], R[~fixed])  # measured: median 0.09, max 0.19 (in: 0.4, 0.8)
    assert rot_out.max() < 0.3 and np.median(rot_out) < 0.4 * np.median(rot_in), (rot_out.max(), np.median(rot_in))
    np.testing.assert_array_equal(out.centers[fixed], c[fixed])
    np.testing.assert_array_equal(out.R_wc[fixed], R[fixed])
    # without the points the same stretch is mostly left out (the spin model alone is too uncertain)
    alone = place_by_motion_model(pre, tracks, sol, GraphConfig())
    assert alone.residuals["motion_model"]["placed"] < 0.5 * out.residuals["motion_model"]["placed"]


def test_without_line_fixed_frames_the_point_tracks_alone_place_the_spin():
    """No frame fixed by lines (a bare room, issue #40): the point tracks place every frame in a gauge of their
    own (a stand point, the arm's length, one rotation). After the similarity alignment the centres are within
    the accuracy bar, the rotation drift the IMU had is corrected, and the gauge-free std is honest."""
    from scipy.spatial.transform import Rotation

    from panosfm_graph.evaluate import umeyama
    from panosfm_graph.geometry import rotation_angle_deg

    R, c = _spin(0.05)
    none = np.zeros(F, bool)
    drift = Rotation.from_rotvec(np.outer(np.arange(F) / F, [0, 0, np.deg2rad(1.5)]))
    R_drift = np.einsum("nij,njk->nik", drift.as_matrix(), R)
    pre, tracks, sol = _inputs(R, c, none)
    pre.R_wc = R_drift
    out = place_by_motion_model(pre, tracks, sol, GraphConfig(), points=_point_tracks(R, c))
    assert out.residuals["motion_model"]["anchor_free"] and out.registered.all()
    assert set(out.residuals["frame_source"]) == {"points"}
    s, A, t = umeyama(out.centers, c)
    diameter = 2 * np.hypot(*np.ptp(c[:, :2], axis=0)) / np.sqrt(2)
    err = np.linalg.norm(s * out.centers @ A.T + t - c, axis=1) / diameter
    assert err.max() < 0.02, err.max()
    sig = np.array(out.residuals["frame_sigma_rel"])
    assert np.median(err / sig) < 2.0 and np.percentile(err / sig, 90) < 4.0, (np.median(err / sig))
    rot_in = rotation_angle_deg(R_drift, R)
    R_al = np.einsum("ij,njk->nik", A, out.R_wc)
    rot_out = rotation_angle_deg(R_al, R)
    assert np.median(rot_out) < 0.3 * np.median(rot_in), (np.median(rot_out), np.median(rot_in))
    # without point tracks nothing is placed: the input comes back as it was
    alone = place_by_motion_model(pre, tracks, sol, GraphConfig())
    assert not alone.registered.any() and "motion_model" not in alone.residuals


def test_gauge_free_covariance_removes_the_similarity_and_keeps_the_rest():
    """A covariance made of the similarity's motions alone projects to zero; independent noise on the centres
    keeps its size (N large: 7 of 3N directions removed)."""
    from panosfm_graph.graph.motion_model import gauge_free_covariance

    rng = np.random.default_rng(0)
    c = rng.normal(size=(40, 3)) * [1.0, 1.0, 0.2]
    d = c - c.mean(axis=0)
    J = np.column_stack([np.tile(np.eye(3), (40, 1))] + [np.cross(np.eye(3)[a], d).ravel() for a in range(3)]
                        + [d.ravel()])
    G = J @ np.diag([1.0, 2.0, 3.0, 0.1, 0.2, 0.3, 0.5]) @ J.T
    assert np.abs(gauge_free_covariance(G, c)).max() < 1e-9
    C = gauge_free_covariance(0.01 * np.eye(120), c)
    assert 0.9 * 0.01 * 113 < np.trace(C) < 1.001 * 0.01 * 113  # trace: 3N - 7 directions of 0.01 each


def test_lines_at_poses_triangulates_the_lines_of_placed_frames():
    """Vertical edges of a room seen from a swaying spin: each track's line, triangulated at the true poses from
    its segments' interpretation planes (``graph.readout.lines_at_poses``), lies where the edge is, with its
    seen extent; a track whose segments disagree (another edge in one of its frames) is left out."""
    from panosfm_graph.geometry import project
    from panosfm_graph.graph.readout import lines_at_poses

    R, c = _spin(0.05)
    K = np.array([[768.0, 0, 479.5], [0, 768.0, 269.5], [0, 0, 1]])
    edges = np.array([[2.5, 2.0], [-2.5, 2.0], [-2.5, -2.0], [2.5, -2.0], [0.8, 2.0], [1.6, 2.0]])
    frame, ends, track = [], [], []
    for t, (x, y) in enumerate(edges):
        for i in range(F):
            p, d = project(K, R[i], c[i], np.array([[x, y, 0.3], [x, y, 1.1]]))
            if np.all(d > 0) and np.all((p[:, 0] > 0) & (p[:, 0] < 960)):
                frame.append(i), ends.append(p.ravel()), track.append(t)
    frame, ends, track = np.array(frame), np.array(ends), np.array(track)
    bad = np.flatnonzero(track == 5)[::2]  # edge 5: every other segment taken from 0.3 m further along the wall
    ends[bad, 0::2] += 768.0 * 0.3 / 3.0
    pre = SimpleNamespace(segments=SimpleNamespace(frame=frame, endpoints=ends), manhattan=SimpleNamespace(
        directions=np.eye(3)))
    tracks = SimpleNamespace(track_of=track, axis=np.full(len(edges), 2, np.int8), n=len(edges))
    lines = LineModel(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int8), np.zeros((0, 2)), np.zeros(0, bool))
    cam = Camera("PINHOLE", 960, 540, np.array([768.0, 768.0, 479.5, 269.5]))
    sol = Solution(R_wc=R, centers=c, registered=np.ones(F, bool), lines=lines, camera=cam, metric=True, residuals={})
    out = lines_at_poses(pre, tracks, sol)
    np.testing.assert_array_equal(out.valid, [True] * 5 + [False])
    np.testing.assert_allclose(out.taylor[:5, :2], edges[:5], atol=1e-6)
    np.testing.assert_allclose(out.endpoints[:5, [2, 5]], np.tile([0.3, 1.1], (5, 1)), atol=1e-6)


def test_lines_beyond_the_room_are_left_out():
    """``graph.readout.drop_lines_beyond_room``: a 9 x 7 m hall's edges seen from a stand point 2 m off its centre
    all stay (the far corner 1.5x the median edge's distance); a line slid along its rays to 150 m is marked invalid
    and counted; ratio 0 keeps every line; a line at (9, 4) m, 1.4x, stays."""
    from panosfm_graph.graph import drop_lines_beyond_room

    R, c = _spin(0.05)
    c = c + np.array([2.0, 1.0, 0.0])  # the stand point off the hall's centre
    corners = np.array([[4.5, 3.5], [-4.5, 3.5], [-4.5, -3.5], [4.5, -3.5]])
    along_x = np.array([[x, y] for y in (3.5, -3.5) for x in np.linspace(-4.0, 4.0, 5)])
    vertical = np.concatenate([corners, along_x, [[150.0, 40.0]]])  # the last one beyond the room
    T = len(vertical)
    taylor = np.column_stack([vertical, np.zeros(T)])
    lines = LineModel(taylor, np.tile([0.0, 0.0, 1.0], (T, 1)), np.full(T, 2, np.int8),
                      np.tile([-1.4, 2.6], (T, 1)), np.ones(T, bool))
    cam = Camera("PINHOLE", 960, 540, np.array([768.0, 768.0, 479.5, 269.5]))
    sol = Solution(R_wc=R, centers=c, registered=np.ones(F, bool), lines=lines, camera=cam, metric=True, residuals={})
    out = drop_lines_beyond_room(sol, 4.0)
    np.testing.assert_array_equal(out.lines.valid, [True] * (T - 1) + [False])
    assert out.residuals["lines_beyond_room"] == 1
    np.testing.assert_array_equal(out.lines.taylor, sol.lines.taylor)  # the lines themselves as they were
    assert drop_lines_beyond_room(sol, 0.0).lines.valid.all()
    closer = dataclasses.replace(lines, taylor=np.concatenate([taylor[:-1], [[9.0, 4.0, 0.0]]]))
    assert drop_lines_beyond_room(dataclasses.replace(sol, lines=closer), 4.0).lines.valid.all()  # a hall's edge


def _bent_spin(sway_m: float, bend: float):
    """(R, true centres, the centres the "lines" give: pushed sideways by up to ``bend`` of the diameter, the
    line-fixed frames (the first 200), the diameter): a wrong lines' solution, as on hall seed 12."""
    R, c = _spin(sway_m)
    diameter = 2 * np.hypot(*np.ptp(c[:, :2], axis=0)) / np.sqrt(2)
    bent = c.copy()
    bent[:, 0] += bend * diameter * np.sin(np.pi * np.arange(F) / 200) ** 2
    return R, c, bent, np.arange(F) < 200, diameter


def test_line_fixed_frames_the_points_disagree_with_are_replaced_by_the_points_poses(monkeypatch):
    """Lines fix two thirds of a swaying spin, but bent: their centres pushed sideways by up to 6 % of the
    diameter (a wrong lines' solution, as on hall seed 12). The points alone place the spin and put those
    frames elsewhere; every frame then gets the points' pose, moved onto the line-fixed frames' axes and scale,
    and the result lies within 2 % of the truth, the anchored placement never computed (points first). With the
    line-fixed frames where they are, nothing changes."""
    from panosfm_graph.geometry import umeyama
    from panosfm_graph.graph import motion_model

    placed = []
    place = motion_model._place
    monkeypatch.setattr(motion_model, "_place", lambda *a, anchor_free: placed.append(anchor_free) or
                        place(*a, anchor_free=anchor_free))

    R, c, bent, fixed, diameter = _bent_spin(0.05, 0.06)
    pts = _point_tracks(R, c)
    pre, tracks, sol = _inputs(R, bent, fixed)
    out = place_by_motion_model(pre, tracks, sol, GraphConfig(), points=pts)
    mm = out.residuals["motion_model"]
    assert mm.get("lines_replaced") and mm["lines_vs_points_rel"] > 0.01 and out.registered.all()
    assert set(out.residuals["frame_source"]) == {"points"}
    assert placed == [True]
    s, A, t = umeyama(out.centers, c)
    err = np.linalg.norm(s * out.centers @ A.T + t - c, axis=1) / diameter
    assert err.max() < 0.02, err.max()
    assert 0.9 < s < 1.1  # the line-fixed frames' scale kept
    pre, tracks, sol = _inputs(R, c, fixed)
    kept = place_by_motion_model(pre, tracks, sol, GraphConfig(), points=pts)
    assert not kept.residuals["motion_model"].get("lines_replaced")
    assert kept.residuals["motion_model"]["lines_vs_points_rel"] < 0.01
    assert placed == [True, True, False]  # the points' placement computed once, reused for the comparison
    np.testing.assert_array_equal(kept.centers[fixed], c[fixed])


def test_the_points_placement_made_before_is_reused_and_decides_as_the_motion_model_does(monkeypatch):
    """``place_by_points_alone`` + ``points_replace_lines`` (the pipeline's test before the spin style's trial) say
    what ``place_by_motion_model`` then does: bent line-fixed frames replaced, true ones kept; given that placement,
    the motion model does not make it again and gives the same result."""
    from panosfm_graph.graph import motion_model, place_by_points_alone, points_replace_lines

    R, c, bent, fixed, diameter = _bent_spin(0.05, 0.06)
    pts = _point_tracks(R, c)
    cfg = GraphConfig()
    for centres, replaced in ((bent, True), (c, False)):
        pre, tracks, sol = _inputs(R, centres, fixed)
        free = place_by_points_alone(pre, tracks, sol, cfg, pts, PointsConfig())
        assert free is not None and free.registered.all()
        assert points_replace_lines(sol, free, cfg) is replaced
        placed = []
        place = motion_model._place
        monkeypatch.setattr(motion_model, "_place", lambda *a, anchor_free: placed.append(anchor_free) or
                            place(*a, anchor_free=anchor_free))
        out = place_by_motion_model(pre, tracks, sol, cfg, points=pts, free=free)
        monkeypatch.undo()
        assert placed == ([] if replaced else [False])  # the anchor-free placement not made again
        assert bool(out.residuals["motion_model"].get("lines_replaced")) is replaced
        again = place_by_motion_model(pre, tracks, sol, cfg, points=pts)
        np.testing.assert_allclose(out.centers, again.centers, atol=1e-9)
    pre, tracks, sol = _inputs(R, c, fixed)  # a streamed preview (graph.motion_anchored off): the points' placement
    light = place_by_motion_model(pre, tracks, sol, dataclasses.replace(cfg, motion_anchored=False), points=pts)
    mm = light.residuals["motion_model"]
    assert mm["lines_replaced"] and mm["anchored"] is False and mm["lines_vs_points_rel"] < 0.01
    assert light.registered.all() and set(light.residuals["frame_source"]) == {"points"}
    pre, tracks, sol = _inputs(R, c, np.ones(F, bool))  # every frame fixed by lines: nothing for the points to do
    assert place_by_points_alone(pre, tracks, sol, cfg, pts, PointsConfig()) is None
    assert place_by_points_alone(pre, tracks, _inputs(R, c, fixed)[2], cfg, None, PointsConfig()) is None


def test_the_steady_trial_is_skipped_where_the_point_tracks_replace_the_lines(monkeypatch):
    """The pipeline's bundle adjustment stage: where the point tracks alone place every frame and put the
    line-fixed frames elsewhere (bent lines), the steady style's solve is not tried (its result would be thrown
    away: docs/decisions.md#points-before-the-spin-style) and the result says so; with true lines, or on a steady
    spin (the points' centres on one circle: the steady style could be kept), the trial runs as before."""
    from pathlib import Path

    import panosfm_graph.graph as graph
    from panosfm_graph.config import Config, with_overrides
    from panosfm_graph.pipeline import RunResult, _bundle_adjust

    cfg = with_overrides(Config(), graph={"points_joint_max_line_rms_ratio": 0.0})
    for sway, bend, skipped in ((0.05, 0.06, True), (0.05, 0.0, False), (0.0, 0.06, False)):
        R, c, centres, fixed, _ = _bent_spin(sway, bend)
        pts = _point_tracks(R, c)
        pre, tracks, sol = _inputs(R, centres, fixed)
        trials = []

        def steady(*a, **k):
            trials.append(1)
            hand = a[-1]
            res = dict(hand.residuals, spin_style="hand-held", steady_check={"kept": False})
            return dataclasses.replace(hand, residuals=res), None

        monkeypatch.setattr(graph, "bundle_adjust", lambda *a, **k: sol)
        monkeypatch.setattr(graph, "solve_at_final_scale", lambda *a: a[-1])
        monkeypatch.setattr(graph, "steady_or_hand_held", steady)
        run = RunResult(out_dir=Path("."), summary={}, tracks=tracks, relations=None, linear=sol)
        out = _bundle_adjust(pre, run, cfg, None, lambda: pts)
        monkeypatch.undo()
        assert trials == ([] if skipped else [1])
        assert out.residuals["spin_style"] == "hand-held"
        assert ("skipped" in out.residuals["steady_check"]) is skipped
        assert bool(out.residuals["motion_model"].get("lines_replaced")) is (bend > 0)
        assert out.registered.all()


def test_lines_adjusted_at_held_poses_follow_their_relations():
    """A far wall (5 m, as in a large hall) seen from a swaying spin with 0.7 px of segment noise: each edge
    triangulated alone at the true poses scatters by centimetres about the wall; adjusted with the poses held
    and the coplanarities between the wall's edges (``graph.held_poses.adjust_lines_at_poses``) they lie on it
    (half the error or less), a line started 0.4 m off (fitted to other poses) comes back onto the wall, and the
    poses do not move. Without the relations the lines stay as scattered as triangulated alone."""
    from panosfm_graph.data import PARALLEL, Relations
    from panosfm_graph.geometry import project
    from panosfm_graph.graph.held_poses import adjust_lines_at_poses
    from panosfm_graph.graph.readout import lines_at_poses

    R, c = _spin(0.05)
    K = np.array([[768.0, 0, 479.5], [0, 768.0, 269.5], [0, 0, 1]])
    xs = np.linspace(-3.0, 3.0, 9)
    edges = np.c_[xs, np.full(len(xs), 5.0)]  # vertical edges on the wall y = 5
    rng = np.random.default_rng(0)
    frame, ends, track = [], [], []
    for t, (x, y) in enumerate(edges):
        for i in range(F):
            p, d = project(K, R[i], c[i], np.array([[x, y, 0.3], [x, y, 1.1]]))
            if np.all(d > 0) and np.all((p[:, 0] > 0) & (p[:, 0] < 960)):
                frame.append(i), ends.append(p.ravel() + rng.normal(0, 0.7, 4)), track.append(t)
    frame, ends, track = np.array(frame), np.array(ends), np.array(track)
    M = np.eye(3)
    pre = SimpleNamespace(segments=SimpleNamespace(frame=frame, endpoints=ends),
                          manhattan=SimpleNamespace(directions=M))
    T = len(edges)
    tracks = SimpleNamespace(track_of=track, axis=np.full(T, 2, np.int8), n=T)
    a = np.arange(T - 1)
    relations = Relations(kind=np.full(T - 1, PARALLEL, np.int8), track_a=a.astype(np.int32),
                          track_b=(a + 1).astype(np.int32), normal_axis=np.ones(T - 1, np.int8),
                          support=np.full(T - 1, 5, np.int32))
    empty = LineModel(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int8), np.zeros((0, 2)), np.zeros(0, bool))
    cam = Camera("PINHOLE", 960, 540, np.array([768.0, 768.0, 479.5, 269.5]))
    sol = Solution(R_wc=R, centers=c, registered=np.ones(F, bool), lines=empty, camera=cam, metric=True,
                   residuals={"scale": "metric"})
    alone = lines_at_poses(pre, tracks, sol)
    assert alone.valid.all()
    err_alone = np.abs(alone.taylor[:, 1] - 5.0)
    assert np.median(err_alone) > 0.005  # the noise shows: centimetres at 5 m from a 1 m spin
    stale_taylor = alone.taylor.copy()
    stale_taylor[4, 1] += 0.4  # a line the bundle adjustment fitted to other poses
    start = dataclasses.replace(sol, lines=dataclasses.replace(alone, taylor=stale_taylor))
    out = adjust_lines_at_poses(pre, tracks, relations, start, GraphConfig())
    err = np.abs(out.lines.taylor[:, 1] - 5.0)
    assert np.median(err) < 0.5 * np.median(err_alone), (np.median(err), np.median(err_alone))
    assert err[4] < 0.02, err[4]
    np.testing.assert_allclose(out.lines.taylor[:, 0], xs, atol=0.01)  # along the wall: as seen
    np.testing.assert_array_equal(out.centers, c)
    np.testing.assert_array_equal(out.R_wc, R)
    assert out.residuals["lines_held_poses"]["relations"] == T - 1
    no_rel = adjust_lines_at_poses(pre, tracks, relations, start, dataclasses.replace(
        GraphConfig(), coplanarity_parallel=False))
    err_no_rel = np.abs(no_rel.lines.taylor[:, 1] - 5.0)
    assert np.median(err_no_rel) > 0.7 * np.median(err_alone), (np.median(err_no_rel), np.median(err_alone))


def test_rotations_the_vanishing_points_fix_hold_the_points_placement_unless_the_tracks_refute_them():
    """Issue #63: the point tracks alone trade a rotation for a shift of the centres; frames whose horizontal lines
    fix their heading are held to their preprocessed (vanishing-point) rotations, which must bring the rotations to
    the truth where those are right, and be refused (the free placement kept) where a heading ramp of 3 deg the
    preprocessing left makes the tracks fit worse."""
    from scipy.spatial.transform import Rotation

    from panosfm_graph.evaluate import umeyama
    from panosfm_graph.geometry import rotation_angle_deg

    R, c = _spin(0.05)
    pts = _point_tracks(R, c, noise_px=0.3)
    diameter = 2 * np.hypot(*np.ptp(c[:, :2], axis=0)) / np.sqrt(2)

    def place(ramp_deg, vp_sigma_deg):
        pre, _, sol = _inputs(R, c, np.zeros(F, bool))
        drift = Rotation.from_rotvec(np.outer(np.arange(F) / F, [0, 0, np.deg2rad(ramp_deg)]))
        pre.R_wc = np.einsum("nij,njk->nik", drift.as_matrix(), R)
        pre.labels = np.zeros(2 * F, np.int8)  # two horizontal Manhattan segments in every frame
        pre.segments = SimpleNamespace(frame=np.repeat(np.arange(F), 2), endpoints=np.zeros((2 * F, 4)))
        tracks = SimpleNamespace(track_of=np.full(2 * F, -1, np.int64), n=0, axis=np.zeros(0, np.int8))
        out = place_by_motion_model(pre, tracks, sol, GraphConfig(), points=pts,
                                    points_config=PointsConfig(vp_sigma_deg=vp_sigma_deg))
        s, A, t = umeyama(out.centers, c)
        err = np.linalg.norm(s * out.centers @ A.T + t - c, axis=1) / diameter
        rot = rotation_angle_deg(np.einsum("ij,njk->nik", A, out.R_wc), R)
        return out.residuals["motion_model"]["vanishing_point_rotations"], np.median(err), np.median(rot)

    free = place(0.0, 0.0)
    held = place(0.0, 0.2)
    assert free[0] is None and held[0]["kept"]
    # measured: rotations 0.45 -> 0.10 deg median, centres 0.38 -> 0.29 % of the diameter
    assert held[2] < 0.4 * free[2] and held[1] < free[1], (free, held)
    refused = place(3.0, 0.2)
    assert not refused[0]["kept"] and refused[0]["fit_px"][1] > 1.05 * refused[0]["fit_px"][0]
    assert refused[2] == pytest.approx(place(3.0, 0.0)[2])  # the free placement, as it was
