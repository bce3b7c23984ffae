"""Procedural rooms and spins for a benchmark that cannot be over-fitted (issue #63): ``panosfm synth --scene random``.

Every draw comes from the seed, so a seed is one room and one spin (:func:`procedural_room`, :func:`random_spin`):

* the room: length and width 2-10 m with an aspect up to 5:1, ceiling 2.2-5 m; sometimes an L-shape (a solid
  corner), an alcove (two wall blocks beside a recess) or a chimney breast; in a high room sometimes a gallery
  (a slab on pillars with a railing) and sometimes ceiling beams (all :data:`~.scenes.STRUCTURE` boxes);
* 0-3 doors, 0-3 windows, 0-4 posters, then 0-15 furniture boxes of random size, against the walls or free;
* each surface's texture (:mod:`.textures`): plain, noise of its own strength and grain, or, with a folder of
  equirectangular photos (``photo_dir``: e.g. the project's ``shared/real``), a crop of a real panorama;
* the spin: the stand point anywhere at least ``max(0.6 m, arm + 3 sway + 0.25 m)`` from the walls and every box
  (drawn before the furniture, which then keeps clear of it); arm 0.25-0.5 m; sway 0-8 cm RMS (a quarter of
  the spins exact circles); 0.9-1.3 turns; 60-600 frames per turn; horizontal field of view 50-90 deg.

The photos chosen are drawn whether or not a folder is given (the same seed gives the same room shape and
spin either way); without one, a surface drawn to carry a photo gets noise instead.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .scenes import STRUCTURE, Scene, _Builder, _random_color
from .textures import PHOTO_MAX_PX, PHOTO_PX_PER_DEG, PhotoCrop, SurfaceTextures, file_sha256

PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg")
PHOTO_SHARE = 0.3  # share of surfaces drawn to carry a photo (where a photo folder is given)
PLAIN_SHARE = 0.25  # share of surfaces painted plain (no texture)
STAND_MIN_WALL_M = 0.6
PHONE_CLEARANCE_M = 0.25
GRID_M = 0.05


@dataclass(frozen=True)
class RandomSpin:
    """The seeded spin of a procedural room: arm (m), sway (m RMS), turn (deg), frames, field of view (deg)."""

    arm_m: float
    sway_m: float
    turn_deg: float
    frames_per_turn: int
    hfov_deg: float

    @property
    def n_frames(self) -> int:
        return max(int(round(self.frames_per_turn * self.turn_deg / 360.0)), 8)

    @property
    def clearance_m(self) -> float:
        """The stand point's horizontal clearance to walls and boxes: at least 0.6 m, and the arm, three sways and
        ``PHONE_CLEARANCE_M`` (nobody spins with the phone a hand's width from a wall)."""
        return max(STAND_MIN_WALL_M, self.arm_m + 3.0 * self.sway_m + PHONE_CLEARANCE_M)


def random_spin(seed: int) -> RandomSpin:
    """Returns the seeded spin of the procedural room ``seed`` (module docstring)."""
    rng = np.random.default_rng([int(seed), 7312])
    arm = float(rng.uniform(0.25, 0.5))
    sway = 0.0 if rng.uniform() < 0.25 else float(rng.uniform(0.005, 0.08))
    turns = float(rng.uniform(0.9, 1.3))
    fpt = int(round(np.exp(rng.uniform(np.log(60.0), np.log(600.0)))))
    return RandomSpin(arm, sway, 360.0 * turns, fpt, float(rng.uniform(50.0, 90.0)))


def list_photos(photo_dir: str | os.PathLike | None) -> list[Path]:
    """Returns the equirectangular photos (2:1 PNG / JPEG, by name) in ``photo_dir`` (none for None)."""
    if photo_dir is None:
        return []
    import cv2

    out = []
    for p in sorted(Path(photo_dir).iterdir()):
        if p.suffix.lower() in PHOTO_SUFFIXES and p.is_file():
            img = cv2.imread(str(p), cv2.IMREAD_REDUCED_GRAYSCALE_8)
            if img is not None and img.shape[1] == 2 * img.shape[0]:
                out.append(p)
    return out


def procedural_room(seed: int, photo_dir: str | os.PathLike | None = None) -> Scene:
    """Returns the seeded procedural room (module docstring); ``photo_dir``: equirectangular photos to paint with."""
    rng = np.random.default_rng([int(seed), 7311])
    clear = random_spin(seed).clearance_m
    long_side = rng.uniform(2.5, 10.0)
    aspect = np.exp(rng.uniform(0.0, np.log(5.0)))
    short_side = float(np.clip(long_side / aspect, 2.0, 10.0))
    W, D = (long_side, short_side) if rng.uniform() < 0.5 else (short_side, long_side)
    H = float(rng.uniform(2.2, 3.0) if rng.uniform() < 0.7 else rng.uniform(3.0, 5.0))
    b = _Builder((W, D, H))
    # the room's shape: drawn until a stand point fits (each failure draws it again; the sixth has none)
    shape_rng = np.random.default_rng([int(seed), 7313])
    stand = None
    for attempt in range(6):
        b.pop(len(b.mins))
        if attempt < 5:
            _structure(b, shape_rng, W, D, H)
        stand = _stand_point(b, rng, clear)
        if stand is not None:
            break
    if stand is None:  # no structure and still no room: the clearest point
        stand = _stand_point(b, rng, 0.0)
    n_structure = len(b.mins)
    placer = _Placer(b, rng, np.array(stand), clear)
    n_doors, n_windows, n_posters = int(rng.integers(0, 4)), int(rng.integers(0, 4)), int(rng.integers(0, 5))
    placer.doors(n_doors)
    placer.windows(n_windows)
    placer.posters(n_posters)
    placer.furniture(int(rng.integers(0, 16)))
    shell = [_muted_color(rng, (0.45, 0.9), 0.4) for _ in range(4)]
    shell += [_muted_color(rng, (0.2, 0.6), 0.6), _muted_color(rng, (0.8, 0.97), 0.15)]
    for i in range(n_structure):  # structure takes the colour of a wall
        b.colors[i] = tuple(float(v) for v in shell[int(rng.integers(4))])
    textures = _textures(rng, 6 + len(b.mins), b, photo_dir)
    light = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.5, 1.0)])
    scene = b.build("random", seed, float(rng.uniform(-90.0, 90.0)), shell, stand)
    return replace(scene, light_dir=light / np.linalg.norm(light), textures=textures)


