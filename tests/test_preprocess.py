"""Preprocessing (paper §3.1, supplement §1-3): segments, Manhattan frame, rotation refinement, tracks.

Captures are ray-cast here (a painted box room, ~2 s) so the tests do not
depend on the synthetic generator; the metrics are those of
``tools/bench_preprocess.py``.
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import cv2
import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from panosfm_graph.config import Config, DetectConfig, with_overrides
from panosfm_graph.data import Camera, Capture, GroundTruth, Segments
from panosfm_graph.errors import InputError, TooFewLinesError
from panosfm_graph.lines import preprocess, track_lines
from panosfm_graph.lines.tracking import pair_angle_deg
from panosfm_graph.lines.detect import detect_frame, detect_segments, merge_segments
from panosfm_graph.lines.manhattan import label_segments, manhattan_frame, sphere_bins
from panosfm_graph.lines.rotations import heading_drift, manhattan_factor, neighbour_pairs, rotate_heading

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from bench_preprocess import evaluate, gt_edge_of_segments, rotation_errors  # noqa: E402

# --- a tiny ray-cast Manhattan room ------------------------------------------------------------------

ROOM = np.array([[-2.5, -2.0, 0.0], [3.0, 2.2, 2.6]])  # min / max corner (m)
# painted rectangles: (wall normal axis, wall coordinate, (u0, u1) along the other horizontal axis, (z0, z1))
RECTS = [
    (0, -2.5, (-1.0, 0.2), (0.0, 2.0)), (0, 3.0, (0.4, 1.6), (0.9, 1.9)), (1, -2.0, (-1.5, -0.3), (1.0, 1.8)),
    (1, 2.2, (0.5, 2.2), (0.0, 2.1)), (1, 2.2, (-2.0, -0.8), (1.2, 1.7)), (0, -2.5, (0.8, 1.5), (1.3, 1.9)),
    (0, 3.0, (-1.6, -0.5), (0.3, 0.8)), (1, -2.0, (0.5, 2.4), (0.2, 0.7)), (0, 3.0, (-1.8, 2.0), (2.2, 2.3)),
    (1, -2.0, (-2.4, 2.8), (2.25, 2.35)), (0, -2.5, (-1.9, 2.1), (2.3, 2.4)), (1, 2.2, (-2.4, 2.9), (2.3, 2.4)),
]
FACE_BGR = np.array([[180, 170, 160], [150, 160, 175], [200, 190, 150], [140, 175, 150], [90, 100, 110],
                     [235, 235, 230]], float)


def room_edges() -> tuple[np.ndarray, np.ndarray]:
    """Returns (M, 6) GT 3D edges of the room and its painted rectangles, (M,) axis labels."""
    lo, hi = ROOM
    out = []
    for y in (lo[1], hi[1]):
        for z in (lo[2], hi[2]):
            out.append([lo[0], y, z, hi[0], y, z, 0])
    for x in (lo[0], hi[0]):
        for z in (lo[2], hi[2]):
            out.append([x, lo[1], z, x, hi[1], z, 1])
        for y in (lo[1], hi[1]):
            out.append([x, y, lo[2], x, y, hi[2], 2])
    for ax, w, (u0, u1), (z0, z1) in RECTS:
        o = 1 - ax
        for u in (u0, u1):
            p, q = [0.0] * 3, [0.0] * 3
            p[ax] = q[ax] = w
            p[o] = q[o] = u
            p[2], q[2] = z0, z1
            out.append(p + q + [2])
        for z in (z0, z1):
            p, q = [0.0] * 3, [0.0] * 3
            p[ax] = q[ax] = w
            p[o], q[o] = u0, u1
            p[2] = q[2] = z
            out.append(p + q + [o])
    a = np.array(out)
    return a[:, :6], a[:, 6].astype(np.int8)


def render(K, R_wc, c, w, h, ss=2) -> np.ndarray:
    """Returns a BGR uint8 view of the room (ray cast, ss x ss supersampled)."""
    ys, xs = np.mgrid[0 : h * ss, 0 : w * ss]
    u, v = (xs + 0.5) / ss - 0.5, (ys + 0.5) / ss - 0.5
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ R_wc.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t_all = np.stack([(ROOM[s, ax] - c[ax]) / d[..., ax] for ax in range(3) for s in range(2)], -1)
    t_all = np.where(t_all > 0, t_all, np.inf)
    face, t = np.argmin(t_all, -1), np.min(t_all, -1)
    p = c + d * t[..., None]
    col = FACE_BGR[face].copy()
    for ax, wv, (u0, u1), (z0, z1) in RECTS:
        o = 1 - ax
        on = (np.abs(p[..., ax] - wv) < 1e-6) & (p[..., o] > u0) & (p[..., o] < u1) & (p[..., 2] > z0) & (p[..., 2] < z1)
        col[on] = col[on] * 0.45 + np.array([40.0, 60.0, 120.0]) * 0.55
    col *= (0.85 + 0.15 * np.exp(-t / 4.0))[..., None]
    return np.clip(cv2.resize(col.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA), 0, 255).astype(np.uint8)


def make_capture(n_frames=60, w=320, h=180, sweep_deg=380.0, drift_deg=(0.2, 0.15, 4.0), heading_deg=25.0,
                 seed=0, blank=False, yaw_deg=None, pitch_deg=None) -> Capture:
    """Returns an in-memory spin Capture of the room: GT poses, IMU = heading offset + growing drift.

    The drift is mostly heading (a phone's tilt comes from gravity and barely drifts). ``yaw_deg`` /
    ``pitch_deg`` ((n_frames,) each) replace the even sweep and the default pitch.
    """
    rng = np.random.default_rng(seed)
    f = 0.6 * w
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    if yaw_deg is not None:
        n_frames = len(yaw_deg)
    s = np.linspace(0, 1, n_frames)
    yaw = np.radians(sweep_deg) * s if yaw_deg is None else np.radians(np.asarray(yaw_deg, float))
    pitch, roll = np.radians(6.0 * np.sin(3 * np.pi * s)), np.radians(2.0 * np.cos(5 * s))
    if pitch_deg is not None:
        pitch = np.radians(np.asarray(pitch_deg, float))
    base = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # camera z -> world x, camera y -> world -z
    R_gt = np.stack([Rotation.from_euler("zyx", e).as_matrix() @ base for e in zip(yaw, pitch, roll)])
    centers = np.stack([0.25 * np.cos(yaw) + 0.2, 0.25 * np.sin(yaw) + 0.1, np.full_like(yaw, 1.5)], 1)
    drift = Rotation.from_rotvec(np.radians(np.asarray(drift_deg))[None] * s[:, None]).as_matrix()
    heading = Rotation.from_euler("z", heading_deg, degrees=True).as_matrix()
    R_imu = np.einsum("ij,fjk,fkl->fil", heading, drift, R_gt)
    imgs = []
    for i in range(n_frames):
        img = np.full((h, w, 3), 128.0) if blank else render(K, R_gt[i], centers[i], w, h).astype(np.float32)
        imgs.append(np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8))
    lines, labels = room_edges()
    gt = GroundTruth(R_wc=R_gt, centers=centers, lines=lines, line_labels=labels,
                     scene={"manhattan_directions_world": np.eye(3).tolist()})
    cam = Camera("PINHOLE", w, h, np.array([f, f, (w - 1) / 2, (h - 1) / 2]))
    return Capture(root=Path("/nonexistent/synthetic"), camera=cam,
                   frame_names=tuple(f"{i:06d}.png" for i in range(n_frames)), timestamps=s * 10,
                   R_wc_imu=R_imu, ground_truth=gt, reader=imgs.__getitem__)


@pytest.fixture(scope="module")
def spin():
    """A 380 degree spin (60 frames) and its preprocessing."""
    cap = make_capture()
    return cap, preprocess(cap, with_overrides(Config(), detect={"workers": 1}))


@pytest.fixture(scope="module")
def slow_pan():
    """A 60 degree pan in 1 degree steps (tracking links frames within 2 degrees)."""
    cap = make_capture(n_frames=61, sweep_deg=60.0, drift_deg=(0.2, 0.2, 1.0))
    return cap, preprocess(cap, with_overrides(Config(), detect={"workers": 1}))


# --- detection --------------------------------------------------------------------------------------

def test_merge_joins_colinear_pieces_only():
    segs = np.array([
        [10, 50, 100, 50.3],     # a, with b: colinear, 6 px gap -> merged
        [106, 50.35, 200, 50.8],
        [10, 80, 100, 80],       # parallel to c at 3 px offset: not merged
        [104, 83, 200, 83],
        [10, 120, 100, 120],     # 5 degrees off its continuation: not merged
        [104, 120, 200, 128.4],
    ])
    out = merge_segments(segs, angle_deg=1.0, dist_px=9.0, offset_px=1.5)
    assert len(out) == 5
    longest = out[np.argmax(np.hypot(out[:, 2] - out[:, 0], out[:, 3] - out[:, 1]))]
    xs = sorted([longest[0], longest[2]])
    assert xs[0] == pytest.approx(10, abs=0.5) and xs[1] == pytest.approx(200, abs=0.5)
    assert np.mean([longest[1], longest[3]]) == pytest.approx(50.4, abs=0.5)


def test_detect_frame_finds_rectangle_edges():
    img = np.full((180, 320, 3), 60, np.uint8)
    cv2.rectangle(img, (60, 40), (260, 140), (200, 190, 180), -1)
    ends, colors, contrast = detect_frame(img, DetectConfig())
    truth = np.array([[60, 40, 260, 40], [60, 140, 260, 140], [60, 40, 60, 140], [260, 40, 260, 140]], float)
    # the bright rectangle's inside: each edge's polarity says on which side of it that lies
    inside = np.array([[160, 90]] * 4, float)
    for t, c in zip(truth, inside):  # each edge is found as one segment within 1.5 px (either orientation)
        fwd, rev = np.abs(ends - t).max(1), np.abs(ends[:, [2, 3, 0, 1]] - t).max(1)
        d = np.minimum(fwd, rev)
        k = int(np.argmin(d))
        assert d[k] < 1.5, (t, ends)
        # polarity: the grey level left of the segment's own direction minus right of it
        e = ends[k].astype(float)
        left = np.array([e[3] - e[1], -(e[2] - e[0])])  # left normal of (dx, dy) in image axes
        inside_left = np.dot(c - e[:2], left) > 0
        assert abs(contrast[k]) > 50 and (contrast[k] > 0) == inside_left, (e, contrast[k])
    assert len(ends) <= 8  # LSD may give both sides of a 1 px edge; merged pieces do not multiply
    assert np.all(ends.min(0) >= -1) and colors.dtype == np.uint8 and contrast.shape == (len(ends),)


def test_detect_segments_pool_equals_inline():
    cap = make_capture(n_frames=6, sweep_deg=30.0)
    one = detect_segments(cap, DetectConfig(workers=1))
    two = detect_segments(cap, DetectConfig(workers=2))
    assert one.n > 30 and np.array_equal(one.frame_offsets, two.frame_offsets)
    np.testing.assert_allclose(one.endpoints, two.endpoints)
    assert np.all(one.lengths >= 0.05 * 180 - 1e-3)
    assert np.all(np.diff(one.frame) >= 0)


# --- Manhattan frame, labels, rotations -------------------------------------------------------------

def test_sphere_bins_near_uniform():
    b = sphere_bins(10242)
    assert np.allclose(np.linalg.norm(b, axis=1), 1.0)
    from scipy.spatial import cKDTree
    d, _ = cKDTree(b).query(b, k=2)
    spacing = np.degrees(d[:, 1])
    assert 1.5 < np.median(spacing) < 2.6 and spacing.max() < 3.0


def test_manhattan_factor_jacobian_matches_numerical():
    rng = np.random.default_rng(3)
    n = rng.normal(size=(7, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = np.eye(3)[rng.integers(0, 3, 7)]
    weights = rng.uniform(0.5, 2.0, 7)
    key = gtsam.symbol("r", 0)
    R = gtsam.Rot3(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix())
    for huber in (0.0, 0.02):
        f = manhattan_factor(key, n, v, huber, weights)
        vals = gtsam.Values()
        vals.insert(key, R)
        J = f.linearize(vals).jacobian()[0]  # whitened = unit noise
        num = np.zeros((7, 3))
        for k in range(3):
            e = np.zeros(3)
            e[k] = 1e-6
            vp, vm = gtsam.Values(), gtsam.Values()
            vp.insert(key, R.retract(e))
            vm.insert(key, R.retract(-e))
            num[:, k] = (f.unwhitenedError(vp) - f.unwhitenedError(vm)) / 2e-6
        np.testing.assert_allclose(J, num, atol=1e-6)
        r = f.unwhitenedError(vals)
        if huber == 0.0:  # the residual is v . (R n), weighted
            np.testing.assert_allclose(r, weights * np.einsum("ij,ij->i", v, n @ R.matrix().T), atol=1e-12)


def test_neighbours_are_local_in_time():
    cap = make_capture(n_frames=120, blank=True)
    pairs = neighbour_pairs(cap.R_wc_imu, 10.0, 8)
    assert len(pairs)
    # the 380 degree spin overlaps itself, but start and end frames are never paired
    assert np.all(pairs[:, 1] - pairs[:, 0] <= 5)
    assert {(i, i + 1) for i in range(119)} <= set(map(tuple, pairs))


def test_heading_drift_recovers_a_gyro_bias_despite_outliers():
    rng = np.random.default_rng(3)
    F = 200
    t = np.linspace(0.0, 20.0, F)
    R_true = Rotation.from_euler("zyx", np.c_[np.linspace(0, 6.6, F), rng.normal(0, 0.1, (F, 2))]).as_matrix()
    true_drift = np.radians(0.15) * t  # a constant gyro bias: 3 degrees over 20 s
    R_imu = rotate_heading(R_true, true_drift)
    # refined rotations: the truth with 0.05 degree heading noise, plus ten frames badly off
    noise = np.radians(rng.normal(0, 0.05, F))
    noise[rng.choice(F, 10, replace=False)] += np.radians(2.0)
    R_ref = rotate_heading(R_true, noise)
    w = rng.uniform(0.5, 2.0, F)
    w[:30] = 0.0  # frames without horizontal lines do not vote
    est = heading_drift(R_ref, R_imu, t, w, degree=1)  # correction that maps the IMU onto the refined rotations
    assert np.max(np.abs(np.degrees(est + true_drift))) < 0.05
    # removing it leaves the IMU within its noise of the truth
    err = np.degrees(np.abs(np.asarray([Rotation.from_matrix(a @ b.T).magnitude() for a, b in zip(rotate_heading(R_imu, est), R_true)])))
    assert err.max() < 0.05
    # off: no correction
    assert np.all(heading_drift(R_ref, R_imu, t, w, degree=-1) == 0)


def test_heading_drift_from_a_spins_two_ends_cancels_the_lines_bias():
    """The lines of two views bias the refined headings by 0.3 degrees wherever the camera looks that way (0.1 degree
    noise): the first and the last frames of a 380-degree spin, and 80 degrees of its first half. The plain fit tilts (its slope takes the
    bias); with the pairs a turn apart that look the same way (``pairs``) the drift between the ends is measured
    free of the bias, and the fit's error drops at least 3x."""
    from panosfm_graph.lines.tracking import loop_pairs

    rng = np.random.default_rng(5)
    F = 300
    t = np.linspace(0.0, 20.0, F)
    yaw = np.radians(np.linspace(0.0, 380.0, F))
    base = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # camera z -> world x
    R_true = np.stack([Rotation.from_euler("z", a).as_matrix() @ base for a in yaw])
    true_drift = np.radians(0.15) * t
    R_imu = rotate_heading(R_true, true_drift)
    view = np.degrees(yaw) % 360.0
    bias = np.radians(0.3) * ((view < 20.0) | ((view > 60.0) & (view < 140.0)))  # the same view biased alike
    R_ref = rotate_heading(R_true, bias + np.radians(rng.normal(0, 0.1, F)))
    w = np.ones(F)
    pairs = loop_pairs(R_ref, 3.0)
    assert len(pairs) >= 10 and np.all(pairs[:, 1] - pairs[:, 0] > 250)
    err = {}
    for name, P in (("plain", None), ("ends", pairs)):
        est = heading_drift(R_ref, R_imu, t, w, degree=1, pairs=P)
        err[name] = np.max(np.abs(np.degrees(est + true_drift - np.mean(est + true_drift))))
    assert err["plain"] > 0.05 and err["ends"] * 3 < err["plain"], err


def test_manhattan_frame_rotations_and_labels(spin):
    cap, pre = spin
    ev = evaluate(cap, pre, track_lines(cap, pre, Config()), gt_px=1.5)
    # Manhattan frame: right-handed, vertical up, consistent with GT axes (same alignment as rotations)
    D = pre.manhattan.directions
    assert np.allclose(D @ D.T, np.eye(3), atol=1e-9) and np.linalg.det(D) > 0 and D[2, 2] > 0.99
    assert ev["manhattan_err_deg"] < 0.5
    # rotations: IMU drift (about 1 degree median) removed at least 3x, median below 0.3 degrees
    imu, ref = ev["rot_err_imu_deg"]["median"], ev["rot_err_refined_deg"]["median"]
    assert imu > 0.7 and ref < 0.3 and ref * 3 < imu, ev
    assert ev["rot_err_refined_deg"]["max"] < 1.0
    # labelling: segments on GT edges get their edge's axis
    assert ev["labelling_accuracy"] >= 0.95 and ev["labelling_recall"] > 0.8, ev


def test_heading_prior_holds_frames_whose_lines_mislead(spin):
    """Frames 20-35 see their segments as from a camera turned 1 degree further (as a thin top's two edges
    fitted as one bias a vanishing point): refined without the IMU prior (``heading_weight`` 0, the paper)
    they follow the lines; held to the drift-free IMU (``prior_weight`` 10) their error drops at least 3x and
    the other frames stay within 0.05 degrees of where they were."""
    from panosfm_graph.lines.rotations import refine_rotations

    cap, pre = spin
    K, R_gt = cap.camera.K, pre.R_wc  # the refined rotations, in the Manhattan frame's world, as the truth
    seg, lab = pre.segments, pre.labels
    up = pre.manhattan.directions[2]
    bad = (seg.frame >= 20) & (seg.frame < 36)
    turn = Rotation.from_rotvec(np.radians(1.0) * up).as_matrix()
    ends = seg.endpoints.astype(np.float64).reshape(-1, 2)
    fr = np.repeat(seg.frame, 2)
    # the image of the camera R' = turn R: a point seen along ray d (world) appears at K R'^T d
    H = np.einsum("ij,fkj,kl,flm,mn->fin", K, R_gt[fr], turn.T, R_gt[fr], np.linalg.inv(K))
    p = np.einsum("fij,fj->fi", H, np.c_[ends, np.ones(len(ends))])
    moved = (p[:, :2] / p[:, 2:]).reshape(-1, 4).astype(np.float32)
    seg_bad = Segments(np.where(bad[:, None], moved, seg.endpoints), seg.frame, seg.frame_offsets, seg.colors)
    R_prior = R_gt  # the IMU with its drift removed (here: exactly the truth)
    err = {}
    for w in (0.0, 10.0):
        R = refine_rotations(seg_bad, lab, K, R_prior, pre.manhattan, Config().rotation, R_wc_init=R_gt,
                             prior_weight=w)
        err[w] = np.degrees([Rotation.from_matrix(a @ b.T).magnitude() for a, b in zip(R, R_gt)])
    f = np.arange(len(R_gt))
    mid = (f >= 23) & (f < 33)
    assert np.median(err[0.0][mid]) > 0.5, err[0.0][mid]  # the paper's cost follows the misleading lines
    assert np.median(err[10.0][mid]) * 3 < np.median(err[0.0][mid]), (err[0.0][mid], err[10.0][mid])
    far = (f < 15) | (f > 40)
    assert np.all(err[10.0][far] < err[0.0][far] + 0.05), (err[0.0][far], err[10.0][far])


def test_label_85_degree_rule():
    K = np.array([[200.0, 0, 160], [0, 200, 90], [0, 0, 1]])
    # camera looking along world +x; a vertical image line at x=250 is a world-vertical line
    R = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
    ends = np.array([[250, 20, 250, 160], [20, 60, 300, 60], [40, 30, 200, 150]], np.float32)
    segs = Segments(endpoints=ends, frame=np.zeros(3, np.int32), frame_offsets=np.array([0, 3]),
                    colors=np.zeros((3, 3), np.uint8))
    from panosfm_graph.data import ManhattanFrame
    labels = label_segments(segs, K, R[None], ManhattanFrame(np.eye(3)), Config())
    # vertical -> z (2); horizontal image line above the horizon -> world y (1); a diagonal -> -1
    assert labels.tolist() == [2, 1, -1]


def test_too_few_lines_raises_input_error():
    cap = make_capture(n_frames=5, blank=True)
    with pytest.raises(TooFewLinesError) as info:
        preprocess(cap, with_overrides(Config(), detect={"workers": 1}))
    assert isinstance(info.value, InputError) and "segments" in str(info.value)


# --- tracking ---------------------------------------------------------------------------------------

def test_tracks_are_pure_and_long(slow_pan):
    cap, pre = slow_pan
    assert pre.R_wc.flags.c_contiguous  # as the stage cache returns it (a resumed run repeats a fresh one)
    tracks = track_lines(cap, pre, Config())
    ev = evaluate(cap, pre, tracks, gt_px=1.5)
    assert tracks.n >= 15
    assert ev["track_purity_mean"] >= 0.95, ev
    assert ev["track_length_mean"] >= 5, ev
    # one segment per frame per track, labels agree with the track's axis
    seg, off = tracks.members()
    t_of = np.repeat(np.arange(tracks.n), np.diff(off))
    key = t_of * cap.n_frames + pre.segments.frame[seg]
    assert len(np.unique(key)) == len(key)
    assert np.all(pre.labels[seg] == tracks.axis[t_of])
    assert np.all(tracks.track_of[pre.labels < 0] == -1)


def test_a_spin_of_few_frames_is_tracked():
    """Frames 5 degrees apart (a spin of 72 frames per turn): the paper's fixed 2 degrees pairs no frames and
    leaves no track; pairing neighbours by the spin's median step gives pure tracks over several frames."""
    cap = make_capture(n_frames=13, sweep_deg=60.0, drift_deg=(0.2, 0.2, 1.0))
    pre = preprocess(cap, with_overrides(Config(), detect={"workers": 1}))
    assert 7.0 < pair_angle_deg(pre.R_wc, 2.0, 1.5) < 9.0  # 1.5 steps of about 5 degrees (with drift)
    assert pair_angle_deg(pre.R_wc, 2.0, 0.0) == 2.0
    assert track_lines(cap, pre, with_overrides(Config(), tracking={"axis_angle_steps": 0.0})).n == 0
    tracks = track_lines(cap, pre, Config())
    ev = evaluate(cap, pre, tracks, gt_px=1.5)
    assert tracks.n >= 10
    assert ev["track_purity_mean"] >= 0.95, ev
    assert ev["track_length_mean"] >= 3, ev


def test_gt_edge_matching_is_exact_on_gt_projections():
    """The bench's GT matcher (used above) recovers the edge of a projected GT segment."""
    cap = make_capture(n_frames=2, sweep_deg=10.0, blank=True)
    gt = cap.ground_truth
    K = cap.camera.K
    from panosfm_graph.geometry import project
    uv, z = project(K, gt.R_wc[0], gt.centers[0], gt.lines.reshape(-1, 3))
    uv, z = uv.reshape(-1, 4), z.reshape(-1, 2)
    inside = (z > 0.5).all(1) & (np.abs(uv - [160, 90, 160, 90]) < [150, 80, 150, 80]).all(1)
    idx = np.flatnonzero(inside)
    assert len(idx) >= 3
    segs = Segments(endpoints=uv[idx].astype(np.float32), frame=np.zeros(len(idx), np.int32),
                    frame_offsets=np.array([0, len(idx), len(idx)]), colors=np.zeros((len(idx), 3), np.uint8))
    got = gt_edge_of_segments(segs, K, gt.R_wc, gt.centers, gt.lines, tol_px=1.0)
    assert np.all(gt.line_labels[got] == gt.line_labels[idx])


def test_bridging_reconnects_tracks_over_missed_frames(slow_pan):
    """Track ends are linked across frames with no detection (bridge_angle_deg), keeping purity."""
    import dataclasses

    cap, pre = slow_pan
    dropped = (pre.segments.frame % 3) == 1  # every third frame's segments are missing
    pre_d = dataclasses.replace(pre, labels=np.where(dropped, -1, pre.labels).astype(np.int8))
    # fragments are not joined here (merge_gap_frames: tested below), so the bridging alone is measured
    base = with_overrides(Config(), tracking={"axis_angle_deg": 1.5, "bridge_angle_deg": 0.0, "merge_gap_frames": 0})
    bridged = with_overrides(Config(), tracking={"axis_angle_deg": 1.5, "bridge_angle_deg": 4.0, "merge_gap_frames": 0})
    ev0 = evaluate(cap, pre_d, track_lines(cap, pre_d, base), gt_px=1.5)
    tracks = track_lines(cap, pre_d, bridged)
    ev1 = evaluate(cap, pre_d, tracks, gt_px=1.5)
    assert ev1["track_length_mean"] >= 1.5 * ev0["track_length_mean"], (ev0, ev1)
    assert ev1["track_purity_mean"] >= 0.95, ev1
    seg, off = tracks.members()
    t_of = np.repeat(np.arange(tracks.n), np.diff(off))
    key = t_of * cap.n_frames + pre.segments.frame[seg]
    assert len(np.unique(key)) == len(key)  # still one segment per frame per track
    assert not np.any(tracks.track_of[dropped] >= 0)


def test_loop_closure_joins_the_tracks_of_a_spins_two_ends():
    """loop_angle_deg matches the last frames of a turn with the first (3 degrees apart in pitch), purely."""
    from panosfm_graph.lines.tracking import loop_pairs

    # 1-degree steps over the first and the last 30 degrees, 15-degree steps between: the end overlaps the start
    yaw = np.concatenate([np.arange(0, 31), np.arange(45, 331, 15), np.arange(335, 366)]).astype(float)
    pitch = np.where(yaw > 300, 3.0, 0.0)  # the second pass looks 3 degrees higher: not a 2-degree neighbour
    cap = make_capture(yaw_deg=yaw, pitch_deg=pitch, drift_deg=(0.1, 0.1, 1.0))
    pre = preprocess(cap, with_overrides(Config(), detect={"workers": 1}))
    F = cap.n_frames
    pairs = loop_pairs(pre.R_wc, 6.0)
    assert len(pairs) > 20
    assert np.all(yaw[pairs[:, 1]] - yaw[pairs[:, 0]] >= 330)  # only frames a turn apart
    assert len(loop_pairs(pre.R_wc, 0.0)) == 0

    def spanning(tracks):
        seg, off = tracks.members()
        fr = pre.segments.frame[seg]
        t_of = np.repeat(np.arange(tracks.n), np.diff(off))
        first = np.bincount(t_of, weights=yaw[fr] <= 30, minlength=tracks.n) > 0
        last = np.bincount(t_of, weights=yaw[fr] >= 335, minlength=tracks.n) > 0
        return int(np.sum(first & last)), t_of, fr

    open_cfg = with_overrides(Config(), tracking={"loop_angle_deg": 0.0})
    closed_cfg = with_overrides(Config(), tracking={"loop_angle_deg": 6.0})
    assert spanning(track_lines(cap, pre, open_cfg))[0] == 0
    tracks = track_lines(cap, pre, closed_cfg)
    n_loop, t_of, fr = spanning(tracks)
    assert n_loop >= 5, n_loop
    ev = evaluate(cap, pre, tracks, gt_px=1.5)
    assert ev["track_purity_mean"] >= 0.95, ev
    key = t_of * F + fr
    assert len(np.unique(key)) == len(key)  # one segment per frame per track


def test_fragments_of_one_line_are_joined_across_gaps(slow_pan):
    """merge_fragments joins the tracks a missed detection cut, never tracks of two lines."""
    import dataclasses

    cap, pre = slow_pan
    dropped = (pre.segments.frame % 4) == 2  # every fourth frame's segments are missing
    pre_d = dataclasses.replace(pre, labels=np.where(dropped, -1, pre.labels).astype(np.int8))
    base = with_overrides(Config(), tracking={"axis_angle_deg": 1.5, "merge_gap_frames": 0})
    merged = with_overrides(Config(), tracking={"axis_angle_deg": 1.5, "merge_gap_frames": 3, "merge_tol_px": 2.0})
    t0 = track_lines(cap, pre_d, base)
    t1 = track_lines(cap, pre_d, merged)
    ev0 = evaluate(cap, pre_d, t0, gt_px=1.5)
    ev1 = evaluate(cap, pre_d, t1, gt_px=1.5)
    assert t1.n < 0.6 * t0.n, (t0.n, t1.n)
    assert ev1["track_length_mean"] >= 1.8 * ev0["track_length_mean"], (ev0, ev1)
    assert ev1["track_purity_mean"] >= 0.95, ev1
    # every merged track is a union of whole base tracks of one axis, one segment per frame
    m = t0.track_of >= 0
    pairs = np.unique(np.column_stack([t0.track_of[m], t1.track_of[m]]), axis=0)
    assert len(np.unique(pairs[:, 0])) == len(pairs)
    assert np.all(t0.axis[pairs[:, 0]] == t1.axis[pairs[:, 1]])
    seg, off = t1.members()
    t_of = np.repeat(np.arange(t1.n), np.diff(off))
    key = t_of * cap.n_frames + pre.segments.frame[seg]
    assert len(np.unique(key)) == len(key)
    # a gap longer than merge_gap_frames is not crossed
    short = with_overrides(Config(), tracking={"axis_angle_deg": 1.5, "merge_gap_frames": 1, "merge_tol_px": 2.0})
    assert track_lines(cap, pre_d, short).n == t0.n


def test_tracks_without_a_long_segment_are_dropped():
    """drop_short_tracks removes texture tracks (no segment of the minimum length) and renumbers the rest."""
    from panosfm_graph.data import Tracks
    from panosfm_graph.lines.tracking import drop_short_tracks

    ep = np.array([[0, 0, 100, 0], [0, 5, 30, 5],  # frame 0: a long piece of track 0, a short one of track 1
                   [0, 0, 40, 0], [0, 5, 35, 5], [0, 9, 80, 9]], np.float32)  # frame 1: tracks 0, 1, 2
    segs = Segments(ep, np.array([0, 0, 1, 1, 1], np.int32), np.array([0, 2, 5]), np.zeros((5, 3), np.uint8))
    tracks = Tracks(np.array([0, 1, 0, 1, 2], np.int32), np.array([0, 1, 2], np.int8))
    out = drop_short_tracks(tracks, segs, min_longest_px=50.0)
    assert out.track_of.tolist() == [0, -1, 0, -1, 1]
    assert out.axis.tolist() == [0, 2]
    assert drop_short_tracks(tracks, segs, 20.0).track_of.tolist() == tracks.track_of.tolist()


def _split_pieces(pre, frames_mask):
    """Returns pre with every Manhattan segment of the masked frames cut into two colinear pieces (8 px gap)."""
    import dataclasses

    seg = pre.segments
    cut = frames_mask[seg.frame] & (pre.labels >= 0) & (seg.lengths > 40)
    e = seg.endpoints.astype(np.float64)
    mid = 0.5 * (e[:, :2] + e[:, 2:])
    u = (e[:, 2:] - e[:, :2]) / seg.lengths[:, None]
    first = np.where(cut[:, None], np.concatenate([e[:, :2], mid - 4 * u], axis=1), e)
    second = np.concatenate([mid + 4 * u, e[:, 2:]], axis=1)[cut]
    ends = np.concatenate([first, second])
    frame = np.concatenate([seg.frame, seg.frame[cut]])
    labels = np.concatenate([pre.labels, pre.labels[cut]])
    colors = np.concatenate([seg.colors, seg.colors[cut]])
    order = np.argsort(frame, kind="stable")
    offsets = np.searchsorted(frame[order], np.arange(len(seg.frame_offsets)))
    new = Segments(endpoints=ends[order].astype(np.float32), frame=frame[order].astype(np.int32),
                   frame_offsets=offsets.astype(np.int64), colors=colors[order])
    return dataclasses.replace(pre, segments=new, labels=labels[order].astype(np.int8))


def test_colinear_pieces_do_not_split_tracks(slow_pan):
    """Supplement §3 deviation: a line cut into two pieces in every other frame keeps one track."""
    cap, pre = slow_pan
    ev_whole = evaluate(cap, pre, track_lines(cap, pre, Config()), gt_px=1.5)
    split = _split_pieces(pre, np.arange(cap.n_frames) % 2 == 1)
    paper = with_overrides(Config(), tracking={"colinear_px": 0.0})
    ev_paper = evaluate(cap, split, track_lines(cap, split, paper), gt_px=1.5)
    tracks = track_lines(cap, split, Config())
    ev = evaluate(cap, split, tracks, gt_px=1.5)
    # without grouping the pieces fragment the tracks; with it they stay as long as on whole segments
    assert ev_paper["track_length_mean"] < 0.75 * ev_whole["track_length_mean"], (ev_paper, ev_whole)
    assert ev["track_length_mean"] >= 0.9 * ev_whole["track_length_mean"], (ev, ev_whole)
    assert ev["track_purity_mean"] >= 0.95, ev
    seg, off = tracks.members()
    t_of = np.repeat(np.arange(tracks.n), np.diff(off))
    key = t_of * cap.n_frames + split.segments.frame[seg]
    assert len(np.unique(key)) == len(key)  # still at most one segment (the longest piece) per frame


def test_colinear_groups_merge_only_colinear_pieces():
    from panosfm_graph.lines.tracking import colinear_groups

    ends = np.array([[0, 100, 200, 100],  # long piece
                     [230, 100.8, 300, 100.8],  # colinear piece 0.8 px off the line: grouped
                     [0, 104, 200, 104],  # parallel, 4 px away: separate
                     [230, 100, 300, 100],  # colinear but another label: separate
                     [50, 50, 50, 250],  # other direction
                     [40, 99.4, 150, 99.4]], dtype=np.float32)  # 0.6 px off but overlapping: another line
    seg = Segments(endpoints=ends, frame=np.zeros(6, np.int32), frame_offsets=np.array([0, 6]),
                   colors=np.zeros((6, 3), np.uint8))
    labels = np.array([0, 0, 0, 1, 2, 0], np.int8)
    rep, merged = colinear_groups(seg, labels, 1.0)
    np.testing.assert_array_equal(rep, [0, 0, 2, 3, 4, 5])
    np.testing.assert_allclose(merged[0], [0, 100, 300, 100], atol=1e-6)  # spans both pieces on the long line
    np.testing.assert_allclose(merged[2:], ends[2:], atol=1e-6)
    np.testing.assert_array_equal(colinear_groups(seg, labels, 0.0)[0], np.arange(6))


def test_colinear_groups_by_vanishing_point_lines_tolerate_piece_angle_noise():
    from panosfm_graph.lines.tracking import colinear_groups, manhattan_lines

    # a camera looking along +y (world z up): world x lines are horizontal in the image (vanishing
    # point at infinity), world z lines vertical. Pieces of one horizontal image line y = 300 whose
    # own angles are off by 1.5 degrees (short pieces on a textured edge) but whose mid-points lie on it
    K = np.array([[500.0, 0, 480], [0, 500.0, 270], [0, 0, 1]])
    R_wc = np.array([[[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]])  # camera x = world x, y = -z, z = y
    dirs = np.eye(3)
    tilt = np.tan(np.radians(1.5))

    def piece(x0, x1, y, slope):
        xm = 0.5 * (x0 + x1)
        return [x0, y + slope * (x0 - xm), x1, y + slope * (x1 - xm)]

    ends = np.array([piece(100, 300, 300, tilt),  # long piece, tilted
                     piece(320, 400, 300, -tilt),  # colinear piece tilted the other way: 2 px off at its far end
                     piece(100, 300, 303, 0.0),  # parallel line 3 px away, overlapping: another line
                     [600, 100, 600, 400]], np.float32)  # a vertical line
    seg = Segments(endpoints=ends, frame=np.zeros(4, np.int32), frame_offsets=np.array([0, 4]),
                   colors=np.zeros((4, 3), np.uint8))
    labels = np.array([0, 0, 0, 2], np.int8)
    L = manhattan_lines(seg, labels, K, R_wc, dirs)
    np.testing.assert_allclose(L[:3, :2] / L[:3, 1:2], [[0, 1]] * 3, atol=1e-9)  # horizontal lines
    np.testing.assert_allclose(np.abs(L[:3, 2]), [300, 300, 303], atol=1e-6)  # through the mid-points
    np.testing.assert_allclose(np.abs(L[3] / L[3, 0]), [1, 0, 600], atol=1e-9)  # vertical through x = 600
    rep_ends, _ = colinear_groups(seg, labels, 1.0)  # endpoint test: the tilts keep the pieces apart
    rep_vp, merged = colinear_groups(seg, labels, 1.0, L)
    assert rep_ends[1] == 1
    np.testing.assert_array_equal(rep_vp, [0, 0, 2, 3])
    assert merged[0][0] == pytest.approx(100, abs=0.5) and merged[0][2] == pytest.approx(400, abs=0.5)


def test_polarity_keeps_a_trims_two_sides_apart():
    from panosfm_graph.lines.tracking import match_pair

    # frame a: a trim's two vertical sides 3 px apart, dark-to-bright then bright-to-dark; in frame b
    # both moved 3 px right (parallax), so a's right side falls on b's left side's line exactly
    a = np.array([[100, 50, 100, 250], [103, 50, 103, 250]], np.float64)
    b = a + [3, 0, 3, 0]
    b_rev = b[:, [2, 3, 0, 1]]  # b's segments stored in the other direction: polarity flips sign with it
    lab = np.zeros(2, np.int8)
    ca = np.array([40.0, -40.0])
    H = np.eye(3)
    ia, ib, _ = match_pair(a, lab, b, lab, H, 27.0, 1.0)
    assert list(zip(ia, ib)) == [(1, 0)]  # without polarity: a's right side takes b's left side
    for eb, cb in ((b, ca), (b_rev, -ca)):
        ia, ib, _ = match_pair(a, lab, eb, lab, H, 27.0, 1.0, contrast_a=ca, contrast_b=cb, polarity_min=8.0)
        assert list(zip(ia, ib)) == [(0, 0), (1, 1)]
    # weak contrast (below polarity_min) says nothing
    ia, ib, _ = match_pair(a, lab, b, lab, H, 27.0, 1.0, contrast_a=ca / 10, contrast_b=ca / 10, polarity_min=8.0)
    assert list(zip(ia, ib)) == [(1, 0)]


def test_angle_tolerance_grows_for_short_segments():
    from panosfm_graph.lines.tracking import match_pair

    def seg(length, deg):
        t = np.radians(deg)
        return np.array([[100, 100, 100 + length * np.cos(t), 100 + length * np.sin(t)]])

    lab = np.zeros(1, np.int8)
    H = np.eye(3)
    # 40 px, 2 degrees apart: paper's 1 degree rejects; atan(2 px / 40 px) = 2.9 degrees accepts
    assert len(match_pair(seg(40, 0), lab, seg(40, 2), lab, H, 20.0, 1.0)[0]) == 0
    assert len(match_pair(seg(40, 0), lab, seg(40, 2), lab, H, 20.0, 1.0, angle_px=2.0)[0]) == 1
    # 300 px long segments keep the 1 degree tolerance (atan(2 / 300) = 0.38 degrees)
    assert len(match_pair(seg(300, 0), lab, seg(300, 2), lab, H, 20.0, 1.0, angle_px=2.0)[0]) == 0
    assert len(match_pair(seg(300, 0), lab, seg(300, 0.5), lab, H, 20.0, 1.0, angle_px=2.0)[0]) == 1


def test_image_colinear_lines_side_by_side_do_not_match():
    from panosfm_graph.lines.tracking import match_pair

    H = np.eye(3)
    a = np.array([[100, 200, 300, 200]], np.float64)  # frame a: a piece on the left
    right = np.array([[340, 200.5, 500, 200.5]], np.float64)  # frame b: a colinear piece further right
    over = np.array([[250, 200.5, 420, 200.5]], np.float64)  # frame b: the same line, overlapping
    lab = np.zeros(1, np.int8)
    for piece, gap, expected in ((right, None, 1), (right, 0.0, 0), (right, 50.0, 1), (over, 0.0, 1)):
        ia, ib, _ = match_pair(a, lab, piece, lab, H, dist_px=27.0, angle_deg=1.0, gap_px=gap)
        assert len(ia) == expected, (piece, gap)


def _shifted_pair(shift):
    """Two frames of one view: 6 horizontal and 6 vertical lines, a door trim (two verticals 5 px apart);
    frame 1 is frame 0 moved by ``shift`` px (parallax / rotation error the homography does not model)."""
    rng = np.random.default_rng(3)
    hz = [[60, y, 260, y] for y in (30, 70, 95, 140, 160, 175)]
    vt = [[x, 20, x, 170] for x in (40, 110, 150, 210, 280, 300)] + [[180, 30, 180, 160], [185, 30, 185, 160]]
    e0 = np.array(hz + vt, np.float64)
    e1 = e0 + np.tile(shift, 2) + rng.normal(0, 0.2, e0.shape)
    labels = np.array([0] * len(hz) + [2] * len(vt), np.int8)
    n = len(e0)
    seg = Segments(endpoints=np.concatenate([e0, e1]).astype(np.float32), frame=np.repeat([0, 1], n).astype(np.int32),
                   frame_offsets=np.array([0, n, 2 * n]), colors=np.zeros((2 * n, 3), np.uint8))
    return seg, np.concatenate([labels, labels]), n


def test_residual_shift_recovers_an_image_translation():
    from panosfm_graph.lines.tracking import residual_shift

    seg, _, n = _shifted_pair(np.array([4.0, -1.5]))
    e = seg.endpoints.astype(np.float64)
    np.testing.assert_allclose(residual_shift(e[:n], e[n:]), [4.0, -1.5], atol=0.15)
    # only vertical lines: y is unconstrained and stays 0
    t = residual_shift(e[6:n], e[n + 6:])
    assert abs(t[0] - 4.0) < 0.15 and abs(t[1]) < 1e-3


def test_shift_refinement_keeps_a_trims_two_edges_apart():
    """A 4 px unmodelled shift crosses the matches of two lines 5 px apart; the refined homography does not."""
    from panosfm_graph.lines.tracking import track_lines as track_segments

    seg, labels, n = _shifted_pair(np.array([4.0, 0.0]))
    K = np.array([[300.0, 0, 160], [0, 300.0, 90], [0, 0, 1]])
    R = np.repeat(np.eye(3)[None], 2, axis=0)
    for m, crossed in ((0, True), (4, False)):
        cfg = with_overrides(Config(), tracking={"shift_min_matches": m})
        tracks = track_segments(seg, labels, K, R, cfg.tracking, image_size=(320, 180))
        t0, t1 = tracks.track_of[:n], tracks.track_of[n:]
        right = (t0 >= 0) & (t0 == t1)  # segment k of frame 0 and segment k of frame 1 in one track
        assert right[:12].all()  # well-separated lines match either way
        assert right[12:].all() != crossed, (m, t0[12:], t1[12:])


def test_a_match_never_jumps_to_the_neighbouring_line():
    """TrackingConfig.jump_px: frame 0 sees only a trim's left edge, frame 1 only its right one (5 px on); with
    the Manhattan directions the match is 5 px off the vanishing-point line after the common shift: not kept."""
    from panosfm_graph.lines.tracking import line_jumps, manhattan_lines
    from panosfm_graph.lines.tracking import track_lines as track_segments

    seg, labels, n = _shifted_pair(np.array([0.0, 0.0]))
    labels = labels.copy()
    labels[13] = -1  # frame 0: the trim's right edge (x=185) unseen
    labels[n + 12] = -1  # frame 1: its left edge (x=180) unseen
    K = np.array([[300.0, 0, 160], [0, 300.0, 90], [0, 0, 1]])
    R = np.repeat(np.eye(3)[None], 2, axis=0)
    directions = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]])  # label 0: image x, label 2: image y
    e = seg.endpoints.astype(np.float64)
    ml = manhattan_lines(seg, labels, K, R, directions)
    true = np.arange(12)  # the well-separated lines, matched to themselves, and the trim's jump 12 -> 13
    d = line_jumps(e[np.r_[true, 12]], ml[np.r_[n + true, n + 13]])
    assert np.all(d[:12] < 1.0) and abs(d[12] - 5.0) < 1.0, d
    for jump, mixed in ((0.0, True), (3.0, False)):
        cfg = with_overrides(Config(), tracking={"jump_px": jump})
        tracks = track_segments(seg, labels, K, R, cfg.tracking, image_size=(320, 180), directions=directions)
        t0, t1 = tracks.track_of[:n], tracks.track_of[n:]
        same = (t0 >= 0) & (t0 == t1)
        assert same[:12].all()  # the other lines match either way
        assert (t0[12] >= 0 and t0[12] == t1[13]) == mixed, (jump, t0[12:], t1[12:])


