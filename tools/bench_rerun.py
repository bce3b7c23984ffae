"""What rerun logging costs: the same run with and without the recording.

    python tools/bench_rerun.py CAPTURE [--repeats 2] [--json out.json]

Runs ``panosfm run`` in fresh subprocesses (no cache), alternating with and
without ``--no-rerun``, and prints the wall time of each, the minimum of each
side and the overhead in percent (target: at most 10 % on a 300-frame capture).
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def timed_run(capture: str, with_rerun: bool) -> float:
    """Returns the wall seconds of one uncached ``panosfm run`` of ``capture``."""
    out = Path(tempfile.mkdtemp(prefix="panosfm-bench-rerun-")) / "out"
    cmd = [sys.executable, "-m", "panosfm_graph", "run", capture, str(out), "--camera-height", "1.5"]
    if not with_rerun:
        cmd.append("--no-rerun")
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    dt = time.perf_counter() - t0
    shutil.rmtree(out.parent, ignore_errors=True)
    return dt


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("capture")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    runs = {"with": [], "without": []}
    for _ in range(args.repeats):
        for side in ("without", "with"):
            runs[side].append(timed_run(args.capture, side == "with"))
            print(f"{side:>7} rerun: {runs[side][-1]:.2f} s", flush=True)
    best = {k: min(v) for k, v in runs.items()}
    overhead = 100.0 * (best["with"] - best["without"]) / best["without"]
    print(f"best without {best['without']:.2f} s, with {best['with']:.2f} s: rerun adds {overhead:.1f} %")
    if args.json:
        Path(args.json).write_text(json.dumps({"runs": runs, "best": best, "overhead_pct": overhead}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
