"""The ``orientation-map`` normal source: geometric normals from Manhattan line segments, no learning.

Lee, Hebert & Kanade, *Geometric Reasoning for Single Image Structure
Recovery* (CVPR 2009), the "orientation map": a segment of Manhattan
direction ``a`` swept (in 3D: translated) along direction ``b`` covers a
region of the image that may belong to a plane spanned by ``a`` and ``b``,
whose normal is the third direction ``c``. In the image the sweep moves the
segment's points towards (and away from) ``b``'s vanishing point and stops
at the first segment of direction ``c`` it meets (a ``c`` line bounds every
plane of normal ``c``). A pixel swept both by ``a`` lines along ``b`` and by
``b`` lines along ``a`` gets normal ``c``; pixels supported by exactly one
normal direction keep it, all others are invalid.

Vectorised per frame: the stopping distances for all segments of one
direction against all blocking segments are one numpy broadcast; each swept
quad is one ``cv2.fillConvexPoly`` into a per-(a, b) mask at the normal map's
low resolution. This is the fallback source when no model is usable.

Beyond Lee et al., the maps of neighbouring frames are fused
(:meth:`OrientationMapNormals.fused_orientation`, ``NormalsConfig.fuse_deg``):
a spin sees every direction in dozens of frames, so a majority vote over
the frames within 10 degrees raises the labelled share of the pixels
(living, 300 frames: coverage 0.50 -> 0.62, 90 -> 88 % of them within 20
degrees of the truth) and end-to-end accuracy (README, benchmark).
"""
from __future__ import annotations

import cv2
import numpy as np

from ..data import Capture, Preprocessed
from ..lines.tracking import median_step_deg
from . import NormalSource, lowres_rays

_SHIFT = 4  # fixed-point bits for cv2.fillConvexPoly (1/16 pixel)


def _cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _first_hit(P: np.ndarray, d: np.ndarray, C: np.ndarray, min_dist_px: float) -> np.ndarray:
    """Returns (n, S) the distance along rays ``P + lam d`` (unit d) to the first of the segments ``C`` (m, 4); inf if none."""
    if len(C) == 0:
        return np.full(P.shape[:2], np.inf)
    q = C[:, :2]
    e = C[:, 2:] - C[:, :2]
    den = _cross2(d[:, :, None, :], e[None, None])  # (n, S, m)
    qp = q[None, None] - P[:, :, None, :]  # (n, S, m, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = _cross2(qp, e[None, None]) / den
        mu = _cross2(qp, d[:, :, None, :]) / den
    ok = (np.abs(den) > 1e-9) & (lam > min_dist_px) & (mu >= 0.0) & (mu <= 1.0)
    return np.where(ok, lam, np.inf).min(axis=2)


def orientation_map(
    endpoints: np.ndarray,
    labels: np.ndarray,
    vanishing_points: np.ndarray,
    h: int,
    w: int,
    samples: int = 5,
    min_block_px: float = 1.0,
) -> np.ndarray:
    """Returns an (h, w) int8 orientation map: the Manhattan axis of each pixel's plane normal, -1 where unknown.

    Lee et al. 2009 line sweeping. ``endpoints`` (N, 4) and the homogeneous
    ``vanishing_points`` (3, 3) (row k: image of Manhattan direction k) are in
    the map's pixels; ``labels`` (N,) are Manhattan axes (-1 ignored).
    ``samples`` points per segment test where its sweep is blocked.
    """
    ep = np.asarray(endpoints, dtype=np.float64)
    labels = np.asarray(labels)
    swept = np.zeros((3, 3, h, w), dtype=np.uint8)  # [a, b]: a lines swept along b
    far = 2.0 * float(np.hypot(h, w))
    t = np.linspace(0.05, 0.95, samples)
    for a in range(3):
        A = ep[labels == a]
        if len(A) == 0:
            continue
        P = A[:, None, :2] * (1.0 - t)[None, :, None] + A[:, None, 2:] * t[None, :, None]  # (n, S, 2)
        ends = np.stack([A[:, :2], A[:, 2:]], axis=1)  # (n, 2, 2)
        for b in range(3):
            if b == a:
                continue
            C = ep[labels == 3 - a - b]
            vp = vanishing_points[b]
            finite = abs(vp[2]) > 1e-9 * max(1.0, float(np.abs(vp[:2]).max()))
            for side in (1.0, -1.0):
                # direction towards the vanishing point at each sample and at both endpoints
                dirs = []
                for X in (P, ends):
                    D = side * (vp[:2][None, None] - X * vp[2])
                    D /= np.maximum(np.linalg.norm(D, axis=-1, keepdims=True), 1e-12)
                    dirs.append(D)
                dP, dE = dirs
                lam = _first_hit(P, dP, C, min_block_px)
                if finite:  # a sweep towards a finite vanishing point stops there
                    to_vp = vp[:2] / vp[2] - P
                    towards = np.sum(to_vp * dP, axis=-1) > 0
                    lam = np.where(towards, np.minimum(lam, np.linalg.norm(to_vp, axis=-1)), lam)
                lam = np.minimum(lam.min(axis=1), far)  # the whole segment stops at its first block
                quads = np.stack(
                    [ends[:, 0], ends[:, 1], ends[:, 1] + lam[:, None] * dE[:, 1], ends[:, 0] + lam[:, None] * dE[:, 0]],
                    axis=1,
                )
                quads = np.round(quads * (1 << _SHIFT)).astype(np.int32)
                mask = swept[a, b]
                for q in quads:
                    cv2.fillConvexPoly(mask, q, 1, lineType=cv2.LINE_8, shift=_SHIFT)
    votes = np.zeros((3, h, w), dtype=bool)
    for c in range(3):
        a, b = [k for k in range(3) if k != c]
        votes[c] = (swept[a, b] > 0) & (swept[b, a] > 0)
    n_votes = votes.sum(axis=0)
    return np.where(n_votes == 1, np.argmax(votes, axis=0), -1).astype(np.int8)


