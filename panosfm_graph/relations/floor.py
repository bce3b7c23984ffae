"""Floor coplanarity: horizontal segments inside the floor region (paper §3.2).

Floor pixels have normals within ``floor_normal_deg`` (25°) of the vertical
(Manhattan axis 2, up) and look below the horizon; the mask is dilated once;
horizontal segments (labels 0/1) fully inside are on the floor. Floor
relations on furniture tops are dropped later, by the linear solve
(``linear.floor_verified``), and with the floor-contact option by
:func:`~panosfm_graph.relations.floor_contacts.hanging_verticals`.
"""
from __future__ import annotations

import cv2
import numpy as np

from ..config import RelationsConfig
from ..data import Camera, NormalMaps, Preprocessed

FLOOR_SAMPLES = 9  # points tested along a segment for "fully inside the floor region"


def floor_masks(
    pre: Preprocessed, normals: NormalMaps, camera: Camera, config: RelationsConfig, lowest_only: bool = True
) -> np.ndarray:
    """Returns (F, h, w) bool floor regions (paper §3.2, floor coplanarity).

    Pixels whose normal is within ``floor_normal_deg`` of the vertical
    Manhattan direction (up) and whose viewing ray points below the horizon,
    dilated once with a 3 x 3 kernel. With ``lowest_only`` (a deviation from
    the paper, for precision) a pixel must also be reached from the image's
    bottom row, column-wise, without crossing a valid non-horizontal normal:
    the floor is the lowest horizontal surface, so the tops of furniture seen
    above their front faces are not taken for floor.
    """
    from ..normals import lowres_rays

    F, h, w = normals.valid.shape
    up = pre.manhattan.directions[2] * (1.0 if pre.manhattan.directions[2, 2] >= 0 else -1.0)
    rays = lowres_rays(camera, h, w, normals.scale).reshape(-1, 3)
    cos_max = np.cos(np.radians(config.floor_normal_deg))
    kernel = np.ones((3, 3), np.uint8)
    out = np.zeros((F, h, w), bool)
    for f in range(F):
        below = ((rays @ (pre.R_wc[f].T @ up)) < 0).reshape(h, w)  # ray_w . up = ray_c . (R_wc^T up)
        n_up = (normals.maps[f].reshape(-1, 3).astype(np.float32) @ up).reshape(h, w)
        valid = normals.valid[f]
        up_n = valid & (n_up > cos_max)
        if lowest_only:
            # from the bottom row upwards, stop at the first pixel of a non-horizontal surface
            blocked = valid & ~up_n
            reach = np.cumprod(~blocked[::-1], axis=0)[::-1].astype(bool)
            up_n &= reach
        m = (below & up_n).astype(np.uint8)
        out[f] = cv2.dilate(m, kernel, iterations=1) > 0
    return out


def on_mask(mask: np.ndarray, frame: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Returns (n, ...) bool: whether points ``X`` (n, ..., 2) in mask pixels of frames ``frame`` (n,) are set in ``mask`` (F, h, w).

    Points outside the image are not.
    """
    F, h, w = mask.shape
    xi = np.rint(X[..., 0]).astype(np.int64)
    yi = np.rint(X[..., 1]).astype(np.int64)
    inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
    ff = np.broadcast_to(np.asarray(frame, np.int64).reshape((-1,) + (1,) * (X.ndim - 2)), xi.shape)
    return inside & mask[ff, np.clip(yi, 0, h - 1), np.clip(xi, 0, w - 1)]


def inside_floor(mask: np.ndarray, frame: np.ndarray, ep: np.ndarray, segs: np.ndarray, scale: float) -> np.ndarray:
    """Returns the segments of ``segs`` fully inside the floor region ``mask`` (paper §3.2, floor coplanarity).

    ``FLOOR_SAMPLES`` points along each segment (endpoints ``ep`` in image
    pixels, ``scale`` to normal-map pixels) must all be set in ``mask``.
    """
    t = np.linspace(0.0, 1.0, FLOOR_SAMPLES)[None, :, None]
    e = ep[segs] * scale
    X = e[:, None, :2] * (1.0 - t) + e[:, None, 2:] * t  # (N, K, 2)
    return segs[on_mask(mask, frame[segs], X).all(axis=1)]
