"""Reconstruction files: COLMAP text model, ``lines.ply``, ``summary.json``, atomic output.

The layout is fixed in ``capture-format.md`` ("A reconstruction: one output
directory")::

    <out>/sparse/{cameras,images,points3D}.txt   COLMAP text model
    <out>/lines.ply                              3D segments (vertices + edges)
    <out>/summary.json                           counts, residuals, timings

Conventions: ``R_wc`` is world_from_camera, ``centers`` are camera centres in
the world; COLMAP stores cam_from_world, so ``images.txt`` holds
``q(R_wc^T)`` and ``t = -R_wc^T c``. Only registered frames are written.

Atomic replacement (:func:`atomic_output_dir`): a run writes into
``.<name>.tmp-<pid>-<random>`` next to ``<out>``; on success the previous
result is renamed to ``.<name>.backup``, the new one renamed to ``<out>``, and
the backup removed. Recovery rule for a leftover backup (applied by
:func:`recover_output_dir`, which :func:`atomic_output_dir` calls first): if
``<out>`` is missing, the backup IS the previous complete result and is
renamed back; if ``<out>`` exists, the new result was already in place and the
backup is deleted. Leftover ``.tmp-<pid>-*`` directories of dead processes
are incomplete and deleted.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .data import AXIS_NAMES, UNLABELLED, Camera, Solution
from .errors import InputError
from .geometry import matrix_to_quat_wxyz, quat_wxyz_to_matrix

log = logging.getLogger(__name__)

# COLMAP camera models this project reads, with their parameter counts. SIMPLE_RADIAL
# and RADIAL are converted to the equivalent OPENCV camera (same distortion polynomial).
COLMAP_MODELS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8}

# Colours used for lines when no per-line colour is given: x red, y green, z blue, none grey.
AXIS_COLORS = np.array([[230, 60, 60], [60, 200, 60], [60, 110, 240], [160, 160, 160]], dtype=np.uint8)


def _fmt(x: float) -> str:
    """Returns ``x`` as COLMAP writes doubles (17 significant digits, exact round trip; -0 as 0)."""
    return "%.17g" % (float(x) + 0.0)


# --------------------------------------------------------------------------------------
# COLMAP text model
# --------------------------------------------------------------------------------------


def write_colmap_text(
    sparse_dir: str | Path,
    camera: Camera,
    frame_names: tuple[str, ...] | list[str],
    R_wc: np.ndarray,
    centers: np.ndarray,
    registered: np.ndarray,
    points3D: np.ndarray | None = None,
) -> Path:
    """Returns ``sparse_dir`` after writing cameras.txt, images.txt and points3D.txt there.

    One camera (id 1, ``camera.model`` and its COLMAP-ordered params). Image ids are
    frame index + 1, so they stay stable whichever frames registered; only frames with
    ``registered[f]`` are written (a non-finite pose there is a ``ValueError``). Each
    image line is followed by an empty POINTS2D line. ``points3D`` is ``(P, 3)`` xyz or
    ``(P, 6)`` xyz + RGB (0..255), written with ERROR -1 and an empty track.
    """
    sparse_dir = Path(sparse_dir)
    sparse_dir.mkdir(parents=True, exist_ok=True)
    R_wc = np.asarray(R_wc, dtype=np.float64)
    centers = np.asarray(centers, dtype=np.float64)
    registered = np.asarray(registered, dtype=bool)
    n = len(frame_names)
    if not (R_wc.shape == (n, 3, 3) and centers.shape == (n, 3) and registered.shape == (n,)):
        raise ValueError(f"write_colmap_text: {n} names but R_wc {R_wc.shape}, centers {centers.shape}, registered {registered.shape}")
    params = np.asarray(camera.params, dtype=np.float64)
    if camera.model not in COLMAP_MODELS or len(params) != COLMAP_MODELS[camera.model]:
        raise ValueError(f"write_colmap_text: camera model {camera.model} with {len(params)} params is not a COLMAP model")

    with open(sparse_dir / "cameras.txt", "w") as f:
        f.write("# Camera list with one line of data per camera:\n")
        f.write("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        f.write("# Number of cameras: 1\n")
        f.write(" ".join(["1", camera.model, str(int(camera.width)), str(int(camera.height))] + [_fmt(p) for p in params]) + "\n")

    idx = np.flatnonzero(registered)
    if not (np.all(np.isfinite(R_wc[idx])) and np.all(np.isfinite(centers[idx]))):
        raise ValueError("write_colmap_text: a registered frame has a non-finite pose")
    R_cw = np.transpose(R_wc[idx], (0, 2, 1))
    q = matrix_to_quat_wxyz(R_cw) if len(idx) else np.zeros((0, 4))
    t = -np.einsum("nij,nj->ni", R_cw, centers[idx])
    with open(sparse_dir / "images.txt", "w") as f:
        f.write("# Image list with two lines of data per image:\n")
        f.write("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n")
        f.write("#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        f.write(f"# Number of images: {len(idx)}, mean observations per image: 0\n")
        for k, i in enumerate(idx):
            name = str(frame_names[i])
            if any(c.isspace() for c in name):
                log.warning("frame name %r has white space: COLMAP's reader keeps only its first word", name)
            vals = " ".join(_fmt(v) for v in (*q[k], *t[k]))
            f.write(f"{i + 1} {vals} 1 {name}\n\n")

    pts = np.zeros((0, 6)) if points3D is None else np.asarray(points3D, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] not in (3, 6):
        raise ValueError(f"write_colmap_text: points3D must be (P, 3) or (P, 6), got {pts.shape}")
    if pts.shape[1] == 3:
        pts = np.concatenate([pts, np.full((len(pts), 3), 255.0)], axis=1)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    rgb = np.clip(np.rint(pts[:, 3:]), 0, 255).astype(int)
    with open(sparse_dir / "points3D.txt", "w") as f:
        f.write("# 3D point list with one line of data per point:\n")
        f.write("#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
        f.write(f"# Number of points: {len(pts)}, mean track length: 0\n")
        for k in range(len(pts)):
            f.write(f"{k + 1} {_fmt(pts[k, 0])} {_fmt(pts[k, 1])} {_fmt(pts[k, 2])} {rgb[k, 0]} {rgb[k, 1]} {rgb[k, 2]} -1\n")
    return sparse_dir


def _data_lines(path: Path) -> list[tuple[int, str]]:
    """Returns (1-based line number, stripped text) of every line, comments dropped."""
    if not path.is_file():
        raise InputError("missing (a COLMAP text model needs cameras.txt and images.txt)", path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise InputError(f"cannot read ({e.strerror})", path) from None
    return [(k + 1, ln.strip()) for k, ln in enumerate(text.splitlines()) if not ln.lstrip().startswith("#")]


def colmap_camera_to_camera(model: str, width: int, height: int, params: np.ndarray) -> Camera:
    """Returns the project's :class:`Camera` for a COLMAP camera (SIMPLE_RADIAL/RADIAL become OPENCV).

    COLMAP's SIMPLE_RADIAL (f, cx, cy, k) and RADIAL (f, cx, cy, k1, k2) use the same
    radial polynomial as OpenCV, so they map exactly onto OPENCV (fx=fy=f, p1=p2=0).
    """
    p = np.asarray(params, dtype=np.float64)
    if model == "SIMPLE_RADIAL":
        return Camera("OPENCV", width, height, np.array([p[0], p[0], p[1], p[2], p[3], 0.0, 0.0, 0.0]))
    if model == "RADIAL":
        return Camera("OPENCV", width, height, np.array([p[0], p[0], p[1], p[2], p[3], p[4], 0.0, 0.0]))
    return Camera(model, width, height, p)


def read_colmap_text(sparse_dir: str | Path) -> dict:
    """Returns the COLMAP text model in ``sparse_dir`` as plain arrays (the project's own reader).

    Keys: ``camera`` (the first camera as :class:`Camera`), ``cameras`` {id: Camera},
    ``colmap_models`` {id: model name as written}, ``images`` {name: {"image_id",
    "camera_id", "R_wc" (3, 3), "center" (3,)}} in file order, ``points3D`` (P, 3) and
    ``points3D_rgb`` (P, 3) uint8 (empty when points3D.txt is missing). Tolerates
    comments, blank or missing POINTS2D lines, names with spaces and unnormalised
    quaternions; any malformed line is an :class:`InputError` naming file and line.
    """
    sparse_dir = Path(sparse_dir)
    cam_path, img_path, pts_path = (sparse_dir / n for n in ("cameras.txt", "images.txt", "points3D.txt"))

    cameras: dict[int, Camera] = {}
    models: dict[int, str] = {}
    for no, ln in _data_lines(cam_path):
        if not ln:
            continue
        tok = ln.split()
        try:
            cid, model, w, h = int(tok[0]), tok[1].upper(), int(tok[2]), int(tok[3])
            params = np.array([float(v) for v in tok[4:]])
        except (ValueError, IndexError):
            raise InputError(f"line {no}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'", cam_path) from None
        if model not in COLMAP_MODELS:
            raise InputError(f"line {no}: camera model {model} not supported (use one of {', '.join(COLMAP_MODELS)})", cam_path)
        if len(params) != COLMAP_MODELS[model]:
            raise InputError(f"line {no}: {model} needs {COLMAP_MODELS[model]} params, got {len(params)}", cam_path)
        cameras[cid] = colmap_camera_to_camera(model, w, h, params)
        models[cid] = model
    if not cameras:
        raise InputError("no camera", cam_path)

    images: dict[str, dict] = {}
    lines = _data_lines(img_path)
    k = 0
    while k < len(lines):
        no, ln = lines[k]
        k += 1
        if not ln:
            continue
        tok = ln.split(maxsplit=9)
        try:
            iid, cid = int(tok[0]), int(tok[8])
            qt = np.array([float(v) for v in tok[1:8]])
            name = tok[9].strip()
        except (ValueError, IndexError):
            raise InputError(f"line {no}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME'", img_path) from None
        if cid not in cameras:
            raise InputError(f"line {no}: camera {cid} is not in cameras.txt", img_path)
        qn = np.linalg.norm(qt[:4])
        if not (np.all(np.isfinite(qt)) and qn > 0.5):
            raise InputError(f"line {no}: invalid pose", img_path)
        # The POINTS2D line follows (possibly empty). A writer that left it out would make the
        # next line an image line: POINTS2D lines hold only numbers, image lines end in a name.
        if k < len(lines):
            nxt = lines[k][1].split()
            if not nxt or (len(nxt) % 3 == 0 and all(_is_number(v) for v in nxt)):
                k += 1
        R_cw = quat_wxyz_to_matrix(qt[:4] / qn)
        images[name] = {"image_id": iid, "camera_id": cid, "R_wc": R_cw.T, "center": -R_cw.T @ qt[4:7]}

    xyz, rgb = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    if pts_path.is_file():
        rows = []
        for no, ln in _data_lines(pts_path):
            if not ln:
                continue
            tok = ln.split()
            try:
                rows.append([float(v) for v in tok[1:7]])
            except ValueError:
                raise InputError(f"line {no}: expected 'POINT3D_ID X Y Z R G B ERROR TRACK...'", pts_path) from None
            if len(rows[-1]) != 6:
                raise InputError(f"line {no}: expected 'POINT3D_ID X Y Z R G B ERROR TRACK...'", pts_path)
        if rows:
            arr = np.array(rows)
            xyz, rgb = arr[:, :3], np.clip(arr[:, 3:], 0, 255).astype(np.uint8)
    first = min(cameras)
    return {"camera": cameras[first], "cameras": cameras, "colmap_models": models, "images": images,
            "points3D": xyz, "points3D_rgb": rgb}


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def match_frame_names(model_names, frame_names) -> np.ndarray:
    """Returns (F,) int: for each capture frame, the index into ``model_names`` of its image, or -1.

    Matches the exact name first, then the base name (``frames/000001.png`` ~
    ``000001.png``), then the stem (``000001.jpg`` ~ ``000001.png``); each model
    image is used once.
    """
    model_names = list(model_names)
    out = np.full(len(frame_names), -1, dtype=np.int64)
    used: set[int] = set()
    keys = [lambda s: s, lambda s: s.replace("\\", "/").rsplit("/", 1)[-1],
            lambda s: s.replace("\\", "/").rsplit("/", 1)[-1].rsplit(".", 1)[0]]
    for key in keys:
        table: dict[str, int] = {}
        for j, nm in enumerate(model_names):
            if j not in used:
                table.setdefault(key(str(nm)), j)
        for i, fn in enumerate(frame_names):
            if out[i] < 0:
                j = table.get(key(str(fn)))
                if j is not None and j not in used:
                    out[i] = j
                    used.add(j)
    return out


def poses_for_frames(model: dict, frame_names) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (R_wc (F, 3, 3), centers (F, 3), registered (F,)) of a read model, in capture frame order.

    Frames with no image in the model are unregistered (NaN pose).
    """
    names = list(model["images"])
    match = match_frame_names(names, frame_names)
    F = len(frame_names)
    R = np.full((F, 3, 3), np.nan)
    c = np.full((F, 3), np.nan)
    reg = match >= 0
    for i in np.flatnonzero(reg):
        im = model["images"][names[match[i]]]
        R[i], c[i] = im["R_wc"], im["center"]
    return R, c, reg


# --------------------------------------------------------------------------------------
# lines.ply
# --------------------------------------------------------------------------------------


def write_lines_ply(path: str | Path, endpoints: np.ndarray, labels: np.ndarray | None = None,
                    colors: np.ndarray | None = None) -> Path:
    """Returns ``path`` after writing segments as an ASCII PLY: vertices + edges.

    Edge ``i`` joins vertices ``2i`` and ``2i + 1`` and carries ``red green blue``
    (uchar, RGB) and ``label`` (char: Manhattan axis 0/1/2, -1 none); vertices carry
    double ``x y z`` and their edge's colour (for viewers that colour points only).
    Opens as a LineSet in Open3D and in MeshLab.
    """
    path = Path(path)
    E = np.asarray(endpoints, dtype=np.float64).reshape(-1, 6)
    T = len(E)
    lab = np.full(T, UNLABELLED, dtype=np.int64) if labels is None else np.asarray(labels, dtype=np.int64).reshape(T)
    if colors is None:
        col = AXIS_COLORS[np.where((lab >= 0) & (lab <= 2), lab, 3)]
    else:
        col = np.asarray(colors).reshape(T, 3).astype(np.uint8)
    V = E.reshape(2 * T, 3)
    vcol = np.repeat(col, 2, axis=0)
    header = [
        "ply", "format ascii 1.0",
        "comment panosfm 3D line segments: edge i joins vertices 2i and 2i+1",
        "comment label: Manhattan axis of the edge (0 x, 1 y, 2 z; -1 none)",
        f"element vertex {2 * T}", "property double x", "property double y", "property double z",
        "property uchar red", "property uchar green", "property uchar blue",
        f"element edge {T}", "property int vertex1", "property int vertex2",
        "property uchar red", "property uchar green", "property uchar blue", "property char label",
        "end_header",
    ]
    with open(path, "w") as f:
        f.write("\n".join(header) + "\n")
        for k in range(2 * T):
            f.write(f"{_fmt(V[k, 0])} {_fmt(V[k, 1])} {_fmt(V[k, 2])} {vcol[k, 0]} {vcol[k, 1]} {vcol[k, 2]}\n")
        for k in range(T):
            f.write(f"{2 * k} {2 * k + 1} {col[k, 0]} {col[k, 1]} {col[k, 2]} {lab[k]}\n")
    return path


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _read_ply(path: Path) -> dict[str, dict[str, np.ndarray]]:
    """Returns {element: {property: array}} of an ASCII or binary PLY (list properties skipped)."""
    try:
        data = path.read_bytes()
    except OSError as e:
        raise InputError(f"cannot read ({e.strerror})", path) from None
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file (no 'ply' magic or no end_header)", path)
    body_start = data.index(b"\n", end) + 1
    fmt, elements = None, []  # elements: [name, count, [(prop, type, list_types or None)]]
    for raw in data[:end].decode("ascii", errors="replace").splitlines():
        tok = raw.split()
        if not tok or tok[0] in ("comment", "obj_info", "ply"):
            continue
        try:
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                elements.append([tok[1], int(tok[2]), []])
            elif tok[0] == "property" and tok[1] == "list":
                elements[-1][2].append((tok[4], _PLY_TYPES[tok[3]], _PLY_TYPES[tok[2]]))
            elif tok[0] == "property":
                elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]], None))
        except (IndexError, KeyError, ValueError):
            raise InputError(f"bad PLY header line {raw.strip()!r}", path) from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"unknown PLY format {fmt!r}", path)
    out: dict[str, dict[str, np.ndarray]] = {}
    try:
        if fmt == "ascii":
            tokens = data[body_start:].split()
            pos = 0
            for name, count, props in elements:
                if all(p[2] is None for p in props):
                    n = len(props)
                    arr = np.array(tokens[pos:pos + n * count], dtype=np.float64).reshape(count, n)
                    pos += n * count
                    out[name] = {p[0]: arr[:, j].astype(p[1]) for j, p in enumerate(props)}
                else:  # rows with lists (faces of a mesh): walk them, keep the scalars
                    cols: dict[str, list] = {p[0]: [] for p in props if p[2] is None}
                    for _ in range(count):
                        for p in props:
                            if p[2] is None:
                                cols[p[0]].append(float(tokens[pos]))
                                pos += 1
                            else:
                                pos += 1 + int(tokens[pos])
                    out[name] = {p[0]: np.array(cols[p[0]]).astype(p[1]) for p in props if p[2] is None}
        else:
            bo = "<" if fmt == "binary_little_endian" else ">"
            pos = body_start
            for name, count, props in elements:
                if all(p[2] is None for p in props):
                    dt = np.dtype([(p[0], bo + p[1]) for p in props])
                    arr = np.frombuffer(data, dtype=dt, count=count, offset=pos)
                    pos += dt.itemsize * count
                    out[name] = {p[0]: arr[p[0]].astype(p[1]) for p in props}
                else:
                    cols = {p[0]: [] for p in props if p[2] is None}
                    for _ in range(count):
                        for p in props:
                            if p[2] is None:
                                v = np.frombuffer(data, dtype=bo + p[1], count=1, offset=pos)[0]
                                cols[p[0]].append(v)
                                pos += np.dtype(p[1]).itemsize
                            else:
                                m = int(np.frombuffer(data, dtype=bo + p[2], count=1, offset=pos)[0])
                                pos += np.dtype(p[2]).itemsize + m * np.dtype(p[1]).itemsize
                    out[name] = {p[0]: np.array(cols[p[0]]).astype(p[1]) for p in props if p[2] is None}
    except (ValueError, IndexError):
        raise InputError("PLY body is shorter than its header says or malformed", path) from None
    return out


