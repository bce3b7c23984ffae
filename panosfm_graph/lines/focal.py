"""Focal length from the Manhattan vanishing points (our addition; the paper takes a calibrated camera).

A phone video arrives without a focal length. The room's three orthogonal directions fix it: in a frame
that sees two walls, the vanishing points of their horizontal lines satisfy ``(v_x - c) . (v_y - c) = -f^2``
(principal point ``c``), and the IMU's gravity (its tilt does not drift) makes the vertical lines'
convergence say ``f`` too. Rather than pick vanishing points frame by frame, :func:`estimate_focal` scores
each candidate focal length over the whole capture: every frame's rotation is re-fitted to its
Manhattan segments at that focal length (left-perturbation Gauss-Newton from the IMU attitude, the
tilt held to the IMU's gravity by ``gravity_sigma_deg``, the heading free, Huber-weighted), and the cost is
the length-weighted mean of each segment's truncated squared end-point distance (px) from the line through its
mid-point and its vanishing point (angles would favour a long focal length: every interpretation plane then
passes near the direction the camera faces). A wrong focal length bends the interpretation planes in a way no rotation undoes
(lines far from the image centre move more), so the cost has one minimum. The search: a grid of
horizontal fields of view, then a bounded scalar refinement around its best point; the Manhattan frame is
voted at the starting focal length and again at the first estimate (two rounds), its vertical taken from the
IMU's gravity.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation

from ..capture.camera import focal_from_hfov, hfov_deg, with_focal
from ..config import FocalConfig
from ..data import Camera, Segments
from ..geometry import interpretation_normals
from .manhattan import gravity_aligned, manhattan_frame

log = logging.getLogger("panosfm.lines")

UP = np.array([0.0, 0.0, 1.0])  # the IMU's gravity direction (world +z up, capture-format.md)


@dataclass(frozen=True)
class FocalEstimate:
    """The estimated focal length (px, fx = fy) and how well the capture's lines determine it."""

    focal_px: float
    hfov_deg: float
    cost: float  # the capture's Manhattan cost at the estimate (0: every segment on a vanishing direction)
    sharpness: float  # cost at +-5 % focal over the cost at the estimate, the smaller of the two (1: flat)
    frames: int  # frames that took part
    segments: int  # segments that took part


def manhattan_cost(segments: Segments, camera: Camera, R_wc: np.ndarray, directions: np.ndarray, focal_px: float,
                   config: FocalConfig) -> float:
    """Returns the capture's Manhattan cost at ``focal_px``: frames' rotations re-fitted (module docstring)."""
    K = with_focal(camera, focal_px).K
    n_cam = interpretation_normals(K, segments.endpoints.astype(np.float64))
    fr = segments.frame.astype(np.int64)
    F = len(R_wc)
    w_len = segments.lengths.astype(np.float64)
    w_len = w_len / np.mean(w_len)
    R = np.array(R_wc, dtype=np.float64, copy=True)
    tilt_acc = np.zeros((F, 2))  # the accumulated world-frame tilt correction (x, y components), for the prior
    s_g = np.radians(config.gravity_sigma_deg)
    huber = np.sin(np.radians(config.huber_deg))
    label = np.sin(np.radians(90.0 - config.label_angle_deg))
    for _ in range(config.gauss_newton_iterations):
        x = np.einsum("sij,sj->si", R[fr], n_cam)  # world plane normals
        dots = x @ directions.T  # (S, 3)
        k = np.argmin(np.abs(dots), axis=1)
        r = dots[np.arange(len(k)), k]
        use = np.abs(r) < label
        J = np.cross(x, directions[k])  # d r / d delta for R <- Exp(delta) R
        w = w_len * np.where(np.abs(r) <= huber, 1.0, huber / np.maximum(np.abs(r), 1e-12)) * use
        H = np.zeros((F, 3, 3))
        np.add.at(H, fr, w[:, None, None] * J[:, :, None] * J[:, None, :])
        g = np.zeros((F, 3))
        np.add.at(g, fr, (w * r)[:, None] * J)
        H[:, 0, 0] += 1.0 / s_g ** 2
        H[:, 1, 1] += 1.0 / s_g ** 2
        H[:, 2, 2] += 1e-6  # the heading is free (a frame without horizontal lines keeps its own)
        g[:, :2] += tilt_acc / s_g ** 2
        delta = -np.linalg.solve(H, g[:, :, None])[:, :, 0]
        tilt_acc += delta[:, :2]
        R = Rotation.from_rotvec(delta).as_matrix() @ R
    # the cost in pixels (angles favour a long focal length: every plane then passes near the faced direction):
    # each segment's end-point distance from the line joining its mid-point and its vanishing point
    x = np.einsum("sij,sj->si", R[fr], n_cam)
    k = np.argmin(np.abs(x @ directions.T), axis=1)
    vp = np.einsum("ij,sj->si", K, np.einsum("sji,sj->si", R[fr], directions[k]))  # K R^T d, homogeneous
    ep = segments.endpoints.astype(np.float64)
    mid = np.column_stack([0.5 * (ep[:, :2] + ep[:, 2:]), np.ones(len(ep))])
    line = np.cross(mid, vp)
    e = np.abs(line[:, 0] * ep[:, 0] + line[:, 1] * ep[:, 1] + line[:, 2]) / np.maximum(np.hypot(line[:, 0], line[:, 1]), 1e-12)
    t = config.truncate_px
    return float(np.sum(w_len * np.minimum(e, t) ** 2) / np.sum(w_len) / t ** 2)


