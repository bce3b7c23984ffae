"""Relation detection (paper §3.2): known small scenes, and wrong normals rejected."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from panosfm_graph.config import NormalsConfig, RelationsConfig
from panosfm_graph.data import (FLOOR, JUNCTION, ORTHOGONAL, PARALLEL, Camera, Capture, GroundTruth, ManhattanFrame,
                                NormalMaps, Preprocessed, Relations, Segments, Tracks)
from panosfm_graph.normals import estimate_normals
from panosfm_graph.relations import detect_relations, relations_true
from panosfm_graph.synth.problem import make_problem
from panosfm_graph.synth.render import raycast

# ---------------------------------------------------------------- a hand-built frame with known answers
# Camera looks along world +y, level: camera x = world x, camera y = world -z, camera z = world y.
R_WC = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
CAM = Camera("PINHOLE", 200, 100, np.array([100.0, 100.0, 99.5, 49.5]))


def _frame(segs, labels, n_frames=1):
    """Returns (Preprocessed, Tracks, NormalMaps): one track per segment, the same view repeated."""
    ep = np.tile(np.asarray(segs, np.float32), (n_frames, 1))
    S1 = len(segs)
    frame = np.repeat(np.arange(n_frames, dtype=np.int32), S1)
    seg = Segments(ep, frame, np.arange(0, (n_frames + 1) * S1, S1, dtype=np.int64), np.zeros((len(ep), 3), np.uint8))
    lab = np.tile(np.asarray(labels, np.int8), n_frames)
    R = np.repeat(R_WC[None], n_frames, axis=0)
    pre = Preprocessed(seg, ManhattanFrame(np.eye(3)), lab, R, R)
    tracks = Tracks(np.tile(np.arange(S1, dtype=np.int32), n_frames), np.asarray(labels, np.int8))
    # normals (world): left half a wall facing -y (normal axis 1), right half facing -x (axis 0),
    # bottom rows (below the horizon) the floor (+z)
    h, w = 50, 100
    n = np.zeros((h, w, 3), np.float32)
    n[:, :50] = [0, -1, 0]
    n[:, 50:] = [-1, 0, 0]
    n[40:] = [0, 0, 1]
    maps = np.repeat(n[None], n_frames, axis=0).astype(np.float16)
    return pre, tracks, NormalMaps(maps, np.ones((n_frames, h, w), bool), 0.5, "test")


SEGS = [
    (10, 20, 80, 20),   # 0: x line on the left wall (label 0)
    (20, 10, 20, 60),   # 1: z line on the left wall (label 2)
    (70, 10, 70, 60),   # 2: z line on the left wall (label 2)
    (130, 15, 130, 60),  # 3: z line on the right wall (label 2)
    (40, 90, 90, 90),   # 4: x line on the floor (label 0)
    (160, 30, 195, 30),  # 5: y line on the right wall (label 1)
]
LABELS = [0, 2, 2, 2, 0, 1]


def _rows(rel, kind):
    m = rel.kind == kind
    return set(zip(rel.track_a[m].tolist(), rel.track_b[m].tolist(), rel.normal_axis[m].tolist()))


def test_known_frame_relations():
    pre, tracks, nm = _frame(SEGS, LABELS, n_frames=2)
    ours = detect_relations(pre, tracks, nm, CAM, RelationsConfig(parallel=True))
    # our crossed-quad rule: segment 0 lies between the z lines 1 and 2 (a poster edge here, but it could
    # as well be a cabinet's outline): that pair is dropped, the others stay
    assert (1, 2, 1) not in _rows(ours, PARALLEL) and (0, 1, 1) in _rows(ours, ORTHOGONAL)
    rel = detect_relations(pre, tracks, nm, CAM, RelationsConfig(parallel=True, quad_clear_frac=0.0))  # the paper's test
    ortho, par = _rows(rel, ORTHOGONAL), _rows(rel, PARALLEL)
    assert (0, 1, 1) in ortho and (0, 2, 1) in ortho  # x and z lines on the y-facing wall
    assert (1, 2, 0) not in par and (1, 2, 1) in par  # parallel z lines: plane normal y, not x
    assert (2, 3, 1) not in par and (2, 3, 0) not in par  # quad straddles the corner: mixed normals
    assert (3, 5, 0) in ortho  # z and y lines on the x-facing wall: plane normal x
    assert not any(a in (0, 1, 2) and b in (3, 5) for a, b, _ in ortho)  # never across the corner
    assert _rows(rel, FLOOR) == {(4, -1, 2)}
    # junctions: endpoints within 0.1 * 100 px: segment 0 (10,20) and segment 1 (20,10): 14 px -> no;
    # segment 0's end (80,20) and segment 2 (70,10): 14 px -> no
    assert _rows(rel, JUNCTION) == set()
    assert set(rel.support.tolist()) == {2}  # each relation seen in both frames, counted once per frame
    assert np.all(rel.track_a[rel.kind != FLOOR] < rel.track_b[rel.kind != FLOOR])


# the paper's endpoint test only, in every frame
PAPER_JUNCTION = dict(junction_corner_frac=0.0, junction_normals=False, junction_border_px=0.0, junction_min_support=1)
ONE_FRAME = dict(junction_min_support=1)  # the hand-built scenes below are one frame


def test_junction_threshold():
    segs = [(20, 20, 80, 20), (84, 24, 84, 70), (20, 30, 20, 90)]  # 0-1 ends 5.7 px apart; 0-2 10 px
    pre, tracks, nm = _frame(segs, [0, 2, 1])
    rel = detect_relations(pre, tracks, nm, CAM, RelationsConfig(parallel=True, junction_dist_frac=0.08, **PAPER_JUNCTION))
    assert _rows(rel, JUNCTION) == {(0, 1, 1)}
    rel = detect_relations(pre, tracks, nm, CAM, RelationsConfig(parallel=True, junction_dist_frac=0.12, **PAPER_JUNCTION))
    assert _rows(rel, JUNCTION) == {(0, 1, 1), (0, 2, 2)}


def test_junction_min_support_drops_single_frame_junctions():
    """Option junction_min_support: a junction seen in fewer frames is dropped (the others stay)."""
    segs = [(20, 20, 80, 20), (84, 24, 84, 70)]  # ends 5.7 px apart
    cfg = RelationsConfig(parallel=True, junction_dist_frac=0.08, **PAPER_JUNCTION)
    for frames, need, found in ((1, 1, True), (1, 2, False), (2, 2, True)):
        pre, tracks, nm = _frame(segs, [0, 2], n_frames=frames)
        rel = detect_relations(pre, tracks, nm, CAM, dataclasses.replace(cfg, junction_min_support=need))
        assert (_rows(rel, JUNCTION) == {(0, 1, 1)}) == found, (frames, need)


def test_junction_needs_an_l_corner_with_consistent_normals():
    """Beyond the paper: the segments must meet (not merely end near each other) and the L must be one face."""
    segs = [
        (20, 20, 80, 20), (82, 22, 82, 70),  # 0-1: an L on the y-facing wall (corner (82, 20), 2 px from both)
        (20, 40, 60, 40), (66, 44, 66, 75),  # 2-3: ends 7 px apart but 6 px short of the lines' intersection
        (20, 55, 80, 55), (80, 55, 80, 65),  # 4-5: meet, labels 0 and 1 (plane normal z) but the L is on the wall
    ]
    labels = [0, 2, 0, 2, 0, 1]

    def found(cfg):  # each pair in a frame of its own (the pairs' lines would cross each other's quads)
        out = set()
        for a in (0, 2, 4):
            pre, tracks, nm = _frame(segs[a:a + 2], labels[a:a + 2])
            out |= {(a + i, a + j, k) for i, j, k in _rows(detect_relations(pre, tracks, nm, CAM, cfg), JUNCTION)}
        return out

    paper = found(RelationsConfig(parallel=True, **PAPER_JUNCTION))
    assert {(0, 1, 1), (2, 3, 1)} <= paper
    ours = found(RelationsConfig(parallel=True, **ONE_FRAME))
    assert (0, 1, 1) in ours
    assert (2, 3, 1) not in ours  # a gap: the L-corner test rejects it
    assert (4, 5, 2) not in ours  # normals say the inside of the L is the wall (y), not a floor (z)
    no_normals = found(RelationsConfig(parallel=True, junction_normals=False, **ONE_FRAME))
    assert (2, 3, 1) not in no_normals and (0, 1, 1) in no_normals


def test_junction_cut_by_the_image_border_is_no_corner():
    """Beyond the paper: two lines whose ends meet where the frame cuts them show no corner (junction_border_px)."""
    labels = [0, 2]

    def found(top, cfg):  # an x line and a z line meeting at (60, top) on the y-facing wall, seen in two frames
        pre, tracks, nm = _frame([(10, top, 60, top), (60, top, 60, top + 45)], labels, n_frames=2)
        return _rows(detect_relations(pre, tracks, nm, CAM, cfg), JUNCTION)

    ours = RelationsConfig()
    assert ours.junction_border_px > 0
    assert found(10.0, ours) == {(0, 1, 1)}  # the corner inside the image
    assert found(0.5, ours) == set()  # both ends on the top row: cut by the frame
    assert found(0.5, dataclasses.replace(ours, junction_border_px=0.0)) == {(0, 1, 1)}


def test_switches_turn_relation_types_off():
    pre, tracks, nm = _frame(SEGS, LABELS)
    rel = detect_relations(pre, tracks, nm, CAM, RelationsConfig(parallel=True, orthogonal=False, floor=False, quad_clear_frac=0.0))
    assert not np.any(rel.kind == ORTHOGONAL) and not np.any(rel.kind == FLOOR)
    assert np.any(rel.kind == PARALLEL)


def test_untracked_segments_are_ignored():
    pre, tracks, nm = _frame(SEGS, LABELS)
    tr = Tracks(np.where(np.arange(len(SEGS)) == 0, -1, tracks.track_of).astype(np.int32), tracks.axis)
    rel = detect_relations(pre, tr, nm, CAM, RelationsConfig(parallel=True))
    assert 0 not in set(rel.track_a.tolist()) | set(rel.track_b.tolist())


# ---------------------------------------------------------------- a ray-cast room along a spin


@pytest.fixture(scope="module")
def spin():
    P = make_problem("living", n_frames=16, size=(320, 180), seed=0)
    cam, sc = P.camera, P.scene
    hits = lambda i: raycast(sc, cam.K, P.gt_R_wc[i], P.gt_centers[i], (cam.width, cam.height))  # noqa: E731
    gt = GroundTruth(R_wc=P.gt_R_wc, centers=P.gt_centers, lines=np.zeros((0, 6)), line_labels=np.zeros(0, np.int8),
                     scene={}, normals=lambda i: hits(i)["normal_cam"], depth=lambda i: hits(i)["depth"],
                     has_normals=True, has_depth=True)
    cap = Capture(None, cam, tuple(map(str, range(P.n_frames))), np.arange(P.n_frames) / 30.0,
                  P.preprocessed.R_wc_imu, gt, lambda i: None)
    nm = estimate_normals(cap, P.preprocessed, NormalsConfig(source="oracle", width=160))
    L = np.concatenate([sc.to_room(P.gt_track_lines[:, :3]), sc.to_room(P.gt_track_lines[:, 3:])], axis=1)
    return P, nm, L


def test_oracle_relations_on_a_spin(spin):
    P, nm, L = spin
    rel = detect_relations(P.preprocessed, P.tracks, nm, P.camera, RelationsConfig(parallel=True))
    ok = relations_true(rel, L, float(P.scene.room_min[2]), tol_m=0.05)
    for kind in (ORTHOGONAL, PARALLEL):
        m = rel.kind == kind
        assert m.sum() >= 10
        # measured 0.90-0.95 (errors: thin fixtures 1-5 cm off the wall; occluding edges)
        assert ok[m].mean() >= 0.8, (kind, ok[m].mean())
    # the paper's endpoint test finds every generator junction (shared GT endpoint) ...
    gm = P.relations.kind == JUNCTION
    truth = set(zip(P.relations.track_a[gm].tolist(), P.relations.track_b[gm].tolist(),
                    P.relations.normal_axis[gm].tolist()))
    paper = detect_relations(P.preprocessed, P.tracks, nm, P.camera, RelationsConfig(parallel=True, **PAPER_JUNCTION))
    assert len(truth & _rows(paper, JUNCTION)) >= 0.9 * len(truth)  # measured 0.98, precision 0.85
    # ... ours keeps those whose L is a visible face: measured precision 1.0, recall 0.57 (junctions of
    # faces hidden from the camera, e.g. the top of a box above eye level, are dropped)
    m = rel.kind == JUNCTION
    assert ok[m].mean() >= 0.95, ok[m].mean()
    one = detect_relations(P.preprocessed, P.tracks, nm, P.camera, RelationsConfig(parallel=True, **ONE_FRAME))
    assert len(truth & _rows(one, JUNCTION)) >= 0.45 * len(truth)
    # junction_min_support 2 (the default) keeps those seen in two frames or more: measured recall 0.32 (19 / 60)
    assert _rows(rel, JUNCTION) <= _rows(one, JUNCTION)
    assert len(truth & _rows(rel, JUNCTION)) >= 0.25 * len(truth)
    assert np.all(rel.track_a < P.tracks.n) and np.all(rel.track_b < P.tracks.n)


@pytest.mark.parametrize("const", [(1.0, 1.0, 1.0), "random"])
def test_wrong_normals_reject_quad_coplanarities(spin, const):
    """Constant off-axis normals or random normals: no orthogonal / parallel coplanarity is accepted."""
    P, nm, L = spin
    if const == "random":
        n = np.random.default_rng(0).normal(size=nm.maps.shape)
    else:
        n = np.broadcast_to(np.asarray(const, float) @ P.preprocessed.manhattan.directions, nm.maps.shape)
    n = (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float16)
    bad = NormalMaps(n, np.ones_like(nm.valid), nm.scale, "wrong")
    rel = detect_relations(P.preprocessed, P.tracks, bad, P.camera, RelationsConfig(parallel=True))
    assert np.sum((rel.kind == ORTHOGONAL) | (rel.kind == PARALLEL)) == 0
    assert np.sum(rel.kind == FLOOR) == 0
    good = detect_relations(P.preprocessed, P.tracks, nm, P.camera, RelationsConfig(parallel=True))
    assert np.sum(good.kind == ORTHOGONAL) > 10  # the same pairs are accepted with the right normals


# ---------------------------------------------------------------- a real capture through the real pipeline


@pytest.fixture(scope="module")
def real_capture(tmp_path_factory):
    """A small synthetic capture run through the pipeline up to the tracks; GT edges mapped to the tracks."""
    import importlib.util
    import subprocess
    import sys
    from pathlib import Path

    from panosfm_graph.config import Config
    from panosfm_graph.pipeline import run_pipeline

    spec = importlib.util.spec_from_file_location(
        "bench_relations", Path(__file__).resolve().parents[1] / "tools" / "bench_relations.py")
    bench = importlib.util.module_from_spec(spec)
    sys.modules.setdefault(spec.name, bench)  # its dataclass needs the module registered
    spec.loader.exec_module(sys.modules[spec.name])
    bench = sys.modules[spec.name]
    root = tmp_path_factory.mktemp("relcap")
    cap = root / "cap"
    subprocess.run([sys.executable, "-m", "panosfm_graph", "synth", str(cap), "--scene", "living", "--frames",
                    "200", "--size", "320x180", "--seed", "0"], check=True, stdout=subprocess.DEVNULL)
    res = run_pipeline(cap, root / "out", Config(), rerun=False, views=False, stop_after="track")
    g = bench.ground_truth_view(res.capture, res.preprocessed, res.tracks)
    nm = estimate_normals(res.capture, res.preprocessed, NormalsConfig(source="oracle", width=160))
    return bench, res, g, nm


def test_real_capture_precision_with_oracle_normals(real_capture):
    bench, res, g, nm = real_capture
    pre, tracks, cam = res.preprocessed, res.tracks, res.capture.camera
    # the judge knows nearly every track's GT edge (measured 0.96 with the fragments of a line as separate tracks,
    # 0.88 with them joined: tracking.merge_gap_frames leaves the texture tracks a larger share)
    assert np.mean(g.track_edge >= 0) > 0.85
    truth = bench.gt_relation_sets(pre, tracks, g, 0.02)
    # the judge agrees with the GT relation sets it builds (consistency of the two GT views)
    for kind, rows in truth.items():
        if rows:
            a, b, k = (np.array(v) for v in zip(*sorted(rows)))
            R = Relations(np.full(len(a), kind, np.int8), a.astype(np.int32), b.astype(np.int32), k.astype(np.int8),
                          np.ones(len(a), np.int32))
            sc, ok = bench.score(R, g, truth, 0.02)
            assert np.all(ok == 1), (kind, np.mean(ok == 1))
    ours, _ = bench.score(detect_relations(pre, tracks, nm, cam, RelationsConfig(parallel=True)), g, truth, 0.02)
    paper, _ = bench.score(detect_relations(pre, tracks, nm, cam, RelationsConfig(parallel=True, **PAPER_JUNCTION)), g, truth, 0.02)
    # measured (living, 200 frames 320x180): orthogonal 0.79, parallel 0.89, junction 0.96 (24 seen in two frames
    # or more; paper's test 0.6x)
    assert ours["orthogonal"]["precision"] >= 0.7 and ours["orthogonal"]["recall"] >= 0.25
    assert ours["parallel"]["precision"] >= 0.8 and ours["parallel"]["recall"] >= 0.25
    assert ours["junction"]["precision"] >= 0.9 and ours["junction"]["n"] >= 20
    assert ours["junction"]["precision"] >= paper["junction"]["precision"] + 0.15
    assert ours["floor"]["recall"] >= 0.8  # floor precision is low (furniture tops): see the module docstring


def test_quad_valid_share():
    """A quad half without normals passes at the default share (0.5) and fails when 95 % must be known."""
    pre, tracks, nm = _frame(SEGS, LABELS)
    valid = nm.valid.copy()
    valid[:, 10:, 5:22] = False  # map columns of image x 10..44: the left part of the 0-1 and 0-2 quads
    nm = NormalMaps(nm.maps, valid, nm.scale, nm.source)
    loose = _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig(parallel=True)), ORTHOGONAL)
    strict = _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig(parallel=True, quad_valid_share=0.95)), ORTHOGONAL)
    assert (0, 2, 1) in loose and (0, 2, 1) not in strict
    assert (3, 5, 0) in strict  # the right wall's quad is untouched


def test_a_line_inside_the_quad_rejects_the_coplanarity():
    """Our deviation: a cabinet's outline between two wall lines means they need not share a plane."""
    from panosfm_graph.relations import quad_crossed

    segs = [(20, 10, 20, 60), (70, 10, 70, 60), (45, 15, 45, 55)]  # two z lines, a third one between them
    pre, tracks, nm = _frame(segs, [2, 2, 2])
    cfg = RelationsConfig(parallel=True)
    assert quad_crossed(pre, np.array([0]), np.array([1]), min_len_px=5.0).tolist() == [True]
    assert quad_crossed(pre, np.array([0]), np.array([2]), min_len_px=5.0).tolist() == [False]
    assert quad_crossed(pre, np.array([0]), np.array([1]), min_len_px=60.0).tolist() == [False]  # too short to count
    par = _rows(detect_relations(pre, tracks, nm, CAM, cfg), PARALLEL)
    assert (0, 1, 1) not in par and (0, 2, 1) in par and (1, 2, 1) in par
    paper = _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig(parallel=True, quad_clear_frac=0.0)), PARALLEL)
    assert (0, 1, 1) in paper
    # a piece of one of the two lines themselves is not "between" them
    pre2, tracks2, nm2 = _frame([(20, 10, 20, 60), (70, 10, 70, 60), (21, 62, 21, 80)], [2, 2, 2])
    assert (0, 1, 1) in _rows(detect_relations(pre2, tracks2, nm2, CAM, cfg), PARALLEL)