def read_lines_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (endpoints (T, 6) float64, labels (T,) int8, colors (T, 3) uint8 RGB) from a line PLY.

    Reads ASCII and binary PLYs with ``element vertex`` (x y z) and ``element edge``
    (vertex1 vertex2, optional red green blue and label), whoever wrote them (Open3D
    LineSets included). Missing labels are -1; missing edge colours come from the
    vertices' colours, else grey.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("missing", path)
    el = _read_ply(path)
    v, e = el.get("vertex"), el.get("edge")
    if v is None or not all(k in v for k in "xyz"):
        raise InputError("no 'element vertex' with x y z", path)
    if e is None or "vertex1" not in e or "vertex2" not in e:
        raise InputError("no 'element edge' with vertex1 vertex2", path)
    V = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    i1, i2 = e["vertex1"].astype(np.int64), e["vertex2"].astype(np.int64)
    if len(i1) and (min(i1.min(), i2.min()) < 0 or max(i1.max(), i2.max()) >= len(V)):
        raise InputError("an edge refers to a vertex that does not exist", path)
    endpoints = np.concatenate([V[i1], V[i2]], axis=1)
    labels = e["label"].astype(np.int8) if "label" in e else np.full(len(i1), UNLABELLED, dtype=np.int8)
    if all(k in e for k in ("red", "green", "blue")):
        colors = np.stack([e["red"], e["green"], e["blue"]], axis=1).astype(np.uint8)
    elif all(k in v for k in ("red", "green", "blue")):
        colors = np.stack([v["red"], v["green"], v["blue"]], axis=1)[i1].astype(np.uint8)
    else:
        colors = np.full((len(i1), 3), 160, dtype=np.uint8)
    return endpoints, labels, colors


