"""The spin model (our addition): the circle the phone describes about the person's stand point.

:func:`fit_spin` fits it to camera centres (the spin prior's starting values), :func:`spin_fit` /
:func:`spin_arm_length` measure the arm and how far the centres lie off one circle, and after a
solve :func:`_check_steady` warns where a steady spin was not, and :func:`_check_arm` takes the
scale from the arm where the floor's puts it out of range.
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np

import factors

from ..config import GraphConfig
from ..data import Solution
from ..geometry import turned_degrees
from .scale import _scaled

log = logging.getLogger("panosfm.graph")


def fit_spin(centers: np.ndarray, view_dirs: np.ndarray, manhattan: np.ndarray, j: np.ndarray, alpha: np.ndarray,
             n_knots: int, walk_weight: float = 1.0) -> tuple[np.ndarray, np.ndarray, float]:
    """Returns (stand-point knots (K, 3) world, arm (a, b), RMS): the least-squares spin circle through the centres.

    The rows of :func:`factors.spin_prior.spin_model_rows` (knots ``j``/``alpha``
    from :func:`factors.spin_prior.spin_knots`) with the centres given;
    neighbouring knots are tied with ``walk_weight`` (relative to a centre).
    RMS: the horizontal distance of the centres from the fitted circle.
    """
    M = np.asarray(manhattan, dtype=np.float64)
    cm = (np.asarray(centers, dtype=np.float64) @ M.T).ravel()  # 3 i + k, as the rows' centre index
    kind, centre, cols, vals = factors.spin_model_rows(factors.horizontal_direction(M, view_dirs), j, alpha, n_knots)
    w = np.where(kind == 2, walk_weight, 1.0)
    A = np.zeros((len(kind), 3 * int(n_knots) + 2))
    np.add.at(A, (np.repeat(np.arange(len(kind)), cols.shape[1]), cols.ravel()), (vals * w[:, None]).ravel())
    b = np.where(centre >= 0, cm[np.maximum(centre, 0)], 0.0)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    r = (b - A @ x)[kind == 0]  # two horizontal rows per centre
    rms = float(np.sqrt(2.0 * np.mean(r ** 2))) if len(r) else 0.0
    return x[:3 * n_knots].reshape(-1, 3) @ M, x[3 * n_knots:].copy(), rms


def spin_arm_length(centers: np.ndarray, R_wc: np.ndarray, manhattan: np.ndarray, knot_deg: float,
                    min_turn_deg: float = 0.0) -> float | None:
    """Returns the length of the spin's arm (:func:`fit_spin`) through the finite centres, in their units.

    None with fewer than 3 centres or where they span less than ``min_turn_deg`` of turn (on a short
    arc the arm and the stand point trade off).
    """
    fit = spin_fit(centers, R_wc, manhattan, knot_deg, min_turn_deg)
    return None if fit is None else fit[0]


def spin_fit(centers: np.ndarray, R_wc: np.ndarray, manhattan: np.ndarray, knot_deg: float,
             min_turn_deg: float = 0.0) -> tuple[float, float] | None:
    """Returns (arm length, RMS horizontal distance of the centres from the circle): :func:`fit_spin` on the finite centres.

    None as :func:`spin_arm_length`. With ``knot_deg`` 0 (one stand point) the RMS says how
    steady the spin was (the steady style's BA centres: 0.9-2.6 % of the arm on 29 of the
    project's 30 ideal circles; 2.4 % and more on the 15 spins that sway 5 cm, at the 0.1-degree
    rotation prior).
    """
    ok = np.all(np.isfinite(centers), axis=1) & np.all(np.isfinite(R_wc), axis=(1, 2))
    if ok.sum() < 3:
        return None
    turned = turned_degrees(R_wc[ok])
    if float(np.ptp(turned)) < min_turn_deg:
        return None
    j, alpha, n = factors.spin_knots(turned, knot_deg)
    _, arm, rms = fit_spin(centers[ok], R_wc[ok][:, :, 2], manhattan, j, alpha, n)
    return float(np.hypot(*arm)), rms


def circle_rms_arm(sol: Solution, manhattan: np.ndarray, config: GraphConfig) -> float | None:
    """Returns the RMS horizontal distance of ``sol``'s centres from one circle over its arm (:func:`spin_fit` about
    one stand point; the steady style is kept at most ``graph.steady_max_rms_arm``), None where the spin turned less
    than ``graph.metric_arm_min_turn_deg`` or has no arm."""
    fit = spin_fit(sol.centers, sol.R_wc, manhattan, 0.0, config.metric_arm_min_turn_deg)
    return None if fit is None or fit[0] <= 0 else float(fit[1] / fit[0])


def _check_steady(sol: Solution, manhattan: np.ndarray, config: GraphConfig) -> None:
    """Warns where a run set for a steady spin (``spin_position``) finds the centres off one circle.

    ``residuals["spin_circle_rms_arm"]``: the RMS horizontal distance of the centres from one
    stand point's circle, as a share of the arm (:func:`spin_fit`), on every run that turned far
    enough. Above ``steady_max_rms_arm`` with ``spin_position`` on, the spin was likely hand-held
    (measured: the steady style's worst capture 46 % centre error on spins swaying 5 cm).
    """
    rel = circle_rms_arm(sol, manhattan, config)
    sol.residuals["spin_circle_rms_arm"] = rel
    if config.spin_position and rel is not None and rel > config.steady_max_rms_arm:
        _warn(sol.residuals, f"the camera centres lie {100 * rel:.1f} % of the arm off one circle (a steady spin: "
                             f"under {100 * config.steady_max_rms_arm:.1f} %): the spin looks hand-held; compare "
                             f"with a run without --spin steady")


def _warn(residuals: dict, msg: str) -> None:
    """Logs ``msg`` and adds it to ``residuals["warnings"]`` (the run's summary.json ``warnings``)."""
    log.warning("BA: %s", msg)
    residuals.setdefault("warnings", []).append(msg)


def _check_arm(sol: Solution, manhattan: np.ndarray, config: GraphConfig) -> Solution:
    """Returns ``sol``, rescaled and marked not metric where its metric scale puts the spin's arm out of range.

    Our addition. The metric scale rests on the floor (camera height), and the floor is rarely in
    view (39 degrees of vertical field at 1.5 m see it only beyond 4 m): where only furniture tops
    were taken for it the model came out 1.7-2.3 times too large. The phone's distance from the
    body's axis is known to a few tens of percent (``metric_arm_range_m``); an arm outside that
    range means the floor's scale is wrong, and the arm (``metric_arm_fallback_m``) is the better
    one. Only over ``metric_arm_min_turn_deg`` of turn (not on the early batches of an incremental
    solve). ``residuals``: ``spin_arm_m`` (after any rescale; None on a shorter turn), and
    ``spin_arm_m_from_floor`` with the factor ``scale_from_arm`` when rescaled.
    """
    res = sol.residuals
    arm = spin_arm_length(sol.centers, sol.R_wc, manhattan, config.spin_knot_deg, config.metric_arm_min_turn_deg)
    res["spin_arm_m"] = arm
    lo, hi = config.metric_arm_range_m
    if arm is None or arm <= 0 or not sol.metric or lo <= arm <= hi:
        return sol
    s = config.metric_arm_fallback_m / arm
    _warn(res, f"the metric scale puts the spin's arm at {arm:.2f} m (outside {lo:g}-{hi:g} m): the floor lines "
               f"were likely not the floor; scaled by {s:.3g} so that the arm is {config.metric_arm_fallback_m:g} m, "
               f"scale reported arbitrary")
    res["spin_arm_m_from_floor"] = arm
    res["scale_from_arm"] = float(s)
    res["spin_arm_m"] = float(config.metric_arm_fallback_m)
    if "floor_height" in res:
        res["floor_height"] = float(res["floor_height"]) * s
    return dataclasses.replace(_scaled(sol, s), metric=False)
