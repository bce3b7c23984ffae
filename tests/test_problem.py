"""Tests of the image-free synthetic problem (panosfm_graph.synth.problem)."""
import numpy as np
import pytest

from panosfm_graph.data import FLOOR, JUNCTION, ORTHOGONAL, PARALLEL
from panosfm_graph.geometry import project, rotation_angle_deg
from panosfm_graph.synth.problem import _occluded, make_problem


@pytest.fixture(scope="module")
def clean():
    return make_problem("living", 30, (320, 180), seed=0, pixel_noise_px=0.0)


def _endpoint_line_dist(p):
    """Returns (2S,) pixel distances of tracked segment endpoints to their projected GT line."""
    pre, K = p.preprocessed, p.camera.K
    s = np.flatnonzero(p.tracks.track_of >= 0)
    out = []
    for f in np.unique(pre.segments.frame[s]):
        m = s[pre.segments.frame[s] == f]
        L = p.gt_track_lines[p.tracks.track_of[m]]
        a, _ = project(K, p.gt_R_wc[f], p.gt_centers[f], L[:, :3])
        b, _ = project(K, p.gt_R_wc[f], p.gt_centers[f], L[:, 3:])
        d = b - a
        n = np.stack([-d[:, 1], d[:, 0]], 1) / np.linalg.norm(d, axis=1, keepdims=True)
        ep = pre.segments.endpoints[m].astype(float)
        out += [np.abs(np.sum((ep[:, :2] - a) * n, 1)), np.abs(np.sum((ep[:, 2:] - a) * n, 1))]
    return np.concatenate(out)


def test_segments_lie_on_projected_gt_edges(clean):
    d = _endpoint_line_dist(clean)
    assert len(d) > 100
    assert d.max() < 1e-2  # float32 endpoints
    noisy = make_problem("living", 30, (320, 180), seed=0, pixel_noise_px=0.3)
    dn = _endpoint_line_dist(noisy)
    assert 0.1 < np.median(dn) < 0.4  # median |N(0, 0.3)| = 0.2
    seg = clean.preprocessed.segments
    assert np.all(seg.lengths >= 0.05 * 180 - 1e-3)
    assert np.all(seg.endpoints >= -0.5 - 1e-3) and np.all(seg.endpoints[:, [0, 2]] <= 319.5 + 1e-3)
    assert np.all(np.diff(seg.frame) >= 0)


def test_tracks_and_labels(clean):
    tr, pre = clean.tracks, clean.preprocessed
    seg, off = tr.members()
    assert np.all(np.diff(off) >= 2)
    frames = pre.segments.frame[seg]
    key = tr.track_of[seg].astype(np.int64) * 10_000 + frames
    assert len(np.unique(key)) == len(key)  # at most one segment per frame
    assert np.all(pre.labels[seg] == tr.axis[tr.track_of[seg]])
    # GT line directions are the tracks' Manhattan directions
    d = clean.gt_track_lines[:, 3:] - clean.gt_track_lines[:, :3]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    M = pre.manhattan.directions
    assert np.allclose(np.abs(np.sum(d * M[tr.axis], 1)), 1.0, atol=1e-9)
    assert np.isclose(np.linalg.det(M), 1.0)


def test_relations_hold_in_ground_truth():
    p = make_problem("office", 30, (320, 180), seed=0, pixel_noise_px=0.0, false_relation_ratio=0.2)
    r, sc = p.relations, p.scene
    counts = r.counts()
    assert counts["parallel"] > 0 and counts["orthogonal"] > 0 and counts["junction"] > 0
    mid = sc.to_room(0.5 * (p.gt_track_lines[:, :3] + p.gt_track_lines[:, 3:]))
    pair = r.kind != FLOOR
    a, b, k = r.track_a[pair], r.track_b[pair], r.normal_axis[pair].astype(int)
    gap = np.abs(mid[a, k] - mid[b, k])
    true = p.relation_true[pair]
    assert np.all(gap[true] < 1e-6)
    assert np.sum(~true) == int(round(0.2 * np.sum(p.relation_true)))
    assert np.all(gap[~true] > 0.1)
    ax = p.tracks.axis
    assert np.all((k != ax[a]) & (k != ax[b]))
    assert np.all((ax[a] == ax[b]) == (r.kind[pair] == PARALLEL))
    assert np.all(np.isin(r.kind[pair], (ORTHOGONAL, PARALLEL, JUNCTION)))
    fl = r.track_a[r.kind == FLOOR]
    assert np.all(np.abs(mid[fl, 2]) < 1e-6)
    assert np.all(r.support >= 1)


def test_rotation_noise_and_drift():
    p = make_problem("bedroom", 40, (320, 180), seed=1, rot_noise_deg=0.5, imu_drift_deg=3.0)
    ang = rotation_angle_deg(p.gt_R_wc, p.preprocessed.R_wc)
    assert 0.3 < np.sqrt(np.mean(ang ** 2)) < 0.8
    drift = rotation_angle_deg(p.gt_R_wc, p.preprocessed.R_wc_imu)
    assert abs(drift[-1] - 3.0) < 1e-6 and drift[0] < 1e-6


def test_occlusion_ray_test():
    c = np.zeros(3)
    bmin, bmax = np.array([[1.0, -0.5, -0.5]]), np.array([[2.0, 0.5, 0.5]])
    P = np.array([[3.0, 0.0, 0.0], [0.5, 0.0, 0.0], [3.0, 3.0, 0.0], [1.0, 0.5, 0.5], [2.0, 0.5, 0.5]])
    # behind the box, before it, beside it, its near corner (visible), its far corner (hidden)
    assert _occluded(c, P, bmin, bmax).tolist() == [True, False, False, False, True]
