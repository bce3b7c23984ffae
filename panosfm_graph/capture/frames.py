"""A capture's frames and their timestamps: ``frames/`` or ``video.<ext>``, ``frames.csv`` (``capture-format.md``).

:func:`_read_source` finds and checks all frames (images or a video);
:func:`_timestamps` takes each frame's time from ``frames.csv``, else the
video container, else ``camera.json``'s ``fps``; :func:`_frame_reader`
reads the frames a run takes.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..data import Camera
from ..errors import InputError
from .camera import _Warp
from .images import _IMREAD_FLAGS, _ImageReader, _image_size, _image_truncated, _list_images
from .validate import _numbers, _read_csv
from .video import _find_video, _scan_video, _VideoReader

log = logging.getLogger("panosfm.capture")

FRAMES_CSV_HEADER = ("file", "timestamp_s")
DEFAULT_FPS = 30.0


@dataclass(frozen=True)
class _Source:
    """All frames of a capture (before every_k / max_frames)."""

    kind: str  # "frames" | "video"
    names: tuple[str, ...]  # file names or "video.mp4#000123"
    stems: tuple[str, ...]  # keys for ground_truth/<stem>.npy and poses.csv
    paths: tuple[Path, ...]  # image paths (frames) or (video path,)
    msec: np.ndarray | None  # video container timestamps (ms)
    container_fps: float


def _read_source(root: Path, camera: Camera, camera_json: Path) -> _Source:
    frames_dir = root / "frames"
    images = _list_images(frames_dir) if frames_dir.is_dir() else []
    video = _find_video(root)
    if images:
        if video is not None:
            log.info("%s: both frames/ and %s, using frames/", root, video.name)
        for p in images:
            problem = _image_truncated(p)
            if problem is not None:
                raise InputError(problem, p)
            size = _image_size(p)
            if size is None:
                img = cv2.imread(str(p), _IMREAD_FLAGS)
                if img is None:
                    raise InputError("cannot be read as a PNG or JPEG image", p)
                size = (img.shape[1], img.shape[0])
            if size != (camera.width, camera.height):
                raise InputError(f"is {size[0]}x{size[1]} but {camera_json.name} says "
                                 f"{camera.width}x{camera.height}", p)
        names = tuple(p.name for p in images)
        return _Source("frames", names, tuple(p.stem for p in images), tuple(images), None, 0.0)
    if video is not None:
        n, msec, size, fps = _scan_video(video)
        if size != (camera.width, camera.height):
            raise InputError(f"frames are {size[0]}x{size[1]} but {camera_json.name} says "
                             f"{camera.width}x{camera.height}", video)
        names = tuple(f"{video.name}#{i:06d}" for i in range(n))
        return _Source("video", names, tuple(f"{i:06d}" for i in range(n)), (video,), msec, fps)
    if frames_dir.is_dir():
        raise InputError("holds no PNG or JPEG images (and there is no video.<ext>)", frames_dir)
    raise InputError("has no frames/ folder and no video.<ext>", root)


def _read_frames_csv(path: Path, source: _Source) -> np.ndarray:
    """Returns the timestamps (s) of ``frames.csv`` in the source's frame order, checked against the frames."""
    rows = _read_csv(path, FRAMES_CSV_HEADER)
    t = _numbers(path, rows, slice(1, 2))[:, 0]
    files = [r[0] for r in rows]
    if not np.all(np.isfinite(t)):
        raise InputError(f"line {int(np.argmax(~np.isfinite(t))) + 2}: NaN or infinite timestamp", path)
    n = len(source.names)
    where = "frames/" if source.kind == "frames" else source.paths[0].name
    if len(rows) != n:
        raise InputError(f"has {len(rows)} rows but {where} has {n} frames", path)
    if source.kind == "frames":
        index = {name: k for k, name in enumerate(source.names)}
        seen = np.zeros(n, dtype=bool)
        order = np.empty(n, dtype=np.int64)
        for k, name in enumerate(files):
            j = index.get(Path(name).name)
            if j is None:
                raise InputError(f"line {k + 2}: {name!r} is not in frames/", path)
            if seen[j]:
                raise InputError(f"line {k + 2}: {name!r} is listed twice", path)
            seen[j] = True
            order[j] = k
        t = t[order]
    if np.any(np.diff(t) <= 0):
        k = int(np.argmax(np.diff(t) <= 0))
        raise InputError(f"timestamps must increase in frame order ({source.names[k + 1]} at {t[k + 1]} s "
                         f"follows {source.names[k]} at {t[k]} s)", path)
    return t


def _timestamps(root: Path, source: _Source, fps: float | None) -> tuple[np.ndarray, str, float]:
    """Returns (timestamps of all frames (s), where they came from, nominal fps)."""
    n = len(source.names)
    csv_path = root / "frames.csv"
    if csv_path.is_file():
        t = _read_frames_csv(csv_path, source)
        rate = (n - 1) / (t[-1] - t[0]) if n > 1 else (fps or DEFAULT_FPS)
        return t, "frames.csv", float(rate)
    if source.msec is not None and n > 0 and np.all(np.isfinite(source.msec)) and (
            n == 1 or np.all(np.diff(source.msec) > 0)):
        t = source.msec / 1000.0
        rate = (n - 1) / (t[-1] - t[0]) if n > 1 else (source.container_fps or fps or DEFAULT_FPS)
        return t, "video", float(rate)
    rate = fps or (source.container_fps if source.container_fps > 0 else None) or DEFAULT_FPS
    return np.arange(n) / rate, "fps", float(rate)


def _frame_reader(source: _Source, take: np.ndarray, raw_camera: Camera, warp: _Warp,
                  camera_json: Path) -> _ImageReader | _VideoReader:
    """Returns the reader of the taken frames ``take`` (indices into the source): working images on demand."""
    if source.kind == "frames":
        return _ImageReader([source.paths[k] for k in take], (raw_camera.width, raw_camera.height), warp,
                            camera_json)
    msec = source.msec
    usable = msec is not None and np.all(np.isfinite(msec)) and np.all(np.diff(msec) > 0)
    return _VideoReader(source.paths[0], take, msec if usable else None, warp)
