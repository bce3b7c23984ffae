"""``frames/``: PNG or JPEG images, in file-name order (``capture-format.md``).

Headers are read without decoding (size, truncation); :class:`_ImageReader`
decodes one frame on demand.
"""
from __future__ import annotations

import os
import struct
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from .camera import _Warp
from .validate import _check_index

IMAGE_EXTS = (".png", ".jpg", ".jpeg")
PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # the IEND chunk every complete PNG ends with
JPEG_TAIL_BYTES = 1024  # a complete JPEG has its end-of-image marker (FF D9) this close to its end
# pixels as stored: EXIF orientation is ignored so that frames agree with their header and camera.json
_IMREAD_FLAGS = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION


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
