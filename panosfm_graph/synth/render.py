"""Vectorised ray casting of box rooms: colour, depth and normals of one pinhole view.

Rays are cast in the ROOM frame, where every surface is axis-aligned: the
shell (an inside-out box; a ray leaves it through the nearest of the three
planes it is heading to) and each box (slab method, only over the pixels of
the box's projected bounding rectangle). Shading: base colour per surface x
a fixed directional light with a wrap-around Lambertian term (every face
orientation gets a distinct brightness, so all box edges show) x a mild
periodic procedural texture (1/f noise, so SIFT/ORB find features). Then a
small optical blur (sigma 0.6 px), optional horizontal motion blur and
Gaussian image noise.
"""
from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from .scenes import Scene
from .textures import paint_photos

TEXTURE_TILE_PX = 512  # periodic texture tile (texels)
TEXTURE_TILE_M = 1.0  # one tile covers this many metres of surface
TEXTURE_CONTRAST = 0.08  # relative brightness variation (std) at texture=1
OPTICS_SIGMA_PX = 0.6
MIP_LEVELS = 7  # texture pre-filter levels: up to 64 texels per pixel
AMBIENT, DIFFUSE = 0.62, 0.36


@lru_cache(maxsize=4)
def texture_tile(seed: int = 0, size: int = TEXTURE_TILE_PX) -> np.ndarray:
    """Returns a (size, size) float32 periodic 1/f noise tile with zero mean and unit std."""
    rng = np.random.default_rng([int(seed), 99])
    white = rng.standard_normal((size, size))
    f = np.fft.fftfreq(size)
    r = np.hypot(f[:, None], f[None, :])
    r[0, 0] = 1.0
    spec = np.fft.fft2(white) / r**1.1
    spec[0, 0] = 0.0
    tile = np.real(np.fft.ifft2(spec))
    tile = (tile - tile.mean()) / tile.std()
    return np.clip(tile, -3.0, 3.0).astype(np.float32)


@lru_cache(maxsize=4)
def texture_mips(seed: int = 0, levels: int = MIP_LEVELS) -> tuple[np.ndarray, ...]:
    """Returns the texture tile pre-filtered for 1, 2, 4, ... texels per pixel (periodic Gaussian blur).

    Level ``l`` is the tile blurred with sigma = 0.5 * 2**l texels (wrap-around),
    kept at full size so all levels share texel coordinates (anti-aliasing).
    """
    tile = texture_tile(seed)
    out = [tile]
    for lev in range(1, levels):
        out.append(_wrap_blur(tile, 0.5 * 2.0**lev))
    return tuple(out)


def _wrap_blur(tile: np.ndarray, sigma: float) -> np.ndarray:
    """Returns ``tile`` blurred by a periodic Gaussian of ``sigma`` texels (via the FFT)."""
    f = np.fft.fftfreq(tile.shape[0])
    g = np.exp(-2.0 * (np.pi * sigma) ** 2 * (f[:, None] ** 2 + f[None, :] ** 2))
    return np.real(np.fft.ifft2(np.fft.fft2(tile) * g)).astype(np.float32)


def intrinsics(size: tuple[int, int], focal_frac: float = 0.8) -> np.ndarray:
    """Returns the 3x3 K of a ``size = (width, height)`` camera: fx = fy = focal_frac * width, centred."""
    w, h = size
    f = focal_frac * w
    return np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])


