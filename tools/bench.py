"""Whole-pipeline benchmark: panosfm (and the COLMAP peer, when pycolmap is installed) on synthetic scenes.

    python tools/bench.py --scenes living,bedroom,office --frames 300 --size 960x540 --out bench/
    python tools/bench.py --peer none --seeds 3 --set linear.robust_iterations=5   # a setting, 3 captures per scene
    python tools/bench.py --peer none --seeds 3 --frames 60,100,150,300,600 --out bench-speeds   # spin speeds

With several ``--frames`` each spin speed is its own benchmark in ``OUT/f<N>`` and ``OUT/speeds.json`` /
``speeds.md`` gather them: per speed and scene the medians, and how the time per capture grows with the
frames (the exponent b of seconds ~ frames^b, fitted over the speeds).

For each scene (and each of ``--seeds`` captures of it: the single-capture results of this
pipeline swing a lot with small changes, so compare settings over several): synthesise a
capture (cached in ``OUT/captures``), run
panosfm with the camera height given, run the peer (``--peer`` incremental,
global and/or global-gravity, i.e. GLOMAP given the IMU's gravity per image:
``tools/peer_colmap.py``), score everything with ``evaluate_reconstruction``, and write
``bench.json`` and ``bench.md`` (metrics, seconds per stage, peak memory; with several
seeds also the median over them per scene and method). ``--set`` passes pipeline settings to
``panosfm run``. Each panosfm run is a fresh subprocess so peak memory is per run.
"""
from __future__ import annotations

import argparse
import datetime
import importlib.util
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
PEER_MAX_MINUTES = 8  # COLMAP's incremental mapper can grind for half an hour on a degenerate spin


def _run(cmd: list[str]) -> tuple[int, float, str]:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    return proc.returncode, time.perf_counter() - t0, (proc.stderr or "")[-2000:]


def capture_dir(out: Path, scene: str, frames: int, size: tuple[int, int], seed: int, sway_m: float = 0.0,
                exposure_s: float = 0.0) -> Path:
    """Returns where a benchmark keeps the synthetic capture of these settings (``OUT/captures/NAME``): one name
    for every benchmark, so that captures can be linked from one output folder into another."""
    return out / "captures" / (f"{scene}-{frames}-{size[0]}x{size[1]}-s{seed}" + (f"-sway{sway_m:g}" if sway_m > 0 else "")
                               + (f"-exp{exposure_s:g}" if exposure_s > 0 else ""))


