"""Geometric relationship detection between line tracks (paper §3.2).

Four coplanarity tests on the segments of each frame, then deduplicated
across frames into relations between *tracks* (colinearity is the tracks
themselves):

* **orthogonal**: two segments of different Manhattan labels ``a``, ``b``; the
  mean surface normal inside the quad of their four endpoints lies within
  ``quad_normal_deg`` (20°) of the third direction and the mean angle between
  that mean and the quad's normals is below ``quad_deviation_deg`` (5°);
* **parallel**: the same test for two segments of one label ``a``; the plane
  normal is whichever of the two other directions the mean normal is nearer;
* **junction**: two segments of different labels whose endpoints are within
  ``junction_dist_frac * min(w, h)``; the plane normal is the third direction;
  beyond the paper, both must end near their lines' intersection (an L, not
  the T of an occluding edge) and the inside of the L must pass the
  orthogonal normal test (measured on real pipeline output: junction
  precision 0.44-0.65 -> 0.92-0.96 with oracle normals);
* **floor**: floor pixels have normals within ``floor_normal_deg`` (25°) of
  the vertical (Manhattan axis 2, up) and look below the horizon; the mask is
  dilated once; horizontal segments (labels 0/1) fully inside are on the floor.

Beyond the paper, an orthogonal or parallel pair is rejected when another
Manhattan segment lies inside its quad (:func:`quad_crossed`,
``quad_clear_frac``): a cabinet's outline between two wall lines shows that
the normals in the quad may belong to two parallel planes (measured on real
pipeline output with orientation-map normals: orthogonal precision
0.44-0.57 -> 0.66-0.77, recall 0.50-0.75 -> 0.37-0.64). A segment counts
when enough of its length runs through the quad (``quad_clear_samples``
points along it), not only when its mid-point lies inside: a cabinet top
crossing the quad between a wall line and a cabinet edge has its mid-point
beyond them (oracle normals, 200-frame captures: orthogonal precision
0.90/0.83/0.85 -> 0.92/0.90/0.86, parallel 0.88/0.84/0.73 -> 0.94/0.84/0.74,
recall unchanged within 0.02). Floor relations on
furniture tops are dropped later, by the linear solve (``linear.floor_verified``).

Known limits (measured on real pipeline output, ``tools/bench_relations.py``):
normals cannot tell two parallel planes apart (a bookshelf's front and the
wall behind it, a desk top and the floor seen past it), so orthogonal /
parallel pairs across such an occluding edge pass (oracle precision
0.73-0.95), and the tops of tables and sofa seats are taken for floor when
the floor itself is out of view (oracle floor precision 0.2-0.56).

Vectorised: candidate pairs for all frames come from one ``cKDTree`` over
midpoints and endpoints (frames kept apart by an offset), never an all-pairs
loop; each quad is sampled on a fixed bilinear grid between its two segments
(area-weighted, so the mean is the quad's area mean) and all samples of a
chunk of pairs are gathered from the low-resolution normal maps at once.
"""
from __future__ import annotations

import dataclasses
import logging

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .config import RelationsConfig
from .data import FLOOR, JUNCTION, ORTHOGONAL, PARALLEL, Camera, NormalMaps, Preprocessed, Relations, Tracks

log = logging.getLogger("panosfm.relations")

QUAD_GRID = 8  # samples per side of a quad (QUAD_GRID**2 per pair)
MIN_SEPARATION_PX = 2.0  # quads thinner than this (normal-map pixels) say nothing about a plane
FLOOR_SAMPLES = 9  # points tested along a segment for "fully inside the floor region"
_CHUNK = 20000


def empty_relations() -> Relations:
    """Returns a :class:`Relations` with no rows."""
    z = np.zeros(0, np.int32)
    return Relations(z.astype(np.int8), z, z.copy(), z.astype(np.int8), z.copy())


