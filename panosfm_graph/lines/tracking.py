"""Manhattan line tracking across frames (paper §3.1 'Line tracking', supplement §3)."""
from __future__ import annotations

import dataclasses
import logging

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..config import Config, TrackingConfig
from ..data import Segments, Tracks
from ..geometry import rotation_homography, turned_degrees
from .fragments import interpretation_angle, interpretation_offset, join_tracks, merge_fragments  # noqa: F401

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


def pair_angle_deg(R_wc: np.ndarray, axis_angle_deg: float, axis_angle_steps: float) -> float:
    """Returns the largest angle (deg) between the optical axes of two frames that are matched.

    The paper's fixed ``axis_angle_deg`` (supplement §3) pairs only frames
    closer than 2 degrees, about one frame step of a 300-frame spin. A spin
    filmed at a lower frame rate (or every k-th frame taken) turns further
    between frames, and no pair would be left. So the angle is at least
    ``axis_angle_steps`` times the median angle between consecutive frames
    (ours): every frame is matched to its neighbours at any spin speed.
    """
    return max(float(axis_angle_deg), max(axis_angle_steps, 0.0) * median_step_deg(R_wc))


def median_step_deg(R_wc: np.ndarray) -> float:
    """Returns the median angle (deg) between the optical axes of consecutive frames (0 for fewer than 2)."""
    if len(R_wc) < 2:
        return 0.0
    axes = R_wc[:, :, 2]
    cos = np.clip(np.sum(axes[1:] * axes[:-1], axis=1), -1.0, 1.0)
    return float(np.degrees(np.median(np.arccos(cos))))


def merge_gap(R_wc: np.ndarray, gap_frames: int, gap_deg: float) -> int:
    """Returns the frame gap :func:`merge_fragments` may cross: ``gap_frames``, fewer where they turn more than ``gap_deg``.

    Ours: ``gap_frames`` (3) was set on spins of 300 frames per turn (1.2 degrees a step). Fewer frames per turn
    turn further across the same frame gap, and the fragments' fits, compared half-way across it, joined two lines
    (measured, bedroom, 150 frames per turn: a track holding two lines over 77 degrees, 18 % registered; with the
    gap at 2 frames none: 83 %, 100 % with the jump threshold of :func:`jump_threshold`). So the gap holds at most
    the median frame steps that fit in ``gap_deg``, at least 1 (``gap_deg`` 0: ``gap_frames`` at any spin speed).
    """
    if gap_frames < 1 or gap_deg <= 0:
        return gap_frames
    step = median_step_deg(R_wc)
    return gap_frames if step <= 0 else min(gap_frames, max(1, int(np.floor(gap_deg / step))))


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

    Frame pairs whose optical axes are within ``axis_angle_deg`` (or :func:`pair_angle_deg`) are related
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
    manhattan = labels >= 0
    if S == 0 or not np.any(manhattan):
        return _no_tracks(S)
    min_side = _min_side(K, image_size)
    pairs = frame_pairs(R_wc, pair_angle_deg(R_wc, cfg.axis_angle_deg, cfg.axis_angle_steps))
    bridges = _bridge_pairs(R_wc, cfg.bridge_angle_deg, pairs)
    loops = loop_pairs(R_wc, cfg.loop_angle_deg, pairs)
    matcher = _pair_matcher(segments, labels, K, R_wc, directions, cfg, min_side)
    matches = _match_frame_pairs(matcher, _observations(segments, labels, matcher.rep, len(R_wc)),
                                 np.concatenate([pairs, loops]), bridges, S)
    if matches is None:
        return _no_tracks(S)
    tracks = _tracks_of_matches(*matches, segments, labels, cfg.min_track_length, len(pairs) + len(loops))
    gap_frames = merge_gap(R_wc, cfg.merge_gap_frames, cfg.merge_gap_deg)
    if (gap_frames > 0 or cfg.merge_spin_px > 0) and directions is not None:
        tracks = merge_fragments(tracks, segments, K, R_wc, directions, gap_frames, cfg.merge_tol_px,
                                 cfg.merge_overlap, cfg.merge_image_px, cfg.merge_spin_px, cfg.merge_gap_frames)
    if cfg.min_longest_frac > 0:
        tracks = drop_short_tracks(tracks, segments, cfg.min_longest_frac * min_side)
    return tracks


def _no_tracks(n_segments: int) -> Tracks:
    """Returns :class:`Tracks` with no track (every segment -1)."""
    return Tracks(track_of=np.full(n_segments, -1, dtype=np.int32), axis=np.zeros(0, dtype=np.int8))