class OrientationMapNormals(NormalSource):
    """Manhattan normals from the orientation map of each frame's labelled segments."""

    name = "orientation-map"

    def prepare(self, capture: Capture, pre: Preprocessed) -> None:
        self._rays = None
        self._orient: dict[int, np.ndarray] = {}  # frame -> (h, w) int8 orientation map
        self._onehot: dict[int, np.ndarray] = {}  # frame -> (h, w, 3) uint8 one-hot of it (fusion)
        self._stride: int | None = None  # every k-th neighbour votes (fuse_step_deg)

    def _orientation(self, capture, pre, f, h, w, scale) -> np.ndarray:
        """Returns frame ``f``'s (h, w) int8 orientation map (Manhattan axis of the normal, -1 unknown), cached."""
        if f not in self._orient:
            sl = pre.segments.of_frame(f)
            ep = pre.segments.endpoints[sl].astype(np.float64) * scale
            K_low = np.diag([scale, scale, 1.0]) @ capture.camera.K
            vps = (pre.manhattan.directions @ pre.R_wc[f]) @ K_low.T
            self._orient[f] = orientation_map(ep, pre.labels[sl], vps, h, w)
        return self._orient[f]

    def fused_orientation(self, capture, pre, f, h, w, scale) -> np.ndarray:
        """Returns frame ``f``'s orientation map fused with its neighbours' (a deviation from Lee et al.).

        The spin sees every direction in dozens of frames; one frame's map is
        bounded by its image border and by the segments it happened to
        detect. The maps of the frames whose optical axes are within
        ``fuse_deg`` are warped into frame ``f`` by the rotation homography
        (the camera's few-centimetre translation is below a low-resolution
        pixel at room depths) and vote per pixel; the winning axis needs
        ``fuse_share`` of the frames that label the pixel. On a spin slower
        than one frame per ``fuse_step_deg`` only every k-th of them votes:
        the work per frame of a 300-frame spin, linear in the frames.
        """
        deg = self.config.fuse_deg
        if deg <= 0:
            return self._orientation(capture, pre, f, h, w, scale)
        axes = pre.R_wc[:, :, 2]
        near = np.flatnonzero(axes @ axes[f] >= np.cos(np.radians(deg)))
        if self._stride is None:
            med = median_step_deg(pre.R_wc)
            step = self.config.fuse_step_deg
            self._stride = max(1, int(round(step / med))) if step > 0 and med > 0 else 1
        near = near[(near - f) % self._stride == 0]  # a slow spin: every k-th frame, f itself among them
        K_low = np.diag([scale, scale, 1.0]) @ capture.camera.K
        K_inv = np.linalg.inv(K_low)
        votes = np.zeros((h, w, 3), np.int16)  # per pixel: frames voting x, y, z
        for g in near:
            H = K_low @ pre.R_wc[f].T @ pre.R_wc[g] @ K_inv  # pixels of g -> pixels of f
            votes += cv2.warpPerspective(self._one_hot(capture, pre, g, h, w, scale), H, (w, h),
                                         flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        labelled = votes.sum(axis=2)
        best = np.argmax(votes, axis=2)
        win = np.take_along_axis(votes, best[..., None], axis=2)[..., 0]
        ok = (labelled > 0) & (win >= self.config.fuse_share * labelled)
        return np.where(ok, best, -1).astype(np.int8)

    def _one_hot(self, capture, pre, g, h, w, scale) -> np.ndarray:
        """Returns frame ``g``'s orientation map as an (h, w, 3) uint8 one-hot image (all 0: unknown), cached."""
        if g not in self._onehot:
            o = self._orientation(capture, pre, g, h, w, scale)
            self._onehot[g] = (o[..., None] == np.arange(3)).astype(np.uint8)
        return self._onehot[g]

    def camera_normals(self, capture, pre, f, h, w, scale):
        """Returns frame ``f``'s camera-frame Manhattan normals (towards the camera) and where the orientation map is known."""
        if self._rays is None:
            self._rays = lowres_rays(capture.camera, h, w, scale)
        orient = self.fused_orientation(capture, pre, f, h, w, scale)
        dirs_c = pre.manhattan.directions @ pre.R_wc[f]  # row k = R_wc^T d_k, camera frame
        valid = orient >= 0
        n = dirs_c[np.maximum(orient, 0)].astype(np.float32)  # (h, w, 3)
        facing = np.sum(n * self._rays, axis=-1)
        n *= -np.sign(np.where(facing == 0, 1.0, facing))[..., None]
        n[~valid] = 0.0
        return n, valid
