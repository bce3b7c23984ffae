"""Joining the fragments of one 3D line into one track (our addition to supplement §3 'Line tracking').

A line whose detections break into pieces is tracked as a chain of short
tracks; :func:`merge_fragments` joins those whose planes through the camera
(:func:`interpretation_angle`) agree across the gap. :func:`join_tracks`
renumbers the joined tracks (also used by ``tools/bench_tracking.py``).
"""
from __future__ import annotations

import logging

import numpy as np

from ..data import Segments, Tracks
from ..geometry import world_rays

log = logging.getLogger("panosfm.lines")


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


def spin_line_rms(phi: np.ndarray, frame: np.ndarray, axis: int, R_wc: np.ndarray, directions: np.ndarray,
                  groups: np.ndarray, n_groups: int, focal: float) -> np.ndarray:
    """Returns (G,) the RMS (px) of one 3D line through each group's observations, cameras on a spin's circle.

    Ours (a test for joining fragments across wide gaps, supplement §3): a spin's camera centre is
    ``c0 + a h_i`` (``h_i`` the horizontal view direction of frame ``i``, ``a`` the arm, ``c0`` the
    stand point). A line of Manhattan axis ``axis`` is a point ``L`` in the plane across it, and each
    observation's plane through the camera (:func:`interpretation_angle` ``phi``, normal ``n``) passes
    through it: ``n . L = n . c_i``. A stand point and an arm of any length only shift and scale ``L``,
    so the fit takes ``c0 = 0``, ``a = 1``. ``L`` is the least-squares point of each group (observation
    ``k`` in group ``groups[k]``, -1: none); the residual is the angle (times ``focal``) by which each
    plane misses it, seen from its camera. Groups of fewer than 3 observations get 0 (always fitted), groups
    whose planes are all parallel (no baseline) infinity.
    """
    other = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    B = directions[other]  # (2, 3): the plane across the line
    v = R_wc[frame][:, :, 2]
    v = v - np.outer(v @ directions[2], directions[2])  # the horizontal view direction: the arm
    c = (v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)) @ B.T
    n = np.column_stack([np.cos(phi), np.sin(phi)])
    rhs = np.sum(n * c, axis=1)
    g = np.where(groups >= 0, groups, n_groups)  # -1: a bin of its own, dropped
    G = n_groups + 1
    A = np.stack([np.bincount(g, n[:, i] * n[:, j], G) for i, j in ((0, 0), (0, 1), (1, 1))], axis=1)
    b = np.stack([np.bincount(g, n[:, i] * rhs, G) for i in (0, 1)], axis=1)
    det = A[:, 0] * A[:, 2] - A[:, 1] ** 2
    ok = det > 1e-12 * np.maximum(A[:, 0] + A[:, 2], 1e-12) ** 2
    det = np.where(ok, det, 1.0)
    L = np.column_stack([A[:, 2] * b[:, 0] - A[:, 1] * b[:, 1], A[:, 0] * b[:, 1] - A[:, 1] * b[:, 0]]) / det[:, None]
    r = (np.sum(n * L[g], axis=1) - rhs) / np.maximum(np.linalg.norm(L[g] - c, axis=1), 1e-9)
    count = np.bincount(g, minlength=G)
    rms = focal * np.sqrt(np.bincount(g, r * r, G) / np.maximum(count, 1))
    return np.where(count < 3, 0.0, np.where(ok, rms, np.inf))[:n_groups]


def _wrap_pi(a: np.ndarray) -> np.ndarray:
    """Returns angles modulo pi in [-pi/2, pi/2)."""
    return (a + np.pi / 2) % np.pi - np.pi / 2


