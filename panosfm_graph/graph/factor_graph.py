"""The factor graph of one bundle-adjustment phase (paper §3.4): :func:`_build_graph`.

Line reprojection, colinearity, coplanarity and floor relations, the rotation prior, the IMU
relative rotations, the spin prior, the gauge priors (first centre, scale) and, in phase 3, the
focal length's prior; each switched by :class:`~panosfm_graph.config.GraphConfig` (the factors and
their sigmas are described in the package docstring).
"""
from __future__ import annotations

import gtsam
import numpy as np

import factors

from ..config import GraphConfig
from ..data import FLOOR, Preprocessed, Relations
from .problem import (ARM_KEY, DRIFT_KEY, FLOOR_KEY, FOCAL_KEY, _Problem, _relation_sigma, center_key, line_key,
                      relation_sigmas, rotation_key, stand_key)

CHUNK_OBS = 8  # observations per reprojection factor (bounds the zero blocks of stacked Jacobians)
GAUGE_SIGMA = 1e-4  # m: priors fixing the first centre and the scale
FOCAL_PRIOR_FRAC = 0.1  # phase 3: weak prior on the focal length, sigma = this * calibrated focal


def widened_robust_k(config: GraphConfig, k: float, rms_initial_px: float) -> float:
    """Returns the reprojection kernel's threshold (sigmas) of a first solve: ``k`` widened to
    ``reprojection_robust_widen`` times the initial RMS residual, at most ``reprojection_robust_k_max``."""
    wide = config.reprojection_robust_widen * rms_initial_px / config.reprojection_sigma_px
    if not np.isfinite(wide):
        return k
    return float(np.clip(wide, k, max(k, config.reprojection_robust_k_max)))


def reprojection_kernel(config: GraphConfig, phase: int, rms_initial_px: float = 0.0) -> tuple[str, float]:
    """Returns (kernel, threshold in sigmas) of the line reprojection terms in BA ``phase`` (1-3): the phase's
    ``reprojection_robust_k``, graduated in phase 1 (:func:`widened_robust_k`); "none" where the threshold is 0."""
    ks = tuple(config.reprojection_robust_k) or (0.0,)
    k = float(ks[min(phase, len(ks)) - 1])
    if phase == 1 and k > 0:  # graduated: at first as wide as the initial residuals
        k = widened_robust_k(config, k, rms_initial_px)
    return (config.reprojection_robust if k > 0 else "none"), k