class _Placer:
    """Places a procedural room's doors, windows, posters and furniture where they fit: inside the room, off the
    boxes placed so far and their keep-out margins, clear of the stand point's circle."""

    WALLS = ("-x", "+x", "-y", "+y")

    def __init__(self, b: _Builder, rng: np.random.Generator, stand: np.ndarray, clear: float):
        self.b, self.rng, self.stand, self.clear = b, rng, stand, clear
        self.keep: list[tuple[np.ndarray, np.ndarray]] = []  # keep-out boxes: in front of doors, around what is placed
        self.W, self.D, self.H = (float(v) for v in b.size)

    def extent(self, wall: str) -> tuple[float, float]:
        """Returns (length along the wall, depth across the room)."""
        return (self.W, self.D) if wall in ("-y", "+y") else (self.D, self.W)

    def wall_box(self, wall: str, u0: float, width: float, depth: float, z0: float, height: float):
        if wall in ("-y", "+y"):
            y0 = 0.0 if wall == "-y" else self.D - depth
            return (u0, y0, z0), (u0 + width, y0 + depth, z0 + height)
        x0 = 0.0 if wall == "-x" else self.W - depth
        return (x0, u0, z0), (x0 + depth, u0 + width, z0 + height)

    def free(self, lo, hi) -> bool:
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        if np.any(lo < -1e-9) or np.any(hi > self.b.size + 1e-9):
            return False
        for k_lo, k_hi in self.keep:
            if not (np.any(hi <= k_lo) or np.any(lo >= k_hi)):
                return False
        for m_lo, m_hi in zip(self.b.mins, self.b.maxs):
            if not (np.any(hi <= m_lo + 1e-9) or np.any(lo >= m_hi - 1e-9)):
                return False
        q = np.maximum(lo[:2] - self.stand, self.stand - hi[:2])  # the box's horizontal distance to the stand point
        return float(np.linalg.norm(np.maximum(q, 0.0))) >= self.clear

    def _wall(self) -> str:
        return self.WALLS[int(self.rng.integers(4))]

    def doors(self, n: int) -> None:
        rng = self.rng
        for k in range(n):
            for _ in range(30):
                wall, width = self._wall(), float(rng.uniform(0.75, 1.0))
                L, _ = self.extent(wall)
                if L < width + 0.4:
                    break
                u0 = float(rng.uniform(0.15, L - width - 0.15))
                lo, hi = self.wall_box(wall, u0 - 0.08, width + 0.16, 0.05, 0.0, 2.15)
                if self.free(lo, hi):
                    self.b.door(f"door{k}", wall, u0, _random_color(rng, (0.4, 0.9)), _random_color(rng, (0.8, 0.97)),
                                width=width, height=float(rng.uniform(1.95, 2.1)))
                    self.keep.append((np.array(lo) - [0.6, 0.6, 0.0], np.array(hi) + [0.6, 0.6, 0.0]))  # to open it
                    break

    def windows(self, n: int) -> None:
        rng = self.rng
        for k in range(n):
            for _ in range(30):
                wall, width = self._wall(), float(rng.uniform(0.6, 1.8))
                L, _ = self.extent(wall)
                z0 = float(rng.uniform(0.7, 1.1))
                height = float(min(rng.uniform(0.8, 1.5), self.H - z0 - 0.3))
                if L < width + 0.6 or height < 0.4:
                    break
                u0 = float(rng.uniform(0.3, L - width - 0.3))
                lo, hi = self.wall_box(wall, u0 - 0.15, width + 0.3, 0.12, z0 - 0.1, height + 0.2)
                if self.free(lo, hi):
                    self.b.window(f"window{k}", wall, u0, z0, width, height, (0.6, 0.72, 0.85),
                                  _random_color(rng, (0.8, 0.97)))
                    self.keep.append((np.array(lo), np.array(hi)))
                    break

    def posters(self, n: int) -> None:
        rng = self.rng
        for k in range(n):
            for _ in range(30):
                wall = self._wall()
                pw, ph = float(rng.uniform(0.3, 1.2)), float(rng.uniform(0.3, 1.0))
                L, _ = self.extent(wall)
                if L < pw + 0.4 or self.H < ph + 1.2:
                    break
                u0 = float(rng.uniform(0.2, L - pw - 0.2))
                z0 = float(rng.uniform(0.9, self.H - ph - 0.25))
                lo, hi = self.wall_box(wall, u0 - 0.03, pw + 0.06, 0.03, z0 - 0.03, ph + 0.06)
                if self.free(lo, hi):
                    self.b.poster(f"poster{k}", wall, u0, z0, pw, ph, _random_color(rng, (0.2, 0.9)))
                    self.keep.append((np.array(lo), np.array(hi)))
                    break

    def furniture(self, n: int) -> None:
        """Places ``n`` boxes of random size: about two in three against a wall, the rest free-standing."""
        rng, placed = self.rng, 0
        for _ in range(40 * max(n, 1)):
            if placed >= n:
                break
            w, d = float(rng.uniform(0.3, 2.4)), float(rng.uniform(0.3, 1.2))
            h = float(rng.uniform(0.3, 1.0) if rng.uniform() < 0.6 else rng.uniform(1.0, min(2.3, self.H - 0.1)))
            color = _muted_color(rng, (0.15, 0.85), 0.8)
            if rng.uniform() < 0.65:  # against a wall
                wall = self._wall()
                L, across = self.extent(wall)
                if L < w + 0.1 or across < d + 0.5:
                    continue
                lo, hi = self.wall_box(wall, float(rng.uniform(0.05, L - w - 0.05)), w, d, 0.0, h)
            else:  # free-standing (a table top on legs reads as a box)
                x0 = float(rng.uniform(0.3, max(self.W - w - 0.3, 0.31)))
                y0 = float(rng.uniform(0.3, max(self.D - d - 0.3, 0.31)))
                lo, hi = (x0, y0, 0.0), (x0 + w, y0 + d, h)
            if self.free(lo, hi):
                self.b.box(f"furniture{placed}", "furniture", lo, hi, color)
                self.keep.append((np.array(lo) - 0.05, np.array(hi) + 0.05))
                placed += 1


