"""JPEG thumbnails of frames: made once, while detection already holds each decoded frame."""
from __future__ import annotations

import cv2
import numpy as np

JPEG_QUALITY = 80


def jpeg_thumbnail(img_bgr: np.ndarray, width: int) -> bytes:
    """Returns the JPEG bytes of ``img_bgr`` downscaled to ``width`` pixels wide."""
    h, w = img_bgr.shape[:2]
    k = w // width  # integer box-filter first (OpenCV's fast INTER_AREA path), then bilinear: ~7x faster
    if k >= 2:
        img_bgr = cv2.resize(img_bgr, (w // k, h // k), interpolation=cv2.INTER_AREA)
    if img_bgr.shape[1] != width:
        img_bgr = cv2.resize(img_bgr, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_LINEAR)
    ok, buf = cv2.imencode(".jpg", img_bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()
