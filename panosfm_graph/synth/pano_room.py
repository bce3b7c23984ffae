"""Hand-held spins with parallax inside a real panorama's room (issue #63): ``panosfm synth --panorama P --layout L
--sway S``.

The room is the layout's floor polygon extruded from the floor (z = 0) to the ceiling; every point of its walls,
floor and ceiling is painted with the colour the panorama sees in that point's direction from the panorama's
centre (furniture is flattened onto the surfaces behind it). A person stands near that centre and turns once
around as in :mod:`.trajectory` (arm, bob, sway); each frame is ray-cast against the polygon's walls and the two
horizontal planes (:func:`raycast_room`), so near surfaces move against far ones as in a real spin, with real
image texture and exact ground truth (poses, the room's edges, depth and normal maps).

Layouts (``shared/real/README.md``): PanoAnnotator JSON (:func:`.panorama.read_layout`) or a HorizonNet /
LayoutNet corner file (``*.txt``: ceiling and floor corner of each vertical wall edge, in panorama pixels; the
camera 1.6 m above the floor, the floor corners' latitude giving their distance, the ceiling corners' the
ceiling height). The room's Manhattan frame is the walls' dominant direction (:func:`room_axes`): a wall within
``AXIS_TOL_DEG`` of one of its axes is labelled with it in ``lines.csv``, others -1 (a bay window's slanted
walls).
"""
from __future__ import annotations

import hashlib
import logging
import os
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..progress import progress
from .panorama import PAD_PX, _check, _pad, pano_pixel, pinhole_intrinsics, read_layout, read_panorama
from .render import finish
from .scenes import yaw_matrix
from .trajectory import imu_attitude, spin_params, spin_pose
from .writer import PNG_PARAMS, atomic_capture_dir, frame_name, write_capture_tables

log = logging.getLogger("panosfm")

CORNERS_CAMERA_HEIGHT_M = 1.6  # a corner file's camera height (its README: assume 1.6 m)
AXIS_TOL_DEG = 3.0
PHONE_CLEARANCE_M = 0.25  # the stand point keeps the arm, three sways and this from every wall
STAND_SEARCH_M = 0.6  # the stand point is drawn within this of the panorama's centre where the room allows
IMU_RATE_HZ = 100.0


# --------------------------------------------------------------------------------------
# The layout
# --------------------------------------------------------------------------------------


def read_room_layout(path: str | os.PathLike, pano_shape: tuple[int, ...]) -> dict:
    """Returns {camera_height, ceiling_z, corners (N, 2) world x, y counter-clockwise} of a PanoAnnotator JSON or a
    corner file (module docstring; ``pano_shape``: the panorama's (H, W), the corners' pixel frame)."""
    p = Path(path)
    if p.suffix.lower() != ".txt":
        lay = read_layout(p)
    else:
        lay = _read_corners(p, pano_shape)
    c = np.asarray(lay["corners"], dtype=np.float64)
    x, y = c[:, 0], c[:, 1]
    if 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) < 0:  # clockwise: turn it round
        c = c[::-1].copy()
    return {**lay, "corners": c}


def _read_corners(p: Path, pano_shape: tuple[int, ...]) -> dict:
    try:
        rows = [ln.split() for ln in p.read_text(encoding="utf-8-sig").splitlines() if ln.strip()]
        uv = np.array(rows, dtype=np.float64)
    except FileNotFoundError:
        raise InputError("layout not found", p) from None
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise InputError(f"not a corner file (x y per line): {type(e).__name__}", p) from None
    if uv.ndim != 2 or uv.shape[1] != 2 or len(uv) < 6 or len(uv) % 2 or not np.all(np.isfinite(uv)):
        raise InputError(f"needs an even number (>= 6) of 'x y' corner lines, got shape {uv.shape}", p)
    H, W = int(pano_shape[0]), int(pano_shape[1])
    ceil, floor = uv[0::2], uv[1::2]
    lon = ((floor[:, 0] + 0.5) / W - 0.5) * 2 * np.pi
    lat_f = (0.5 - (floor[:, 1] + 0.5) / H) * np.pi
    lat_c = (0.5 - (ceil[:, 1] + 0.5) / H) * np.pi
    if np.any(lat_f >= -1e-3) or np.any(lat_c <= 1e-3):
        raise InputError("each pair must be a ceiling corner above the horizon, then a floor corner below it", p)
    cam_h = CORNERS_CAMERA_HEIGHT_M
    dist = cam_h / np.tan(-lat_f)
    corners = np.column_stack([dist * np.sin(lon), dist * np.cos(lon)])
    ceiling = float(np.median(cam_h + dist * np.tan(lat_c)))
    return {"camera_height": cam_h, "ceiling_z": ceiling, "corners": corners}


