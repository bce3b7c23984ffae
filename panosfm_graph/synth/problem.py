"""Image-free synthetic SfM problems for solver tests (linear solve, bundle adjustment).

:func:`make_problem` builds, from a synthetic box room (:func:`panosfm_graph.synth.make_scene`)
and a spin trajectory (:func:`panosfm_graph.synth.spin_trajectory`), exactly what the
pipeline's solver stages consume -- :class:`~panosfm_graph.data.Preprocessed`,
:class:`~panosfm_graph.data.Tracks`, :class:`~panosfm_graph.data.Relations` -- plus the
ground truth, without rendering or detecting anything.

How it is made (all per frame, vectorised over edges):

* **Segments**: every GT scene edge (``Scene.edges()``) is clipped in the camera frame
  to the near plane ``z >= 0.1 m`` and to the image rectangle (exact Liang-Barsky clipping
  against the five frustum planes). **Occlusion** is approximated: 24 points are sampled
  along the clipped edge and a segment-vs-box slab test (boxes shrunk by 5 mm so that an
  edge is not hidden by its own box) marks the points hidden by any furniture box; the
  segment is the longest contiguous run of visible samples (so an edge cut in two by an
  occluder keeps its longer piece, and a partly hidden end is cut at sample resolution).
  The endpoints are projected with the GT pose and get Gaussian pixel noise
  (``pixel_noise_px`` per coordinate). Segments shorter than ``0.05 * min(w, h)`` are
  dropped, as the detector would drop them.
* **Labels** are the edges' GT room axes; ``manhattan.directions`` are the room axes in
  the world (rows of ``R_world_room.T``).
* **Rotations**: ``R_wc`` = GT rotations perturbed by a random rotation of angle
  ``~ N(0, rot_noise_deg)`` per frame; ``R_wc_imu`` = GT with a linear heading (yaw) drift
  reaching ``imu_drift_deg`` at the last frame.
* **Tracks**: one per GT edge that yields a segment in at least two frames (edges seen in
  one frame leave untracked segments, ``track_of = -1``).
* **Relations** (ground truth, no quad test): PARALLEL / ORTHOGONAL between two tracks whose
  edges lie on one common planar face (a face of the room shell or of a box), normal = the
  face's axis; JUNCTION between tracks of different axes that share an endpoint (normal =
  the third axis; such pairs get no ORTHOGONAL relation as well); FLOOR for horizontal tracks
  lying on the floor plane ``z = room_min[2]``. Pair relations need both tracks seen in a
  common frame; ``support`` = number of frames both were seen (FLOOR: frames the track was
  seen). ``false_relation_ratio`` appends that fraction (of the true relations) of wrong
  PARALLEL / ORTHOGONAL relations between random track pairs with a plausible normal axis
  (one orthogonal to both tracks) along which the GT lines are at least 10 cm apart;
  :attr:`SyntheticProblem.relation_true` tells them apart.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..data import (
    FLOOR,
    JUNCTION,
    ORTHOGONAL,
    PARALLEL,
    Camera,
    LineModel,
    ManhattanFrame,
    Preprocessed,
    Relations,
    Segments,
    Solution,
    Tracks,
)

_NEAR_M = 0.1
_N_SAMPLES = 24
_BOX_SHRINK_M = 0.005
_ON_FACE_EPS_M = 1e-4


@dataclass(frozen=True)
class SyntheticProblem:
    """A solver-ready synthetic problem and its ground truth (see module docstring)."""

    camera: Camera
    preprocessed: Preprocessed
    tracks: Tracks
    relations: Relations
    gt_R_wc: np.ndarray  # (F, 3, 3) world_from_camera
    gt_centers: np.ndarray  # (F, 3) camera centres (m)
    gt_track_lines: np.ndarray  # (T, 6) GT 3D edge of each track, world (m)
    scene: object  # panosfm_graph.synth.Scene
    relation_true: np.ndarray | None = None  # (R,) bool: False for injected wrong relations
    segment_edge: np.ndarray | None = None  # (S,) int: GT scene-edge index of each segment

    @property
    def n_frames(self) -> int:
        return len(self.gt_centers)

    def gt_solution(self) -> Solution:
        """Returns the ground truth as a Solution: GT poses, Taylor lines from the GT edges (paper §3.4)."""
        from factors import taylor_from_point_direction

        A = self.preprocessed.manhattan.directions[self.tracks.axis]
        ends = self.gt_track_lines
        lam = taylor_from_point_direction(ends[:, :3], A)
        s = np.stack([np.sum((ends[:, :3] - lam) * A, 1), np.sum((ends[:, 3:] - lam) * A, 1)], 1)
        lines = LineModel(lam, A, self.tracks.axis.copy(), np.sort(s, axis=1), np.ones(self.tracks.n, bool))
        return Solution(self.gt_R_wc.copy(), self.gt_centers.copy(), np.ones(self.n_frames, bool), lines,
                        self.camera, True, {})


def _all_boxes(scene) -> tuple[np.ndarray, np.ndarray]:
    """Returns (min, max) corners (N, 3) of the room shell (row 0) and every box, room frame."""
    bmin = np.vstack([np.asarray(scene.room_min, float)[None], np.asarray(scene.boxes_min, float).reshape(-1, 3)])
    bmax = np.vstack([np.asarray(scene.room_max, float)[None], np.asarray(scene.boxes_max, float).reshape(-1, 3)])
    return bmin, bmax


def _faces(bmin: np.ndarray, bmax: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Returns the boxes' faces: normal axis (G,), offset (G,), 3D lower/upper bounds (G, 3)."""
    axis, offset, lo, hi = [], [], [], []
    for k in range(3):
        for side in (bmin, bmax):
            axis.append(np.full(len(bmin), k))
            offset.append(side[:, k])
            lo.append(bmin)
            hi.append(bmax)
    return np.concatenate(axis), np.concatenate(offset), np.vstack(lo), np.vstack(hi)


