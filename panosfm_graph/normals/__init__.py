"""Per-frame surface normals in the world frame (paper §3.2), from one of several sources.

LIMAP-style: one small base class (:class:`NormalSource`) and one module per
source, registered by name in :data:`SOURCES`:

* ``oracle`` (:mod:`.oracle`): the capture's ``ground_truth/normals``;
* ``orientation-map`` (:mod:`.orientation_map`): Lee, Hebert & Kanade's
  geometric orientation map from the Manhattan line segments (no learning);
* ``model`` (:mod:`.onnx`): an ONNX image-to-normal network run on the CPU
  (falls back to ``orientation-map`` with a warning when no model exists).

Every source produces camera-frame normals per frame at low resolution
(``NormalsConfig.width`` wide, aspect kept); the base rotates them into the
world with the refined rotations ``pre.R_wc`` (the paper projects each normal
onto the global Manhattan frame). Normals point towards the camera.

A new source is one file with a :class:`NormalSource` subclass plus one
:func:`register_source` call.
"""
from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from ..config import NormalsConfig
from ..data import Camera, Capture, NormalMaps, Preprocessed
from ..errors import InputError
from ..progress import progress

log = logging.getLogger("panosfm.normals")


def lowres_shape(camera: Camera, width: int) -> tuple[int, int, float]:
    """Returns (h, w, scale) of the normal maps: ``width`` wide, the camera's aspect kept.

    ``scale`` is normal-map pixels per working-image pixel, so working pixel
    (u, v) maps to (u * scale, v * scale).
    """
    w = int(min(width, camera.width)) if width > 0 else camera.width
    scale = w / camera.width
    h = max(1, int(round(camera.height * scale)))
    return h, w, scale


def lowres_rays(camera: Camera, h: int, w: int, scale: float) -> np.ndarray:
    """Returns (h, w, 3) float32 unit camera-frame rays through the low-resolution pixel grid."""
    K = camera.K
    x = (np.arange(w) / scale - K[0, 2]) / K[0, 0]
    y = (np.arange(h) / scale - K[1, 2]) / K[1, 1]
    X, Y = np.meshgrid(x, y)
    d = np.stack([X, Y, np.ones_like(X)], axis=-1)
    return (d / np.linalg.norm(d, axis=-1, keepdims=True)).astype(np.float32)