def _subset(segments: Segments, R_wc: np.ndarray, max_frames: int) -> tuple[Segments, np.ndarray]:
    """Returns the segments and rotations of at most ``max_frames`` evenly spread frames (renumbered)."""
    F = len(R_wc)
    step = max(1, int(np.ceil(F / max_frames)))
    frames = np.arange(0, F, step)
    keep = segments.frame % step == 0
    frame = (segments.frame[keep] // step).astype(segments.frame.dtype)
    sub = Segments(endpoints=segments.endpoints[keep], frame=frame,
                   frame_offsets=np.searchsorted(frame, np.arange(len(frames) + 1)).astype(np.int64),
                   colors=segments.colors[keep],
                   contrast=None if segments.contrast is None else segments.contrast[keep])
    return sub, R_wc[frames]


def estimate_focal(segments: Segments, R_wc_imu: np.ndarray, camera: Camera, config: FocalConfig,
                   manhattan_config) -> FocalEstimate:
    """Returns the focal length that best fits the capture's lines to one Manhattan frame (module docstring).

    ``camera``'s focal length is only the starting point (the Manhattan frame's first vote); the principal
    point is kept. Raises :class:`TooFewLinesError` when the lines cannot vote a Manhattan frame; warns when the
    cost is nearly flat about the estimate (``min_sharpness``).
    """
    seg, R = _subset(segments, np.asarray(R_wc_imu, dtype=np.float64), config.max_frames)
    w = camera.width
    f0 = float(camera.K[0, 0])
    grid = np.arange(config.hfov_min_deg, config.hfov_max_deg + 1e-9, config.hfov_step_deg)
    for _ in range(2):  # the Manhattan frame voted at the starting focal length, then at the first estimate
        # the vertical from the IMU's gravity (a wrong focal length tilts the voted one); the heading of x is
        # immaterial (every frame's heading is re-fitted), only its being horizontal counts
        D = gravity_aligned(manhattan_frame(seg, with_focal(camera, f0).K, R, manhattan_config).directions, UP)
        focals = np.array([focal_from_hfov(h, w) for h in grid])
        costs = np.array([manhattan_cost(seg, camera, R, D, f, config) for f in focals])
        i = int(np.argmin(costs))
        lo, hi = focals[min(i + 1, len(focals) - 1)], focals[max(i - 1, 0)]  # focal falls as the FOV grows
        res = minimize_scalar(lambda lf: manhattan_cost(seg, camera, R, D, float(np.exp(lf)), config),
                              bounds=(np.log(lo), np.log(hi)), method="bounded", options={"xatol": 1e-4})
        f0 = float(np.exp(res.x))
    c0 = manhattan_cost(seg, camera, R, D, f0, config)
    around = [manhattan_cost(seg, camera, R, D, f0 * s, config) for s in (0.95, 1.05)]
    est = FocalEstimate(focal_px=f0, hfov_deg=hfov_deg(f0, w), cost=c0, sharpness=float(min(around) / max(c0, 1e-12)),
                        frames=len(R), segments=seg.n)
    if est.sharpness < config.min_sharpness:
        log.warning("the lines barely determine the focal length (cost %.3fx higher 5 %% off the best %.0f px): give "
                    "it in camera.json if it is known", est.sharpness, f0)
    log.info("focal length from the Manhattan vanishing points: %.1f px (HFOV %.1f deg; cost %.3f, %.2fx at +-5 %%)",
             f0, est.hfov_deg, c0, est.sharpness)
    return est
