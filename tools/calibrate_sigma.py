"""Calibrates the reliability check's stds (``verify.*``) against the truth of benchmark captures (issue #63).

    python tools/bench.py --scenes random --seeds 0-49 --peer none --out bench-random --photo-textures ../shared/real
    python tools/calibrate_sigma.py bench-random [--json calib.json]          # fit on these runs
    python tools/calibrate_sigma.py bench-heldout --use calib.json           # check the fit on other runs

Reads each run's ``summary.json`` (``frames``: source, ``model_sigma_rel``, ``nearest_gap_rel``,
``evidence_gap_rel``) and its capture's ground truth, and fits :mod:`panosfm_graph.graph.reliability`'s constants:

* ``model_ratio``, ``gap_ratio`` and ``other_ratio``: the median of a frame's centre error over each evidence (the
  motion model's marginal, the distance to the nearest solution, to the solution independent of the frame's own
  source), so that each becomes a median predictor of the error;
* ``lines_scale``, ``points_scale``, ``motion_scale`` (with the steady circle's frames): per source, so that 3 stds
  of the combined evidence (``combine_evidence``: the geometric mean of the scaled
  marginal and nearest distance, never under the scaled independent distance) cover 96 % of the frames' errors
  (pooled over the runs; ``COVER``: a margin under the 5 % the issue allows beyond 3 stds).

Then prints, with those constants (or ``--use``'s): the share of frames beyond 3 stds per source, the share of
frames whose std exceeds ``verify.flag_sigma_rel`` (doubtful; also those beyond ``verify.max_gap_rel`` from the
nearest independent solution, and in a doubtful run those no independent solution places), the runs that would call
themselves doubtful (more than ``verify.max_doubtful_share`` of their frames doubtful; how many of those have every
frame accurate: false alarms; the frames left out of the trusted ones), and the runs whose vouched-for frames are
under 99 % accurate.
The lines and the points far apart (over 3 % of the diameter, the lines not refuted) make every frame of a run
doubtful, as in the pipeline; a focal length the vanishing points contradict is not replayed here. Errors are those of ``panosfm eval``: centre over the true trajectory's diameter after the orientations'
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
        v = (summary.get("residuals", {}).get("bundle_adjust") or {}).get("verify") or {}
        lp, ref = v.get("lines_vs_points_rel"), (v.get("lines_refuted_by_points") or {}).get("refuted")
        out.append({"name": name, "run_doubt": bool(lp is not None and lp > 0.03 and not ref),
                    "source": np.array([fr["source"][i] or "lines" for i in use]),
                    "gap": f("nearest_gap_rel"), "other": f("evidence_gap_rel"), "model": f("model_sigma_rel"),
                    "err": err, "rot": rot})
    return out


EVIDENCE = (("model", "model_ratio"), ("gap", "gap_ratio"), ("other", "other_ratio"))
SOURCES = {"lines_scale": ("lines", "shared centre"), "points_scale": ("points",),
           "motion_scale": ("motion model", "steady circle")}
COVER = 96.0  # percentile of error / std that 3 stds cover on the fitted runs: a margin under the 5 % allowed


def sigma_of(run: dict, cfg) -> np.ndarray:
    """Returns the run's frames' stds with the constants of ``cfg`` (graph.reliability.combine_evidence)."""
    from panosfm_graph.graph.reliability import combine_evidence, source_scale

    return combine_evidence(run["model"], run["gap"], run["other"], cfg, source_scale(list(run["source"]), cfg))


def fit(runs: list[dict], cfg):
    """Returns ``cfg`` with the evidences' ratios and the sources' scales fitted on ``runs`` (module docstring)."""
    err = np.concatenate([r["err"] for r in runs])
    ratios = {}
    for key, ratio in EVIDENCE:
        v = np.concatenate([r[key] for r in runs])
        ok = np.isfinite(v) & (v > 0)
        ratios[ratio] = round(float(np.median(err[ok] / v[ok])), 3) if ok.any() else 1.0
    cfg = replace(cfg, **ratios, lines_scale=1.0, points_scale=1.0, motion_scale=1.0)
    src = np.concatenate([r["source"] for r in runs])
    z = np.concatenate([r["err"] / sigma_of(r, cfg) for r in runs])
    scales = {}
    for field, names in SOURCES.items():
        m = np.isin(src, names)
        scales[field] = round(float(np.percentile(z[m], COVER)) / 3.0, 3) if m.sum() >= 20 else 1.0
    return replace(cfg, **scales)


def report(runs: list[dict], cfg) -> dict:
    """Returns the calibration's figures over ``runs`` with ``cfg`` (module docstring)."""
    src = np.concatenate([r["source"] for r in runs])
    err = np.concatenate([r["err"] for r in runs])
    acc = np.concatenate([(r["err"] <= 0.05) & (r["rot"] <= 1.0) for r in runs])
    sig = np.concatenate([sigma_of(r, cfg) for r in runs])
    beyond = {s: {"frames": int((src == s).sum()), "beyond_3sigma": float(np.mean(err[src == s] > 3 * sig[src == s]))}
              for s in sorted(set(src))}
    doubtful, false_alarm, wrong, dropped = [], [], [], 0
    for r in runs:
        s = sigma_of(r, cfg)
        a = (r["err"] <= 0.05) & (r["rot"] <= 1.0)
        flagged = s > cfg.flag_sigma_rel
        if cfg.max_gap_rel > 0:  # far from every independent solution, whatever the std
            flagged |= r["gap"] > cfg.max_gap_rel
        if r["run_doubt"]:  # a run-level reason (the lines and the points far apart): every frame doubtful
            flagged[:] = True
        if flagged.mean() > cfg.max_doubtful_share:  # graph.reliability's rule: kept, flagged, the run doubtful
            doubtful.append(r["name"])
            if cfg.doubt_unchecked:  # a doubtful run vouches only for frames an independent solution places
                flagged |= ~np.isfinite(r["other"])
            if a.all():
                false_alarm.append(r["name"])
        else:  # a few: left out, the run trusted
            dropped += int(flagged.sum())
        confident = ~flagged
        if confident.any() and np.mean(a[confident]) < 0.99:
            wrong.append((r["name"], round(float(np.mean(a[confident])), 3)))
    return {"runs": len(runs), "frames": int(len(err)), "beyond_3sigma": float(np.mean(err > 3 * sig)),
            "by_source": beyond, "sigma_median": float(np.median(sig)), "accurate": float(np.mean(acc)),
            "flagged": float(np.mean(sig > cfg.flag_sigma_rel)), "left_out_in_trusted_runs": dropped,
            "doubtful_runs": len(doubtful),
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
    consts = {k: getattr(cfg, k) for k in ("model_ratio", "gap_ratio", "other_ratio", *SOURCES)}
    figures = report(runs, cfg)
    print(json.dumps({"constants": consts, **figures}, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps({"constants": consts, **figures}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