def test_a_line_running_through_the_quad_rejects_it_even_with_its_midpoint_outside():
    """A cabinet top running across the quad of two wall lines (its mid-point beyond them) rejects the pair."""
    from panosfm_graph.relations import quad_crossed

    # two z lines 50 px apart and a long x line crossing between them whose mid-point (x = 95) is outside
    segs = [(20, 10, 20, 60), (70, 10, 70, 60), (30, 35, 160, 35)]
    pre, tracks, nm = _frame(segs, [2, 2, 0])
    i, j = np.array([0]), np.array([1])
    assert quad_crossed(pre, i, j, min_len_px=5.0, samples=1).tolist() == [False]  # the mid-point test misses it
    assert quad_crossed(pre, i, j, min_len_px=5.0, samples=9).tolist() == [True]
    assert quad_crossed(pre, i, j, min_len_px=45.0, samples=9).tolist() == [False]  # ~40 px inside: too short
    sampled = _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig(parallel=True, quad_clear_samples=9)), PARALLEL)
    midpoint = _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig(parallel=True, quad_clear_samples=1)), PARALLEL)
    assert (0, 1, 1) in midpoint and (0, 1, 1) not in sampled


def test_relations_between_placed_lines():
    """``Relations.between``: a pair needs both lines, a floor relation its one line; tracks outside the range never pass."""
    rel = Relations(np.array([ORTHOGONAL, JUNCTION, FLOOR, FLOOR, PARALLEL], np.int8),
                    np.array([0, 1, 2, 1, 0], np.int32), np.array([1, 2, -1, -1, 7], np.int32),
                    np.zeros(5, np.int8), np.ones(5, np.int32))
    np.testing.assert_array_equal(rel.between(np.array([True, True, False])), [True, False, False, True, False])
    np.testing.assert_array_equal(rel.between(np.ones(3, bool)), [True, True, True, True, False])
    assert not rel.between(np.zeros(0, bool)).any()