def bench(scenes: list[str], frames: int, size: tuple[int, int], out: Path, peers: list[str],
          seed: int = 0, reuse_peer: bool = False, seeds: int = 1, settings: list[str] = (),
          resume: bool = False, sway_m: float = 0.0, drop_captures: bool = False, every: int = 1,
          exposure_s: float = 0.0) -> dict:
    """Returns the benchmark record (also written to ``out/bench.json`` and ``out/bench.md``).

    With ``drop_captures`` each capture is deleted once its runs are scored (1.6-1.7 GB each at 300 frames
    960x540, most of it the ground truth's depth and normal maps; the synthesis is deterministic, so a later
    ``--resume`` run writes it again). With ``every`` > 1 panosfm takes every k-th frame of each capture
    (``panosfm run --every``: a spin of fewer frames per turn) and its registered share is of the frames taken.
    ``exposure_s`` > 0 renders each frame's motion blur (``panosfm synth --exposure``).
    """
    from panosfm_graph.capture import load_capture
    from panosfm_graph.evaluate import evaluate_reconstruction
    from panosfm_graph.synth import synthesize

    out.mkdir(parents=True, exist_ok=True)
    record = {"date": datetime.date.today().isoformat(), "machine": f"{platform.machine()}, {os.cpu_count()} cores",
              "frames": frames, "size": list(size), "scenes": {}}
    runs = [(k, scene, j) for j in range(max(seeds, 1)) for k, scene in enumerate(scenes)]
    set_args = [a for kv in settings for a in ("--set", kv)]
    record["settings"] = list(settings)
    record["sway_m"] = sway_m
    record["every"] = every
    record["exposure_s"] = exposure_s
    for k, scene, j in runs:
        name = scene if j == 0 else f"{scene}#{j}"  # capture j of the scene: seed + k + 10 j
        cap = capture_dir(out, scene, frames, size, seed + k + 10 * j, sway_m, exposure_s)
        if not (cap / "imu.csv").exists():
            t0 = time.perf_counter()
            synthesize(cap, scene=scene, n_frames=frames, size=size, seed=seed + k + 10 * j, sway_m=sway_m,
                       exposure_s=exposure_s)
            print(f"[{scene}] synthesised in {time.perf_counter() - t0:.1f} s", flush=True)
        gt = load_capture(cap).ground_truth
        height = gt.camera_height_m
        entry = {}
        rec = out / "runs" / name / "panosfm"
        code, secs, err = _run([sys.executable, "-m", "panosfm_graph", "run", str(cap), str(rec),
                                "--camera-height", f"{height:.4f}", "--no-rerun", *set_args,
                                *(["--every", str(every)] if every > 1 else []),
                                *(["--resume"] if resume else [])])
        entry["panosfm"] = _score(rec, cap, code, secs, err, evaluate_reconstruction)
        print(f"[{name}] panosfm: {_line(entry['panosfm'])}", flush=True)
        for mapper in peers:
            pdir = out / "runs" / name / f"colmap-{mapper}"
            if reuse_peer and (pdir / "summary.json").exists():  # the peer is deterministic for a capture
                secs = json.loads((pdir / "summary.json").read_text())["seconds"]["total"]
                code, err = 0, ""
            else:
                code, secs, err = _run([sys.executable, str(HERE / "peer_colmap.py"), str(cap), str(pdir),
                                        "--mapper", mapper, "--max-mapping-minutes", str(PEER_MAX_MINUTES)])
            entry[f"colmap-{mapper}"] = _score(pdir, cap, code, secs, err, evaluate_reconstruction)
            print(f"[{name}] colmap-{mapper}: {_line(entry[f'colmap-{mapper}'])}", flush=True)
        record["scenes"][name] = entry
        if drop_captures:
            shutil.rmtree(cap, ignore_errors=True)
    if seeds > 1:
        record["median_over_seeds"] = _medians(record["scenes"], scenes)
    from panosfm_graph.export import to_jsonable

    (out / "bench.json").write_text(json.dumps(to_jsonable(record), indent=2))
    md = format_bench(record)
    (out / "bench.md").write_text(md + "\n")
    print(md)
    return record


# the metrics tabulated, as paths into ``evaluate_reconstruction``'s dictionary
METRICS = {"registered": ("registered_share",), "accurate": ("accurate_share",), "centre": ("center_error_rel", "median"),
           "rotation": ("rotation_error_rotalign_deg", "median"), "reprojection": ("reprojection_px", "mean"),
           "lines": ("lines", "distance_m", "median"), "recovered": ("lines", "recovered_share")}


def _medians(runs: dict, scenes: list[str]) -> dict:
    """Returns {scene: {method: {metric: median over the scene's captures}}} (failed or missing: left out)."""
    import numpy as np

    out: dict = {}
    for scene in scenes:
        entries = [e for name, e in runs.items() if name.split("#")[0] == scene]
        for method in sorted({m for e in entries for m in e}):
            vals = {}
            for key, path in METRICS.items():
                v = [_m(e[method], *path) for e in entries if method in e and "error" not in e[method]]
                v = [x for x in v if x is not None]
                vals[key] = float(np.median(v)) if v else None
            vals["captures"] = len(entries)
            vals["failed"] = sum(1 for e in entries if method in e and "error" in e[method])
            out.setdefault(scene, {})[method] = vals
    return out


def _score(rec: Path, cap: Path, code: int, secs: float, err: str, evaluate) -> dict:
    r = {"exit": code, "wall_s": round(secs, 2)}
    if code != 0:
        r["error"] = err.strip().splitlines()[-1] if err.strip() else "failed"
        return r
    summary = json.loads((rec / "summary.json").read_text())
    r["seconds"] = summary.get("seconds", {})
    r["peak_memory_mb"] = summary.get("peak_memory_mb")
    r["metrics"] = m = evaluate(cap, rec)
    taken = m.get("run_frames") or m["frames"]
    m["registered_share"] = m["registered"] / taken  # of the frames the run took
    m["accurate_share"] = m.get("accurate", 0) / taken  # rotation <= 1 deg, centre <= 5 % of the diameter
    return r


