"""Line segment detection (paper §3.1 'Line segment detection'): LSD, merging, length filter."""
from __future__ import annotations

import logging
import os
from collections import deque

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..config import Config, DetectConfig
from ..data import Capture, Segments
from ..parallel import process_pool
from ..progress import progress
from ..thumbnails import jpeg_thumbnail

log = logging.getLogger("panosfm.lines")

_COLOR_SAMPLES = 16  # points sampled along a segment for its mean colour


def _detect_config(config: Config | DetectConfig) -> DetectConfig:
    return config.detect if isinstance(config, Config) else config


def merge_segments(
    endpoints: np.ndarray, angle_deg: float, dist_px: float, offset_px: float
) -> np.ndarray:
    """Returns (M, 4) segments after merging neighbouring colinear ones (paper §3.1, after Tavares 1995).

    Two segments are neighbours when two of their endpoints are closer than
    ``dist_px``, their directions differ by less than ``angle_deg`` and each
    of those two endpoints lies within ``offset_px`` of the other segment's
    line. Neighbours are chained (connected components); a merged segment
    is the length-weighted fitted line clipped to the extreme projections of
    its members' endpoints. Vectorised: cKDTree on endpoints.
    """
    e = np.asarray(endpoints, dtype=np.float64).reshape(-1, 4)
    n = len(e)
    if n < 2:
        return e.astype(np.float32)
    d = e[:, 2:] - e[:, :2]
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    u = d / length[:, None]
    theta = np.arctan2(u[:, 1], u[:, 0]) % np.pi
    pts = np.concatenate([e[:, :2], e[:, 2:]])  # endpoint k belongs to segment k % n
    pairs = cKDTree(pts).query_pairs(dist_px, output_type="ndarray")
    if len(pairs):
        a, b = pairs[:, 0], pairs[:, 1]
        sa, sb = a % n, b % n
        keep = sa != sb
        a, b, sa, sb = a[keep], b[keep], sa[keep], sb[keep]
        dth = np.abs(theta[sa] - theta[sb])
        dth = np.minimum(dth, np.pi - dth)
        # perpendicular offset of each close endpoint from the other segment's line
        nrm_a = np.stack([-u[sa, 1], u[sa, 0]], axis=1)
        nrm_b = np.stack([-u[sb, 1], u[sb, 0]], axis=1)
        off_b = np.abs(np.sum((pts[b] - e[sa, :2]) * nrm_a, axis=1))
        off_a = np.abs(np.sum((pts[a] - e[sb, :2]) * nrm_b, axis=1))
        ok = (dth < np.radians(angle_deg)) & (np.maximum(off_a, off_b) < offset_px)
        sa, sb = sa[ok], sb[ok]
    else:
        sa = sb = np.zeros(0, dtype=np.int64)
    if len(sa) == 0:
        return e.astype(np.float32)
    graph = coo_matrix((np.ones(len(sa)), (sa, sb)), shape=(n, n))
    n_comp, comp = connected_components(graph, directed=False)
    # length-weighted mean direction per component (sign-free: doubled angles)
    w = length
    c2 = np.bincount(comp, w * np.cos(2 * theta), n_comp)
    s2 = np.bincount(comp, w * np.sin(2 * theta), n_comp)
    phi = 0.5 * np.arctan2(s2, c2)
    dirs = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    wsum = np.bincount(comp, w, n_comp)
    mid = 0.5 * (e[:, :2] + e[:, 2:])
    centroid = np.stack(
        [np.bincount(comp, w * mid[:, 0], n_comp), np.bincount(comp, w * mid[:, 1], n_comp)], axis=1
    ) / wsum[:, None]
    comp2 = np.concatenate([comp, comp])
    t = np.sum((pts - centroid[comp2]) * dirs[comp2], axis=1)
    t_min = np.full(n_comp, np.inf)
    t_max = np.full(n_comp, -np.inf)
    np.minimum.at(t_min, comp2, t)
    np.maximum.at(t_max, comp2, t)
    p0 = centroid + t_min[:, None] * dirs
    p1 = centroid + t_max[:, None] * dirs
    return np.concatenate([p0, p1], axis=1).astype(np.float32)


def segment_colors(image: np.ndarray, endpoints: np.ndarray) -> np.ndarray:
    """Returns (N, 3) uint8 mean BGR colour sampled along each segment (for the quarter view)."""
    if len(endpoints) == 0:
        return np.zeros((0, 3), np.uint8)
    t = np.linspace(0.0, 1.0, _COLOR_SAMPLES)
    x = endpoints[:, None, 0] + t * (endpoints[:, None, 2] - endpoints[:, None, 0])
    y = endpoints[:, None, 1] + t * (endpoints[:, None, 3] - endpoints[:, None, 1])
    h, w = image.shape[:2]
    xi = np.clip(np.rint(x).astype(np.int64), 0, w - 1)
    yi = np.clip(np.rint(y).astype(np.int64), 0, h - 1)
    img = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
    return np.rint(img[yi, xi].astype(np.float64).mean(axis=1)).astype(np.uint8)