def raycast(scene: Scene, K: np.ndarray, R_wc: np.ndarray, center: np.ndarray, size: tuple[int, int]
            ) -> dict[str, np.ndarray]:
    """Returns the first hits of one view's pixel rays: depth, surface id, face axis, normals, plane coordinates.

    Keys: ``depth`` (H, W) float32 along the optical axis (m); ``surface``
    (H, W) int32 (0..5 shell walls -x, +x, -y, +y, floor, ceiling; 6 + b box
    b); ``axis`` (H, W) int8 normal axis in the room frame; ``nsign`` (H, W)
    float32 sign of the room-frame normal (it points towards the camera);
    ``normal_cam`` (H, W, 3) float32 unit camera-frame normals towards the
    camera; ``plane_uv`` (2, H, W) float32 room-frame coordinates of the hit
    point along the face's two in-plane axes (increasing axis order);
    ``focal_px`` the focal length (for texture filtering). Every pixel hits
    a surface when the camera is inside the room.
    """
    w, h = size
    R_room_cam = (scene.R_world_room.T @ R_wc).astype(np.float32)
    o = scene.to_room(np.asarray(center, dtype=np.float64)).astype(np.float32)
    u = (np.arange(w, dtype=np.float32) - np.float32(K[0, 2])) / np.float32(K[0, 0])
    v = (np.arange(h, dtype=np.float32) - np.float32(K[1, 2])) / np.float32(K[1, 1])
    # room-frame ray directions with unit camera-z component: the hit parameter is the depth
    D = u[None, None, :] * R_room_cam[:, 0, None, None] + v[None, :, None] * R_room_cam[:, 1, None, None]
    D += R_room_cam[:, 2, None, None]
    D[(D < 1e-9) & (D > -1e-9)] = np.float32(1e-9)
    inv = np.float32(1.0) / D  # (3, H, W)

    # shell (inside-out): on each axis the ray exits through the plane ahead (the positive parameter)
    lo = scene.room_min.astype(np.float32) - o
    hi = scene.room_max.astype(np.float32) - o
    t_ax = [np.maximum(lo[a] * inv[a], hi[a] * inv[a]) for a in range(3)]
    t = np.minimum(np.minimum(t_ax[0], t_ax[1]), t_ax[2])
    axis = np.where(t_ax[0] == t, np.int8(0), np.where(t_ax[1] == t, np.int8(1), np.int8(2)))
    del t_ax
    surface = np.full(t.shape, -1, np.int32)  # shell faces are filled in below from the hit axis

    # boxes: slab test over each box's projected bounding rectangle
    bmins, bmaxs = scene.boxes_min.astype(np.float32), scene.boxes_max.astype(np.float32)
    corner_sel = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=bool)
    for b in range(len(bmins)):
        corners = np.where(corner_sel, bmaxs[b], bmins[b])  # (8, 3) room
        Xc = (corners - o) @ R_room_cam  # camera frame
        if np.all(Xc[:, 2] <= 1e-4):
            continue
        if np.any(Xc[:, 2] <= 1e-2):
            u0, u1, v0, v1 = 0, w, 0, h
        else:
            px = Xc[:, 0] / Xc[:, 2] * K[0, 0] + K[0, 2]
            py = Xc[:, 1] / Xc[:, 2] * K[1, 1] + K[1, 2]
            u0, u1 = max(int(np.floor(px.min())) - 1, 0), min(int(np.ceil(px.max())) + 2, w)
            v0, v1 = max(int(np.floor(py.min())) - 1, 0), min(int(np.ceil(py.max())) + 2, h)
            if u0 >= u1 or v0 >= v1:
                continue
        tmin, tmax = [], []
        for a in range(3):
            ia = inv[a, v0:v1, u0:u1]
            t1 = (bmins[b, a] - o[a]) * ia
            t2 = (bmaxs[b, a] - o[a]) * ia
            tmin.append(np.minimum(t1, t2))
            tmax.append(np.maximum(t1, t2))
        tnear = np.maximum(np.maximum(tmin[0], tmin[1]), tmin[2])
        tfar = np.minimum(np.minimum(tmax[0], tmax[1]), tmax[2])
        t_s = t[v0:v1, u0:u1]
        hit = (tnear <= tfar) & (tnear > 0) & (tnear < t_s)
        if not hit.any():
            continue
        np.copyto(t_s, tnear, where=hit)
        ax_b = np.where(tmin[0] == tnear, np.int8(0), np.where(tmin[1] == tnear, np.int8(1), np.int8(2)))
        np.copyto(axis[v0:v1, u0:u1], ax_b, where=hit)
        surface[v0:v1, u0:u1][hit] = 6 + b

    d_ax = np.where(axis == 0, D[0], np.where(axis == 1, D[1], D[2]))
    shell = surface < 0
    np.copyto(surface, 2 * axis.astype(np.int32) + (d_ax > 0), where=shell)
    nsign = np.where(d_ax > 0, np.float32(-1.0), np.float32(1.0))
    normal_cam = R_room_cam[axis] * nsign[..., None]  # row `axis` of R_room_cam = room axis in camera
    # in-plane coordinates of the hit point: (y, z) on x-faces, (x, z) on y-faces, (x, y) on z-faces
    pu = o[0] + t * np.where(axis == 0, D[1], D[0])
    pu[axis == 0] += o[1] - o[0]
    pv = o[2] + t * np.where(axis == 2, D[1], D[2])
    pv[axis == 2] += o[1] - o[2]
    return {"depth": t, "surface": surface, "axis": axis, "nsign": nsign,
            "normal_cam": normal_cam, "plane_uv": np.stack([pu, pv]), "focal_px": float(K[0, 0])}


def shade(scene: Scene, hits: dict[str, np.ndarray], texture: float = 1.0, texture_seed: int = 0) -> np.ndarray:
    """Returns the (H, W, 3) float32 RGB image in 0..1 of ray-cast hits: colour x light x texture (a scene with
    per-surface textures: :func:`_shade_surfaces`)."""
    if scene.textures is not None:
        return _shade_surfaces(scene, hits, texture, texture_seed)
    surface, axis, nsign = hits["surface"], hits["axis"], hits["nsign"]
    colors = np.vstack([scene.shell_colors, scene.box_colors.reshape(-1, 3)]).astype(np.float32)
    L = scene.light_dir.astype(np.float32)
    lam = AMBIENT + DIFFUSE * (nsign * L[axis])  # wrap-around Lambert: distinct per orientation
    if texture > 0:
        tex = _noise(hits, len(colors), np.float32(TEXTURE_TILE_PX / TEXTURE_TILE_M), texture_seed)
        lam = lam * (1.0 + np.float32(TEXTURE_CONTRAST * texture) * tex)
    return colors[surface] * lam[..., None]


