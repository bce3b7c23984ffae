"""The optimiser: our own Levenberg-Marquardt loop over a gtsam graph and vectorised batches of terms.

Why our own loop (GTSAM's optimizers are slow with many Python factors) is told in the package
docstring ("Solver").
"""
from __future__ import annotations

import time

import gtsam
import numpy as np


def _dims(values: gtsam.Values) -> list[tuple[int, int]]:
    """Returns (key, tangent dimension) of every variable."""
    out = []
    for k in values.keys():
        ch = chr(gtsam.Symbol(k).chr())
        out.append((k, 1 if ch in "hfd" else 2 if ch == "a" else 3))
    return out


def levenberg_marquardt(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, max_iterations: int = 30,
                        rel_tol: float = 1e-4, lam0: float = 1e-4, batches=()) -> tuple[gtsam.Values, dict]:
    """Returns (optimised values, info) from a Levenberg-Marquardt loop driven from Python.

    Damping ``lam * I`` per variable is added as unit JacobianFactors before
    the sparse multifrontal solve; a step is accepted if it lowers the error;
    an indeterminate linear system (a direction no factor constrains, e.g.
    Lambda along A without colinearity) raises the damping, and the damping
    never goes below the smallest that solved since (measured, 300 frames: every
    other solve had failed so, each at about half a solve's time). ``batches``
    (e.g. :class:`factors.LineReprojectionSet`) are more terms of the cost,
    each with ``error(values)`` and ``linearize(values)``. ``info``:
    cost_before, cost_after, iterations, seconds.
    """
    t0 = time.perf_counter()
    dims = _dims(values)

    def total_error(v):
        return graph.error(v) + sum(b.error(v) for b in batches)

    err0 = err = total_error(values)
    lam = lam0
    lam_floor = 1e-12  # raised above a damping whose system was indeterminate
    it = 0
    unit = {d: gtsam.noiseModel.Unit.Create(d) for d in (1, 2, 3)}
    eyes = {d: np.eye(d) for d in (1, 2, 3)}
    zeros = {d: np.zeros(d) for d in (1, 2, 3)}
    for it in range(1, max_iterations + 1):
        gfg = graph.linearize(values)
        for b in batches:
            gfg.push_back(b.linearize(values))
        accepted = False
        while lam < 1e12:
            damped = gtsam.GaussianFactorGraph()
            damped.push_back(gfg)
            s = np.sqrt(lam)
            for k, d in dims:
                damped.push_back(gtsam.JacobianFactor(k, s * eyes[d], zeros[d], unit[d]))
            try:
                delta = damped.optimize()
            except RuntimeError:  # indeterminate (a null direction, damping too weak): damp more
                lam *= 10.0
                lam_floor = max(lam_floor, lam)
                continue
            cand = values.retract(delta)
            new_err = total_error(cand)
            if np.isfinite(new_err) and new_err <= err:
                accepted = True
                break
            lam *= 10.0
        if not accepted:
            break
        decrease = err - new_err
        values, err = cand, new_err
        lam = max(lam / 10.0, lam_floor)
        if decrease <= rel_tol * max(err, 1e-30) or err < 1e-20:
            break
    return values, {"cost_before": float(err0), "cost_after": float(err), "iterations": it,
                    "seconds": time.perf_counter() - t0}