def test_the_jump_test_allows_the_parallax_of_a_wider_turn():
    """TrackingConfig.jump_ref_deg: a line's own parallax grows with the turn between two frames. Frames 4 degrees
    apart (a spin of 90 frames per turn), one line 4 px off where the rotation puts it: a true match that the fixed
    3 px (jump_ref_deg 0) drops and 3 px * 4 / 2 keeps; pairs within the paper's 2 degrees keep 3 px."""
    from panosfm_graph.lines.tracking import _warp, jump_threshold, rotation_homography
    from panosfm_graph.lines.tracking import track_lines as track_segments

    seg, labels, n = _shifted_pair(np.array([0.0, 0.0]))
    K = np.array([[300.0, 0, 160], [0, 300.0, 90], [0, 0, 1]])
    R = np.stack([np.eye(3), Rotation.from_euler("y", 4.0, degrees=True).as_matrix()])
    e = seg.endpoints.astype(np.float64)
    e1 = _warp(rotation_homography(K, R[0], R[1]), e[:n])
    e1[7] += [4.0, 0.0, 4.0, 0.0]  # the vertical at x=110: 4 px of its own parallax
    seg = dataclasses.replace(seg, endpoints=np.concatenate([e[:n], e1]).astype(np.float32))
    directions = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]])  # label 0: image x, label 2: image y
    for ref, kept in ((2.0, True), (0.0, False)):
        cfg = with_overrides(Config(), tracking={"jump_ref_deg": ref})
        assert jump_threshold(R[0], R[1], cfg.tracking) == pytest.approx(6.0 if ref else 3.0, rel=1e-6)
        tracks = track_segments(seg, labels, K, R, cfg.tracking, image_size=(320, 180), directions=directions)
        t0, t1 = tracks.track_of[:n], tracks.track_of[n:]
        assert ((t0 >= 0) & (t0 == t1))[np.r_[0:7, 8:12]].all()  # the other lines match either way
        assert (t0[7] >= 0 and t0[7] == t1[7]) == kept, (ref, t0[7], t1[7])
    near = Rotation.from_euler("y", 1.5, degrees=True).as_matrix()
    assert jump_threshold(np.eye(3), near, Config().tracking) == pytest.approx(3.0)


