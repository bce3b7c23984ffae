"""Manhattan box-room scenes for the synthetic capture generator.

A :class:`Scene` is an inside-out box (the room shell, floor at z = 0, +z up,
metres) plus axis-aligned boxes (furniture, door and window frames, posters),
all given in the ROOM frame. The room frame is placed in the world by a yaw
about +z (``R_world_room``) and a translation (``t_world_room``)::

    p_world = R_world_room @ p_room + t_world_room

so the scene's Manhattan frame is not the identity. Manhattan axis indices
0, 1, 2 are the room's x, y, z axes; axis 2 is vertical.

``scene.json`` (what :meth:`Scene.to_json` returns; schema version 1)::

    {
      "version": 1,
      "name": "living",                      # preset name or "random"
      "seed": 0,
      "units": "m",
      "frame": "room",                       # all min/max below are room-frame
      "room_yaw_deg": 20.0,                  # yaw of the room axes about world +z
      "R_world_room": [[...], [...], [...]], # 3x3, p_world = R p_room + t
      "t_world_room": [tx, ty, tz],
      "manhattan_directions_world": [[...], [...], [...]],  # rows: room x, y, z in world
      "room": {"min": [0, 0, 0], "max": [W, D, H]},   # shell's inner corners
      "stand_point_room": [x, y, 0],         # where the person stands (floor)
      "light_dir_room": [lx, ly, lz],        # unit vector towards the light
      "boxes": [{"name": "sofa_seat", "kind": "furniture",
                 "min": [x0, y0, z0], "max": [x1, y1, z1],
                 "color": [r, g, b]}, ...],  # solid boxes, colours in 0..1
      "shell_colors": [[r, g, b] x 6]        # walls -x, +x, -y, +y, floor, ceiling
    }

A consumer computes point-to-surface distances by mapping world points into
the room frame (``R^T (p - t)``) and taking the minimum over the shell's six
planes and the boxes' surfaces; :meth:`Scene.distance_to_surfaces` does that
and :func:`scene_from_json` reads the dictionary back.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .textures import SurfaceTextures, textures_from_json

SCENES: tuple[str, ...] = ("living", "bedroom", "office", "random", "bare", "plain", "hall", "narrow")

# Box kinds (all are solid axis-aligned boxes). STRUCTURE: part of the room's own shape (the solid corner of an
# L-shaped room, the wall beside an alcove, a pillar, a gallery, a beam): its faces are walls.
FURNITURE, DOOR, WINDOW, POSTER, STRUCTURE = "furniture", "door", "window", "poster", "structure"

_WALLS = ("-x", "+x", "-y", "+y")  # shell face order 0..3; 4 = floor, 5 = ceiling


@dataclass(frozen=True)
class Faces:
    """Every planar rectangle of a scene, in the room frame (struct of arrays).

    Face ``k`` lies in the plane ``x[axis[k]] = offset[k]``, its outward normal
    (for the shell: pointing into the room) is ``sign[k] * e_axis``; it spans
    ``lo[k] .. hi[k]`` along the two other axes in increasing axis order
    (axis 0 -> (y, z), 1 -> (x, z), 2 -> (x, y)). ``surface[k]`` is 0..5 for
    the shell (walls -x, +x, -y, +y, floor, ceiling) and ``6 + b`` for box ``b``.
    """

    axis: np.ndarray  # (N,) int8
    offset: np.ndarray  # (N,) float64
    sign: np.ndarray  # (N,) int8
    lo: np.ndarray  # (N, 2) float64
    hi: np.ndarray  # (N, 2) float64
    surface: np.ndarray  # (N,) int32

    @property
    def n(self) -> int:
        return len(self.axis)


def _other_axes(a: int) -> tuple[int, int]:
    return ((1, 2), (0, 2), (0, 1))[a]


def yaw_matrix(yaw_deg: float) -> np.ndarray:
    """Returns the 3x3 rotation by ``yaw_deg`` degrees about +z."""
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, eq=False)
class Scene:
    """A Manhattan box room: shell + boxes in the room frame, placed in the world by a yaw.

    Arrays: ``room_min``/``room_max`` (3,) inner shell corners (floor z = 0);
    ``boxes_min``/``boxes_max`` (B, 3); ``box_colors`` (B, 3) and
    ``shell_colors`` (6, 3) RGB in 0..1; ``stand_point`` (3,) room-frame
    point on the floor where the person stands; ``light_dir`` (3,) unit
    room-frame direction towards the light.
    """

    name: str
    seed: int
    room_min: np.ndarray
    room_max: np.ndarray
    boxes_min: np.ndarray
    boxes_max: np.ndarray
    box_names: tuple[str, ...]
    box_kinds: tuple[str, ...]
    box_colors: np.ndarray
    shell_colors: np.ndarray
    yaw_deg: float
    R_world_room: np.ndarray
    t_world_room: np.ndarray
    stand_point: np.ndarray
    light_dir: np.ndarray
    textures: SurfaceTextures | None = None  # per-surface textures (procedural rooms); None: one noise for all

    @property
    def n_boxes(self) -> int:
        return len(self.boxes_min)

    @property
    def manhattan_directions(self) -> np.ndarray:
        """Returns (3, 3) rows = the room's x, y, z axes as unit world vectors (a ManhattanFrame)."""
        return self.R_world_room.T.copy()

    def to_world(self, p_room: np.ndarray) -> np.ndarray:
        """Returns room-frame points (..., 3) mapped into the world frame."""
        return np.asarray(p_room) @ self.R_world_room.T + self.t_world_room

    def to_room(self, p_world: np.ndarray) -> np.ndarray:
        """Returns world points (..., 3) mapped into the room frame."""
        return (np.asarray(p_world) - self.t_world_room) @ self.R_world_room

    @property
    def stand_point_world(self) -> np.ndarray:
        return self.to_world(self.stand_point)

    def all_boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """Returns (mins, maxs) (1 + B, 3) of the shell followed by the boxes, room frame."""
        mins = np.vstack([self.room_min[None], self.boxes_min.reshape(-1, 3)])
        maxs = np.vstack([self.room_max[None], self.boxes_max.reshape(-1, 3)])
        return mins, maxs

    def edges(self, min_length_m: float = 0.0, frame: str = "world") -> tuple[np.ndarray, np.ndarray]:
        """Returns (lines (M, 6) x1 y1 z1 x2 y2 z2 metres, labels (M,) int8 room axis 0/1/2).

        All 12 edges of the shell and of every box (the ground-truth lines a
        detector should find), in the world frame (``frame="world"``) or the
        room frame (``frame="room"``). Label 2 is the vertical axis. Edges
        shorter than ``min_length_m`` (e.g. the 1-4 cm depth edges of thin
        wall boxes) are dropped.
        """
        mins, maxs = self.all_boxes()
        lines, labels = [], []
        for a in range(3):
            b, c = _other_axes(a)
            for sb in (0, 1):
                for sc in (0, 1):
                    p = mins.copy()
                    q = maxs.copy()
                    vb = np.where(sb, maxs[:, b], mins[:, b])
                    vc = np.where(sc, maxs[:, c], mins[:, c])
                    p[:, b] = q[:, b] = vb
                    p[:, c] = q[:, c] = vc
                    lines.append(np.concatenate([p, q], axis=1))
                    labels.append(np.full(len(p), a, dtype=np.int8))
        L = np.concatenate(lines)
        lab = np.concatenate(labels)
        if STRUCTURE in self.box_kinds:
            L, lab = crease_pieces(L, lab, mins, maxs)
        keep = np.linalg.norm(L[:, 3:] - L[:, :3], axis=1) >= max(min_length_m, 1e-9)
        L, lab = L[keep], lab[keep]
        if frame == "world":
            L = np.concatenate([self.to_world(L[:, :3]), self.to_world(L[:, 3:])], axis=1)
        elif frame != "room":
            raise ValueError(f"frame must be 'world' or 'room', not {frame!r}")
        return L, lab

    def faces(self) -> Faces:
        """Returns every planar rectangle (shell faces first, then 6 per box) in the room frame."""
        mins, maxs = self.all_boxes()
        n = len(mins)
        axis, offset, sign, lo, hi, surface = [], [], [], [], [], []
        for a in range(3):
            b, c = _other_axes(a)
            for side in (0, 1):
                # shell: the face at room_min[a] faces +a (into the room); boxes: outward
                s = np.where(np.arange(n) == 0, 1 if side == 0 else -1, -1 if side == 0 else 1)
                axis.append(np.full(n, a, np.int8))
                offset.append(np.where(side, maxs[:, a], mins[:, a]))
                sign.append(s.astype(np.int8))
                lo.append(np.stack([mins[:, b], mins[:, c]], axis=1))
                hi.append(np.stack([maxs[:, b], maxs[:, c]], axis=1))
                surf = np.concatenate([[2 * a + side], 6 + np.arange(n - 1)])
                surface.append(surf.astype(np.int32))
        # order: shell faces first (surface 0..5), then by box
        axis, offset, sign = (np.concatenate(v) for v in (axis, offset, sign))
        lo, hi, surface = np.concatenate(lo), np.concatenate(hi), np.concatenate(surface)
        face_rank = np.tile(np.arange(6), (n, 1)).T.ravel()  # position within its box
        order = np.lexsort((face_rank, surface))
        return Faces(axis[order], offset[order], sign[order], lo[order], hi[order], surface[order])

    def distance_to_surfaces(self, points_world: np.ndarray) -> np.ndarray:
        """Returns (N,) distances (m) from world points to the nearest scene surface.

        The shell counts as its six infinite planes clipped to the room (for
        points inside the room: the distance to the nearest plane); boxes as
        solid boxes (distance to their surface, inside or out).
        """
        p = self.to_room(np.asarray(points_world, dtype=np.float64).reshape(-1, 3))
        inside_d = np.minimum(p - self.room_min, self.room_max - p)  # (N, 3)
        outside = np.maximum(np.maximum(self.room_min - p, p - self.room_max), 0.0)
        d_shell = np.where(np.all(outside == 0, axis=1), np.abs(inside_d).min(axis=1), np.linalg.norm(outside, axis=1))
        if self.n_boxes == 0:
            return d_shell
        lo = self.boxes_min[None] - p[:, None]  # (N, B, 3)
        hi = p[:, None] - self.boxes_max[None]
        q = np.maximum(lo, hi)  # > 0 outside along that axis
        out = np.linalg.norm(np.maximum(q, 0.0), axis=2)
        inn = -np.minimum(q.max(axis=2), 0.0)
        d_box = np.where(out > 0, out, inn).min(axis=1)
        return np.minimum(d_shell, d_box)

    def to_json(self) -> dict:
        """Returns the ``scene.json`` dictionary (schema in the module docstring)."""
        r = lambda a: np.round(np.asarray(a, dtype=np.float64), 6).tolist()  # noqa: E731
        return {
            "version": 1,
            "name": self.name,
            "seed": int(self.seed),
            "units": "m",
            "frame": "room",
            "room_yaw_deg": float(self.yaw_deg),
            "R_world_room": np.asarray(self.R_world_room, dtype=np.float64).tolist(),
            "t_world_room": r(self.t_world_room),
            "manhattan_directions_world": np.asarray(self.manhattan_directions).tolist(),
            "room": {"min": r(self.room_min), "max": r(self.room_max)},
            "stand_point_room": r(self.stand_point),
            "light_dir_room": r(self.light_dir),
            "boxes": [
                {"name": n, "kind": k, "min": r(lo), "max": r(hi), "color": r(c)}
                for n, k, lo, hi, c in zip(self.box_names, self.box_kinds, self.boxes_min, self.boxes_max, self.box_colors)
            ],
            "shell_colors": r(self.shell_colors),
            **({"textures": self.textures.to_json()} if self.textures is not None else {}),
        }