def _min_side(K: np.ndarray, image_size: tuple[int, int] | None) -> float:
    """Returns min(w, h) of the images (px): of ``image_size`` (w, h), else from the principal point (image centre)."""
    if image_size is not None:
        return float(min(image_size))
    return min(2.0 * K[0, 2] + 1.0, 2.0 * K[1, 2] + 1.0)  # principal point ~ image centre


@dataclasses.dataclass(frozen=True)
class _PairMatcher:
    """Callable ``(i, j, ia, ib) -> (index in ia, index in ib, distance px)``: the matches between frames i and j.

    Supplement §3 with our refinements (see :func:`track_lines`): ``ia``/``ib``
    are the frames' observations (segment ids); a segment is matched as
    ``ends[s]``, the span of its group of colinear pieces (``rep``: each
    segment's group head, :func:`colinear_groups`); ``lines`` are the
    segments' vanishing-point lines (:func:`manhattan_lines`, None without
    the Manhattan directions); ``contrast`` their polarity (None: not used);
    ``dist_px`` the paper's distance threshold, ``gap_px`` the largest gap
    along the line (None: no overlap test).
    """

    segments: Segments
    labels: np.ndarray
    K: np.ndarray
    R_wc: np.ndarray
    cfg: TrackingConfig
    rep: np.ndarray
    ends: np.ndarray
    lines: np.ndarray | None
    contrast: np.ndarray | None
    dist_px: float
    gap_px: float | None

    def __call__(self, i: int, j: int, ia: np.ndarray, ib: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cfg, ends, labs, contrast = self.cfg, self.ends, self.labels, self.contrast
        gap, dist_px = self.gap_px, self.dist_px
        H = rotation_homography(self.K, self.R_wc[i], self.R_wc[j])
        pol = {} if contrast is None else dict(contrast_a=contrast[ia], contrast_b=contrast[ib],
                                               polarity_min=cfg.polarity_min)
        a, b, d = match_pair(ends[ia], labs[ia], ends[ib], labs[ib], H, dist_px, cfg.match_angle_deg,
                             cfg.match_angle_px, gap, **pol)
        if cfg.shift_min_matches > 0 and len(a) >= cfg.shift_min_matches:
            t = residual_shift(_warp(H, ends[ia[a]]), ends[ib[b]])
            H = np.array([[1.0, 0.0, t[0]], [0.0, 1.0, t[1]], [0.0, 0.0, 1.0]]) @ H
            a, b, d = match_pair(ends[ia], labs[ia], ends[ib], labs[ib], H, dist_px, cfg.match_angle_deg,
                                 cfg.match_angle_px, gap, **pol)
        if cfg.jump_px > 0 and self.lines is not None and len(a):  # a chain never jumps to a neighbouring line
            warped = _warp(H, self.segments.endpoints[ia[a]].astype(np.float64))
            lb = self.lines[ib[b]]
            near = line_jumps(warped, lb) < jump_threshold(self.R_wc[i], self.R_wc[j], cfg, np.abs(lb[:, 0]))
            a, b, d = a[near], b[near], d[near]
        return a, b, d


def jump_threshold(R_i: np.ndarray, R_j: np.ndarray, cfg: TrackingConfig, across_x: np.ndarray | float = 0.0
                   ) -> np.ndarray | float:
    """Returns how far (px) a match of frames i and j may lie off its partner's vanishing-point line (:func:`line_jumps`).

    ``jump_px``, times the pair's turn (the angle between the optical axes) / ``jump_ref_deg`` where that is more
    than 1 (ours): what :func:`line_jumps` leaves is a line's own parallax, which grows with the camera's
    translation between the frames, i.e. with the turn. Measured (true matches' jumps, 99th percentile,
    living/bedroom/office): pairs 1.3 degrees apart 1.3/2.1/1.9 px, 2.5 degrees 2.4/4.9/3.7 px, 3.8 degrees
    4.0/10.1/6.2 px; so pairs within the paper's 2 degrees keep ``jump_px`` (``jump_ref_deg`` 0: at any turn).
    ``across_x`` (per match: |x component| of the line's unit normal, 1 for an upright line) raises that factor
    to the power 1 + ``jump_across_power`` * ``across_x`` (ours): a spin moves the camera sideways, which shifts a
    line across itself by f t / Z |n_x|, so upright lines at other depths than the pair's common shift keep
    parallax that horizontal ones do not. Measured (office, 60 frames per turn, 6.5 degrees a pair, jump test
    off): true matches' jumps 99th percentile 2.1 px for |n_x| < 0.7, 20.7 px above; the 9 false matches were all
    upright and at 1-4 px (the test cannot tell them at that turn), so the fixed factor (9.8 px) only lost 14
    true matches of upright lines.
    """
    if cfg.jump_ref_deg <= 0:
        return cfg.jump_px
    angle = float(np.degrees(np.arccos(np.clip(np.dot(R_i[:, 2], R_j[:, 2]), -1.0, 1.0))))
    scale = max(1.0, angle / cfg.jump_ref_deg)
    return cfg.jump_px * scale ** (1.0 + cfg.jump_across_power * np.asarray(across_x, dtype=np.float64))


def _pair_matcher(segments: Segments, labels: np.ndarray, K: np.ndarray, R_wc: np.ndarray,
                  directions: np.ndarray | None, cfg: TrackingConfig, min_side: float) -> _PairMatcher:
    """Returns the :class:`_PairMatcher` of the segments: colinear pieces grouped, thresholds in pixels."""
    dist_px = cfg.match_dist_frac * min_side
    mlines = None if directions is None else manhattan_lines(segments, labels, K, R_wc, directions)
    rep, ends = colinear_groups(segments, labels, cfg.colinear_px, mlines if cfg.vp_colinear else None)
    contrast = segments.contrast if cfg.polarity_min > 0 else None
    gap = None if cfg.match_gap_frac is None else cfg.match_gap_frac * min_side
    return _PairMatcher(segments, labels, K, R_wc, cfg, rep, ends, mlines, contrast, dist_px, gap)


def _observations(segments: Segments, labels: np.ndarray, rep: np.ndarray, n_frames: int) -> list[np.ndarray]:
    """Returns each frame's observations: its Manhattan segments that head their group of colinear pieces."""
    head = (labels >= 0) & (rep == np.arange(segments.n))  # one observation per group of colinear pieces
    return [np.flatnonzero(head[segments.of_frame(f)]) + segments.frame_offsets[f] for f in range(n_frames)]


def _match_frame_pairs(match: _PairMatcher, idx: list[np.ndarray], pairs: np.ndarray, bridges: np.ndarray,
                       S: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Returns (edges (M, 2) segment ids, distances (M,) px) of the matches of all frame pairs (None: no pair matched).

    ``pairs`` first, then the ``bridges``, nearest in time first: a bridge
    keeps a mutual-best match (among ALL segments of both frames) only
    between a segment not yet continued to a later frame within the gap and
    one not yet continued from an earlier frame (a track end and a track
    start).
    """
    fwd_gap = np.full(S, np.iinfo(np.int64).max)  # smallest frame gap to a later matched frame
    bwd_gap = np.full(S, np.iinfo(np.int64).max)  # ... to an earlier one
    src, dst, wts = [], [], []
    for bridge, todo in ((False, pairs), (True, bridges)):
        for i, j in todo:
            i, j = int(i), int(j)
            ia, ib = idx[i], idx[j]
            if len(ia) == 0 or len(ib) == 0:
                continue
            a, b, d = match(i, j, ia, ib)
            if bridge:  # mutual best among ALL segments, then kept only between a track end and a track start
                g = j - i
                end = (fwd_gap[ia[a]] >= g) & (bwd_gap[ib[b]] >= g)
                a, b, d = a[end], b[end], d[end]
            src.append(ia[a])
            dst.append(ib[b])
            wts.append(d)
            np.minimum.at(fwd_gap, ia[a], j - i)
            np.minimum.at(bwd_gap, ib[b], j - i)
    if not src:
        return None
    return np.stack([np.concatenate(src), np.concatenate(dst)], axis=1), np.concatenate(wts)


def _tracks_of_matches(edges: np.ndarray, weights: np.ndarray, segments: Segments, labels: np.ndarray,
                       min_track_length: int, n_pairs: int) -> Tracks:
    """Returns the tracks: connected components of the matches, split where one holds two segments of a frame.

    Components shorter than ``min_track_length`` (at least 2) are dropped;
    a track's axis is its segments' Manhattan label.
    """
    S = segments.n
    manhattan = labels >= 0
    track_of = np.full(S, -1, dtype=np.int32)
    comp = _split_conflicts(edges, weights, segments.frame.astype(np.int64), S)
    size = np.bincount(comp)
    keep = manhattan & (size[comp] >= max(min_track_length, 2))
    ids, track = np.unique(comp[keep], return_inverse=True)
    track_of[keep] = track
    axis = np.zeros(len(ids), dtype=np.int8)
    axis[track] = labels[keep]
    log.info(
        "%d tracks from %d matches over %d frame pairs (mean length %.1f)",
        len(ids), len(edges), n_pairs, keep.sum() / max(len(ids), 1),
    )
    return Tracks(track_of=track_of, axis=axis)


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
