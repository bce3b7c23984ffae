"""Per-surface textures of a synthetic room: procedural noise of its own strength and scale, or a real photo.

A preset room (:mod:`.scenes`) paints every surface with one 1/f noise tile of
one strength (:func:`.render.shade`). A procedural room (:mod:`.procedural`)
gives each surface its own :class:`SurfaceTextures` entry:

* ``contrast``: the noise's relative brightness std (0: a plain painted surface);
* ``tile_m``: how many metres one noise tile covers (coarse or fine grain);
* ``photo``: the index of a :class:`PhotoCrop` painted instead (-1: none), a
  perspective crop of a real equirectangular panorama (gravity-aligned; the
  project's ``shared/real`` images are such) stretched over the surface's
  plane coordinates and mirrored beyond them. Its lines are lines of the
  surface plane (a photo of a door on a wall), in any direction.

Photos are read from the file a crop names and cut once per process
(:func:`photo_pyramid`, cached); the crop's settings come from the room's seed,
so a room with the same photo folder is the same room.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

PHOTO_SHADE = 0.8  # a photo surface's brightness is the photo times (its Lambert term / this)
PHOTO_PX_PER_DEG = 9.0  # crops are cut at this resolution (a 2048 px panorama has 5.7 px per degree)
PHOTO_MAX_PX = 1024
PHOTO_LEVELS = 6


@dataclass(frozen=True)
class PhotoCrop:
    """A pinhole crop of an equirectangular photo, painted over ``size_m`` of a surface's plane from ``origin_m``.

    ``path``: the photo file (read when rendering); ``name`` and ``sha256``: what scene.json records;
    ``yaw_deg`` / ``pitch_deg`` / ``hfov_deg``: the crop's view in the panorama; ``size_px`` (w, h);
    ``size_m`` (w, h) and ``origin_m`` (u, v): the plane coordinates (:func:`.render.raycast`'s ``plane_uv``)
    the crop covers, beyond which it repeats mirrored.
    """

    path: str
    name: str
    sha256: str
    yaw_deg: float
    pitch_deg: float
    hfov_deg: float
    size_px: tuple[int, int]
    size_m: tuple[float, float]
    origin_m: tuple[float, float]

    def to_json(self) -> dict:
        return {"name": self.name, "sha256": self.sha256, "yaw_deg": round(self.yaw_deg, 6),
                "pitch_deg": round(self.pitch_deg, 6), "hfov_deg": round(self.hfov_deg, 6),
                "size_px": list(self.size_px), "size_m": [round(v, 6) for v in self.size_m],
                "origin_m": [round(v, 6) for v in self.origin_m]}


@dataclass(frozen=True)
class SurfaceTextures:
    """Each surface's texture (struct of arrays over the scene's surfaces: the shell's 6, then one per box).

    ``contrast`` (S,) float32 relative std of the noise at ``texture=1``; ``tile_m`` (S,) float32 metres per
    noise tile; ``photo`` (S,) int32 index into ``photos`` (-1: noise only).
    """

    contrast: np.ndarray
    tile_m: np.ndarray
    photo: np.ndarray
    photos: tuple[PhotoCrop, ...] = ()

    def to_json(self) -> dict:
        return {"contrast": np.round(self.contrast.astype(np.float64), 6).tolist(),
                "tile_m": np.round(self.tile_m.astype(np.float64), 6).tolist(),
                "photo": self.photo.astype(int).tolist(), "photos": [p.to_json() for p in self.photos]}


def textures_from_json(d: dict | None) -> SurfaceTextures | None:
    """Returns the :class:`SurfaceTextures` of scene.json's ``textures`` (photos by name: not renderable)."""
    if not d:
        return None
    photos = tuple(PhotoCrop(path=p["name"], name=p["name"], sha256=p.get("sha256", ""), yaw_deg=p["yaw_deg"],
                             pitch_deg=p["pitch_deg"], hfov_deg=p["hfov_deg"], size_px=tuple(p["size_px"]),
                             size_m=tuple(p["size_m"]), origin_m=tuple(p["origin_m"])) for p in d.get("photos", []))
    return SurfaceTextures(np.asarray(d["contrast"], np.float32), np.asarray(d["tile_m"], np.float32),
                           np.asarray(d["photo"], np.int32), photos)


@lru_cache(maxsize=16)
def file_sha256(path: str) -> str:
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


@lru_cache(maxsize=4)
def _panorama(path: str) -> np.ndarray:
    from .panorama import read_panorama

    return read_panorama(path)


@lru_cache(maxsize=64)
def photo_pyramid(crop: PhotoCrop) -> tuple[np.ndarray, ...]:
    """Returns the crop (float32 RGB in 0..1) and its ``PHOTO_LEVELS - 1`` halvings (cv2.pyrDown)."""
    from scipy.spatial.transform import Rotation

    from .panorama import pinhole_intrinsics, render_view

    pano = _panorama(crop.path)
    w, h = crop.size_px
    K = pinhole_intrinsics((w, h), crop.hfov_deg)
    yaw, pitch = np.radians(crop.yaw_deg), np.radians(crop.pitch_deg)
    f = np.array([np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch), np.sin(pitch)])  # panorama convention
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    R = np.stack([right, down, f], axis=1)  # columns: camera x, y, z in the panorama's world
    R = Rotation.from_matrix(R).as_matrix()
    img = render_view(pano, K, R, (w, h))[..., ::-1].astype(np.float32) / 255.0
    levels = [np.ascontiguousarray(img)]
    for _ in range(PHOTO_LEVELS - 1):
        if min(levels[-1].shape[:2]) < 8:
            break
        levels.append(cv2.pyrDown(levels[-1]))
    return tuple(levels)


