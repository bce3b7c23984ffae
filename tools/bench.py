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


def parse_seeds(text: str) -> int | list[int]:
    """Returns ``--seeds``: a count N (captures per scene, seeds SEED + k + 10 j) or an explicit list ("0-49",
    "3,7,20-24": every capture of every scene takes these seeds)."""
    text = str(text).strip()
    if text.isdigit():
        return int(text)
    seeds: list[int] = []
    for part in text.split(","):
        a, _, b = part.strip().partition("-")
        seeds += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return seeds


def real_rooms(real_dir: Path) -> list[tuple[str, Path, Path]]:
    """Returns (name, panorama, layout) of every panorama in ``real_dir`` with a layout (``NAME-corners.txt`` or
    ``NAME-layout.json``), by name."""
    out = []
    for pano in sorted(p for p in real_dir.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg")):
        for lay in (real_dir / f"{pano.stem}-corners.txt", real_dir / f"{pano.stem}-layout.json"):
            if lay.is_file():
                out.append((pano.stem, pano, lay))
                break
    return out


def _synthesise(cap: Path, scene: str, frames: int, size: tuple[int, int], seed: int, sway_m: float,
                exposure_s: float, photo_dir: Path | None, real: dict) -> None:
    """Writes one benchmark capture: a preset at the benchmark's frames and sway, a procedural room with its own
    spin (``random``: the photos of ``photo_dir`` painted on some surfaces), or a hand-held spin in a real
    panorama's room (``real:NAME``, ``real`` maps names to (panorama, layout))."""
    from panosfm_graph.synth import room_spin, synthesize

    if scene.startswith("real:"):
        pano, lay = real[scene[5:]]
        room_spin(pano, lay, cap, n_frames=frames, size=size, seed=seed, sway_m=sway_m)
    elif scene == "random":
        synthesize(cap, scene="random", size=size, seed=seed, gt_maps=False, photo_dir=photo_dir)
    else:
        synthesize(cap, scene=scene, n_frames=frames, size=size, seed=seed, sway_m=sway_m, exposure_s=exposure_s)


def bench(scenes: list[str], frames: int, size: tuple[int, int], out: Path, peers: list[str],
          seed: int = 0, reuse_peer: bool = False, seeds: int | list[int] = 1, settings: list[str] = (),
          resume: bool = False, sway_m: float = 0.0, drop_captures: bool = False, every: int = 1,
          exposure_s: float = 0.0, photo_dir: Path | None = None, real: dict | None = None) -> dict:
    """Returns the benchmark record (also written to ``out/bench.json`` and ``out/bench.md``).

    With ``drop_captures`` each capture is deleted once its runs are scored (1.6-1.7 GB each at 300 frames
    960x540, most of it the ground truth's depth and normal maps; the synthesis is deterministic, so a later
    ``--resume`` run writes it again). With ``every`` > 1 panosfm takes every k-th frame of each capture
    (``panosfm run --every``: a spin of fewer frames per turn) and its registered share is of the frames taken.
    ``exposure_s`` > 0 renders each frame's motion blur (``panosfm synth --exposure``).
    """
    from panosfm_graph.capture import load_capture
    from panosfm_graph.evaluate import evaluate_reconstruction

    out.mkdir(parents=True, exist_ok=True)
    record = {"date": datetime.date.today().isoformat(), "machine": f"{platform.machine()}, {os.cpu_count()} cores",
              "frames": frames, "size": list(size), "scenes": {}}
    if isinstance(seeds, int):  # capture j of scene k: seed + k + 10 j
        runs = [(k, scene, j, seed + k + 10 * j) for j in range(max(seeds, 1)) for k, scene in enumerate(scenes)]
    else:  # explicit seeds: every scene with each
        runs = [(k, scene, j, s) for j, s in enumerate(seeds) for k, scene in enumerate(scenes)]
    set_args = [a for kv in settings for a in ("--set", kv)]
    record["settings"] = list(settings)
    record["sway_m"] = sway_m
    record["every"] = every
    record["exposure_s"] = exposure_s
    record["seeds"] = seeds if isinstance(seeds, list) else None
    for k, scene, j, cap_seed in runs:
        name = scene if j == 0 else f"{scene}#{j}"
        if isinstance(seeds, list):
            name = f"{scene}#s{cap_seed}"
        cap = (out / "captures" / f"random-s{cap_seed}-{size[0]}x{size[1]}" if scene == "random"
               else capture_dir(out, scene.replace("real:", "real-"), frames, size, cap_seed, sway_m, exposure_s))
        if not (cap / "imu.csv").exists():
            t0 = time.perf_counter()
            _synthesise(cap, scene, frames, size, cap_seed, sway_m, exposure_s, photo_dir, real or {})
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
    if isinstance(seeds, list) or seeds > 1:
        record["median_over_seeds"] = _medians(record["scenes"], scenes)
        record["distribution"] = distribution(record["scenes"], scenes)
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


# per-capture figures whose spread is reported (p10 / median / worst), and which end is the worst
SPREAD = {"registered": (("registered_share",), "low"), "accurate": (("accurate_share",), "low"),
          "confident accurate": (("uncertainty", "confident_accurate_share"), "low"),
          "centre": (("center_error_rel", "median"), "high"), "corners": (("reprojection_px", "mean"), "high"),
          "lines": (("lines", "distance_m", "median"), "high"),
          "beyond 3 sigma": (("uncertainty", "all", "beyond_3sigma"), "high"),
          "seconds per 300 frames": ((), "high")}


def distribution(runs: dict, scenes: list[str], method: str = "panosfm") -> dict:
    """Returns {scene: {figure: {"p10", "median", "worst", "captures"}}} over the scene's captures: the 10th
    percentile from the bad end (the share of captures at least this bad is 10 %), the median and the worst;
    a failed run counts 0 for shares ("all": every capture of every scene, where there are several). Also, per frame
    source, the share of frames beyond 3 sigma pooled over
    the captures (issue #63's calibration bar), and the captures whose run called itself doubtful."""
    import numpy as np

    out: dict = {}
    for scene in scenes + (["all"] if len(scenes) > 1 else []):
        entries = [e.get(method) for name, e in runs.items()
                   if (scene == "all" or name.split("#")[0] == scene) and method in e]
        figs: dict = {}
        for key, (path, bad) in SPREAD.items():
            vals = []
            for r in entries:
                if key == "seconds per 300 frames":
                    v = None if "error" in r else r["wall_s"] * 300.0 / max(_m(r, "run_frames") or _m(r, "frames") or 300, 1)
                else:
                    v = 0.0 if ("error" in r and bad == "low") else _m(r, *path)
                if v is not None:
                    vals.append(float(v))
            if not vals:
                continue
            v = np.array(vals)
            figs[key] = {"p10": float(np.percentile(v, 10 if bad == "low" else 90)), "median": float(np.median(v)),
                         "worst": float(v.min() if bad == "low" else v.max()), "captures": len(v)}
        pooled: dict = {}
        for r in entries:
            for src, b in ((_m(r, "uncertainty", "by_source") or {}).items()):
                n, share = b.get("frames") or 0, b.get("beyond_3sigma")
                if n and share is not None:
                    p = pooled.setdefault(src, [0, 0.0])
                    p[0] += n
                    p[1] += share * n
        figs["beyond 3 sigma by source"] = {s: {"frames": n, "share": w / n} for s, (n, w) in pooled.items()}
        figs["doubtful runs"] = sum(1 for r in entries if _m(r, "uncertainty", "verdict") == "doubtful")
        out[scene] = figs
    return out


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
    dist = record.get("distribution")
    if dist:
        rows += ["", "Spread over the captures of each scene (p10: the 10th percentile from the bad end):", "",
                 "| scene | figure | captures | p10 | median | worst |", "|" + "---|" * 6]
        for scene, figs in dist.items():
            for key, v in figs.items():
                if isinstance(v, dict) and "median" in v:
                    pct = key in ("registered", "accurate", "confident accurate", "centre", "beyond 3 sigma")
                    sc, spec = (100.0, ".1f") if pct else (1.0, ".2f" if key != "lines" else ".3f")
                    rows.append(f"| {scene} | {key}{' (%)' if pct else ''} | {v['captures']} | {sc * v['p10']:{spec}} "
                                f"| {sc * v['median']:{spec}} | {sc * v['worst']:{spec}} |")
            by = figs.get("beyond 3 sigma by source") or {}
            if by:
                rows.append(f"| {scene} | beyond 3 sigma by source (pooled frames) | | "
                            + "; ".join(f"{s}: {100 * b['share']:.1f} % of {b['frames']}" for s, b in by.items())
                            + " | | |")
            rows.append(f"| {scene} | runs that called themselves doubtful | {figs.get('doubtful runs', 0)} | | | |")
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
    p.add_argument("--seeds", default="1", help="captures per scene (a count N: seeds SEED + k + 10 j), or the "
                   "seeds themselves for every scene ('0-49', '3,7,20-24'); with --scenes random each seed is a "
                   "procedural room and spin of its own (its frames and sway: --frames and --sway do not apply)")
    p.add_argument("--photo-textures", default=None, metavar="DIR",
                   help="with --scenes random: paint some surfaces with crops of the equirectangular photos in DIR "
                        "(e.g. ../shared/real)")
    p.add_argument("--real", default=None, metavar="DIR",
                   help="add a scene real:NAME per panorama in DIR with a layout (NAME-corners.txt or "
                        "NAME-layout.json): a hand-held spin inside its room (panosfm synth --panorama --layout "
                        "--sway; --sway defaults to 0.05 there), at --size")
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
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    real, sway = {}, args.sway
    if args.real:
        real = {name: (pano, lay) for name, pano, lay in real_rooms(Path(args.real))}
        scenes = [s for s in scenes if s != "real"] + [f"real:{name}" for name in real]
        sway = sway or 0.05
    records = {}
    for n in frames:
        records[n] = bench(scenes, n, (w, h), out / f"f{n}" if len(frames) > 1 else out, peers, args.seed,
                           args.reuse_peer, parse_seeds(args.seeds), args.set, args.resume, sway,
                           args.drop_captures, args.every, args.exposure,
                           Path(args.photo_textures) if args.photo_textures else None, real)
    if len(frames) > 1:
        summary = speeds_summary(records)
        (out / "speeds.json").write_text(json.dumps(summary, indent=2))
        md = format_speeds(summary)
        (out / "speeds.md").write_text(md + "\n")
        print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