def resize_normals(n: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Returns (h, w, 3) float32 unit normals and (h, w) validity from a full-size normal image.

    Area-averaged, then renormalised; pixels whose averaged vector is short
    (no surface, or strongly mixed normals) are invalid.
    """
    import cv2

    n = np.nan_to_num(np.asarray(n, dtype=np.float32))
    if n.shape[:2] != (h, w):
        n = cv2.resize(n, (w, h), interpolation=cv2.INTER_AREA)
    norm = np.linalg.norm(n, axis=-1)
    valid = norm > 0.5
    n = n / np.maximum(norm, 1e-6)[..., None]
    n[~valid] = 0.0
    return n, valid


class NormalSource:
    """Base of a normal source: camera-frame normals per frame; :meth:`estimate` does the rest."""

    name = ""

    def __init__(self, config: NormalsConfig):
        self.config = config

    def prepare(self, capture: Capture, pre: Preprocessed) -> None:
        """Checks inputs and loads what the source needs, before the per-frame loop."""

    def camera_normals(
        self, capture: Capture, pre: Preprocessed, f: int, h: int, w: int, scale: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Returns frame ``f``'s (h, w, 3) camera-frame unit normals (towards the camera) and (h, w) validity."""
        raise NotImplementedError

    def estimate(self, capture: Capture, pre: Preprocessed, frames: np.ndarray | None = None,
                 previous: NormalMaps | None = None) -> NormalMaps:
        """Returns the world-frame :class:`NormalMaps` of all frames (paper §3.2).

        ``frames`` (streaming, ``stream.py``): only those frames are estimated; the others are
        copied from ``previous`` (the maps of the first ``previous.maps.shape[0]`` frames), or left
        invalid where it has none.
        """
        self.prepare(capture, pre)
        h, w, scale = lowres_shape(capture.camera, self.config.width)
        F = capture.n_frames
        maps = np.zeros((F, h, w, 3), dtype=np.float16)
        valid = np.zeros((F, h, w), dtype=bool)
        if previous is not None and frames is not None:
            k = min(F, previous.maps.shape[0])
            maps[:k], valid[:k] = previous.maps[:k], previous.valid[:k]
        todo = range(F) if frames is None else np.asarray(frames, np.int64)
        for f in progress(todo, f"normals ({self.name})", total=len(todo)):
            n_c, ok = self.camera_normals(capture, pre, f, h, w, scale)
            # world = R_wc @ n_c for every pixel, i.e. n_c @ R_wc^T on rows
            maps[f] = (n_c.reshape(-1, 3) @ pre.R_wc[f].T).reshape(h, w, 3).astype(np.float16)
            valid[f] = ok
        return NormalMaps(maps=maps, valid=valid, scale=scale, source=self.name)


SOURCES: dict[str, Callable[[NormalsConfig], NormalSource]] = {}


def register_source(name: str, factory: Callable[[NormalsConfig], NormalSource]) -> None:
    """Registers a normal source under ``name`` (the value of ``NormalsConfig.source``)."""
    SOURCES[name] = factory


def make_source(config: NormalsConfig) -> NormalSource:
    """Returns the :class:`NormalSource` selected by ``config.source``."""
    if config.source not in SOURCES:
        raise InputError(f"unknown normals source {config.source!r}; choose one of {sorted(SOURCES)}")
    return SOURCES[config.source](config)


def estimate_normals(capture: Capture, pre: Preprocessed, config: NormalsConfig, frames: np.ndarray | None = None,
                     previous: NormalMaps | None = None) -> NormalMaps:
    """Returns world-frame per-frame surface normal maps from the source ``config.source`` (paper §3.2).

    ``NormalMaps.source`` names the source actually used (``model`` falls back
    to ``orientation-map`` when no model file exists). ``frames``/``previous``: only those frames
    are estimated, the others copied from ``previous`` (:meth:`NormalSource.estimate`).
    """
    return make_source(config).estimate(capture, pre, frames, previous)


def camera_frame_maps(maps: NormalMaps, R_wc: np.ndarray) -> np.ndarray:
    """Returns (F, h, w, 3) float32 camera-frame normals of world-frame ``maps`` rotated by ``R_wc``."""
    n = maps.maps.astype(np.float32)
    return np.einsum("fhwi,fij->fhwj", n, R_wc)  # n_c = R_wc^T n_w


def normal_accuracy(maps: NormalMaps, capture: Capture, R_wc: np.ndarray, frames=None) -> dict:
    """Returns the accuracy of ``maps`` against ``ground_truth/normals``: median angular error and share within 20°.

    Compared in the camera frame (the maps rotated back with the ``R_wc``
    they were made with), over pixels valid in both; ``coverage`` is the share
    of GT-valid pixels the source labels at all.
    """
    gt = capture.ground_truth
    if gt is None or not gt.has_normals:
        raise InputError("no ground_truth/normals to compare with", capture.root)
    F, h, w = maps.valid.shape
    frames = range(F) if frames is None else frames
    errs, n_gt, n_est = [], 0, 0
    for f in frames:
        g, g_ok = resize_normals(gt.normals(f), h, w)
        n = maps.maps[f].astype(np.float32).reshape(-1, 3) @ R_wc[f]
        ok = g_ok.ravel() & maps.valid[f].ravel()
        a, b = n[ok], g.reshape(-1, 3)[ok]
        errs.append(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))))
        n_gt += int(g_ok.sum())
        n_est += int(ok.sum())
    e = np.concatenate(errs) if errs else np.zeros(0)
    return {
        "source": maps.source,
        "median_deg": float(np.median(e)) if len(e) else float("nan"),
        "within_20deg": float(np.mean(e < 20.0)) if len(e) else float("nan"),
        "coverage": n_est / max(n_gt, 1),
    }


from .oracle import OracleNormals  # noqa: E402
from .orientation_map import OrientationMapNormals  # noqa: E402
from .onnx import OnnxNormals  # noqa: E402

register_source("oracle", OracleNormals)
register_source("orientation-map", OrientationMapNormals)
register_source("model", OnnxNormals)

__all__ = [
    "NormalSource",
    "SOURCES",
    "register_source",
    "make_source",
    "estimate_normals",
    "lowres_shape",
    "lowres_rays",
    "resize_normals",
    "camera_frame_maps",
    "normal_accuracy",
    "OracleNormals",
    "OrientationMapNormals",
    "OnnxNormals",
]
