"""Raw phone sensor logs -> :class:`RawSensors`: gyroscope (rad/s) and the "up" specific force (m/s²).

Three layouts are read (``docs/import.md``):

* ``generic``: a folder with ``gyro.csv`` (``timestamp_s,x,y,z``, rad/s) and
  ``accel.csv`` (``timestamp_s,x,y,z``, m/s², gravity included: at rest it
  reads about +9.81 along the axis pointing up), in any right-handed frame
  fixed to the phone (the import finds the camera's axes itself);
* ``sensor-logger``: an export of the Sensor Logger app (folder or ``.zip``):
  ``Gyroscope.csv`` and ``Gravity.csv`` / ``TotalAcceleration.csv`` /
  ``Accelerometer.csv`` with columns ``time`` (ns since the epoch) and ``x,y,z``;
  iOS exports (``metadata.csv``) have their gravity's sign flipped back;
* ``phyphox``: a phyphox CSV export (``Gyroscope.csv`` / ``Accelerometer.csv``
  with ``Time (s)`` and ``... x (rad/s)`` / ``... x (m/s^2)`` columns).

Every problem (missing file, bad header, NaN, unsorted or repeated timestamps,
gaps, a rate under :data:`MIN_RATE_HZ`, values in the wrong unit) is an
:class:`~panosfm_graph.errors.InputError`: one line naming the file.
"""
from __future__ import annotations

import csv
import io
import logging
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError

log = logging.getLogger("panosfm.phone")

G = 9.80665  # m/s²
MIN_RATE_HZ = 50.0  # gyroscope rate below this is rejected (the spin's wobble is not resolved)
MAX_GAP_S = 0.1  # a longer gap between two gyroscope samples is rejected
MAX_GYRO_RAD_S = 10.0  # the 99th percentile of |omega| above this: the log is in deg/s, not rad/s
FORMATS = ("auto", "generic", "sensor-logger", "phyphox")


@dataclass(frozen=True)
class RawSensors:
    """The phone's raw motion samples on the sensor clock (seconds), in the phone's own axes.

    ``up`` is the specific force (accelerometer with gravity, or the OS's
    gravity vector), which points up at rest. ``epoch_s`` is the sensor
    clock's 0 in UNIX seconds when the log says so (else None).
    """

    t_gyro: np.ndarray  # (N,)
    gyro: np.ndarray  # (N, 3) rad/s
    t_up: np.ndarray  # (M,)
    up: np.ndarray  # (M, 3) m/s²
    source: str  # e.g. "generic: gyro.csv + accel.csv"
    epoch_s: float | None = None

    @property
    def span(self) -> tuple[float, float]:
        """Returns the time span both streams cover."""
        return max(self.t_gyro[0], self.t_up[0]), min(self.t_gyro[-1], self.t_up[-1])

    @property
    def gyro_rate_hz(self) -> float:
        return float((len(self.t_gyro) - 1) / (self.t_gyro[-1] - self.t_gyro[0]))


class _Files:
    """The files of a sensor log folder or ``.zip``, by base name (case-insensitive)."""

    def __init__(self, path: Path):
        self.path = path
        if path.is_file() and zipfile.is_zipfile(path):
            self._zip = zipfile.ZipFile(path)
            names = [n for n in self._zip.namelist() if not n.endswith("/")]
        elif path.is_dir():
            self._zip = None
            names = [str(p.relative_to(path)) for p in sorted(path.rglob("*")) if p.is_file()]
        else:
            raise InputError("not a sensor log folder or .zip", path)
        self.by_name = {}
        for n in names:
            self.by_name.setdefault(Path(n).name.lower(), n)

    def has(self, name: str) -> bool:
        return name.lower() in self.by_name

    def where(self, name: str) -> Path:
        if not self.has(name):
            raise InputError(f"no {name} in this sensor log", self.path)
        return self.path / self.by_name[name.lower()]

    def text(self, name: str) -> str:
        where = self.where(name)
        try:
            raw = self._zip.read(self.by_name[name.lower()]) if self._zip else where.read_bytes()
            return raw.decode("utf-8-sig")
        except (OSError, UnicodeDecodeError, zipfile.BadZipFile) as e:
            raise InputError(f"cannot be read ({e})", where) from None


