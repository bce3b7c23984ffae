"""Many captures: :func:`run_batch` reconstructs each capture on a Dask cluster (``panosfm batch``).

Each capture is one Dask task that runs the same public functions as ``panosfm run``
(:func:`~panosfm_graph.pipeline.run_pipeline`, then
:func:`~panosfm_graph.evaluate.evaluate_reconstruction` when the capture has
``ground_truth/``) into ``OUT/<name>/`` with the same atomic writes. Without a
scheduler address a local cluster is started on this machine; with one
(``tcp://host:8786``) the tasks go to an existing cluster whose workers have
panosfm installed and see the captures and ``OUT`` at the same paths (a shared
file system). Dask is an optional extra: ``pip install 'panosfm[cluster]'``.

``OUT/index.csv`` and ``OUT/index.json`` list every capture of the batch: status
(``pending`` until its task ends, then ``ok`` or ``failed``), frames, registered
and accurate frames (with ground truth), seconds, peak memory, worker, the
process pool it used and, for a failure, its one-line error. Both files are
rewritten (atomically) after every capture, so a crash of the machine that runs
the batch leaves an index of what finished. A failing capture never stops the
others.

How the cores are shared (no nested oversubscription). A capture's stages are
serial Python and numpy except line detection, which runs in a process pool of
``config.detect.workers`` processes (:mod:`panosfm_graph.parallel`). In a batch
each Dask worker runs one capture at a time (one thread) and the capture's
detection pool gets the worker's share of its machine's cores: ``min(
config.detect.workers, cores // tasks that run at once on the machine)``, at
least 1 (then detection runs in-process, no pool). The local cluster starts
``workers`` worker processes with one thread each and sets their BLAS/OpenMP
and OpenCV threads to the same share (Dask's nanny sets ``OMP_NUM_THREADS=1``
in workers by default). Dask worker processes are daemonic by default, and a
daemonic process may not start a pool, so the local cluster starts them
non-daemonic (``distributed.worker.daemon: False``); on an existing cluster
whose workers are daemonic (``dask worker`` without
``DASK_DISTRIBUTED__WORKER__DAEMON=False``) detection runs in-process. On
a 2-core machine: 1 worker runs detection in 2 processes as ``panosfm run``
does; 2 workers run two captures at once, each with detection in-process
(``tools/bench_batch.py`` measures both).

A worker that dies while it runs a capture (killed, out of memory) is replaced by
Dask's nanny and the capture is given to a worker again, up to ``retries`` more
times (the scheduler's ``distributed.scheduler.allowed-failures``: set by
``retries`` for the local cluster, by the scheduler's own configuration for an
existing one); after that it is reported failed. The run writes into a
temporary folder that only replaces ``OUT/<name>`` when it is complete, and the
next attempt removes the temporary folders of dead processes, so a killed
worker never leaves a half-written output. ``OUT/<name>/batch.json``, written
last (after ``eval.json``), marks a capture as finished.

Resume: a capture is skipped when ``OUT/<name>/batch.json`` records the same
capture path, the same capture content (size and modification time of each of
its files) and the same run key (the config, the panosfm version, the source of
every pipeline stage and the run options). A capture that failed on its input
(a corrupt or unusable capture) is skipped too while its content, the config
and the code are unchanged: it would fail the same way. Other failures (a dead
worker, an unexpected error, a full disk) are run again.
"""
from __future__ import annotations

import csv
import dataclasses
import datetime
import io
import json
import logging
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Sequence

from . import __version__
from .config import Config
from .errors import InputError
from .export import ensure_writable_dir

log = logging.getLogger("panosfm.batch")

INSTALL_HINT = "pip install 'panosfm[cluster]'"
STAMP = "batch.json"  # written last into a finished capture's output folder
INDEX_COLUMNS = ("capture", "status", "reused", "frames", "registered", "accurate", "seconds", "peak_memory_mb",
                 "worker", "pool", "error_kind", "error", "path", "out")
_CAPTURE_MARKERS = ("camera.json", "imu.csv", "frames", "frames.csv")


