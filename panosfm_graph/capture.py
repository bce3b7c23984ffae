"""Read and validate a capture directory (``capture-format.md``): camera, frames, timestamps, IMU, ground truth.

:func:`load_capture` returns a :class:`~panosfm_graph.data.Capture` whose
frames are read lazily (never all held at once), downscaled by
``CaptureConfig.scale`` and, for the OPENCV model, undistorted: the pipeline
works in undistorted pinhole coordinates, so ``Capture.camera`` is then the
PINHOLE camera of the undistorted images (same K). The IMU attitude is
slerped to every frame's timestamp (paper supplement §2 uses it as the
initial rotation and as a relative-rotation prior).

Every problem with the input raises :class:`~panosfm_graph.errors.InputError`
with one line naming the file. :func:`inspect_capture` describes a capture
(also one whose IMU does not cover its frames) and :func:`format_inspection`
prints that as a table. :func:`capture_warnings` checks a loaded capture as a
spin to reconstruct (IMU turn span, dropped frames); the pipeline calls it.
"""
from __future__ import annotations

import csv
import json
import logging
import math
import os
import struct
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .config import CaptureConfig, Config
from .data import Camera, Capture, GroundTruth
from .errors import InputError
from .geometry import quat_wxyz_to_matrix, slerp_rotations

log = logging.getLogger("panosfm.capture")

N_PARAMS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "OPENCV": 8}
IMAGE_EXTS = (".png", ".jpg", ".jpeg")
IMU_HEADER = ("timestamp_s", "qw", "qx", "qy", "qz")
FRAMES_CSV_HEADER = ("file", "timestamp_s")
DEFAULT_FPS = 30.0
QUAT_NORM_TOL = 1e-3  # |‖q‖ - 1| above this is rejected
TIME_TOL_S = 1e-6  # frames this close outside the IMU span still count as covered
SEEK_AHEAD_FRAMES = 48  # read forward sequentially up to this many frames instead of seeking
FOCAL_RANGE_FRAC = (0.2, 10.0)  # plausible focal length, as a fraction of the image width
PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # the IEND chunk every complete PNG ends with
JPEG_TAIL_BYTES = 1024  # a complete JPEG has its end-of-image marker (FF D9) this close to its end
# pixels as stored: EXIF orientation is ignored so that frames agree with their header and camera.json
_IMREAD_FLAGS = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION
AXIS_LABELS = {"x": 0, "y": 1, "z": 2, "0": 0, "1": 1, "2": 2, "-1": -1}


# --------------------------------------------------------------------------- camera