# --------------------------------------------------------------------------------------
# summary.json
# --------------------------------------------------------------------------------------


def to_jsonable(obj: Any) -> Any:
    """Returns ``obj`` with numpy scalars/arrays, paths, dataclasses and tuples made JSON-safe.

    Non-finite floats become ``null`` (strict JSON has no NaN).
    """
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(dataclasses.asdict(obj))
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        x = float(obj)
        return x if math.isfinite(x) else None
    if isinstance(obj, Path):
        return str(obj)
    if obj is None or isinstance(obj, str):
        return obj
    return str(obj)


def write_summary(path: str | Path, summary: dict) -> Path:
    """Returns ``path`` after writing ``summary`` as indented JSON (numpy values converted)."""
    path = Path(path)
    with open(path, "w") as f:
        json.dump(to_jsonable(summary), f, indent=2, allow_nan=False)
        f.write("\n")
    return path


# --------------------------------------------------------------------------------------
# Atomic output directory
# --------------------------------------------------------------------------------------


def _backup_path(out_dir: Path) -> Path:
    return out_dir.parent / f".{out_dir.name}.backup"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def recover_output_dir(out_dir: str | Path, keep: tuple[str, ...] = ()) -> None:
    """Returns nothing; repairs what an interrupted :func:`atomic_output_dir` left next to ``out_dir``.

    A backup with ``out_dir`` missing is the previous complete result: renamed back.
    A backup with ``out_dir`` present is stale: removed. Temporary directories of
    processes that no longer run are incomplete results: removed, after their
    ``keep`` entries (the stage cache, moved in just before the swap) are moved
    back into ``out_dir``.
    """
    out_dir = Path(out_dir)
    backup = _backup_path(out_dir)
    if backup.is_dir():
        if out_dir.exists():
            log.info("removing stale backup %s", backup)
            shutil.rmtree(backup, ignore_errors=True)
        else:
            log.warning("restoring previous result %s from interrupted run", out_dir)
            os.rename(backup, out_dir)
    if out_dir.parent.is_dir():
        for tmp in out_dir.parent.glob(f".{out_dir.name}.tmp-*"):
            try:
                pid = int(tmp.name.rsplit(".tmp-", 1)[1].split("-")[0])
            except (IndexError, ValueError):
                continue
            if tmp.is_dir() and pid != os.getpid() and not _pid_alive(pid):
                for name in keep:
                    if (tmp / name).exists() and not (out_dir / name).exists():
                        out_dir.mkdir(exist_ok=True)
                        os.rename(tmp / name, out_dir / name)
                shutil.rmtree(tmp, ignore_errors=True)


