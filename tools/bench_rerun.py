"""What rerun logging costs: the same run with and without the recording.

    python tools/bench_rerun.py CAPTURE [--repeats 2] [--json out.json]

Runs ``panosfm run`` in fresh subprocesses (no cache), alternating with and
without ``--no-rerun``, and prints the wall and CPU time of each (CPU time, workers
included, is the steadier figure on a shared machine), the minimum of each
side and the overhead in percent (target: at most 10 % on a 300-frame capture).
"""
from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def timed_run(capture: str, with_rerun: bool) -> tuple[float, float]:
    """Returns (wall seconds, CPU seconds incl. worker processes) of one uncached ``panosfm run``."""
    out = Path(tempfile.mkdtemp(prefix="panosfm-bench-rerun-")) / "out"
    cmd = [sys.executable, "-m", "panosfm_graph", "run", capture, str(out), "--camera-height", "1.5"]
    if not with_rerun:
        cmd.append("--no-rerun")
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    dt = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    shutil.rmtree(out.parent, ignore_errors=True)
    return dt, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("capture")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    runs = {"with": [], "without": []}
    cpu = {"with": [], "without": []}
    for _ in range(args.repeats):
        for side in ("without", "with"):
            wall, secs = timed_run(args.capture, side == "with")
            runs[side].append(wall)
            cpu[side].append(secs)
            print(f"{side:>7} rerun: {wall:.2f} s wall, {secs:.2f} s CPU", flush=True)
    best = {k: min(v) for k, v in runs.items()}
    best_cpu = {k: min(v) for k, v in cpu.items()}
    overhead = 100.0 * (best["with"] - best["without"]) / best["without"]
    overhead_cpu = 100.0 * (best_cpu["with"] - best_cpu["without"]) / best_cpu["without"]
    print(f"best without {best['without']:.2f} s, with {best['with']:.2f} s: rerun adds {overhead:.1f} % wall "
          f"({overhead_cpu:.1f} % CPU time: {best_cpu['without']:.1f} -> {best_cpu['with']:.1f} s)")
    if args.json:
        Path(args.json).write_text(json.dumps({"wall_s": runs, "cpu_s": cpu, "best_wall_s": best,
                                               "best_cpu_s": best_cpu, "overhead_wall_pct": overhead,
                                               "overhead_cpu_pct": overhead_cpu}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