# ---------------------------------------------------------------- where segments meet the floor (beyond the paper)


CONTACT = dict(parallel=True, floor_contact_frac=0.03)  # 3 px on the 200 x 100 test camera


def test_standing_verticals_off_one_floor_line_are_not_coplanar():
    """Two verticals standing on the floor 8 px apart in height are on two planes (a cabinet before the wall).

    The hand-built frame's floor starts at image row 80, below a cabinet's front at row 88; the quad between
    the two z lines is wall and cabinet front (both normal y) but for a sliver of floor, so normals alone
    accept the pair.
    """
    cabinet = [(20, 20, 20, 80), (70, 20, 70, 88)]
    pre, tracks, nm = _frame(cabinet, [2, 2], n_frames=3)
    nm.maps[:, 40:44, 15:40] = [0, -1, 0]  # the cabinet's front (image x 30-80) reaches down to row 88
    assert (0, 1, 1) in _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig(parallel=True)), PARALLEL)
    assert (0, 1, 1) not in _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig(**CONTACT)), PARALLEL)
    direct = RelationsConfig(**CONTACT, floor_contact_propagate=False)  # the pair itself is contradicted
    assert (0, 1, 1) not in _rows(detect_relations(pre, tracks, nm, CAM, direct), PARALLEL)
    # seen in fewer frames than floor_contact_min_frames (3), the contradiction is not trusted
    few = RelationsConfig(**CONTACT, floor_contact_min_frames=4)
    assert (0, 1, 1) in _rows(detect_relations(pre, tracks, nm, CAM, few), PARALLEL)
    wall = [(20, 20, 20, 80), (70, 30, 70, 80)]  # both stand on the wall's foot
    pre, tracks, nm = _frame(wall, [2, 2], n_frames=3)
    assert (0, 1, 1) in _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig(**CONTACT)), PARALLEL)