@dataclass(frozen=True)
class CaptureResult:
    """One capture of a batch: one row of ``OUT/index.csv``.

    ``status`` is ``pending`` (not finished), ``ok`` or ``failed``; ``reused`` is True
    when ``resume`` kept an earlier result (figures from that run). ``error_kind``
    of a failure: ``input`` (the capture is unusable, or the settings for it),
    ``output`` (its output folder is), ``error`` (an unexpected error) or
    ``worker died``.
    """

    capture: str  # name: the output folder OUT/<capture>
    path: str  # the capture directory
    out: str  # the output directory
    status: str = "pending"
    reused: bool = False
    frames: int | None = None
    registered: int | None = None
    accurate: int | None = None  # with ground truth only
    seconds: float | None = None
    peak_memory_mb: float | None = None
    worker: str | None = None
    pool: int | None = None  # detection processes (1: in-process)
    error_kind: str | None = None
    error: str | None = None
    key: str = ""  # run key (config, version, code, options): see the module docstring
    fingerprint: str = ""  # the capture's files (names, sizes, mtimes)


@dataclass(frozen=True)
class BatchResult:
    """What :func:`run_batch` did: one :class:`CaptureResult` per capture, in the order given."""

    out: Path
    captures: tuple[CaptureResult, ...]
    seconds: float
    scheduler: str | None  # the cluster's address (a local one's too); None when nothing had to run
    workers: int  # Dask workers when the batch started (0 when nothing had to run)

    @property
    def failed(self) -> tuple[CaptureResult, ...]:
        return tuple(c for c in self.captures if c.status != "ok")

    @property
    def ok(self) -> bool:
        """True when every capture has a complete output."""
        return not self.failed

    @property
    def ran(self) -> int:
        """Captures run by this batch (not reused)."""
        return sum(not c.reused for c in self.captures)

    def report(self) -> str:
        """Returns a short account: counts, throughput, the failures with their errors, the index."""
        n_ok = sum(c.status == "ok" for c in self.captures)
        reused = len(self.captures) - self.ran
        lines = [f"panosfm batch: {n_ok}/{len(self.captures)} captures ok, {len(self.failed)} failed"
                 + (f", {reused} reused from an earlier run" if reused else "")]
        if self.ran:
            rate = 60.0 * self.ran / self.seconds if self.seconds > 0 else float("nan")
            lines.append(f"  ran {self.ran} in {self.seconds:.1f} s ({rate:.2f} captures per minute) on "
                         f"{self.workers} worker{'s' if self.workers != 1 else ''} ({self.scheduler})")
        for c in self.failed:
            lines.append(f"  failed {c.capture}: {c.error}")
        lines.append(f"  index: {self.out / 'index.csv'}")
        return "\n".join(lines)


# --- finding captures ------------------------------------------------------------------------------

def _looks_like_capture(d: Path) -> bool:
    return d.is_dir() and (any((d / m).exists() for m in _CAPTURE_MARKERS) or any(d.glob("video.*")))


def find_captures(paths: Iterable[str | Path], out: str | Path | None = None) -> list[Path]:
    """Returns the capture directories named by ``paths``: each a capture, or a folder holding captures.

    A path that holds ``camera.json``, ``imu.csv``, ``frames/``, ``frames.csv`` or ``video.*``
    is a capture (a corrupt one fails in its task, not here); otherwise its sub-folders that
    do are, in name order; a folder with neither is taken as a capture (it fails with the
    capture reader's message). A path that does not exist is an :class:`InputError`.
    Duplicates are dropped; ``out`` and the folders under it are never captures.
    """
    out_abs = Path(out).expanduser().absolute() if out is not None else None
    found: list[Path] = []
    for p in paths:
        path = Path(p).expanduser().absolute()
        if not path.exists():
            raise InputError("no such capture or folder of captures", path)
        if not path.is_dir():
            raise InputError("not a directory (a capture is a directory, see capture-format.md)", path)
        if _looks_like_capture(path):
            found.append(path)
            continue
        subs = [d for d in sorted(path.iterdir()) if not d.name.startswith(".") and _looks_like_capture(d)
                and not (out_abs is not None and (d == out_abs or out_abs in d.parents))]
        found.extend(subs if subs else [path])
    unique: list[Path] = []
    for p in found:
        if p not in unique and not (out_abs is not None and (p == out_abs or out_abs in p.parents)):
            unique.append(p)
    if not unique:
        raise InputError("no capture to run")
    return unique


