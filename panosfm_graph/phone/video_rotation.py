"""The camera's rotation between consecutive video frames, from feature flow (for the time offset, ``sync``).

A spin is nearly a pure rotation, so corners tracked from frame k to k+1
(OpenCV's Shi-Tomasi corners and pyramidal Lucas-Kanade flow) map through
the infinite homography ``K R K^-1``; the RANSAC homography's inliers give
the rotation by orthogonal Procrustes on their rays (``scipy``'s
``Rotation.align_vectors``). The returned rotation vectors are the camera's
body-frame turn over each interval, what a gyroscope fixed to the camera
would integrate: ``R_wc(t_k+1) = R_wc(t_k) Exp(theta_k)``. Parallax makes the
turn about the spin axis look a few per cent larger; ``sync`` fits that as a
scale and leans on the other two axes.
"""
from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError

MAX_WIDTH = 480  # frames are downscaled to at most this width for the flow
MAX_CORNERS = 300
MIN_INLIERS = 20  # fewer tracked inliers: no rotation for that interval (NaN)


def frame_rotations(video, K: np.ndarray, max_width: int = MAX_WIDTH) -> np.ndarray:
    """Returns (F-1, 3) the camera-frame rotation vectors (rad) between consecutive frames of ``video``.

    ``K`` is the intrinsic matrix at the video's resolution; rows are NaN
    where too few corners were tracked (blank walls, blur).
    """
    cap = cv2.VideoCapture(str(video))
    if not cap.isOpened():
        raise InputError("OpenCV cannot open this video (unknown container or codec)", video)
    out = []
    prev = None
    scale = 1.0
    Kinv = None
    try:
        while True:
            ok, img = cap.read()
            if not ok or img is None:
                break
            grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            if Kinv is None:
                scale = min(1.0, max_width / grey.shape[1])
                Ks = np.diag([scale, scale, 1.0]) @ K
                Kinv = np.linalg.inv(Ks)
            if scale < 1.0:
                grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            if prev is not None:
                out.append(_pair_rotation(prev, grey, Kinv))
            prev = grey
    finally:
        cap.release()
    if not out:
        raise InputError("fewer than 2 frames could be decoded", video)
    return np.array(out)


def _pair_rotation(a: np.ndarray, b: np.ndarray, Kinv: np.ndarray) -> np.ndarray:
    """Returns the rotation vector theta with rays_b = Exp(theta)^T rays_a (NaN (3,) when not enough flow)."""
    nan = np.full(3, np.nan)
    p0 = cv2.goodFeaturesToTrack(a, MAX_CORNERS, 0.01, 8)
    if p0 is None or len(p0) < MIN_INLIERS:
        return nan
    p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None, winSize=(21, 21), maxLevel=3)
    good = st.ravel() == 1
    if good.sum() < MIN_INLIERS:
        return nan
    x0, x1 = p0.reshape(-1, 2)[good], p1.reshape(-1, 2)[good]
    _, inl = cv2.findHomography(x0, x1, cv2.RANSAC, 1.0)
    if inl is None or inl.sum() < MIN_INLIERS:
        return nan
    inl = inl.ravel() == 1
    r0 = np.column_stack([x0[inl], np.ones(inl.sum())]) @ Kinv.T
    r1 = np.column_stack([x1[inl], np.ones(inl.sum())]) @ Kinv.T
    r0 /= np.linalg.norm(r0, axis=1, keepdims=True)
    r1 /= np.linalg.norm(r1, axis=1, keepdims=True)
    # camera b from camera a: r1 = R_ba r0, and R_ba = R_wc(b)^T R_wc(a) = Exp(theta)^T
    R_ba, _ = Rotation.align_vectors(r1, r0)
    return R_ba.inv().as_rotvec()