def test_floor_contacts_and_floor_line_consistency():
    from panosfm_graph.relations import floor_consistent, floor_contacts, floor_masks

    segs = [(10, 80, 90, 80),  # 0: the wall's foot (x line, floor below it)
            (50, 30, 50, 80),  # 1: a z line standing on it
            (30, 40, 30, 92),  # 2: a z line standing on the floor 12 px lower (in front of the wall)
            (70, 20, 70, 60),  # 3: a z line ending above the floor (a window's edge)
            (60, 30, 60, 90)]  # 4: a z line reaching below the foot, its own foot unseen (hidden)
    labels = np.array([0, 2, 2, 2, 2])
    pre, tracks, nm = _frame(segs, labels)
    cfg = RelationsConfig(**CONTACT)
    mask = floor_masks(pre, nm, CAM, cfg)
    fc = floor_contacts(pre, nm, CAM, mask, labels, np.arange(5))
    assert fc.floor_line.tolist() == [True, False, False, False, False]
    assert fc.contact.tolist() == [False, True, True, False, True]
    np.testing.assert_allclose(fc.bottom[1:], [[50, 80], [30, 92], [70, 60], [60, 90]])
    ep = pre.segments.endpoints.astype(np.float64)
    i, j = np.zeros(4, np.int64), np.arange(1, 5)
    ok = floor_consistent(fc, ep, i, j, labels, np.zeros(4, np.int64), np.ones(4, np.int64), 3.0)
    assert ok.tolist() == [True, False, True, False]
    # on a horizontal plane (axis 2) nothing is tested
    assert floor_consistent(fc, ep, i, j, labels, np.zeros(4, np.int64), np.full(4, 2), 3.0).all()


