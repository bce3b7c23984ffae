"""Manhattan line tracking across frames (paper §3.1 'Line tracking', supplement §3)."""
from __future__ import annotations

import logging

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..config import Config, TrackingConfig
from ..data import Segments, Tracks
from ..geometry import turned_degrees, world_rays

log = logging.getLogger("panosfm.lines")


def _tracking_config(config: Config | TrackingConfig) -> TrackingConfig:
    return config.tracking if isinstance(config, Config) else config


def frame_pairs(R_wc: np.ndarray, axis_angle_deg: float) -> np.ndarray:
    """Returns (P, 2) frame pairs i < j whose optical axes are within ``axis_angle_deg`` (supplement §3)."""
    if len(R_wc) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    chord = 2.0 * np.sin(np.radians(axis_angle_deg) / 2.0)
    pairs = cKDTree(R_wc[:, :, 2]).query_pairs(chord, output_type="ndarray").reshape(-1, 2)
    return np.sort(pairs, axis=1).astype(np.int64)


def _bridge_pairs(R_wc: np.ndarray, bridge_angle_deg: float, base: np.ndarray) -> np.ndarray:
    """Returns (P, 2) frame pairs i < j within ``bridge_angle_deg`` not in ``base``, by frame gap j - i then i."""
    if bridge_angle_deg <= 0 or len(R_wc) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    extra = _pairs_beyond(R_wc, bridge_angle_deg, base)
    return extra[np.lexsort((extra[:, 0], extra[:, 1] - extra[:, 0]))]


def _pairs_beyond(R_wc: np.ndarray, angle_deg: float, base: np.ndarray) -> np.ndarray:
    """Returns (P, 2) the frame pairs i < j within ``angle_deg`` (:func:`frame_pairs`) that ``base`` does not hold."""
    wide = frame_pairs(R_wc, angle_deg)
    F = len(R_wc)
    return wide[~np.isin(wide[:, 0] * F + wide[:, 1], base[:, 0] * F + base[:, 1])]


def loop_pairs(R_wc: np.ndarray, loop_angle_deg: float, base: np.ndarray | None = None,
               min_turn_deg: float = 180.0) -> np.ndarray:
    """Returns (P, 2) frame pairs i < j within ``loop_angle_deg`` whose camera turned ``min_turn_deg`` or more between them.

    Loop closure, our addition: a spin's last frames look where its first ones did (a turn apart),
    but a few degrees off in pitch or past the start, so the neighbouring-frame pairs
    (:func:`frame_pairs`, 2 degrees) never relate them and the lines both ends see become two tracks.
    Pairs in ``base`` (those neighbouring-frame pairs, matched already) are left out.
    """
    if loop_angle_deg <= 0 or len(R_wc) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    wide = _pairs_beyond(R_wc, loop_angle_deg, np.zeros((0, 2), np.int64) if base is None else base)
    turned = turned_degrees(R_wc)
    return wide[np.abs(turned[wide[:, 1]] - turned[wide[:, 0]]) >= min_turn_deg]


def rotation_homography(K: np.ndarray, R_wc_i: np.ndarray, R_wc_j: np.ndarray) -> np.ndarray:
    """Returns the 3x3 homography H = K R_j^T R_i K^-1 mapping pixels of frame i to frame j (pure rotation)."""
    return K @ R_wc_j.T @ R_wc_i @ np.linalg.inv(K)


def _warp(H: np.ndarray, endpoints: np.ndarray) -> np.ndarray:
    p = np.concatenate([endpoints.reshape(-1, 2), np.ones((2 * len(endpoints), 1))], axis=1) @ H.T
    return (p[:, :2] / p[:, 2:]).reshape(-1, 4)


