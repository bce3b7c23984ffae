"""Manhattan frame extraction and Manhattan line labelling (paper §3.1, supplement §1-2)."""
from __future__ import annotations

import logging
from functools import lru_cache

import numpy as np

from ..config import Config, ManhattanConfig
from ..data import ManhattanFrame, Segments, UNLABELLED
from ..errors import OnlyVerticalEdgesError, TooFewLinesError
from ..geometry import interpretation_normals

log = logging.getLogger("panosfm.lines")

_CHUNK = 4096  # segments per voting chunk (bounds the S x B matrix)


def _manhattan_config(config: Config | ManhattanConfig) -> ManhattanConfig:
    return config.manhattan if isinstance(config, Config) else config


@lru_cache(maxsize=4)
def sphere_bins(n: int) -> np.ndarray:
    """Returns (n, 3) near-uniform unit directions on the Gaussian sphere (Fibonacci lattice).

    Supplement §1 uses 10242 bins (an icosphere); a Fibonacci lattice of the
    same size has the same ~2 degree spacing.
    """
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def world_normals(segments: Segments, K: np.ndarray, R_wc: np.ndarray) -> np.ndarray:
    """Returns (S, 3) unit world-frame interpretation-plane normals (supplement §1: R_i^T K^-1 x)."""
    n_cam = interpretation_normals(K, segments.endpoints.astype(np.float64))
    return np.einsum("sij,sj->si", R_wc[segments.frame], n_cam)


def vote_sphere(normals: np.ndarray, weights: np.ndarray, bins: np.ndarray, band_rad: float) -> np.ndarray:
    """Returns (B,) votes: each plane normal adds its weight to bins within ``band_rad`` of its great circle.

    Supplement §1: a bin d gets a vote when the angle between d and the
    interpretation plane, asin|n . d|, is below ``band_rad``. Chunked matrix
    products, no loop per segment.
    """
    votes = np.zeros(len(bins), dtype=np.float64)
    s = np.sin(band_rad)
    b32 = bins.astype(np.float32)
    for start in range(0, len(normals), _CHUNK):
        n = normals[start : start + _CHUNK].astype(np.float32)
        hit = np.abs(n @ b32.T) < s  # (chunk, B)
        votes += weights[start : start + _CHUNK].astype(np.float32) @ hit
    return votes


def _refine_frame(normals: np.ndarray, weights: np.ndarray, D: np.ndarray, band: float) -> np.ndarray:
    """Returns the 3 directions (rows) refined by weighted least squares on their own segments.

    Each direction d_k becomes the d minimising sum w (n . d)^2 over the
    segments compatible with d_k only (the 85 degree rule, ``band`` = its
    sine), with the inlier band shrinking to band/4 over three rounds so that
    clutter near a direction does not bias it; then re-orthogonalised.
    """
    for scale in (1.0, 0.5, 0.25):
        a = np.abs(normals @ D.T)  # (S, 3) |n . d_k|
        compatible = a < band
        new = D.copy()
        for k in range(3):
            sel = compatible[:, k] & (compatible.sum(axis=1) == 1) & (a[:, k] < band * scale)
            if np.count_nonzero(sel) < 3:
                continue
            n, w = normals[sel], weights[sel]
            evals, evecs = np.linalg.eigh((n * w[:, None]).T @ n)
            d = evecs[:, 0]
            new[k] = d if d @ D[k] >= 0 else -d
        D = _orthonormalise(new)
    return D


def _orthonormalise(D: np.ndarray) -> np.ndarray:
    """Returns the rotation matrix nearest to D (rows), right-handed, row 2 kept near +z."""
    U, _, Vt = np.linalg.svd(D)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R[1] = -R[1]
    return R


def gravity_aligned(D: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Returns the Manhattan directions (rows) with the vertical set to gravity ``g`` and x the old x made
    horizontal (ours: the IMU's gravity is trusted over a vertical that the lines pull far off it)."""
    x = D[0] - (D[0] @ g) * g
    if np.linalg.norm(x) < 1e-9:  # the old x was vertical: take the old y
        x = D[1] - (D[1] @ g) * g
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(g, x), g])