def read_camera(path: str | Path) -> tuple[Camera, float | None]:
    """Returns the camera of ``camera.json`` (COLMAP model and parameter order) and its ``fps`` (or None)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("missing (every capture needs camera.json)", path)
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"not valid JSON ({_first_line(e)})", path) from None
    if not isinstance(data, dict):
        raise InputError("must hold a JSON object with model, width, height, params", path)
    model = data.get("model")
    if not isinstance(model, str) or model.upper() not in N_PARAMS:
        raise InputError(f"unknown camera model {model!r} (expected one of {', '.join(N_PARAMS)})", path)
    model = model.upper()
    size = []
    for key in ("width", "height"):
        v = data.get(key)
        if v is None:
            raise InputError(f"'{key}' is missing", path)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not float(v).is_integer() or v <= 0:
            raise InputError(f"'{key}' must be a positive integer, got {v!r}", path)
        size.append(int(v))
    params = data.get("params")
    if not isinstance(params, list) or not all(_is_number(p) for p in params):
        raise InputError(f"'params' must be a list of numbers, got {params!r}", path)
    if len(params) != N_PARAMS[model]:
        raise InputError(f"{model} takes {N_PARAMS[model]} params, got {len(params)}", path)
    params = np.asarray(params, dtype=np.float64)
    if not np.all(np.isfinite(params)):
        raise InputError(f"params must be finite numbers, got {params.tolist()}", path)
    n_intr = 3 if model == "SIMPLE_PINHOLE" else 4
    if np.any(params[:n_intr] <= 0):
        raise InputError(f"focal lengths and principal point must be positive, got {params[:n_intr].tolist()}", path)
    w, h = size
    focal = params[:1] if model == "SIMPLE_PINHOLE" else params[:2]
    lo, hi = FOCAL_RANGE_FRAC
    if np.any(focal < lo * w) or np.any(focal > hi * w):
        raise InputError(f"focal length {', '.join(f'{f:g}' for f in focal)} px is implausible for a {w} px wide "
                         f"image (expected {lo:g}..{hi:g} x width = {lo * w:g}..{hi * w:g} px)", path)
    cx, cy = params[1:3] if model == "SIMPLE_PINHOLE" else params[2:4]
    if not (-0.5 <= cx <= w - 0.5 and -0.5 <= cy <= h - 0.5):
        raise InputError(f"principal point ({cx:g}, {cy:g}) lies outside the {w}x{h} image", path)
    fps = data.get("fps")
    if fps is not None:
        if not _is_number(fps) or not math.isfinite(fps) or fps <= 0:
            raise InputError(f"'fps' must be a positive number, got {fps!r}", path)
        fps = float(fps)
    return Camera(model, size[0], size[1], params), fps


def working_camera(camera: Camera, scale: float = 1.0) -> Camera:
    """Returns the camera of the working images: scaled by ``scale``; for OPENCV, the undistorted PINHOLE camera.

    Image size is rounded to whole pixels and the intrinsics follow the
    actual per-axis factor ``s``: ``f * s``, ``c' = (c + 0.5) * s - 0.5``
    (pixel (0, 0) is the centre of the top-left pixel).
    """
    w = max(1, int(round(camera.width * scale)))
    h = max(1, int(round(camera.height * scale)))
    sx, sy = w / camera.width, h / camera.height
    K = camera.K
    fx, fy = K[0, 0] * sx, K[1, 1] * sy
    cx, cy = (K[0, 2] + 0.5) * sx - 0.5, (K[1, 2] + 0.5) * sy - 0.5
    if camera.model == "SIMPLE_PINHOLE" and sx == sy:
        return Camera("SIMPLE_PINHOLE", w, h, np.array([fx, cx, cy]))
    return Camera("PINHOLE", w, h, np.array([fx, fy, cx, cy]))


def undistort_points(camera: Camera, pts: np.ndarray) -> np.ndarray:
    """Returns (N, 2) undistorted pixel coordinates (same K) of distorted pixels ``pts`` (N, 2).

    Inverts the OPENCV model (k1, k2, p1, p2) iteratively to 1e-12 in
    normalised coordinates; pinhole cameras return ``pts`` unchanged.
    """
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    if camera.model != "OPENCV" or not np.any(camera.distortion) or len(pts) == 0:
        return pts.copy()
    K = camera.K
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    out = cv2.undistortPoints(pts[:, None, :], K, camera.distortion, None, K, criteria=crit)
    return out.reshape(-1, 2)


def distort_points(camera: Camera, pts: np.ndarray) -> np.ndarray:
    """Returns (N, 2) distorted pixels of undistorted pixels ``pts`` (N, 2): the OPENCV model, forward."""
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    if camera.model != "OPENCV":
        return pts.copy()
    K = camera.K
    k1, k2, p1, p2 = camera.distortion
    x = (pts[:, 0] - K[0, 2]) / K[0, 0]
    y = (pts[:, 1] - K[1, 2]) / K[1, 1]
    r2 = x * x + y * y
    radial = 1.0 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd * K[0, 0] + K[0, 2], yd * K[1, 1] + K[1, 2]], axis=1)


class _Warp:
    """Callable: raw image -> working image (downscale with INTER_AREA, then undistort with a cached remap)."""

    def __init__(self, camera: Camera, work: Camera):
        self.raw_size = (camera.width, camera.height)
        self.work_size = (work.width, work.height)
        self.K = work.K
        self.dist = camera.distortion
        self._maps = None

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_maps"] = None
        return state

    def maps(self):
        if self._maps is None:
            self._maps = cv2.initUndistortRectifyMap(self.K, self.dist, None, self.K, self.work_size, cv2.CV_32FC1)
        return self._maps

    def __call__(self, img: np.ndarray, nearest: bool = False) -> np.ndarray:
        if img.shape[1::-1] != self.raw_size:
            img = cv2.resize(img, self.raw_size, interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)
        if img.shape[1::-1] != self.work_size:
            img = cv2.resize(img, self.work_size, interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)
        if np.any(self.dist):
            m1, m2 = self.maps()
            interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
            img = cv2.remap(img, m1, m2, interp, borderMode=cv2.BORDER_CONSTANT)
        return img


# --------------------------------------------------------------------------- frames


class _ImageReader:
    """Callable: frame index -> BGR uint8 working image, read from ``frames/`` on demand (one frame cached)."""

    def __init__(self, paths: list[Path], raw_size: tuple[int, int], warp: _Warp, camera_json: Path):
        self.paths = paths
        self.raw_size = raw_size
        self.warp = warp
        self.camera_json = camera_json
        self._last: tuple[int, np.ndarray] | None = None

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_last"] = None
        return state

    def __call__(self, i: int) -> np.ndarray:
        i = _check_index(i, len(self.paths))
        if self._last is not None and self._last[0] == i:
            return self._last[1].copy()
        path = self.paths[i]
        img = cv2.imread(str(path), _IMREAD_FLAGS)
        if img is None:
            raise InputError("cannot be read as an image", path)
        if img.shape[1::-1] != self.raw_size:
            raise InputError(f"is {img.shape[1]}x{img.shape[0]} but {self.camera_json.name} says "
                             f"{self.raw_size[0]}x{self.raw_size[1]}", path)
        img = self.warp(img)
        self._last = (i, img)
        return img.copy()


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


def _image_size(path: Path) -> tuple[int, int] | None:
    """Returns (width, height) from a PNG or JPEG header without decoding, or None when it cannot tell."""
    try:
        with open(path, "rb") as f:
            head = f.read(26)
            if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
                return struct.unpack(">II", head[16:24])
            if head[:2] != b"\xff\xd8":
                return None
            f.seek(2)
            while True:
                b = f.read(1)
                while b and b != b"\xff":
                    b = f.read(1)
                while b == b"\xff":
                    b = f.read(1)
                if not b:
                    return None
                marker = b[0]
                if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
                    continue
                seg = f.read(2)
                if len(seg) < 2:
                    return None
                length = struct.unpack(">H", seg)[0]
                if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                    sof = f.read(5)
                    if len(sof) < 5:
                        return None
                    h, w = struct.unpack(">HH", sof[1:5])
                    return w, h
                f.seek(length - 2, os.SEEK_CUR)
    except OSError:
        return None


def _image_truncated(path: Path) -> str | None:
    """Returns why a PNG or JPEG file is cut short (its end marker missing), or None when it ends properly.

    Reads only the file's last bytes: a PNG must end with its IEND chunk, a
    JPEG must have its end-of-image marker (FF D9) within its last
    :data:`JPEG_TAIL_BYTES` bytes. Corruption inside a complete file is found
    when the frame is decoded (the reader then raises InputError naming it).
    """
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(8)
            f.seek(max(0, size - JPEG_TAIL_BYTES))
            tail = f.read()
    except OSError as e:
        return f"cannot be read ({e.strerror})"
    if size == 0:
        return "is empty (0 bytes)"
    if head[:8] == b"\x89PNG\r\n\x1a\n":
        return None if tail.endswith(PNG_END) else f"is truncated ({size} bytes, no PNG IEND chunk at the end)"
    if head[:2] == b"\xff\xd8":
        return None if b"\xff\xd9" in tail else f"is truncated ({size} bytes, no JPEG end-of-image marker)"
    return None


def _list_images(folder: Path) -> list[Path]:
    try:
        entries = sorted(os.listdir(folder))
    except OSError as e:
        raise InputError(f"cannot list the folder ({e.strerror})", folder) from None
    return [folder / n for n in entries if n.lower().endswith(IMAGE_EXTS) and not n.startswith(".")
            and (folder / n).is_file()]


def _find_video(root: Path) -> Path | None:
    videos = sorted(p for p in root.glob("video.*") if p.is_file())
    if len(videos) > 1:
        log.warning("%s: several video files, using %s", root, videos[0].name)
    return videos[0] if videos else None


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


# --------------------------------------------------------------------------- csv files


def _read_csv(path: Path, header: tuple[str, ...]) -> list[list[str]]:
    """Returns the rows (lists of stripped strings) of a CSV whose first columns must be ``header``."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            rows = [[c.strip() for c in r] for r in csv.reader(f) if r and any(c.strip() for c in r)]
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise InputError(f"cannot be read ({_first_line(e)})", path) from None
    if not rows:
        raise InputError(f"is empty (expected the header {','.join(header)})", path)
    got = tuple(c.lower() for c in rows[0][: len(header)])
    if got != header:
        raise InputError(f"bad header {','.join(rows[0])!r} (expected {','.join(header)})", path)
    return rows[1:]