def _muted_color(rng: np.random.Generator, lum: tuple[float, float], max_saturation: float) -> np.ndarray:
    """Returns a random colour of luminance in ``lum``, blended towards grey (saturation up to ``max_saturation``)."""
    c = _random_color(rng, lum)
    y = 0.299 * c[0] + 0.587 * c[1] + 0.114 * c[2]
    return np.clip(y + rng.uniform(0.0, max_saturation) * (c - y), 0.02, 1.0)


def _structure(b: _Builder, rng: np.random.Generator, W: float, D: float, H: float) -> None:
    """Adds the room's shape: an L-shape, an alcove or a chimney breast, a gallery in a high room, beams."""
    grey = (0.8, 0.8, 0.8)  # recoloured like a wall afterwards
    u = rng.uniform()
    if u < 0.3 and min(W, D) >= 3.0:  # L-shape: a solid corner
        fx, fy = rng.uniform(0.25, 0.5) * W, rng.uniform(0.25, 0.5) * D
        x0 = 0.0 if rng.uniform() < 0.5 else W - fx
        y0 = 0.0 if rng.uniform() < 0.5 else D - fy
        b.box("l_corner", STRUCTURE, (x0, y0, 0.0), (x0 + fx, y0 + fy, H), grey)
    elif u < 0.5:  # an alcove: two wall blocks beside a recess, along one wall
        along_x = rng.uniform() < 0.5
        L, across = (W, D) if along_x else (D, W)
        depth = rng.uniform(0.4, min(1.2, 0.3 * across))
        a0 = rng.uniform(0.1, 0.6) * L
        a1 = a0 + rng.uniform(0.9, max(1.0, 0.5 * L))
        at_max = rng.uniform() < 0.5
        for k, (s0, s1) in enumerate(((0.0, a0), (min(a1, L), L))):
            if s1 - s0 < 0.2:
                continue
            c0 = across - depth if at_max else 0.0
            lo, hi = ((s0, c0, 0.0), (s1, c0 + depth, H)) if along_x else ((c0, s0, 0.0), (c0 + depth, s1, H))
            b.box(f"alcove_wall{k}", STRUCTURE, lo, hi, grey)
    elif u < 0.65:  # a chimney breast
        along_x = rng.uniform() < 0.5
        L, across = (W, D) if along_x else (D, W)
        w, depth = rng.uniform(0.6, min(1.6, 0.5 * L)), rng.uniform(0.3, 0.6)
        s0 = rng.uniform(0.2, L - w - 0.2)
        c0 = across - depth if rng.uniform() < 0.5 else 0.0
        lo, hi = ((s0, c0, 0.0), (s0 + w, c0 + depth, H)) if along_x else ((c0, s0, 0.0), (c0 + depth, s0 + w, H))
        b.box("chimney", STRUCTURE, lo, hi, grey)
    if H >= 3.6 and rng.uniform() < 0.5:  # a gallery along one wall
        along_x = rng.uniform() < 0.5
        L, across = (W, D) if along_x else (D, W)
        depth = rng.uniform(1.0, max(1.05, min(2.0, 0.35 * across)))
        z0 = rng.uniform(2.4, min(H - 1.2, 3.2))
        thick = rng.uniform(0.2, 0.3)
        at_max = rng.uniform() < 0.5
        c0 = across - depth if at_max else 0.0
        front = c0 if at_max else c0 + depth

        def box(name, s0, s1, a0, a1, z_0, z_1):
            lo, hi = ((s0, a0, z_0), (s1, a1, z_1)) if along_x else ((a0, s0, z_0), (a1, s1, z_1))
            b.box(name, STRUCTURE, lo, hi, grey)

        box("gallery", 0.0, L, c0, c0 + depth, z0, z0 + thick)
        rail = 0.05
        box("gallery_rail", 0.0, L, front - (0 if at_max else rail), front + (rail if at_max else 0),
            z0 + thick, z0 + thick + rng.uniform(0.9, 1.05))
        n_pillars = int(rng.integers(2, 5))
        side = rng.uniform(0.2, 0.35)
        for k, s in enumerate(np.linspace(0.15 * L, 0.85 * L, n_pillars)):
            a0 = front if at_max else front - side
            box(f"pillar{k}", s - side / 2, s + side / 2, a0, a0 + side, 0.0, z0)
    if rng.uniform() < 0.3:  # ceiling beams
        depth = rng.uniform(0.2, 0.4)
        if H - depth >= 2.05:
            along_x = rng.uniform() < 0.5
            L, across = (W, D) if along_x else (D, W)
            for k in range(int(rng.integers(1, 3))):
                wdt, c = rng.uniform(0.15, 0.3), rng.uniform(0.2, 0.8) * across
                lo, hi = ((0.0, c, H - depth), (L, c + wdt, H)) if along_x else ((c, 0.0, H - depth), (c + wdt, L, H))
                b.box(f"beam{k}", STRUCTURE, lo, hi, grey)