def test_upright_lines_keep_more_parallax_than_horizontal_ones():
    """TrackingConfig.jump_across_power: frames 4 degrees apart, an upright line 8 px across itself (a sideways step
    shifts it by f t / Z) is kept (3 px * 2^2 = 12 px), dropped without the power (3 px * 2 = 6 px); a horizontal
    line 8 px off is dropped either way (6 px)."""
    from panosfm_graph.lines.tracking import _warp, jump_threshold, rotation_homography
    from panosfm_graph.lines.tracking import track_lines as track_segments

    seg, labels, n = _shifted_pair(np.array([0.0, 0.0]))
    K = np.array([[300.0, 0, 160], [0, 300.0, 90], [0, 0, 1]])
    R = np.stack([np.eye(3), Rotation.from_euler("y", 4.0, degrees=True).as_matrix()])
    e = seg.endpoints.astype(np.float64)
    e1 = _warp(rotation_homography(K, R[0], R[1]), e[:n])
    e1[7] += [8.0, 0.0, 8.0, 0.0]  # the upright line at x=110
    e1[2] += [0.0, 8.0, 0.0, 8.0]  # the horizontal line at y=95
    seg = dataclasses.replace(seg, endpoints=np.concatenate([e[:n], e1]).astype(np.float32))
    directions = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]])
    for power, upright_kept in ((1.0, True), (0.0, False)):
        cfg = with_overrides(Config(), tracking={"jump_across_power": power})
        assert jump_threshold(R[0], R[1], cfg.tracking, 1.0) == pytest.approx(12.0 if power else 6.0, rel=1e-6)
        tracks = track_segments(seg, labels, K, R, cfg.tracking, image_size=(320, 180), directions=directions)
        t0, t1 = tracks.track_of[:n], tracks.track_of[n:]
        assert ((t0 >= 0) & (t0 == t1))[np.r_[0:2, 3:7, 8:12]].all()
        assert (t0[7] >= 0 and t0[7] == t1[7]) == upright_kept, (power, t0[7], t1[7])
        assert not (t0[2] >= 0 and t0[2] == t1[2])