def _build_graph(pre: Preprocessed, relations: Relations, prob: _Problem, phase: int, R_fixed: np.ndarray,
                 K: np.ndarray, rel_mask: np.ndarray, config: GraphConfig, gauge: dict,
                 batched: bool = False) -> tuple[gtsam.NonlinearFactorGraph, dict, list]:
    """Returns (graph, factor counts by type, batches) for one phase (relations of ``prob.rel_idx[rel_mask]``).

    With ``batched`` the line reprojection terms come as a
    :class:`factors.LineReprojectionSet` in ``batches`` (for
    :func:`levenberg_marquardt`, which linearises them in one vectorised call)
    instead of as CustomFactors in the graph, also when the focal length is a
    variable (phase 3; the set then linearises its column as cross-term
    HessianFactors), and the spin prior as a :class:`factors.SpinPriorSet`;
    ``counts["reprojection"]`` is the number of CustomFactors the terms make
    without ``batched``, either way.
    """
    graph = gtsam.NonlinearFactorGraph()
    counts = {"reprojection": 0, "colinearity": 0, "orthogonal": 0, "parallel": 0, "junction": 0, "floor": 0,
              "imu": 0, "rotation_prior": 0, "prior": 0, "spin": 0}
    ep = pre.segments.endpoints.astype(np.float64)
    rel_sigma = _relation_sigma(config)
    batches = []
    rep_robust, rep_k = reprojection_kernel(config, phase, gauge.get("reprojection_rms_initial", 0.0))
    if config.reprojection and len(prob.obs_seg):
        fr = prob.obs_frame
        with_focal = phase >= 3 and gauge.get("focal_free", True)
        rep = factors.LineReprojectionSet(
            [line_key(t) for t in prob.obs_track], [center_key(i) for i in fr], ep[prob.obs_seg],
            prob.directions[prob.obs_track], K, config.reprojection_sigma_px,
            rotation_keys=[rotation_key(i) for i in fr] if phase >= 2 else None,
            R_wc_fixed=R_fixed[fr] if phase < 2 else None, robust=rep_robust, k=rep_k,
            focal_key=FOCAL_KEY if with_focal else None)
        if batched:
            batches.append(rep)
        else:
            for f in rep.factors(CHUNK_OBS):  # on the focal too when the set has it
                graph.add(f)
        counts["reprojection"] = len(rep.runs(CHUNK_OBS))
    if config.colinearity:
        for t in prob.lines:
            graph.add(factors.colinearity_factor_builtin(line_key(t), prob.directions[t], rel_sigma))
        counts["colinearity"] = len(prob.lines)
    dirs = pre.manhattan.directions
    sig = relation_sigmas(relations, config)
    for r in prob.rel_idx[rel_mask]:
        kind = int(relations.kind[r])
        normal = dirs[int(relations.normal_axis[r])]
        if kind == FLOOR:
            graph.add(factors.floor_factor(line_key(relations.track_a[r]), FLOOR_KEY, normal,
                                           factors.noise_model(1, sig[r], config.robust, config.robust_k)))
        else:
            graph.add(factors.coplanarity_factor_builtin(line_key(relations.track_a[r]), line_key(relations.track_b[r]),
                                                         normal, sig[r], config.robust, config.robust_k))
        counts[("orthogonal", "parallel", "junction", "floor")[kind]] += 1
    if phase >= 2 and config.rotation_prior_sigma_deg > 0 and "R_prior" in gauge:
        noise = gtsam.noiseModel.Isotropic.Sigma(3, float(np.radians(config.rotation_prior_sigma_deg)))
        tau = gauge.get("drift_tau")  # with a drift slope (heading_drift_sigma_deg): factors.drift_prior_factor
        up = pre.manhattan.directions[2]
        for i in prob.rot_frames:
            if tau is None:
                graph.add(gtsam.PriorFactorRot3(rotation_key(i), gauge["R_prior"][i], noise))
            else:
                graph.add(factors.drift_prior_factor(rotation_key(i), DRIFT_KEY, gauge["R_prior"][i].matrix(), up,
                                                     tau[i], noise))
            counts["rotation_prior"] += 1
        if tau is not None:
            graph.add(gtsam.PriorFactorVector(DRIFT_KEY, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(
                1, float(np.radians(config.heading_drift_sigma_deg)))))
            counts["prior"] += 1
    if phase >= 2 and config.imu_prior and len(prob.rot_frames) > 1:
        fr = prob.rot_frames
        for i, j in zip(fr[:-1], fr[1:]):
            noise = factors.imu_noise(config.imu_sigma_deg * np.sqrt(j - i))
            graph.add(factors.imu_rotation_factor(rotation_key(i), rotation_key(j), pre.R_wc_imu[i], pre.R_wc_imu[j], noise))
            counts["imu"] += 1
    if "spin" in gauge:
        M = pre.manhattan.directions
        noise = factors.spin_noise(config.spin_sigma_m, config.spin_sigma_m * config.spin_vertical_ratio,
                                   config.spin_robust, config.robust_k)
        j, alpha, n_knots = gauge["spin"]
        knots = [(stand_key(jj), stand_key(min(jj + 1, n_knots - 1))) for jj in j]
        if batched:  # one vectorised term (factors.SpinPriorSet): the same cost and linearisation
            batches.append(factors.SpinPriorSet(
                [center_key(i) for i in prob.frames], knots, alpha, ARM_KEY, M, R_fixed[prob.frames][:, :, 2],
                config.spin_sigma_m, config.spin_sigma_m * config.spin_vertical_ratio, config.spin_robust,
                config.robust_k))
        else:
            for i, kk, al in zip(prob.frames, knots, alpha):
                graph.add(factors.spin_prior_factor(center_key(i), kk, al, ARM_KEY, M, R_fixed[i][:, 2], noise))
        walk = gtsam.noiseModel.Isotropic.Sigma(3, config.spin_walk_sigma_m)
        for jj in range(n_knots - 1):
            graph.add(gtsam.BetweenFactorPoint3(stand_key(jj), stand_key(jj + 1), np.zeros(3), walk))
        counts["spin"] = len(prob.frames)
    tight = lambda d: gtsam.noiseModel.Isotropic.Sigma(d, GAUGE_SIGMA)  # noqa: E731
    if "held_centers" in gauge:  # the poses held (adjust_lines_at_poses): each centre fixes the gauge, the floor free
        for i in prob.frames:
            graph.add(gtsam.PriorFactorPoint3(center_key(i), gauge["held_centers"][i], tight(3)))
        counts["prior"] += len(prob.frames)
        return graph, counts, batches
    # gauge: first centre, scale
    graph.add(gtsam.PriorFactorPoint3(center_key(gauge["first"]), gauge["first_center"], tight(3)))
    counts["prior"] += 1
    if gauge["use_floor"] and not config.scale_line_gauge:
        graph.add(gtsam.PriorFactorVector(FLOOR_KEY, np.array([gauge["floor_h"]]), tight(1)))
    else:
        graph.add(factors.plane_offset_factor(line_key(gauge["scale_line"]), center_key(gauge["first"]),
                                              gauge["scale_normal"], gauge["scale_offset"], tight(1)))
    counts["prior"] += 1
    if phase >= 3 and gauge.get("focal_free", True):
        graph.add(gtsam.PriorFactorVector(FOCAL_KEY, np.array([K[0, 0]]),
                                          gtsam.noiseModel.Isotropic.Sigma(1, FOCAL_PRIOR_FRAC * K[0, 0])))
        counts["prior"] += 1
    return graph, counts, batches