def _stand_point(b: _Builder, rng: np.random.Generator, clearance_m: float) -> tuple[float, float] | None:
    """Returns a uniformly drawn room-frame (x, y) at least ``clearance_m`` from the walls and every box reaching
    below 2 m (the beams and the gallery's slab pass overhead), or None where no grid point is that clear."""
    W, D, _ = b.size
    xs, ys = np.meshgrid(np.arange(GRID_M / 2, W, GRID_M), np.arange(GRID_M / 2, D, GRID_M), indexing="ij")
    p = np.stack([xs.ravel(), ys.ravel()], axis=1)
    d = np.minimum.reduce([p[:, 0], W - p[:, 0], p[:, 1], D - p[:, 1]])
    low = [k for k in range(len(b.mins)) if b.mins[k][2] < 2.0]
    if low:
        lo, hi = np.array(b.mins)[low, :2], np.array(b.maxs)[low, :2]
        q = np.maximum(lo[None] - p[:, None], p[:, None] - hi[None])
        d = np.minimum(d, np.linalg.norm(np.maximum(q, 0.0), axis=2).min(axis=1))
        inside = np.any(np.all(q < 0, axis=2), axis=1)
        d[inside] = -1.0
    if clearance_m <= 0:
        i = int(np.argmax(d))
        return float(p[i, 0]), float(p[i, 1])
    ok = np.flatnonzero(d >= clearance_m)
    if not len(ok):
        return None
    i = int(rng.choice(ok))
    return float(p[i, 0]), float(p[i, 1])