def scene_from_json(d: dict) -> Scene:
    """Returns the :class:`Scene` described by a ``scene.json`` dictionary."""
    boxes = d.get("boxes", [])
    as3 = lambda key: np.array([b[key] for b in boxes], dtype=np.float64).reshape(-1, 3)  # noqa: E731
    return Scene(
        name=str(d.get("name", "scene")),
        seed=int(d.get("seed", 0)),
        room_min=np.asarray(d["room"]["min"], dtype=np.float64),
        room_max=np.asarray(d["room"]["max"], dtype=np.float64),
        boxes_min=as3("min"),
        boxes_max=as3("max"),
        box_names=tuple(str(b.get("name", f"box{i}")) for i, b in enumerate(boxes)),
        box_kinds=tuple(str(b.get("kind", FURNITURE)) for b in boxes),
        box_colors=np.array([b.get("color", [0.6, 0.6, 0.6]) for b in boxes], dtype=np.float64).reshape(-1, 3),
        shell_colors=np.asarray(d.get("shell_colors", [[0.7, 0.7, 0.7]] * 6), dtype=np.float64),
        yaw_deg=float(d.get("room_yaw_deg", 0.0)),
        R_world_room=np.asarray(d["R_world_room"], dtype=np.float64),
        t_world_room=np.asarray(d["t_world_room"], dtype=np.float64),
        stand_point=np.asarray(d.get("stand_point_room", [0, 0, 0]), dtype=np.float64),
        light_dir=np.asarray(d.get("light_dir_room", [0.5, 0.3, 0.81]), dtype=np.float64),
        textures=textures_from_json(d.get("textures")),
    )