def output_names(captures: Sequence[Path]) -> list[str]:
    """Returns one output folder name per capture: its folder name, ``PARENT-NAME`` where two share one."""
    names = [c.name for c in captures]
    clash = {n for n in names if names.count(n) > 1}
    names = [f"{c.parent.name}-{c.name}" if c.name in clash else c.name for c in captures]
    for n in names:
        if names.count(n) > 1 or n in ("index.csv", "index.json") or n.startswith("."):
            raise InputError(f"two captures would write the same output folder {n!r}: rename one")
    return names


def capture_fingerprint(capture: str | Path) -> str:
    """Returns a hash of the capture's files (relative path, size, modification time): cheap, stats only."""
    from .cache import stable_hash

    root = Path(capture)
    entries = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        for f in sorted(filenames):
            p = Path(dirpath) / f
            try:
                st = p.stat()
            except OSError:
                continue
            entries.append((str(p.relative_to(root)), st.st_size, st.st_mtime_ns))
    return stable_hash(str(root), entries)


def run_key(config: Config, rerun: bool, views: bool) -> str:
    """Returns the key a finished capture's stamp must match for ``resume``: config, version, stage code, options."""
    from .cache import stable_hash, stage_code_hash
    from .pipeline import STAGES

    return stable_hash(__version__, config.to_dict(), [stage_code_hash(s) for s in STAGES], rerun, views)


def _previous(out_dir: Path, path: Path, key: str, fingerprint: str, index_row: dict | None) -> CaptureResult | None:
    """Returns the earlier result of a capture when it is complete and current (or failed on the same input)."""
    try:
        stamp = json.loads((out_dir / STAMP).read_text())
        if ((out_dir / "summary.json").is_file() and stamp.get("key") == key
                and stamp.get("fingerprint") == fingerprint and stamp.get("path") == str(path)):
            return dataclasses.replace(_from_dict(stamp), reused=True, out=str(out_dir))
    except (OSError, ValueError, TypeError, AttributeError):
        pass
    if (index_row and index_row.get("status") == "failed" and index_row.get("error_kind") == "input"
            and index_row.get("key") == key and index_row.get("fingerprint") == fingerprint
            and index_row.get("path") == str(path)):
        return dataclasses.replace(_from_dict(index_row), reused=True)
    return None


def _from_dict(d: dict) -> CaptureResult:
    names = {f.name for f in dataclasses.fields(CaptureResult)}
    return CaptureResult(**{k: v for k, v in d.items() if k in names})


# --- one capture (runs on a worker) ----------------------------------------------------------------

class _PeakMemory:
    """Samples the resident memory of this process and its children (the detection pool) while it runs."""

    def __init__(self, interval_s: float = 0.1):
        self.interval_s = interval_s
        self.peak = 0
        self._stop = threading.Event()

    def _sample(self) -> None:
        import psutil

        me = psutil.Process()
        while True:
            total = 0
            try:
                total = me.memory_info().rss
                for child in me.children(recursive=True):
                    try:
                        total += child.memory_info().rss
                    except psutil.Error:
                        pass
            except psutil.Error:
                pass
            self.peak = max(self.peak, total)
            if self._stop.wait(self.interval_s):
                return

    def __enter__(self) -> "_PeakMemory":
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    @property
    def mb(self) -> float:
        return round(self.peak / 2**20, 1)


