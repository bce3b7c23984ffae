"""Calibrates the reliability check's stds (``verify.*``) against the truth of benchmark captures (issue #63).

    python tools/bench.py --scenes random --seeds 0-49 --peer none --out bench-random --photo-textures ../shared/real
    python tools/calibrate_sigma.py bench-random [--json calib.json]          # fit on these runs
    python tools/calibrate_sigma.py bench-heldout --use calib.json           # check the fit on other runs

Reads each run's ``summary.json`` (``frames``: source, ``model_sigma_rel``, ``nearest_gap_rel``,
``evidence_gap_rel``) and its capture's ground truth, and fits :mod:`panosfm_graph.graph.reliability`'s constants:

* ``model_ratio``, ``gap_ratio`` and ``other_ratio``: the median of a frame's centre error over each evidence (the
  motion model's marginal, the distance to the nearest solution, to the solution independent of the frame's own
  source), so that each becomes a median predictor of the error;
* ``sigma_scale``: so that 3 stds of the geometric mean of the scaled evidences cover 95 % of the frames' errors
  (pooled over the runs).

Then prints, with those constants (or ``--use``'s): the share of frames beyond 3 stds per source, the share of
frames whose std exceeds ``verify.flag_sigma_rel`` (doubtful), the runs that would call themselves doubtful
(and how many of those have every frame accurate: false alarms), and the runs with a confident frame that is
wrong. Errors are those of ``panosfm eval``: centre over the true trajectory's diameter after the orientations'
rotation and the centres' scale and shift.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np


def _frames(bench: Path) -> list[dict]:
    """Returns per run {name, source, gap, model, err, rot} arrays over its registered frames."""
    from panosfm_graph.capture import load_capture
    from panosfm_graph.evaluate import frame_errors
    from panosfm_graph.export import poses_for_frames, read_colmap_text
    from scipy.spatial.distance import pdist

    record = json.loads((bench / "bench.json").read_text())
    out = []
    for name, entry in record["scenes"].items():
        r = entry.get("panosfm") or {}
        if "error" in r or "metrics" not in r:
            continue
        rec, cap = Path(r["metrics"]["reconstruction"]), Path(r["metrics"]["capture"])
        summary = json.loads((rec / "summary.json").read_text())
        fr = summary["frames"]
        if "evidence_gap_rel" not in fr:
            print(f"{name}: no evidence in summary.json (a run before the reliability check): skipped", file=sys.stderr)
            continue
        c = load_capture(cap)
        gt = c.ground_truth
        R, C, reg = poses_for_frames(read_colmap_text(rec / "sparse"), c.frame_names)
        use = np.flatnonzero(reg)
        if len(use) < 3 or len(fr["sigma_rel"]) != c.n_frames:
            continue
        diam = float(pdist(gt.centers).max())
        err, rot = frame_errors(C[use], gt.centers[use], R[use], gt.R_wc[use], diam)
        f = lambda key: np.array([np.nan if fr[key][i] is None else fr[key][i] for i in use], float)  # noqa: E731
        out.append({"name": name, "source": np.array([fr["source"][i] or "lines" for i in use]),
                    "gap": f("nearest_gap_rel"), "other": f("evidence_gap_rel"), "model": f("model_sigma_rel"),
                    "err": err, "rot": rot})
    return out


EVIDENCE = (("model", "model_ratio"), ("gap", "gap_ratio"), ("other", "other_ratio"))


def sigma_of(run: dict, cfg) -> np.ndarray:
    """Returns the run's frames' stds with the constants of ``cfg`` (as graph.reliability.honest_sigma)."""
    logs = np.stack([np.log(getattr(cfg, ratio) * np.where(run[key] > 0, run[key], np.nan)) for key, ratio in EVIDENCE])
    have = np.isfinite(logs)
    comb = np.exp(np.nansum(np.where(have, logs, 0.0), axis=0) / np.maximum(have.sum(axis=0), 1))
    comb = np.where(have.any(axis=0), comb, cfg.fallback_sigma_rel / cfg.sigma_scale)
    return np.maximum(cfg.sigma_scale * comb, cfg.floor_sigma_rel)


def fit(runs: list[dict], cfg):
    """Returns ``cfg`` with model_ratio, gap_ratio and sigma_scale fitted on ``runs`` (module docstring)."""
    err = np.concatenate([r["err"] for r in runs])
    ratios = {}
    for key, ratio in EVIDENCE:
        v = np.concatenate([r[key] for r in runs])
        ok = np.isfinite(v) & (v > 0)
        ratios[ratio] = round(float(np.median(err[ok] / v[ok])), 3) if ok.any() else 1.0
    cfg = replace(cfg, **ratios, sigma_scale=1.0)
    z = np.concatenate([r["err"] / sigma_of(r, cfg) for r in runs])
    return replace(cfg, sigma_scale=round(float(np.percentile(z, 95)) / 3.0, 3))


def report(runs: list[dict], cfg) -> dict:
    """Returns the calibration's figures over ``runs`` with ``cfg`` (module docstring)."""
    src = np.concatenate([r["source"] for r in runs])
    err = np.concatenate([r["err"] for r in runs])
    acc = np.concatenate([(r["err"] <= 0.05) & (r["rot"] <= 1.0) for r in runs])
    sig = np.concatenate([sigma_of(r, cfg) for r in runs])
    beyond = {s: {"frames": int((src == s).sum()), "beyond_3sigma": float(np.mean(err[src == s] > 3 * sig[src == s]))}
              for s in sorted(set(src))}
    doubtful, false_alarm, wrong = [], [], []
    for r in runs:
        s = sigma_of(r, cfg)
        a = (r["err"] <= 0.05) & (r["rot"] <= 1.0)
        flagged = s > cfg.flag_sigma_rel
        if flagged.any():
            doubtful.append(r["name"])
            if a.all():
                false_alarm.append(r["name"])
        confident = ~flagged
        if confident.any() and np.mean(a[confident]) < 0.99:
            wrong.append((r["name"], round(float(np.mean(a[confident])), 3)))
    return {"runs": len(runs), "frames": int(len(err)), "beyond_3sigma": float(np.mean(err > 3 * sig)),
            "by_source": beyond, "sigma_median": float(np.median(sig)), "accurate": float(np.mean(acc)),
            "flagged": float(np.mean(sig > cfg.flag_sigma_rel)), "doubtful_runs": len(doubtful),
            "doubtful_runs_all_accurate": len(false_alarm), "runs_with_confident_wrong": wrong}


def main(argv: list[str] | None = None) -> int:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from panosfm_graph.config import VerifyConfig

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("bench", nargs="+", help="benchmark output folders (bench.json, runs/, captures/)")
    p.add_argument("--use", default=None, metavar="JSON", help="check these constants instead of fitting")
    p.add_argument("--json", default=None, metavar="FILE", help="write the constants and figures here")
    args = p.parse_args(argv)
    runs = [r for b in args.bench for r in _frames(Path(b))]
    if not runs:
        print("no run with the reliability check's evidence", file=sys.stderr)
        return 2
    cfg = VerifyConfig()
    if args.use:
        cfg = replace(cfg, **json.loads(Path(args.use).read_text())["constants"])
    else:
        cfg = fit(runs, cfg)
    consts = {k: getattr(cfg, k) for k in ("model_ratio", "gap_ratio", "other_ratio", "sigma_scale")}
    figures = report(runs, cfg)
    print(json.dumps({"constants": consts, **figures}, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps({"constants": consts, **figures}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