def _looks_like_result(d: Path, keep: tuple[str, ...] = ()) -> bool:
    """Returns True when ``d`` is empty or holds a reconstruction (safe to replace)."""
    try:
        entries = {p.name for p in d.iterdir()} - set(keep)
    except OSError:
        return False
    return not entries or bool(entries & {"summary.json", "sparse", "lines.ply"})


def _fsync_dir(d: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(d, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)



def ensure_writable_dir(d: Path, name: str) -> None:
    """Creates directory ``d`` (and its parents) if needed; ``InputError`` naming it ``name`` when that fails or
    it is not writable."""
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"cannot create the {name} ({e.strerror})", d) from None
    if not os.access(d, os.W_OK | os.X_OK):
        raise InputError(f"{name} is not writable", d)

def check_output_dir(out_dir: str | Path, keep: tuple[str, ...] = ()) -> Path:
    """Returns the absolute ``out_dir`` after checking a result can be written there.

    ``InputError`` when ``out_dir`` is a file, is a non-empty directory that is not
    a reconstruction (never replaced; entries named in ``keep``, such as the stage
    cache, count as part of a reconstruction), or its parent cannot be created or
    written. Leftovers of an interrupted swap are recovered first.
    """
    out_dir = Path(out_dir).expanduser().absolute()
    parent = out_dir.parent
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError("output path exists and is not a directory", out_dir)
    ensure_writable_dir(parent, "output's parent directory")
    recover_output_dir(out_dir, keep)
    if out_dir.is_dir() and not _looks_like_result(out_dir, keep):
        raise InputError("output directory exists, is not empty and is not a panosfm reconstruction; refusing to replace it", out_dir)
    return out_dir