def _textures(rng: np.random.Generator, n_surfaces: int, b: _Builder, photo_dir) -> SurfaceTextures:
    """Returns each surface's texture: plain, noise of a random strength and grain, or a photo crop."""
    photos = list_photos(photo_dir)
    contrast = np.zeros(n_surfaces, np.float32)
    tile = np.ones(n_surfaces, np.float32)
    photo = np.full(n_surfaces, -1, np.int32)
    crops: list[PhotoCrop] = []
    mins = [np.zeros(3)] + [np.asarray(m) for m in b.mins]
    maxs = [b.size] + [np.asarray(m) for m in b.maxs]
    for s in range(n_surfaces):
        kind = rng.uniform()
        c, t = float(rng.uniform(0.03, 0.16)), float(np.exp(rng.uniform(np.log(0.4), np.log(2.5))))
        pick, yaw, pitch, hfov = int(rng.integers(1 << 30)), float(rng.uniform(-180, 180)), float(rng.uniform(-10, 10)), \
            float(rng.uniform(40, 80))
        if kind < PLAIN_SHARE:
            contrast[s] = float(rng.uniform(0.0, 0.02))
        else:
            contrast[s], tile[s] = c, t
        if kind >= 1.0 - PHOTO_SHARE and photos:
            # the surface's size along its plane coordinates: a shell face, or a box's largest extents
            if s < 6:
                a = s // 2
                ext = np.delete(maxs[0] - mins[0], a)
                origin = np.delete(mins[0], a)
            else:
                box = s - 5
                ext3 = maxs[box] - mins[box]
                ext = np.sort(ext3)[1:][::-1] if ext3.min() < 0.1 else ext3[[0, 2]]
                origin = np.array([mins[box][0], mins[box][2]])
            ext = np.maximum(ext, 0.2)
            aspect = float(np.clip(ext[0] / ext[1], 0.4, 2.5))
            width = int(min(PHOTO_MAX_PX, max(64, round(PHOTO_PX_PER_DEG * hfov))))
            height = int(max(32, round(width / aspect)))
            vfov = 2 * np.degrees(np.arctan(np.tan(np.radians(hfov) / 2) / aspect))
            if vfov > 100:
                hfov = float(2 * np.degrees(np.arctan(np.tan(np.radians(100) / 2) * aspect)))
            path = photos[pick % len(photos)]
            crops.append(PhotoCrop(str(path), path.name, file_sha256(str(path)), yaw, pitch, hfov, (width, height),
                                   (float(ext[0]), float(ext[0]) / aspect), (float(origin[0]), float(origin[1]))))
            photo[s] = len(crops) - 1
    return SurfaceTextures(contrast, tile, photo, tuple(crops))