def merge_fragments(tracks: Tracks, segments: Segments, K: np.ndarray, R_wc: np.ndarray, directions: np.ndarray,
                    gap_frames: int, tol_px: float, overlap: bool = False, image_px: float = 0.0,
                    spin_px: float = 0.0, spin_gap_frames: int = 0) -> Tracks:
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
    length). With ``spin_px`` > 0 a track that ends ``1..spin_gap_frames``
    frames before another starts is also joined to it when one line through
    both, seen from cameras on the spin's circle, fits every observation
    within ``spin_px`` RMS (:func:`spin_line_rms`): on spins of few frames per
    turn the linear fits do not carry across a gap of several degrees. Candidate
    pairs come from the tracks sorted by their first frame (no all-pairs loop).
    """
    to = np.asarray(tracks.track_of)
    T = tracks.n
    spin_gap = spin_gap_frames if spin_px > 0 else 0
    if T < 2 or max(gap_frames, spin_gap) < 1:
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
    hi = np.searchsorted(first[order], last + max(gap_frames, spin_gap), side="right")
    cnt = np.maximum(hi - lo, 0)
    a = np.repeat(np.arange(T), cnt)
    b = order[np.repeat(lo, cnt) + (np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt))]
    keep = (tracks.axis[a] == tracks.axis[b]) & (a != b) & ((first[b] > first[a]) | (b > a))
    a, b = a[keep], b[keep]
    seq = first[b] > last[a]
    # where the two fits are compared: half-way across the gap, or the middle of the overlap
    at = np.where(seq, 0.5 * (last[a] + first[b]), 0.5 * (first[b] + np.minimum(last[a], last[b])))
    d = np.abs(_wrap_pi(icpt[b] + slope[b] * (at - first[b]) - icpt[a] - slope[a] * (at - first[a]))) * K[0, 0] / tol_px
    d = np.where(~seq | (first[b] - last[a] <= gap_frames), d, np.inf)  # the linear fits: within gap_frames
    if spin_gap > 0:  # and one line through both from the spin's cameras, across up to spin_gap frames
        gap = first[b] - last[a]
        spin = _spin_join_score(a, b, seq & (gap <= spin_gap), t, fr, phi, tracks, R_wc, directions, K[0, 0]) / spin_px
    else:
        spin = np.full(len(a), np.inf)
    by_spin = spin < np.minimum(d, 1.0)  # the spin's line fits every observation: no linear fit to check
    d = np.minimum(d, spin)
    keep = d < 1.0
    a, b, d, seq, by_spin = a[keep], b[keep], d[keep], seq[keep], by_spin[keep]
    if image_px > 0 and len(a):  # and in the image: each fit against the other track's nearest segment
        first_seg = np.zeros(T, np.int64)  # a track holds one segment per frame: the one in its first / last frame
        last_seg = np.zeros(T, np.int64)
        at_first, at_last = fr == first[t], fr == last[t]
        first_seg[t[at_first]] = seg[at_first]
        last_seg[t[at_last]] = seg[at_last]

        def off(fit: np.ndarray, at: np.ndarray) -> np.ndarray:
            angle = icpt[fit] + slope[fit] * (segments.frame[at] - first[fit])
            return interpretation_offset(segments, at, tracks.axis[fit].astype(np.int64), angle, K, R_wc, directions)

        keep = by_spin | (np.maximum(off(a, first_seg[b]), off(b, last_seg[a])) < image_px)
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
    log.info("fragments: %d tracks joined into %d (gaps <= %d frames, %.1f px; spin line <= %d frames, %.1f px; %d "
             "duplicate segments left out)", T, joined.n, gap_frames, tol_px, spin_gap, spin_px, dropped)
    return joined


def _spin_join_score(a: np.ndarray, b: np.ndarray, test: np.ndarray, t: np.ndarray, fr: np.ndarray, phi: np.ndarray,
                     tracks: Tracks, R_wc: np.ndarray, directions: np.ndarray, focal: float) -> np.ndarray:
    """Returns (C,) the :func:`spin_line_rms` (px) of candidate pairs ``a[k], b[k]`` where ``test`` (inf elsewhere).

    Each candidate's group holds the observations (in track ``t``, frame ``fr``, angle ``phi``) of
    both its tracks: the observations sorted by track, each candidate gathers its two tracks' runs.
    """
    score = np.full(len(a), np.inf)
    idx = np.flatnonzero(test)
    if not len(idx):
        return score
    order = np.argsort(t, kind="stable")
    count = np.bincount(t, minlength=tracks.n)
    start = np.cumsum(count) - count
    obs, group = [], []
    for tr in (a[idx], b[idx]):  # each candidate's two tracks: runs of the sorted observations
        n = count[tr]
        k = np.repeat(np.arange(len(idx)), n)
        obs.append(order[np.repeat(start[tr], n) + np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)])
        group.append(k)
    obs, group = np.concatenate(obs), np.concatenate(group)
    axis = tracks.axis[a[idx]].astype(np.int64)
    for ax in np.unique(axis):
        g = np.where(axis[group] == ax, group, -1)
        rms = spin_line_rms(phi[obs], fr[obs], int(ax), R_wc, directions, g, len(idx), focal)
        score[idx[axis == ax]] = rms[axis == ax]
    return score


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
