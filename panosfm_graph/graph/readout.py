"""Reading a :class:`~panosfm_graph.data.Solution` out of the optimised values.

Centres and Taylor vectors from the gtsam values, the lines' extents from their observations
(:func:`line_extents`), the refined focal length into the camera, and the RMS reprojection distance; the lines
of frames the points placed (:func:`lines_at_poses`) and the lines beyond the room left out
(:func:`drop_lines_beyond_room`).
"""
from __future__ import annotations

import dataclasses
import logging
from typing import Callable

import gtsam
import numpy as np

import factors

from ..data import Camera, LineModel, Preprocessed, Solution, Tracks
from ..geometry import closest_on_lines, interpretation_normals, world_rays
from .problem import _Problem, center_key, line_key

log = logging.getLogger("panosfm.graph")


def line_extents(taylor: np.ndarray, direction: np.ndarray, endpoints: np.ndarray, R_wc: np.ndarray,
                 centers: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Returns (N, 2) line coordinates s of the points of the 3D lines closest to the endpoints' viewing rays.

    Rows are observations: ``taylor``/``direction`` (N, 3), ``endpoints`` (N, 4) pixels,
    ``R_wc`` (N, 3, 3), ``centers`` (N, 3). NaN where a ray is parallel to its line.
    """
    out = np.empty((len(endpoints), 2))
    for e in range(2):
        D = world_rays(K, R_wc, endpoints[:, 2 * e:2 * e + 2])
        out[:, e] = closest_on_lines(taylor, direction, centers, D, min_sin2=1e-6)
    return out


def track_extents(s: np.ndarray, track: np.ndarray, n_tracks: int) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((T, 2) the smallest and largest line coordinate over each track's observations, (T,) bool where
    finite): ``s`` (N, 2) the observations' end-point coordinates (:func:`line_extents`; NaN ignored)."""
    s = np.where(np.isfinite(s), s, np.nan)
    lo = np.full(n_tracks, np.inf)
    hi = np.full(n_tracks, -np.inf)
    np.minimum.at(lo, track, np.nanmin(s, axis=1, initial=np.inf))
    np.maximum.at(hi, track, np.nanmax(s, axis=1, initial=-np.inf))
    return np.c_[lo, hi], np.isfinite(lo) & np.isfinite(hi)


def _solution(pre: Preprocessed, tracks: Tracks, initial: Solution, prob: _Problem, values: gtsam.Values,
              R_wc: np.ndarray, camera: Camera, residuals: dict) -> Solution:
    """Returns the Solution read from ``values`` (Lambda projected onto its direction's normal plane, extents from observations)."""
    centers = _read_points(values, center_key, prob.frames, initial.centers)
    taylor = initial.lines.taylor.copy()
    raw = np.array([values.atPoint3(line_key(t)) for t in prob.lines]).reshape(-1, 3)
    A = prob.directions[prob.lines]
    taylor[prob.lines] = factors.taylor_from_point_direction(raw, A)
    direction = initial.lines.direction.copy()
    direction[prob.lines] = A
    extent = initial.lines.extent.copy()
    if len(prob.obs_seg):
        t = prob.obs_track
        s = line_extents(taylor[t], prob.directions[t], pre.segments.endpoints[prob.obs_seg].astype(np.float64),
                         R_wc[prob.obs_frame], centers[prob.obs_frame], camera.K)
        lo_hi, ok = track_extents(s, t, tracks.n)
        extent[ok] = lo_hi[ok]
    valid = initial.lines.valid.copy()
    residuals["colinearity_rms_m"] = float(np.sqrt(np.mean(np.sum(raw * A, axis=1) ** 2))) if len(raw) else 0.0
    lines = LineModel(taylor=taylor, direction=direction, axis=tracks.axis.copy(), extent=extent, valid=valid)
    centers[~initial.registered] = np.nan
    return Solution(R_wc=R_wc, centers=centers, registered=initial.registered.copy(), lines=lines, camera=camera,
                    metric=initial.metric, residuals=residuals)


def _read_points(values: gtsam.Values, key: Callable[[int], int], ids: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Returns a copy of ``base`` (N, 3) with rows ``ids`` read from the Point3 variables ``key(id)``."""
    out = np.array(base, dtype=np.float64, copy=True)
    for i in ids:
        out[i] = values.atPoint3(key(i))
    return out


def _camera_with_focal(camera: Camera, fx: float) -> Camera:
    """Returns ``camera`` with fx set to ``fx`` and fy scaled by the same factor (principal point kept)."""
    p = np.array(camera.params, dtype=np.float64)
    if camera.model == "SIMPLE_PINHOLE":
        p[0] = fx
    else:
        scale = fx / p[0]
        p[0] = fx
        p[1] = p[1] * scale
    return dataclasses.replace(camera, params=p)


def _reprojection_rms(pre: Preprocessed, prob: _Problem, taylor: np.ndarray, R_wc: np.ndarray, centers: np.ndarray,
                      K: np.ndarray) -> float:
    """Returns the RMS segment-averaged reprojection distance (pixels) over all observations."""
    if len(prob.obs_seg) == 0:
        return 0.0
    t, f = prob.obs_track, prob.obs_frame
    r = factors.reprojection_terms(pre.segments.endpoints[prob.obs_seg].astype(np.float64), prob.directions[t],
                                   taylor[t], centers[f], R_wc[f], K)
    return float(np.sqrt(np.mean(np.sum(r**2, axis=1))))


def lines_at_poses(pre: Preprocessed, tracks: Tracks, sol: Solution, only_missing: bool = True, min_obs: int = 3,
                   min_spread_deg: float = 1.0, max_rms_px: float = 2.0) -> LineModel:
    """Returns the solution's lines with the tracks it has no line for triangulated at its registered poses
    (our addition, issue #40: frames the point tracks placed see lines the adjustment never held).

    A Manhattan line of direction ``d`` is ``lambda = mu_1 e_1 + mu_2 e_2`` (Taylor point, paper §3.4, with
    e_1, e_2 the other two Manhattan directions); each observation in frame i, the interpretation plane of normal
    ``n`` through the centre ``c_i``, gives ``n . lambda = n . c_i``: a 2 x 2 least squares per track. Kept where
    at least ``min_obs`` registered frames see it, their planes spread by ``min_spread_deg`` (the RMS angle about
    the mean normal) and the line lies within ``max_rms_px`` (RMS) of their planes; extents as
    :func:`line_extents`. ``only_missing`` False: every track is triangulated again.
    """
    lines, seg, M = sol.lines, pre.segments, pre.manhattan.directions
    T = tracks.n
    valid = lines.valid if len(lines.valid) == T else np.zeros(T, bool)
    taylor = lines.taylor if len(lines.taylor) == T else np.full((T, 3), np.nan)
    extent = lines.extent if len(lines.extent) == T else np.full((T, 2), np.nan)
    tr = tracks.track_of
    s = np.flatnonzero((tr >= 0) & sol.registered[seg.frame])
    if only_missing:
        s = s[~valid[tr[s]]]
    t, f = tr[s], seg.frame[s]
    axis = np.clip(tracks.axis, 0, 2)
    other = np.array([[1, 2], [0, 2], [0, 1]])[axis]  # (T, 2) the two Manhattan axes orthogonal to each line
    K = sol.camera.K
    n = np.einsum("sij,sj->si", sol.R_wc[f], interpretation_normals(K, seg.endpoints[s].astype(np.float64)))
    a = np.einsum("si,sji->sj", n, M[other[t]])  # (S, 2): n . e_1, n . e_2
    b = np.einsum("si,si->s", n, sol.centers[f])
    A = np.zeros((T, 2, 2))
    r = np.zeros((T, 2))
    np.add.at(A, t, a[:, :, None] * a[:, None, :])
    np.add.at(r, t, a * b[:, None])
    cnt = np.bincount(t, minlength=T)
    lam_min = np.linalg.eigvalsh(A + 1e-15 * np.eye(2))[:, 0]
    spread = np.sqrt(np.maximum(lam_min, 0.0) / np.maximum(cnt, 1))  # ~ sin of the planes' spread about the line
    ok = (cnt >= min_obs) & (spread > np.sin(np.radians(min_spread_deg)))
    mu = np.zeros((T, 2))
    mu[ok] = np.linalg.solve(A[ok], r[ok][:, :, None])[:, :, 0]
    lam = np.einsum("tk,tki->ti", mu, M[other])
    depth = np.linalg.norm((lam[t] - sol.centers[f]) - np.einsum("si,si->s", lam[t] - sol.centers[f],
                                                                  M[axis[t]])[:, None] * M[axis[t]], axis=1)
    px = K[0, 0] * (np.einsum("sk,sk->s", a, mu[t]) - b) / np.maximum(depth, 1e-9)
    rms = np.sqrt(np.bincount(t, px ** 2, minlength=T) / np.maximum(cnt, 1))
    ok &= rms <= max_rms_px
    keep = ok[t]
    ext = line_extents(lam[t[keep]], M[axis[t[keep]]], seg.endpoints[s[keep]].astype(np.float64),
                       sol.R_wc[f[keep]], sol.centers[f[keep]], K)
    lo_hi, has = track_extents(ext, t[keep], T)
    ok &= has
    new_taylor, new_extent, new_valid = taylor.copy(), extent.copy(), valid.copy()
    new_taylor[ok], new_extent[ok], new_valid[ok] = lam[ok], lo_hi[ok], True
    return LineModel(taylor=new_taylor, direction=M[axis], axis=tracks.axis.copy(), extent=new_extent,
                     valid=new_valid)


def drop_lines_beyond_room(sol: Solution, ratio: float) -> Solution:
    """Returns ``sol`` with the valid lines that reach beyond the room marked invalid (our addition, issue #40):
    those whose far end lies more than ``ratio`` times the median valid line's far end from the registered
    centres' mean. A line seen over a few centimetres of baseline is held in depth by its relations and the
    reprojection's curvature only, and can slide along its viewing rays to hundreds of metres, where every
    observation still fits within a pixel (measured: 5 of 36 swaying runs wrote a line 34-1,700x the median
    line's distance, 100 m to 5 km; room lines reach 2.1x at most, a 9 x 7 m hall's stand point off centre
    included). ``residuals["lines_beyond_room"]`` counts them; ``ratio`` <= 0: off."""
    lines = sol.lines
    reg = sol.registered
    if ratio <= 0 or not reg.any() or len(lines.valid) == 0:
        return sol
    valid = lines.valid & np.all(np.isfinite(lines.taylor), axis=1) & np.all(np.isfinite(lines.extent), axis=1)
    if valid.sum() < 3:
        return sol
    E = lines.endpoints[valid]
    c0 = sol.centers[reg].mean(axis=0)
    far = np.maximum(np.linalg.norm(E[:, :3] - c0, axis=1), np.linalg.norm(E[:, 3:] - c0, axis=1))
    beyond = far > ratio * np.median(far)
    res = {**sol.residuals, "lines_beyond_room": int(beyond.sum())}
    if not beyond.any():
        return dataclasses.replace(sol, residuals=res)
    log.warning("%d of %d lines reach beyond the room (their far end over %g times the median line's from the "
                "spin's centre, up to %.0f times): left out of the line model", int(beyond.sum()), len(far), ratio,
                float(far.max() / np.median(far)))
    keep = lines.valid.copy()
    keep[np.flatnonzero(valid)[beyond]] = False
    return dataclasses.replace(sol, lines=dataclasses.replace(lines, valid=keep), residuals=res)
