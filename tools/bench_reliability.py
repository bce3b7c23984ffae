"""Reliability benchmark: bad input, killed runs, wrong relations, hard captures.

Four sections (``--sections``, all by default); each prints a table and all
go to one JSON file (``--json``, default ``<work>/reliability.json``):

* ``bad_input``: a synthetic capture is damaged in one way at a time and
  ``panosfm run`` (a subprocess, as a user runs it) is pointed at a directory
  holding a previous complete result. Reported: exit status, stderr lines
  (libpng writes its own line to stderr before ours for a damaged PNG),
  whether the message names the file, a traceback, and whether the previous
  result changed (``data lost``; the stage cache ``cache/`` is not counted).
* ``kill``: a run is SIGKILLed during detection (from outside, on its
  ``-v`` log line), at the start of bundle adjustment, during export and
  between the two renames of the output swap (the latter three from inside,
  deterministic); then ``panosfm run --resume``. Reported: what the output
  directory held after the kill, whether the rerun succeeded, left nothing
  behind, which stages it reused, and whether its result equals an
  uninterrupted run's.
* ``relations``: image-free problems (``synth.problem.make_problem``) with
  10, 20, 30 % of wrong coplanarities appended (random track pairs with a
  plausible normal whose true lines are >= 10 cm apart), solved by
  ``linear.solve_linear`` then ``graph.bundle_adjust`` with the default
  config (robust kernel + relation rejection) and, for contrast, without
  either. Metrics after a similarity (Umeyama) alignment of the registered
  centres: median centre error in % of the trajectory diameter, median
  rotation error (deg), median line-to-surface distance (m); the
  degradation is relative to the clean problem's value.
* ``hard``: synthetic captures with heavy IMU drift (10 deg), motion blur,
  a partial (180 deg) turn and little texture, reconstructed by the
  pipeline: registered frames, lines, warnings, errors, the consistency of
  the written result (images.txt entries == summary count, nothing
  non-finite written) and, where possible, ``evaluate_reconstruction``.

    python tools/bench_reliability.py --work /tmp/rel --frames 120
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

STAGES = ("detect", "preprocess", "track", "normals", "relations", "linear", "bundle_adjust")
# bad-input and kill runs: no recording, and normals that do not depend on models/normals.onnx (which may
# change between two runs while a model is being trained; the cache key does not cover the file)
PIN = ["--no-rerun", "--normals", "orientation-map"]


# --------------------------------------------------------------------------- helpers


def snapshot(d: Path, skip: tuple[str, ...] = ("cache",)) -> dict[str, str]:
    """Returns {relative path: sha1} of the files under ``d``, top-level entries in ``skip`` left out."""
    if not d.exists():
        return {}
    return {str(p.relative_to(d)): hashlib.sha1(p.read_bytes()).hexdigest() for p in sorted(d.rglob("*"))
            if p.is_file() and p.relative_to(d).parts[0] not in skip}


def reap(proc: subprocess.Popen, timeout: float = 600, kill_on: str | None = None,
         kill_delay_s: float = 0.3) -> tuple[int, str]:
    """Returns (exit status, stderr) of ``proc`` (started in its own session); its process group is killed after.

    ``kill_on``: SIGKILL the run's process group ``kill_delay_s`` after a stderr line containing it.
    Shared with tests/test_reliability.py.
    """
    lines = []
    try:
        if kill_on:
            for line in proc.stderr:
                lines.append(line)
                if kill_on in line:
                    time.sleep(kill_delay_s)
                    os.killpg(proc.pid, signal.SIGKILL)
                    break
        _, err = proc.communicate(timeout=timeout)
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
    return proc.returncode, "".join(lines) + (err or "")


def run_cli(args: list[str], script: str | None = None, extra: list[str] = (), timeout: float = 600,
            kill_on: str | None = None, kill_delay_s: float = 0.3) -> tuple[int, str]:
    """Returns (exit status, stderr) of ``panosfm ARGS`` in a new session (:func:`reap`)."""
    cmd = [sys.executable, "-c", script, *extra, *args] if script else [sys.executable, "-m", "panosfm_graph", *args]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    return reap(proc, timeout, kill_on, kill_delay_s)


def leftovers(out: Path) -> list[str]:
    return sorted(p.name for p in out.parent.glob(f".{out.name}.*"))


def result_check(out: Path) -> dict:
    """Returns the consistency of a written result: images == summary count, finite poses and lines."""
    from panosfm_graph.export import read_colmap_text, read_lines_ply

    s = json.loads((out / "summary.json").read_text())
    model = read_colmap_text(out / "sparse")
    ends, _, _ = read_lines_ply(out / "lines.ply")
    text = ((out / "sparse" / "images.txt").read_text() + (out / "sparse" / "points3D.txt").read_text()).lower()
    finite = all(np.all(np.isfinite(v["R_wc"])) and np.all(np.isfinite(v["center"])) for v in model["images"].values())
    return {"registered": s["frames"]["registered"], "total": s["frames"]["total"], "lines": s["lines"],
            "images_match_summary": len(model["images"]) == s["frames"]["registered"],
            "lines_match_summary": len(ends) == s["lines"],
            "nothing_nonfinite": bool(finite and np.all(np.isfinite(ends)) and "nan" not in text and "inf" not in text),
            "warnings": s.get("warnings", []), "resumed_stages": s.get("resumed_stages", [])}


def table(rows: list[dict], cols: list[str]) -> str:
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        if isinstance(v, (list, tuple)):
            return ",".join(str(x) for x in v) or "-"
        return str(v)

    cells = [[fmt(r.get(c, "")) for c in cols] for r in rows]
    width = [max(len(c), *(len(x[i]) for x in cells)) if cells else len(c) for i, c in enumerate(cols)]
    line = lambda xs: "  ".join(x.ljust(w) for x, w in zip(xs, width))
    return "\n".join([line(cols), line(["-" * w for w in width])] + [line(x) for x in cells])


# --------------------------------------------------------------------------- bad input


def _rows(p: Path) -> list[str]:
    return p.read_text().splitlines()


def _truncate(frame: int, frac: float):
    def f(cap: Path) -> str:
        p = sorted((cap / "frames").iterdir())[frame]
        b = p.read_bytes()
        p.write_bytes(b[: int(len(b) * frac)])
        return p.name
    return f


def _to_jpeg_truncated(cap: Path) -> str:
    rows = _rows(cap / "frames.csv")
    for p in sorted((cap / "frames").iterdir()):
        cv2.imwrite(str(p.with_suffix(".jpg")), cv2.imread(str(p)))
        p.unlink()
    (cap / "frames.csv").write_text("\n".join([rows[0]] + [r.replace(".png", ".jpg") for r in rows[1:]]) + "\n")
    return _truncate(len(rows) // 2, 0.7)(cap)


def _corrupt_inside(cap: Path) -> str:
    p = sorted((cap / "frames").iterdir())[len(list((cap / "frames").iterdir())) * 2 // 3]
    b = bytearray(p.read_bytes())
    b[200:-100:97] = bytes(x ^ 0x55 for x in b[200:-100:97])
    p.write_bytes(bytes(b))
    return p.name


def _empty_frame(cap: Path) -> str:
    p = sorted((cap / "frames").iterdir())[5]
    p.write_bytes(b"")
    return p.name


def _video_ends_early(cap: Path) -> str:
    frames = sorted((cap / "frames").iterdir())
    img = cv2.imread(str(frames[0]))
    w = cv2.VideoWriter(str(cap / "video.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, img.shape[1::-1])
    for p in frames[:-6]:
        w.write(cv2.imread(str(p)))
    w.release()
    shutil.rmtree(cap / "frames")
    rows = _rows(cap / "frames.csv")
    (cap / "frames.csv").write_text("\n".join([rows[0]] + [f"{k:06d},{r.split(',')[1]}" for k, r in enumerate(rows[1:])]) + "\n")
    return "frames.csv"


def _dup_timestamp(cap: Path) -> str:
    rows = _rows(cap / "frames.csv")
    rows[11] = rows[11].split(",")[0] + "," + rows[10].split(",")[1]
    (cap / "frames.csv").write_text("\n".join(rows) + "\n")
    return "frames.csv"


def _drop_frames(cap: Path) -> str:
    rows = _rows(cap / "frames.csv")
    n = len(rows) - 1
    for r in rows[n // 2: n // 2 + 8]:
        (cap / "frames" / r.split(",")[0]).unlink()
    (cap / "frames.csv").write_text("\n".join(rows[: n // 2] + rows[n // 2 + 8:]) + "\n")
    return str(cap.name)


def _slow_imu(cap: Path) -> str:
    rows = _rows(cap / "imu.csv")
    t = np.array([float(r.split(",")[0]) for r in rows[1:]])
    keep = np.unique(np.concatenate([[0], np.flatnonzero(np.diff(np.floor(t / 0.5)) > 0) + 1, [len(t) - 1]]))
    (cap / "imu.csv").write_text("\n".join([rows[0]] + [rows[1 + k] for k in keep]) + "\n")
    return "imu.csv"


def _camera(**changes):
    def f(cap: Path) -> str:
        cam = json.loads((cap / "camera.json").read_text())
        fx, fy, cx, cy = cam["params"]
        v = {"fx": fx, "fy": fy, "cx": cx, "cy": cy}
        v.update({k: (val(cam) if callable(val) else val) for k, val in changes.items()})
        cam["params"] = [v["fx"], v["fy"], v["cx"], v["cy"]]
        (cap / "camera.json").write_text(json.dumps(cam))
        return "camera.json"
    return f


def _blank(cap: Path) -> str:
    for p in (cap / "frames").iterdir():
        img = cv2.imread(str(p))
        cv2.imwrite(str(p), np.full_like(img, 128))
    return ""


def _short_turn(cap: Path) -> str:
    from panosfm_graph.synth import synthesize

    shutil.rmtree(cap)
    synthesize(cap, n_frames=30, size=(320, 180), turn_deg=60.0, gt_maps=False)
    return "imu.csv"


BAD_INPUT = [
    ("truncated PNG (frame 37)", _truncate(37, 0.5)),
    ("truncated JPEG (middle frame)", _to_jpeg_truncated),
    ("empty image file", _empty_frame),
    ("PNG damaged inside", _corrupt_inside),
    ("video ends 6 frames early", _video_ends_early),
    ("duplicate timestamps", _dup_timestamp),
    ("8 dropped frames (gap)", _drop_frames),
    ("IMU at 2 Hz", _slow_imu),
    ("principal point outside image", _camera(cx=lambda c: c["width"] + 40.0)),
    ("focal 0.1 x width", _camera(fx=lambda c: 0.1 * c["width"], fy=lambda c: 0.1 * c["width"])),
    ("focal 12 x width", _camera(fx=lambda c: 12.0 * c["width"], fy=lambda c: 12.0 * c["width"])),
    ("60 deg turn", _short_turn),
    ("blank frames (no lines)", _blank),
]


def bench_bad_input(work: Path, cap: Path, previous: Path) -> list[dict]:
    rows = []
    for name, mutate in BAD_INPUT:
        d = work / "bad" / name.replace(" ", "_").replace("(", "").replace(")", "")
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
        c = shutil.copytree(cap, d / "capture", ignore=shutil.ignore_patterns("ground_truth"))
        out = shutil.copytree(previous, d / "out")
        need = mutate(c)
        before = snapshot(out)
        t0 = time.perf_counter()
        code, err = run_cli(["run", str(c), str(out), *PIN])
        lines = [ln for ln in err.strip().splitlines() if ln.strip()]
        ours = [ln for ln in lines if ln.startswith("panosfm: error:")]
        warns = [ln for ln in lines if ln.startswith("WARNING panosfm.capture")]
        rows.append({"input": name, "exit": code, "seconds": round(time.perf_counter() - t0, 2),
                     "stderr_lines": len(lines), "message": (ours or warns or lines or [""])[-1][:150],
                     "names_file": bool(need) and any(need in ln for ln in ours + warns),
                     "traceback": "Traceback" in err, "data_lost": snapshot(out) != before and code != 0,
                     "leftovers": leftovers(out)})
    return rows


# --------------------------------------------------------------------------- kills

KILLER = r"""
import os, signal, sys
import panosfm_graph.export as export, panosfm_graph.graph as graph
where = sys.argv[1]
def die(*a, **k):
    os.kill(os.getpid(), signal.SIGKILL)
