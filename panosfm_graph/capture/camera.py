"""``camera.json`` (COLMAP camera models) and the working camera the pipeline sees (``capture-format.md``).

:func:`read_camera` validates the intrinsics; :func:`working_camera` is the
camera of the downscaled (``CaptureConfig.scale``) and, for OPENCV,
undistorted images, and :class:`_Warp` turns a raw image into that working
image.
"""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np

from ..data import Camera
from ..errors import InputError
from .validate import _first_line, _is_number

N_PARAMS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "OPENCV": 8}
FOCAL_RANGE_FRAC = (0.2, 10.0)  # plausible focal length, as a fraction of the image width
PROVISIONAL_HFOV_DEG = 65.0  # a capture without a focal length is loaded with this field of view (then estimated)


def read_camera(path: str | Path) -> tuple[Camera, float | None]:
    """Returns the camera of ``camera.json`` (COLMAP model and parameter order) and its ``fps`` (or None).

    Without ``params`` (PINHOLE / SIMPLE_PINHOLE only) the focal length is unknown: NaN, the principal point
    the image centre (:func:`focal_known`; the pipeline estimates it, ``lines/focal.py``).
    """
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
    if params is None:  # the focal length is not known: NaN until the pipeline estimates it
        if model == "OPENCV":
            raise InputError("OPENCV needs its 'params' (distortion); omit them only for PINHOLE or SIMPLE_PINHOLE",
                             path)
        w, h = size
        params = [math.nan] * (1 if model == "SIMPLE_PINHOLE" else 2) + [(w - 1) / 2.0, (h - 1) / 2.0]
        return Camera(model, w, h, np.asarray(params, dtype=np.float64)), _fps(data, path)
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
    return Camera(model, size[0], size[1], params), _fps(data, path)


def _fps(data: dict, path: Path) -> float | None:
    """Returns camera.json's optional ``fps``."""
    fps = data.get("fps")
    if fps is not None:
        if not _is_number(fps) or not math.isfinite(fps) or fps <= 0:
            raise InputError(f"'fps' must be a positive number, got {fps!r}", path)
        fps = float(fps)
    return fps


def focal_known(camera: Camera) -> bool:
    """Returns whether ``camera.json`` gave the focal length (``params`` omitted: NaN, estimated by the pipeline)."""
    return bool(np.all(np.isfinite(camera.params)))


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


def hfov_deg(focal_px: float, width: int) -> float:
    """Returns the horizontal field of view (deg) of a centred pinhole camera."""
    return float(np.degrees(2.0 * np.arctan(0.5 * width / focal_px)))


def focal_from_hfov(hfov: float, width: int) -> float:
    """Returns the focal length (px) of a centred pinhole camera with this horizontal field of view (deg)."""
    return float(0.5 * width / np.tan(np.radians(hfov) / 2.0))


def with_focal(camera: Camera, focal_px: float) -> Camera:
    """Returns ``camera`` with fx = ``focal_px`` and fy keeping the aspect fy / fx (1 where unknown); the principal
    point and distortion kept."""
    p = np.array(camera.params, dtype=np.float64)
    if camera.model == "SIMPLE_PINHOLE":
        p[0] = focal_px
    else:
        aspect = p[1] / p[0] if np.isfinite(p[0]) and np.isfinite(p[1]) and p[0] > 0 else 1.0
        p[0], p[1] = focal_px, focal_px * aspect
    return dataclasses.replace(camera, params=p)