def _table(files: _Files, name: str) -> tuple[Path, list[str], np.ndarray]:
    """Returns (path, lower-case header, float rows) of one CSV; InputError naming the first bad line."""
    where = files.where(name)
    try:
        rows = [r for r in csv.reader(io.StringIO(files.text(name))) if r and any(c.strip() for c in r)]
    except csv.Error as e:
        raise InputError(f"cannot be parsed ({e})", where) from None
    if len(rows) < 3:
        raise InputError(f"has {max(len(rows) - 1, 0)} samples", where)
    header = [c.strip().strip('"').lower() for c in rows[0]]
    out = np.full((len(rows) - 1, len(header)), np.nan)
    for k, r in enumerate(rows[1:]):
        if len(r) != len(header):
            raise InputError(f"line {k + 2}: expected {len(header)} values, got {len(r)}", where)
        for j, c in enumerate(r):
            try:
                out[k, j] = float(c.strip().strip('"'))
            except ValueError:  # a text column, or a bad number: _columns names the line if it is one it needs
                pass
    return where, header, out


def _columns(where: Path, header: list[str], data: np.ndarray, time_names: tuple[str, ...],
             axis_prefix: str = "") -> tuple[np.ndarray, np.ndarray]:
    """Returns (t (N,), xyz (N, 3)) of a table with a time column named one of ``time_names`` and x, y, z columns."""
    def col(names):
        for n in names:
            if n in header:
                return header.index(n)
        return None

    ti = col(time_names)
    axes = [col((a,) if not axis_prefix else tuple(h for h in header if h.startswith(f"{axis_prefix} {a} ")))
            for a in "xyz"]
    if ti is None or None in axes:
        want = f"{time_names[0]},x,y,z" if not axis_prefix else f"{time_names[0]},{axis_prefix} x/y/z"
        raise InputError(f"bad header {','.join(header)!r} (expected columns {want})", where)
    t, v = data[:, ti], data[:, axes]
    bad = ~(np.isfinite(t) & np.all(np.isfinite(v), axis=1))
    if bad.any():
        raise InputError(f"line {int(np.argmax(bad)) + 2}: NaN, empty or not a number", where)
    return t, v


