"""Point tracks (our addition; issue #40): corners followed from frame to frame by optical flow.

Lines fix a frame's centre only where they span the room's three axes; in a plain
room a stretch of the spin sees one or two lines. The room's texture (a
poster, a door handle, the grain of a wall) still gives corners, and a corner
seen from two points of the spin's circle gives parallax. This stage follows
Shi-Tomasi corners (OpenCV ``goodFeaturesToTrack``) from each frame to the
next with pyramidal Lucas-Kanade (``calcOpticalFlowPyrLK``), started where the
rotation between the frames puts them -- the spin is nearly a pure rotation,
so the infinite homography ``K R_j^T R_i K^-1`` predicts each corner up to a
small parallax -- and keeps a step only if

* tracking back lands within ``points.fb_px`` of where it started, and
* it departs from the rotation's prediction by at most ``points.max_parallax_px``.

New corners are seeded where no track runs (at most ``points.per_frame`` per
frame), and only where the image varies in both directions (the structure
tensor's eigenvalues within ``points.min_eigen_ratio`` of each other): a
corner on a straight edge slides along it. Tracks shorter than ``points.min_frames`` are dropped.

A spin comes back to where it began: a frame that has turned at least
``points.loop_min_turn_deg`` since an earlier one which looks within
``points.loop_max_deg`` of its direction sees the same wall again. Every
``points.loop_every``-th such frame follows its corners into that earlier frame
(the same prediction, first shifted by a coarse correlation of the two
images, and checks, the parallax bound ``points.loop_parallax_px``: the
rotations have drifted more over a turn), which closes the loop: the
late frames are tied to the early ones by shared points, not only through
the chain of frames between them. The observations are undistorted pixels of
the working images.
"""
from __future__ import annotations

import logging
from typing import Callable

import cv2
import numpy as np

from ..config import PointsConfig
from ..data import Capture, PointTracks
from ..geometry import rotation_angle_deg, rotation_homography, turned_degrees
from ..lines.tracking import median_step_deg
from ..progress import progress

log = logging.getLogger("panosfm.points")

_COARSE_SCALE, _COARSE_SEARCH, _COARSE_MIN_SCORE = 4, 40, 0.3  # the loop's coarse alignment (_coarse_shift)
_COARSE_MIN_STD = 1.0  # grey levels
_BLOCK = 7  # corner window (goodFeaturesToTrack's blockSize)
_LK_WIN = (21, 21)
_LK_LEVELS = 3
_LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)


def _grey(capture: Capture, i: int) -> np.ndarray:
    return cv2.cvtColor(capture.frame(i), cv2.COLOR_BGR2GRAY)


def _apply(H: np.ndarray, p: np.ndarray) -> np.ndarray:
    q = p @ H[:, :2].T + H[:, 2]
    return q[:, :2] / q[:, 2:3]


def _seed(grey: np.ndarray, existing: np.ndarray, config: PointsConfig) -> np.ndarray:
    """Returns (N, 2) float32 new corners at least ``min_distance_px`` from ``existing`` (M, 2)."""
    room = config.per_frame - len(existing)
    if room <= 0:
        return np.zeros((0, 2), np.float32)
    mask = np.full(grey.shape, 255, np.uint8)
    r = int(round(config.min_distance_px))
    for x, y in np.round(existing).astype(int):
        cv2.circle(mask, (x, y), r, 0, -1)
    c = cv2.goodFeaturesToTrack(grey, maxCorners=room, qualityLevel=config.quality, minDistance=config.min_distance_px,
                                mask=mask, blockSize=_BLOCK)
    if c is None:
        return np.zeros((0, 2), np.float32)
    c = c.reshape(-1, 2).astype(np.float32)
    return c[_eigen_ratio(grey, c) >= config.min_eigen_ratio]