def _clip_to_frustum(A: np.ndarray, B: np.ndarray, K: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """Returns the parameter range [t0, t1] of camera-frame segments A + t (B - A) inside the frustum.

    Empty ranges have ``t0 > t1``. Planes: z >= near and the image rectangle [-0.5, w-0.5] x [-0.5, h-0.5].
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    # plane functions g(X) = n . X + d >= 0
    n = np.array([
        [0.0, 0.0, 1.0],
        [fx, 0.0, cx + 0.5],
        [-fx, 0.0, w - 0.5 - cx],
        [0.0, fy, cy + 0.5],
        [0.0, -fy, h - 0.5 - cy],
    ])
    d = np.array([-_NEAR_M, 0.0, 0.0, 0.0, 0.0])
    gA = A @ n.T + d  # (M, 5)
    gB = B @ n.T + d
    with np.errstate(divide="ignore", invalid="ignore"):
        tstar = gA / (gA - gB)
    enter = (gA < 0) & (gB >= 0)
    leave = (gA >= 0) & (gB < 0)
    t0 = np.max(np.where(enter, tstar, 0.0), axis=1)
    t1 = np.min(np.where(leave, tstar, 1.0), axis=1)
    outside = np.any((gA < 0) & (gB < 0), axis=1)
    t0[outside] = 1.0
    t1[outside] = 0.0
    return t0, t1


def _occluded(c: np.ndarray, P: np.ndarray, bmin: np.ndarray, bmax: np.ndarray) -> np.ndarray:
    """Returns (N,) bool: the segment from camera centre ``c`` to point ``P[n]`` crosses a box (room frame)."""
    if len(bmin) == 0:
        return np.zeros(len(P), bool)
    shrink = np.minimum(_BOX_SHRINK_M, 0.25 * (bmax - bmin))
    lo = bmin + shrink
    hi = bmax - shrink
    d = P - c  # (N, 3)
    d = np.where(np.abs(d) < 1e-12, 1e-12, d)
    inv = 1.0 / d
    ta = (lo[None] - c) * inv[:, None]  # (N, B, 3)
    tb = (hi[None] - c) * inv[:, None]
    tmin = np.max(np.minimum(ta, tb), axis=2)
    tmax = np.min(np.maximum(ta, tb), axis=2)
    hit = (tmin < tmax) & (tmax > 0.0) & (tmin < 1.0)
    return np.any(hit, axis=1)


def _longest_runs(vis: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (rows, first, last) sample index of the longest run of True in each row that has one."""
    M, S = vis.shape
    padded = np.zeros((M, S + 2), np.int8)
    padded[:, 1:-1] = vis
    dif = np.diff(padded, axis=1)
    r_s, c_s = np.nonzero(dif == 1)
    r_e, c_e = np.nonzero(dif == -1)  # row-major order keeps starts and ends paired
    length = c_e - c_s
    order = np.lexsort((-length, r_s))
    r_s, c_s, c_e = r_s[order], c_s[order], c_e[order]
    first = np.ones(len(r_s), bool)
    first[1:] = r_s[1:] != r_s[:-1]
    return r_s[first], c_s[first], c_e[first] - 1


def _random_rotations(rng: np.random.Generator, n: int, sigma_deg: float) -> np.ndarray:
    """Returns (n, 3, 3) random rotations about uniform axes with angles ~ N(0, sigma_deg)."""
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    ang = np.radians(rng.normal(0.0, sigma_deg, size=n)) if sigma_deg > 0 else np.zeros(n)
    return Rotation.from_rotvec(axes * ang[:, None]).as_matrix()


def make_problem(scene="living", n_frames: int = 60, size: tuple[int, int] = (480, 270), seed: int = 0, *,
                 pixel_noise_px: float = 0.3, rot_noise_deg: float = 0.0, false_relation_ratio: float = 0.0,
                 turn_deg: float = 380.0, imu_drift_deg: float = 3.0, sway_m: float = 0.0) -> SyntheticProblem:
    """Returns a :class:`SyntheticProblem`: GT edges seen along a spin, as segments, tracks and relations.

    ``scene`` is a preset name (``make_scene(scene, seed)``) or a ``Scene``. See the module
    docstring for visibility, noise and relation rules. ``sway_m``: the spin departs this far from
    an ideal circle (:mod:`panosfm_graph.synth.trajectory`).
    """
    try:
        from . import make_scene, spin_trajectory
    except ImportError:  # the package __init__ not yet exporting them
        from .scenes import make_scene
        from .trajectory import spin_trajectory

    sc = make_scene(scene, seed) if isinstance(scene, str) else scene
    rng = np.random.default_rng(seed + 7919)
    w, h = int(size[0]), int(size[1])
    f = 0.8 * w
    camera = Camera("PINHOLE", w, h, np.array([f, f, (w - 1) / 2.0, (h - 1) / 2.0]))
    K = camera.K

    gt_R, gt_c, _ = spin_trajectory(sc, n_frames, seed=seed, turn_deg=turn_deg, sway_m=sway_m)
    gt_R = np.asarray(gt_R, float)
    gt_c = np.asarray(gt_c, float)
    F = len(gt_c)

    lines_w, labels = sc.edges()
    lines_w = np.asarray(lines_w, float)
    labels = np.asarray(labels, np.int8)
    R_wr = np.asarray(sc.R_world_room, float)
    t_wr = np.asarray(sc.t_world_room, float)
    bmin, bmax = _all_boxes(sc)
    obox_min, obox_max = bmin[1:], bmax[1:]  # the shell never occludes from inside
    A_w, B_w = lines_w[:, :3], lines_w[:, 3:]
    M = len(lines_w)
    ts_unit = np.linspace(0.0, 1.0, _N_SAMPLES)
    min_len = 0.05 * min(w, h)

    seg_ep, seg_frame, seg_edge = [], [], []
    for i in range(F):
        Rc, cc = gt_R[i], gt_c[i]
        A = (A_w - cc) @ Rc
        B = (B_w - cc) @ Rc
        t0, t1 = _clip_to_frustum(A, B, K, w, h)
        keep = np.flatnonzero(t1 - t0 > 1e-6)
        if len(keep) == 0:
            continue
        ts = t0[keep, None] + (t1 - t0)[keep, None] * ts_unit[None]  # (m, S)
        P_w = A_w[keep, None] + ts[..., None] * (B_w - A_w)[keep, None]
        P_r = (P_w.reshape(-1, 3) - t_wr) @ R_wr
        c_r = (cc - t_wr) @ R_wr
        vis = ~_occluded(c_r, P_r, obox_min, obox_max).reshape(len(keep), _N_SAMPLES)
        rows, first, last = _longest_runs(vis)
        rows_sel = np.flatnonzero(last > first)
        rows, first, last = rows[rows_sel], first[rows_sel], last[rows_sel]
        e = keep[rows]
        ta = ts[rows, first]
        tb = ts[rows, last]
        Pa = A[e] + ta[:, None] * (B[e] - A[e])
        Pb = A[e] + tb[:, None] * (B[e] - A[e])
        uva = Pa[:, :2] / Pa[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        uvb = Pb[:, :2] / Pb[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        ep = np.concatenate([uva, uvb], axis=1)
        if pixel_noise_px > 0:
            ep = ep + rng.normal(0.0, pixel_noise_px, size=ep.shape)
        long_enough = np.hypot(ep[:, 2] - ep[:, 0], ep[:, 3] - ep[:, 1]) >= min_len
        seg_ep.append(ep[long_enough])
        seg_edge.append(e[long_enough])
        seg_frame.append(np.full(int(long_enough.sum()), i))

    endpoints = np.concatenate(seg_ep).astype(np.float32) if seg_ep else np.zeros((0, 4), np.float32)
    seg_edge_a = np.concatenate(seg_edge) if seg_edge else np.zeros(0, int)
    frame = np.concatenate(seg_frame).astype(np.int32) if seg_frame else np.zeros(0, np.int32)
    offsets = np.concatenate([[0], np.cumsum(np.bincount(frame, minlength=F))]).astype(np.int64)
    colors = np.full((len(frame), 3), 160, np.uint8)
    colors[:, :] = (np.array([[60, 60, 220], [60, 200, 60], [220, 80, 60]], np.uint8)[labels[seg_edge_a]]
                    if len(frame) else colors)
    segments = Segments(endpoints, frame, offsets, colors)

    # tracks: edges seen in >= 2 frames
    n_seen = np.bincount(seg_edge_a, minlength=M)
    tracked = np.flatnonzero(n_seen >= 2)
    track_id_of_edge = np.full(M, -1, np.int32)
    track_id_of_edge[tracked] = np.arange(len(tracked), dtype=np.int32)
    track_of = track_id_of_edge[seg_edge_a] if len(seg_edge_a) else np.zeros(0, np.int32)
    tracks = Tracks(track_of.astype(np.int32), labels[tracked].astype(np.int8))
    T = len(tracked)

    # relations
    relations, rel_true = _gt_relations(lines_w[tracked], labels[tracked], track_of, frame, F, T,
                                        bmin, bmax, R_wr, t_wr, rng, false_relation_ratio)

    # rotations
    R_noisy = np.einsum("nij,njk->nik", _random_rotations(rng, F, rot_noise_deg), gt_R)
    yaw = np.radians(imu_drift_deg) * np.linspace(0.0, 1.0, F)
    R_imu = np.einsum("nij,njk->nik", Rotation.from_euler("z", yaw[:, None]).as_matrix(), gt_R)
    pre = Preprocessed(segments=segments, manhattan=ManhattanFrame(R_wr.T.copy()),
                       labels=labels[seg_edge_a].astype(np.int8), R_wc=R_noisy, R_wc_imu=R_imu)
    return SyntheticProblem(camera=camera, preprocessed=pre, tracks=tracks, relations=relations,
                            gt_R_wc=gt_R, gt_centers=gt_c, gt_track_lines=lines_w[tracked].copy(), scene=sc,
                            relation_true=rel_true, segment_edge=seg_edge_a)


def _gt_relations(lines_w, axes, track_of, frame, F, T, bmin, bmax, R_wr, t_wr, rng, false_ratio):
    """Returns (Relations, relation_true) of the tracked GT edges (see module docstring)."""
    empty = Relations(np.zeros(0, np.int8), np.zeros(0, np.int32), np.zeros(0, np.int32),
                      np.zeros(0, np.int8), np.zeros(0, np.int32))
    if T == 0:
        return empty, np.zeros(0, bool)
    A = (lines_w[:, :3] - t_wr) @ R_wr  # room frame
    B = (lines_w[:, 3:] - t_wr) @ R_wr
    lo_e, hi_e = np.minimum(A, B), np.maximum(A, B)
    f_axis, f_off, f_lo, f_hi = _faces(bmin, bmax)
    eps = _ON_FACE_EPS_M
    in_plane = (np.abs(lo_e[:, None, :] - f_off[None, :, None]) < eps) & (np.abs(hi_e[:, None, :] - f_off[None, :, None]) < eps)
    in_plane = np.take_along_axis(in_plane, np.broadcast_to(f_axis[None, :, None], (T, len(f_axis), 1)), axis=2)[..., 0]
    in_bounds = np.all((lo_e[:, None] >= f_lo[None] - eps) & (hi_e[:, None] <= f_hi[None] + eps), axis=2)
    on = in_plane & in_bounds & (axes[:, None] != f_axis[None])  # (T, G)

    seen = np.zeros((F, T), np.int32)
    tr = track_of >= 0
    seen[frame[tr], track_of[tr]] = 1
    support = seen.T @ seen  # (T, T)

    # junctions: shared endpoints, different axes
    ends = np.vstack([A, B])
    pairs = cKDTree(ends).query_pairs(1e-3, output_type="ndarray")
    ja, jb = pairs[:, 0] % T, pairs[:, 1] % T
    jm = (ja != jb) & (axes[ja] != axes[jb])
    ja, jb = np.minimum(ja[jm], jb[jm]), np.maximum(ja[jm], jb[jm])
    junction = np.zeros((T, T), bool)
    junction[ja, jb] = True

    kind, ta, tb, nax, sup = [], [], [], [], []
    upper = np.triu(np.ones((T, T), bool), 1)
    for k in range(3):
        onk = on[:, f_axis == k].astype(np.int32)
        co = (onk @ onk.T > 0) & upper & (support > 0)
        a, b = np.nonzero(co)
        same = axes[a] == axes[b]
        is_j = junction[a, b]
        keep = same | ~is_j
        a, b, same = a[keep], b[keep], same[keep]
        kind.append(np.where(same, PARALLEL, ORTHOGONAL))
        ta.append(a)
        tb.append(b)
        nax.append(np.full(len(a), k))
        sup.append(support[a, b])
    a, b = np.nonzero(junction & (support > 0))
    kind.append(np.full(len(a), JUNCTION))
    ta.append(a)
    tb.append(b)
    nax.append(3 - axes[a].astype(int) - axes[b].astype(int))
    sup.append(support[a, b])
    floor_z = bmin[0, 2]
    fl = np.flatnonzero((axes != 2) & (np.abs(A[:, 2] - floor_z) < eps) & (np.abs(B[:, 2] - floor_z) < eps))
    kind.append(np.full(len(fl), FLOOR))
    ta.append(fl)
    tb.append(np.full(len(fl), -1))
    nax.append(np.full(len(fl), 2))
    sup.append(support[fl, fl])

    kind, ta, tb, nax, sup = (np.concatenate(x) for x in (kind, ta, tb, nax, sup))
    true = np.ones(len(kind), bool)

    n_false = int(round(false_ratio * len(kind)))
    if n_false > 0 and T >= 2:
        fa, fb, fk = [], [], []
        mid = 0.5 * (A + B)
        tries = 0
        while len(fa) < n_false and tries < 50:
            tries += 1
            a = rng.integers(0, T, 4 * n_false)
            b = rng.integers(0, T, 4 * n_false)
            third = 3 - axes[a].astype(int) - axes[b].astype(int)
            other = np.array([[1, 2], [0, 2], [0, 1]])[axes[a]][np.arange(len(a)), rng.integers(0, 2, len(a))]
            k = np.where(axes[a] == axes[b], other, third)
            ok = (a != b) & (np.abs(mid[a, k] - mid[b, k]) > 0.1)
            fa.extend(a[ok].tolist())
            fb.extend(b[ok].tolist())
            fk.extend(k[ok].tolist())
        fa, fb, fk = np.array(fa[:n_false]), np.array(fb[:n_false]), np.array(fk[:n_false])
        kind = np.concatenate([kind, np.where(axes[fa] == axes[fb], PARALLEL, ORTHOGONAL)])
        ta = np.concatenate([ta, fa])
        tb = np.concatenate([tb, fb])
        nax = np.concatenate([nax, fk])
        sup = np.concatenate([sup, rng.integers(1, 4, len(fa))])
        true = np.concatenate([true, np.zeros(len(fa), bool)])

    rel = Relations(kind.astype(np.int8), ta.astype(np.int32), tb.astype(np.int32),
                    nax.astype(np.int8), sup.astype(np.int32))
    return rel, true
