"""Batch throughput: ``panosfm batch`` (``run_batch``) on a local Dask cluster of 1 and 2 workers, and on a
scheduler and workers started separately on localhost (``dask scheduler`` + ``dask worker`` processes).

    python tools/bench_batch.py --out /tmp/bench_batch                       # 6 captures, 300 frames, 960x540
    python tools/bench_batch.py --out /tmp/bench_batch --size 480x270 --json bench_batch.json

Synthesises ``--captures`` captures (scenes living, bedroom, office in turn, seeds 0, 1, ...; without the
per-frame ground-truth maps; kept in ``OUT/captures`` and reused), then runs the whole batch once per
configuration into a fresh ``OUT/<mode>-<workers>`` and records seconds (from the call to the last capture,
cluster start included for the local cluster), captures per minute, and per capture its seconds, peak
memory, worker and detection pool. The external cluster: ``dask scheduler`` on a free localhost port
and ``dask worker --nworkers N --nthreads 1`` (non-daemonic, as the local cluster's, so a capture may start
a detection pool), both stopped at the end. The record goes to ``OUT/bench_batch.json`` (and ``--json``).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench import capture_dir  # noqa: E402

SCENES = ("living", "bedroom", "office")


def captures(out: Path, n: int, frames: int, size: tuple[int, int]) -> list[Path]:
    """Returns ``n`` synthetic captures under ``out/captures`` (synthesised where missing)."""
    from panosfm_graph.synth import synthesize

    paths = []
    for k in range(n):
        scene, seed = SCENES[k % len(SCENES)], k // len(SCENES)
        cap = capture_dir(out, scene, frames, size, seed)
        done = cap.parent / f".{cap.name}.done"  # written after the synthesis: a half-written capture is redone
        if not done.exists():
            shutil.rmtree(cap, ignore_errors=True)
            t0 = time.perf_counter()
            synthesize(cap, scene=scene, n_frames=frames, size=size, seed=seed, gt_maps=False)
            done.write_text("")
            print(f"synthesised {cap.name} in {time.perf_counter() - t0:.1f} s", flush=True)
        paths.append(cap)
    return paths


def _record(name: str, res) -> dict:
    return {"mode": name, "workers": res.workers, "scheduler": res.scheduler, "seconds": round(res.seconds, 2),
            "captures_per_minute": round(60.0 * res.ran / res.seconds, 3) if res.seconds > 0 else None,
            "ok": sum(c.status == "ok" for c in res.captures), "failed": [c.error for c in res.failed],
            "per_capture": [{"capture": c.capture, "seconds": c.seconds, "peak_memory_mb": c.peak_memory_mb,
                             "registered": c.registered, "frames": c.frames, "accurate": c.accurate,
                             "worker": c.worker, "pool": c.pool} for c in res.captures]}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def external(caps: list[Path], out: Path, n_workers: int, rerun: bool, log_dir: Path) -> dict:
    """Returns the record of a batch sent to a ``dask scheduler`` + ``dask worker`` started here on localhost."""
    from distributed import Client

    from panosfm_graph.batch import run_batch

    dask_cli = Path(sys.executable).with_name("dask")
    cmd = [str(dask_cli)] if dask_cli.exists() else [sys.executable, "-m", "dask"]
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ, DASK_DISTRIBUTED__WORKER__DAEMON="False")
    log_dir.mkdir(parents=True, exist_ok=True)
    procs = []
    try:
        procs.append(subprocess.Popen([*cmd, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                       "--no-dashboard"], stdout=subprocess.DEVNULL,
                                      stderr=open(log_dir / "scheduler.log", "w"), env=env))
        procs.append(subprocess.Popen([*cmd, "worker", address, "--nworkers", str(n_workers), "--nthreads", "1",
                                       "--no-dashboard"], stdout=subprocess.DEVNULL,
                                      stderr=open(log_dir / "worker.log", "w"), env=env))
        t0 = time.perf_counter()
        with Client(address, timeout="60s") as client:
            client.wait_for_workers(n_workers, timeout=120)
        started = time.perf_counter() - t0
        res = run_batch(caps, out, scheduler=address, rerun=rerun)
        rec = _record("external", res)
        rec["cluster_start_seconds"] = round(started, 2)
        return rec
    finally:
        for p in reversed(procs):  # the processes this function started, by their handles
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="bench_batch", help="captures, outputs and bench_batch.json go here")
    p.add_argument("--captures", type=int, default=6)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--size", default="960x540")
    p.add_argument("--workers", default="1,2", help="local cluster sizes to run, comma list")
    p.add_argument("--external-workers", type=int, default=2,
                   help="worker processes of the separately started cluster (0: skip it)")
    p.add_argument("--no-rerun", action="store_true", help="do not write recording.rrd (as panosfm batch --no-rerun)")
    p.add_argument("--json", default=None, metavar="FILE", help="also write the record here")
    args = p.parse_args(argv)
    from panosfm_graph.batch import run_batch

    w, h = (int(v) for v in args.size.lower().split("x"))
    out = Path(args.out).absolute()
    out.mkdir(parents=True, exist_ok=True)
    caps = captures(out, args.captures, args.frames, (w, h))
    record = {"date": datetime.datetime.now().isoformat(timespec="seconds"),
              "machine": f"{platform.machine()}, {os.cpu_count()} cores", "load_average_before": os.getloadavg(),
              "captures": len(caps), "frames": args.frames, "size": [w, h], "recording": not args.no_rerun,
              "command": " ".join([Path(sys.argv[0]).name, *(argv if argv is not None else sys.argv[1:])]),
              "runs": []}
    for n in [int(v) for v in args.workers.split(",") if v.strip()]:
        dest = out / f"local-{n}"
        shutil.rmtree(dest, ignore_errors=True)
        res = run_batch(caps, dest, workers=n, rerun=not args.no_rerun)
        record["runs"].append(_record("local", res))
        print(f"local cluster, {n} worker(s): {res.seconds:.1f} s, {60 * res.ran / res.seconds:.2f} captures/min, "
              f"{len(res.failed)} failed", flush=True)
    if args.external_workers > 0:
        dest = out / f"external-{args.external_workers}"
        shutil.rmtree(dest, ignore_errors=True)
        rec = external(caps, dest, args.external_workers, not args.no_rerun, out / "logs")
        record["runs"].append(rec)
        print(f"external scheduler, {args.external_workers} worker(s): {rec['seconds']:.1f} s, "
              f"{rec['captures_per_minute']:.2f} captures/min, {len(rec['failed'])} failed", flush=True)
    record["load_average_after"] = os.getloadavg()
    text = json.dumps(record, indent=2)
    (out / "bench_batch.json").write_text(text + "\n")
    if args.json:
        Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
