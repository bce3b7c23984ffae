"""What the observations determine: line and centre stds, the focal's marginal, relations checked against the tracks.

:func:`determinacy` (Gauss-Newton information of each line and centre) decides which lines stay
valid and which frames stay registered (:func:`_mark_undetermined`) and which coplanarities the
tracks contradict (:func:`_verify_relations`, our addition to paper §3.4); :func:`focal_sigma`
decides whether phase 3 refines the focal length (paper §3.4).
"""
from __future__ import annotations

import dataclasses
import logging

import gtsam
import numpy as np

import factors

from ..config import GraphConfig
from ..data import FLOOR, Preprocessed, Relations, Solution
from .factor_graph import _build_graph
from .lm import levenberg_marquardt
from .problem import FLOOR_KEY, FOCAL_KEY, _Problem, center_key, line_key, relation_residuals, relation_sigmas
from .readout import _read_points

log = logging.getLogger("panosfm.graph")


def determinacy(pre: Preprocessed, relations: Relations, prob: _Problem, rel_used: np.ndarray, taylor: np.ndarray,
                R_wc: np.ndarray, centers: np.ndarray, K: np.ndarray, config: GraphConfig,
                floor_h: float = 0.0, center_prior: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Returns (line std (T,) m, centre std (F,) m): how well each line's position and each centre are determined.

    Gauss-Newton information of one variable with all others held: a
    reprojected line moved by delta along the unit normal u of its
    interpretation plane moves by ``f delta / d`` pixels (d: camera-to-line
    distance), so each observation adds ``(f / d / sigma_px)^2 u u^T`` to the
    line's and to the frame centre's 3x3 information; each used relation
    (robust weight at its residual) adds ``n n^T / sigma^2`` to its lines.
    The std is ``1 / sqrt`` of the smallest eigenvalue (for lines, in the plane
    normal to the line's direction: the position along it is not a quantity).
    ``center_prior`` (3, 3), when given, is added to the information of every frame
    of ``prob.frames`` (the spin prior's hold on the height, or on the whole centre
    of a steady spin). Other frames without observations get inf.
    """
    T, F = len(prob.directions), len(centers)
    H_l = np.zeros((T, 3, 3))
    H_c = np.zeros((F, 3, 3))
    if len(prob.obs_seg):
        t, f = prob.obs_track, prob.obs_frame
        w = np.cross(taylor[t] - centers[f], prob.directions[t])
        d = np.linalg.norm(w, axis=1)
        ok = np.isfinite(d) & (d > 1e-9)
        u = w[ok] / d[ok, None]
        g = (K[0, 0] / d[ok] / config.reprojection_sigma_px) ** 2
        outer = g[:, None, None] * u[:, :, None] * u[:, None, :]
        np.add.at(H_l, t[ok], outer)
        np.add.at(H_c, f[ok], outer)
    r = prob.rel_idx[rel_used]
    if len(r):
        sub = relations.subset(r)
        sig = relation_sigmas(sub, config)
        white = np.abs(relation_residuals(sub, pre.manhattan.directions, taylor, floor_h)) / sig
        wgt = factors.robust_weight(white, config.robust, config.robust_k) / sig**2
        n = pre.manhattan.directions[sub.normal_axis.astype(int)]
        outer = wgt[:, None, None] * n[:, :, None] * n[:, None, :]
        np.add.at(H_l, sub.track_a, outer)
        pair = sub.kind != FLOOR
        np.add.at(H_l, sub.track_b[pair], outer[pair])
    A = prob.directions
    e1 = np.cross(A, np.where(np.abs(A[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]]))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    B = np.stack([e1, np.cross(A, e1)], axis=2)  # (T, 3, 2) basis of the plane normal to A
    lam_l = np.linalg.eigvalsh(np.einsum("tia,tij,tjb->tab", B, H_l, B))[:, 0]
    if center_prior is not None:
        seen_f = np.zeros(F, bool)
        seen_f[prob.frames] = True  # every centre variable (a steady spin's also those that see no line: _select)
        H_c[seen_f] += center_prior
    lam_c = np.linalg.eigvalsh(H_c)[:, 0]
    with np.errstate(divide="ignore"):
        return 1.0 / np.sqrt(np.maximum(lam_l, 0.0)), 1.0 / np.sqrt(np.maximum(lam_c, 0.0))


def _mark_undetermined(pre: Preprocessed, relations: Relations, prob: _Problem, rel_mask: np.ndarray, sol: Solution,
                       config: GraphConfig, values: gtsam.Values) -> Solution:
    """Returns ``sol`` with undetermined lines invalid and undetermined frames unregistered (:func:`determinacy`).

    A frame is kept only if its centre was a BA variable and its observations
    of the kept lines determine it within ``max_center_sigma_m``; a line only
    if within ``max_line_sigma_m``. Their counts go to ``residuals``.
    """
    h = values.atVector(FLOOR_KEY)[0] if values.exists(FLOOR_KEY) else 0.0
    seen = prob if config.reprojection else dataclasses.replace(prob, obs_seg=prob.obs_seg[:0],
                                                                 obs_track=prob.obs_track[:0], obs_frame=prob.obs_frame[:0])
    line_sig, _ = determinacy(pre, relations, seen, rel_mask, sol.lines.taylor, sol.R_wc, sol.centers,
                              sol.camera.K, config, h)
    line_ok = np.zeros(len(line_sig), bool)
    line_ok[prob.lines] = line_sig[prob.lines] <= config.max_line_sigma_m
    keep = line_ok[prob.obs_track] & config.reprojection  # without reprojection factors no centre is determined
    sub = dataclasses.replace(prob, obs_seg=prob.obs_seg[keep], obs_track=prob.obs_track[keep],
                              obs_frame=prob.obs_frame[keep])
    prior = None
    if config.spin_sigma_m > 0 and (config.spin_height or config.spin_position):  # the spin prior holds the height
        up = pre.manhattan.directions[2]
        prior = np.outer(up, up) / (config.spin_sigma_m * config.spin_vertical_ratio) ** 2
        if config.spin_position:  # ... and the horizontal position (a steady spin: config.SPIN_STYLES)
            prior = prior + (np.eye(3) - np.outer(up, up)) / config.spin_sigma_m ** 2
    _, center_sig = determinacy(pre, relations, sub, np.zeros(len(rel_mask), bool), sol.lines.taylor, sol.R_wc,
                                sol.centers, sol.camera.K, config, h, center_prior=prior)
    frame_ok = np.zeros(len(center_sig), bool)
    frame_ok[prob.frames] = center_sig[prob.frames] <= config.max_center_sigma_m
    registered = sol.registered & frame_ok
    valid = sol.lines.valid.copy()
    valid[prob.lines] &= line_ok[prob.lines]
    centers = np.where(registered[:, None], sol.centers, np.nan)
    R = np.where(registered[:, None, None], sol.R_wc, np.nan)
    res = dict(sol.residuals)
    res["lines_undetermined"] = int(np.sum(sol.lines.valid[prob.lines] & ~line_ok[prob.lines]))
    res["frames_undetermined"] = int(np.sum(sol.registered & ~registered))
    return dataclasses.replace(sol, registered=registered, centers=centers, R_wc=R,
                               lines=dataclasses.replace(sol.lines, valid=valid), residuals=res)


def _verify_relations(pre: Preprocessed, relations: Relations, prob: _Problem, R_wc: np.ndarray, K: np.ndarray,
                      config: GraphConfig, gauge: dict, values: gtsam.Values,
                      residuals: dict) -> tuple[gtsam.Values, np.ndarray]:
    """Returns (values, relation mask over ``prob.rel_idx``): coplanarities checked against the tracks.

    Our addition to paper §3.4. Phase 1 is solved first without any coplanarity (reprojection
    and colinearity only); a pair coplanarity whose two lines that solve determines
    (:func:`determinacy`) but puts further apart along its normal than ``verify_sigma`` of their
    combined std plus ``verify_tolerance`` of the median camera-to-line distance is dropped
    before the three phases. A false coplanarity (a wall and a sofa
    arm 1.5 m in front of it, with normals alike) is otherwise satisfied by shrinking the camera
    motion that shows their depth difference: parallax is small in a spin, so the shrunken sweep
    costs little reprojection (measured, office capture 2: 0.37 px without coplanarities at
    1.1 % centre error, 0.44 px with them at 20 %). Floor relations and relations of lines the
    tracks alone do not determine are kept. The phases start from that solve when it determines
    at least ``verify_start_share`` of the frames (else from ``values``: with too few frames fixed
    by their tracks alone the relation-free solve wanders, e.g. 40 frames 9 degrees apart).
    """
    mask = np.zeros(len(prob.rel_idx), bool)
    graph, _, batches = _build_graph(pre, relations, prob, 1, R_wc, K, mask, config, gauge, batched=True)
    free, info = levenberg_marquardt(graph, values, config.max_iterations, batches=batches)
    residuals["phases"]["phase1_without_relations"] = info
    taylor = _read_points(free, line_key, prob.lines, np.full((len(prob.directions), 3), np.nan))
    centers = _read_points(free, center_key, prob.frames, np.full((len(R_wc), 3), np.nan))
    line_sig, _ = determinacy(pre, relations, prob, mask, taylor, R_wc, centers, K, config)
    seen = line_sig[prob.obs_track] <= config.max_line_sigma_m  # as _mark_undetermined: determined lines only
    fixed = dataclasses.replace(prob, obs_seg=prob.obs_seg[seen], obs_track=prob.obs_track[seen],
                                obs_frame=prob.obs_frame[seen])
    _, center_sig = determinacy(pre, relations, fixed, mask, taylor, R_wc, centers, K, config)
    share = float(np.mean(center_sig[prob.frames] <= config.max_center_sigma_m)) if len(prob.frames) else 0.0
    residuals["relation_free_share"] = share
    sub = relations.subset(prob.rel_idx)
    pair = sub.kind != FLOOR
    res = np.abs(relation_residuals(sub, pre.manhattan.directions, taylor, 0.0))
    sa = line_sig[sub.track_a]
    sb = np.where(pair, line_sig[np.maximum(sub.track_b, 0)], 0.0)
    known = pair & (sa <= config.max_line_sigma_m) & (sb <= config.max_line_sigma_m)
    t, f = prob.obs_track, prob.obs_frame
    dist = np.linalg.norm(np.cross(taylor[t] - centers[f], prob.directions[t]), axis=1)
    tol = config.verify_tolerance * float(np.nanmedian(dist)) if len(dist) else 0.0
    false = known & (res > config.verify_sigma * np.hypot(sa, sb) + tol)
    log.info("BA: %d of %d coplanarities contradict the tracks' own solve and are dropped (%d checked)",
             int(false.sum()), len(false), int(known.sum()))
    return (free if share >= config.verify_start_share else values), ~false


def focal_sigma(pre: Preprocessed, relations: Relations, prob: _Problem, R_wc: np.ndarray, K: np.ndarray,
                rel_mask: np.ndarray, config: GraphConfig, gauge: dict, values: gtsam.Values) -> float:
    """Returns the marginal std (px) of the focal length in the phase-3 graph at ``values`` (inf if indeterminate).

    The focal is refined (paper §3.4, phase 3) only where the images determine
    it (reprojection, colinearity, IMU and priors; relations are left out: with
    their weight 1e4 they pin it to whatever the possibly wrong structure says): a spin seen by a level camera barely constrains it (the vertical
    vanishing point is at infinity and the focal trades off against the
    rotation angles), and an undetermined focal drifts with the smallest bias
    (measured: 512 -> 520 px, lines 3 cm -> 23 cm from the true surfaces).
    The reprojection terms are taken without their kernel here (information, not fit).
    Weak priors (10 m, 1 rad) on every other variable keep the marginal
    computable when some line is undetermined; they do not change the focal's.
    """
    g = dict(gauge, focal_free=True)
    plain = dataclasses.replace(config, reprojection_robust="none")  # a kernel would make one factor per observation
    graph, _, _ = _build_graph(pre, relations, prob, 3, R_wc, K, np.zeros_like(rel_mask), plain, g)
    weak3 = gtsam.noiseModel.Isotropic.Sigma(3, 10.0)
    weak_r = gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
    for k in values.keys():
        ch = chr(gtsam.Symbol(k).chr())
        if ch in "cl":
            graph.add(gtsam.PriorFactorPoint3(k, values.atPoint3(k), weak3))
        elif ch == "r":
            graph.add(gtsam.PriorFactorRot3(k, values.atRot3(k), weak_r))
    try:
        cov = gtsam.Marginals(graph, values).marginalCovariance(FOCAL_KEY)
    except RuntimeError:
        return float("inf")
    return float(np.sqrt(max(cov[0, 0], 0.0)))
