"""Reading a :class:`~panosfm_graph.data.Solution` out of the optimised values.

Centres and Taylor vectors from the gtsam values, the lines' extents from their observations
(:func:`line_extents`), the refined focal length into the camera, and the RMS reprojection distance.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import gtsam
import numpy as np

import factors

from ..data import Camera, LineModel, Preprocessed, Solution, Tracks
from ..geometry import closest_on_lines, world_rays
from .problem import _Problem, center_key, line_key


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
