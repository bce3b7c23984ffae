"""Gauge and scale of the linear solve (paper §3.3 leaves both open: the constraints fix neither).

* Gauge: the first registered camera's centre is the origin. Scale, in this order:
  floor relations and ``camera_height_m`` -> the floor lies ``camera_height_m`` below the mean
  camera height (metric); floor relations only -> mean camera-to-floor distance = 1; otherwise
  the mean depth = 1 (solved with one depth fixed at 1, then rescaled) -- or*, with the spin model on,
  the spin's arm ``spin_arm_m`` long (about 0.35 m for a phone held out at eye height), so that the bundle
  adjustment's sigmas and determinacy thresholds in metres are about right (measured, the only two of
  45 captures with no floor verified: kept-back bedroom capture 81, 7.4 -> 5.5 % centre error and
  9.2 -> 6.9 px corner reprojection; bedroom capture 1 unchanged but 2 frames fewer registered). The
  arm does not check a metric scale: measured, a distorted linear solve's arm came out 0.06-0.09 m
  where the floor's scale was right (the BA then keeps it). ``min_depth_m`` is applied during the solve
  (with the floor ``camera_height_m`` -- or 1 -- below the FIRST camera, or the reference depth = 1) and
  is thus in approximately those units.

(* marks a deviation from the paper.)
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ..config import LinearConfig
from .robust import Estimate
from .system import VERTICAL, Observations, SystemMembers, Unknowns

log = logging.getLogger("panosfm.linear")


@dataclasses.dataclass(frozen=True, eq=False)
class Gauge:
    """The unknowns the solve fixes: ``fixed_val`` (n_cols,) their values (NaN: free).

    ``h0``: the floor height during the solve (``-camera_height_m``, or -1; 0 without floor
    relations); ``ref_obs``: the observation whose depth is fixed at 1 (-1: none); ``scale_mode``:
    the scale the solution will be normalised to (module docstring).
    """

    use_floor: bool
    h0: float
    scale_mode: str
    fixed_val: np.ndarray
    ref_obs: int


def choose_gauge(unknowns: Unknowns, members: SystemMembers, obs: Observations, config: LinearConfig) -> Gauge:
    """Returns the gauge: the first registered centre at the origin, the floor height or one depth fixed."""
    Fk, frames, u_col = unknowns.n_frames, unknowns.frames, unknowns.u_col
    use_floor = bool(np.any(members.floor))
    H = config.camera_height_m
    if use_floor:
        h0 = -(H if H is not None else 1.0)
        scale_mode = "metric" if H is not None else "camera_to_floor"
    else:
        h0 = 0.0
        scale_mode = "mean_depth"
        if H is not None:
            log.warning("linear: camera_height_m given but no floor relations among registered frames; "
                        "the scale is arbitrary")
    ob = members.obs
    fixed_val = np.full(unknowns.n_cols, np.nan)
    fixed_val[unknowns.col_h] = h0
    if Fk:
        if config.zero_translation:
            fixed_val[:3 * Fk] = 0.0
        else:
            fixed_val[unknowns.tau_col(frames[0], np.arange(3))] = 0.0
    ref_obs = -1
    if not use_floor and len(ob):
        # fix one depth: an observation in the first registered frame of its most observed track
        cand = ob[obs.frame[ob] == obs.frame[ob].min()]
        ref_obs = int(cand[np.argmax(members.n_obs[obs.track[cand]])])
        t0 = obs.track[ref_obs]
        tau0 = np.zeros(3)  # the reference frame's centre is the origin
        for kk, dd in ((obs.k1[ref_obs], obs.d1[ref_obs]), (obs.k2[ref_obs], obs.d2[ref_obs])):
            fixed_val[u_col(np.array([t0]), np.array([kk]))[0]] = tau0[kk] + 1.0 * dd
    return Gauge(use_floor=use_floor, h0=h0, scale_mode=scale_mode, fixed_val=fixed_val, ref_obs=ref_obs)


@dataclasses.dataclass(frozen=True, eq=False)
class Scaled:
    """The solution in its final units: ``x`` (n_cols,) the unknowns, ``depths`` (n,).

    ``factor``: final units per solve units (the depth bound applies in solve units); ``mode``: the
    scale (``metric``, ``camera_to_floor``, ``mean_depth`` or ``spin_arm``).
    """

    x: np.ndarray
    depths: np.ndarray
    factor: float
    mode: str


def normalise_scale(est: Estimate, unknowns: Unknowns, gauge: Gauge, config: LinearConfig) -> Scaled:
    """Returns the solution rescaled to the gauge's scale (module docstring; the spin's arm without a floor)."""
    x, lam, Fk, h0 = est.x, est.depths, unknowns.n_frames, gauge.h0
    H = config.camera_height_m
    scale_mode = gauge.scale_mode
    tau = x[:3 * Fk].reshape(Fk, 3)
    if scale_mode == "metric":
        s = H / (tau[:, VERTICAL].mean() - h0)
    elif scale_mode == "camera_to_floor":
        s = 1.0 / (tau[:, VERTICAL].mean() - h0)
    else:
        s = 1.0 / lam.mean() if len(lam) else 1.0
        if unknowns.use_spin and config.spin_arm_m > 0:
            col_arm = unknowns.col_arm
            arm = float(np.hypot(*x[col_arm:col_arm + 2])) * s  # in mean-depth units
            if np.isfinite(arm) and arm > 0.01:  # a spin at all (1 % of the mean depth): units ~ metres
                s *= config.spin_arm_m / arm
                scale_mode = "spin_arm"
    if not np.isfinite(s) or s <= 0:
        log.warning("linear: degenerate scale (%s); left unnormalised", s)
        s = 1.0
    return Scaled(x=x * s, depths=lam * s, factor=s, mode=scale_mode)
