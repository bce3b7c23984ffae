"""``video.<ext>``: any video OpenCV can decode, instead of ``frames/`` (``capture-format.md``).

:func:`_scan_video` decodes it once for its frame count and container
timestamps; :class:`_VideoReader` decodes frames on demand, sequentially
where it can.
"""
from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from .camera import _Warp
from .validate import _check_index

log = logging.getLogger("panosfm.capture")

SEEK_AHEAD_FRAMES = 48  # read forward sequentially up to this many frames instead of seeking


class _VideoReader:
    """Callable: frame index -> BGR uint8 working image decoded from a video.

    Keeps one ``cv2.VideoCapture`` open (per process) and reads sequentially
    when the next requested frame lies at or shortly after the last one; a
    backward or long jump seeks by frame number and checks the decoded
    frame's timestamp, falling back to reopening and reading forward when
    the container's seeking is inexact.
    """

    def __init__(self, path: Path, raw_indices: np.ndarray, msec: np.ndarray | None, warp: _Warp):
        self.path = path
        self.raw_indices = np.asarray(raw_indices, dtype=np.int64)
        self.msec = msec  # container timestamp (ms) of every raw frame, or None if unusable
        self.warp = warp
        self._lock = threading.Lock()
        self._reset()

    def _reset(self) -> None:
        self._cap = None
        self._pid = None
        self._next = 0  # raw index the open capture returns on the next read
        self._last: tuple[int, np.ndarray] | None = None

    def __getstate__(self):
        state = dict(self.__dict__)
        state.update(_cap=None, _pid=None, _next=0, _last=None, _lock=None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
        self._reset()

    def _open(self) -> None:
        if self._cap is not None:
            self._cap.release()
        self._cap = _open_video(self.path)
        self._pid = os.getpid()
        self._next = 0

    def _seek(self, raw: int) -> None:
        """Positions the open capture so that the next read returns raw frame ``raw``."""
        if self._cap is None or self._pid != os.getpid():
            self._open()
        if not self._next <= raw <= self._next + SEEK_AHEAD_FRAMES:
            # Seek to the frame before and identify the frame actually decoded by its timestamp
            # (container seeks can land elsewhere); read forward from there, or from the start.
            landed = -1
            if self.msec is not None and raw > 0 and self._cap.set(cv2.CAP_PROP_POS_FRAMES, raw - 1) \
                    and self._cap.grab():
                got = self._cap.get(cv2.CAP_PROP_POS_MSEC)
                j = int(np.clip(np.searchsorted(self.msec, got), 0, len(self.msec) - 1))
                j = j - 1 if j > 0 and abs(self.msec[j - 1] - got) < abs(self.msec[j] - got) else j
                if abs(self.msec[j] - got) < 0.5 and j < raw:
                    landed = j
            if landed >= 0:
                self._next = landed + 1
            else:
                self._open()
        while self._next < raw:
            if not self._cap.grab():
                raise InputError(f"frame {raw} could not be decoded (video ended at frame {self._next})", self.path)
            self._next += 1

    def __call__(self, i: int) -> np.ndarray:
        with self._lock:
            return self._read(i)

    def _read(self, i: int) -> np.ndarray:
        i = _check_index(i, len(self.raw_indices))
        if self._last is not None and self._last[0] == i and self._pid == os.getpid():
            return self._last[1].copy()
        raw = int(self.raw_indices[i])
        self._seek(raw)
        ok, img = self._cap.read()
        if not ok or img is None:
            self.close()
            raise InputError(f"frame {raw} could not be decoded", self.path)
        self._next = raw + 1
        img = self.warp(img)
        self._last = (i, img)
        return img.copy()


def _open_video(path: Path) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise InputError("OpenCV cannot open this video (unknown container or codec)", path)
    return cap


def _scan_video(path: Path) -> tuple[int, np.ndarray, tuple[int, int], float]:
    """Returns (frame count, container timestamps in ms, frame size (w, h), container fps) by decoding once."""
    cap = _open_video(path)
    try:
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        ok, first = cap.read()
        if not ok or first is None:
            raise InputError("no frame could be decoded", path)
        msec = [cap.get(cv2.CAP_PROP_POS_MSEC)]
        while cap.grab():
            msec.append(cap.get(cv2.CAP_PROP_POS_MSEC))
    finally:
        cap.release()
    return len(msec), np.asarray(msec, dtype=np.float64), (first.shape[1], first.shape[0]), fps


def _find_video(root: Path) -> Path | None:
    videos = sorted(p for p in root.glob("video.*") if p.is_file())
    if len(videos) > 1:
        log.warning("%s: several video files, using %s", root, videos[0].name)
    return videos[0] if videos else None
