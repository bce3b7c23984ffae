"""Option: where segments meet the floor vetoes coplanarities (beyond paper §3.2).

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
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ..data import JUNCTION, ORTHOGONAL, Camera, NormalMaps, Preprocessed
from ..geometry import pixel_rays
from .floor import FLOOR_SAMPLES, on_mask
from .pairs import segment_pairs

log = logging.getLogger("panosfm.relations")


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
    pairs = segment_pairs(pts, frame[owner], owner, near_px, span)
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


def cannot_linked(uniq: np.ndarray, support: np.ndarray, weak: np.ndarray, cannot: list[np.ndarray], n_tracks: int,
                  propagate: bool) -> np.ndarray:
    """Returns (R,) bool: the relations (rows ``uniq`` of kind, track_a, track_b, axis) the cannot-links drop.

    With ``propagate`` the coplanarities are merged into planes, most precise
    kind first (:func:`consistent_planes`, ``weak`` ones left out); otherwise
    only the contradicted pairs themselves are dropped.
    """
    c = np.unique(np.concatenate(cannot), axis=0)
    if propagate:
        rank = np.select([uniq[:, 0] == JUNCTION, uniq[:, 0] == ORTHOGONAL], [0, 1], 2)  # most precise first
        apart = ~consistent_planes(uniq[:, 1], uniq[:, 2], uniq[:, 3], support, c[:, 0], c[:, 1], c[:, 2], ~weak,
                                   rank)
    else:  # only the contradicted pairs themselves
        def key(a, b, k):  # one integer per (track_a, track_b >= -1, axis)
            return ((a + 1) * (n_tracks + 1) + (b + 1)) * 3 + k

        apart = np.isin(key(uniq[:, 1], uniq[:, 2], uniq[:, 3]), key(c[:, 0], c[:, 1], c[:, 2])) & (uniq[:, 2] >= 0)
    log.debug("floor contacts: %d cannot-links, %d coplanarities dropped", len(c), int((apart & ~weak).sum()))
    return apart