def room_axes(corners: np.ndarray) -> tuple[float, np.ndarray]:
    """Returns (the room's yaw in degrees: its x axis' heading from world x, (N,) each wall's axis 0/1 or -1).

    The yaw is the length-weighted circular mean of the walls' directions modulo 90 deg; a wall within
    ``AXIS_TOL_DEG`` of an axis takes its label.
    """
    e = np.roll(corners, -1, axis=0) - corners
    ang = np.arctan2(e[:, 1], e[:, 0])
    length = np.linalg.norm(e, axis=1)
    yaw = 0.25 * np.angle(np.sum(length * np.exp(4j * ang)))
    off = np.degrees(np.angle(np.exp(1j * (ang - yaw))))  # -180..180 from the x axis
    rel = np.mod(off + 45.0, 180.0) - 45.0  # 0: along x, 90: along y
    labels = np.where(np.abs(rel) <= AXIS_TOL_DEG, 0, np.where(np.abs(rel - 90.0) <= AXIS_TOL_DEG, 1, -1))
    return float(np.degrees(yaw)), labels.astype(np.int8)


def room_lines(layout: dict) -> tuple[np.ndarray, np.ndarray]:
    """Returns (lines (3N, 6) world metres, labels (3N,) int8): floor edges, ceiling edges, vertical edges, labelled
    by the room's Manhattan axes (:func:`room_axes`)."""
    c = np.asarray(layout["corners"], dtype=np.float64)
    n = len(c)
    z1 = float(layout["ceiling_z"])
    nxt = np.roll(np.arange(n), -1)
    floor = np.column_stack([c, np.zeros(n), c[nxt], np.zeros(n)])
    ceil = np.column_stack([c, np.full(n, z1), c[nxt], np.full(n, z1)])
    vert = np.column_stack([c, np.zeros(n), c, np.full(n, z1)])
    _, wall_axis = room_axes(c)
    labels = np.concatenate([wall_axis, wall_axis, np.full(n, 2, np.int8)])
    return np.concatenate([floor, ceil, vert]), labels


def room_scene(layout: dict, name: str) -> dict:
    """Returns scene.json of a layout room (``room_polygon``: corners, floor and ceiling heights; the room's
    Manhattan frame as R_world_room)."""
    c = np.asarray(layout["corners"], dtype=np.float64)
    yaw, _ = room_axes(c)
    R = yaw_matrix(yaw)
    return {"version": 1, "name": name, "units": "m", "frame": "world", "source": "panorama layout",
            "floor_z": 0.0, "ceiling_z": float(layout["ceiling_z"]), "camera_height_m": float(layout["camera_height"]),
            "corners_xy": np.round(c, 6).tolist(),
            "room_polygon": {"corners_xy": np.round(c, 6).tolist(), "floor_z": 0.0,
                             "ceiling_z": float(layout["ceiling_z"])},
            "room_yaw_deg": yaw, "R_world_room": R.tolist(), "t_world_room": [0.0, 0.0, 0.0],
            "manhattan_directions_world": R.T.tolist()}


