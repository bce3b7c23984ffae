"""The linear solve's results (paper §3.3): camera centres, one 3D line per track, the residual report.

Lines: direction = the track's Manhattan direction, position = the median of its observations'
points (orthogonal to the direction), extent = the closest points on the line to its segments'
end-point rays.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..data import JUNCTION, ORTHOGONAL, PARALLEL, RELATION_NAMES, Camera, LineModel, Preprocessed, Tracks
from ..geometry import closest_on_lines
from .registration import reason_counts
from .robust import Estimate
from .scale import Scaled
from .system import VERTICAL, LinearSystem, Observations, SystemMembers, Unknowns, UsableRelations, observation_rays


def camera_centres(x: np.ndarray, unknowns: Unknowns, n_frames: int, M: np.ndarray) -> np.ndarray:
    """Returns (F, 3) world camera centres ``T_i`` from their Manhattan coordinates ``tau`` (NaN: unregistered)."""
    Fk = unknowns.n_frames
    tau = x[:3 * Fk].reshape(Fk, 3)
    centers = np.full((n_frames, 3), np.nan)
    centers[unknowns.frames] = tau @ M
    return centers


def line_model(pre: Preprocessed, camera: Camera, tracks: Tracks, obs: Observations, members: SystemMembers,
               centers: np.ndarray, lam: np.ndarray, M: np.ndarray) -> LineModel:
    """Returns one 3D line per track from the observations' points ``P = T_i + lambda D`` of registered frames."""
    T = tracks.n
    axis = tracks.axis.astype(int)
    ob = members.obs
    o_f, o_t = obs.frame[ob], obs.track[ob]
    P = centers[o_f] + lam[:, None] * obs.ray[ob]  # (n, 3) observation points (world)
    Pm = P @ M.T
    coord = np.full((T, 3), 0.0)
    for k in range(3):
        has_k = obs.axis[ob] != k
        coord[:, k] = _group_median(Pm[has_k, k], o_t[has_k], T)
    coord[np.arange(T), axis] = 0.0
    n_obs_sys = np.bincount(o_t, minlength=T)  # observations in the system
    valid = members.in_sys & (n_obs_sys > 0) & (n_obs_sys + members.n_rel >= 2)
    valid &= np.isfinite(coord).all(axis=1)
    taylor = np.where(valid[:, None], coord @ M, np.nan)
    direction = M[axis]
    extent = _extents(pre, camera, obs.seg[ob], o_t, centers[o_f], taylor, direction, T)
    valid &= np.isfinite(extent).all(axis=1)
    return LineModel(taylor=taylor, direction=direction.copy(), axis=tracks.axis.astype(np.int8),
                     extent=extent, valid=valid)


def residual_report(scaled: Scaled, est: Estimate, registered: np.ndarray, reasons: np.ndarray,
                    rels: UsableRelations, members: SystemMembers, unknowns: Unknowns, system: LinearSystem,
                    use_floor: bool) -> dict[str, Any]:
    """Returns the solve's summary: registration, scale, and the rms residual of each kind of constraint."""
    xr, lam, s, scale_mode = scaled.x, scaled.depths, scaled.factor, scaled.mode
    u_col = unknowns.u_col
    r_a, r_b, r_k, r_kind, f_t = rels.a, rels.b, rels.k, rels.kind, rels.floor_track
    rs, fs = members.pairs, members.floor
    h = xr[unknowns.col_h]
    res = {
        "scale": scale_mode,
        "metric": scale_mode == "metric",
        "frames": int(len(registered)),
        "registered": int(registered.sum()),
        "solved": int(unknowns.n_frames),
        "tracks_solved": int(len(unknowns.tracks)),
        "observations": int(len(members.obs)),
        "depths_at_bound": int(est.pinned.sum()),
        "active_set_iterations": int(est.iterations),
        "relations_downweighted": int(est.n_down),
        "floor_height": float(h) if use_floor else None,
        "scale_factor": float(s),  # final units per solve units (the depth bound applies in solve units)
        "depth_min": float(lam.min()) if len(lam) else None,
        "depth_median": float(np.median(lam)) if len(lam) else None,
        "unregistered_reasons": reason_counts(reasons, registered),
        "unregistered_reason_codes": reasons.tolist(),  # per frame, into UNREGISTERED_REASONS
    }
    a1 = xr[system.c_t1] - xr[system.c_u1] + lam * system.e1
    a2 = xr[system.c_t2] - xr[system.c_u2] + lam * system.e2
    res["colinearity_rms"] = _rms(np.concatenate([a1, a2]))
    res["colinearity_count"] = int(len(members.obs))
    for kind in (ORTHOGONAL, PARALLEL, JUNCTION):
        m = rs & (r_kind == kind)
        r = xr[u_col(r_a[m], r_k[m])] - xr[u_col(r_b[m], r_k[m])] if np.any(m) else np.zeros(0)
        res[f"{RELATION_NAMES[kind]}_rms"] = _rms(r)
        res[f"{RELATION_NAMES[kind]}_count"] = int(np.sum(m))
    r = xr[u_col(f_t[fs], np.full(int(fs.sum()), VERTICAL))] - h if np.any(fs) else np.zeros(0)
    res["floor_rms"] = _rms(r)
    res["floor_count"] = int(np.sum(fs))
    return res


def _rms(r: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(r ** 2))) if len(r) else None


def _extents(pre: Preprocessed, camera: Camera, seg_ids: np.ndarray, seg_track: np.ndarray, seg_centers: np.ndarray,
             taylor: np.ndarray, direction: np.ndarray, T: int) -> np.ndarray:
    """Returns (T, 2) the line parameters (s0, s1) spanned by the closest points to the end-point rays."""
    ext = np.full((T, 2), np.nan)
    if len(seg_ids) == 0:
        return ext
    lo = np.full(T, np.inf)
    hi = np.full(T, -np.inf)
    p = taylor[seg_track]
    u = direction[seg_track]
    for which in ("start", "end"):
        s = closest_on_lines(p, u, seg_centers, observation_rays(pre, camera, seg_ids, which))
        good = np.isfinite(s)
        np.minimum.at(lo, seg_track[good], s[good])
        np.maximum.at(hi, seg_track[good], s[good])
    has = np.isfinite(lo) & np.isfinite(hi)
    ext[has, 0] = lo[has]
    ext[has, 1] = hi[has]
    return ext


def _group_median(values: np.ndarray, groups: np.ndarray, n_groups: int) -> np.ndarray:
    """Returns (G,) the median of ``values`` per group id (NaN for empty groups), vectorised."""
    out = np.full(n_groups, np.nan)
    if len(values) == 0:
        return out
    order = np.lexsort((values, groups))
    v, g = values[order], groups[order]
    counts = np.bincount(g, minlength=n_groups)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    has = counts > 0
    lo = start[has] + (counts[has] - 1) // 2
    hi = start[has] + counts[has] // 2
    out[has] = 0.5 * (v[lo] + v[hi])
    return out