def align_to(mf: ManhattanFrame, reference: ManhattanFrame) -> ManhattanFrame:
    """Returns ``mf`` with its horizontal axes permuted / negated to match ``reference`` best.

    The heading of a Manhattan frame is ambiguous up to the 4-fold symmetry
    about the vertical; this keeps labels stable across iterations.
    """
    D, ref = mf.directions, reference.directions
    best, best_score = D, -np.inf
    for perm in ((0, 1), (1, 0)):
        for sx in (1.0, -1.0):
            x = sx * D[perm[0]]
            y = np.cross(D[2], x)
            cand = np.stack([x, y, D[2]])
            score = float(np.trace(cand @ ref.T))
            if score > best_score:
                best, best_score = cand, score
    return ManhattanFrame(directions=best)


def manhattan_frame(
    segments: Segments,
    K: np.ndarray,
    R_wc: np.ndarray,
    config: Config | ManhattanConfig,
    gravity: np.ndarray = (0.0, 0.0, 1.0),
    reference: ManhattanFrame | None = None,
) -> ManhattanFrame:
    """Returns the Manhattan frame (3 orthogonal world directions) voted by all segments (supplement §1).

    1. Each segment votes its length along its great circle on ``sphere_bins``
       bins; 2. the vertical is the strongest bin within
       ``vertical_search_deg`` of ``gravity``; the second is the strongest bin
       within 1 degree of orthogonal to it; the third is their cross product;
       3. each direction is refined by the weighted least-squares fit to its
       voters' plane normals (smallest eigenvector of sum w n n^T), then the
       three are re-orthogonalised (SVD). Rows: x, y, z (vertical), det = +1.
       With ``reference`` the horizontal axes are permuted to match it.
    Raises :class:`TooFewLinesError` when the votes cannot define two directions.
    """
    cfg = _manhattan_config(config)
    g = np.asarray(gravity, dtype=np.float64)
    g = g / np.linalg.norm(g)
    _check_enough_segments(segments, cfg)
    normals = world_normals(segments, K, R_wc)
    weights = segments.lengths.astype(np.float64)
    bins = sphere_bins(cfg.sphere_bins)
    votes = vote_sphere(normals, weights, bins, cfg.vote_band_rad)

    near_g = bins @ g > np.cos(np.radians(cfg.vertical_search_deg))
    if not np.any(near_g):
        raise TooFewLinesError("no sphere bin near gravity; increase manhattan.sphere_bins")
    vz = bins[near_g][np.argmax(votes[near_g])]
    if vz @ g < 0:
        vz = -vz
    ortho = np.abs(bins @ vz) < np.sin(np.radians(1.0))
    if not np.any(ortho) or votes[ortho].max() <= 0:
        raise TooFewLinesError("no horizontal line direction found: the frames show no horizontal edges")
    vx = bins[ortho][np.argmax(votes[ortho])]
    vx = vx - (vx @ vz) * vz
    vx /= np.linalg.norm(vx)
    D = np.stack([vx, np.cross(vz, vx), vz])
    D = _refine_frame(normals, weights, D, np.cos(np.radians(cfg.label_angle_deg)))
    mf = ManhattanFrame(directions=_vertical_up_near_gravity(D, g, cfg))
    if reference is not None:
        mf = align_to(mf, reference)
    return mf


def refined_manhattan_frame(segments: Segments, K: np.ndarray, R_wc: np.ndarray, previous: ManhattanFrame,
                            config: Config | ManhattanConfig) -> ManhattanFrame:
    """Returns ``previous`` refined by the segments: :func:`manhattan_frame` without the sphere vote (supplement §1,
    step 3 from ``previous``'s directions), for a warm start whose frames grew (streaming; ours: the vote over all
    frames so far cost 0.6-1.6 s a batch at 250 frames, docs/decisions.md#warm-manhattan-frame)."""
    cfg = _manhattan_config(config)
    _check_enough_segments(segments, cfg)
    normals = world_normals(segments, K, R_wc)
    D = _refine_frame(normals, segments.lengths.astype(np.float64), np.asarray(previous.directions, np.float64),
                      np.cos(np.radians(cfg.label_angle_deg)))
    return align_to(ManhattanFrame(directions=_vertical_up_near_gravity(D, np.array([0.0, 0.0, 1.0]), cfg)), previous)


