"""Streaming reconstruction (issue 42): the one-shot run against the streamed run on one capture.

    python tools/bench_stream.py CAPTURE OUT [--batch 50] [--no-final] [--repeats 2] [--json bench_stream.json]

Runs, one after the other in this process, ``panosfm run CAPTURE OUT/oneshot --no-rerun`` and
``panosfm run CAPTURE OUT/stream --no-rerun --incremental N`` (with the final full solve; with
``--no-final`` a third run without it), each from an empty output directory, and scores each
against the capture's ground truth (``panosfm eval``). Prints the wall seconds of each run, the
ratio, the per-batch latency (seconds from a batch's last frame read to its estimate: median and
max over the batches; with the final solve the last batch is solved in full), each batch's seconds per stage, and the
metrics with the streamed runs' relative differences to the one-shot. The record goes to
``OUT/bench_stream.json`` (and ``--json``). Timings are wall clock on a shared machine: run the
comparison back to back, as this script does (``--repeats``: round robin, each run's fastest repeat).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import statistics
import time
from pathlib import Path

METRICS = {  # name -> path into evaluate_reconstruction's dict
    "registered": ("registered",),
    "accurate": ("accurate",),
    "centre_error_rel_mean": ("center_error_rel", "mean"),
    "rotation_deg_median": ("rotation_error_rotalign_deg", "median"),
    "corners_px_median": ("reprojection_px", "median"),
    "lines_distance_m_median": ("lines", "distance_m", "median"),
    "edges_recovered": ("lines", "recovered"),
}


def _metric(m: dict, path: tuple[str, ...]):
    for k in path:
        m = m.get(k) if isinstance(m, dict) else None
    return None if m is None else float(m)


def run_once(capture: Path, out: Path, config) -> dict:
    """Returns the wall seconds, summary figures and metrics of one run of ``config`` into ``out``."""
    from panosfm_graph.evaluate import evaluate_reconstruction
    from panosfm_graph.pipeline import run_pipeline

    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    res = run_pipeline(capture, out, config, rerun=False, views=False)
    wall = time.perf_counter() - t0
    m = evaluate_reconstruction(capture, out)
    s = res.summary
    rec = {"wall_s": round(wall, 2), "seconds": s["seconds"],
           "metrics": {k: _metric(m, p) for k, p in METRICS.items()}}
    if "incremental_batches" in s:
        lat = s["incremental_batch_seconds"]  # the last batch's is the final solve's, where there is one
        rec.update(batches_registered=s["incremental_batches"], batch_seconds=s["incremental_batch_seconds"],
                   stage_seconds=s.get("incremental_stage_seconds"),
                   latency_median_s=round(statistics.median(lat), 2), latency_max_s=round(max(lat), 2))
    return rec


def _rel(a, b):
    return None if a is None or b is None or b == 0 else round((a - b) / abs(b), 4)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--batch", type=int, default=50, help="frames per batch")
    ap.add_argument("--no-final", action="store_true", help="also a streamed run without the final full solve")
    ap.add_argument("--repeats", type=int, default=1, help="runs of each, round robin; the fastest is reported")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    from panosfm_graph.config import Config

    base = Config()
    graph = dataclasses.replace(base.graph, incremental_batch=args.batch)
    runs = {"oneshot": base, "stream": dataclasses.replace(base, graph=graph)}
    if args.no_final:
        runs["stream_no_final"] = dataclasses.replace(
            base, graph=dataclasses.replace(graph, incremental_final_solve=False))
    record: dict = {"capture": str(args.capture.resolve()), "batch": args.batch, "runs": {}}
    for _ in range(max(1, args.repeats)):  # round robin: a load that comes and goes hits every run alike
        for name, cfg in runs.items():
            r = run_once(args.capture, args.out / name, cfg)
            best = record["runs"].get(name)
            r["walls_s"] = (best["walls_s"] if best else []) + [r["wall_s"]]
            if best is not None and best["wall_s"] <= r["wall_s"]:  # the fastest repeat's figures are kept
                best["walls_s"] = r["walls_s"]
                r = best
            record["runs"][name] = r
            print(f"{name:16s} wall {r['wall_s']:6.1f} s (best of {len(r['walls_s'])})" + (
                f"  latency median {r['latency_median_s']:.1f} s max {r['latency_max_s']:.1f} s"
                f"  registered per batch {r['batches_registered']}" if "latency_median_s" in r else ""), flush=True)
    one = record["runs"]["oneshot"]
    for name, r in record["runs"].items():
        if name == "oneshot":
            continue
        r["wall_ratio"] = round(r["wall_s"] / one["wall_s"], 3)
        r["metrics_rel_diff"] = {k: _rel(v, one["metrics"][k]) for k, v in r["metrics"].items()}
        print(f"{name}: wall {r['wall_ratio']:.2f}x one-shot; batch seconds {r['batch_seconds']}")
        for k, st in enumerate(r["stage_seconds"] or []):
            print(f"  batch {k}: " + ", ".join(f"{s} {v:.2f}" for s, v in st.items()))
    print(f"{'metric':26s} " + " ".join(f"{n:>16s}" for n in record["runs"]))
    for k in METRICS:
        vals = [record["runs"][n]["metrics"][k] for n in record["runs"]]
        print(f"{k:26s} " + " ".join(f"{'-' if v is None else f'{v:.4g}':>16s}" for v in vals))
    args.out.mkdir(parents=True, exist_ok=True)
    for path in [args.out / "bench_stream.json"] + ([args.json] if args.json else []):
        path.write_text(json.dumps(record, indent=2))
    print(f"wrote {args.out / 'bench_stream.json'}")


if __name__ == "__main__":
    main()