def segment_contrast(gray: np.ndarray, endpoints: np.ndarray, offset_px: float = 2.0, samples: int = 16) -> np.ndarray:
    """Returns (N,) float32: each segment's polarity, the mean grey level ``offset_px`` to the left
    of its direction (x1, y1) -> (x2, y2) minus that to its right (bilinear samples along it).

    Two parallel edges a few pixels apart (a door trim's two sides, the frame of a window) have
    opposite polarity; the tracker uses it to keep their tracks apart (a deviation from the paper).
    """
    if len(endpoints) == 0:
        return np.zeros(0, np.float32)
    e = np.asarray(endpoints, np.float64)
    d = e[:, 2:] - e[:, :2]
    n = np.stack([d[:, 1], -d[:, 0]], axis=1) / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)[:, None]
    t = (np.arange(samples) + 0.5) / samples
    p = e[:, None, :2] + t[None, :, None] * d[:, None, :]  # (N, samples, 2)
    left = (p + offset_px * n[:, None, :]).reshape(-1, 1, 2).astype(np.float32)
    right = (p - offset_px * n[:, None, :]).reshape(-1, 1, 2).astype(np.float32)
    img = gray.astype(np.float32)
    sample = lambda q: cv2.remap(img, q[..., 0], q[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    diff = (sample(left) - sample(right)).reshape(len(e), samples)
    return diff.mean(axis=1).astype(np.float32)


def detect_frame(
    image: np.ndarray,
    config: Config | DetectConfig,
    K: np.ndarray | None = None,
    distortion: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (endpoints (N, 4) float32, colors (N, 3) uint8, contrast (N,) float32) of one frame's
    merged segments (paper §3.1; contrast: :func:`segment_contrast`).

    LSD on the grayscale image, then :func:`merge_segments`, then segments
    shorter than ``min_length_frac * min(w, h)`` are dropped. With non-zero
    ``distortion`` (OpenCV k1 k2 p1 p2) the endpoints are undistorted with ``K``.
    """
    cfg = _detect_config(config)
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    h, w = gray.shape[:2]
    min_side = min(h, w)
    lines = cv2.createLineSegmentDetector().detect(gray)[0]
    raw = np.zeros((0, 4)) if lines is None else lines.reshape(-1, 4).astype(np.float64)
    merged = merge_segments(raw, cfg.merge_angle_deg, cfg.merge_dist_frac * min_side, cfg.merge_offset_px)
    d = merged[:, 2:] - merged[:, :2]
    merged = merged[np.hypot(d[:, 0], d[:, 1]) >= cfg.min_length_frac * min_side]
    colors = segment_colors(image, merged)
    contrast = segment_contrast(gray, merged)
    if distortion is not None and K is not None and np.any(np.asarray(distortion) != 0):
        pts = cv2.undistortPoints(
            merged.reshape(-1, 1, 2).astype(np.float64), K, np.asarray(distortion, np.float64), P=K
        )
        merged = pts.reshape(-1, 4)
    return merged.astype(np.float32), colors, contrast


def _read(capture: Capture, i: int, thumbnails: list[bytes] | None, width: int) -> np.ndarray:
    img = capture.frame(i)
    if thumbnails is not None:
        thumbnails.append(jpeg_thumbnail(img, min(width, img.shape[1])))
    return img


def detect_segments(capture: Capture, config: Config | DetectConfig,
                    thumbnails: list[bytes] | None = None, thumbnail_width: int = 480) -> Segments:
    """Returns the merged LSD segments of every frame of ``capture`` (paper §3.1 'Line segment detection').

    Frames are read in this process (sequential access suits videos) and
    detected in ``config.workers`` worker processes; ``workers <= 1`` runs
    in-process. When a list is given as ``thumbnails``, each frame's JPEG
    thumbnail (``thumbnail_width`` wide) is appended to it while the frame is
    in memory anyway.
    """
    cfg = _detect_config(config)
    K = capture.camera.K
    dist = capture.camera.distortion
    n = capture.n_frames
    workers = max(1, min(int(cfg.workers), os.cpu_count() or 1, n))
    results: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    if workers <= 1:
        for i in progress(range(n), "lines", total=n):
            results.append(detect_frame(_read(capture, i, thumbnails, thumbnail_width), cfg, K, dist))
    else:
        # a sliding window of in-flight frames: read lazily, never all held in memory
        window = 4 * workers
        pending: deque = deque()
        with process_pool(workers) as pool:
            for i in progress(range(n), "lines", total=n):
                pending.append(pool.submit(detect_frame, _read(capture, i, thumbnails, thumbnail_width),
                                           cfg, K, dist))
                if len(pending) > window:
                    results.append(pending.popleft().result())
            results.extend(f.result() for f in pending)
    segments = segments_of_frames(results)
    log.info("detected %d segments in %d frames (%.1f per frame)", segments.n, n, segments.n / max(n, 1))
    return segments


def segments_of_frames(results: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> Segments:
    """Returns the :class:`Segments` of frames 0..F-1 from their :func:`detect_frame` results, in frame order."""
    counts = np.array([len(r[0]) for r in results], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    endpoints = np.concatenate([r[0] for r in results] + [np.zeros((0, 4), np.float32)]).astype(np.float32)
    colors = np.concatenate([r[1] for r in results] + [np.zeros((0, 3), np.uint8)]).astype(np.uint8)
    contrast = np.concatenate([r[2] for r in results] + [np.zeros(0, np.float32)]).astype(np.float32)
    frame = np.repeat(np.arange(len(results), dtype=np.int32), counts)
    return Segments(endpoints=endpoints, frame=frame, frame_offsets=offsets, colors=colors, contrast=contrast)
