"""Junction coplanarity: two lines that meet at an L (paper §3.2).

Two segments of different labels whose endpoints are within
``junction_dist_frac * min(w, h)`` are coplanar; the plane normal is the
third direction. Beyond the paper, both must end near their lines'
intersection (an L, not the T of an occluding edge) and the inside of the L
must pass the orthogonal normal test (measured on real pipeline output:
junction precision 0.44-0.65 -> 0.92-0.96 with oracle normals).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .quads import quad_normal_test


def junction_test(pre, normals, i, j, labels, ep, min_side, cfg, dirs, size):
    """Returns the junction candidates (i, j) that meet as an L (paper §3.2 plus two checks of ours).

    The paper's test (endpoints within ``junction_dist_frac``) also accepts
    T-junctions of an occluding edge and lines merely near in the image.
    With ``junction_corner_frac`` both segments must end within that share of
    ``min(w, h)`` of the intersection of their supporting lines (an L, not a
    T); with ``junction_normals`` the quad between them -- the inside of the
    L, which a face bounded by both lines fills -- must pass the orthogonal
    normal test. With ``junction_border_px`` (and the corner test) the ends
    at the corner must lie more than that inside the image ``size`` (w, h):
    where the frame cuts two lines their ends meet, but no corner is seen
    (a nightstand's edge and the wall's foot behind it, both cut by the
    image's bottom row).
    """
    if cfg.junction_corner_frac > 0 and len(i):
        def homog(e):
            return np.cross(np.column_stack([e[:, :2], np.ones(len(e))]), np.column_stack([e[:, 2:], np.ones(len(e))]))

        def corner_end(e):  # (P, 2) each segment's end nearer the corner X
            near0 = np.linalg.norm(e[:, :2] - X, axis=1) <= np.linalg.norm(e[:, 2:] - X, axis=1)
            return np.where(near0[:, None], e[:, :2], e[:, 2:])

        X = np.cross(homog(ep[i]), homog(ep[j]))
        finite = np.abs(X[:, 2]) > 1e-9 * np.maximum(np.abs(X[:, :2]).max(axis=1), 1.0)
        X = X[:, :2] / np.where(finite, X[:, 2], 1.0)[:, None]
        lim = cfg.junction_corner_frac * min_side
        ends = (corner_end(ep[i]), corner_end(ep[j]))
        keep = finite & (np.linalg.norm(ends[0] - X, axis=1) < lim) & (np.linalg.norm(ends[1] - X, axis=1) < lim)
        if cfg.junction_border_px > 0:
            b = cfg.junction_border_px
            for e in ends:
                keep &= (e[:, 0] > b) & (e[:, 0] < size[0] - 1 - b) & (e[:, 1] > b) & (e[:, 1] < size[1] - 1 - b)
        i, j = i[keep], j[keep]
    if cfg.junction_normals and len(i):
        qcfg = dataclasses.replace(cfg, orthogonal=True)
        _, i, j, _ = quad_normal_test(pre, normals, i, j, labels, qcfg, dirs)
    return i, j
