"""Spin captures cut from a gravity-aligned equirectangular panorama (rotation only, zero baseline).

:func:`cut_spin` renders pinhole frames along a person's spin (yaw through
``turn_deg``, pitch and roll wobbling; :mod:`.trajectory`'s spin with the arm
length and bob set to zero) from one panorama and writes a capture in the
format of ``capture-format.md``, as :func:`~panosfm_graph.synth.synthesize`
does for box rooms::

    camera.json            PINHOLE, fx = fy = (width / 2) / tan(hfov / 2), principal point at the centre, fps
    frames/000000.png ...  BGR PNG, one cv2.remap of the panorama per frame (bicubic)
    frames.csv             file,timestamp_s   (i / fps)
    imu.csv                timestamp_s,qw,qx,qy,qz   100 Hz attitude = truth with linear heading drift + noise
    ground_truth/
      poses.csv            true R_wc; every centre the same (the panorama's optical centre): zero baseline
      lines.csv            with a layout only: the room's wall edges (floor, ceiling, vertical), label = axis
      scene.json           with a layout only: floor/ceiling heights, corners (and ``room`` for a box room)
      synth.json           the panorama (name, sha256), layout and settings, to reproduce

Panorama convention (``shared/real/README.md``): the world frame is the
panorama's, +z up (the panorama is gravity-aligned, horizon on the middle
row); column centre ``u + 0.5`` -> longitude ``((u + 0.5) / W - 0.5) 2 pi``,
row centre ``v + 0.5`` -> latitude ``(0.5 - (v + 0.5) / H) pi``; the viewing
direction is ``(cos lat sin lon, cos lat cos lon, sin lat)``.

Layouts are PanoAnnotator JSON (``cameraHeight``, ``layoutHeight``,
``layoutPoints.points[].xyz`` with y up, x and -z horizontal, camera at the
origin, corners at camera height). In the capture the floor is z = 0, the
ceiling z = ``layoutHeight`` and the camera at (0, 0, ``cameraHeight``); a
layout point (x, y, z) lies at world (x, -z, .), which is the direction its
``coords`` u gives under the convention above.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np

from ..errors import InputError
from ..progress import progress
from .trajectory import SpinParams, imu_attitude, spin_params, spin_pose
from .writer import PNG_PARAMS, atomic_capture_dir, frame_name, write_capture_tables

log = logging.getLogger("panosfm")

PAD_PX = 4  # panorama padding: columns wrap around, rows repeat (bicubic needs 2)
ROLL_PER_PITCH = 0.5  # roll wobble amplitude relative to the pitch wobble's
IMU_RATE_HZ = 100.0
AXIS_COS = np.cos(np.radians(1.0))  # a layout edge within 1 deg of a world axis gets that axis' label


# --------------------------------------------------------------------------------------
# The panorama
# --------------------------------------------------------------------------------------


def read_panorama(path: str | os.PathLike) -> np.ndarray:
    """Returns the equirectangular panorama at ``path`` as an H x 2H x 3 uint8 BGR image.

    Raises :class:`InputError` (one line) for a missing or unreadable image or
    one whose width is not twice its height.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError("panorama not found", p)
    img = cv2.imread(str(p), cv2.IMREAD_COLOR)
    if img is None or img.size == 0:
        raise InputError("cannot be read as an image (corrupt or not an image format OpenCV reads)", p)
    h, w = img.shape[:2]
    if w != 2 * h:
        raise InputError(f"is {w}x{h}: an equirectangular panorama must be twice as wide as high", p)
    if h < 16:
        raise InputError(f"is {w}x{h}: too small for a panorama (at least 32x16)", p)
    return img


