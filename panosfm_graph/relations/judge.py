"""Ground-truth judging of relations, for benchmarks (``tools/bench_relations.py``) and tests."""
from __future__ import annotations

import numpy as np

from ..data import FLOOR, Camera, Preprocessed, Relations, Tracks


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