def test_occluding_t_junction():
    from panosfm_graph.relations import occluding_t

    segs = np.array([(50, 10, 50, 90),   # 0: a vertical edge
                     (10, 50, 49, 50),   # 1: a horizontal ending on its inside (a T: hidden behind it)
                     (10, 88, 49, 88),   # 2: ending near its lower end (an L, not a T)
                     (10, 30, 90, 30),   # 3: crossing it
                     (10, 60, 40, 60)],  # 4: ending 10 px short of it
                    float)
    labels = np.array([2, 0, 0, 0, 0])
    t = occluding_t(segs, np.zeros(4, np.int64), np.arange(1, 5), labels, 5.0)
    assert t.tolist() == [True, False, False, False]
    assert occluding_t(segs, np.arange(1, 5), np.zeros(4, np.int64), labels, 5.0).tolist() == t.tolist()


def test_consistent_planes_keeps_cannot_links_apart():
    from panosfm_graph.relations import consistent_planes

    a, b = np.array([0, 1, 2, 0]), np.array([1, 2, 3, -1])
    axis, support = np.array([0, 0, 0, 2]), np.array([5, 9, 3, 7])
    rank = np.array([0, 2, 1, 0])  # a junction, a parallel pair, an orthogonal pair, a floor relation
    cannot = (np.array([0]), np.array([2]), np.array([0]))
    # by rank: 0-1 and 2-3 join, then 1-2 would put the cannot-linked 0 and 2 on one plane: dropped
    assert consistent_planes(a, b, axis, support, *cannot, rank=rank).tolist() == [True, False, True, True]
    # by support alone: 1-2 first, then 0-1 is the one dropped
    assert consistent_planes(a, b, axis, support, *cannot).tolist() == [False, True, True, True]
    # a cannot-link on another axis blocks nothing
    assert consistent_planes(a, b, axis, support, cannot[0], cannot[1], np.array([1]), rank=rank).all()