def pano_pixel(d_world: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Returns (u, v): panorama pixel coordinates (pixel centres at integers) of world directions (..., 3)."""
    H, W = int(shape[0]), int(shape[1])
    d = np.asarray(d_world, dtype=np.float64)
    lon = np.arctan2(d[..., 0], d[..., 1])
    lat = np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))
    return (lon / (2 * np.pi) + 0.5) * W - 0.5, (0.5 - lat / np.pi) * H - 0.5


def pano_direction(u: np.ndarray, v: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Returns (..., 3) unit world directions of panorama pixel coordinates ``u``, ``v`` (inverse of pano_pixel)."""
    H, W = int(shape[0]), int(shape[1])
    lon = ((np.asarray(u, dtype=np.float64) + 0.5) / W - 0.5) * 2 * np.pi
    lat = (0.5 - (np.asarray(v, dtype=np.float64) + 0.5) / H) * np.pi
    return np.stack([np.cos(lat) * np.sin(lon), np.cos(lat) * np.cos(lon), np.sin(lat)], axis=-1)


def pinhole_intrinsics(size: tuple[int, int], hfov_deg: float) -> np.ndarray:
    """Returns the 3x3 K of a centred pinhole camera of ``size = (width, height)`` and horizontal FOV ``hfov_deg``."""
    w, h = size
    f = 0.5 * w / np.tan(np.radians(hfov_deg) / 2.0)
    return np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])