@contextlib.contextmanager
def atomic_output_dir(out_dir: str | Path, keep: tuple[str, ...] = ()) -> Iterator[Path]:
    """Yields a fresh temporary directory next to ``out_dir`` that replaces it on success.

    On normal exit: entries of the old ``out_dir`` named in ``keep`` (e.g. the
    stage cache) are moved into the new result, old result -> ``.<name>.backup``,
    temporary -> ``out_dir``, backup removed (see the module docstring for the
    recovery rule). On any exception (KeyboardInterrupt included) the temporary
    directory is removed and ``out_dir`` is untouched. Errors: see
    :func:`check_output_dir`.
    """
    out_dir = check_output_dir(out_dir, keep)
    parent = out_dir.parent
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-{os.getpid()}-", dir=parent))
    except OSError as e:
        raise InputError(f"cannot create a temporary directory ({e.strerror})", parent) from None
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    backup = _backup_path(out_dir)
    try:
        for name in keep:
            if (out_dir / name).exists() and not (tmp / name).exists():
                os.rename(out_dir / name, tmp / name)
        if out_dir.exists():
            os.rename(out_dir, backup)
        try:
            os.rename(tmp, out_dir)
        except BaseException:
            if backup.exists() and not out_dir.exists():
                os.rename(backup, out_dir)
            raise
        _fsync_dir(parent)
        shutil.rmtree(backup, ignore_errors=True)
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise InputError(f"cannot move the new result into place ({e.strerror})", out_dir) from None