def test_the_merge_gap_holds_a_turn_at_any_spin_speed():
    """TrackingConfig.merge_gap_deg: merge_fragments crosses merge_gap_frames (3) at 300 frames per turn, fewer
    frames where they turn further than 5.5 degrees (2 at 150 per turn, 1 at 100 or fewer), never more."""
    from panosfm_graph.lines.tracking import merge_gap

    def spin(per_turn: int) -> np.ndarray:
        yaw = np.arange(per_turn) * 360.0 / per_turn
        return Rotation.from_euler("y", yaw[:, None], degrees=True).as_matrix()

    assert [merge_gap(spin(k), 3, 5.5) for k in (600, 300, 270, 150, 100, 60)] == [3, 3, 3, 2, 1, 1]
    assert merge_gap(spin(150), 3, 0.0) == 3 and merge_gap(spin(150), 0, 5.5) == 0
    assert merge_gap(spin(1), 3, 5.5) == 3  # one frame: no step


def test_merge_needs_the_join_to_hold_in_the_image():
    """merge_fragments' image_px: fragments of two parallel lines 8 px apart agree in angle within a loose
    tol_px near the vanishing point, but not in the image; pieces of one line do."""
    from panosfm_graph.data import Tracks
    from panosfm_graph.lines.tracking import merge_fragments

    K = np.array([[300.0, 0, 160], [0, 300.0, 90], [0, 0, 1]])
    R = np.repeat(np.eye(3)[None], 6, axis=0)
    directions = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]])
    # vertical lines x=100 (frames 0-2 then 3-5: one line cut) and x=108 (frames 3-5: the neighbour)
    ep = [[100, 20, 100, 160]] * 3 + [[100, 20, 100, 160], [108, 20, 108, 160]] * 3
    frame = np.array([0, 1, 2, 3, 3, 4, 4, 5, 5], np.int32)
    segs = Segments(np.array(ep, np.float32), frame, np.array([0, 1, 2, 3, 5, 7, 9]), np.zeros((9, 3), np.uint8))
    for piece in (3, 4):  # track 1: the cut line's second piece, or the neighbouring line
        of = np.array([0, 0, 0, -1, -1, -1, -1, -1, -1], np.int32)
        of[[piece, piece + 2, piece + 4]] = 1
        tracks = Tracks(of, np.array([2, 2], np.int8))
        loose = merge_fragments(tracks, segs, K, R, directions, gap_frames=3, tol_px=20.0)
        strict = merge_fragments(tracks, segs, K, R, directions, gap_frames=3, tol_px=20.0, image_px=3.0)
        assert loose.n == 1  # the angle test alone joins either
        assert strict.n == (1 if piece == 3 else 2), (piece, strict.track_of)