def _numbers(path: Path, rows: list[list[str]], cols: slice, first_line: int = 2) -> np.ndarray:
    """Returns rows[:, cols] as float64, raising InputError naming the first bad line."""
    n_cols = len(range(*cols.indices(10_000)))
    out = np.empty((len(rows), n_cols))
    for k, r in enumerate(rows):
        vals = r[cols]
        if len(vals) != n_cols:
            raise InputError(f"line {k + first_line}: expected {n_cols} values, got {len(vals)}", path)
        try:
            out[k] = [float(v) for v in vals]
        except ValueError:
            raise InputError(f"line {k + first_line}: not a number in {','.join(r)!r}", path) from None
    return out


def read_imu(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Returns (timestamps (N,) s, world_from_camera rotations (N, 3, 3)) of ``imu.csv``, validated."""
    path = Path(path)
    if not path.is_file():
        raise InputError("missing (every capture needs the IMU attitude, timestamp_s,qw,qx,qy,qz)", path)
    rows = _read_csv(path, IMU_HEADER)
    data = _numbers(path, rows, slice(0, 5))
    if len(data) < 2:
        raise InputError(f"needs at least 2 rows to interpolate, got {len(data)}", path)
    bad = ~np.all(np.isfinite(data), axis=1)
    if bad.any():
        raise InputError(f"line {int(np.argmax(bad)) + 2}: NaN or infinite value", path)
    t, q = data[:, 0], data[:, 1:]
    dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.argmax(dt <= 0))
        raise InputError(f"timestamps must be strictly increasing (line {k + 3}: {t[k + 1]} after {t[k]})", path)
    norm = np.linalg.norm(q, axis=1)
    bad = np.abs(norm - 1.0) > QUAT_NORM_TOL
    if bad.any():
        k = int(np.argmax(bad))
        raise InputError(f"line {k + 2}: quaternion norm {norm[k]:.6f} is not 1 (tolerance {QUAT_NORM_TOL})", path)
    return t, quat_wxyz_to_matrix(q / norm[:, None])


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


# --------------------------------------------------------------------------- ground truth


class _MapLoader:
    """Callable: frame index -> ground-truth map at working resolution (nearest-neighbour; normals renormalised)."""

    def __init__(self, folder: Path, stems: tuple[str, ...], warp: _Warp, normals: bool):
        self.folder = folder
        self.stems = stems
        self.warp = warp
        self.normals = normals

    def __call__(self, i: int) -> np.ndarray | None:
        i = _check_index(i, len(self.stems))
        path = self.folder / f"{self.stems[i]}.npy"
        if not path.is_file():
            return None
        try:
            m = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise InputError(f"cannot be read as a .npy array ({_first_line(e)})", path) from None
        want = 3 if self.normals else 2
        if m.ndim != want or (self.normals and m.shape[2] != 3):
            raise InputError(f"has shape {m.shape}, expected {'H x W x 3' if self.normals else 'H x W'}", path)
        m = self.warp(np.ascontiguousarray(m, dtype=np.float32), nearest=True)
        if self.normals:
            n = np.linalg.norm(m, axis=2, keepdims=True)
            m = np.where(n > 1e-6, m / np.maximum(n, 1e-6), 0.0).astype(np.float32)
        return m


def _no_map(i: int) -> None:
    return None


def _gt_key(name: str) -> str:
    name = Path(name.replace("\\", "/")).name
    if "#" in name:
        name = name.rsplit("#", 1)[1]
    return Path(name).stem


def _read_ground_truth(gt: Path, stems: tuple[str, ...], warp: _Warp) -> GroundTruth:
    """Returns the ground truth of the taken frames (poses matched by file stem; missing ones NaN)."""
    F = len(stems)
    R = np.full((F, 3, 3), np.nan)
    C = np.full((F, 3), np.nan)
    poses = gt / "poses.csv"
    if poses.is_file():
        rows = _read_csv(poses, ("file", "qw", "qx", "qy", "qz", "tx", "ty", "tz"))
        vals = _numbers(poses, rows, slice(1, 8))
        if not np.all(np.isfinite(vals)):
            raise InputError("NaN or infinite values", poses)
        norm = np.linalg.norm(vals[:, :4], axis=1)
        if np.any(np.abs(norm - 1.0) > QUAT_NORM_TOL):
            k = int(np.argmax(np.abs(norm - 1.0) > QUAT_NORM_TOL))
            raise InputError(f"line {k + 2}: quaternion norm {norm[k]:.6f} is not 1", poses)
        key_row = {_gt_key(r[0]): k for k, r in enumerate(rows)}
        num_row = {int(k): v for k, v in key_row.items() if k.isdigit()}
        idx = np.array([key_row.get(s, num_row.get(int(s), -1) if s.isdigit() else -1) for s in stems], dtype=np.int64)
        hit = idx >= 0
        if (~hit).any():
            log.warning("%s: no pose for %d of %d frames", poses, int((~hit).sum()), F)
        R[hit] = quat_wxyz_to_matrix(vals[idx[hit], :4] / norm[idx[hit], None])
        C[hit] = vals[idx[hit], 4:]
    lines = np.zeros((0, 6))
    labels = np.zeros(0, dtype=np.int8)
    lines_csv = gt / "lines.csv"
    if lines_csv.is_file():
        rows = _read_csv(lines_csv, ("x1", "y1", "z1", "x2", "y2", "z2", "label"))
        lines = _numbers(lines_csv, rows, slice(0, 6)).reshape(-1, 6)
        labels = np.array([AXIS_LABELS.get(r[6].lower(), -1) if len(r) > 6 else -1 for r in rows], dtype=np.int8)
    scene: dict = {}
    scene_json = gt / "scene.json"
    if scene_json.is_file():
        try:
            scene = json.loads(scene_json.read_text(encoding="utf-8-sig"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise InputError(f"not valid JSON ({_first_line(e)})", scene_json) from None
    has_n = (gt / "normals").is_dir() and any((gt / "normals" / f"{s}.npy").is_file() for s in stems)
    has_d = (gt / "depth").is_dir() and any((gt / "depth" / f"{s}.npy").is_file() for s in stems)
    return GroundTruth(
        R_wc=R, centers=C, lines=lines, line_labels=labels, scene=scene,
        normals=_MapLoader(gt / "normals", stems, warp, True) if has_n else _no_map,
        depth=_MapLoader(gt / "depth", stems, warp, False) if has_d else _no_map,
        has_normals=has_n, has_depth=has_d,
    )


# --------------------------------------------------------------------------- public API


def _check_config(config: CaptureConfig) -> None:
    if isinstance(config.every_k, bool) or not isinstance(config.every_k, int) or config.every_k < 1:
        raise InputError(f"capture.every_k must be an integer >= 1, got {config.every_k!r}")
    if config.max_frames is not None and (not isinstance(config.max_frames, int) or config.max_frames < 1):
        raise InputError(f"capture.max_frames must be an integer >= 1, got {config.max_frames!r}")
    if not (_is_number(config.scale) and 0 < config.scale <= 1):
        raise InputError(f"capture.scale must be in (0, 1], got {config.scale!r}")


def _root(path: str | Path) -> Path:
    root = Path(path)
    if not root.exists():
        raise InputError("capture directory does not exist", root)
    if not root.is_dir():
        raise InputError("is not a capture directory", root)
    return root


def imu_coverage(t_imu: np.ndarray, t_frames: np.ndarray) -> np.ndarray:
    """Returns a (F,) bool mask: frame timestamps inside the IMU span (within 1 µs)."""
    return (t_frames >= t_imu[0] - TIME_TOL_S) & (t_frames <= t_imu[-1] + TIME_TOL_S)


def check_imu_rate(imu_path: Path, t_imu: np.ndarray, frame_rate_hz: float, min_rate_hz: float) -> float:
    """Returns the IMU's mean rate (Hz); InputError when it is below ``min_rate_hz`` and half the frame rate.

    One IMU row per frame is always accepted (capture-format.md allows it);
    a stream much sparser than the frames cannot give each frame its own
    attitude (paper supplement §2 uses it as every frame's initial rotation).
    """
    span = float(t_imu[-1] - t_imu[0])
    rate = (len(t_imu) - 1) / span if span > 0 else math.inf
    if rate < min_rate_hz and rate < 0.5 * frame_rate_hz:
        raise InputError(f"IMU rate {rate:.3g} Hz is far below the frame rate {frame_rate_hz:.3g} Hz "
                         f"(need >= {min_rate_hz:g} Hz or one row per frame)", imu_path)
    return rate


def turn_span_deg(R_wc: np.ndarray) -> float:
    """Returns the yaw span (degrees) swept by the optical axis: max - min of its unwrapped heading.

    The heading is the azimuth of the optical axis (``R_wc[:, :, 2]``)
    projected on the horizontal plane (world +z is up, capture-format.md);
    frames looking within ~12° of straight up or down carry no heading and
    are skipped.
    """
    z = np.asarray(R_wc, dtype=np.float64)[:, :, 2]
    ok = np.hypot(z[:, 0], z[:, 1]) > 0.2
    if ok.sum() < 2:
        return 0.0
    heading = np.unwrap(np.arctan2(z[ok, 1], z[ok, 0]))
    return float(np.degrees(np.ptp(heading)))


def capture_warnings(capture: Capture, config: CaptureConfig | Config = CaptureConfig()) -> list[str]:
    """Returns the warnings about a loaded capture as a spin to reconstruct (also logged); InputError if hopeless.

    * the IMU yaw span over the taken frames (:func:`turn_span_deg`) below
      ``config.min_turn_deg``: InputError (no turn to reconstruct); below
      ``config.full_turn_deg``: a warning, the result covers part of the room;
    * dropped frames: a timestamp gap longer than ``config.max_gap_intervals``
      median frame intervals (a warning: the frames on both sides are still
      used, but tracking across the gap is weaker).
    """
    config = getattr(config, "capture", config)
    imu_path = Path(capture.root) / "imu.csv"
    warnings: list[str] = []
    n = capture.n_frames
    span = turn_span_deg(capture.R_wc_imu)
    if span < config.min_turn_deg:
        raise InputError(f"the IMU heading turns only {span:.1f} deg over the {n} frames; a spin capture needs at "
                         f"least {config.min_turn_deg:g} deg (ideally a full turn)", imu_path)
    if span < config.full_turn_deg:
        warnings.append(f"{imu_path}: partial turn: the IMU heading spans {span:.1f} deg (< "
                        f"{config.full_turn_deg:g} deg): the reconstruction covers only part of the room")
    t = np.asarray(capture.timestamps, dtype=np.float64)
    if n >= 3:
        dt = np.diff(t)
        med = float(np.median(dt))
        gaps = np.flatnonzero(dt > config.max_gap_intervals * med)
        if len(gaps):
            k = int(gaps[np.argmax(dt[gaps])])
            warnings.append(f"{capture.root}: {len(gaps)} gap(s) in the frame timestamps longer than "
                            f"{config.max_gap_intervals:g} frame intervals ({med * 1e3:.1f} ms), e.g. "
                            f"{dt[k]:.3f} s between {capture.frame_names[k]} and {capture.frame_names[k + 1]} "
                            f"(dropped frames?)")
    for w in warnings:
        log.warning("%s", w)
    return warnings


def load_capture(path: str | Path, config: CaptureConfig | Config = CaptureConfig()) -> Capture:
    """Returns the validated :class:`Capture` of a capture directory (``capture-format.md``).

    Frames are taken every ``config.every_k``, at most ``config.max_frames``,
    downscaled by ``config.scale`` (images and intrinsics alike) and, for
    OPENCV cameras, undistorted (``Capture.camera`` is then PINHOLE). The IMU
    attitude is slerped to each taken frame's timestamp. Raises
    :class:`InputError` (one line naming the file) for any bad input,
    including taken frames outside the IMU's time span.
    """
    config = getattr(config, "capture", config)  # a whole Config works too
    _check_config(config)
    root = _root(path)
    camera_json = root / "camera.json"
    raw_camera, fps = read_camera(camera_json)
    imu_path = root / "imu.csv"
    t_imu, R_imu = read_imu(imu_path)
    source = _read_source(root, raw_camera, camera_json)
    t_all, t_from, frame_rate = _timestamps(root, source, fps)
    check_imu_rate(imu_path, t_imu, frame_rate, config.min_imu_rate_hz)

    take = np.arange(0, len(source.names), config.every_k)
    if config.max_frames is not None:
        take = take[: config.max_frames]
    t = t_all[take]
    inside = imu_coverage(t_imu, t)
    if not inside.all():
        out = t[~inside]
        raise InputError(f"{int((~inside).sum())} of {len(t)} frames (times {out.min():.3f}..{out.max():.3f} s, "
                         f"from {t_from}) lie outside the IMU time span {t_imu[0]:.3f}..{t_imu[-1]:.3f} s",
                         imu_path)
    R_wc = slerp_rotations(t_imu, R_imu, np.clip(t, t_imu[0], t_imu[-1]))

    work = working_camera(raw_camera, config.scale)
    warp = _Warp(raw_camera, work)
    if source.kind == "frames":
        reader = _ImageReader([source.paths[k] for k in take], (raw_camera.width, raw_camera.height), warp,
                              camera_json)
    else:
        msec = source.msec
        usable = msec is not None and np.all(np.isfinite(msec)) and np.all(np.diff(msec) > 0)
        reader = _VideoReader(source.paths[0], take, msec if usable else None, warp)
    stems = tuple(source.stems[k] for k in take)
    gt_dir = root / "ground_truth"
    gt = _read_ground_truth(gt_dir, stems, warp) if gt_dir.is_dir() else None
    log.info("capture %s: %d of %d frames (%s), %dx%d %s, timestamps from %s, IMU %d rows",
             root, len(take), len(source.names), source.kind, work.width, work.height, raw_camera.model,
             t_from, len(t_imu))
    return Capture(root=root, camera=work, frame_names=tuple(source.names[k] for k in take), timestamps=t,
                   R_wc_imu=R_wc, ground_truth=gt, reader=reader)


def inspect_capture(path: str | Path) -> dict[str, Any]:
    """Returns a description of a capture: frames, resolution, camera, fps, duration, IMU coverage, ground truth.

    Structural problems (a missing or malformed file) raise :class:`InputError`
    as in :func:`load_capture`; frames outside the IMU span are reported in
    ``imu.coverage`` and ``problems`` instead.
    """
    root = _root(path)
    camera_json = root / "camera.json"
    camera, fps = read_camera(camera_json)
    t_imu, R_imu = read_imu(root / "imu.csv")
    source = _read_source(root, camera, camera_json)
    t, t_from, rate = _timestamps(root, source, fps)
    inside = imu_coverage(t_imu, t)
    problems = []
    during = (t_imu >= t[0] - TIME_TOL_S) & (t_imu <= t[-1] + TIME_TOL_S) if len(t) else np.zeros(0, bool)
    turn = turn_span_deg(R_imu[during]) if during.sum() >= 2 else turn_span_deg(R_imu)
    if not inside.all():
        out = t[~inside]
        problems.append(f"imu.csv: {int((~inside).sum())} of {len(t)} frames (times {out.min():.3f}.."
                        f"{out.max():.3f} s) lie outside the IMU time span {t_imu[0]:.3f}..{t_imu[-1]:.3f} s")
    gt_dir = root / "ground_truth"
    gt = None
    if gt_dir.is_dir():
        def count(sub: str) -> int:
            d = gt_dir / sub
            return sum(1 for s in source.stems if (d / f"{s}.npy").is_file()) if d.is_dir() else 0

        def rows(name: str) -> int | None:
            p = gt_dir / name
            if not p.is_file():
                return None
            with open(p, newline="", encoding="utf-8-sig") as f:
                return max(0, sum(1 for r in csv.reader(f) if r and any(c.strip() for c in r)) - 1)

        gt = {"poses": rows("poses.csv"), "lines": rows("lines.csv"), "scene": (gt_dir / "scene.json").is_file(),
              "normals": count("normals"), "depth": count("depth")}
    duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    imu_span = float(t_imu[-1] - t_imu[0])
    return {
        "path": str(root),
        "source": source.kind if source.kind == "frames" else source.paths[0].name,
        "frames": len(source.names),
        "resolution": [camera.width, camera.height],
        "camera_model": camera.model,
        "params": [float(p) for p in camera.params],
        "fps": round(rate, 4),
        "timestamps_from": t_from,
        "time_span_s": [float(t[0]), float(t[-1])] if len(t) else None,
        "duration_s": round(duration, 4),
        "imu": {
            "rows": len(t_imu),
            "rate_hz": round((len(t_imu) - 1) / imu_span, 3),
            "time_span_s": [float(t_imu[0]), float(t_imu[-1])],
            "turn_deg": round(turn, 2),
            "coverage": {"frames_inside": int(inside.sum()), "frames_outside": int((~inside).sum()),
                         "fraction": float(inside.mean()) if len(inside) else 0.0},
        },
        "ground_truth": gt,
        "problems": problems,
    }


def format_inspection(info: dict[str, Any]) -> str:
    """Returns :func:`inspect_capture`'s description as a readable multi-line table."""
    imu = info["imu"]
    cov = imu["coverage"]
    span = info["time_span_s"] or [0.0, 0.0]
    model = info["camera_model"]
    params = ", ".join(f"{p:g}" for p in info["params"])
    rows = [
        ("capture", info["path"]),
        ("frames", f"{info['frames']} from {info['source']}"),
        ("resolution", f"{info['resolution'][0]} x {info['resolution'][1]}"),
        ("camera", f"{model} [{params}]" + (" (frames are undistorted on load)" if model == "OPENCV" else "")),
        ("fps", f"{info['fps']:g} (timestamps from {info['timestamps_from']})"),
        ("duration", f"{info['duration_s']:.3f} s  ({span[0]:.3f} .. {span[1]:.3f} s)"),
        ("IMU", f"{imu['rows']} rows, {imu['rate_hz']:g} Hz, {imu['time_span_s'][0]:.3f} .. "
                f"{imu['time_span_s'][1]:.3f} s, heading turns {imu.get('turn_deg', 0.0):g} deg"),
        ("IMU coverage", f"{cov['frames_inside']} of {info['frames']} frames ({100 * cov['fraction']:.1f}%)"),
    ]
    gt = info["ground_truth"]
    if gt is None:
        rows.append(("ground truth", "none"))
    else:
        parts = []
        if gt["poses"] is not None:
            parts.append(f"poses ({gt['poses']})")
        if gt["lines"] is not None:
            parts.append(f"lines ({gt['lines']})")
        if gt["scene"]:
            parts.append("scene.json")
        if gt["normals"]:
            parts.append(f"normals ({gt['normals']} frames)")
        if gt["depth"]:
            parts.append(f"depth ({gt['depth']} frames)")
        rows.append(("ground truth", ", ".join(parts) or "empty folder"))
    for p in info["problems"]:
        rows.append(("PROBLEM", p))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


# --------------------------------------------------------------------------- helpers


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)


def _first_line(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def _check_index(i: int, n: int) -> int:
    i = int(i)
    if i < 0:
        i += n
    if not 0 <= i < n:
        raise IndexError(f"frame {i} out of range (capture has {n} frames)")
    return i
