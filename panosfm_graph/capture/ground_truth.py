"""``ground_truth/`` (benchmark captures): poses.csv, lines.csv, scene.json, normals/ and depth/ maps.

Poses are matched to the taken frames by file stem (missing ones NaN); the
maps are read on demand at working resolution (``capture-format.md``).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..data import GroundTruth
from ..errors import InputError
from ..geometry import quat_wxyz_to_matrix
from .camera import _Warp
from .imu import QUAT_NORM_TOL
from .validate import _check_index, _first_line, _numbers, _read_csv

log = logging.getLogger("panosfm.capture")

AXIS_LABELS = {"x": 0, "y": 1, "z": 2, "0": 0, "1": 1, "2": 2, "-1": -1}


class _MapLoader:
    """Callable: frame index -> ground-truth map at working resolution (nearest-neighbour; normals renormalised)."""

    def __init__(self, folder: Path, stems: tuple[str, ...], warp: _Warp, normals: bool):
        self.folder = folder
        self.stems = stems
        self.warp = warp
        self.normals = normals

    def __call__(self, i: int) -> np.ndarray | None:
        i = _check_index(i, len(self.stems))
        path = self.folder / f"{self.stems[i]}.npy"
        if not path.is_file():
            return None
        try:
            m = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise InputError(f"cannot be read as a .npy array ({_first_line(e)})", path) from None
        want = 3 if self.normals else 2
        if m.ndim != want or (self.normals and m.shape[2] != 3):
            raise InputError(f"has shape {m.shape}, expected {'H x W x 3' if self.normals else 'H x W'}", path)
        m = self.warp(np.ascontiguousarray(m, dtype=np.float32), nearest=True)
        if self.normals:
            n = np.linalg.norm(m, axis=2, keepdims=True)
            m = np.where(n > 1e-6, m / np.maximum(n, 1e-6), 0.0).astype(np.float32)
        return m


def _no_map(i: int) -> None:
    return None


def _gt_key(name: str) -> str:
    name = Path(name.replace("\\", "/")).name
    if "#" in name:
        name = name.rsplit("#", 1)[1]
    return Path(name).stem


def _read_ground_truth(gt: Path, stems: tuple[str, ...], warp: _Warp) -> GroundTruth:
    """Returns the ground truth of the taken frames (poses matched by file stem; missing ones NaN)."""
    F = len(stems)
    R = np.full((F, 3, 3), np.nan)
    C = np.full((F, 3), np.nan)
    poses = gt / "poses.csv"
    if poses.is_file():
        rows = _read_csv(poses, ("file", "qw", "qx", "qy", "qz", "tx", "ty", "tz"))
        vals = _numbers(poses, rows, slice(1, 8))
        if not np.all(np.isfinite(vals)):
            raise InputError("NaN or infinite values", poses)
        norm = np.linalg.norm(vals[:, :4], axis=1)
        if np.any(np.abs(norm - 1.0) > QUAT_NORM_TOL):
            k = int(np.argmax(np.abs(norm - 1.0) > QUAT_NORM_TOL))
            raise InputError(f"line {k + 2}: quaternion norm {norm[k]:.6f} is not 1", poses)
        key_row = {_gt_key(r[0]): k for k, r in enumerate(rows)}
        num_row = {int(k): v for k, v in key_row.items() if k.isdigit()}
        idx = np.array([key_row.get(s, num_row.get(int(s), -1) if s.isdigit() else -1) for s in stems], dtype=np.int64)
        hit = idx >= 0
        if (~hit).any():
            log.warning("%s: no pose for %d of %d frames", poses, int((~hit).sum()), F)
        R[hit] = quat_wxyz_to_matrix(vals[idx[hit], :4] / norm[idx[hit], None])
        C[hit] = vals[idx[hit], 4:]
    lines = np.zeros((0, 6))
    labels = np.zeros(0, dtype=np.int8)
    lines_csv = gt / "lines.csv"
    if lines_csv.is_file():
        rows = _read_csv(lines_csv, ("x1", "y1", "z1", "x2", "y2", "z2", "label"))
        lines = _numbers(lines_csv, rows, slice(0, 6)).reshape(-1, 6)
        labels = np.array([AXIS_LABELS.get(r[6].lower(), -1) if len(r) > 6 else -1 for r in rows], dtype=np.int8)
    scene: dict = {}
    scene_json = gt / "scene.json"
    if scene_json.is_file():
        try:
            scene = json.loads(scene_json.read_text(encoding="utf-8-sig"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise InputError(f"not valid JSON ({_first_line(e)})", scene_json) from None
    has_n = (gt / "normals").is_dir() and any((gt / "normals" / f"{s}.npy").is_file() for s in stems)
    has_d = (gt / "depth").is_dir() and any((gt / "depth" / f"{s}.npy").is_file() for s in stems)
    return GroundTruth(
        R_wc=R, centers=C, lines=lines, line_labels=labels, scene=scene,
        normals=_MapLoader(gt / "normals", stems, warp, True) if has_n else _no_map,
        depth=_MapLoader(gt / "depth", stems, warp, False) if has_d else _no_map,
        has_normals=has_n, has_depth=has_d,
    )