if where == "bundle_adjust":
    graph.bundle_adjust = die
elif where == "export":
    export.write_lines_ply = die
elif where == "swap":
    real = os.rename
    def rename(src, dst, *a, **k):
        if ".tmp-" in os.path.basename(str(src)):
            die()
        return real(src, dst, *a, **k)
    os.rename = rename
from panosfm_graph.cli import main
sys.exit(main(sys.argv[2:]))
"""


def bench_kill(work: Path, cap: Path, previous: Path) -> list[dict]:
    rows = []
    for moment in ("detect", "bundle_adjust", "export", "swap"):
        out = work / "kill" / moment / "out"
        shutil.rmtree(out.parent, ignore_errors=True)
        out.parent.mkdir(parents=True)
        shutil.copytree(previous, out)
        shutil.rmtree(out / "cache")
        before = snapshot(out)
        if moment == "detect":
            code, _ = run_cli(["-v", "run", str(cap), str(out), *PIN], kill_on="panosfm: detect ...")
        else:
            code, _ = run_cli(["run", str(cap), str(out), *PIN], script=KILLER, extra=[moment])
        after = snapshot(out)
        backup = out.parent / f".{out.name}.backup"
        state = ("previous result intact" if after == before else
                 "previous result in .backup" if not out.exists() and snapshot(backup) == before else
                 "CHANGED")
        left = leftovers(out)
        code2, err2 = run_cli(["run", str(cap), str(out), "--resume", *PIN])
        rec = {"kill at": moment, "killed": code == -signal.SIGKILL, "after kill": state,
               "leftovers after kill": left, "rerun exit": code2, "leftovers after rerun": leftovers(out)}
        if code2 == 0:
            chk = result_check(out)
            rec["resumed"] = chk["resumed_stages"]
            rec["consistent"] = chk["images_match_summary"] and chk["lines_match_summary"] and chk["nothing_nonfinite"]
            rec["equals uninterrupted"] = all((out / n).read_bytes() == (previous / n).read_bytes()
                                              for n in ("sparse/images.txt", "sparse/points3D.txt", "lines.ply"))
        else:
            rec["error"] = err2.strip().splitlines()[-1:]
        rows.append(rec)
    return rows


# --------------------------------------------------------------------------- wrong relations


def _metrics(p, sol) -> dict:
    from panosfm_graph.evaluate import rotation_angle_deg, umeyama

    reg = sol.registered & np.all(np.isfinite(sol.centers), axis=1)
    gt = p.gt_centers
    diam = float(np.max(np.linalg.norm(gt[:, None] - gt[None], axis=2)))
    if reg.sum() < 3:
        return {"registered": float(reg.mean()), "center_pct": float("nan"), "rot_deg": float("nan"),
                "line_surface_m": float("nan")}
    s, R, t = umeyama(sol.centers[reg], gt[reg])
    err = np.linalg.norm(s * sol.centers[reg] @ R.T + t - gt[reg], axis=1)
    rot = rotation_angle_deg(p.gt_R_wc[reg], sol.R_wc[reg])
    ep = sol.lines.endpoints[sol.lines.valid]
    pts = np.concatenate([ep[:, :3], ep[:, 3:], 0.5 * (ep[:, :3] + ep[:, 3:])])
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    d = p.scene.distance_to_surfaces(s * pts @ R.T + t) if len(pts) else np.array([np.nan])
    return {"registered": float(reg.mean()), "center_pct": float(100 * np.median(err) / diam),
            "rot_deg": float(np.median(rot)), "line_surface_m": float(np.median(d))}


def bench_relations(frames: int, ratios=(0.0, 0.1, 0.2, 0.3), scenes=("living", "office"), seed: int = 0) -> list[dict]:
    from panosfm_graph.config import GraphConfig, LinearConfig
    from panosfm_graph.graph import bundle_adjust
    from panosfm_graph.linear import solve_linear
    from panosfm_graph.synth.problem import make_problem

    variants = {"default (robust + reject)": (LinearConfig(), GraphConfig()),
                "robust linear (IRLS 3)": (LinearConfig(robust_iterations=3), GraphConfig()),
                "plain LS, no rejection": (LinearConfig(), GraphConfig(robust="none", reject_sigma=1e12))}
    rows = []
    for scene in scenes:
        clean = {}
        for ratio in ratios:
            p = make_problem(scene, frames, size=(480, 270), seed=seed, pixel_noise_px=0.5, rot_noise_deg=0.3,
                             false_relation_ratio=ratio)
            n_false = int(np.sum(~p.relation_true)) if p.relation_true is not None else 0
            for name, (lcfg, gcfg) in variants.items():
                t0 = time.perf_counter()
                rec = {"scene": scene, "false %": int(round(100 * ratio)), "variant": name,
                       "relations": int(p.relations.n) if hasattr(p.relations, "n") else len(p.relations.kind),
                       "false": n_false}
                try:
                    lin = solve_linear(p.preprocessed, p.tracks, p.relations, p.camera, lcfg)
                    sol = bundle_adjust(p.preprocessed, p.tracks, p.relations, lin, gcfg)
                    m = _metrics(p, sol)
                    rej = np.asarray(sol.residuals.get("rejected_relations", []), int)
                    rec["rejected (false)"] = f"{len(rej)} ({int(np.sum(~p.relation_true[rej])) if len(rej) and p.relation_true is not None else 0})"
                    rec.update(m)
                    rec["linear center_pct"] = _metrics(p, lin)["center_pct"]
                except Exception as e:  # a solver failure is a result of the benchmark, not its end
                    rec["error"] = f"{type(e).__name__}: {str(e).strip().splitlines()[0][:80]}"
                rec["seconds"] = round(time.perf_counter() - t0, 2)
                if ratio == 0:
                    clean[name] = rec
                base = clean.get(name, {})
                for k in ("center_pct", "line_surface_m"):
                    if k in rec and base.get(k):
                        rec[f"{k} vs clean"] = f"{100 * (rec[k] / base[k] - 1):+.0f} %"
                rows.append(rec)
    return rows


# --------------------------------------------------------------------------- hard captures

HARD = [
    ("clean", {}),
    ("IMU drift 10 deg", {"imu_drift_deg": 10.0}),
    ("motion blur 6 px", {"blur": 6.0}),
    ("partial turn 180 deg", {"turn_deg": 180.0}),
    ("little texture (0.1)", {"texture": 0.1}),
]


def bench_hard(work: Path, frames: int, size: tuple[int, int]) -> list[dict]:
    from panosfm_graph.evaluate import evaluate_reconstruction
    from panosfm_graph.synth import synthesize

    rows = []
    for name, kw in HARD:
        d = work / "hard" / name.split(" ")[0]
        shutil.rmtree(d, ignore_errors=True)
        cap = synthesize(d / "capture", n_frames=frames, size=size, gt_maps=False, **kw)
        t0 = time.perf_counter()
        code, err = run_cli(["run", str(cap), str(d / "out"), "--no-rerun"])
        rec = {"capture": name, "exit": code, "seconds": round(time.perf_counter() - t0, 1)}
        if code == 0:
            chk = result_check(d / "out")
            rec.update({k: chk[k] for k in ("registered", "total", "lines", "images_match_summary",
                                             "nothing_nonfinite")})
            rec["warnings"] = len(chk["warnings"])
            try:
                m = evaluate_reconstruction(cap, d / "out")
                rec["center_err_rel"] = m.get("center_error_rel", {}).get("median") if isinstance(
                    m.get("center_error_rel"), dict) else m.get("center_error_rel")
            except Exception as e:
                rec["eval"] = f"{type(e).__name__}: {str(e)[:60]}"
        else:
            rec["error"] = (err.strip().splitlines() or [""])[-1][:120]
        rows.append(rec)
    return rows


# --------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="/tmp/panosfm_reliability", help="scratch directory (replaced)")
    ap.add_argument("--frames", type=int, default=120, help="frames of the synthetic captures")
    ap.add_argument("--size", type=int, nargs=2, default=[320, 180])
    ap.add_argument("--problem-frames", type=int, default=120, help="frames of the image-free relation problems")
    ap.add_argument("--sections", nargs="+", default=["bad_input", "kill", "relations", "hard"])
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    report: dict = {"frames": args.frames, "size": args.size}
    if {"bad_input", "kill"} & set(args.sections):
        from panosfm_graph.synth import synthesize

        cap = work / "capture"
        shutil.rmtree(cap, ignore_errors=True)
        synthesize(cap, n_frames=args.frames, size=tuple(args.size), gt_maps=False)
        previous = work / "previous"
        shutil.rmtree(previous, ignore_errors=True)
        code, err = run_cli(["run", str(cap), str(previous), *PIN])
        if code != 0:
            print(err, file=sys.stderr)
            return 1
    if "bad_input" in args.sections:
        rows = report["bad_input"] = bench_bad_input(work, cap, previous)
        print("\n== bad input (a previous result in the output directory) ==")
        print(table(rows, ["input", "exit", "stderr_lines", "names_file", "traceback", "data_lost", "message"]))
    if "kill" in args.sections:
        rows = report["kill"] = bench_kill(work, cap, previous)
        print("\n== SIGKILL, then `run --resume` ==")
        print(table(rows, ["kill at", "killed", "after kill", "leftovers after kill", "rerun exit",
                           "leftovers after rerun", "resumed", "consistent", "equals uninterrupted"]))
    if "relations" in args.sections:
        rows = report["relations"] = bench_relations(args.problem_frames)
        print("\n== wrong coplanarities (image-free problems, linear + BA) ==")
        print(table(rows, ["scene", "false %", "variant", "relations", "false", "rejected (false)", "registered",
                           "linear center_pct", "center_pct", "center_pct vs clean", "rot_deg", "line_surface_m",
                           "line_surface_m vs clean", "seconds", "error"]))
    if "hard" in args.sections:
        rows = report["hard"] = bench_hard(work, args.frames, tuple(args.size))
        print("\n== hard captures (pipeline) ==")
        print(table(rows, ["capture", "exit", "registered", "total", "lines", "warnings", "images_match_summary",
                           "nothing_nonfinite", "center_err_rel", "seconds", "error"]))
    path = Path(args.json) if args.json else work / "reliability.json"
    path.write_text(json.dumps(report, indent=1, default=str))
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
