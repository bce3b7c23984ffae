"""The lines adjusted with the poses held (paper §3.4's cost, the cameras fixed; our addition, issue #40).

Where the point tracks place the frames (:mod:`.motion_model`: a bare room, or the points' poses kept over the
line-fixed ones) the lines are first triangulated at those poses one track at a time
(:func:`~.readout.lines_at_poses`), with none of the relations the paper finds between them: a wall's lines 5 m
away from a 0.7 m spin then scatter by centimetres about their plane. :func:`adjust_lines_at_poses` solves the
bundle adjustment's cost over the lines alone: line reprojection at the held rotations and centres, colinearity,
and the coplanarity (orthogonal, parallel, junction, floor) relations the bundle adjustment kept (robust, no
rejection rounds: at held poses a few centimetres' inconsistency between far walls rejected true relations); the
centres are held by tight priors, which also fix the gauge.
"""
from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from ..config import GraphConfig
from ..data import Preprocessed, Relations, Solution, Tracks
from .factor_graph import _build_graph
from .lm import levenberg_marquardt
from .problem import FLOOR_KEY, _select, initial_values
from .readout import _reprojection_rms, _solution
from .scale import _gauge

log = logging.getLogger("panosfm.graph")


def adjust_lines_at_poses(pre: Preprocessed, tracks: Tracks, relations: Relations, sol: Solution,
                          config: GraphConfig) -> Solution:
    """Returns ``sol`` with its valid lines bundle-adjusted at its registered poses, which stay as they are
    (module docstring); ``residuals["lines_held_poses"]``: lines, relations used, the RMS
    reprojection before and after (px) and the seconds. ``sol`` unchanged where it has no line seen twice."""
    t0 = time.perf_counter()
    # no spin prior (the centres are held) and only frames that see a line (_select)
    cfg = dataclasses.replace(config, spin_sigma_m=0.0, spin_position=False)
    prob = _select(pre, tracks, relations, sol, cfg)
    if not len(prob.lines):
        return sol
    values = initial_values(prob, sol)
    gauge = _gauge(relations, prob, sol, pre.manhattan.directions)
    gauge["held_centers"] = sol.centers
    if gauge["use_floor"]:
        values.insert(FLOOR_KEY, np.array([gauge["floor_h"]]))
    K = sol.camera.K
    rms0 = _reprojection_rms(pre, prob, sol.lines.taylor, sol.R_wc, sol.centers, K)
    rel_mask = np.ones(len(prob.rel_idx), bool)  # every relation the bundle adjustment kept (_select): no rounds
    # phase 1's factors (the rotations fixed), solved twice: with the reprojection kernel widened to the lines'
    # initial residuals (the lines the bundle adjustment fitted to other poses start far off), then at its threshold
    for widened in (True, False):
        if widened:
            gauge["reprojection_rms_initial"] = rms0
        else:
            gauge.pop("reprojection_rms_initial", None)
        graph, _, batches = _build_graph(pre, relations, prob, 1, sol.R_wc, K, rel_mask, cfg, gauge, batched=True)
        values, _ = levenberg_marquardt(graph, values, config.max_iterations, batches=batches)
    out = _solution(pre, tracks, sol, prob, values, sol.R_wc, sol.camera, dict(sol.residuals))
    out = dataclasses.replace(out, centers=sol.centers.copy(), registered=sol.registered.copy())
    kept = np.zeros(relations.n, bool)
    kept[prob.rel_idx] = True
    record = {"lines": int(len(prob.lines)), "relations": int(len(prob.rel_idx)),
              "reprojection_rms_px": [rms0, _reprojection_rms(pre, prob, out.lines.taylor, sol.R_wc, sol.centers, K)],
              "seconds": round(time.perf_counter() - t0, 3)}
    out.residuals["lines_held_poses"] = record
    log.info("lines adjusted at the held poses: %d lines, %d relations, RMS reprojection %.3f -> %.3f px (%.2f s)",
             record["lines"], record["relations"], *record["reprojection_rms_px"], record["seconds"])
    return dataclasses.replace(out, relations_kept=kept)
