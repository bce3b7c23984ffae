"""The per-stage cache: each stage's output saved as ``.npz`` under ``<out>/cache/``.

A stage's file name carries a hash of everything it depends on (the capture's
identity, its part of the config, and the hashes of the stages before it), so
``--resume`` picks up every stage whose inputs did not change and a changed
setting reruns only the stages it affects. Files are written to a temporary
name and renamed, so a killed run never leaves a half-written cache entry.

The code is part of the key too: each stage's key hashes the source files of
the modules it runs (:data:`STAGE_SOURCES`, :func:`stage_code_hash`), so
``--resume`` after an edit (or an upgrade) reruns the edited stage and every
stage after it instead of returning what the old code computed.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib.util
import json
import os
import tempfile
import typing
from pathlib import Path
from typing import Any

import numpy as np

from . import data as _data

_SEP = "__"

# modules (a package: all its files) whose source is part of each stage's key; a stage's key chains the
# keys before it, so the modules of earlier stages count for the later ones too. tests/test_cache.py
# checks that every module a stage imports (of these two packages) is listed for it or an earlier stage,
# or in KEYED_BY_VALUE: the config, whose values (each stage's section) are in the keys themselves, so that
# a new option or a changed default elsewhere does not re-run detection for every capture. A stage that uses
# code or constants of config.py beyond its section's values lists it by source (the BA: SPIN_STYLES)
KEYED_BY_VALUE: tuple[str, ...] = ("panosfm_graph.config",)
STAGE_SOURCES: dict[str, tuple[str, ...]] = {
    "detect": ("panosfm_graph.__init__", "panosfm_graph.pipeline", "panosfm_graph.capture",
               "panosfm_graph.data", "panosfm_graph.cache", "panosfm_graph.errors", "panosfm_graph.geometry", "panosfm_graph.parallel",
               "panosfm_graph.progress", "panosfm_graph.thumbnails", "panosfm_graph.lines.detect"),
    "preprocess": ("panosfm_graph.lines", "panosfm_graph.lines.manhattan", "panosfm_graph.lines.rotations"),
    "track": ("panosfm_graph.lines.tracking", "panosfm_graph.lines.fragments"),
    "normals": ("panosfm_graph.normals",),
    "relations": ("panosfm_graph.relations",),
    "linear": ("panosfm_graph.linear", "factors"),
    "points": ("panosfm_graph.points", "panosfm_graph.graph", "factors"),  # points.stitch fits with graph's LM
    "bundle_adjust": ("panosfm_graph.graph", "factors", "panosfm_graph.config"),  # graph uses config.SPIN_STYLES
}


def module_files(name: str) -> list[Path]:
    """Returns the source files of module ``name``: one file, or every ``.py`` file of a package's folder.

    ``"pkg.__init__"`` names a package's ``__init__.py`` alone.
    """
    init = name.endswith(".__init__")
    spec = importlib.util.find_spec(name[: -len(".__init__")] if init else name)
    if spec is None or spec.origin is None:
        raise ModuleNotFoundError(name)
    path = Path(spec.origin)
    return sorted(path.parent.glob("*.py")) if path.name == "__init__.py" and not init else [path]


@functools.lru_cache(maxsize=None)
def stage_code_hash(stage: str) -> str:
    """Returns a short hex digest of the source of the modules stage ``stage`` runs (:data:`STAGE_SOURCES`)."""
    h = hashlib.sha1()
    for name in STAGE_SOURCES[stage]:
        for path in module_files(name):
            h.update(path.name.encode())
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def stable_hash(*parts: Any) -> str:
    """Returns a short hex digest of JSON-serialisable ``parts`` (dataclasses and arrays allowed)."""

    def default(o: Any) -> Any:
        if dataclasses.is_dataclass(o):
            return dataclasses.asdict(o)
        if isinstance(o, np.ndarray):
            return hashlib.sha1(np.ascontiguousarray(o).tobytes()).hexdigest()
        if isinstance(o, (np.integer, np.floating)):
            return o.item()
        if isinstance(o, Path):
            return str(o)
        raise TypeError(f"cannot hash {type(o)}")

    text = json.dumps(parts, sort_keys=True, default=default)
    return hashlib.sha1(text.encode()).hexdigest()[:16]


def _flatten(obj: Any, prefix: str, out: dict[str, np.ndarray]) -> None:
    if dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            if f.name.startswith("_"):
                continue
            _flatten(getattr(obj, f.name), f"{prefix}{f.name}{_SEP}", out)
        return
    key = prefix[: -len(_SEP)]
    if obj is None:
        out[key + "@none"] = np.zeros(0)
    elif isinstance(obj, (dict, list, tuple, str, bool, int, float)) and not isinstance(obj, np.ndarray):
        out[key + "@json"] = np.frombuffer(json.dumps(obj, default=_json_default).encode(), dtype=np.uint8)
    else:
        out[key] = np.asarray(obj)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.integer, np.floating, np.bool_)):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def _unflatten(cls: type, arrays: dict[str, np.ndarray], prefix: str) -> Any:
    hints = typing.get_type_hints(cls, vars(_data))
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name.startswith("_"):
            continue
        key = f"{prefix}{f.name}"
        hint = hints.get(f.name)
        sub = _dataclass_in(hint)
        if key + "@none" in arrays:
            kwargs[f.name] = None
        elif key + "@json" in arrays:
            kwargs[f.name] = json.loads(arrays[key + "@json"].tobytes().decode())
        elif sub is not None and any(k.startswith(key + _SEP) for k in arrays):
            kwargs[f.name] = _unflatten(sub, arrays, key + _SEP)
        elif key in arrays:
            a = arrays[key]
            kwargs[f.name] = a.item() if a.ndim == 0 and hint in (float, int, bool, str) else a
    return cls(**kwargs)


def _dataclass_in(hint: Any) -> type | None:
    if dataclasses.is_dataclass(hint):
        return hint
    for arg in typing.get_args(hint):
        if dataclasses.is_dataclass(arg):
            return arg
    return None


def save_stage(path: Path, obj: Any) -> None:
    """Writes a stage's dataclass (nested dataclasses of arrays, JSON-able fields) atomically."""
    arrays: dict[str, np.ndarray] = {}
    _flatten(obj, "", arrays)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name, suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_stage(path: Path, cls: type) -> Any:
    """Returns the dataclass ``cls`` saved by :func:`save_stage` at ``path``."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    return _unflatten(cls, arrays, "")


class StageCache:
    """Reads and writes stage outputs under ``root`` keyed by ``<stage>-<hash>.npz``."""

    def __init__(self, root: Path, enabled: bool = True):
        self.root = Path(root)
        self.enabled = enabled

    def path(self, stage: str, key: str) -> Path:
        return self.root / f"{stage}-{key}.npz"

    def load(self, stage: str, key: str, cls: type) -> Any | None:
        p = self.path(stage, key)
        if not (self.enabled and p.exists()):
            return None
        try:
            return load_stage(p, cls)
        except Exception:  # a corrupt cache entry is recomputed, never trusted
            p.unlink(missing_ok=True)
            return None

    def save(self, stage: str, key: str, obj: Any) -> None:
        for old in self.root.glob(f"{stage}-*.npz"):
            old.unlink(missing_ok=True)
        save_stage(self.path(stage, key), obj)