def _camera_rays(K: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Returns (H, W, 3) camera-frame rays (z = 1) of every pixel centre."""
    w, h = size
    x = (np.arange(w, dtype=np.float64) - K[0, 2]) / K[0, 0]
    y = (np.arange(h, dtype=np.float64) - K[1, 2]) / K[1, 1]
    X, Y = np.meshgrid(x, y)
    return np.stack([X, Y, np.ones_like(X)], axis=-1)


def _pad(pano: np.ndarray) -> np.ndarray:
    """Returns the panorama padded by PAD_PX: columns wrap around (longitude), rows repeat."""
    p = cv2.copyMakeBorder(pano, 0, 0, PAD_PX, PAD_PX, cv2.BORDER_WRAP)
    return cv2.copyMakeBorder(p, PAD_PX, PAD_PX, 0, 0, cv2.BORDER_REPLICATE)


def render_view(pano: np.ndarray, K: np.ndarray, R_wc: np.ndarray, size: tuple[int, int],
                _padded: np.ndarray | None = None, _rays: np.ndarray | None = None) -> np.ndarray:
    """Returns the (H, W, 3) pinhole view with intrinsics ``K`` and attitude ``R_wc`` cut from ``pano`` (bicubic)."""
    padded = _pad(pano) if _padded is None else _padded
    rays = _camera_rays(K, size) if _rays is None else _rays
    u, v = pano_pixel(rays @ np.asarray(R_wc, dtype=np.float64).T, pano.shape)
    return cv2.remap(padded, (u + PAD_PX).astype(np.float32), (v + PAD_PX).astype(np.float32),
                     interpolation=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)


# --------------------------------------------------------------------------------------
# The spin and the IMU
# --------------------------------------------------------------------------------------


def pano_spin_params(n_frames: int, seed: int = 0, turn_deg: float = 380.0, fps: float = 30.0,
                     wobble_deg: float = 2.5) -> SpinParams:
    """Returns the seeded spin of :mod:`.trajectory` about a fixed optical centre.

    Yaw start, speed variation, pitch and roll offsets (the phone looks 4-8 deg
    down), wobble frequencies and phases come from :func:`spin_params`; the arm
    length and bob are zero; the pitch wobbles with amplitude ``wobble_deg``
    and the roll with ``ROLL_PER_PITCH * wobble_deg``.
    """
    p = spin_params(SimpleNamespace(stand_point_world=np.zeros(3)), n_frames, seed, turn_deg, fps)
    w = float(wobble_deg)
    return dataclasses.replace(p, radius_m=0.0, height_m=0.0, bob_m=0.0, view_offset_deg=0.0,
                               pitch_deg=(p.pitch_deg[0], w, p.pitch_deg[2], p.pitch_deg[3]),
                               roll_deg=(p.roll_deg[0], ROLL_PER_PITCH * w, p.roll_deg[2], p.roll_deg[3]))


# --------------------------------------------------------------------------------------
# The layout
# --------------------------------------------------------------------------------------


def read_layout(path: str | os.PathLike) -> dict:
    """Returns a PanoAnnotator layout as {camera_height, ceiling_z, corners (N, 2) world x, y}; InputError if bad.

    The floor is z = 0 and the camera at (0, 0, ``camera_height``) (module docstring).
    """
    p = Path(path)
    try:
        d = json.loads(p.read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        raise InputError("layout not found", p) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"cannot be read as JSON ({str(e).splitlines()[0] if str(e) else type(e).__name__})",
                         p) from None
    try:
        cam_h = float(d["cameraHeight"])
        room_h = float(d["layoutHeight"])
        xyz = np.array([pt["xyz"] for pt in d["layoutPoints"]["points"]], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"not a PanoAnnotator layout (cameraHeight, layoutHeight, layoutPoints.points[].xyz): "
                         f"{type(e).__name__} {e}", p) from None
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) < 3:
        raise InputError(f"needs at least 3 layout points with xyz, got shape {xyz.shape}", p)
    if not (np.all(np.isfinite(xyz)) and np.isfinite(cam_h) and np.isfinite(room_h)) or not 0 < cam_h < room_h:
        raise InputError(f"needs finite values and 0 < cameraHeight ({cam_h}) < layoutHeight ({room_h})", p)
    corners = np.column_stack([xyz[:, 0], -xyz[:, 2]])
    return {"camera_height": cam_h, "ceiling_z": room_h, "corners": corners}


def layout_lines(layout: dict) -> tuple[np.ndarray, np.ndarray]:
    """Returns (lines (3N, 6) world metres, labels (3N,) int8) of a layout: floor edges, ceiling edges, vertical edges.

    Labels are the world axis 0/1/2 of an edge within 1 deg (2 = vertical), -1 otherwise
    (the layout's walls are taken as the room's Manhattan frame, aligned with the panorama).
    """
    c = np.asarray(layout["corners"], dtype=np.float64)
    n = len(c)
    z0, z1 = 0.0, float(layout["ceiling_z"])
    nxt = np.roll(np.arange(n), -1)
    floor = np.column_stack([c, np.full(n, z0), c[nxt], np.full(n, z0)])
    ceil = np.column_stack([c, np.full(n, z1), c[nxt], np.full(n, z1)])
    vert = np.column_stack([c, np.full(n, z0), c, np.full(n, z1)])
    lines = np.concatenate([floor, ceil, vert])
    d = lines[:, 3:] - lines[:, :3]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    axis = np.argmax(np.abs(d), axis=1)
    labels = np.where(np.abs(d[np.arange(len(d)), axis]) >= AXIS_COS, axis, -1).astype(np.int8)
    return lines, labels


def _layout_scene(layout: dict, layout_path: Path) -> dict:
    """Returns scene.json for a layout; ``room`` (the evaluation's shell box) only for an axis-aligned box room."""
    c = np.asarray(layout["corners"], dtype=np.float64)
    lo = [float(c[:, 0].min()), float(c[:, 1].min()), 0.0]
    hi = [float(c[:, 0].max()), float(c[:, 1].max()), float(layout["ceiling_z"])]
    scene = {"version": 1, "name": layout_path.stem, "units": "m", "frame": "world",
             "source": "PanoAnnotator layout", "floor_z": 0.0, "ceiling_z": float(layout["ceiling_z"]),
             "camera_height_m": float(layout["camera_height"]),
             "corners_xy": np.round(c, 6).tolist(), "R_world_room": np.eye(3).tolist(), "t_world_room": [0.0] * 3}
    on_box = np.all((np.isclose(c[:, 0], lo[0]) | np.isclose(c[:, 0], hi[0]))
                    & (np.isclose(c[:, 1], lo[1]) | np.isclose(c[:, 1], hi[1])))
    if len(c) == 4 and on_box:
        scene["room"] = {"min": lo, "max": hi}
        scene["boxes"] = []
    return scene


# --------------------------------------------------------------------------------------
# The capture
# --------------------------------------------------------------------------------------


def _check(out: Path, n_frames: int, size, hfov_deg: float, **nonneg: float) -> None:
    if int(n_frames) < 2:
        raise InputError(f"n_frames must be at least 2, got {n_frames}")
    if len(size) != 2 or min(int(size[0]), int(size[1])) < 16:
        raise InputError(f"size must be (width, height) of at least 16 px, got {size}")
    if not np.isfinite(hfov_deg) or not 10.0 <= hfov_deg <= 150.0:
        raise InputError(f"hfov_deg must be between 10 and 150, got {hfov_deg}")
    for k, v in nonneg.items():
        if not np.isfinite(v) or v < 0:
            raise InputError(f"{k} must be a finite number >= 0, got {v}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError("output path exists and is not an empty directory; choose another or remove it", out)


def cut_spin(panorama_path: str | os.PathLike, out: str | os.PathLike, *, n_frames: int = 240,
             size: tuple[int, int] = (640, 360), hfov_deg: float = 65.0, seed: int = 0, imu_drift_deg: float = 3.0,
             imu_noise_deg: float = 0.3, wobble_deg: float = 2.5, turn_deg: float = 380.0, fps: float = 30.0,
             layout: str | os.PathLike | None = None) -> Path:
    """Returns the path of a new rotation-only spin capture cut from an equirectangular panorama.

    ``panorama_path``: a gravity-aligned equirectangular image (width = 2 x
    height, horizon on the middle row; module docstring). ``n_frames`` pinhole
    frames of ``size`` (width, height) px and horizontal FOV ``hfov_deg`` along a
    spin of ``turn_deg`` at ``fps``; ``wobble_deg``: pitch wobble amplitude (roll
    half of it); ``imu_drift_deg``: IMU heading drift from the first to the last
    frame; ``imu_noise_deg``: RMS white noise per IMU sample. ``layout``: a
    PanoAnnotator JSON of the room, giving ground_truth/lines.csv and scene.json.
    Every ground-truth centre is the same point. Raises :class:`InputError` for a
    bad panorama or layout, bad settings or an existing non-empty ``out``.
    """
    out = Path(out)
    _check(out, n_frames, size, hfov_deg, imu_drift_deg=abs(imu_drift_deg), imu_noise_deg=imu_noise_deg,
           wobble_deg=wobble_deg, turn_deg=turn_deg, fps=fps)
    if fps <= 0 or turn_deg <= 0:
        raise InputError(f"fps and turn_deg must be > 0, got fps={fps}, turn_deg={turn_deg}")
    pano = read_panorama(panorama_path)
    lay = read_layout(layout) if layout is not None else None
    n_frames, size, seed = int(n_frames), (int(size[0]), int(size[1])), int(seed)
    K = pinhole_intrinsics(size, hfov_deg)
    p = pano_spin_params(n_frames, seed, turn_deg, fps, wobble_deg)
    ts = np.arange(n_frames, dtype=np.float64) / float(fps)
    R_wc, _ = spin_pose(p, ts)
    t_imu, R_imu = imu_attitude(p, n_frames, fps, seed, imu_drift_deg, imu_noise_deg, IMU_RATE_HZ)
    center = np.array([0.0, 0.0, lay["camera_height"] if lay else 0.0])

    with atomic_capture_dir(out) as tmp:
        pano_bytes = Path(panorama_path).read_bytes()
        settings = dict(panorama=Path(panorama_path).name, panorama_sha256=hashlib.sha256(pano_bytes).hexdigest(),
                        panorama_size=[int(pano.shape[1]), int(pano.shape[0])],
                        layout=None if layout is None else Path(layout).name, n_frames=n_frames, size=list(size),
                        hfov_deg=float(hfov_deg), seed=seed, imu_drift_deg=float(imu_drift_deg),
                        imu_noise_deg=float(imu_noise_deg), wobble_deg=float(wobble_deg), turn_deg=float(turn_deg),
                        fps=float(fps))
        lines, labels = layout_lines(lay) if lay is not None else (None, None)
        write_capture_tables(tmp, K, size, fps, ts, t_imu, R_imu, R_wc, center,
                             {"generator": "panosfm_graph.synth.panorama", **settings}, lines, labels,
                             _layout_scene(lay, Path(layout)) if lay is not None else None)
        padded, rays = _pad(pano), _camera_rays(K, size)
        for i in progress(range(n_frames), "cut frames"):
            img = render_view(pano, K, R_wc[i], size, _padded=padded, _rays=rays)
            path = tmp / "frames" / frame_name(i)
            if not cv2.imwrite(str(path), img, PNG_PARAMS):
                raise OSError(f"could not write {path}")
    log.info("wrote panorama spin capture %s (%s, %d frames, %dx%d)", out, Path(panorama_path).name, n_frames, *size)
    return out
