"""Shared fixtures: ``tiny_capture`` writes a small valid capture by hand (see ``capture-format.md``).

The scene is a box room (x, y in [-2, 2] m, floor at z = -1.4 m, ceiling at
z = 1.2 m) whose four walls carry coloured rectangles (doors, windows). A
camera held 0.3 m in front of a body turns about the vertical with a small
pitch wobble; frames are ray-cast analytically (2x2 supersampled), so the
images, ground-truth poses, lines, normals and depth all agree exactly.

    def test_something(tiny_capture):
        root = tiny_capture(n_frames=8, model="OPENCV", video=True)
        truth = tiny_capture.rotation(tiny_capture.times(8))   # (8, 3, 3) R_wc

Parameters of ``tiny_capture(...)``: ``model`` (PINHOLE, SIMPLE_PINHOLE,
OPENCV), ``n_frames``, ``size`` (w, h), ``video`` (write ``video.mp4``
instead of ``frames/``), ``frames_csv`` (write ``frames.csv``), ``imu_rate``
(Hz; ``None`` = one IMU row per frame), ``fps``, ``t0`` (first timestamp;
non-zero needs ``frames_csv`` since video/fps timestamps start at 0),
``ground_truth``, ``ext`` (".png" / ".jpg"), ``distortion`` (OPENCV k1 k2 p1
p2), ``yaw_rate_deg_s``, ``imu_drift_deg_s`` (IMU yaw drift), ``name``.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

ROOM_HALF_M = 2.0
FLOOR_Z_M, CEILING_Z_M = -1.4, 1.2
BODY_M = np.array([0.2, -0.1, 0.0])  # the turning person's body axis
ARM_M = 0.3  # camera centre this far in front of the body axis
# camera frame -> world at yaw 0: optical axis +x, image right -y, image down -z
R_WC0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
# rectangles on the walls: (wall, a0, a1, b0, b1, BGR); wall k: 0 x=+2, 1 y=+2, 2 x=-2, 3 y=-2;
# a runs along the wall (left to right seen from inside), b is height z
RECTS = [
    (0, -0.5, 0.4, -1.4, 0.6, (40, 60, 200)),
    (0, 0.8, 1.6, 0.0, 0.7, (200, 180, 60)),
    (1, -1.2, -0.3, -0.3, 0.4, (60, 200, 80)),
    (1, 0.5, 1.5, -1.4, 0.5, (30, 30, 120)),
    (2, -0.8, 0.8, -0.2, 0.6, (220, 220, 220)),
    (3, -1.5, -0.7, -0.5, 0.5, (150, 40, 150)),
    (3, 0.2, 1.0, -1.4, 0.7, (90, 140, 30)),
]
WALL_BGR = [(150, 150, 160), (120, 160, 170), (170, 140, 120), (140, 140, 140)]
FLOOR_BGR, CEILING_BGR = (60, 70, 80), (235, 235, 230)
DEFAULT_DISTORTION = (-0.12, 0.03, 0.001, -0.0005)


def _wall_point(wall: int, a, b):
    """World points (..., 3) at in-wall coordinates (a, b) of wall ``wall``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    h = np.full_like(a, ROOM_HALF_M)
    xy = [(h, a), (-a, h), (-h, -a), (a, -h)][wall]
    return np.stack([xy[0], xy[1], b], axis=-1)