def crease_pieces(lines: np.ndarray, labels: np.ndarray, mins: np.ndarray, maxs: np.ndarray, eps: float = 2e-3
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Returns the parts of axis-aligned room-frame edges (M, 6) that are creases of the free space.

    ``mins`` / ``maxs`` (1 + B, 3): the shell (free inside) then solid boxes. Each edge is cut where a box
    begins or ends along it; a piece is a crease where the four quadrants about it (``eps`` off the edge) are
    not two neighbouring free ones and two solid ones (a flat surface), all free or all solid. Pieces that
    are creases and touch are joined again.
    """
    if not len(lines):
        return lines, labels
    axis = labels.astype(int)
    lo_e = np.minimum(lines[:, :3], lines[:, 3:])[np.arange(len(lines)), axis]
    hi_e = np.maximum(lines[:, :3], lines[:, 3:])[np.arange(len(lines)), axis]
    cuts = np.concatenate([mins, maxs])  # (2(1+B), 3)
    out, out_lab = [], []
    for a in range(3):
        b, c = _other_axes(a)
        idx = np.flatnonzero(axis == a)
        if not len(idx):
            continue
        t = np.unique(cuts[:, a])
        for e in idx:
            ts = np.concatenate([[lo_e[e]], t[(t > lo_e[e]) & (t < hi_e[e])], [hi_e[e]]])
            mid = 0.5 * (ts[:-1] + ts[1:])
            p = np.repeat(lines[e, None, :3], len(mid), axis=0)
            p[:, a] = mid
            free = []
            for db, dc in ((eps, eps), (-eps, eps), (-eps, -eps), (eps, -eps)):  # quadrants in turn
                q = p.copy()
                q[:, b] += db
                q[:, c] += dc
                inside_shell = np.all((q > mins[0]) & (q < maxs[0]), axis=1)
                in_box = np.any(np.all((q[:, None] > mins[None, 1:]) & (q[:, None] < maxs[None, 1:]), axis=2), axis=1)
                free.append(inside_shell & ~in_box)
            free = np.stack(free, axis=1)
            n_free = free.sum(axis=1)
            flat = (n_free == 2) & ((free[:, 0] == free[:, 1]) | (free[:, 1] == free[:, 2]))
            crease = (n_free > 0) & (n_free < 4) & ~flat
            start = None
            for k in range(len(mid) + 1):
                if k < len(mid) and crease[k]:
                    start = ts[k] if start is None else start
                elif start is not None:
                    seg = np.repeat(lines[e, None, :3], 2, axis=0)
                    seg[0, a], seg[1, a] = start, ts[k]
                    out.append(seg.ravel())
                    out_lab.append(a)
                    start = None
    if not out:
        return np.zeros((0, 6)), np.zeros(0, np.int8)
    return np.array(out), np.array(out_lab, dtype=np.int8)


# --------------------------------------------------------------------------- builders


class _Builder:
    """Collects boxes of one room (room frame) with names, kinds and colours."""

    def __init__(self, size: tuple[float, float, float]):
        self.size = np.asarray(size, dtype=np.float64)
        self.mins: list[np.ndarray] = []
        self.maxs: list[np.ndarray] = []
        self.names: list[str] = []
        self.kinds: list[str] = []
        self.colors: list[tuple[float, float, float]] = []

    def box(self, name, kind, lo, hi, color):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        assert np.all(hi > lo), (name, lo, hi)
        self.mins.append(lo)
        self.maxs.append(hi)
        self.names.append(name)
        self.kinds.append(kind)
        self.colors.append(tuple(float(c) for c in color))

    def pop(self, n: int = 1) -> None:
        """Removes the last ``n`` boxes."""
        for lst in (self.mins, self.maxs, self.names, self.kinds, self.colors):
            del lst[len(lst) - n:]

    def floor_box(self, name, x0, y0, sx, sy, sz, color, z0=0.0, kind=FURNITURE):
        self.box(name, kind, (x0, y0, z0), (x0 + sx, y0 + sy, z0 + sz), color)

    def wall_box(self, name, kind, wall, u0, z0, width, height, thick, color):
        """A box against ``wall`` ('-x', '+x', '-y', '+y'): ``u0..u0+width`` along the wall, protruding ``thick``."""
        W, D, _ = self.size
        if wall in ("-y", "+y"):
            y0 = 0.0 if wall == "-y" else D - thick
            self.box(name, kind, (u0, y0, z0), (u0 + width, y0 + thick, z0 + height), color)
        else:
            x0 = 0.0 if wall == "-x" else W - thick
            self.box(name, kind, (x0, u0, z0), (x0 + thick, u0 + width, z0 + height), color)

    def against(self, name, wall, u0, width, depth, height, color, z0=0.0):
        """A furniture box whose back touches ``wall``; ``depth`` is its extent into the room."""
        self.wall_box(name, FURNITURE, wall, u0, z0, width, height, depth, color)

    def door(self, name, wall, u0, color_leaf, color_trim, width=0.9, height=2.05):
        t = 0.06  # trim width
        self.wall_box(f"{name}_leaf", DOOR, wall, u0, 0.0, width, height, 0.02, color_leaf)
        self.wall_box(f"{name}_jamb_l", DOOR, wall, u0 - t, 0.0, t, height + t, 0.035, color_trim)
        self.wall_box(f"{name}_jamb_r", DOOR, wall, u0 + width, 0.0, t, height + t, 0.035, color_trim)
        self.wall_box(f"{name}_head", DOOR, wall, u0, height, width, t, 0.035, color_trim)

    def window(self, name, wall, u0, z0, width, height, color_glass, color_trim):
        t = 0.06
        self.wall_box(f"{name}_glass", WINDOW, wall, u0, z0, width, height, 0.01, color_glass)
        self.wall_box(f"{name}_trim_l", WINDOW, wall, u0 - t, z0, t, height, 0.04, color_trim)
        self.wall_box(f"{name}_trim_r", WINDOW, wall, u0 + width, z0, t, height, 0.04, color_trim)
        self.wall_box(f"{name}_trim_t", WINDOW, wall, u0 - t, z0 + height, width + 2 * t, t, 0.04, color_trim)
        self.wall_box(f"{name}_sill", WINDOW, wall, u0 - t - 0.04, z0 - t, width + 2 * t + 0.08, t, 0.09, color_trim)

    def poster(self, name, wall, u0, z0, width, height, color):
        self.wall_box(name, POSTER, wall, u0, z0, width, height, 0.012, color)

    def build(self, name, seed, yaw_deg, shell_colors, stand_xy) -> Scene:
        W, D, H = self.size
        R = yaw_matrix(yaw_deg)
        t = -R @ np.array([W / 2, D / 2, 0.0])  # world origin: the room's floor centre
        light = np.array([0.5, 0.3, 0.81])
        return Scene(
            name=name,
            seed=int(seed),
            room_min=np.zeros(3),
            room_max=self.size.copy(),
            boxes_min=np.array(self.mins, dtype=np.float64).reshape(-1, 3),
            boxes_max=np.array(self.maxs, dtype=np.float64).reshape(-1, 3),
            box_names=tuple(self.names),
            box_kinds=tuple(self.kinds),
            box_colors=np.array(self.colors, dtype=np.float64).reshape(-1, 3),
            shell_colors=np.asarray(shell_colors, dtype=np.float64),
            yaw_deg=float(yaw_deg),
            R_world_room=R,
            t_world_room=t,
            stand_point=np.array([stand_xy[0], stand_xy[1], 0.0]),
            light_dir=light / np.linalg.norm(light),
        )


def _living(seed: int) -> Scene:
    b = _Builder((6.0, 4.5, 2.7))
    b.against("sofa_seat", "+y", 1.6, 2.1, 0.9, 0.45, (0.25, 0.35, 0.55))
    b.against("sofa_back", "+y", 1.6, 2.1, 0.22, 0.9, (0.22, 0.30, 0.50))
    b.floor_box("sofa_arm_l", 1.45, 3.6, 0.15, 0.9, 0.62, (0.20, 0.28, 0.47))
    b.floor_box("sofa_arm_r", 3.7, 3.6, 0.15, 0.9, 0.62, (0.20, 0.28, 0.47))
    b.floor_box("coffee_table", 2.1, 2.5, 1.1, 0.6, 0.42, (0.55, 0.36, 0.20))
    b.against("tv_cabinet", "-y", 1.9, 1.7, 0.45, 0.5, (0.15, 0.15, 0.17))
    b.wall_box("tv", FURNITURE, "-y", 2.15, 1.0, 1.2, 0.7, 0.05, (0.05, 0.05, 0.06))
    b.against("bookshelf", "-x", 0.3, 0.9, 0.35, 1.95, (0.70, 0.55, 0.35))
    b.against("sideboard", "+x", 2.6, 1.4, 0.45, 0.8, (0.80, 0.78, 0.72))
    b.door("door", "-x", 3.1, (0.85, 0.82, 0.75), (0.95, 0.95, 0.93))
    b.window("window", "+x", 0.8, 0.95, 1.3, 1.25, (0.62, 0.75, 0.85), (0.96, 0.96, 0.96))
    b.poster("poster_a", "+y", 2.0, 1.35, 0.7, 0.9, (0.85, 0.35, 0.25))
    b.poster("poster_b", "-y", 4.3, 1.2, 0.6, 0.8, (0.30, 0.60, 0.35))
    shell = [(0.78, 0.74, 0.62), (0.66, 0.72, 0.70), (0.80, 0.70, 0.58), (0.70, 0.66, 0.74), (0.52, 0.38, 0.26), (0.93, 0.93, 0.90)]
    return b.build("living", seed, 20.0, shell, (3.9, 1.7))


def _bedroom(seed: int) -> Scene:
    b = _Builder((4.5, 3.8, 2.5))
    b.against("bed", "+y", 1.3, 1.6, 2.0, 0.5, (0.85, 0.85, 0.80))
    b.against("headboard", "+y", 1.3, 1.6, 0.08, 1.05, (0.45, 0.30, 0.20))
    b.against("nightstand_l", "+y", 0.75, 0.45, 0.4, 0.55, (0.55, 0.40, 0.25))
    b.against("nightstand_r", "+y", 3.05, 0.45, 0.4, 0.55, (0.55, 0.40, 0.25))
    b.against("wardrobe", "-x", 0.15, 1.2, 0.6, 2.1, (0.90, 0.88, 0.82))
    b.against("dresser", "-y", 2.3, 1.1, 0.45, 0.85, (0.35, 0.25, 0.18))
    b.wall_box("mirror", FURNITURE, "-y", 2.45, 1.2, 0.8, 0.6, 0.02, (0.50, 0.56, 0.60))
    b.door("door", "+x", 0.4, (0.92, 0.90, 0.86), (0.97, 0.97, 0.97))
    b.window("window", "-y", 0.5, 0.9, 1.1, 1.2, (0.60, 0.72, 0.85), (0.96, 0.96, 0.96))
    b.poster("poster", "+x", 1.9, 1.25, 0.6, 0.8, (0.25, 0.45, 0.70))
    shell = [(0.74, 0.78, 0.70), (0.78, 0.72, 0.66), (0.84, 0.72, 0.56), (0.66, 0.70, 0.78), (0.60, 0.48, 0.36), (0.94, 0.94, 0.92)]
    return b.build("bedroom", seed, -35.0, shell, (2.6, 1.2))


def _office(seed: int) -> Scene:
    b = _Builder((5.0, 4.0, 2.8))
    top, leg = (0.80, 0.76, 0.68), (0.25, 0.25, 0.27)
    b.floor_box("desk_top", 0.4, 3.2, 1.6, 0.75, 0.04, top, z0=0.72)
    for i, (x, y) in enumerate([(0.45, 3.25), (1.9, 3.25), (0.45, 3.85), (1.9, 3.85)]):
        b.floor_box(f"desk_leg{i}", x, y, 0.05, 0.05, 0.72, leg)
    b.against("monitor", "+y", 0.8, 0.6, 0.12, 0.4, (0.08, 0.08, 0.09), z0=0.9)
    b.against("filing_cabinet", "+y", 2.3, 0.5, 0.6, 0.75, (0.55, 0.58, 0.62))
    b.against("bookshelf_a", "+x", 0.4, 0.9, 0.35, 2.0, (0.62, 0.45, 0.28))
    b.against("bookshelf_b", "+x", 1.35, 0.9, 0.35, 2.0, (0.62, 0.45, 0.28))
    b.floor_box("meeting_table", 2.9, 0.9, 1.4, 0.9, 0.74, (0.40, 0.30, 0.22))
    b.against("cabinet", "-y", 0.5, 1.2, 0.5, 1.1, (0.85, 0.85, 0.85))
    b.door("door", "-x", 0.5, (0.60, 0.45, 0.30), (0.92, 0.92, 0.90))
    b.window("window_a", "-y", 2.4, 1.0, 1.0, 1.3, (0.60, 0.72, 0.85), (0.95, 0.95, 0.95))
    b.window("window_b", "-y", 3.7, 1.0, 0.9, 1.3, (0.60, 0.72, 0.85), (0.95, 0.95, 0.95))
    b.poster("whiteboard", "-x", 1.8, 1.0, 1.6, 1.0, (0.97, 0.97, 0.97))
    b.poster("poster", "+y", 3.2, 1.3, 0.7, 0.5, (0.80, 0.60, 0.20))
    shell = [(0.80, 0.80, 0.76), (0.70, 0.74, 0.78), (0.76, 0.72, 0.68), (0.66, 0.70, 0.66), (0.40, 0.42, 0.46), (0.95, 0.95, 0.95)]
    return b.build("office", seed, 50.0, shell, (1.6, 1.9))


def _bare(seed: int) -> Scene:
    """A bare painted room: four walls, floor, ceiling and one door (issue #40's hardest kind)."""
    b = _Builder((4.2, 3.6, 2.6))
    b.door("door", "+x", 1.2, (0.90, 0.89, 0.86), (0.96, 0.96, 0.95))
    shell = [(0.86, 0.85, 0.80), (0.84, 0.84, 0.80), (0.85, 0.84, 0.79), (0.83, 0.83, 0.79), (0.62, 0.55, 0.46),
             (0.95, 0.95, 0.93)]
    return b.build("bare", seed, 10.0, shell, (2.5, 1.5))


def _plain(seed: int) -> Scene:
    """A plain-walled playroom: a door, a window and a few small objects on the floor, nothing on the walls."""
    b = _Builder((4.6, 3.9, 2.6))
    b.door("door", "-x", 2.4, (0.88, 0.86, 0.82), (0.96, 0.96, 0.95))
    b.window("window", "+y", 1.4, 0.9, 1.2, 1.2, (0.62, 0.74, 0.86), (0.96, 0.96, 0.96))
    b.floor_box("toy_box", 3.6, 0.3, 0.6, 0.4, 0.4, (0.85, 0.30, 0.25))
    b.floor_box("blocks", 1.0, 0.8, 0.3, 0.3, 0.3, (0.25, 0.45, 0.80))
    b.floor_box("stool", 0.5, 3.0, 0.35, 0.35, 0.45, (0.95, 0.80, 0.20))
    b.against("low_shelf", "+x", 2.2, 0.8, 0.3, 0.6, (0.75, 0.60, 0.40))
    shell = [(0.84, 0.82, 0.76), (0.80, 0.84, 0.82), (0.85, 0.80, 0.74), (0.80, 0.80, 0.84), (0.58, 0.50, 0.40),
             (0.95, 0.95, 0.93)]
    return b.build("plain", seed, -15.0, shell, (2.9, 2.3))


def _hall(seed: int) -> Scene:
    """A large hall, 9 x 7 x 4 m, the stand point well off its centre (lines 3-7 m away)."""
    b = _Builder((9.0, 7.0, 4.0))
    b.door("door_a", "-x", 1.5, (0.55, 0.40, 0.28), (0.92, 0.92, 0.90), width=1.6, height=2.4)
    b.door("door_b", "+y", 6.5, (0.55, 0.40, 0.28), (0.92, 0.92, 0.90))
    for k, u in enumerate((1.2, 3.6, 6.0)):
        b.window(f"window_{k}", "-y", u, 1.2, 1.6, 2.0, (0.62, 0.74, 0.86), (0.96, 0.96, 0.96))
    b.against("stage", "+x", 1.5, 4.0, 1.5, 0.5, (0.45, 0.32, 0.22))
    b.against("piano", "+y", 1.0, 1.5, 0.6, 1.1, (0.08, 0.08, 0.09))
    b.floor_box("table_a", 3.0, 4.5, 1.8, 0.8, 0.75, (0.70, 0.55, 0.35))
    b.floor_box("table_b", 5.4, 4.5, 1.8, 0.8, 0.75, (0.70, 0.55, 0.35))
    b.poster("banner", "-x", 4.2, 1.8, 1.8, 1.0, (0.80, 0.25, 0.25))
    shell = [(0.86, 0.82, 0.72), (0.78, 0.80, 0.78), (0.84, 0.78, 0.70), (0.80, 0.78, 0.82), (0.50, 0.36, 0.24),
             (0.95, 0.95, 0.93)]
    return b.build("hall", seed, 30.0, shell, (6.4, 2.2))


def _narrow(seed: int) -> Scene:
    """A long narrow room (a corridor-like study), 7.0 x 2.4 x 2.6 m: the near walls 0.8-1.6 m away."""
    b = _Builder((7.0, 2.4, 2.6))
    b.door("door", "-x", 0.7, (0.90, 0.88, 0.84), (0.96, 0.96, 0.95))
    b.window("window", "+x", 0.6, 0.9, 1.2, 1.2, (0.62, 0.74, 0.86), (0.96, 0.96, 0.96))
    b.against("bookshelf", "+y", 1.0, 2.4, 0.25, 2.0, (0.62, 0.45, 0.28))
    b.against("desk", "-y", 4.2, 1.4, 0.6, 0.75, (0.80, 0.76, 0.68))
    b.poster("poster", "-y", 1.5, 1.3, 0.8, 0.6, (0.30, 0.55, 0.70))
    shell = [(0.82, 0.80, 0.74), (0.78, 0.80, 0.76), (0.84, 0.80, 0.72), (0.80, 0.78, 0.80), (0.55, 0.45, 0.35),
             (0.95, 0.95, 0.93)]
    return b.build("narrow", seed, -60.0, shell, (3.0, 1.15))


def _random_color(rng: np.random.Generator, lum: tuple[float, float]) -> np.ndarray:
    c = rng.uniform(0.15, 0.95, 3)
    y = 0.299 * c[0] + 0.587 * c[1] + 0.114 * c[2]
    target = rng.uniform(*lum)
    return np.clip(c * target / max(y, 1e-3), 0.02, 1.0)


def random_box_room(seed: int) -> Scene:
    """Returns a seeded furnished box room: size, yaw, door, window, posters, 3-6 furniture pieces (the rooms the
    shipped normal network was trained on, ``tools/train_normals.py``; ``--scene random`` is :mod:`.procedural`)."""
    rng = np.random.default_rng([seed, 7311])
    W, D, H = rng.uniform(3.6, 7.0), rng.uniform(3.2, 6.0), rng.uniform(2.4, 3.0)
    b = _Builder((W, D, H))
    keepout: list[tuple[np.ndarray, np.ndarray]] = []

    def free(lo, hi) -> bool:
        lo, hi = np.asarray(lo), np.asarray(hi)
        if np.any(lo < -1e-9) or np.any(hi > b.size + 1e-9):
            return False
        return all(np.any(hi <= k_lo) or np.any(lo >= k_hi) for k_lo, k_hi in keepout)

    def wall_extent(wall):
        return W if wall in ("-y", "+y") else D

    def wall_aabb(wall, u0, z0, width, height, depth):
        if wall in ("-y", "+y"):
            y0 = 0.0 if wall == "-y" else D - depth
            return (u0, y0, z0), (u0 + width, y0 + depth, z0 + height)
        x0 = 0.0 if wall == "-x" else W - depth
        return (x0, u0, z0), (x0 + depth, u0 + width, z0 + height)

    walls = list(rng.permutation(_WALLS))
    # door (with 0.8 m keep-out in front of it)
    for _ in range(50):
        u0 = rng.uniform(0.2, wall_extent(walls[0]) - 1.2)
        lo, hi = wall_aabb(walls[0], u0 - 0.1, 0.0, 1.1, 2.2, 0.8)
        if free(lo, hi):
            b.door("door", walls[0], u0, _random_color(rng, (0.6, 0.9)), _random_color(rng, (0.85, 0.97)))
            keepout.append((np.array(lo), np.array(hi)))
            break
    # window
    for _ in range(50):
        wdt = rng.uniform(0.8, 1.6)
        if wall_extent(walls[1]) - wdt < 0.6:
            break
        u0 = rng.uniform(0.3, wall_extent(walls[1]) - wdt - 0.3)
        z0 = rng.uniform(0.85, 1.05)
        lo, hi = wall_aabb(walls[1], u0 - 0.15, z0 - 0.1, wdt + 0.3, min(1.3, H - z0 - 0.3) + 0.2, 0.12)
        if free(lo, hi):
            b.window("window", walls[1], u0, z0, wdt, min(1.3, H - z0 - 0.3), (0.6, 0.72, 0.85), _random_color(rng, (0.85, 0.97)))
            keepout.append((np.array(lo), np.array(hi)))
            break
    # furniture against walls (and one free-standing table)
    kinds = [("sofa", 2.0, 0.9, 0.8), ("cabinet", 1.2, 0.5, 1.0), ("shelf", 0.9, 0.35, 1.9),
             ("bed", 1.6, 2.0, 0.55), ("desk", 1.4, 0.7, 0.75), ("dresser", 1.0, 0.45, 0.85)]
    n_furn = int(rng.integers(3, 7))
    placed = 0
    for _ in range(200):
        if placed >= n_furn:
            break
        kname, w, d, h = kinds[int(rng.integers(len(kinds)))]
        w, d, h = (v * rng.uniform(0.85, 1.15) for v in (w, d, h))
        wall = walls[int(rng.integers(4))]
        if wall_extent(wall) < w + 0.2:
            continue
        u0 = rng.uniform(0.05, wall_extent(wall) - w - 0.05)
        lo, hi = wall_aabb(wall, u0, 0.0, w, h, d)
        lo_k, hi_k = np.array(lo) - 0.05, np.array(hi) + 0.05
        if free(np.maximum(lo_k, 0), np.minimum(hi_k, b.size)):
            b.against(f"{kname}{placed}", wall, u0, w, d, h, _random_color(rng, (0.2, 0.8)))
            if _best_clearance(b) < STAND_CLEARANCE_M:  # keep room to spin
                b.pop()
                continue
            keepout.append((lo_k, hi_k))
            placed += 1
    for _ in range(50):
        w, d = rng.uniform(0.8, 1.4), rng.uniform(0.5, 0.9)
        x0, y0 = rng.uniform(0.6, W - w - 0.6), rng.uniform(0.6, D - d - 0.6)
        lo, hi = (x0 - 0.1, y0 - 0.1, 0.0), (x0 + w + 0.1, y0 + d + 0.1, 0.8)
        if free(lo, hi):
            b.floor_box("table", x0, y0, w, d, rng.uniform(0.42, 0.76), _random_color(rng, (0.2, 0.7)))
            if _best_clearance(b) < STAND_CLEARANCE_M:
                b.pop()
                continue
            keepout.append((np.array(lo), np.array(hi)))
            break
    # posters, above furniture height
    n_post = int(rng.integers(1, 4))
    for i in range(n_post):
        for _ in range(50):
            wall = walls[int(rng.integers(4))]
            pw, ph = rng.uniform(0.4, 1.0), rng.uniform(0.4, 0.9)
            if wall_extent(wall) < pw + 0.4:
                continue
            u0 = rng.uniform(0.2, wall_extent(wall) - pw - 0.2)
            z0 = rng.uniform(1.0, max(1.05, H - ph - 0.35))
            lo, hi = wall_aabb(wall, u0 - 0.05, z0 - 0.05, pw + 0.1, ph + 0.1, 0.05)
            if free(lo, hi):
                b.poster(f"poster{i}", wall, u0, z0, pw, ph, _random_color(rng, (0.25, 0.85)))
                keepout.append((np.array(lo), np.array(hi)))
                break
    shell = [_random_color(rng, (0.55, 0.85)) for _ in range(4)]
    shell += [_random_color(rng, (0.3, 0.5)), _random_color(rng, (0.88, 0.95))]
    stand = _pick_stand_point(b, rng)
    return b.build("random", seed, float(rng.uniform(-45.0, 45.0)), shell, stand)


STAND_CLEARANCE_M = 0.95  # horizontal clearance around the stand point (camera circle + margin)


def _clearance(b: _Builder) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (grid points (N, 2), horizontal clearance (N,) to walls and boxes, distance to the centre (N,))."""
    W, D, _ = b.size
    xs, ys = np.meshgrid(np.arange(0.0, W, 0.05), np.arange(0.0, D, 0.05), indexing="ij")
    p = np.stack([xs.ravel(), ys.ravel()], axis=1)
    d = np.minimum.reduce([p[:, 0], W - p[:, 0], p[:, 1], D - p[:, 1]])
    if b.mins:
        lo, hi = np.array(b.mins)[:, :2], np.array(b.maxs)[:, :2]
        q = np.maximum(lo[None] - p[:, None], p[:, None] - hi[None])  # (N, B, 2)
        d = np.minimum(d, np.linalg.norm(np.maximum(q, 0.0), axis=2).min(axis=1))
    return p, d, np.linalg.norm(p - np.array([W / 2, D / 2]), axis=1)


def _best_clearance(b: _Builder) -> float:
    _, d, off = _clearance(b)
    return float(np.max(np.where(off >= 0.25, d, -1.0)))


def _pick_stand_point(b: _Builder, rng: np.random.Generator, clearance_m: float = STAND_CLEARANCE_M
                      ) -> tuple[float, float]:
    """Returns a room-frame (x, y) with ``clearance_m`` to walls and furniture, away from the centre."""
    p, d, off_centre = _clearance(b)
    ok = (d >= clearance_m) & (off_centre >= 0.25)
    if ok.any():
        cand = np.flatnonzero(ok)
        # prefer points far from the centre among the clear ones
        far = cand[off_centre[cand] >= np.quantile(off_centre[cand], 0.4)]
        i = int(rng.choice(far))
    else:  # a crowded room: the clearest point off the centre
        i = int(np.argmax(np.where(off_centre >= 0.25, d, -1.0)))
    return float(p[i, 0]), float(p[i, 1])


def _procedural(seed: int, photo_dir=None) -> Scene:
    from .procedural import procedural_room

    return procedural_room(seed, photo_dir)


_PRESETS = {"living": _living, "bedroom": _bedroom, "office": _office, "random": _procedural, "bare": _bare,
            "plain": _plain, "hall": _hall, "narrow": _narrow}


def make_scene(name: str, seed: int = 0, photo_dir=None) -> Scene:
    """Returns the named scene (``SCENES``); ``seed`` only changes the ``random`` room (:mod:`.procedural`), which
    paints some surfaces with crops of the equirectangular photos in ``photo_dir`` where given."""
    from ..errors import InputError

    if name not in _PRESETS:
        raise InputError(f"unknown scene {name!r}; choose one of {', '.join(SCENES)}")
    if name == "random":
        return _procedural(int(seed), photo_dir)
    return _PRESETS[name](int(seed))
