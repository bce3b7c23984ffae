"""The spin style (our addition): a capture solved hand-held, and again as a steady spin where that registers more.

:func:`steady_or_hand_held` runs the steady style's linear solve and bundle adjustment where the
hand-held one left frames unregistered, and keeps it where its centres lie on one circle.
"""
from __future__ import annotations

import dataclasses
import logging
import time

from ..config import SPIN_STYLES, GraphConfig, LinearConfig
from ..data import Camera, Preprocessed, Relations, Solution, Tracks
from ..linear import solve_linear
from .solve import bundle_adjust

log = logging.getLogger("panosfm.graph")


def steady_tried(hand_held: Solution, config: GraphConfig) -> bool:
    """Returns whether :func:`steady_or_hand_held` solves ``hand_held``'s capture in the steady style too: the auto
    style on (``graph.steady_auto``, not set steady) and some frames, not all, registered."""
    reg = hand_held.registered
    return bool(config.steady_auto and not config.spin_position and reg.any() and not reg.all())


def steady_or_hand_held(pre: Preprocessed, tracks: Tracks, relations: Relations, camera: Camera,
                        linear_config: LinearConfig, config: GraphConfig,
                        hand_held: Solution) -> tuple[Solution, Solution | None]:
    """Returns (the steady-spin solution, its linear solve) where the capture was steady, else (``hand_held``, None).

    Our addition. ``config.steady_auto``: where the hand-held solution (``hand_held``, solved with ``linear_config``
    and ``config``) left frames unregistered, the capture is solved again in the steady style
    (``config.SPIN_STYLES['steady']``: one stand point; the frames between two that their lines fix
    placed on its circle) and that solution kept when its centres lie within ``steady_max_rms_arm``
    of one circle (RMS, a share of the arm: :func:`spin_fit`) and it registers more frames. The
    steady style alone (measured, README): ideal circles 97/23/85 -> 100/96/100 % registered, but a
    spin swaying 5 cm put 43 % centre error where 1.2 % was; its centres lay 2.4 % of the arm and
    more off one circle on all 15 swaying captures, 2.2 % and less on 28 of 30 ideal ones.
    ``camera``: the capture's (the linear solve's) camera. ``residuals["spin_style"]`` says which
    result this is; ``residuals["steady_check"]`` what the steady solve gave; a kept steady result
    carries its linear solve's residuals as ``residuals["linear_steady"]`` too (what a cached result keeps).
    """
    res = dict(hand_held.residuals)
    res["spin_style"] = "steady" if config.spin_position else "hand-held"
    reg = hand_held.registered
    if not steady_tried(hand_held, config):
        return dataclasses.replace(hand_held, residuals=res), None
    t0 = time.perf_counter()
    style = SPIN_STYLES["steady"]
    linear = solve_linear(pre, tracks, relations, camera, dataclasses.replace(linear_config, **style["linear"]))
    # the circle test is made here (a rejected steady solve is no result to warn about: _check_steady)
    trial = dataclasses.replace(config, **style["graph"], steady_max_rms_arm=float("inf"))
    steady = bundle_adjust(pre, tracks, relations, linear, trial) if linear.registered.any() else linear
    rms = steady.residuals.get("spin_circle_rms_arm")
    n_steady, n_hand = int(steady.registered.sum()), int(reg.sum())
    kept = rms is not None and rms <= config.steady_max_rms_arm and n_steady > n_hand
    check = {"rms_arm": rms, "max_rms_arm": config.steady_max_rms_arm, "registered": n_steady,
             "registered_hand_held": n_hand, "kept": bool(kept), "seconds": round(time.perf_counter() - t0, 3)}
    log.info("auto spin style: steady solve registers %d frames (hand-held %d), centres %s of the arm off one "
             "circle (at most %.1f %%): %s", n_steady, n_hand, "n/a" if rms is None else f"{100 * rms:.1f} %",
             100 * config.steady_max_rms_arm, "steady kept" if kept else "hand-held kept")
    if not kept:
        res["steady_check"] = check
        return dataclasses.replace(hand_held, residuals=res), None
    out = dict(steady.residuals)
    out.update(spin_style="steady (auto)", steady_check=check, linear_steady=dict(linear.residuals),
               # the frames only the steady style registers sit on its circle, not where lines put them
               frame_source=["lines" if h else ("steady circle" if st else None)
                             for h, st in zip(reg, steady.registered)])
    return dataclasses.replace(steady, residuals=out), linear