def test_a_vertical_hanging_from_a_floor_candidate_lifts_it_off_the_floor():
    """A table's front edge seen against the floor is no floor line when a leg hangs from its end."""
    segs = [(20, 85, 80, 85),   # 0: an x line inside the floor region (a table top's front edge, or the floor's)
            (20, 86, 20, 98)]   # 1: a z line hanging 12 px down from its left end (the table's leg)
    pre, tracks, nm = _frame(segs, [0, 2])
    on = dict(CONTACT, floor_hanging_frac=0.05)
    off = dict(CONTACT, floor_hanging_frac=0.0)
    assert _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig(**off)), FLOOR) == {(0, -1, 2)}
    assert _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig(**on)), FLOOR) == set()
    # a vertical standing on the line (going up from it) says nothing against it
    pre, tracks, nm = _frame([(20, 85, 80, 85), (20, 60, 20, 84)], [0, 2])
    assert _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig(**on)), FLOOR) == {(0, -1, 2)}
    # nor one shorter than floor_hanging_frac * min(w, h) (5 px here)
    pre, tracks, nm = _frame([(20, 85, 80, 85), (20, 86, 20, 89)], [0, 2])
    assert _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig(**on)), FLOOR) == {(0, -1, 2)}


def test_floor_contacts_vanishing_points_follow_the_rotations():
    """FloorContacts.vp[f, d] is the image of Manhattan direction d in frame f: K R_wc^T d."""
    from scipy.spatial.transform import Rotation

    from panosfm_graph.relations import floor_contacts

    pre, tracks, nm = _frame(SEGS, LABELS, n_frames=2)
    R = Rotation.from_euler("xyz", [[80, 10, 25], [95, -5, 140]], degrees=True).as_matrix()
    dirs = Rotation.from_euler("z", 30, degrees=True).as_matrix().T  # rows: a Manhattan frame turned 30 degrees
    pre = dataclasses.replace(pre, R_wc=R, manhattan=ManhattanFrame(dirs))
    fc = floor_contacts(pre, nm, CAM, np.zeros(nm.valid.shape, bool), np.asarray(pre.labels, np.int64),
                        np.arange(pre.segments.n))
    for f in range(2):
        for d in range(3):
            want = CAM.K @ R[f].T @ dirs[d]
            np.testing.assert_allclose(np.cross(fc.vp[f, d], want), 0, atol=1e-9)


