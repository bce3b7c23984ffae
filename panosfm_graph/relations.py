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

Also beyond the paper, an option (off: measured, it costs the swaying spins more than
it gives), where segments meet the floor (``floor_contact_frac``,
:func:`floor_contacts`, :func:`floor_consistent`): a vertical plane meets the
floor in one line, so two verticals standing on the floor stand on one image
line through the plane's horizontal vanishing point, a vertical on the plane
does not reach below the plane's foot, and a horizontal that ends on the
inside of a vertical edge (a T, ``t_junction_frac``: the wall's foot hidden
behind a nightstand's front edge) is not on its plane. Such pairs are
cannot-links between tracks, tested in every frame that sees both; the
coplanarities are then merged into planes (junctions first, then orthogonal,
then parallel pairs, each by support) and one that would put two cannot-linked
tracks on one plane is dropped (:func:`consistent_planes`): the frame that sees
the cabinet's foot vetoes its front's coplanarity with the wall in the frames
where the foot is out of view, and through the wall's corner line too. A
floor candidate from whose end a vertical hangs down (``floor_hanging_frac``,
:func:`hanging_verticals`: a cabinet's or bed's top) is not floor. Measured:
README (status) and ``RelationsConfig``.

Also beyond the paper (``junction_sides``): an L-junction tells on which
side of each of its lines the face lies (the inside of the L), and that side
is a direction of the Manhattan frame (:func:`face_sides`), the same in every
frame. A bookshelf's front edge bounds the front towards its top edge; a
quad from that edge to a wall line on its other side, where the wall behind
shows the same normal, is dropped: its line has faces of that orientation
only on the side the junctions show (:func:`junction_sided`). A line no
junction touches keeps all its pairs. Measured: ``RelationsConfig``.

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
from .geometry import pixel_rays, world_rays

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


def on_mask(mask: np.ndarray, frame: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Returns (n, ...) bool: whether points ``X`` (n, ..., 2) in mask pixels of frames ``frame`` (n,) are set in ``mask`` (F, h, w).

    Points outside the image are not.
    """
    F, h, w = mask.shape
    xi = np.rint(X[..., 0]).astype(np.int64)
    yi = np.rint(X[..., 1]).astype(np.int64)
    inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
    ff = np.broadcast_to(np.asarray(frame, np.int64).reshape((-1,) + (1,) * (X.ndim - 2)), xi.shape)
    return inside & mask[ff, np.clip(yi, 0, h - 1), np.clip(xi, 0, w - 1)]


@dataclasses.dataclass(frozen=True)
class FloorContacts:
    """Where segments meet the floor, per segment (index = segment id; see :func:`floor_contacts`).

    ``contact``: a vertical segment whose lower end stands on floor pixels;
    ``bottom`` / ``top`` (N, 2) its lower / upper end (image pixels); ``floor_line``: a
    horizontal segment with floor pixels on its lower side and none on its
    upper side (a wall's or a cabinet's foot); ``line`` (N, 3) its image line
    scaled so that ``line . (x, y, 1)`` is the signed distance in pixels,
    positive on the floor side; ``vp`` (F, 3, 3) each frame's vanishing
    points (homogeneous image points of the Manhattan directions).
    """

    contact: np.ndarray
    bottom: np.ndarray
    top: np.ndarray
    floor_line: np.ndarray
    line: np.ndarray
    vp: np.ndarray


def floor_contacts(pre: Preprocessed, normals: NormalMaps, camera: Camera, mask: np.ndarray, labels: np.ndarray,
                   segs: np.ndarray, probe_px: float = 2.0, samples: int = FLOOR_SAMPLES) -> FloorContacts:
    """Returns the :class:`FloorContacts` of segments ``segs`` (labels from the tracks; others stay False).

    A vertical segment's lower end (the end whose viewing ray points further
    down) is a floor contact when the floor region (``mask``, :func:`floor_masks`)
    holds ``probe_px`` normal-map pixels beyond it along the segment. A
    horizontal segment is a floor line when at least 70 % of ``samples``
    points ``probe_px`` to its lower side are floor and at most 30 % to its
    upper side.
    """
    seg = pre.segments
    N = seg.n
    K = camera.K
    up = pre.manhattan.directions[2] * (1.0 if pre.manhattan.directions[2, 2] >= 0 else -1.0)
    R = pre.R_wc.astype(np.float64)
    vp = np.einsum("ij,fkj,dk->fdi", K, R, pre.manhattan.directions)  # K R_wc^T d
    contact = np.zeros(N, bool)
    floor_line = np.zeros(N, bool)
    bottom = np.zeros((N, 2))
    top = np.zeros((N, 2))
    line = np.zeros((N, 3))
    if len(segs) == 0:
        return FloorContacts(contact, bottom, top, floor_line, line, vp)
    scale = normals.scale
    delta = probe_px / scale
    ep = seg.endpoints[segs].astype(np.float64)
    f = seg.frame[segs].astype(np.int64)
    up_c = np.einsum("fji,j->fi", R, up)[f]  # (n, 3) up in each segment's camera frame

    def height(x):  # (n, ..., 2) image points -> sine of their viewing ray's elevation
        return np.einsum("n...c,nc->n...", pixel_rays(K, x), up_c)

    def on_floor(x):  # (n, ..., 2) image points -> bool: inside the image and on the floor region
        return on_mask(mask, f, x * scale)

    a, b = ep[:, :2], ep[:, 2:]
    vert = labels[segs] == 2
    lower_b = height(b) < height(a)
    lo = np.where(lower_b[:, None], b, a)
    hi = np.where(lower_b[:, None], a, b)
    u = (lo - hi) / np.maximum(np.linalg.norm(lo - hi, axis=1, keepdims=True), 1e-9)
    contact[segs] = vert & on_floor(lo + delta * u)
    bottom[segs] = lo
    top[segs] = hi
    # horizontal segments: which image side is down, and is the floor there (and not on the other side)?
    d = b - a
    nrm = np.column_stack([-d[:, 1], d[:, 0]]) / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    mid = 0.5 * (a + b)
    down = np.where((height(mid + delta * nrm) < height(mid - delta * nrm))[:, None], nrm, -nrm)
    t = ((np.arange(samples) + 0.5) / samples)[None, :, None]
    X = a[:, None] + t * d[:, None]  # (n, S, 2)
    below = on_floor(X + delta * down[:, None]).mean(axis=1)
    above = on_floor(X - delta * down[:, None]).mean(axis=1)
    floor_line[segs] = ~vert & (labels[segs] >= 0) & (below >= 0.7) & (above <= 0.3)
    # the image line through the mid-point and the vanishing point of its direction (extrapolates better)
    lab = np.clip(labels[segs], 0, 2)
    L = np.cross(np.column_stack([mid, np.ones(len(a))]), vp[f, lab])
    L /= np.maximum(np.hypot(L[:, 0], L[:, 1]), 1e-12)[:, None]
    probe = np.column_stack([mid + delta * down, np.ones(len(a))])
    line[segs] = L * np.where(np.einsum("nc,nc->n", L, probe) < 0, -1.0, 1.0)[:, None]
    return FloorContacts(contact, bottom, top, floor_line, line, vp)


def hanging_verticals(fc: FloorContacts, ep: np.ndarray, frame: np.ndarray, labels: np.ndarray, segs: np.ndarray,
                      near_px: float, min_len_px: float, span: float) -> np.ndarray:
    """Returns (N,) bool: horizontal segments from whose end a vertical segment hangs down (so above the floor).

    A deviation from the paper, for the precision of floor coplanarity: the
    top of a cabinet, a bed or a table looks like floor when the floor is
    out of view, but its front edges hang from its corners. A vertical
    segment (of ``segs``) at least ``min_len_px`` long whose upper end lies
    within ``near_px`` of a horizontal segment's end marks it.
    """
    out = np.zeros(len(ep), bool)
    vert = segs[labels[segs] == 2]
    hz = segs[(labels[segs] >= 0) & (labels[segs] != 2)]
    if len(vert) == 0 or len(hz) == 0:
        return out
    vert = vert[np.linalg.norm(fc.top[vert] - fc.bottom[vert], axis=1) >= min_len_px]
    pts = np.concatenate([fc.top[vert], ep[hz, :2], ep[hz, 2:]])
    owner = np.concatenate([vert, hz, hz])
    pairs = _frame_pairs(pts, frame[owner], owner, near_px, span)
    if len(pairs) == 0:
        return out
    a, b = pairs[:, 0], pairs[:, 1]
    v_first = labels[a] == 2
    v, h = np.where(v_first, a, b), np.where(v_first, b, a)
    # the only points of verticals are their upper ends; a pair of two verticals or two horizontals says nothing
    out[h[(labels[v] == 2) & (labels[h] != 2)]] = True
    return out


def floor_consistent(fc: FloorContacts, ep: np.ndarray, seg_i: np.ndarray, seg_j: np.ndarray, labels: np.ndarray,
                     frame: np.ndarray, axis: np.ndarray, tol_px: float, t_junction_px: float = 0.0) -> np.ndarray:
    """Returns (P,) bool: False where a coplanarity on a vertical plane contradicts where its segments meet the floor.

    A deviation from the paper, for precision: normals cannot tell a wall
    from the parallel front of a cabinet before it, but the floor can. A
    vertical plane ``x_k = c`` meets the floor in one line, so on it (beyond
    ``tol_px`` image pixels): two vertical segments that stand on the floor
    stand on one line through the vanishing point of the plane's horizontal
    direction; a vertical segment stands on the plane's floor line if it
    stands on the floor and never reaches below it; two floor lines of the
    plane are one image line, and no segment of it reaches below its floor
    line. ``ep`` (N, 4) are the segments' endpoints (image pixels); pairs on
    horizontal planes (``axis`` 2) are not tested.
    """
    la, lb = labels[seg_i], labels[seg_j]
    ok = np.ones(len(seg_i), bool)
    wall = axis != 2
    bh = np.column_stack([fc.bottom, np.ones(len(fc.bottom))])
    # two standing verticals: their bottoms and the plane's horizontal vanishing point are colinear
    vv = wall & (la == 2) & (lb == 2) & fc.contact[seg_i] & fc.contact[seg_j]
    if vv.any():
        lj = np.cross(bh[seg_j[vv]], fc.vp[frame[seg_i[vv]], 1 - axis[vv]])  # axis 0/1 -> the other horizontal
        lj /= np.maximum(np.hypot(lj[:, 0], lj[:, 1]), 1e-12)[:, None]
        ok[vv] = np.abs(np.einsum("pc,pc->p", bh[seg_i[vv]], lj)) <= tol_px
    # a vertical and a floor line: the vertical stands on it, or ends above it
    for v, hz in ((seg_i, seg_j), (seg_j, seg_i)):
        m = wall & (labels[v] == 2) & (labels[hz] != 2) & fc.floor_line[hz]
        if m.any():
            s = np.einsum("pc,pc->p", bh[v[m]], fc.line[hz[m]])
            ok[m] &= np.where(fc.contact[v[m]], np.abs(s) <= tol_px, s <= tol_px)
    # two horizontal segments of one direction, one (or both) a floor line
    hh = wall & (la == lb) & (la != 2)
    for p, q in ((seg_i, seg_j), (seg_j, seg_i)):
        m = hh & fc.floor_line[p]
        if m.any():
            L = fc.line[p[m]]
            e = ep[q[m]]
            s0 = L[:, 0] * e[:, 0] + L[:, 1] * e[:, 1] + L[:, 2]
            s1 = L[:, 0] * e[:, 2] + L[:, 1] * e[:, 3] + L[:, 2]
            worst = np.where(fc.floor_line[q[m]], np.maximum(np.abs(s0), np.abs(s1)), np.maximum(s0, s1))
            ok[m] &= worst <= tol_px
    if t_junction_px > 0:
        ok &= ~occluding_t(ep, seg_i, seg_j, labels, t_junction_px)
    return ok


def occluding_t(ep: np.ndarray, seg_i: np.ndarray, seg_j: np.ndarray, labels: np.ndarray, ext_px: float) -> np.ndarray:
    """Returns (P,) bool: a horizontal segment of the pair ends on the inside of the vertical one (a T).

    The vertical runs on past the horizontal's end by more than ``ext_px``
    on both sides, and the horizontal's end lies within ``ext_px / 2`` of
    the vertical's line, its other end beyond: the horizontal line goes on
    behind the vertical edge, which is in front of its surface (the wall's
    foot hidden by a nightstand's front edge), so the two are not coplanar.
    """
    out = np.zeros(len(seg_i), bool)
    for v, hz in ((seg_i, seg_j), (seg_j, seg_i)):
        m = (labels[v] == 2) & (labels[hz] >= 0) & (labels[hz] != 2)
        if not m.any():
            continue
        V, H = ep[v[m]], ep[hz[m]]
        dv = V[:, 2:] - V[:, :2]
        lv = np.linalg.norm(dv, axis=1)
        uv = dv / np.maximum(lv, 1e-9)[:, None]
        nv = np.column_stack([-uv[:, 1], uv[:, 0]])
        d0 = np.einsum("pc,pc->p", H[:, :2] - V[:, :2], nv)
        d1 = np.einsum("pc,pc->p", H[:, 2:] - V[:, :2], nv)
        near0 = np.abs(d0) <= np.abs(d1)
        dn, df = np.where(near0, d0, d1), np.where(near0, d1, d0)
        # where the horizontal's line meets the vertical's, as a position along the vertical
        dh = H[:, 2:] - H[:, :2]
        den = np.einsum("pc,pc->p", dh, nv)
        with np.errstate(divide="ignore", invalid="ignore"):
            tx = -np.einsum("pc,pc->p", H[:, :2] - V[:, :2], nv) / den
        X = H[:, :2] + tx[:, None] * dh
        along = np.einsum("pc,pc->p", X - V[:, :2], uv)
        t = (np.abs(dn) <= 0.5 * ext_px) & (np.abs(df) > ext_px) & (np.sign(dn) * np.sign(df) >= 0) & (
            along > ext_px) & (along < lv - ext_px) & np.isfinite(along)
        out[np.flatnonzero(m)] |= t
    return out


def contradicted_pairs(fc: FloorContacts, ep: np.ndarray, seg_i: np.ndarray, seg_j: np.ndarray, labels: np.ndarray,
                       frame: np.ndarray, track_of: np.ndarray, tol_px: float, t_junction_px: float,
                       min_frames: int = 1) -> np.ndarray:
    """Returns (C, 3) unique (track_a < track_b, axis) that :func:`floor_consistent` puts on no common plane.

    Tested for each segment pair on every vertical plane it could share:
    both axes 0 and 1 for two verticals, the plane holding the horizontal's
    direction otherwise; two horizontals of different directions (a
    horizontal plane) are not tested. A track pair must be contradicted in
    at least ``min_frames`` frames (one frame's misjudged floor is not enough).
    """
    li, lj = labels[seg_i], labels[seg_j]
    out = []
    for k in (0, 1):
        # plane normal k holds the vertical and the horizontal direction 1 - k
        m = ((li == 2) & (lj == 2)) | ((li == 2) & (lj == 1 - k)) | ((lj == 2) & (li == 1 - k)) | (
            (li == lj) & (li == 1 - k))
        i, j = seg_i[m], seg_j[m]
        bad = ~floor_consistent(fc, ep, i, j, labels, frame, np.full(len(i), k), tol_px, t_junction_px)
        a, b = track_of[i[bad]], track_of[j[bad]]
        # one row per frame and track pair (a track holds one segment per frame, but a pair may repeat)
        out.append(np.column_stack([np.minimum(a, b), np.maximum(a, b), np.full(len(a), k), frame[i[bad]]]))
    c = np.unique(np.concatenate(out).astype(np.int64), axis=0)
    if len(c) == 0:
        return np.zeros((0, 3), np.int64)
    pairs, count = np.unique(c[:, :3], axis=0, return_counts=True)
    return pairs[count >= min_frames]


def consistent_planes(track_a: np.ndarray, track_b: np.ndarray, axis: np.ndarray, support: np.ndarray,
                      cannot_a: np.ndarray, cannot_b: np.ndarray, cannot_axis: np.ndarray,
                      use: np.ndarray | None = None, rank: np.ndarray | None = None) -> np.ndarray:
    """Returns (R,) bool: the pair relations kept when they are merged into planes without joining a cannot-link.

    For each normal axis, relations are taken by ``rank`` (lowest first:
    the most precise kind), then by decreasing ``support``, each joining its two tracks' planes (union-find) unless some cannot-link pair
    (``cannot_*``: tracks seen on no common plane of that axis) would end up
    on one plane: then it is dropped. A nightstand's edge contradicted by the
    wall's foot is then not put on the wall through the wall's corner line
    either. FLOOR relations (``track_b`` -1) and those not in ``use`` are
    passed through / ignored.
    """
    R = len(track_a)
    keep = np.ones(R, bool)
    use = np.ones(R, bool) if use is None else use
    rank = np.zeros(R, np.int64) if rank is None else rank
    if len(cannot_a) == 0:
        return keep
    T = int(max(track_a.max(initial=0), track_b.max(initial=0), cannot_a.max(initial=0), cannot_b.max(initial=0))) + 1
    for k in np.unique(axis):
        ck = cannot_axis == k
        ca, cb = cannot_a[ck], cannot_b[ck]
        if len(ca) == 0:
            continue
        root = np.arange(T)
        rows = np.flatnonzero(use & (axis == k) & (track_b >= 0))
        for r in rows[np.lexsort((-support[rows], rank[rows]))]:
            ra, rb = root[track_a[r]], root[track_b[r]]
            if ra == rb:
                continue
            xa, xb = root[ca], root[cb]
            if np.any(((xa == ra) & (xb == rb)) | ((xa == rb) & (xb == ra))):
                keep[r] = False
                continue
            root[root == rb] = ra
    return keep


def _junction_pairs(pre, normals, i, j, labels, ep, min_side, cfg, dirs, size):
    """Returns the junction candidates (i, j) that meet as an L (paper §3.2 plus two checks of ours).

    The paper's test (endpoints within ``junction_dist_frac``) also accepts
    T-junctions of an occluding edge and lines merely near in the image.
    With ``junction_corner_frac`` both segments must end within that share of
    ``min(w, h)`` of the intersection of their supporting lines (an L, not a
    T); with ``junction_normals`` the quad between them -- the inside of the
    L, which a face bounded by both lines fills -- must pass the orthogonal
    normal test. With ``junction_border_px`` (and the corner test) the ends
    at the corner must lie more than that inside the image ``size`` (w, h):
    where the frame cuts two lines their ends meet, but no corner is seen
    (a nightstand's edge and the wall's foot behind it, both cut by the
    image's bottom row).
    """
    if cfg.junction_corner_frac > 0 and len(i):
        def homog(e):
            return np.cross(np.column_stack([e[:, :2], np.ones(len(e))]), np.column_stack([e[:, 2:], np.ones(len(e))]))

        def corner_end(e):  # (P, 2) each segment's end nearer the corner X
            near0 = np.linalg.norm(e[:, :2] - X, axis=1) <= np.linalg.norm(e[:, 2:] - X, axis=1)
            return np.where(near0[:, None], e[:, :2], e[:, 2:])

        X = np.cross(homog(ep[i]), homog(ep[j]))
        finite = np.abs(X[:, 2]) > 1e-9 * np.maximum(np.abs(X[:, :2]).max(axis=1), 1.0)
        X = X[:, :2] / np.where(finite, X[:, 2], 1.0)[:, None]
        lim = cfg.junction_corner_frac * min_side
        ends = (corner_end(ep[i]), corner_end(ep[j]))
        keep = finite & (np.linalg.norm(ends[0] - X, axis=1) < lim) & (np.linalg.norm(ends[1] - X, axis=1) < lim)
        if cfg.junction_border_px > 0:
            b = cfg.junction_border_px
            for e in ends:
                keep &= (e[:, 0] > b) & (e[:, 0] < size[0] - 1 - b) & (e[:, 1] > b) & (e[:, 1] < size[1] - 1 - b)
        i, j = i[keep], j[keep]
    if cfg.junction_normals and len(i):
        qcfg = dataclasses.replace(cfg, orthogonal=True)
        _, i, j, _ = _quad_relations(pre, normals, i, j, labels, qcfg, dirs)
    return i, j


def face_sides(pre: Preprocessed, camera: Camera, seg_i: np.ndarray, seg_j: np.ndarray, axis: np.ndarray,
               labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns (s_i, s_j) (P,) in {-1, 0, +1}: which way the face on plane ``axis`` runs from each segment to the other.

    Our addition to paper §3.2. Segment i (Manhattan label ``a``) on the plane
    ``x_axis = k`` bounds a face that extends from it along the plane's other
    direction ``3 - a - axis``; its sign, in the Manhattan frame (so the same
    in every frame), is the sign of that coordinate of the way from i's
    mid-point to j's on the plane, found from the viewing rays alone (the
    unknown ``k`` has the sign of the rays' ``axis`` coordinate). 0 where a
    ray runs nearly inside the plane (the plane seen edge-on).
    """
    if len(seg_i) == 0:
        z = np.zeros(0, np.int64)
        return z, z.copy()
    R = pre.R_wc.astype(np.float64)
    dirs = pre.manhattan.directions
    mid = pre.segments.midpoints
    frame = pre.segments.frame

    def rays(s):  # (P, 3) unit viewing rays of the mid-points in Manhattan coordinates
        r = world_rays(camera.K, R[frame[s]], mid[s]) @ dirs.T
        return r / np.linalg.norm(r, axis=1, keepdims=True)

    n = np.arange(len(seg_i))
    rx, ry = rays(seg_i), rays(seg_j)
    c = np.asarray(axis, np.int64)
    xc, yc = rx[n, c], ry[n, c]
    edge_on = (np.abs(xc) < 0.05) | (np.abs(yc) < 0.05) | (np.sign(xc) != np.sign(yc))
    xc, yc = np.where(edge_on, 1.0, xc), np.where(edge_on, 1.0, yc)
    out = []
    for u, v, uc, vc, lab in ((rx, ry, xc, yc, labels[seg_i]), (ry, rx, yc, xc, labels[seg_j])):
        along = 3 - lab - c
        out.append(np.where(edge_on, 0, np.sign(uc) * np.sign(v[n, along] / vc - u[n, along] / uc)).astype(np.int64))
    return out[0], out[1]


def junction_sided(track_of: np.ndarray, n_tracks: int, seg_i: np.ndarray, seg_j: np.ndarray, axis: np.ndarray,
                   s_i: np.ndarray, s_j: np.ndarray) -> np.ndarray:
    """Returns (T, 3, 2) bool: ``[t, k, 0/1]`` whether a junction puts a face of plane normal ``k`` on the -/+ side of track t.

    The inside of an L-junction (paper §3.2's junction coplanarity, with our
    corner and normal checks) is a face the two lines bound: each line's face
    on that plane lies towards the other line (:func:`face_sides`).
    """
    known = np.zeros((n_tracks, 3, 2), bool)
    for s, side in ((seg_i, s_i), (seg_j, s_j)):
        m = side != 0
        known[track_of[s[m]], axis[m], (side[m] > 0).astype(np.int64)] = True
    return known


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
    mask = floor_masks(pre, normals, camera, config) if (config.floor or config.floor_contact_frac > 0) else None
    contacts, contact_tol, cannot = None, config.floor_contact_frac * min_side, []
    if config.floor_contact_frac > 0:
        contacts = floor_contacts(pre, normals, camera, mask, labels, tracked)

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
        quad = _quad_relations(pre, normals, pairs[:, 0], pairs[:, 1], labels, config, dirs)
        if contacts is not None:
            cannot.append(contradicted_pairs(contacts, ep, pairs[:, 0], pairs[:, 1], labels, frame, track_of,
                                             contact_tol, config.t_junction_frac * min_side,
                                             config.floor_contact_min_frames))
        log.debug("quad tests: %d candidate pairs, %d accepted", len(pairs), len(quad[1]))

    if config.junction:
        pts = np.concatenate([ep[tracked, :2], ep[tracked, 2:]])
        owner = np.tile(tracked, 2)
        pairs = _frame_pairs(pts, np.tile(frame[tracked], 2), owner, config.junction_dist_frac * min_side, span)
        i, j = pairs[:, 0], pairs[:, 1]
        diff = labels[i] != labels[j]
        i, j = _junction_pairs(pre, normals, i[diff], j[diff], labels, ep, min_side, config, dirs,
                               (camera.width, camera.height))
        add(JUNCTION, i, j, 3 - labels[i] - labels[j])
        junctions = (i, j, 3 - labels[i] - labels[j])

    if config.orthogonal or config.parallel:
        kind, i, j, axis = quad
        if config.junction_sides and config.junction and len(i) and len(junctions[0]):
            # a face runs from a line only to the sides its L-junctions show: a bookshelf's front edge bounds the
            # front towards its top edge, and the wall beyond it (same normal, further back) is another plane
            ji, jj, jk = junctions
            a, b = np.minimum(track_of[ji], track_of[jj]), np.maximum(track_of[ji], track_of[jj])
            _, inv, cnt = np.unique(np.column_stack([a, b, jk]), axis=0, return_inverse=True, return_counts=True)
            strong = cnt[inv.ravel()] >= config.junction_min_support
            ji, jj, jk = ji[strong], jj[strong], jk[strong]
            known = junction_sided(track_of, tracks.n, ji, jj, jk, *face_sides(pre, camera, ji, jj, jk, labels))
            contradicted = np.zeros(len(i), bool)
            for s, side in zip((i, j), face_sides(pre, camera, i, j, axis, labels)):
                t = track_of[s]
                here = known[t, axis, (side > 0).astype(np.int64)]
                there = known[t, axis, (side < 0).astype(np.int64)]
                contradicted |= (side != 0) & there & ~here
            log.debug("junction sides: %d of %d quad pairs contradicted", int(contradicted.sum()), len(i))
            kind, i, j, axis = kind[~contradicted], i[~contradicted], j[~contradicted], axis[~contradicted]
        add(kind, i, j, axis)

    if config.floor:
        hz = tracked[labels[tracked] != 2]
        if len(hz):
            t = np.linspace(0.0, 1.0, FLOOR_SAMPLES)[None, :, None]
            e = ep[hz] * normals.scale
            X = e[:, None, :2] * (1.0 - t) + e[:, None, 2:] * t  # (N, K, 2)
            i = hz[on_mask(mask, frame[hz], X).all(axis=1)]
            if contacts is not None and config.floor_hanging_frac > 0:  # tracks with a vertical hanging from them
                hang = hanging_verticals(contacts, ep, frame, labels, tracked, config.junction_corner_frac * min_side,
                                         config.floor_hanging_frac * min_side, span)
                i = i[~np.isin(track_of[i], track_of[hang])]
            add(FLOOR, i, None, 2)

    if not kinds:
        return empty_relations()
    rows = np.column_stack([np.concatenate(x).astype(np.int64) for x in (kinds, ta, tb, axes)])
    if len(rows) == 0:
        return empty_relations()
    uniq, support = np.unique(rows, axis=0, return_counts=True)
    weak = (uniq[:, 0] == JUNCTION) & (support < config.junction_min_support)
    if cannot:
        c = np.unique(np.concatenate(cannot), axis=0)
        if config.floor_contact_propagate:
            rank = np.select([uniq[:, 0] == JUNCTION, uniq[:, 0] == ORTHOGONAL], [0, 1], 2)  # most precise first
            apart = ~consistent_planes(uniq[:, 1], uniq[:, 2], uniq[:, 3], support, c[:, 0], c[:, 1], c[:, 2], ~weak,
                                       rank)
        else:  # only the contradicted pairs themselves
            def key(a, b, k):  # one integer per (track_a, track_b >= -1, axis)
                return ((a + 1) * (tracks.n + 1) + (b + 1)) * 3 + k

            apart = np.isin(key(uniq[:, 1], uniq[:, 2], uniq[:, 3]), key(c[:, 0], c[:, 1], c[:, 2])) & (uniq[:, 2] >= 0)
        log.debug("floor contacts: %d cannot-links, %d coplanarities dropped", len(c), int((apart & ~weak).sum()))
        weak |= apart
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
