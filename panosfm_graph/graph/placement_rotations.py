"""The rotations of the frames the point tracks place (our addition; issues #40, #63): each frame the motion model
places (:mod:`.motion_model`) gets a rotation variable, tied to its neighbours' by the refined rotations' relative
rotation (``points.relative_sigma_deg``), the line-fixed frames' held as anchors (``points.anchor_sigma_deg``); a
frame whose horizontal lines fix its heading (:func:`heading_by_lines`) may be held to its vanishing-point rotation
(:func:`.motion_model._held_to_vanishing_points`).
"""
from __future__ import annotations

import gtsam
import numpy as np

import factors

from ..config import PointsConfig
from ..data import Preprocessed
from ..lines.manhattan import horizontal_counts
from .problem import rotation_key


def heading_by_lines(pre: Preprocessed, F: int, min_horizontal: int) -> np.ndarray:
    """Returns (F,) whether each frame shows at least ``min_horizontal`` horizontal Manhattan segments: its vanishing
    points fix its heading, not only the IMU's relative rotations from its neighbours."""
    labels = getattr(pre, "labels", None)
    if labels is None or not len(labels):
        return np.zeros(F, bool)
    return horizontal_counts(pre.segments, labels, F) >= min_horizontal


def add_rotations(graph, values, fixed: np.ndarray, todo: np.ndarray, R: np.ndarray, R_refined: np.ndarray,
                  config: PointsConfig) -> None:
    """Adds every frame's rotation as a variable: the line-fixed ones (``fixed``) anchored within
    ``points.anchor_sigma_deg``, each frame to place (``todo``) tied to its neighbours by the refined rotations'
    relative rotation (std ``points.relative_sigma_deg``; a shared heading-drift slope in these priors was tried and
    dropped: docs/decisions.md#a-drift-slope-in-the-placement)."""
    hold = gtsam.noiseModel.Isotropic.Sigma(3, np.deg2rad(config.anchor_sigma_deg))
    rel = gtsam.noiseModel.Isotropic.Sigma(3, np.deg2rad(config.relative_sigma_deg))
    for i in fixed:
        values.insert(rotation_key(int(i)), gtsam.Rot3(R[i]))
        graph.add(gtsam.PriorFactorRot3(rotation_key(int(i)), gtsam.Rot3(R[i]), hold))
    for i in todo:
        values.insert(rotation_key(int(i)), gtsam.Rot3(R[i]))
    known = np.zeros(len(R), bool)
    known[np.concatenate([fixed, todo])] = True
    pairs = {(a, a + 1) for i in todo for a in (i - 1, i) if a >= 0 and a + 1 < len(R) and known[a] and known[a + 1]}
    for a, b in sorted(pairs):
        graph.add(factors.imu_rotation_factor(rotation_key(a), rotation_key(b), R_refined[a], R_refined[b], rel))