def test_a_face_runs_only_to_the_side_its_l_junctions_show():
    """Beyond the paper (junction_sides): a bookshelf's front edge bounds the front, not the wall beyond it."""
    segs = [
        (50, 25, 50, 75),  # 0: a vertical front edge (label 2) on the y-facing wall's normals
        (20, 25, 50, 25),  # 1: the front's top edge, an L with 0 whose inside lies to the left
        (58, 15, 95, 15),  # 2: a wall line to the right of 0: same normal, but another plane
        (20, 70, 44, 70),  # 3: a line to the left of 0, on the side of the front
    ]
    labels = [2, 0, 0, 0]
    pre, tracks, nm = _frame(segs, labels, n_frames=2)
    off = _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig()), ORTHOGONAL)
    assert {(0, 2, 1), (0, 3, 1)} <= off
    assert (0, 1, 1) in _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig()), JUNCTION)
    on = _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig(junction_sides=True)), ORTHOGONAL)
    assert (0, 2, 1) not in on and (0, 3, 1) in on
    assert on == off - {(0, 2, 1)}
    # without the junction (seen in one frame only, below junction_min_support) nothing says which side
    pre, tracks, nm = _frame(segs, labels, n_frames=1)
    assert (0, 2, 1) in _rows(detect_relations(pre, tracks, nm, CAM, RelationsConfig(junction_sides=True)), ORTHOGONAL)