def _lines(endpoints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns (unit directions (N, 2), homogeneous normalised lines (N, 3)) of segments."""
    d = endpoints[:, 2:] - endpoints[:, :2]
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    n = np.stack([-d[:, 1], d[:, 0]], axis=1)
    return d, np.concatenate([n, -np.sum(n * endpoints[:, :2], axis=1, keepdims=True)], axis=1)


def overlap_along(ea: np.ndarray, eb: np.ndarray, db: np.ndarray) -> np.ndarray:
    """Returns (A, B) how far segments a and b overlap along b's unit direction ``db`` (px; negative: the gap)."""
    pa0, pa1 = ea[:, :2] @ db.T, ea[:, 2:] @ db.T  # a's endpoints along each b's direction
    pb0, pb1 = np.sum(eb[:, :2] * db, axis=1), np.sum(eb[:, 2:] * db, axis=1)
    return (np.minimum(np.maximum(pa0, pa1), np.maximum(pb0, pb1)[None])
            - np.maximum(np.minimum(pa0, pa1), np.minimum(pb0, pb1)[None]))


def manhattan_lines(segments: Segments, labels: np.ndarray, K: np.ndarray, R_wc: np.ndarray,
                    directions: np.ndarray) -> np.ndarray:
    """Returns (S, 3) each Manhattan segment's image line through its mid-point and its vanishing point.

    The line is normalised (``l . (x, y, 1)`` is a signed distance in pixels); NaN for unlabelled
    segments. Its direction comes from the Manhattan direction (``directions[label]``, world) and
    the frame's rotation, not from the segment's own endpoints, whose angle is only known to ~1
    degree for a 60 px segment: two pieces of one line 200 px long then disagree by 3 px.
    """
    S = segments.n
    out = np.full((S, 3), np.nan)
    lab = np.asarray(labels)
    m = np.flatnonzero(lab >= 0)
    if len(m) == 0:
        return out
    f = segments.frame[m]
    vp = np.einsum("ij,fkj,fk->fi", K, R_wc[f], directions[lab[m]])  # K R^T d (R = world_from_camera)
    mid = np.concatenate([segments.midpoints[m].astype(np.float64), np.ones((len(m), 1))], axis=1)
    line = np.cross(mid, vp)
    out[m] = line / np.maximum(np.hypot(line[:, 0], line[:, 1]), 1e-12)[:, None]
    return out


def colinear_groups(
    segments: Segments, labels: np.ndarray, dist_px: float, lines: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns (representative segment id (S,), merged endpoints (S, 4)) of colinear pieces per frame (supplement §3).

    A deviation that keeps tracks long: LSD often cuts one image line into
    pieces (occlusion, texture), and a track holds one segment per frame, so
    the pieces used to split the track. Within each frame, Manhattan segments
    of one label are grouped (connected components) when both endpoints of the
    shorter are within ``dist_px`` of the longer one's line and the two lie
    side by side along it (overlapping by at most ``dist_px``: two overlapping
    parallel segments are two lines, like a trim's edges). Each group is
    represented by its longest piece; ``merged[rep]`` spans the extreme
    projections of all the group's endpoints on the representative's line
    (used for matching only). Non-Manhattan segments and pieces that are their
    own group map to themselves. ``dist_px`` <= 0 disables grouping. With
    ``lines`` (:func:`manhattan_lines`) the test is instead that each piece's
    mid-point lies within ``dist_px`` of the other's Manhattan line (the
    direction is the vanishing point's, so short pieces' angle noise does not
    separate them).
    """
    S = segments.n
    rep = np.arange(S)
    ends = segments.endpoints.astype(np.float64)
    merged = ends.copy()
    if S == 0 or dist_px <= 0:
        return rep, merged
    length = np.linalg.norm(ends[:, 2:] - ends[:, :2], axis=1)
    d, L = _lines(ends)
    src, dst = [], []
    for f in range(len(segments.frame_offsets) - 1):
        m = np.flatnonzero(labels[segments.of_frame(f)] >= 0) + segments.frame_offsets[f]
        if len(m) < 2:
            continue
        e = ends[m]
        h0 = np.concatenate([e[:, :2], np.ones((len(m), 1))], axis=1)
        h1 = np.concatenate([e[:, 2:], np.ones((len(m), 1))], axis=1)
        longer = length[m][:, None] >= length[m][None, :]
        if lines is None:
            far = np.maximum(np.abs(L[m] @ h0.T), np.abs(L[m] @ h1.T))  # [i, j]: j's farther endpoint to i's line
        else:  # each mid-point to the other's vanishing-point line
            hm = 0.5 * (h0 + h1)
            dm = np.abs(lines[m] @ hm.T)  # [i, j]: j's mid-point to i's line
            far = np.maximum(dm, dm.T)
        ok = longer & (far < dist_px) & (labels[m][:, None] == labels[m][None, :])
        # pieces lie side by side along the line; two that overlap are two lines (the edges of a trim)
        ok &= overlap_along(e, e, d[m]).T <= dist_px  # [i, j] along i's direction
        np.fill_diagonal(ok, False)
        i, j = np.nonzero(ok)
        src.append(m[i])
        dst.append(m[j])
    if not src or sum(len(x) for x in src) == 0:
        return rep, merged
    a, b = np.concatenate(src), np.concatenate(dst)
    _, comp = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(S, S)), directed=False)
    # representative: the longest piece of each component
    order = np.lexsort((-length, comp))
    first = np.r_[True, comp[order][1:] != comp[order][:-1]]
    rep_of_comp = np.empty(comp.max() + 1, dtype=np.int64)
    rep_of_comp[comp[order][first]] = order[first]
    rep = rep_of_comp[comp]
    # merged extent along the representative's line
    p0, dr = ends[rep, :2], d[rep]
    t0 = np.sum((ends[:, :2] - p0) * dr, axis=1)
    t1 = np.sum((ends[:, 2:] - p0) * dr, axis=1)
    lo = np.full(S, np.inf)
    hi = np.full(S, -np.inf)
    np.minimum.at(lo, rep, np.minimum(t0, t1))
    np.maximum.at(hi, rep, np.maximum(t0, t1))
    grouped = np.flatnonzero(np.bincount(rep, minlength=S) > 1)
    merged[grouped] = np.concatenate(
        [ends[grouped, :2] + lo[grouped, None] * d[grouped], ends[grouped, :2] + hi[grouped, None] * d[grouped]], axis=1)
    return rep, merged


def match_pair(
    ea: np.ndarray, la: np.ndarray, eb: np.ndarray, lb: np.ndarray, H: np.ndarray, dist_px: float, angle_deg: float,
    angle_px: float = 0.0, gap_px: float | None = None,
    contrast_a: np.ndarray | None = None, contrast_b: np.ndarray | None = None, polarity_min: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (index in a, index in b, distance px) of mutual-best segment matches between two frames.

    Supplement §3: segments of frame a are warped by ``H``; a pair matches
    when labels agree, directions differ by less than ``angle_deg`` and the
    smallest of the four endpoint-to-other-line distances is below
    ``dist_px``; then each keeps only its mutual best, ranked by a stricter
    distance (the farther endpoint of the better-fitting segment from the
    other's line) so that a nearby parallel line loses to the true one.
    With ``angle_px`` > 0 the angle tolerance of a pair grows for short
    segments to max(``angle_deg``, atan(``angle_px`` / shorter length)): the
    direction of a 40 px segment is only known to ~1.4 degrees at 1 px of
    endpoint noise (a deviation; long segments keep the paper's 1 degree).
    With ``gap_px`` not None (a deviation) the two must also overlap along
    the line, up to a gap of ``gap_px``: two 3D lines that happen to be
    colinear in the image (a table edge continuing a skirting line) are
    usually side by side along it, not on top of each other.
    With ``contrast_a``/``contrast_b`` (:func:`~panosfm_graph.lines.detect.segment_contrast`) and
    ``polarity_min`` > 0 (a deviation), two segments whose polarities both exceed ``polarity_min``
    grey levels and disagree (after aligning their directions) never match: a trim's two sides,
    2-4 px apart, are as close as the parallax between neighbouring frames.
    """
    wa = _warp(H, ea.astype(np.float64))
    da, La = _lines(wa)
    db, Lb = _lines(eb.astype(np.float64))
    dot = da @ db.T  # (A, B) cosines of the directions, signed
    cos = np.abs(dot)
    hom = lambda e, k: np.concatenate([e[:, 2 * k : 2 * k + 2], np.ones((len(e), 1))], axis=1)
    eb64 = eb.astype(np.float64)
    d_a0, d_a1 = np.abs(hom(wa, 0) @ Lb.T), np.abs(hom(wa, 1) @ Lb.T)  # a's endpoints to b's line
    d_b0, d_b1 = np.abs(La @ hom(eb64, 0).T), np.abs(La @ hom(eb64, 1).T)  # b's endpoints to a's line
    gate = np.minimum.reduce([d_a0, d_a1, d_b0, d_b1])  # the paper's distance
    # ranking score: the worse endpoint of the better-fitting segment (whole segment near the other's line)
    score = np.minimum(np.maximum(d_a0, d_a1), np.maximum(d_b0, d_b1))
    tol = np.full(cos.shape, np.radians(angle_deg))
    if angle_px > 0:
        short = np.minimum(np.linalg.norm(wa[:, 2:] - wa[:, :2], axis=1)[:, None],
                           np.linalg.norm(eb64[:, 2:] - eb64[:, :2], axis=1)[None, :])
        tol = np.maximum(tol, np.arctan(angle_px / np.maximum(short, 1e-9)))
    ok = (la[:, None] == lb[None, :]) & (cos > np.cos(tol)) & (gate < dist_px)
    if gap_px is not None:  # the two must overlap along the line (up to gap_px): image-colinear lines at other depths do not
        ok &= -overlap_along(wa, eb64, db) < gap_px
    if polarity_min > 0 and contrast_a is not None and contrast_b is not None:
        ca = np.sign(dot) * contrast_a[:, None]  # a's polarity in b's direction
        cb = contrast_b[None, :]
        ok &= ~((ca * cb < 0) & (np.abs(ca) > polarity_min) & (np.abs(cb) > polarity_min))
    cost = np.where(ok, score, np.inf)
    if cost.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    best_b = np.argmin(cost, axis=1)
    best_a = np.argmin(cost, axis=0)
    a = np.arange(len(ea))
    mutual = np.isfinite(cost[a, best_b]) & (best_a[best_b] == a)
    a = a[mutual]
    b = best_b[mutual]
    return a, b, cost[a, b]


def residual_shift(warped: np.ndarray, eb: np.ndarray, huber_px: float = 1.0, iterations: int = 3) -> np.ndarray:
    """Returns the image translation t (2,) that best moves the warped segments onto their matches' lines.

    Least squares on the signed distances of the warped midpoints to the
    matched lines, n_b . (m_a + t) + c_b = 0, Huber-weighted (``huber_px``);
    a direction no match constrains (only vertical lines: no y) stays 0 by a
    ridge worth 0.1 of a match. Under a pure-rotation homography the residual is the
    rotation error plus the parallax of the camera's few-centimetre
    translation: 2-5 px between neighbouring frames at 1.5 m, as much as the
    gap between a door trim's two edges.
    """
    _, Lb = _lines(eb)
    return _line_shift(0.5 * (warped[:, :2] + warped[:, 2:]), Lb, huber_px, iterations)


def _line_shift(points: np.ndarray, lines: np.ndarray, huber_px: float = 1.0, iterations: int = 3) -> np.ndarray:
    """Returns the translation t (2,) minimising the Huber-weighted distances of ``points + t`` to ``lines`` (normalised)."""
    n = lines[:, :2]
    r = np.sum(n * points, axis=1) + lines[:, 2]
    t = np.zeros(2)
    for _ in range(iterations):
        e = r + n @ t
        w = np.minimum(1.0, huber_px / np.maximum(np.abs(e), 1e-12))
        A = (n * w[:, None]).T @ n + 0.1 * np.eye(2)
        t = np.linalg.solve(A, -(n * w[:, None]).T @ r)
    return t


def line_jumps(warped: np.ndarray, lines_b: np.ndarray) -> np.ndarray:
    """Returns (N,) how far (px) each warped segment's mid-point lies from its match's vanishing-point line.

    Our addition to supplement §3, measured after the image shift that best aligns all the pair's
    matches (:func:`_line_shift`, Huber): the rotation error and the common parallax are gone, and
    what is left is a line's own parallax (below 2 px for 99 % of true matches between neighbouring
    frames of a steady spin) or a jump to another line. ``lines_b`` are the matched segments'
    :func:`manhattan_lines`: their direction is the vanishing point's, not a short piece's own angle.
    """
    mid = 0.5 * (warped[:, :2] + warped[:, 2:])
    t = _line_shift(mid, lines_b)
    return np.abs(np.sum(lines_b[:, :2] * (mid + t), axis=1) + lines_b[:, 2])


def _split_conflicts(edges: np.ndarray, weights: np.ndarray, frame: np.ndarray, n: int) -> np.ndarray:
    """Returns (n,) component ids where no component holds two segments of one frame.

    Components with a conflict are rebuilt greedily: edges in ascending
    distance are accepted only when they join components with disjoint
    frame sets (Kruskal with a constraint; small-to-large set merging).
    """
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    n_comp, comp = connected_components(graph, directed=False)
    # conflicts: a (component, frame) key that appears more than once
    key = comp.astype(np.int64) * (int(frame.max()) + 1 if n else 1) + frame
    uniq, counts = np.unique(key, return_counts=True)
    bad_comp = np.unique(uniq[counts > 1] // (int(frame.max()) + 1 if n else 1))
    if len(bad_comp) == 0:
        return comp
    in_bad = np.isin(comp, bad_comp)
    parent = np.arange(n)
    frames_of: dict[int, set] = {int(s): {int(frame[s])} for s in np.flatnonzero(in_bad)}

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    sel = in_bad[edges[:, 0]]
    order = np.argsort(weights[sel], kind="stable")
    for s, t in edges[sel][order]:
        rs, rt = find(int(s)), find(int(t))
        if rs == rt:
            continue
        fs, ft = frames_of[rs], frames_of[rt]
        if fs.isdisjoint(ft):
            if len(fs) < len(ft):
                rs, rt, fs, ft = rt, rs, ft, fs
            parent[rt] = rs
            fs |= ft
            del frames_of[rt]
    roots = np.array([find(int(s)) for s in range(n)])
    # renumber: components without conflict keep theirs, split ones get new ids
    out = np.where(in_bad, n_comp + roots, comp)
    return np.unique(out, return_inverse=True)[1]


def interpretation_angle(segments: Segments, seg_ids: np.ndarray, axis: np.ndarray, K: np.ndarray,
                         R_wc: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Returns (N,) the angle (rad, modulo pi) of the plane through the camera and each segment's 3D line.

    The plane holds the Manhattan direction ``directions[axis]`` (world) and
    the ray of the segment's mid-point, so its normal lies in the plane
    orthogonal to that direction; the angle is the normal's direction there
    (basis: the other two Manhattan directions). For a camera that only
    rotates it is the same in every frame; the camera's translation makes it
    drift slowly (2-5 px per frame at 1.5 m). The vanishing point fixes the
    image line's direction, so the mid-point alone gives the angle (the
    segment's own angle is ~1 degree off on a short piece).
    """
    ep = segments.endpoints[seg_ids].astype(np.float64)
    ray = world_rays(K, R_wc[segments.frame[seg_ids]], 0.5 * (ep[:, :2] + ep[:, 2:]))
    other = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    n = np.cross(directions[axis], ray)
    return np.arctan2(np.sum(n * directions[other[:, 1]], axis=1), np.sum(n * directions[other[:, 0]], axis=1))


def interpretation_offset(segments: Segments, seg_ids: np.ndarray, axis: np.ndarray, angle: np.ndarray,
                          K: np.ndarray, R_wc: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Returns (N,) the distance (px) of each segment's mid-point from the image of the plane at ``angle``.

    The inverse of :func:`interpretation_angle`: the plane through the camera holding
    ``directions[axis]`` at ``angle`` (rad) is imaged as a line in the segment's frame. Near a
    vanishing point a small angle is a large image distance, and the other way round, so a
    tolerance on angles alone is uneven across the image.
    """
    other = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    n_w = np.cos(angle)[:, None] * directions[other[:, 0]] + np.sin(angle)[:, None] * directions[other[:, 1]]
    f = segments.frame[seg_ids]
    line = np.einsum("ij,nkj,nk->ni", np.linalg.inv(K).T, R_wc[f], n_w)  # K^-T R^T n: the plane's image line
    ep = segments.endpoints[seg_ids].astype(np.float64)
    mid = np.column_stack([0.5 * (ep[:, :2] + ep[:, 2:]), np.ones(len(ep))])
    return np.abs(np.sum(line * mid, axis=1)) / np.maximum(np.hypot(line[:, 0], line[:, 1]), 1e-12)


def _wrap_pi(a: np.ndarray) -> np.ndarray:
    """Returns angles modulo pi in [-pi/2, pi/2)."""
    return (a + np.pi / 2) % np.pi - np.pi / 2


def merge_fragments(tracks: Tracks, segments: Segments, K: np.ndarray, R_wc: np.ndarray, directions: np.ndarray,
                    gap_frames: int, tol_px: float, overlap: bool = False, image_px: float = 0.0) -> Tracks:
    """Returns tracks with fragments of one 3D line joined (our addition to supplement §3).

    A line whose detections break into pieces (low contrast, texture) is
    tracked as a chain of short tracks: the frame-to-frame matching loses it
    for a frame or two and starts a new track. Each track's
    :func:`interpretation_angle` is fitted as a linear function of the frame
    (the drift is the parallax of the camera's translation); a track that
    ends ``1..gap_frames`` frames before another of the same Manhattan axis
    starts is joined to it when the two fits, evaluated half-way across the
    gap, agree within ``tol_px / f``. Each track end joins at most one track
    start (nearest fits first), so tracks join into chains and never hold two
    segments of one frame. With ``overlap``, tracks whose spans overlap (two
    pieces of one line followed side by side) are joined too when their fits
    agree in the middle of the overlap; in a frame where the joined track then
    holds two segments only the longest stays. With ``image_px`` > 0 the join
    must also hold in the image: each track's fit, carried to the other's
    nearest segment (its first, or last), passes within ``image_px`` of that
    segment's mid-point (:func:`interpretation_offset`; near a vanishing point
    two lines 14 px apart in the image are 2 px apart in angle times focal
    length). Candidate pairs come from the tracks sorted by their first frame
    (no all-pairs loop).
    """
    to = np.asarray(tracks.track_of)
    T = tracks.n
    if T < 2 or gap_frames < 1:
        return tracks
    seg = np.flatnonzero(to >= 0)
    t = to[seg].astype(np.int64)
    fr = segments.frame[seg].astype(np.int64)
    ax = tracks.axis[t].astype(np.int64)
    phi = interpretation_angle(segments, seg, ax, K, R_wc, directions)
    first = np.full(T, np.iinfo(np.int64).max)
    last = np.full(T, -1)
    np.minimum.at(first, t, fr)
    np.maximum.at(last, t, fr)
    # unwrap each track's angles around its first segment's, then a least-squares line phi(f - first)
    ref = np.zeros(T)
    ref[t[::-1]] = phi[::-1]  # a segment of each track (the first listed)
    p = ref[t] + _wrap_pi(phi - ref[t])
    x = (fr - first[t]).astype(np.float64)
    n = np.bincount(t, minlength=T).astype(np.float64)
    sx, sp_ = np.bincount(t, x, T), np.bincount(t, p, T)
    sxx, sxp = np.bincount(t, x * x, T), np.bincount(t, x * p, T)
    den = n * sxx - sx * sx
    ok = den > 1e-9
    slope = np.where(ok, (n * sxp - sx * sp_) / np.where(ok, den, 1.0), 0.0)
    icpt = (sp_ - slope * sx) / np.maximum(n, 1.0)
    # candidates: b starts after a's first frame and at most gap_frames after a's last, same axis
    order = np.argsort(first, kind="stable")
    lo = np.searchsorted(first[order], (first if overlap else last + 1), side="left")
    hi = np.searchsorted(first[order], last + gap_frames, side="right")
    cnt = np.maximum(hi - lo, 0)
    a = np.repeat(np.arange(T), cnt)
    b = order[np.repeat(lo, cnt) + (np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt))]
    keep = (tracks.axis[a] == tracks.axis[b]) & (a != b) & ((first[b] > first[a]) | (b > a))
    a, b = a[keep], b[keep]
    seq = first[b] > last[a]
    # where the two fits are compared: half-way across the gap, or the middle of the overlap
    at = np.where(seq, 0.5 * (last[a] + first[b]), 0.5 * (first[b] + np.minimum(last[a], last[b])))
    d = np.abs(_wrap_pi(icpt[b] + slope[b] * (at - first[b]) - icpt[a] - slope[a] * (at - first[a])))
    keep = d * K[0, 0] < tol_px
    a, b, d, seq = a[keep], b[keep], d[keep], seq[keep]
    if image_px > 0 and len(a):  # and in the image: each fit against the other track's nearest segment
        first_seg = np.zeros(T, np.int64)  # a track holds one segment per frame: the one in its first / last frame
        last_seg = np.zeros(T, np.int64)
        at_first, at_last = fr == first[t], fr == last[t]
        first_seg[t[at_first]] = seg[at_first]
        last_seg[t[at_last]] = seg[at_last]

        def off(fit: np.ndarray, at: np.ndarray) -> np.ndarray:
            angle = icpt[fit] + slope[fit] * (segments.frame[at] - first[fit])
            return interpretation_offset(segments, at, tracks.axis[fit].astype(np.int64), angle, K, R_wc, directions)

        keep = np.maximum(off(a, first_seg[b]), off(b, last_seg[a])) < image_px
        a, b, d, seq = a[keep], b[keep], d[keep], seq[keep]
    parent = np.arange(T)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    used_a = np.zeros(T, bool)
    used_b = np.zeros(T, bool)
    for i in np.argsort(d, kind="stable"):  # candidates only (a few per track)
        if seq[i]:  # a chain: each end continues into one start
            if used_a[a[i]] or used_b[b[i]]:
                continue
            used_a[a[i]] = used_b[b[i]] = True
        ra, rb = find(int(a[i])), find(int(b[i]))
        if ra != rb:
            parent[rb] = ra
    root = np.array([find(i) for i in range(T)])
    length = np.linalg.norm(segments.endpoints[:, 2:].astype(np.float64) - segments.endpoints[:, :2], axis=1)
    joined, dropped = join_tracks(tracks, root, segments.frame, length)
    log.info("fragments: %d tracks joined into %d (gaps <= %d frames, %.1f px, %d duplicate segments left out)",
             T, joined.n, gap_frames, tol_px, dropped)
    return joined


def join_tracks(tracks: Tracks, root: np.ndarray, frame: np.ndarray, length: np.ndarray) -> tuple[Tracks, int]:
    """Returns (tracks with each track joined into the track ``root[t]`` names, segments left out).

    Tracks are renumbered in the order of their roots. A track holds one segment per frame: where
    the joined tracks had several in one frame, the longest (``length`` per segment) stays.
    """
    ids, new = np.unique(root, return_inverse=True)
    to = np.asarray(tracks.track_of)
    track_of = np.where(to >= 0, new.ravel()[np.maximum(to, 0)], -1).astype(np.int32)
    s = np.flatnonzero(track_of >= 0)
    o = np.lexsort((-length[s], frame[s], track_of[s]))
    key_t, key_f = track_of[s][o], frame[s][o]
    dup = np.concatenate([[False], (key_t[1:] == key_t[:-1]) & (key_f[1:] == key_f[:-1])])
    track_of[s[o][dup]] = -1
    return Tracks(track_of=track_of, axis=tracks.axis[ids].astype(np.int8)), int(dup.sum())


def track_lines(
    segments: Segments,
    labels: np.ndarray,
    K: np.ndarray,
    R_wc: np.ndarray,
    config: Config | TrackingConfig,
    images=None,
    image_size: tuple[int, int] | None = None,
    directions: np.ndarray | None = None,
) -> Tracks:
    """Returns line tracks: chains of matched Manhattan segments across frames (supplement §3).

    Frame pairs whose optical axes are within ``axis_angle_deg`` are related
    by the rotation homography K R_j^T R_i K^-1 (the refined rotations
    replace the paper's SURF homography; ``images`` is accepted for an
    image-based refinement and currently unused). The paper refines that
    homography by image features; here the line matches themselves are the
    features: with at least ``shift_min_matches`` first matches, the image
    shift that best aligns them (:func:`residual_shift`: rotation error plus
    the parallax of the camera's translation, 2-5 px between neighbouring
    frames at 1.5 m) is added to the homography and the pair matched again
    (measured, 300 frames 960x540: track purity living/bedroom/office
    93.1/97.8/95.6 % -> 98.9/98.6/98.3 %, mean length 7.8 -> 9.9 frames on
    living). Mutual-best matches
    (:func:`match_pair`) are chained by connected components; a component
    holding two segments of one frame is split greedily by match distance;
    tracks shorter than ``min_track_length`` are dropped. With
    ``bridge_angle_deg`` > 0 (a deviation: the paper's 2 degrees are ~1 frame
    apart in a 200-frame spin, so one missed detection cuts a track), pairs
    within that wider angle are matched too, nearest in time first, and a
    mutual-best match (over ALL segments of both frames) is kept only between
    a segment with no later match closer in time and one with no earlier
    one: track ends are bridged, continued tracks are never re-linked. With
    ``colinear_px`` > 0, colinear pieces of one image line in one frame
    (:func:`colinear_groups`) are matched as ONE observation spanning all of
    them, and only the longest piece joins the track (the others stay -1), so
    a track still holds at most one segment per frame; with the Manhattan
    ``directions`` (world, (3, 3)) given and ``vp_colinear``, pieces are
    colinear by their vanishing-point lines (:func:`manhattan_lines`;
    measured, 300 frames 960x540: tracks living/bedroom/office 317/287/387 ->
    162/98/171, mean length 10.6/6.5/8.3 -> 18.1/14.4/15.7 frames, purity
    99.8/99.1/98.9 -> 100.0/98.4/97.4 %: the impure ones mix a trim's edges
    3 cm apart). With ``polarity_min`` > 0 and ``segments.contrast`` known,
    opposite-polarity segments never match (:func:`match_pair`; purity
    98.9/98.8/98.4 -> 99.8/99.1/98.9 %). With the ``directions`` and
    ``jump_px`` > 0, a match farther than that from its partner's
    vanishing-point line once the pair's common shift is taken out
    (:func:`line_jumps`) is a jump to a neighbouring line (a trim's other
    edge) and is dropped; ``merge_image_px`` > 0 makes
    :func:`merge_fragments` check its joins in the image too. ``image_size``
    (w, h) sets the distance threshold's min(w, h); by default it is taken
    from the principal point (image centre).
    """
    cfg = _tracking_config(config)
    S = segments.n
    track_of = np.full(S, -1, dtype=np.int32)
    manhattan = labels >= 0
    if S == 0 or not np.any(manhattan):
        return Tracks(track_of=track_of, axis=np.zeros(0, dtype=np.int8))
    if image_size is not None:
        min_side = float(min(image_size))
    else:
        min_side = min(2.0 * K[0, 2] + 1.0, 2.0 * K[1, 2] + 1.0)  # principal point ~ image centre
    dist_px = cfg.match_dist_frac * min_side
    F = len(R_wc)
    pairs = frame_pairs(R_wc, cfg.axis_angle_deg)
    bridges = _bridge_pairs(R_wc, cfg.bridge_angle_deg, pairs)
    loops = loop_pairs(R_wc, cfg.loop_angle_deg, pairs)
    mlines = None if directions is None else manhattan_lines(segments, labels, K, R_wc, directions)
    rep, ends = colinear_groups(segments, labels, cfg.colinear_px, mlines if cfg.vp_colinear else None)
    contrast = segments.contrast if cfg.polarity_min > 0 else None
    gap = None if cfg.match_gap_frac is None else cfg.match_gap_frac * min_side
    head = manhattan & (rep == np.arange(S))  # one observation per group of colinear pieces
    idx = [np.flatnonzero(head[segments.of_frame(f)]) + segments.frame_offsets[f] for f in range(F)]
    labs = labels
    fwd_gap = np.full(S, np.iinfo(np.int64).max)  # smallest frame gap to a later matched frame
    bwd_gap = np.full(S, np.iinfo(np.int64).max)  # ... to an earlier one
    src, dst, wts = [], [], []

    def match(i: int, j: int, ia: np.ndarray, ib: np.ndarray, bridge: bool = False) -> None:
        if len(ia) == 0 or len(ib) == 0:
            return
        H = rotation_homography(K, R_wc[i], R_wc[j])
        pol = {} if contrast is None else dict(contrast_a=contrast[ia], contrast_b=contrast[ib],
                                               polarity_min=cfg.polarity_min)
        a, b, d = match_pair(ends[ia], labs[ia], ends[ib], labs[ib], H, dist_px, cfg.match_angle_deg,
                             cfg.match_angle_px, gap, **pol)
        if cfg.shift_min_matches > 0 and len(a) >= cfg.shift_min_matches:
            t = residual_shift(_warp(H, ends[ia[a]]), ends[ib[b]])
            H = np.array([[1.0, 0.0, t[0]], [0.0, 1.0, t[1]], [0.0, 0.0, 1.0]]) @ H
            a, b, d = match_pair(ends[ia], labs[ia], ends[ib], labs[ib], H, dist_px, cfg.match_angle_deg,
                                 cfg.match_angle_px, gap, **pol)
        if cfg.jump_px > 0 and mlines is not None and len(a):  # a chain never jumps to a neighbouring line
            near = line_jumps(_warp(H, segments.endpoints[ia[a]].astype(np.float64)), mlines[ib[b]]) < cfg.jump_px
            a, b, d = a[near], b[near], d[near]
        if bridge:  # mutual best among ALL segments, then kept only between a track end and a track start
            g = j - i
            end = (fwd_gap[ia[a]] >= g) & (bwd_gap[ib[b]] >= g)
            a, b, d = a[end], b[end], d[end]
        src.append(ia[a])
        dst.append(ib[b])
        wts.append(d)
        np.minimum.at(fwd_gap, ia[a], j - i)
        np.minimum.at(bwd_gap, ib[b], j - i)

    for i, j in np.concatenate([pairs, loops]):
        match(int(i), int(j), idx[i], idx[j])
    # bridges, nearest in time first: only segments not yet continued within the gap take part
    for i, j in bridges:
        match(int(i), int(j), idx[i], idx[j], bridge=True)
    if not src:
        return Tracks(track_of=track_of, axis=np.zeros(0, dtype=np.int8))
    edges = np.stack([np.concatenate(src), np.concatenate(dst)], axis=1)
    weights = np.concatenate(wts)
    comp = _split_conflicts(edges, weights, segments.frame.astype(np.int64), S)
    size = np.bincount(comp)
    keep = manhattan & (size[comp] >= max(cfg.min_track_length, 2))
    ids, track = np.unique(comp[keep], return_inverse=True)
    track_of[keep] = track
    axis = np.zeros(len(ids), dtype=np.int8)
    axis[track] = labels[keep]
    log.info(
        "%d tracks from %d matches over %d frame pairs (mean length %.1f)",
        len(ids), len(edges), len(pairs) + len(loops), keep.sum() / max(len(ids), 1),
    )
    tracks = Tracks(track_of=track_of, axis=axis)
    if cfg.merge_gap_frames > 0 and directions is not None:
        tracks = merge_fragments(tracks, segments, K, R_wc, directions, cfg.merge_gap_frames, cfg.merge_tol_px,
                                 cfg.merge_overlap, cfg.merge_image_px)
    if cfg.min_longest_frac > 0:
        tracks = drop_short_tracks(tracks, segments, cfg.min_longest_frac * min_side)
    return tracks


def drop_short_tracks(tracks: Tracks, segments: Segments, min_longest_px: float) -> Tracks:
    """Returns the tracks whose longest segment is at least ``min_longest_px`` long (renumbered).

    Our addition to supplement §3: surface texture (wood grain, a stone
    top) gives short strokes that LSD finds, the Manhattan test labels
    (roughly aligned) and the tracker follows (they are fixed in the world),
    but they are no 3D line of the Manhattan directions, and as colinearity
    and reprojection constraints they bend the solution. A structure line
    is long in at least one frame.
    """
    to = np.asarray(tracks.track_of)
    m = to >= 0
    if not np.any(m):
        return tracks
    length = np.linalg.norm(segments.endpoints[:, 2:].astype(np.float64) - segments.endpoints[:, :2], axis=1)
    longest = np.zeros(tracks.n)
    np.maximum.at(longest, to[m], length[m])
    keep = longest >= min_longest_px
    new = np.cumsum(keep) - 1
    track_of = np.where(m & keep[np.maximum(to, 0)], new[np.maximum(to, 0)], -1).astype(np.int32)
    log.info("tracks: %d of %d dropped, no segment of %.0f px (texture)", int((~keep).sum()), tracks.n, min_longest_px)
    return Tracks(track_of=track_of, axis=tracks.axis[keep].astype(np.int8))