def test_spin_line_rms_fits_one_line_seen_from_a_spin_circle():
    """fragments.spin_line_rms: the planes through one vertical line seen from cameras on a spin's circle (any arm,
    any stand point) fit one line (RMS ~0); a piece of a parallel line 15 cm away does not (several px)."""
    from panosfm_graph.lines.fragments import spin_line_rms

    yaw = np.radians(np.arange(12) * 6.0)  # a 60-frame spin's steps
    z = np.column_stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)])
    y = np.tile([0.0, 0.0, -1.0], (len(yaw), 1))
    R_wc = np.stack([np.cross(y, z), y, z], axis=2)
    centres = np.array([0.2, -0.1]) + 0.31 * z[:, :2]  # a stand point off the origin, an arm of 0.31 m

    def phi(line_xy: np.ndarray, frames: np.ndarray) -> np.ndarray:
        r = line_xy - centres[frames]
        return np.arctan2(r[:, 0], -r[:, 1])  # the plane's normal (-r_y, r_x) in the basis (x, y)

    frames = np.arange(12)
    one = np.array([1.8, 0.9])
    other = one + np.array([0.0, 0.15])
    angles = np.concatenate([phi(one, frames[:5]), phi(one, frames[7:]), phi(other, frames[7:])])
    fr = np.concatenate([frames[:5], frames[7:], frames[7:]])
    groups = np.concatenate([np.zeros(5), np.zeros(5), -np.ones(5)]).astype(np.int64)  # group 0: one line
    groups2 = np.concatenate([np.ones(5), -np.ones(5), np.ones(5)]).astype(np.int64)  # group 1: two lines
    rms = spin_line_rms(angles, fr, 2, R_wc, np.eye(3), np.maximum(groups, groups2), 2, 500.0)
    assert rms[0] < 1e-6, rms
    assert rms[1] > 3.0, rms
    # fewer than 3 observations: always fitted; parallel planes only (no baseline): infinity
    assert spin_line_rms(angles[:2], fr[:2], 2, R_wc, np.eye(3), np.zeros(2, np.int64), 1, 500.0)[0] == 0.0
    same = np.full(4, 0.3)
    assert np.isinf(spin_line_rms(same, np.zeros(4, np.int64), 2, R_wc, np.eye(3), np.zeros(4, np.int64), 1, 500.0)[0])