def test_face_sides_are_the_same_in_every_frame():
    """face_sides gives the way along a Manhattan axis, not in the image: a turned camera sees the same sides."""
    from panosfm_graph.relations import face_sides

    K = CAM.K
    # wall y = 3 (normal axis 1); a vertical line at x = 0 and points on the wall left / right of it
    P = np.array([[0.0, 3.0, 0.2], [-0.8, 3.0, 0.4], [0.9, 3.0, -0.3]])
    eps = []
    Rs = []
    for yaw in (0.0, 0.3, -0.25):
        Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
        R = Rz @ R_WC
        x = (P @ R) @ K.T  # camera = R^T world
        x = x[:, :2] / x[:, 2:]
        eps.append(np.column_stack([x - [0, 3], x + [0, 3]]))  # short vertical segments around the projections
        Rs.append(R)
    ep = np.concatenate(eps).astype(np.float32)
    frame = np.repeat(np.arange(3, dtype=np.int32), 3)
    seg = Segments(ep, frame, np.arange(0, 10, 3, dtype=np.int64), np.zeros((9, 3), np.uint8))
    labels = np.tile(np.array([2, 0, 0]), 3)
    pre = Preprocessed(seg, ManhattanFrame(np.eye(3)), labels.astype(np.int8), np.array(Rs), np.array(Rs))
    i = np.array([0, 0, 3, 3, 6, 6])
    j = np.array([1, 2, 4, 5, 7, 8])
    s_i, s_j = face_sides(pre, CAM, i, j, np.ones(6, np.int64), labels)
    assert s_i.tolist() == [-1, 1] * 3  # from the vertical along x: to the left point -, to the right +
    assert s_j.tolist() == [-1, 1] * 3  # from the x lines along z: the vertical's mid-point is lower (left) / higher