# --------------------------------------------------------------------------------------
# The whole reconstruction
# --------------------------------------------------------------------------------------


def package_versions() -> dict[str, str | None]:
    """Returns the installed versions of panosfm and the libraries whose behaviour shapes a result."""
    from importlib import metadata

    out: dict[str, str | None] = {}
    for dist in ("panosfm", "numpy", "scipy", "opencv-python-headless", "gtsam", "onnxruntime", "rerun-sdk"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = None
    return out


def export_reconstruction(out_dir: str | Path, solution: Solution, frame_names, line_colors: np.ndarray | None = None,
                          summary: dict | None = None) -> dict:
    """Returns the summary written after writing ``sparse/``, ``lines.ply`` and ``summary.json`` into ``out_dir``.

    Only registered frames go to images.txt and only valid lines to lines.ply (edge
    label = Manhattan axis; ``line_colors`` (T, 3) uint8 RGB per track, default by
    axis); line endpoints also go to points3D.txt. ``summary`` (the caller's: config,
    seconds per stage, relations, versions) is completed with counts, the scale note
    and ``solution.residuals`` without overwriting the caller's keys. Call it inside
    :func:`atomic_output_dir`.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    lines = solution.lines
    valid = np.asarray(lines.valid, dtype=bool) & np.all(np.isfinite(lines.endpoints), axis=1)
    endpoints = lines.endpoints[valid]
    labels = np.asarray(lines.axis)[valid]
    if line_colors is None:
        colors = AXIS_COLORS[np.where((labels >= 0) & (labels <= 2), labels, 3)]
    else:
        colors = np.asarray(line_colors).reshape(-1, 3)[valid].astype(np.uint8)

    pts = np.concatenate([endpoints.reshape(-1, 3), np.repeat(colors, 2, axis=0).astype(np.float64)], axis=1)
    write_colmap_text(out_dir / "sparse", solution.camera, frame_names, solution.R_wc, solution.centers,
                      solution.registered, points3D=pts)
    write_lines_ply(out_dir / "lines.ply", endpoints, labels, colors)

    summary = dict(summary or {})
    n_reg = int(np.sum(solution.registered))
    summary.setdefault("frames", len(frame_names))
    summary.setdefault("registered_frames", n_reg)
    summary.setdefault("unregistered_frames", len(frame_names) - n_reg)
    summary.setdefault("lines", int(valid.sum()))
    summary.setdefault("lines_by_axis", {AXIS_NAMES[a]: int(np.sum(labels == a)) for a in range(3)})
    summary.setdefault("scale", "metric" if solution.metric else "arbitrary")
    summary.setdefault("camera", {"model": solution.camera.model, "width": solution.camera.width,
                                  "height": solution.camera.height, "params": solution.camera.params})
    summary.setdefault("residuals", solution.residuals)
    summary.setdefault("versions", package_versions())
    write_summary(out_dir / "summary.json", summary)
    return summary
