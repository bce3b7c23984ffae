"""The gauge and the metric scale: the gauge constants and the floor's scale checks after a solve.

:func:`_gauge` picks the first centre, the floor height and the fallback scale line the graph's
gauge priors hold; after the solve the model is rescaled about the origin (:func:`_scaled`) so
that the mean camera-to-floor distance is the initial one (:func:`_keep_camera_height`) and no
well-observed horizontal line lies below the floor (:func:`_floor_below_lines`, our addition).
The spin arm's check of the scale is in :mod:`.spin` (:func:`~.spin._check_arm`).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..data import FLOOR, Relations, Solution
from .problem import _Problem


def _gauge(relations: Relations, prob: _Problem, initial: Solution, manhattan: np.ndarray) -> dict:
    """Returns the gauge constants: first centre, whether floor relations hold the scale and the floor height, and
    the fallback scale line."""
    # the first frame that sees a line (a steady spin's problem also holds frames that see none: _select)
    first = int(prob.obs_frame.min()) if len(prob.obs_frame) else int(np.flatnonzero(initial.registered)[0])
    c0 = np.asarray(initial.centers[first], dtype=np.float64)
    fl = prob.rel_idx[relations.kind[prob.rel_idx] == FLOOR]
    floor_h = 0.0
    if len(fl):
        n = manhattan[relations.normal_axis[fl].astype(int)]
        floor_h = float(np.median(np.sum(initial.lines.taylor[relations.track_a[fl]] * n, axis=1)))
    counts = np.bincount(prob.obs_track, minlength=len(prob.directions)) if len(prob.obs_track) else np.zeros(1, int)
    best = int(np.argmax(counts)) if len(prob.lines) else 0
    lam = np.asarray(initial.lines.taylor[best], dtype=np.float64)
    A = prob.directions[best]
    v = lam - c0
    v = v - (v @ A) * A
    dist = float(np.linalg.norm(v))
    normal = v / dist if dist > 1e-9 else np.cross(A, [0.0, 0.0, 1.0] if abs(A[2]) < 0.9 else [1.0, 0.0, 0.0])
    normal = normal / np.linalg.norm(normal)
    return {"first": first, "first_center": c0, "use_floor": bool(len(fl)), "floor_h": floor_h, "scale_line": best,
            "scale_normal": normal, "scale_offset": float(normal @ (lam - c0))}


def _keep_camera_height(sol: Solution, initial: Solution, relations: Relations, prob: _Problem,
                        manhattan: np.ndarray, residuals: dict) -> Solution:
    """Returns ``sol`` scaled about the origin so the MEAN camera-to-floor distance is the initial one.

    The floor prior (gauge) holds the floor height relative to the FIRST camera, whose centre is
    fixed; where the initial solution placed that camera badly (measured: living, linear: 3.56 m
    above the floor against a 1.45 m mean), every other camera ends at the first one's height and
    the metric scale inflates by that ratio. Scale is a gauge freedom of the relation and
    reprojection costs, so rescaling restores the linear solve's metric definition (the floor
    ``camera_height_m`` below the mean camera height) exactly.
    """
    up = _floor_normal(relations, prob, manhattan)
    h1 = residuals.get("floor_height")
    h0 = initial.residuals.get("floor_height") if isinstance(initial.residuals, dict) else None
    reg = sol.registered
    if up is None or h1 is None or h0 is None or not np.any(reg):
        return sol
    d0 = float(np.mean(initial.centers[initial.registered] @ up)) - float(h0)
    d1 = float(np.mean(sol.centers[reg] @ up)) - float(h1)
    s = d0 / d1 if d1 > 0 and d0 > 0 else 1.0
    residuals["height_rescale"] = float(s)
    if not np.isfinite(s) or abs(s - 1.0) < 1e-9:
        return sol
    residuals["floor_height"] = float(h1) * s
    return _scaled(sol, s)


def _floor_below_lines(sol: Solution, relations: Relations, prob: _Problem, manhattan: np.ndarray, residuals: dict,
                       min_obs: int) -> Solution:
    """Returns ``sol`` scaled about the origin so that no well-observed horizontal line lies below the floor.

    Our addition to the metric gauge. The floor relations that survive verification are often
    the tops of furniture (the floor is rarely in view of a 39-degree vertical field of view at
    1.5 m), and the floor put ``camera height`` below the cameras on a desk top makes the whole
    model too large. Nothing lies below the floor, so where a horizontal line seen in at least
    ``min_obs`` frames lies deeper below the mean camera height than the floor, the floor is
    moved down to it: the model is scaled by (camera-to-floor distance / that line's depth), which
    keeps the camera height the distance from the cameras to the floor. ``residuals``:
    ``floor_lowered_by`` (the factor, 1 when no line lies below), ``floor_from_line`` (its track).
    """
    up = _floor_normal(relations, prob, manhattan)
    reg = sol.registered
    h = residuals.get("floor_height")
    residuals["floor_lowered_by"] = 1.0
    if up is None or h is None or not np.any(reg):
        return sol
    cam = float(np.mean(sol.centers[reg] @ up))
    d_floor = cam - float(h)
    n_obs = np.bincount(prob.obs_track, minlength=len(sol.lines.valid))
    ok = sol.lines.valid & (np.abs(sol.lines.direction @ up) < 0.5) & (n_obs >= min_obs)
    ok &= np.all(np.isfinite(sol.lines.taylor), axis=1)
    if not np.any(ok) or d_floor <= 0:
        return sol
    depth = cam - sol.lines.taylor[ok] @ up
    k = int(np.argmax(depth))
    if depth[k] <= d_floor:
        return sol
    f = d_floor / float(depth[k])
    residuals["floor_lowered_by"] = float(1.0 / f)
    residuals["floor_from_line"] = int(np.flatnonzero(ok)[k])
    residuals["floor_height"] = float(cam * f - d_floor)
    return _scaled(sol, f)


def _floor_normal(relations: Relations, prob: _Problem, manhattan: np.ndarray) -> np.ndarray | None:
    """Returns the floor relations' (majority) normal, the up direction, or None without floor relations."""
    fl = prob.rel_idx[relations.kind[prob.rel_idx] == FLOOR]
    return manhattan[int(np.bincount(relations.normal_axis[fl].astype(int)).argmax())] if len(fl) else None


def _scaled(sol: Solution, s: float) -> Solution:
    """Returns ``sol`` with centres and lines scaled by ``s`` about the origin (a change of the scale gauge)."""
    lines = dataclasses.replace(sol.lines, taylor=sol.lines.taylor * s, extent=sol.lines.extent * s)
    return dataclasses.replace(sol, centers=sol.centers * s, lines=lines)