def _remap_flat(img: np.ndarray, x: np.ndarray, y: np.ndarray, width: int = 1024) -> np.ndarray:
    """Returns (N, 3) bilinear samples of ``img`` at (x, y) (N,), mirrored beyond its borders (cv2.remap's maps
    are laid out in rows of ``width``: its maps may not be longer than 32767)."""
    n = len(x)
    rows = max(-(-n // width), 1)
    mx = np.zeros(rows * width, np.float32)
    my = np.zeros(rows * width, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(img, mx.reshape(rows, width), my.reshape(rows, width), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REFLECT_101)
    return out.reshape(-1, 3)[:n]


def paint_photos(img: np.ndarray, hits: dict[str, np.ndarray], lam: np.ndarray, textures: SurfaceTextures) -> None:
    """Paints (in place) the pixels of ``img`` (H, W, 3) RGB whose surface carries a photo: the crop at the hit's
    plane coordinates (mirrored beyond it), anti-aliased over the pyramid by the pixel's footprint, times
    ``lam`` / ``PHOTO_SHADE``."""
    surface = hits["surface"]
    which = textures.photo[surface]
    for p in np.unique(which[which >= 0]):
        crop = textures.photos[int(p)]
        m = which == p
        pyr = photo_pyramid(crop)
        w, h = crop.size_px
        sx, sy = w / crop.size_m[0], h / crop.size_m[1]  # photo pixels per metre
        u = (hits["plane_uv"][0][m] - np.float32(crop.origin_m[0])) * np.float32(sx)
        v = (np.float32(crop.origin_m[1]) + np.float32(crop.size_m[1]) - hits["plane_uv"][1][m]) * np.float32(sy)
        cos_inc = np.maximum(np.abs(hits["normal_cam"][..., 2][m]), np.float32(0.2))
        footprint = hits["depth"][m] * np.float32(max(sx, sy) / hits["focal_px"]) / cos_inc
        lev = np.clip(np.log2(np.maximum(footprint, np.float32(1e-6))), 0, len(pyr) - 1)
        col = np.zeros((len(u), 3), np.float32)
        for lv in range(int(np.floor(lev.min())), int(np.ceil(lev.max())) + 1):
            wgt = np.maximum(np.float32(1.0) - np.abs(lev - np.float32(lv)), np.float32(0.0))
            if not np.any(wgt > 0):
                continue
            s = np.float32(2.0 ** -lv)
            col += wgt[:, None] * _remap_flat(pyr[lv], (u + 0.5) * s - 0.5, (v + 0.5) * s - 0.5)
        img[m] = col * (lam[m] / np.float32(PHOTO_SHADE))[:, None]