def polygon_clearance(points_xy: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Returns (N,) each point's distance to the nearest wall, negative outside the polygon."""
    a = corners
    e = np.roll(corners, -1, axis=0) - a
    d = points_xy[:, None] - a[None]  # (N, M, 2)
    t = np.clip(np.sum(d * e[None], axis=2) / np.maximum(np.sum(e * e, axis=1), 1e-12)[None], 0.0, 1.0)
    dist = np.linalg.norm(d - t[..., None] * e[None], axis=2).min(axis=1)
    return np.where(point_in_polygon(points_xy, corners), dist, -dist)


def point_in_polygon(p: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Returns (N,) bool: points (N, 2) inside the polygon (even-odd rule)."""
    a, b = corners, np.roll(corners, -1, axis=0)
    y = p[:, 1:2]
    crosses = (a[None, :, 1] > y) != (b[None, :, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = a[None, :, 0] + (y - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / (b[None, :, 1] - a[None, :, 1])
    return np.sum(crosses & (p[:, 0:1] < x_at), axis=1) % 2 == 1


def distance_to_room(points_world: np.ndarray, corners: np.ndarray, floor_z: float, ceiling_z: float) -> np.ndarray:
    """Returns (N,) distances (m) from world points to the nearest surface of the extruded polygon room."""
    p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    a = corners
    e = np.roll(corners, -1, axis=0) - a
    d = p[:, None, :2] - a[None]
    t = np.clip(np.sum(d * e[None], axis=2) / np.maximum(np.sum(e * e, axis=1), 1e-12)[None], 0.0, 1.0)
    horiz = np.linalg.norm(d - t[..., None] * e[None], axis=2)
    vert = np.maximum(np.maximum(floor_z - p[:, 2], p[:, 2] - ceiling_z), 0.0)
    wall = np.hypot(horiz, vert[:, None]).min(axis=1)
    inside = point_in_polygon(p[:, :2], corners)
    planes = np.where(inside, np.minimum(np.abs(p[:, 2] - floor_z), np.abs(p[:, 2] - ceiling_z)), np.inf)
    return np.minimum(wall, planes)


# --------------------------------------------------------------------------------------
# Ray casting
# --------------------------------------------------------------------------------------


def raycast_room(corners: np.ndarray, ceiling_z: float, K: np.ndarray, R_wc: np.ndarray, center: np.ndarray,
                 size: tuple[int, int]) -> dict[str, np.ndarray]:
    """Returns the first hits of one view's pixel rays in the extruded polygon room: ``depth`` (H, W) float32
    along the optical axis, ``points`` (H, W, 3) float64 world hit points, ``normal_cam`` (H, W, 3) float32 unit
    camera-frame normals towards the camera (the camera inside the room)."""
    w, h = size
    x = (np.arange(w) - K[0, 2]) / K[0, 0]
    y = (np.arange(h) - K[1, 2]) / K[1, 1]
    X, Y = np.meshgrid(x, y)
    rays = np.stack([X, Y, np.ones_like(X)], axis=-1)  # camera frame, unit z: the hit parameter is the depth
    d = rays @ np.asarray(R_wc, dtype=np.float64).T  # (H, W, 3) world
    o = np.asarray(center, dtype=np.float64)
    t = np.full((h, w), np.inf)
    normal = np.zeros((h, w, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        tz = np.where(d[..., 2] < 0, (0.0 - o[2]) / d[..., 2], np.where(d[..., 2] > 0, (ceiling_z - o[2]) / d[..., 2],
                                                                       np.inf))
        t = np.where(tz > 0, tz, np.inf)
        normal[..., 2] = np.where(d[..., 2] < 0, 1.0, -1.0)
        for i in range(len(corners)):
            a, e = corners[i], corners[(i + 1) % len(corners)] - corners[i]
            den = d[..., 0] * e[1] - d[..., 1] * e[0]
            ax, ay = a[0] - o[0], a[1] - o[1]
            tw = (ax * e[1] - ay * e[0]) / den
            s = (ax * d[..., 1] - ay * d[..., 0]) / den
            hit = (tw > 1e-9) & (s >= 0.0) & (s <= 1.0) & (tw < t)
            t = np.where(hit, tw, t)
            n = np.array([e[1], -e[0], 0.0]) / max(np.hypot(*e), 1e-12)  # a counter-clockwise polygon: inward normal
            normal[hit] = -n if np.dot(n, [o[0] - a[0], o[1] - a[1], 0.0]) < 0 else n
    points = o + t[..., None] * d
    normal_cam = normal @ np.asarray(R_wc, dtype=np.float64)  # R^T n per pixel
    return {"depth": t.astype(np.float32), "points": points, "normal_cam": normal_cam.astype(np.float32)}


def paint(padded: np.ndarray, pano_shape: tuple[int, ...], points: np.ndarray, pano_center: np.ndarray) -> np.ndarray:
    """Returns (H, W, 3) float32 RGB in 0..1: each hit point's colour as the panorama sees it from its centre."""
    u, v = pano_pixel(points - pano_center, pano_shape)
    bgr = cv2.remap(padded, (u + PAD_PX).astype(np.float32), (v + PAD_PX).astype(np.float32),
                    interpolation=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    return bgr[..., ::-1].astype(np.float32) / 255.0


def render_room_frame(padded: np.ndarray, pano_shape: tuple[int, ...], layout: dict, K: np.ndarray, R_wc: np.ndarray,
                      center: np.ndarray, size: tuple[int, int], blur: float = 0.0, noise: float = 0.0, seed: int = 0
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (BGR uint8 (H, W, 3), depth (H, W) float32 m, normals (H, W, 3) float32 camera frame) of one view."""
    hits = raycast_room(np.asarray(layout["corners"]), float(layout["ceiling_z"]), K, R_wc, center, size)
    pano_center = np.array([0.0, 0.0, float(layout["camera_height"])])
    img = finish(paint(padded, pano_shape, hits["points"], pano_center), blur, noise, seed)
    return img, hits["depth"], hits["normal_cam"]


# --------------------------------------------------------------------------------------
# The capture
# --------------------------------------------------------------------------------------


def pick_stand_point(corners: np.ndarray, clearance_m: float, seed: int) -> np.ndarray:
    """Returns an (x, y) within ``STAND_SEARCH_M`` of the panorama's centre (the origin) at least ``clearance_m``
    from every wall (drawn uniformly), else the clearest point of the room."""
    rng = np.random.default_rng([int(seed), 4245])
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    xs, ys = np.meshgrid(np.arange(lo[0], hi[0], 0.02), np.arange(lo[1], hi[1], 0.02), indexing="ij")
    p = np.stack([xs.ravel(), ys.ravel()], axis=1)
    clear = polygon_clearance(p, corners)
    ok = np.flatnonzero((clear >= clearance_m) & (np.linalg.norm(p, axis=1) <= STAND_SEARCH_M))
    if not len(ok):
        ok = np.flatnonzero(clear >= clearance_m)
    if not len(ok):
        return p[int(np.argmax(clear))]
    return p[int(rng.choice(ok))]


def room_spin(panorama_path: str | os.PathLike, layout_path: str | os.PathLike, out: str | os.PathLike, *,
              n_frames: int = 300, size: tuple[int, int] = (640, 360), hfov_deg: float = 65.0, seed: int = 0,
              sway_m: float = 0.05, arm_m: float | None = None, turn_deg: float = 380.0, fps: float = 30.0,
              imu_drift_deg: float = 3.0, imu_noise_deg: float = 0.1, gt_maps: bool = True) -> Path:
    """Returns the path of a new hand-held spin capture inside a panorama's room (module docstring).

    ``sway_m``, ``arm_m`` (None: seeded 0.30-0.40 m), ``turn_deg``, ``fps``, IMU drift and noise as for
    :func:`~panosfm_graph.synth.synthesize`. Raises :class:`InputError` for a bad panorama or layout, bad settings
    or an existing non-empty ``out``.
    """
    out = Path(out)
    _check(out, n_frames, size, hfov_deg, imu_drift_deg=abs(imu_drift_deg), imu_noise_deg=imu_noise_deg,
           sway_m=sway_m, turn_deg=turn_deg, fps=fps)
    if fps <= 0 or turn_deg <= 0:
        raise InputError(f"fps and turn_deg must be > 0, got fps={fps}, turn_deg={turn_deg}")
    if arm_m is not None and not (np.isfinite(arm_m) and 0.0 < arm_m <= 2.0):
        raise InputError(f"arm_m must be between 0 (exclusive) and 2 m for a spin with parallax, got {arm_m}")
    pano = read_panorama(panorama_path)
    lay = read_room_layout(layout_path, pano.shape)
    n_frames, size, seed = int(n_frames), (int(size[0]), int(size[1])), int(seed)
    K = pinhole_intrinsics(size, hfov_deg)
    corners = np.asarray(lay["corners"])
    probe = spin_params(_Stand(np.zeros(3)), n_frames, seed, turn_deg, fps, sway_m, arm_m)
    stand = pick_stand_point(corners, probe.radius_m + 3.0 * sway_m + PHONE_CLEARANCE_M, seed)
    p = spin_params(_Stand(np.array([stand[0], stand[1], 0.0])), n_frames, seed, turn_deg, fps, sway_m, arm_m)
    ts = np.arange(n_frames, dtype=np.float64) / float(fps)
    R_wc, centers = spin_pose(p, ts)
    if np.any(polygon_clearance(centers[:, :2], corners) <= 0.02) or np.any(centers[:, 2] >= lay["ceiling_z"] - 0.05):
        raise InputError("the room is too small for this spin (the camera would leave it): try a shorter --arm")
    t_imu, R_imu = imu_attitude(p, n_frames, fps, seed, imu_drift_deg, imu_noise_deg, IMU_RATE_HZ)
    name = Path(layout_path).stem
    with atomic_capture_dir(out) as tmp:
        settings = dict(panorama=Path(panorama_path).name,
                        panorama_sha256=hashlib.sha256(Path(panorama_path).read_bytes()).hexdigest(),
                        panorama_size=[int(pano.shape[1]), int(pano.shape[0])], layout=Path(layout_path).name,
                        n_frames=n_frames, size=list(size), hfov_deg=float(hfov_deg), seed=seed, sway_m=float(sway_m),
                        arm_m=float(p.radius_m), turn_deg=float(turn_deg), fps=float(fps),
                        imu_drift_deg=float(imu_drift_deg), imu_noise_deg=float(imu_noise_deg),
                        stand_point=[float(stand[0]), float(stand[1])], gt_maps=bool(gt_maps))
        lines, labels = room_lines(lay)
        write_capture_tables(tmp, K, size, fps, ts, t_imu, R_imu, R_wc, centers,
                             {"generator": "panosfm_graph.synth.pano_room", **settings}, lines, labels,
                             {**room_scene(lay, name), "stand_point_world": [float(stand[0]), float(stand[1]), 0.0]})
        if gt_maps:
            (tmp / "ground_truth" / "normals").mkdir()
            (tmp / "ground_truth" / "depth").mkdir()
        padded = _pad(pano)
        for i in progress(range(n_frames), "room frames"):
            img, depth, normals = render_room_frame(padded, pano.shape, lay, K, R_wc[i], centers[i], size)
            path = tmp / "frames" / frame_name(i)
            if not cv2.imwrite(str(path), img, PNG_PARAMS):
                raise OSError(f"could not write {path}")
            if gt_maps:
                np.save(tmp / "ground_truth" / "normals" / f"{path.stem}.npy", normals.astype(np.float16))
                np.save(tmp / "ground_truth" / "depth" / f"{path.stem}.npy", depth)
    log.info("wrote panorama room capture %s (%s, %d frames, %dx%d)", out, Path(panorama_path).name, n_frames, *size)
    return out


class _Stand:
    """The stand point :func:`spin_params` reads from a scene."""

    def __init__(self, stand_point_world: np.ndarray):
        self.stand_point_world = stand_point_world