def _m(r: dict, *path: str):
    m = r.get("metrics")
    for p in path:
        if not isinstance(m, dict) or m.get(p) is None:
            return None
        m = m[p]
    return m


def _line(r: dict) -> str:
    if "error" in r:
        return f"FAILED ({r['error']})"
    return (f"registered {100 * (_m(r, 'registered_share') or 0):.1f} %, "
            f"corner reproj {_m(r, 'reprojection_px', 'mean')}, wall {r['wall_s']} s")


def format_bench(record: dict) -> str:
    """Returns the markdown table of a benchmark record."""
    def f(v, spec):
        return "n/a" if v is None else format(v, spec)

    every = record.get("every", 1)
    rows = [f"Benchmark {record['date']}, {record['machine']}, {record['frames']} frames at "
            f"{record['size'][0]}x{record['size'][1]}" + (f", every {every}th frame taken" if every > 1 else ""), "",
            "| scene | method | registered | accurate | centre err. median (% diam., sim3) | rot. err. median (deg) "
            "| corner reproj. mean (px) "
            "| line-surface median (m) | edges recovered | seconds | peak MB |",
            "|" + "---|" * 11]
    for scene, entry in record["scenes"].items():
        for method, r in entry.items():
            if "error" in r:
                rows.append(f"| {scene} | {method} | failed: {r['error']} |" + " |" * 8)
                continue
            cen = _m(r, "center_error_rel", "median")
            rows.append(
                f"| {scene} | {method} | {f(100 * (_m(r, 'registered_share') or 0), '.1f')} % "
                f"| {f(100 * (_m(r, 'accurate_share') or 0), '.1f')} % "
                f"| {f(None if cen is None else 100 * cen, '.2f')} "
                f"| {f(_m(r, 'rotation_error_rotalign_deg', 'median'), '.3f')} "
                f"| {f(_m(r, 'reprojection_px', 'mean'), '.2f')} "
                f"| {f(_m(r, 'lines', 'distance_m', 'median'), '.3f')} "
                f"| {f(_m(r, 'lines', 'recovered_share'), '.2f')} "
                f"| {r['wall_s']:.1f} | {f(r.get('peak_memory_mb'), '.0f')} |")
    med = record.get("median_over_seeds")
    if med:
        rows += ["", "Median over the captures of each scene:", "",
                 "| scene | method | captures | registered | accurate | centre err. median (% diam.) | rot. err. (deg) "
                 "| corner reproj. mean (px) | line-surface median (m) |", "|" + "---|" * 9]
        for scene, methods in med.items():
            for method, v in methods.items():
                reg = v["registered"]
                cen = v["centre"]
                rows.append(f"| {scene} | {method} | {v['captures']} ({v['failed']} failed) "
                            f"| {f(None if reg is None else 100 * reg, '.1f')} % "
                            f"| {f(None if v['accurate'] is None else 100 * v['accurate'], '.1f')} % "
                            f"| {f(None if cen is None else 100 * cen, '.2f')} | {f(v['rotation'], '.3f')} "
                            f"| {f(v['reprojection'], '.2f')} | {f(v['lines'], '.3f')} |")
    return "\n".join(rows)


def speeds_summary(records: dict[int, dict]) -> dict:
    """Returns the summary of one benchmark per spin speed ({frames: record}): per speed and scene the medians
    over its captures (panosfm), the median seconds per capture, and the exponent b of seconds ~ frames^b
    (least squares in log-log over the speeds; 1: linear in the frames)."""
    import numpy as np

    rows, secs = {}, {}
    for n, rec in sorted(records.items()):
        med = _medians(rec["scenes"], list(dict.fromkeys(name.split("#")[0] for name in rec["scenes"])))
        rows[n] = {scene: methods.get("panosfm") for scene, methods in med.items()}
        walls = [e["panosfm"]["wall_s"] for e in rec["scenes"].values() if "metrics" in e.get("panosfm", {})]
        secs[n] = float(np.median(walls)) if walls else None
    pts = [(n, t) for n, t in secs.items() if t]
    slope = float(np.polyfit(np.log([n for n, _ in pts]), np.log([t for _, t in pts]), 1)[0]) if len(pts) >= 2 else None
    return {"by_frames": rows, "seconds_median": secs, "time_exponent": slope}