def _noise(hits: dict[str, np.ndarray], n_surfaces: int, scale, texture_seed: int) -> np.ndarray:
    """Returns (H, W) float32 the periodic noise tile at the hits' plane coordinates times ``scale`` (texels per
    metre: one number, or one per pixel), each surface's tile shifted by a seeded offset; anti-aliased: texels per
    pixel ~ depth / (fx |cos incidence|), neighbouring mip levels tent-blended."""
    surface = hits["surface"]
    n_tile = TEXTURE_TILE_PX
    rng = np.random.default_rng([int(texture_seed), 5])
    offs = rng.uniform(0, n_tile, (n_surfaces, 2)).astype(np.float32)
    mx = np.mod(hits["plane_uv"][0] * scale + offs[surface, 0], np.float32(n_tile))
    my = np.mod(hits["plane_uv"][1] * scale + offs[surface, 1], np.float32(n_tile))
    cos_inc = np.maximum(np.abs(hits["normal_cam"][..., 2]), np.float32(0.2))
    footprint = hits["depth"] * (scale / np.float32(hits["focal_px"])) / cos_inc
    lev = np.clip(np.log2(np.maximum(footprint, np.float32(1e-6))), 0, MIP_LEVELS - 1)
    mips = texture_mips(int(texture_seed))
    tex = np.zeros_like(lev)
    for lv in range(int(np.floor(lev.min())), int(np.ceil(lev.max())) + 1):
        wgt = np.maximum(np.float32(1.0) - np.abs(lev - np.float32(lv)), np.float32(0.0))
        tex += wgt * cv2.remap(mips[lv], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return tex


def _shade_surfaces(scene: Scene, hits: dict[str, np.ndarray], texture: float, texture_seed: int) -> np.ndarray:
    """Returns :func:`shade`'s image for a scene whose surfaces carry their own textures (:mod:`.textures`):
    the noise tile at each surface's contrast and scale, photos painted over their surfaces."""
    surface, axis, nsign = hits["surface"], hits["axis"], hits["nsign"]
    tx = scene.textures
    colors = np.vstack([scene.shell_colors, scene.box_colors.reshape(-1, 3)]).astype(np.float32)
    L = scene.light_dir.astype(np.float32)
    lam = AMBIENT + DIFFUSE * (nsign * L[axis])
    shaded = lam
    contrast = tx.contrast.astype(np.float32) * np.float32(texture)
    if texture > 0 and np.any(contrast > 0):
        tex = _noise(hits, len(colors), (np.float32(TEXTURE_TILE_PX) / tx.tile_m.astype(np.float32))[surface],
                     texture_seed)
        shaded = lam * (1.0 + contrast[surface] * tex)
    img = colors[surface] * shaded[..., None]
    if len(tx.photos):
        paint_photos(img, hits, lam, tx)
    return img


def finish(img_rgb: np.ndarray, blur: float = 0.0, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """Returns the BGR uint8 image after optical blur, horizontal motion blur (px) and noise (sigma, 0..255)."""
    img = cv2.GaussianBlur(img_rgb, (0, 0), OPTICS_SIGMA_PX)
    if blur > 0:
        n = int(np.ceil(blur)) | 1
        k = np.zeros((1, n), np.float32)
        xs = np.arange(n) - (n - 1) / 2
        k[0] = np.clip(blur / 2 + 0.5 - np.abs(xs), 0.0, 1.0)  # box of width `blur`, soft ends
        img = cv2.filter2D(img, -1, k / k.sum(), borderType=cv2.BORDER_REFLECT)
    img = img * 255.0
    if noise > 0:
        img = img + np.random.default_rng([int(seed), 31337]).normal(0.0, noise, img.shape).astype(np.float32)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)[..., ::-1].copy()


def render_frame(scene: Scene, K: np.ndarray, R_wc: np.ndarray, center: np.ndarray, size: tuple[int, int], *,
                 texture: float = 1.0, blur: float = 0.0, noise: float = 0.0, seed: int = 0
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (BGR uint8 (H, W, 3), depth (H, W) float32 m, normals (H, W, 3) float32 camera frame).

    Depth is along the optical axis; normals are unit, camera frame, pointing
    towards the camera. ``seed`` seeds the image noise (use a per-frame seed).
    """
    hits = raycast(scene, K, R_wc, center, size)
    img = finish(shade(scene, hits, texture, texture_seed=scene.seed), blur, noise, seed)
    return img, hits["depth"], hits["normal_cam"]
