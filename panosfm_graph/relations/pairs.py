"""Candidate segment pairs for the coplanarity tests (paper §3.2: pairs of line segments in each frame).

Vectorised: the candidates for all frames come from one ``cKDTree`` over
points of the segments (mid-points and/or endpoints; frames kept apart by an
offset), never an all-pairs loop.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def segment_pairs(points: np.ndarray, frame: np.ndarray, owner: np.ndarray, radius: float, span: float) -> np.ndarray:
    """Returns unique (P, 2) owner pairs (i < j) with points of the same frame within ``radius``.

    One ``cKDTree`` for all frames: each frame's points are shifted along x by
    ``frame * span`` (``span`` exceeds the image size plus the radius).
    """
    if len(points) < 2:
        return np.zeros((0, 2), np.int64)
    X = np.column_stack([points[:, 0] + frame * span, points[:, 1]])
    pp = cKDTree(X).query_pairs(radius, output_type="ndarray")
    if len(pp) == 0:
        return np.zeros((0, 2), np.int64)
    a, b = owner[pp[:, 0]], owner[pp[:, 1]]
    keep = a != b
    pairs = np.column_stack([np.minimum(a, b), np.maximum(a, b)])[keep]
    return np.unique(pairs, axis=0)