def format_speeds(summary: dict) -> str:
    """Returns the markdown table of :func:`speeds_summary`."""
    def f(v, spec, scale=1.0):
        return "n/a" if v is None else format(scale * v, spec)

    rows = ["| frames per turn | scene | registered | accurate | centre err. median (% diam.) | corner reproj. (px) "
            "| seconds per capture |", "|" + "---|" * 7]
    for n, scenes in summary["by_frames"].items():
        for scene, v in scenes.items():
            v = v or {}
            rows.append(f"| {n} | {scene} | {f(v.get('registered'), '.1f', 100)} % | {f(v.get('accurate'), '.1f', 100)} % "
                        f"| {f(v.get('centre'), '.2f', 100)} | {f(v.get('reprojection'), '.2f')} "
                        f"| {f(summary['seconds_median'][n], '.1f')} |")
    b = summary["time_exponent"]
    rows += ["", f"Seconds per capture grow as frames^{f(b, '.2f')} (median seconds per speed, log-log fit; 1 = linear)."]
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", default="living,bedroom,office")
    p.add_argument("--frames", default="300", help="frames per turn; a comma list runs one benchmark per speed "
                   "(OUT/f<N>) and writes OUT/speeds.json and speeds.md")
    p.add_argument("--size", default="960x540")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="bench")
    p.add_argument("--reuse-peer", action="store_true",
                   help="reuse a peer reconstruction already in OUT/runs (same capture, same settings)")
    p.add_argument("--peer", default="auto", help="'auto' (incremental if pycolmap is installed), 'none', "
                   "or a comma list of incremental,global,global-gravity (GLOMAP with IMU gravity priors); "
                   "each is tabulated as colmap-MAPPER")
    p.add_argument("--resume", action="store_true",
                   help="reuse the cached stages of earlier runs in OUT (copy a runs/ folder there): fast setting "
                        "sweeps; seconds then no longer measure the whole pipeline")
    p.add_argument("--seeds", type=int, default=1, help="captures per scene (seeds SEED + k + 10 j)")
    p.add_argument("--sway", type=float, default=0.0, metavar="M",
                   help="synthesise spins that depart this far (m RMS) from an ideal circle (panosfm synth --sway)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="a pipeline setting for panosfm run (repeatable)")
    p.add_argument("--every", type=int, default=1, metavar="K",
                   help="panosfm takes every K-th frame (panosfm run --every): fewer frames per turn")
    p.add_argument("--exposure", type=float, default=0.0, metavar="S",
                   help="render each frame's motion blur for this exposure time (panosfm synth --exposure)")
    p.add_argument("--drop-captures", action="store_true",
                   help="delete each synthetic capture once scored (45 captures at 960x540 take about 75 GB)")
    args = p.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    if args.peer == "auto":
        peers = ["incremental"] if importlib.util.find_spec("pycolmap") is not None else []
    elif args.peer == "none":
        peers = []
    else:
        peers = [s.strip() for s in args.peer.split(",") if s.strip()]
    frames = [int(v) for v in args.frames.split(",") if v.strip()]
    out = Path(args.out)
    records = {}
    for n in frames:
        records[n] = bench([s.strip() for s in args.scenes.split(",")], n, (w, h),
                           out / f"f{n}" if len(frames) > 1 else out, peers, args.seed, args.reuse_peer, args.seeds,
                           args.set, args.resume, args.sway, args.drop_captures, args.every, args.exposure)
    if len(frames) > 1:
        summary = speeds_summary(records)
        (out / "speeds.json").write_text(json.dumps(summary, indent=2))
        md = format_speeds(summary)
        (out / "speeds.md").write_text(md + "\n")
        print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