def _pool_size(config: Config, pool: int | None, share: int | None,
               shares: dict[str, int]) -> tuple[int, int, str | None]:
    """Returns (detection processes for this task, its share of the cores, the Dask worker's address or None)."""
    import multiprocessing as mp

    worker, nthreads = None, 1
    try:
        from distributed import get_worker

        w = get_worker()
        worker, nthreads = w.address, w.state.nthreads
    except (ImportError, ValueError):  # not on a Dask worker: a direct call
        pass
    if share is None:
        share = shares.get(worker) if worker else None
    if share is None:
        share = max(1, (os.cpu_count() or 1) // max(1, nthreads))
    n = pool if pool is not None else min(int(config.detect.workers), share)
    if mp.current_process().daemon:  # a daemonic process cannot start a pool: detection in-process
        n = 1
    return max(1, int(n)), max(1, int(share)), worker


def run_capture(path: str | Path, out_dir: str | Path, config: Config = Config(), *, resume: bool = False,
                rerun: bool = True, views: bool = True, pool: int | None = None, share: int | None = None,
                shares: dict[str, int] | None = None, stamp_key: str = "", fingerprint: str = "",
                quiet: bool = True) -> CaptureResult:
    """Returns the result of one capture of a batch (a Dask task; callable directly too): never raises for a
    failing capture.

    Runs :func:`~panosfm_graph.pipeline.run_pipeline` into ``out_dir`` (atomic), then, when the capture has
    ``ground_truth/``, :func:`~panosfm_graph.evaluate.evaluate_reconstruction` (``out_dir/eval.json``) and the
    accurate-frame count, and writes ``out_dir/batch.json`` last. ``pool``: detection processes; by default
    the worker's share of its machine's cores (``share``, else ``shares[worker address]``, else the cores
    over the worker's threads) capped by ``config.detect.workers``; 1 in a daemonic process.
    ``stamp_key`` and ``fingerprint`` (:func:`run_key`, :func:`capture_fingerprint`) go into the stamp for
    ``resume``. ``quiet`` keeps the pipeline's warnings out of the worker's log (they are in ``summary.json``).
    """
    from .progress import set_enabled

    path, out_dir = Path(path), Path(out_dir)
    row = CaptureResult(capture=out_dir.name, path=str(path), out=str(out_dir), key=stamp_key,
                        fingerprint=fingerprint)
    n_pool, n_threads, worker = _pool_size(config, pool, share, shares or {})
    row = dataclasses.replace(row, worker=worker, pool=n_pool)
    if worker is not None:  # this process is a Dask worker's: its settings are ours to make
        set_enabled(False)  # no progress bars from a worker: the batch shows one over captures
        if quiet:
            logging.getLogger("panosfm").setLevel(logging.ERROR)
        import cv2

        cv2.setNumThreads(n_threads)
    t0 = time.perf_counter()
    with _PeakMemory() as mem:
        try:
            row = dataclasses.replace(row, **_run_and_score(path, out_dir, config, n_pool, resume, rerun, views))
            row = dataclasses.replace(row, status="ok")
        except InputError as e:
            # the output folder's problems (not writable, not a reconstruction) are fixed outside the capture
            on_out = e.path is not None and (e.path in (out_dir, out_dir.parent) or out_dir in e.path.parents)
            row = dataclasses.replace(row, status="failed", error_kind="output" if on_out else "input",
                                      error=_one_line(str(e)))
        except Exception as e:  # noqa: BLE001 - a failing capture never stops the others
            log.exception("capture %s failed", path)
            row = dataclasses.replace(row, status="failed", error_kind="error",
                                      error=_one_line(f"{path}: {type(e).__name__}: {e}"))
    row = dataclasses.replace(row, seconds=round(time.perf_counter() - t0, 3), peak_memory_mb=mem.mb)
    if row.status == "ok":
        try:
            _write_json(out_dir / STAMP, dataclasses.asdict(row))
        except OSError as e:
            row = dataclasses.replace(row, status="failed", error_kind="error",
                                      error=_one_line(f"{out_dir / STAMP}: {e.strerror or e}"))
    return row


def _run_and_score(path: Path, out_dir: Path, config: Config, n_pool: int, resume: bool, rerun: bool,
                   views: bool) -> dict:
    from .export import to_jsonable
    from .pipeline import run_pipeline

    cfg = dataclasses.replace(config, detect=dataclasses.replace(config.detect, workers=n_pool))
    result = run_pipeline(path, out_dir, cfg, resume=resume, rerun=rerun, views=views)
    frames = result.summary.get("frames", {})
    fields = {"frames": frames.get("total"), "registered": frames.get("registered")}
    if (path / "ground_truth").is_dir():
        from .capture import load_capture
        from .evaluate import evaluate_reconstruction

        capture = load_capture(path)
        try:
            metrics = evaluate_reconstruction(capture, out_dir)
        except InputError as e:
            raise InputError(f"evaluation: {e}") from None
        fields["accurate"] = metrics["accurate"]  # evaluate.ACCURATE_CENTER_REL, ACCURATE_ROTATION_DEG
        _write_json(out_dir / "eval.json", to_jsonable(metrics))
    return fields


def _one_line(text: str, limit: int = 400) -> str:
    line = " ".join(str(text).split())
    return line if len(line) <= limit else line[: limit - 3] + "..."


def _write_json(path: Path, obj) -> None:
    """Writes ``obj`` as JSON to ``path`` atomically (temporary file, then rename)."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=2, allow_nan=False, default=str)
        f.write("\n")
    os.replace(tmp, path)


# --- the index -------------------------------------------------------------------------------------

def write_index(out: Path, rows: Sequence[CaptureResult], meta: dict) -> None:
    """Writes ``out/index.json`` (``meta`` + every row) and ``out/index.csv`` (:data:`INDEX_COLUMNS`), atomically."""
    _write_json(out / "index.json", {**meta, "updated": _now(), "captures": [dataclasses.asdict(r) for r in rows]})
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(INDEX_COLUMNS)
    for r in rows:
        d = dataclasses.asdict(r)
        w.writerow(["" if d[c] is None else str(d[c]).lower() if isinstance(d[c], bool) else d[c]
                    for c in INDEX_COLUMNS])
    tmp = out / f".index.csv.tmp-{os.getpid()}"
    tmp.write_text(buf.getvalue())
    os.replace(tmp, out / "index.csv")


def read_index(out: str | Path) -> list[dict]:
    """Returns the rows of ``out/index.json`` ([] when there is none or it is unreadable)."""
    try:
        rows = json.loads((Path(out) / "index.json").read_text()).get("captures", [])
        return [r for r in rows if isinstance(r, dict)]
    except (OSError, ValueError, AttributeError):
        return []


def _now() -> str:
    return datetime.datetime.now().astimezone().isoformat(timespec="seconds")


# --- the batch -------------------------------------------------------------------------------------

def _import_distributed():
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise InputError(f"panosfm batch needs Dask distributed: {INSTALL_HINT}") from None
    return distributed


def run_batch(captures: Iterable[str | Path], out: str | Path, config: Config = Config(), *,
              scheduler: str | None = None, workers: int | None = None, resume: bool = False,
              rerun: bool = True, views: bool = True, pool: int | None = None, retries: int = 2,
              on_result: Callable[[CaptureResult], None] | None = None) -> BatchResult:
    """Returns the batch's result after reconstructing every capture into ``out/<name>/`` (see the module docstring).

    ``captures``: capture directories or folders holding them (:func:`find_captures`). ``scheduler``:
    the address of an existing Dask scheduler (``tcp://host:8786``); without it a local cluster of
    ``workers`` processes (default: one per core, at most one per capture). ``resume`` skips captures
    whose output is complete and current and passes ``resume`` to the pipeline (stage cache) for the
    others. ``rerun``/``views``: as :func:`~panosfm_graph.pipeline.run_pipeline`. ``pool``: detection
    processes per capture (default: the worker's share of the cores). ``retries``: how many more times a
    capture whose worker died is run (local cluster). ``on_result`` sees each capture as it finishes.
    A failing capture is a row with status ``failed``; errors of the batch itself (no Dask, a missing
    path, an unreachable scheduler, an unwritable ``out``) raise :class:`InputError`.
    """
    t0 = time.perf_counter()
    distributed = _import_distributed()
    if scheduler and workers is not None:
        raise InputError("--workers starts a local cluster: with --scheduler the cluster's workers run the captures")
    if workers is not None and workers < 1:
        raise InputError(f"workers must be at least 1, got {workers}")
    if pool is not None and pool < 1:
        raise InputError(f"pool must be at least 1, got {pool}")
    out = Path(out).expanduser().absolute()
    paths = find_captures(captures, out)
    names = output_names(paths)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a directory", out)
    ensure_writable_dir(out, "output directory")

    key = run_key(config, rerun, views)
    previous = {r.get("capture"): r for r in read_index(out)} if resume else {}
    rows: list[CaptureResult] = []
    for path, name in zip(paths, names):
        fp = capture_fingerprint(path)
        row = _previous(out / name, path, key, fp, previous.get(name)) if resume else None
        rows.append(row or CaptureResult(capture=name, path=str(path), out=str(out / name), key=key, fingerprint=fp))
    todo = [i for i, r in enumerate(rows) if not r.reused]
    meta = {"panosfm_version": __version__, "out": str(out), "scheduler": scheduler, "workers": None,
            "resume": resume, "config": config.to_dict(), "started": _now()}
    write_index(out, rows, meta)
    for r in rows:
        if r.reused and on_result is not None:
            on_result(r)
    if not todo:
        return BatchResult(out=out, captures=tuple(rows), seconds=time.perf_counter() - t0, scheduler=None, workers=0)

    quiet = not logging.getLogger("panosfm").isEnabledFor(logging.INFO)
    with _cluster(distributed, scheduler, workers, len(todo), retries) as (client, address, n_workers, share):
        meta.update(scheduler=address, workers=n_workers)
        shares = _worker_shares(client) if scheduler else {}
        futures = {}
        for i in todo:
            r = rows[i]
            fut = client.submit(run_capture, r.path, r.out, config, resume=resume, rerun=rerun, views=views,
                                pool=pool, share=share, shares=shares, stamp_key=key,
                                fingerprint=r.fingerprint, quiet=quiet, pure=False,
                                key=f"panosfm-{r.capture}-{os.urandom(4).hex()}")  # Dask's task key
            futures[fut] = i
        write_index(out, rows, meta)
        from .progress import progress

        try:
            for fut in progress(distributed.as_completed(list(futures)), "captures", total=len(futures)):
                i = futures[fut]
                rows[i] = _collect(fut, rows[i], distributed, local=not scheduler)
                write_index(out, rows, meta)
                log.info("%s: %s%s", rows[i].capture, rows[i].status, f" ({rows[i].error})" if rows[i].error else "")
                if on_result is not None:
                    on_result(rows[i])
        except BaseException:
            for fut in futures:
                fut.cancel()
            write_index(out, rows, meta)
            raise
    return BatchResult(out=out, captures=tuple(rows), seconds=time.perf_counter() - t0, scheduler=meta["scheduler"],
                       workers=n_workers)


def _collect(fut, row: CaptureResult, distributed, local: bool) -> CaptureResult:
    """Returns the finished task's row; a task that raised or whose worker died is a failed row.

    After the last death of a local worker, the temporary folder its run left next to the output is
    removed here (on another machine the next run of the capture removes it: process ids are per machine).
    """
    try:
        return fut.result()
    except distributed.KilledWorker:
        if local:
            from .export import recover_output_dir
            from .pipeline import CACHE_KEEP

            try:
                recover_output_dir(Path(row.out), keep=CACHE_KEEP)
            except OSError:
                pass
        return dataclasses.replace(row, status="failed", error_kind="worker died", error=_one_line(
            f"{row.path}: the worker running it died (killed or out of memory) on every attempt"))
    except Exception as e:  # noqa: BLE001 - e.g. the scheduler went away: this capture failed, the others go on
        return dataclasses.replace(row, status="failed", error_kind="error",
                                   error=_one_line(f"{row.path}: {type(e).__name__}: {e}"))


def _worker_shares(client) -> dict[str, int]:
    """Returns {worker address: its share of its machine's cores} (cores // threads of the workers on that host)."""
    try:
        cores = client.run(os.cpu_count)
        info = _workers_info(client)
    except Exception:  # noqa: BLE001 - a worker that does not answer gets the default share in its task
        return {}
    threads: dict[str, int] = {}
    for addr, w in info.items():
        threads[w.get("host", addr)] = threads.get(w.get("host", addr), 0) + int(w.get("nthreads", 1))
    return {addr: max(1, int(cores.get(addr) or 1) // max(1, threads[w.get("host", addr)]))
            for addr, w in info.items()}


def _workers_info(client) -> dict[str, dict]:
    """Returns the scheduler's {address: info} of every worker (recent Dask lists 5 unless asked for all)."""
    import inspect

    if "n_workers" in inspect.signature(client.scheduler_info).parameters:
        return client.scheduler_info(n_workers=-1)["workers"]
    return client.scheduler_info()["workers"]


class _cluster:
    """Context manager: yields (client, scheduler address, workers, per-capture share of the cores or None).

    A local cluster: ``workers`` processes (default min(cores, captures)) of one thread each, non-daemonic
    (their captures may start a detection pool), BLAS/OpenMP threads set to ``cores // workers``, and
    ``retries`` more attempts for a capture whose worker died. An existing scheduler: a client to it.
    """

    def __init__(self, distributed, scheduler: str | None, workers: int | None, n_tasks: int, retries: int):
        self.d, self.scheduler, self.workers = distributed, scheduler, workers
        self.n_tasks, self.retries = n_tasks, retries
        self.cluster = self.client = self.config = None

    def __enter__(self):
        import dask

        d = self.d
        # Dask logs at INFO level; through the CLI's root handler that would be every worker's start and stop
        self.dask_log = logging.getLogger("distributed")
        self.dask_level = self.dask_log.level
        if not logging.getLogger("panosfm").isEnabledFor(logging.INFO):
            self.dask_log.setLevel(logging.ERROR)
        if self.scheduler:
            try:
                self.client = d.Client(self.scheduler, timeout="10s")
            except (OSError, TimeoutError, ValueError) as e:
                raise InputError(f"cannot reach the Dask scheduler at {self.scheduler} ({_one_line(e)})") from None
            n = len(_workers_info(self.client))
            if n == 0:
                log.warning("the Dask cluster at %s has no worker yet: the captures wait for one", self.scheduler)
            return self.client, self.scheduler, n, None
        cores = os.cpu_count() or 1
        n = self.workers or max(1, min(cores, self.n_tasks))
        share = max(1, cores // n)
        threads = str(share)
        self.config = dask.config.set({
            "distributed.worker.daemon": False,  # a capture's detection pool needs a non-daemonic worker
            "distributed.scheduler.allowed-failures": max(0, int(self.retries)),
            "distributed.nanny.pre-spawn-environ.OMP_NUM_THREADS": threads,
            "distributed.nanny.pre-spawn-environ.MKL_NUM_THREADS": threads,
            "distributed.nanny.pre-spawn-environ.OPENBLAS_NUM_THREADS": threads,
        })
        self.config.__enter__()
        try:
            # the scheduler's HTTP server on a free port: two batches on one machine must not clash on 8787
            self.cluster = d.LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0",
                                          silence_logs=logging.ERROR)
            self.client = d.Client(self.cluster)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self.client, self.cluster.scheduler_address, n, share

    def __exit__(self, *exc) -> None:
        for obj in (self.client, self.cluster):
            if obj is not None:
                try:
                    obj.close()
                except Exception:  # noqa: BLE001 - closing a cluster that is going away anyway
                    pass
        if self.config is not None:
            self.config.__exit__(None, None, None)
        self.dask_log.setLevel(self.dask_level)