def _eigen_ratio(grey: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Returns (N,) the smaller over the larger eigenvalue of the structure tensor (``_BLOCK`` window) at ``xy``:
    near 0 on a straight edge, where a corner slides along it (the aperture problem), near 1 on a blob."""
    g = grey.astype(np.float32)
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    x, y = np.clip(np.round(xy).astype(int).T, 0, [[grey.shape[1] - 1], [grey.shape[0] - 1]])
    a, b, c = (cv2.boxFilter(m, -1, (_BLOCK, _BLOCK))[y, x] for m in (gx * gx, gx * gy, gy * gy))
    root = np.sqrt(((a - c) / 2) ** 2 + b**2)
    hi, lo = (a + c) / 2 + root, (a + c) / 2 - root
    return lo / np.maximum(hi, 1e-12)


def _step(g0: np.ndarray, g1: np.ndarray, p0: np.ndarray, guess: np.ndarray, config: PointsConfig,
          max_parallax_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((N, 2) positions in g1, (N,) bool kept) of points ``p0`` of g0, LK started at ``guess``, at most
    ``max_parallax_px`` from it."""
    if not len(p0):
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(g0, g1, p0[:, None], guess[:, None].astype(np.float32).copy(),
                                         winSize=_LK_WIN, maxLevel=_LK_LEVELS, criteria=_LK_CRITERIA,
                                         flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(g1, g0, p1, p0[:, None].copy(), winSize=_LK_WIN, maxLevel=_LK_LEVELS,
                                            criteria=_LK_CRITERIA, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    p1, back = p1.reshape(-1, 2), back.reshape(-1, 2)
    h, w = g1.shape
    inside = (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
    ok = (st.ravel() == 1) & (st2.ravel() == 1) & inside
    ok &= np.hypot(*(back - p0).T) <= config.fb_px
    ok &= np.hypot(*(p1 - guess).T) <= max_parallax_px
    return p1, ok


def track_points(capture: Capture, R_wc: np.ndarray, config: PointsConfig) -> PointTracks:
    """Returns the point tracks of ``capture`` (module docstring), predicted by the rotations ``R_wc`` (F, 3, 3)."""
    tracker = PointTracker(config)
    tracker.extend(capture, R_wc)
    return tracker.tracks()


class PointTracker:
    """The point tracks of frames that arrive in order (module docstring; issue 42's streamed run).

    :meth:`extend` follows the corners into the frames not yet seen, ``capture.frame(i)`` for each, predicted by the
    rotations ``R_wc`` of all frames so far (the earlier frames' steps stay as they were tracked), and follows
    the new frames' corners into the frames a turn before them (the loop, read through ``capture.frame``);
    :meth:`tracks` returns the tracks so far. Extended once over every frame, it is :func:`track_points`.
    """

    def __init__(self, config: PointsConfig):
        self.config = config
        self.n_frames = 0
        self._frames: list[np.ndarray] = []  # per frame: the frame index of each observation
        self._tracks: list[np.ndarray] = []  # per frame: the track ids seen
        self._xy: list[np.ndarray] = []  # per frame: where
        self._loops: tuple[list, list, list] = ([], [], [])  # the observations the loop added (frame, id, xy)
        self._seen: set[tuple[int, int]] = set()  # (track id, earlier frame) pairs the loop has followed
        self._ids = np.zeros(0, np.int64)
        self._pts = np.zeros((0, 2), np.float32)
        self._next_id = 0
        self._prev: np.ndarray | None = None

    def extend(self, capture: Capture, R_wc: np.ndarray, grey: Callable[[int], np.ndarray] | None = None) -> None:
        """Tracks the frames ``self.n_frames`` .. ``len(R_wc) - 1`` of ``capture`` (module docstring); ``grey``
        (frame index -> grey image) in place of reading ``capture.frame`` where given."""
        grey = grey if grey is not None else (lambda i: _grey(capture, i))
        config, K = self.config, capture.camera.K
        start, n = self.n_frames, len(R_wc)
        # the parallax grows with the baseline, so with the spin's step (60 per turn: 24 px at 1 m on a 0.3 m arm)
        finite = np.all(np.isfinite(R_wc), axis=(1, 2))
        max_parallax = config.max_parallax_px * max(1.0, median_step_deg(R_wc[finite]) / config.parallax_ref_step_deg)
        pts, ids, prev = self._pts, self._ids, self._prev
        for i in progress(range(start, n), "points", total=n - start):
            g = grey(i)
            if prev is not None and len(pts) and np.all(np.isfinite(R_wc[[i - 1, i]])):
                guess = _apply(rotation_homography(K, R_wc[i - 1], R_wc[i]), pts.astype(np.float64))
                pts, ok = _step(prev, g, pts, guess, config, max_parallax)
                pts, ids = pts[ok], ids[ok]
            elif prev is not None:
                pts, ids = np.zeros((0, 2), np.float32), np.zeros(0, np.int64)
            new = _seed(g, pts, config)
            pts = np.concatenate([pts, new]).astype(np.float32)
            ids = np.concatenate([ids, np.arange(self._next_id, self._next_id + len(new))])
            self._next_id += len(new)
            self._frames.append(np.full(len(pts), i, np.int32))
            self._tracks.append(ids.copy())
            self._xy.append(pts.copy())
            prev = g
        self._pts, self._ids, self._prev, self.n_frames = pts, ids, prev, n
        self._close_loops(capture, R_wc, start, grey)

    def tracks(self) -> PointTracks:
        """Returns the tracks so far of at least ``points.min_frames`` frames, sorted by frame."""
        frames, tracks, xy = (self._frames + self._loops[0], self._tracks + self._loops[1], self._xy + self._loops[2])
        frame = np.concatenate(frames) if frames else np.zeros(0, np.int32)
        track = np.concatenate(tracks) if tracks else np.zeros(0, np.int64)
        obs = np.concatenate(xy) if xy else np.zeros((0, 2), np.float32)
        order = np.argsort(frame, kind="stable")
        frame, track, obs = frame[order], track[order], obs[order]
        length = np.bincount(track, minlength=self._next_id)
        keep = length[track] >= self.config.min_frames
        _, track = np.unique(track[keep], return_inverse=True)
        out = PointTracks(frame=frame[keep], track=track.astype(np.int32), xy=obs[keep].astype(np.float32))
        log.info("point tracks: %d over %d frames (%d observations, %.1f per frame)", out.n, self.n_frames,
                 len(out.frame), len(out.frame) / max(self.n_frames, 1))
        return out

    def _close_loops(self, capture: Capture, R_wc: np.ndarray, start: int, grey: Callable[[int], np.ndarray]) -> None:
        """Follows the corners of each loop pair's late frame (from ``start`` on) into the earlier one (one
        observation per track and frame)."""
        pairs = [(i, j) for i, j in loop_pairs(R_wc, self.config) if i >= start]
        if not pairs:
            return
        K = capture.camera.K
        added = 0
        for i, j in pairs:
            ids, pts = self._tracks[i], self._xy[i]
            if not len(pts):
                continue
            H = rotation_homography(K, R_wc[i], R_wc[j])
            g_i, g_j = grey(i), grey(j)
            guess = _apply(H, pts.astype(np.float64)) + _coarse_shift(g_i, g_j, H)
            p1, ok = _step(g_i, g_j, pts, guess, self.config, self.config.loop_parallax_px)
            keep = [k for k in np.flatnonzero(ok) if (int(ids[k]), j) not in self._seen]
            self._seen.update((int(ids[k]), j) for k in keep)
            if keep:
                self._loops[0].append(np.full(len(keep), j, np.int32))
                self._loops[1].append(ids[keep])
                self._loops[2].append(p1[keep].astype(np.float32))
                added += len(keep)
        log.info("point tracks: %d loop observations from %d frame pairs a turn apart", added, len(pairs))


def loop_pairs(R_wc: np.ndarray, config: PointsConfig) -> list[tuple[int, int]]:
    """Returns (late frame i, earlier frame j) pairs that see the same wall a turn apart (module docstring): every
    ``loop_every``-th frame that has turned ``loop_min_turn_deg`` since a frame within ``loop_max_deg`` of its
    rotation, with the closest such frame."""
    ok = np.all(np.isfinite(R_wc), axis=(1, 2))
    if not ok.any() or config.loop_every <= 0:
        return []
    idx = np.flatnonzero(ok)
    turned = np.full(len(R_wc), np.nan)
    turned[idx] = turned_degrees(R_wc[idx])
    pairs = []
    for i in idx[::config.loop_every]:
        cand = idx[turned[i] - turned[idx] >= config.loop_min_turn_deg]
        if not len(cand):
            continue
        ang = rotation_angle_deg(np.broadcast_to(R_wc[i], (len(cand), 3, 3)), R_wc[cand])
        k = int(np.argmin(ang))
        if ang[k] <= config.loop_max_deg:
            pairs.append((int(i), int(cand[k])))
    return pairs


def _coarse_shift(g_i: np.ndarray, g_j: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Returns (2,) the pixel shift that best aligns frame i, warped into frame j by ``H``, with frame j: normalised
    cross-correlation at a quarter of the resolution over +-``_COARSE_SEARCH`` quarter pixels; zero where no shift
    correlates by ``_COARSE_MIN_SCORE``. Over a turn the rotations drift by degrees (measured, plain room seed 1
    swaying: about 120 px at the loop), beyond what LK finds on a plain wall's faint texture."""
    h, w = g_j.shape
    small = (w // _COARSE_SCALE, h // _COARSE_SCALE)
    a = cv2.resize(cv2.warpPerspective(g_i, H, (w, h)), small, interpolation=cv2.INTER_AREA)
    b = cv2.resize(g_j, small, interpolation=cv2.INTER_AREA)
    r = _COARSE_SEARCH
    if min(small) <= 2 * r + 16:  # too small an image for the search: no shift
        return np.zeros(2)
    if min(a[r:-r, r:-r].std(), b.std()) < _COARSE_MIN_STD:  # no texture: a correlation would be noise
        return np.zeros(2)
    res = cv2.matchTemplate(b, a[r:-r, r:-r], cv2.TM_CCOEFF_NORMED)
    _, score, _, loc = cv2.minMaxLoc(res)
    return (np.array(loc, np.float64) - r) * _COARSE_SCALE if score >= _COARSE_MIN_SCORE else np.zeros(2)
