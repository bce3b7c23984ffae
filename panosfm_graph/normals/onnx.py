"""The ``model`` normal source: an image-to-normal ONNX network run with onnxruntime on the CPU.

The paper (§3.2) uses Wang et al.'s network; any network with this contract works:

* input: one float32 tensor ``1 x 3 x H x W``, RGB in [0, 1] (the frame resized
  to ``H x W``; when the model's H and W are dynamic the runner uses
  ``NormalsConfig.width`` wide with the frame's aspect, e.g. 256 x 144);
* output: the first output, float32 ``1 x 3 x H' x W'`` camera-frame normals
  in OpenCV axes (x right, y down, z forward), any length (renormalised here);
  normals should point towards the camera (flipped here where they do not).

The model is ``NormalsConfig.model_path`` (a user's own; missing -> an
:class:`InputError`) or else the shipped ``panosfm_graph/models/normals.onnx``.
When neither exists the source falls back to ``orientation-map`` with a
logged warning (``NormalMaps.source`` then says ``orientation-map``).
"""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from ..data import Capture, NormalMaps, Preprocessed
from ..errors import InputError
from . import NormalSource, lowres_rays

log = logging.getLogger("panosfm.normals")

SHIPPED_MODEL = Path(__file__).resolve().parent.parent / "models" / "normals.onnx"


def load_session(path: str | Path):
    """Returns an onnxruntime CPU ``InferenceSession`` for the model at ``path`` (InputError if unusable)."""
    import onnxruntime as ort

    path = Path(path)
    if not path.is_file():
        raise InputError("normal model not found", path)
    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    try:
        sess = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises several types for a bad file
        raise InputError(f"cannot load ONNX model: {str(exc).splitlines()[0]}", path) from exc
    inp = sess.get_inputs()[0]
    if len(inp.shape) != 4 or (isinstance(inp.shape[1], int) and inp.shape[1] != 3):
        raise InputError(f"model input must be 1x3xHxW, got {inp.shape}", path)
    return sess


def model_input_size(sess, width: int, aspect: float) -> tuple[int, int]:
    """Returns the (H, W) the model is fed: its static size, else ``width`` wide with the frame's ``aspect`` (h / w)."""
    shape = sess.get_inputs()[0].shape
    H, W = shape[2], shape[3]
    if isinstance(H, int) and isinstance(W, int) and H > 0 and W > 0:
        return H, W
    W = int(width)
    H = max(8, int(round(W * aspect / 8.0)) * 8)
    return H, W


def run_model(sess, bgr: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Returns the model's (H', W', 3) float32 camera-frame normals for one BGR uint8 image."""
    H, W = size
    rgb = cv2.cvtColor(cv2.resize(bgr, (W, H), interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)
    x = (rgb.astype(np.float32) / 255.0).transpose(2, 0, 1)[None]
    out = sess.run(None, {sess.get_inputs()[0].name: x})[0]
    if out.ndim != 4 or out.shape[1] != 3:
        raise InputError(f"model output must be 1x3xHxW, got {tuple(out.shape)}")
    return np.ascontiguousarray(out[0].transpose(1, 2, 0), dtype=np.float32)


class OnnxNormals(NormalSource):
    """Normals from an ONNX image-to-normal network (paper §3.2's deep network)."""

    name = "model"

    def _model_path(self) -> Path | None:
        if self.config.model_path:
            return Path(self.config.model_path)
        return SHIPPED_MODEL if SHIPPED_MODEL.is_file() else None

    def estimate(self, capture: Capture, pre: Preprocessed, frames=None, previous=None) -> NormalMaps:
        """Returns the model's world-frame normal maps, or the orientation map's when no model exists."""
        if self._model_path() is None:
            from .orientation_map import OrientationMapNormals

            log.warning(
                "no normal model (%s missing, no model_path given): falling back to the orientation map",
                SHIPPED_MODEL,
            )
            return OrientationMapNormals(self.config).estimate(capture, pre, frames, previous)
        return super().estimate(capture, pre, frames, previous)

    def prepare(self, capture: Capture, pre: Preprocessed) -> None:
        self._sess = load_session(self._model_path())
        cam = capture.camera
        self._size = model_input_size(self._sess, self.config.width, cam.height / cam.width)
        self._rays = None

    def camera_normals(self, capture, pre, f, h, w, scale):
        """Returns the network's camera-frame normals of frame ``f`` at (h, w), flipped towards the camera."""
        if self._rays is None:
            self._rays = lowres_rays(capture.camera, h, w, scale)
        n = run_model(self._sess, capture.frame(f), self._size)
        n = cv2.resize(n, (w, h), interpolation=cv2.INTER_LINEAR)
        norm = np.linalg.norm(n, axis=-1)
        valid = np.isfinite(norm) & (norm > 1e-3)
        n = np.nan_to_num(n / np.maximum(norm, 1e-6)[..., None])
        flip = np.sum(n * self._rays, axis=-1) > 0
        n[flip] *= -1.0
        n[~valid] = 0.0
        return n, valid
