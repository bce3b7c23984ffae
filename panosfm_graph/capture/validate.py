"""The one-line :class:`~panosfm_graph.errors.InputError` checks the readers share (``capture-format.md``).

CSV files with a fixed header and numeric columns (the error names the file
and the first bad line), JSON numbers, the capture directory, the
``capture`` config section and frame indices.
"""
from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from ..config import CaptureConfig
from ..errors import InputError


def _read_csv(path: Path, header: tuple[str, ...]) -> list[list[str]]:
    """Returns the rows (lists of stripped strings) of a CSV whose first columns must be ``header``."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            rows = [[c.strip() for c in r] for r in csv.reader(f) if r and any(c.strip() for c in r)]
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise InputError(f"cannot be read ({_first_line(e)})", path) from None
    if not rows:
        raise InputError(f"is empty (expected the header {','.join(header)})", path)
    got = tuple(c.lower() for c in rows[0][: len(header)])
    if got != header:
        raise InputError(f"bad header {','.join(rows[0])!r} (expected {','.join(header)})", path)
    return rows[1:]


def _numbers(path: Path, rows: list[list[str]], cols: slice, first_line: int = 2) -> np.ndarray:
    """Returns rows[:, cols] as float64, raising InputError naming the first bad line."""
    n_cols = len(range(*cols.indices(10_000)))
    out = np.empty((len(rows), n_cols))
    for k, r in enumerate(rows):
        vals = r[cols]
        if len(vals) != n_cols:
            raise InputError(f"line {k + first_line}: expected {n_cols} values, got {len(vals)}", path)
        try:
            out[k] = [float(v) for v in vals]
        except ValueError:
            raise InputError(f"line {k + first_line}: not a number in {','.join(r)!r}", path) from None
    return out


def _check_config(config: CaptureConfig) -> None:
    if isinstance(config.every_k, bool) or not isinstance(config.every_k, int) or config.every_k < 1:
        raise InputError(f"capture.every_k must be an integer >= 1, got {config.every_k!r}")
    if config.max_frames is not None and (not isinstance(config.max_frames, int) or config.max_frames < 1):
        raise InputError(f"capture.max_frames must be an integer >= 1, got {config.max_frames!r}")
    if not (_is_number(config.scale) and 0 < config.scale <= 1):
        raise InputError(f"capture.scale must be in (0, 1], got {config.scale!r}")


def _root(path: str | Path) -> Path:
    root = Path(path)
    if not root.exists():
        raise InputError("capture directory does not exist", root)
    if not root.is_dir():
        raise InputError("is not a capture directory", root)
    return root


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)


def _first_line(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def _check_index(i: int, n: int) -> int:
    i = int(i)
    if i < 0:
        i += n
    if not 0 <= i < n:
        raise IndexError(f"frame {i} out of range (capture has {n} frames)")
    return i
