"""Zero baseline: does the spin show any parallax at all? (Our addition; not in the paper.)

A tripod spin, a panorama cut into frames, or a phone turned about its own lens has one optical
centre: every translation the linear solve or the bundle adjustment would report is noise fitted
to noise. A camera that only rotates sees each 3D line on ONE plane through its centre in every
frame (:func:`..lines.fragments.interpretation_angle` is constant along the track); a camera on an
arm of a few decimetres sees that plane drift by ``f b / d`` px (``b`` the baseline, ``d`` the
line's distance). :func:`parallax_px` measures the drift: for each track seen over enough turn,
the RMS image distance of its segments from the plane at the track's mean angle; the capture's
parallax is the median over tracks (robust to the few impure ones). Rotation errors add to it
(0.3 degrees at f = 500 px is 2.6 px on a segment far from the centre, much less on average), so
the threshold ``LinearConfig.zero_baseline_px`` sits above what refined rotations leave on the
real panorama cuts and below what an arm of 0.2 m gives at 480x270 (docs/decisions.md#zero-baseline).
"""
from __future__ import annotations

import numpy as np

from ..data import Camera, Preprocessed, Tracks
from ..lines.fragments import interpretation_angle, interpretation_offset
from .system import VERTICAL


def frame_headings_deg(R_wc: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Returns (F,) each frame's heading (deg) about the vertical Manhattan direction, unwrapped along the spin."""
    z = R_wc[:, :, 2]  # optical axes, world
    other = [a for a in range(3) if a != VERTICAL]
    heading = np.arctan2(z @ directions[other[1]], z @ directions[other[0]])
    return np.degrees(np.unwrap(heading))


def parallax_px(pre: Preprocessed, tracks: Tracks, camera: Camera, min_turn_deg: float = 20.0,
                min_obs: int = 4) -> tuple[float, float, int]:
    """Returns (median, 90th percentile, tracks used): the RMS px distance of tracked segments from their
    track's interpretation plane, over the tracks with ``min_obs`` segments seen over ``min_turn_deg`` of turn.

    The median is NaN when no track qualifies (nothing to measure: too few or too short tracks).
    """
    seg, offsets = tracks.members()
    if len(seg) == 0:
        return float("nan"), float("nan"), 0
    tid = tracks.track_of[seg].astype(np.int64)
    count = np.diff(offsets)
    M = np.asarray(pre.manhattan.directions, dtype=np.float64)
    R = np.asarray(pre.R_wc, dtype=np.float64)
    K = camera.K
    axis = tracks.axis[tid].astype(np.int64)
    heading = frame_headings_deg(R, M)[pre.segments.frame[seg]]
    seen = count > 0
    starts = offsets[:-1][seen]
    turn = np.zeros(tracks.n)
    turn[seen] = np.maximum.reduceat(heading, starts) - np.minimum.reduceat(heading, starts)
    use = (count >= min_obs) & (turn >= min_turn_deg)
    if not np.any(use):
        return float("nan"), float("nan"), 0
    keep = use[tid]
    seg, tid, axis = seg[keep], tid[keep], axis[keep]
    angle = interpretation_angle(pre.segments, seg, axis, K, R, M)
    # the track's mean plane: the circular mean of the angles modulo pi (doubled, averaged, halved)
    c = np.bincount(tid, np.cos(2 * angle), minlength=tracks.n)
    s = np.bincount(tid, np.sin(2 * angle), minlength=tracks.n)
    mean = 0.5 * np.arctan2(s, c)
    off = interpretation_offset(pre.segments, seg, axis, mean[tid], K, R, M)
    rms = np.sqrt(np.bincount(tid, off ** 2, minlength=tracks.n)[use] / count[use])
    return float(np.median(rms)), float(np.percentile(rms, 90)), int(use.sum())