def _frame_pairs(points: np.ndarray, frame: np.ndarray, owner: np.ndarray, radius: float, span: float) -> np.ndarray:
    """Returns unique (P, 2) owner pairs (i < j) with points of the same frame within ``radius``.

    One ``cKDTree`` for all frames: each frame's points are shifted along x by
    ``frame * span`` (``span`` exceeds the image size plus the radius).
    """
    if len(points) < 2:
        return np.zeros((0, 2), np.int64)
    X = np.column_stack([points[:, 0] + frame * span, points[:, 1]])
    pp = cKDTree(X).query_pairs(radius, output_type="ndarray")
    if len(pp) == 0:
        return np.zeros((0, 2), np.int64)
    a, b = owner[pp[:, 0]], owner[pp[:, 1]]
    keep = a != b
    pairs = np.column_stack([np.minimum(a, b), np.maximum(a, b)])[keep]
    return np.unique(pairs, axis=0)


def _uncrossed(p1: np.ndarray, p2: np.ndarray, q1: np.ndarray, q2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns segment b's end points (q1, q2) ordered so that the quad p1 p2 q2 q1 has no crossing sides."""
    swap = (np.linalg.norm(p1 - q1, axis=-1) + np.linalg.norm(p2 - q2, axis=-1)) > (
        np.linalg.norm(p1 - q2, axis=-1) + np.linalg.norm(p2 - q1, axis=-1))
    return np.where(swap[..., None], q2, q1), np.where(swap[..., None], q1, q2)


def quad_normal_stats(
    normals: NormalMaps, frame: np.ndarray, seg_a: np.ndarray, seg_b: np.ndarray, grid: int = QUAD_GRID
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Returns (mean unit normal (P, 3), mean angular deviation (P,) deg, valid area share (P,), worst strip deviation (P,) deg).

    Paper §3.2: the average surface normal inside the quad of the two
    segments' four endpoints and the average angle between it and the quad's
    normals. ``seg_a``/``seg_b`` (P, 4) are endpoints in normal-map pixels;
    the quad is the bilinear patch from segment a to segment b (endpoints
    paired so that its sides do not cross), sampled with area weights on
    ``grid`` points along the segments times ``grid + 2`` strips across: two
    thin strips 1 and 2 pixels from each segment (where a thin surface seen
    behind an occluding edge shows) and the rest spread evenly. The worst
    strip deviation is the largest mean angle between one strip's normals
    and the quad's mean (a strip of another orientation along a segment means
    the segment bounds a different surface).
    """
    F, h, w = normals.valid.shape
    P = len(frame)
    p1, p2 = seg_a[:, None, :2], seg_a[:, None, 2:]
    q1, q2 = seg_b[:, None, :2], seg_b[:, None, 2:]
    q1, q2 = _uncrossed(p1, p2, q1, q2)
    sep = np.linalg.norm(0.5 * (p1 + p2) - 0.5 * (q1 + q2), axis=-1)  # (P, 1) pixels
    # strip centres across the quad (fractions of the way from a to b) and their widths
    G = grid + 2
    uni = (np.arange(G) + 0.5) / G
    inner = (np.arange(G - 4) + 0.5) / (G - 4)
    sep_ = np.maximum(sep, 1e-6)
    near = np.concatenate(
        [1.0 / sep_, 2.0 / sep_, 3.0 / sep_ + inner[None] * (1.0 - 6.0 / sep_), 1.0 - 2.0 / sep_, 1.0 - 1.0 / sep_], axis=1
    )
    t_rows = np.where(sep >= 3.0 * G / 2.0, near, uni[None])  # (P, G)
    edges = np.concatenate([np.zeros((P, 1)), 0.5 * (t_rows[:, 1:] + t_rows[:, :-1]), np.ones((P, 1))], axis=1)
    dt_rows = np.diff(edges, axis=1)  # (P, G)
    s = (np.arange(grid) + 0.5) / grid
    s_ = np.broadcast_to(s[None, None, :], (P, G, grid)).reshape(P, -1, 1)
    t_ = np.broadcast_to(t_rows[:, :, None], (P, G, grid)).reshape(P, -1, 1)
    A = p1 + s_ * (p2 - p1)
    B = q1 + s_ * (q2 - q1)
    X = (1.0 - t_) * A + t_ * B  # (P, G*grid, 2)
    ds = (1.0 - t_) * (p2 - p1) + t_ * (q2 - q1)
    dt = B - A
    wgt = np.abs(ds[..., 0] * dt[..., 1] - ds[..., 1] * dt[..., 0])  # (P, G*grid) area element
    wgt *= np.broadcast_to(dt_rows[:, :, None], (P, G, grid)).reshape(P, -1)
    xi = np.rint(X[..., 0]).astype(np.int64)
    yi = np.rint(X[..., 1]).astype(np.int64)
    inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
    idx = (frame[:, None].astype(np.int64) * h + np.clip(yi, 0, h - 1)) * w + np.clip(xi, 0, w - 1)
    n = normals.maps.reshape(-1, 3)[idx].astype(np.float32)  # (P, G*grid, 3)
    ok = inside & normals.valid.reshape(-1)[idx]
    wv = wgt * ok
    total = np.maximum(wgt.sum(axis=1), 1e-12)
    share = wv.sum(axis=1) / total
    m = np.einsum("pk,pkc->pc", wv, n)
    m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-12)
    ang = np.degrees(np.arccos(np.clip(np.einsum("pkc,pc->pk", n, m), -1.0, 1.0)))
    dev = (wv * ang).sum(axis=1) / np.maximum(wv.sum(axis=1), 1e-12)
    okr = ok.reshape(P, G, grid)
    cnt = okr.sum(axis=2)
    strip = np.where(okr, ang.reshape(P, G, grid), 0.0).sum(axis=2) / np.maximum(cnt, 1)
    strip = np.where(cnt >= max(2, grid // 2), strip, 0.0)
    return m, dev, share, strip.max(axis=1)


def quad_crossed(pre: Preprocessed, seg_i: np.ndarray, seg_j: np.ndarray, min_len_px: float,
                 margin_px: float = 3.0, samples: int = 1) -> np.ndarray:
    """Returns (P,) bool: whether another Manhattan segment of the frame lies inside the quad of segments i and j.

    A deviation from the paper, for precision: normals cannot tell two
    parallel planes apart (a cabinet front and the wall behind it), but the
    cabinet's outline -- an image line between the two segments -- can. A
    segment counts when its part inside the quad (endpoints paired so that
    its sides do not cross) and more than ``margin_px`` from both segments'
    lines (not a piece of them) is at least ``min_len_px`` long, measured on
    ``samples`` points along it; ``samples=1`` tests its mid-point only (then
    the whole segment must be ``min_len_px`` long). Vectorised over pairs
    with each frame's segments padded to one width.
    """
    seg = pre.segments
    P = len(seg_i)
    if P == 0:
        return np.zeros(0, bool)
    ep = seg.endpoints.astype(np.float64)
    length = np.linalg.norm(ep[:, 2:] - ep[:, :2], axis=1)
    cand = (np.asarray(pre.labels) >= 0) & (length >= min_len_px)
    frame = seg.frame.astype(np.int64)
    F = len(seg.frame_offsets) - 1
    counts = np.bincount(frame[cand], minlength=F)
    width = int(counts.max()) if len(counts) else 0
    if width == 0:
        return np.zeros(P, bool)
    ids = np.flatnonzero(cand)  # sorted by frame, as segments are
    slot = np.arange(len(ids)) - np.concatenate([[0], np.cumsum(counts)[:-1]])[frame[ids]]
    table = np.full((F, width), -1, np.int64)
    table[frame[ids], slot] = ids
    out = np.zeros(P, bool)
    S = max(int(samples), 1)
    t = (np.arange(S) + 0.5) / S if S > 1 else np.array([0.5])
    chunk = max(_CHUNK // S, 1)
    for c0 in range(0, P, chunk):
        i, j = seg_i[c0:c0 + chunk], seg_j[c0:c0 + chunk]
        k = table[frame[i]]  # (p, width) candidate segments of the pair's frame
        valid = (k >= 0) & (k != i[:, None]) & (k != j[:, None])
        e0, e1 = ep[np.maximum(k, 0), None, :2], ep[np.maximum(k, 0), None, 2:]  # (p, width, 1, 2)
        m = e0 + t[:, None] * (e1 - e0)  # (p, width, S, 2): sample points of each candidate segment
        p1, p2, q1, q2 = ep[i, None, None, :2], ep[i, None, None, 2:], ep[j, None, None, :2], ep[j, None, None, 2:]
        q1, q2 = _uncrossed(p1, p2, q1, q2)
        poly = [p1, p2, q2, q1]
        sides = []
        for a, b in zip(poly, poly[1:] + poly[:1]):
            e = b - a
            sides.append(e[..., 0] * (m[..., 1] - a[..., 1]) - e[..., 1] * (m[..., 0] - a[..., 0]))
        sides = np.stack(sides, axis=-1)
        inside = np.all(sides > 0, axis=-1) | np.all(sides < 0, axis=-1)

        def off_line(a, b):  # distance of the mid-points to the line through a and b
            d = b - a
            n = np.linalg.norm(d, axis=-1)
            return np.abs(d[..., 0] * (m[..., 1] - a[..., 1]) - d[..., 1] * (m[..., 0] - a[..., 0])) / np.maximum(n, 1e-9)

        apart = (off_line(p1, p2) > margin_px) & (off_line(q1, q2) > margin_px)
        if S == 1:
            hit = (inside & apart)[..., 0]
        else:  # the length of the candidate inside the quad (S samples) must reach min_len_px
            seg_len = length[np.maximum(k, 0)]
            hit = (inside & apart).sum(axis=-1) * seg_len / S >= min_len_px
        out[c0:c0 + chunk] = np.any(valid & hit, axis=1)
    return out


def _quad_relations(pre, normals, seg_i, seg_j, labels, cfg, dirs):
    """Returns (kind, seg_i, seg_j, normal_axis) of the pairs passing the orthogonal/parallel quad test."""
    la, lb = labels[seg_i], labels[seg_j]
    same = la == lb
    want = np.where(same, cfg.parallel, cfg.orthogonal)
    seg_i, seg_j, la, lb, same = seg_i[want], seg_j[want], la[want], lb[want], same[want]
    ep = pre.segments.endpoints.astype(np.float64) * normals.scale
    frame = pre.segments.frame.astype(np.int64)
    out = []
    for c0 in range(0, len(seg_i), _CHUNK):
        sl = slice(c0, c0 + _CHUNK)
        i, j = seg_i[sl], seg_j[sl]
        sep = np.linalg.norm(0.5 * (ep[i, :2] + ep[i, 2:]) - 0.5 * (ep[j, :2] + ep[j, 2:]), axis=1)
        m, dev, share, worst = quad_normal_stats(normals, frame[i], ep[i], ep[j])
        cos = np.abs(m @ dirs.T)  # (P, 3) |cos| to each Manhattan direction
        a, b = la[sl].astype(np.int64), lb[sl].astype(np.int64)
        third = 3 - a - b
        # parallel: the nearer of the two directions other than a
        other = np.array([[1, 2], [0, 2], [0, 1]])[a]
        pick = np.take_along_axis(cos, other, axis=1).argmax(axis=1)
        axis = np.where(same[sl], other[np.arange(len(a)), pick], third)
        ang = np.degrees(np.arccos(np.clip(cos[np.arange(len(a)), axis], -1.0, 1.0)))
        ok = (
            (ang < cfg.quad_normal_deg)
            & (dev < cfg.quad_deviation_deg)
            & (worst < cfg.quad_normal_deg)
            & (share >= cfg.quad_valid_share)
            & (sep >= MIN_SEPARATION_PX)
        )
        if cfg.quad_clear_frac > 0 and np.any(ok):
            min_len = cfg.quad_clear_frac * min(normals.valid.shape[1:]) / normals.scale
            ok[ok] &= ~quad_crossed(pre, i[ok], j[ok], min_len, samples=cfg.quad_clear_samples)
        kind = np.where(same[sl], PARALLEL, ORTHOGONAL)
        out.append((kind[ok], i[ok], j[ok], axis[ok]))
    if not out:
        z = np.zeros(0, np.int64)
        return z, z, z, z
    return tuple(np.concatenate(x) for x in zip(*out))


def floor_masks(
    pre: Preprocessed, normals: NormalMaps, camera: Camera, config: RelationsConfig, lowest_only: bool = True
) -> np.ndarray:
    """Returns (F, h, w) bool floor regions (paper §3.2, floor coplanarity).

    Pixels whose normal is within ``floor_normal_deg`` of the vertical
    Manhattan direction (up) and whose viewing ray points below the horizon,
    dilated once with a 3 x 3 kernel. With ``lowest_only`` (a deviation from
    the paper, for precision) a pixel must also be reached from the image's
    bottom row, column-wise, without crossing a valid non-horizontal normal:
    the floor is the lowest horizontal surface, so the tops of furniture seen
    above their front faces are not taken for floor.
    """
    from .normals import lowres_rays

    F, h, w = normals.valid.shape
    up = pre.manhattan.directions[2] * (1.0 if pre.manhattan.directions[2, 2] >= 0 else -1.0)
    rays = lowres_rays(camera, h, w, normals.scale).reshape(-1, 3)
    cos_max = np.cos(np.radians(config.floor_normal_deg))
    kernel = np.ones((3, 3), np.uint8)
    out = np.zeros((F, h, w), bool)
    for f in range(F):
        below = ((rays @ (pre.R_wc[f].T @ up)) < 0).reshape(h, w)  # ray_w . up = ray_c . (R_wc^T up)
        n_up = (normals.maps[f].reshape(-1, 3).astype(np.float32) @ up).reshape(h, w)
        valid = normals.valid[f]
        up_n = valid & (n_up > cos_max)
        if lowest_only:
            # from the bottom row upwards, stop at the first pixel of a non-horizontal surface
            blocked = valid & ~up_n
            reach = np.cumprod(~blocked[::-1], axis=0)[::-1].astype(bool)
            up_n &= reach
        m = (below & up_n).astype(np.uint8)
        out[f] = cv2.dilate(m, kernel, iterations=1) > 0
    return out


def _junction_pairs(pre, normals, i, j, labels, ep, min_side, cfg, dirs):
    """Returns the junction candidates (i, j) that meet as an L (paper §3.2 plus two checks of ours).

    The paper's test (endpoints within ``junction_dist_frac``) also accepts
    T-junctions of an occluding edge and lines merely near in the image.
    With ``junction_corner_frac`` both segments must end within that share of
    ``min(w, h)`` of the intersection of their supporting lines (an L, not a
    T); with ``junction_normals`` the quad between them -- the inside of the
    L, which a face bounded by both lines fills -- must pass the orthogonal
    normal test.
    """
    if cfg.junction_corner_frac > 0 and len(i):
        def homog(e):
            return np.cross(np.column_stack([e[:, :2], np.ones(len(e))]), np.column_stack([e[:, 2:], np.ones(len(e))]))

        def to_corner(e):
            return np.minimum(np.linalg.norm(e[:, :2] - X, axis=1), np.linalg.norm(e[:, 2:] - X, axis=1))

        X = np.cross(homog(ep[i]), homog(ep[j]))
        finite = np.abs(X[:, 2]) > 1e-9 * np.maximum(np.abs(X[:, :2]).max(axis=1), 1.0)
        X = X[:, :2] / np.where(finite, X[:, 2], 1.0)[:, None]
        lim = cfg.junction_corner_frac * min_side
        near = to_corner
        keep = finite & (near(ep[i]) < lim) & (near(ep[j]) < lim)
        i, j = i[keep], j[keep]
    if cfg.junction_normals and len(i):
        qcfg = dataclasses.replace(cfg, orthogonal=True)
        _, i, j, _ = _quad_relations(pre, normals, i, j, labels, qcfg, dirs)
    return i, j


def detect_relations(
    pre: Preprocessed, tracks: Tracks, normals: NormalMaps, camera: Camera, config: RelationsConfig
) -> Relations:
    """Returns the coplanarity relations between tracks, deduplicated across frames (paper §3.2).

    Only segments that belong to a track are tested. A relation is the
    unique (kind, min track, max track, normal axis); ``support`` counts the
    frames in which it was detected. FLOOR relations have ``track_b = -1``
    and ``normal_axis = 2``.
    """
    seg = pre.segments
    track_of = np.asarray(tracks.track_of)
    labels = np.full(seg.n, -1, np.int64)
    tracked = np.flatnonzero(track_of >= 0)
    labels[tracked] = tracks.axis[track_of[tracked]]
    tracked = tracked[labels[tracked] >= 0]
    if len(tracked) == 0:
        return empty_relations()
    min_side = float(min(camera.width, camera.height))
    span = 4.0 * (camera.width + camera.height)
    frame = seg.frame.astype(np.int64)
    ep = seg.endpoints.astype(np.float64)
    dirs = pre.manhattan.directions
    kinds, ta, tb, axes = [], [], [], []

    def add(kind, i, j, axis):
        a, b = track_of[i], (track_of[j] if j is not None else np.full(len(i), -1))
        if j is not None:
            a, b = np.minimum(a, b), np.maximum(a, b)
        kinds.append(np.broadcast_to(kind, len(i)))
        ta.append(a)
        tb.append(b)
        axes.append(np.broadcast_to(axis, len(i)))

    if config.orthogonal or config.parallel:
        pts = np.concatenate([seg.midpoints[tracked], ep[tracked, :2], ep[tracked, 2:]])
        owner = np.tile(tracked, 3)
        pairs = _frame_pairs(pts, np.tile(frame[tracked], 3), owner, config.max_pair_dist_frac * min_side, span)
        kind, i, j, axis = _quad_relations(pre, normals, pairs[:, 0], pairs[:, 1], labels, config, dirs)
        add(kind, i, j, axis)
        log.debug("quad tests: %d candidate pairs, %d accepted", len(pairs), len(i))

    if config.junction:
        pts = np.concatenate([ep[tracked, :2], ep[tracked, 2:]])
        owner = np.tile(tracked, 2)
        pairs = _frame_pairs(pts, np.tile(frame[tracked], 2), owner, config.junction_dist_frac * min_side, span)
        i, j = pairs[:, 0], pairs[:, 1]
        diff = labels[i] != labels[j]
        i, j = _junction_pairs(pre, normals, i[diff], j[diff], labels, ep, min_side, config, dirs)
        add(JUNCTION, i, j, 3 - labels[i] - labels[j])

    if config.floor:
        hz = tracked[labels[tracked] != 2]
        if len(hz):
            mask = floor_masks(pre, normals, camera, config)
            F, h, w = mask.shape
            t = np.linspace(0.0, 1.0, FLOOR_SAMPLES)[None, :, None]
            e = ep[hz] * normals.scale
            X = e[:, None, :2] * (1.0 - t) + e[:, None, 2:] * t  # (N, K, 2)
            xi, yi = np.rint(X[..., 0]).astype(np.int64), np.rint(X[..., 1]).astype(np.int64)
            inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
            on = mask[frame[hz][:, None], np.clip(yi, 0, h - 1), np.clip(xi, 0, w - 1)] & inside
            i = hz[on.all(axis=1)]
            add(FLOOR, i, None, 2)

    if not kinds:
        return empty_relations()
    rows = np.column_stack([np.concatenate(x).astype(np.int64) for x in (kinds, ta, tb, axes)])
    if len(rows) == 0:
        return empty_relations()
    uniq, support = np.unique(rows, axis=0, return_counts=True)
    weak = (uniq[:, 0] == JUNCTION) & (support < config.junction_min_support)
    uniq, support = uniq[~weak], support[~weak]
    rel = Relations(
        kind=uniq[:, 0].astype(np.int8),
        track_a=uniq[:, 1].astype(np.int32),
        track_b=uniq[:, 2].astype(np.int32),
        normal_axis=uniq[:, 3].astype(np.int8),
        support=support.astype(np.int32),
    )
    log.info("relations: %s", rel.counts())
    return rel


def relations_true(
    relations: Relations, track_lines_room: np.ndarray, floor_z_m: float, tol_m: float = 0.02
) -> np.ndarray:
    """Returns (R,) bool: whether each relation holds for the tracks' ground-truth 3D edges.

    For benchmarks and tests. ``track_lines_room`` (T, 6) are each track's GT
    edge in the scene's Manhattan (room) frame, metres (NaN where unknown).
    A pair relation with normal axis ``k`` holds when both edges lie in
    planes ``x_k = const`` with constants within ``tol_m`` (the constraint the
    solver will enforce); a FLOOR relation when the edge lies at ``floor_z_m``.
    """
    L = np.asarray(track_lines_room, dtype=np.float64)
    a = relations.track_a.astype(np.int64)
    b = relations.track_b.astype(np.int64)
    k = relations.normal_axis.astype(np.int64)
    r = np.arange(relations.n)
    A0, A1 = L[a, :3], L[a, 3:]
    flat_a = np.abs(A0[r, k] - A1[r, k]) < tol_m
    floor = (np.abs(A0[:, 2] - floor_z_m) < tol_m) & (np.abs(A1[:, 2] - floor_z_m) < tol_m)
    bb = np.maximum(b, 0)
    B0, B1 = L[bb, :3], L[bb, 3:]
    flat_b = np.abs(B0[r, k] - B1[r, k]) < tol_m
    same = np.abs(0.5 * (A0[r, k] + A1[r, k]) - 0.5 * (B0[r, k] + B1[r, k])) < tol_m
    return np.where(relations.kind == FLOOR, floor, flat_a & flat_b & same)


# --------------------------------------------------------------------------- ground-truth judging (benchmarks, tests)


def track_gt_edges(
    pre: Preprocessed, tracks: Tracks, camera: Camera, gt_R_wc: np.ndarray, gt_centers: np.ndarray,
    edges_world: np.ndarray, edge_axis_pipe: np.ndarray, max_px: float = 3.0, min_share: float = 0.5,
    samples: int = 5,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns (edge (T,) int64, share (T,)): each track's ground-truth 3D edge (-1 if unknown) and its vote share.

    For benchmarks and tests on real pipeline output. Every tracked segment
    votes for the GT edge (``edges_world`` (M, 6), Manhattan axis
    ``edge_axis_pipe`` (M,) in the pipeline's axis order) of its own axis
    whose projection with the GT pose is nearest (mean distance of
    ``samples`` points along the segment to the projected edge segment, below
    ``max_px``); a track takes the majority edge if at least ``min_share`` of
    its segments voted for it. Edges are clipped to 5 cm in front of the
    camera before projection.
    """
    seg = pre.segments
    K = camera.K
    track_of = np.asarray(tracks.track_of)
    tracked = np.flatnonzero(track_of >= 0)
    vote = np.full(seg.n, -1, np.int64)
    t = np.linspace(0.0, 1.0, samples)[None, :, None]
    E0, E1 = edges_world[:, :3], edges_world[:, 3:]
    for f in np.unique(seg.frame[tracked]):
        s = tracked[seg.frame[tracked] == f]
        R, C = gt_R_wc[f], gt_centers[f]
        a, b = (E0 - C) @ R, (E1 - C) @ R  # camera frame
        zmin = 0.05
        keep = (a[:, 2] > zmin) | (b[:, 2] > zmin)
        dz = b[:, 2] - a[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            tz = np.nan_to_num((zmin - a[:, 2]) / dz)
        t0 = np.where(a[:, 2] < zmin, tz, 0.0)[:, None]
        t1 = np.where(b[:, 2] < zmin, tz, 1.0)[:, None]
        a, b = a + t0 * (b - a), a + t1 * (b - a)
        pa = (a @ K.T)[:, :2] / np.maximum(a[:, 2:], 1e-9)
        pb = (b @ K.T)[:, :2] / np.maximum(b[:, 2:], 1e-9)
        ep = seg.endpoints[s].astype(np.float64)
        X = ep[:, None, :2] * (1.0 - t) + ep[:, None, 2:] * t  # (n, S, 2)
        d = pb - pa  # (M, 2)
        L2 = np.maximum(np.sum(d * d, axis=1), 1e-12)
        rel = X[:, :, None, :] - pa[None, None]  # (n, S, M, 2)
        u = np.clip(np.einsum("nsmc,mc->nsm", rel, d) / L2, 0.0, 1.0)
        dist = np.linalg.norm(rel - u[..., None] * d, axis=-1).mean(axis=1)  # (n, M)
        ok = keep[None] & (edge_axis_pipe[None] == tracks.axis[track_of[s]][:, None])
        dist = np.where(ok, dist, np.inf)
        best = dist.argmin(axis=1)
        vote[s] = np.where(dist[np.arange(len(s)), best] < max_px, best, -1)
    T = tracks.n
    edge = np.full(T, -1, np.int64)
    share = np.zeros(T)
    v = vote[tracked] >= 0
    if v.any():
        pairs, cnt = np.unique(np.column_stack([track_of[tracked][v], vote[tracked][v]]), axis=0, return_counts=True)
        order = np.lexsort((-cnt, pairs[:, 0]))
        pairs, cnt = pairs[order], cnt[order]
        first = np.concatenate([[True], pairs[1:, 0] != pairs[:-1, 0]])
        tt, ee, cc = pairs[first, 0], pairs[first, 1], cnt[first]
        n_seg = np.bincount(track_of[tracked], minlength=T)
        share[tt] = cc / np.maximum(n_seg[tt], 1)
        edge[tt] = np.where(share[tt] >= min_share, ee, -1)
    return edge, share


def judge_relations(
    relations: Relations, track_edge: np.ndarray, edges_room: np.ndarray, face_axis: np.ndarray,
    face_offset: np.ndarray, axis_to_room: np.ndarray, floor_z_m: float, tol_m: float = 0.02,
    shell_min: np.ndarray | None = None, shell_max: np.ndarray | None = None, fixture_m: float = 0.05,
) -> np.ndarray:
    """Returns (R,) int8: 1 where a relation holds for the tracks' GT edges, 0 where it does not, -1 unknown.

    For benchmarks and tests. A pair relation with (pipeline) normal axis
    ``k`` holds when both GT edges lie, within ``tol_m``, on one plane
    ``x_k' = c`` (``k' = axis_to_room[k]``) that is the plane of a face of the
    scene (``face_axis``/``face_offset``, room frame): the constraint the
    solver enforces. Thin wall fixtures: with the shell's inner corners
    ``shell_min``/``shell_max`` given, an edge within ``fixture_m`` (5 cm) of
    a wall plane of axis ``k'`` counts as on that wall (posters 1.2 cm, door
    leaves, jambs and window trims 2-4 cm, a TV screen 5 cm off the wall are
    part of the wall's plane: forcing them onto it costs the model less than
    the 5 cm line accuracy target); everything else is judged at ``tol_m``.
    FLOOR holds when the edge lies at ``floor_z_m``. Unknown: a track
    without a GT edge.
    """
    ea = track_edge[relations.track_a]
    eb = np.where(relations.track_b >= 0, track_edge[np.maximum(relations.track_b, 0)], 0)
    known = (ea >= 0) & (eb >= 0)
    L = edges_room
    A, B = L[np.maximum(ea, 0)], L[np.maximum(eb, 0)]
    k = axis_to_room[relations.normal_axis.astype(np.int64)]
    r = np.arange(relations.n)
    flat_a = np.abs(A[r, k] - A[r, 3 + k]) < tol_m
    flat_b = np.abs(B[r, k] - B[r, 3 + k]) < tol_m
    ca, cb = 0.5 * (A[r, k] + A[r, 3 + k]), 0.5 * (B[r, k] + B[r, 3 + k])
    if shell_min is not None and shell_max is not None:
        for wall in (np.asarray(shell_min, float)[k], np.asarray(shell_max, float)[k]):
            ca = np.where(np.abs(ca - wall) <= fixture_m + 1e-9, wall, ca)
            cb = np.where(np.abs(cb - wall) <= fixture_m + 1e-9, wall, cb)
    on_face = (face_axis[None] == k[:, None]) & (np.abs(face_offset[None] - ca[:, None]) < tol_m) & (
        np.abs(face_offset[None] - cb[:, None]) < tol_m)
    pair_ok = flat_a & flat_b & on_face.any(axis=1)
    floor_ok = (np.abs(A[:, 2] - floor_z_m) < tol_m) & (np.abs(A[:, 5] - floor_z_m) < tol_m)
    ok = np.where(relations.kind == FLOOR, floor_ok, pair_ok)
    return np.where(known, ok.astype(np.int8), np.int8(-1)).astype(np.int8)
