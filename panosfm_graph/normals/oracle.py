"""The ``oracle`` normal source: a capture's ``ground_truth/normals`` (for benchmarks and tests).

The ground truth is camera-frame; the base class rotates it into the world
with the refined rotations, exactly like an estimated map, so the oracle
isolates the relation detector from normal-estimation errors (paper §3.2).
"""
from __future__ import annotations

import numpy as np

from ..data import Capture, Preprocessed
from ..errors import InputError
from . import NormalSource, resize_normals


class OracleNormals(NormalSource):
    """Ground-truth camera-frame normals, area-downsampled to the normal-map width."""

    name = "oracle"

    def prepare(self, capture: Capture, pre: Preprocessed) -> None:
        gt = capture.ground_truth
        if gt is None or not gt.has_normals:
            raise InputError("normals source 'oracle' needs ground_truth/normals/*.npy", capture.root)

    def camera_normals(self, capture, pre, f, h, w, scale):
        """Returns frame ``f``'s ground-truth normals at (h, w) and their validity (depth > 0 where known)."""
        g = capture.ground_truth.normals(f)
        if g is None:
            raise InputError(f"missing ground-truth normals for frame {capture.frame_names[f]}", capture.root)
        n, valid = resize_normals(g, h, w)
        if capture.ground_truth.has_depth:
            import cv2

            d = capture.ground_truth.depth(f)
            if d is not None:
                d = cv2.resize(np.asarray(d, np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
                valid &= d > 0
        n[~valid] = 0.0
        return n, valid