class TinyCapture:
    """Factory (the ``tiny_capture`` fixture): ``tiny_capture(**params) -> Path`` of a new capture."""

    def __init__(self, tmp_path: Path):
        self.tmp_path = tmp_path
        self.count = 0

    # ---- the scene's truth, usable by tests
    @staticmethod
    def yaw(t, yaw_rate_deg_s: float = 30.0):
        return np.radians(yaw_rate_deg_s) * np.asarray(t, float)

    @staticmethod
    def rotation(t, yaw_rate_deg_s: float = 30.0) -> np.ndarray:
        """Returns (N, 3, 3) true world_from_camera rotations at times ``t`` (s)."""
        t = np.atleast_1d(np.asarray(t, float))
        yaw = TinyCapture.yaw(t, yaw_rate_deg_s)
        pitch = np.radians(3.0) * np.sin(2 * np.pi * 0.7 * t)  # about the camera x axis
        roll = np.radians(1.5) * np.sin(2 * np.pi * 0.4 * t + 0.3)  # about the optical axis
        Rz = Rotation.from_euler("z", yaw[:, None]).as_matrix()
        Rc = Rotation.from_euler("xz", np.stack([pitch, roll], axis=1)).as_matrix()
        return Rz @ R_WC0 @ Rc

    @staticmethod
    def center(t, yaw_rate_deg_s: float = 30.0) -> np.ndarray:
        """Returns (N, 3) true camera centres at times ``t``: on a circle about the body axis."""
        yaw = TinyCapture.yaw(np.atleast_1d(t), yaw_rate_deg_s)
        return BODY_M + ARM_M * np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=1)

    @staticmethod
    def times(n_frames: int, fps: float = 10.0, t0: float = 0.0) -> np.ndarray:
        return t0 + np.arange(n_frames) / fps

    @staticmethod
    def K(size=(160, 120), focal: float | None = None) -> np.ndarray:
        w, h = size
        f = focal or 0.6 * w
        return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])

    @staticmethod
    def lines() -> tuple[np.ndarray, np.ndarray]:
        """Returns the scene's 3D edges (M, 6) and Manhattan labels (M,): room edges + rectangle borders."""
        h, f, c = ROOM_HALF_M, FLOOR_Z_M, CEILING_Z_M
        segs, labels = [], []
        for z in (f, c):
            for sx, sy, ex, ey, lab in [(-h, -h, h, -h, 0), (-h, h, h, h, 0), (-h, -h, -h, h, 1), (h, -h, h, h, 1)]:
                segs.append([sx, sy, z, ex, ey, z])
                labels.append(lab)
        for x in (-h, h):
            for y in (-h, h):
                segs.append([x, y, f, x, y, c])
                labels.append(2)
        for wall, a0, a1, b0, b1, _ in RECTS:
            for (pa, pb), (qa, qb) in [((a0, b0), (a1, b0)), ((a0, b1), (a1, b1)), ((a0, b0), (a0, b1)), ((a1, b0), (a1, b1))]:
                p, q = _wall_point(wall, pa, pb), _wall_point(wall, qa, qb)
                segs.append(np.concatenate([p, q]))
                d = np.abs(q - p)
                labels.append(int(np.argmax(d)))
        return np.asarray(segs, float), np.asarray(labels, np.int8)

    @staticmethod
    def cast(K, R_wc, center, pix, color: bool = True) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
        """Returns (BGR float (N, 3) or None, depth (N,), camera-frame normals (N, 3)) of undistorted pixels ``pix``."""
        n = len(pix)
        d_cam = np.stack([(pix[:, 0] - K[0, 2]) / K[0, 0], (pix[:, 1] - K[1, 2]) / K[1, 1], np.ones(n)], 1)
        d = d_cam @ R_wc.T
        bound = np.where(d > 0, [ROOM_HALF_M, ROOM_HALF_M, CEILING_Z_M], [-ROOM_HALF_M, -ROOM_HALF_M, FLOOR_Z_M])
        with np.errstate(divide="ignore", invalid="ignore"):
            tt = (bound - center) / d
        tt[~(tt > 0)] = np.inf
        axis = np.argmin(tt, axis=1)
        rows = np.arange(n)
        t = tt[rows, axis]  # d_cam has z = 1, so t is the depth along the optical axis
        positive = d[rows, axis] > 0
        n_world = np.zeros((n, 3))
        n_world[rows, axis] = np.where(positive, -1.0, 1.0)
        normals = n_world @ R_wc  # rows: R_wc^T n
        if not color:
            return None, t, normals
        # surface id: walls 0..3 (x=+2, y=+2, x=-2, y=-2), floor 4, ceiling 5, rectangles 6..
        surface = np.where(axis == 2, np.where(positive, 5, 4), np.where(positive, axis, axis + 2))
        P = center + t[:, None] * d
        a = np.choose(np.minimum(surface, 4), [P[:, 1], -P[:, 0], -P[:, 1], P[:, 0], P[:, 0]])
        for r, (k, a0, a1, b0, b1, _) in enumerate(RECTS):
            idx = np.flatnonzero(surface == k)
            inside = (a[idx] >= a0) & (a[idx] <= a1) & (P[idx, 2] >= b0) & (P[idx, 2] <= b1)
            surface[idx[inside]] = 6 + r
        palette = np.array(WALL_BGR + [FLOOR_BGR, CEILING_BGR] + [rc[5] for rc in RECTS], dtype=np.float64)
        return palette[surface], t, normals

    @classmethod
    def render(cls, K, R_wc, center, size, distortion=None, supersample: int = 2, maps: bool = True):
        """Returns (BGR uint8 image, depth float32, normals float16) seen by one camera (distorted if given).

        ``maps=False`` skips the depth and normal maps (returns None for them).
        """
        w, h = size
        o = (np.arange(supersample) + 0.5) / supersample - 0.5
        us, vs = np.meshgrid((np.arange(w)[:, None] + o).ravel(), (np.arange(h)[:, None] + o).ravel())
        fine = np.stack([us.ravel(), vs.ravel()], 1)
        centres = np.stack(np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float)), -1).reshape(-1, 2)
        if distortion is not None and np.any(distortion):
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
            und = lambda p: cv2.undistortPoints(p[:, None], K, np.asarray(distortion, float), None, K,
                                                criteria=crit).reshape(-1, 2)
            fine = und(fine)
            centres = und(centres) if maps else centres
        color = cls.cast(K, R_wc, center, fine)[0].reshape(h, supersample, w, supersample, 3).mean(axis=(1, 3))
        img = np.clip(np.round(color), 0, 255).astype(np.uint8)
        if not maps:
            return img, None, None
        _, depth, normals = cls.cast(K, R_wc, center, centres, color=False)
        return img, depth.reshape(h, w).astype(np.float32), normals.reshape(h, w, 3).astype(np.float16)

    # ---- writing a capture
    def __call__(self, model: str = "PINHOLE", n_frames: int = 6, size=(160, 120), video: bool = False,
                 frames_csv: bool = False, imu_rate: float | None = 100.0, fps: float = 10.0, t0: float = 0.0,
                 ground_truth: bool = True, ext: str = ".png", distortion=DEFAULT_DISTORTION,
                 yaw_rate_deg_s: float = 30.0, imu_drift_deg_s: float = 0.0, name: str | None = None) -> Path:
        self.count += 1
        root = self.tmp_path / (name or f"capture{self.count}")
        root.mkdir(parents=True)
        w, h = size
        K = self.K(size)
        dist = np.asarray(distortion, float) if model == "OPENCV" else None
        params = {"PINHOLE": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], "SIMPLE_PINHOLE": [K[0, 0], K[0, 2], K[1, 2]],
                  "OPENCV": [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *(dist if dist is not None else [])]}[model]
        (root / "camera.json").write_text(json.dumps({"model": model, "width": w, "height": h,
                                                      "params": [float(p) for p in params], "fps": fps}))
        t = self.times(n_frames, fps, t0)
        R = self.rotation(t, yaw_rate_deg_s)
        C = self.center(t, yaw_rate_deg_s)
        stems = [f"{i:06d}" for i in range(n_frames)]
        gt = root / "ground_truth"
        if ground_truth:
            (gt / "normals").mkdir(parents=True)
            (gt / "depth").mkdir()
        writer = None
        if video:
            writer = cv2.VideoWriter(str(root / "video.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
            if not writer.isOpened():
                pytest.skip("this OpenCV cannot write mp4v video")
        else:
            (root / "frames").mkdir()
        for i in range(n_frames):
            img, depth, normals = self.render(K, R[i], C[i], size, dist, maps=ground_truth)
            if writer is not None:
                writer.write(img)
            else:
                cv2.imwrite(str(root / "frames" / f"{stems[i]}{ext}"), img)
            if ground_truth:
                np.save(gt / "normals" / f"{stems[i]}.npy", normals)
                np.save(gt / "depth" / f"{stems[i]}.npy", depth)
        if writer is not None:
            writer.release()
        if frames_csv:
            files = [f"{s}{ext}" if not video else s for s in stems]
            rows = "".join(f"{f},{ti:.9f}\n" for f, ti in zip(files, t))
            (root / "frames.csv").write_text("file,timestamp_s\n" + rows)
        if imu_rate is None:
            t_imu = t
        else:
            t_imu = np.arange(t[0] - 0.05, t[-1] + 0.05 + 0.5 / imu_rate, 1.0 / imu_rate)
        R_imu = Rotation.from_euler("z", np.radians(imu_drift_deg_s) * (t_imu - t[0])[:, None]).as_matrix() @ \
            self.rotation(t_imu, yaw_rate_deg_s)
        q = Rotation.from_matrix(R_imu).as_quat()[:, [3, 0, 1, 2]]
        (root / "imu.csv").write_text("timestamp_s,qw,qx,qy,qz\n" + "".join(
            f"{ti:.9f},{a:.12f},{b:.12f},{c:.12f},{d:.12f}\n" for ti, (a, b, c, d) in zip(t_imu, q)))
        if ground_truth:
            qg = Rotation.from_matrix(R).as_quat()[:, [3, 0, 1, 2]]
            (gt / "poses.csv").write_text("file,qw,qx,qy,qz,tx,ty,tz\n" + "".join(
                f"{s}{ext},{','.join(f'{v:.12f}' for v in qi)},{','.join(f'{v:.9f}' for v in ci)}\n"
                for s, qi, ci in zip(stems, qg, C)))
            segs, labels = self.lines()
            (gt / "lines.csv").write_text("x1,y1,z1,x2,y2,z2,label\n" + "".join(
                f"{','.join(f'{v:.6f}' for v in sg)},{'xyz'[lab]}\n" for sg, lab in zip(segs, labels)))
            (gt / "scene.json").write_text(json.dumps({"boxes": [{
                "min": [-ROOM_HALF_M, -ROOM_HALF_M, FLOOR_Z_M], "max": [ROOM_HALF_M, ROOM_HALF_M, CEILING_Z_M],
                "inside": True}]}))
        return root


@pytest.fixture
def tiny_capture(tmp_path) -> TinyCapture:
    """Returns a factory writing small valid captures under ``tmp_path`` (see the module docstring)."""
    return TinyCapture(tmp_path)