def _check_enough_segments(segments: Segments, cfg: ManhattanConfig) -> None:
    """Raises :class:`TooFewLinesError` where too few segments were detected to find the Manhattan directions."""
    if segments.n < cfg.min_segments:
        raise TooFewLinesError(
            f"only {segments.n} line segments were detected (at least {cfg.min_segments} needed to find "
            "the room's Manhattan directions); the frames may show a textureless close-up"
        )


def _vertical_up_near_gravity(D: np.ndarray, g: np.ndarray, cfg: ManhattanConfig) -> np.ndarray:
    """Returns the directions (rows) with the vertical pointing up, taken from gravity ``g`` where it lies more than
    ``manhattan.vertical_max_deg`` off it."""
    if D[2] @ g < 0:  # keep the vertical pointing up, stay right-handed
        D = D * np.array([[-1.0], [1.0], [-1.0]])
    tilt = np.degrees(np.arccos(np.clip(D[2] @ g, -1.0, 1.0)))
    if cfg.vertical_max_deg > 0 and tilt > cfg.vertical_max_deg:
        D = gravity_aligned(D, g)
        log.warning("Manhattan vertical %.1f deg off the IMU's gravity (at most %.1f): slanted or non-Manhattan "
                    "lines; the vertical is taken from gravity", tilt, cfg.vertical_max_deg)
    return D


def label_segments(
    segments: Segments,
    K: np.ndarray,
    R_wc: np.ndarray,
    mf: ManhattanFrame,
    config: Config | ManhattanConfig,
) -> np.ndarray:
    """Returns (S,) int8 Manhattan labels 0/1/2, or -1 (supplement §2, the 85 degree rule).

    A segment is a Manhattan segment of direction k when its plane normal is
    more than ``label_angle_deg`` from v_k and less than that from the other
    two; segments compatible with no direction or with two are -1.
    """
    cfg = _manhattan_config(config)
    if segments.n == 0:
        return np.zeros(0, dtype=np.int8)
    normals = world_normals(segments, K, R_wc)
    compatible = np.abs(normals @ mf.directions.T) < np.cos(np.radians(cfg.label_angle_deg))  # (S, 3)
    labels = np.where(compatible.sum(axis=1) == 1, np.argmax(compatible, axis=1), UNLABELLED)
    return labels.astype(np.int8)


def horizontal_counts(segments: Segments, labels: np.ndarray, n_frames: int,
                      weights: np.ndarray | None = None) -> np.ndarray:
    """Returns (n_frames,) each frame's number of horizontal Manhattan segments (labelled with axis 0 or 1): the
    segments whose vanishing points fix the frame's heading, where vertical ones fix only its tilt; with
    ``weights`` (S,) (e.g. the segments' lengths), their sum of weights instead."""
    horizontal = (labels >= 0) & (labels != 2)
    w = None if weights is None else np.asarray(weights)[horizontal]
    return np.bincount(segments.frame[horizontal], w, minlength=n_frames)[:n_frames]


def check_enough_manhattan(labels: np.ndarray, config: Config | ManhattanConfig) -> None:
    """Raises :class:`TooFewLinesError` unless enough segments of two or more axes were labelled."""
    cfg = _manhattan_config(config)
    counts = np.bincount(labels[labels >= 0].astype(np.int64), minlength=3)
    if counts.sum() < cfg.min_segments or np.count_nonzero(counts >= 3) < 2:
        why = ("only vertical edges: the floor's and ceiling's edges and every horizontal edge are out of view (a bare "
               "room; tilt the phone to see where walls meet the floor)" if counts[2] >= cfg.min_segments else
               "the frames may show a textureless close-up or a non-Manhattan scene")
        error = OnlyVerticalEdgesError if counts[2] >= cfg.min_segments else TooFewLinesError
        raise error(
            f"too few Manhattan line segments ({counts[0]} x, {counts[1]} y, {counts[2]} vertical; "
            f"at least {cfg.min_segments} on two or more axes needed): {why}"
        )