def _check_stream(where: Path, t: np.ndarray, v: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Returns (t, v) with exact duplicate rows dropped; InputError for unsorted times, gaps or a low rate."""
    dt = np.diff(t)
    dup = np.flatnonzero((dt == 0) & np.all(v[1:] == v[:-1], axis=1))
    if len(dup):  # some loggers repeat buffered rows verbatim
        log.info("%s: %d repeated rows dropped", where, len(dup))
        keep = np.ones(len(t), bool)
        keep[dup + 1] = False
        t, v = t[keep], v[keep]
        dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.argmax(dt <= 0))
        raise InputError(f"{what} timestamps must increase (sample {k + 2}: {t[k + 1]:.6f} s after {t[k]:.6f} s)",
                         where)
    rate = (len(t) - 1) / (t[-1] - t[0])
    if rate < MIN_RATE_HZ:
        raise InputError(f"{what} rate {rate:.1f} Hz is below {MIN_RATE_HZ:g} Hz", where)
    gap = int(np.argmax(dt))
    if dt[gap] > MAX_GAP_S:
        raise InputError(f"{what} gap of {dt[gap]:.3f} s after t = {t[gap] - t[0]:.3f} s (at most {MAX_GAP_S:g} s)",
                         where)
    return t, v


def _check_units(gyro_where: Path, gyro: np.ndarray, up_where: Path, up: np.ndarray) -> None:
    w = float(np.percentile(np.linalg.norm(gyro, axis=1), 99))
    if w > MAX_GYRO_RAD_S:
        raise InputError(f"gyroscope rates reach {w:.1f}: expected rad/s (a log in deg/s? divide by 57.3)",
                         gyro_where)
    a = float(np.median(np.linalg.norm(up, axis=1)))
    if 0.5 < a < 2.0:
        raise InputError(f"acceleration magnitude {a:.2f}: expected m/s² with gravity (a log in g? multiply by "
                         f"{G})", up_where)
    if not 6.0 < a < 14.0:
        raise InputError(f"acceleration magnitude {a:.2f} m/s²: expected gravity included (about {G}); a log of "
                         f"linear acceleration only cannot give the vertical", up_where)


def _finish(gw: Path, tg, g, uw: Path, tu, u, source: str, epoch_s: float | None) -> RawSensors:
    tg, g = _check_stream(gw, tg, g, "gyroscope")
    tu, u = _check_stream(uw, tu, u, "accelerometer")
    _check_units(gw, g, uw, u)
    if min(tg[-1], tu[-1]) <= max(tg[0], tu[0]):
        raise InputError("the gyroscope and accelerometer logs do not overlap in time", gw.parent)
    return RawSensors(tg, g, tu, u, source, epoch_s)


def _read_generic(files: _Files) -> RawSensors:
    gw, gh, gd = _table(files, "gyro.csv")
    uw, uh, ud = _table(files, "accel.csv")
    tg, g = _columns(gw, gh, gd, ("timestamp_s",))
    tu, u = _columns(uw, uh, ud, ("timestamp_s",))
    return _finish(gw, tg, g, uw, tu, u, "generic: gyro.csv + accel.csv", None)


def _platform(files: _Files) -> str:
    if not files.has("metadata.csv"):
        return "unknown"
    rows = list(csv.reader(io.StringIO(files.text("metadata.csv"))))
    if len(rows) >= 2 and "platform" in [c.strip().lower() for c in rows[0]]:
        return rows[1][[c.strip().lower() for c in rows[0]].index("platform")].strip().lower()
    return "unknown"


def _read_sensor_logger(files: _Files) -> RawSensors:
    gw, gh, gd = _table(files, "Gyroscope.csv")
    tg, g = _columns(gw, gh, gd, ("time",))
    platform = _platform(files)
    ios = platform == "ios"
    if files.has("TotalAcceleration.csv"):
        name, (uw, uh, ud) = "TotalAcceleration.csv", _table(files, "TotalAcceleration.csv")
        tu, u = _columns(uw, uh, ud, ("time",))
    elif files.has("Gravity.csv"):
        name, (uw, uh, ud) = "Gravity.csv", _table(files, "Gravity.csv")
        tu, u = _columns(uw, uh, ud, ("time",))
    else:
        raise InputError("no Gravity.csv or TotalAcceleration.csv (turn on the Gravity sensor in Sensor Logger)",
                         files.path)
    if ios:  # iOS reports gravity pointing down (inertial-force convention): flip to the specific force
        u = -u
    t0 = float(tg[0])
    # time is integer ns since the epoch: keep seconds relative to the first gyroscope sample
    return _finish(gw, (tg - t0) * 1e-9, g, uw, (tu - t0) * 1e-9, u,
                   f"sensor-logger ({platform}): Gyroscope.csv + {name}", t0 * 1e-9)


def _read_phyphox(files: _Files) -> RawSensors:
    gw, gh, gd = _table(files, "Gyroscope.csv")
    uw, uh, ud = _table(files, "Accelerometer.csv")
    tg, g = _columns(gw, gh, gd, ("time (s)",), axis_prefix="gyroscope")
    tu, u = _columns(uw, uh, ud, ("time (s)",), axis_prefix="acceleration")
    return _finish(gw, tg, g, uw, tu, u, "phyphox: Gyroscope.csv + Accelerometer.csv", None)


def detect_format(files: _Files) -> str:
    """Returns the layout of a sensor log folder (see the module docstring); InputError if none fits."""
    if files.has("gyro.csv") and files.has("accel.csv"):
        return "generic"
    if files.has("Gyroscope.csv"):
        head = files.text("Gyroscope.csv").splitlines()[0].lower()
        if "time (s)" in head:
            return "phyphox"
        if "seconds_elapsed" in head or head.startswith("time"):
            return "sensor-logger"
    raise InputError("unknown sensor log layout: expected gyro.csv + accel.csv (generic), a Sensor Logger export "
                     "(Gyroscope.csv, Gravity.csv) or a phyphox export (Gyroscope.csv, Accelerometer.csv)",
                     files.path)


def read_sensors(path: str | Path, fmt: str = "auto") -> RawSensors:
    """Returns the :class:`RawSensors` of a sensor log folder or ``.zip`` in layout ``fmt`` (or detected)."""
    if fmt not in FORMATS:
        raise InputError(f"unknown sensor log format {fmt!r} (one of {', '.join(FORMATS)})")
    path = Path(path)
    if not path.exists():
        raise InputError("missing", path)
    files = _Files(path)
    fmt = detect_format(files) if fmt == "auto" else fmt
    return {"generic": _read_generic, "sensor-logger": _read_sensor_logger, "phyphox": _read_phyphox}[fmt](files)
