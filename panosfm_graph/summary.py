"""The run's ``summary.json`` (capture-format.md): what the pipeline's result says of itself.

:func:`build_summary` gathers the frames registered and why the others are not, the relations kept, how the scale
and the focal length were set, every stage's residuals and seconds, peak memory, the config and versions.
"""
from __future__ import annotations

import dataclasses
import platform
import resource
import time
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from . import __version__
from .config import Config
from .data import RELATION_NAMES, Capture, Relations, Segments, Solution

if TYPE_CHECKING:
    from .pipeline import RunResult


def peak_memory_mb() -> float:
    """Returns this process's peak resident memory in MB (children included)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, kids) / 1024.0



def unregistered_why(result: RunResult, n_frames: int) -> list[str]:
    """Returns, per frame, why it is not registered ("registered" where it is), in words.

    The linear solve's registration criteria (:func:`linear.register_frames`) say why it left a
    frame out; a frame it kept that the bundle adjustment dropped could not be determined there.
    """
    from .linear import REASON_BUNDLE_ADJUST, UNREGISTERED_REASONS

    codes = np.ones(n_frames, np.int64)  # no linear solve: as if no line
    linear = _linear_residuals(result)
    if linear is not None and "unregistered_reason_codes" in linear:
        codes = np.asarray(linear["unregistered_reason_codes"], np.int64)
    sol = result.solution
    if sol is not None and result.linear is not None:
        codes = np.where((codes == 0) & ~sol.registered, REASON_BUNDLE_ADJUST, codes)  # 0: the linear solve's
    why = [UNREGISTERED_REASONS[c] for c in codes]
    if sol is None:
        return why
    sigma = sol.residuals.get("frame_sigma_rel") or [None] * n_frames
    bound = (sol.residuals.get("motion_model") or {}).get("max_sigma_rel")
    checked = sol.residuals.get("frame_doubtful_why") or [None] * n_frames  # graph.reliability's left-out frames
    for i in range(n_frames):
        if sol.registered[i]:
            why[i] = UNREGISTERED_REASONS[0]
        elif checked[i]:
            why[i] = checked[i]
        elif sigma[i] is not None and bound is not None:
            why[i] = f"{why[i]}; the motion model's std is over {100 * bound:.1f} % of the spin's diameter"
    return why


def frame_status(result: RunResult, n_frames: int) -> list[str]:
    """Returns, per frame, what the rerun recording's ``status`` log says: "registered" with its std (and "doubtful:"
    with why, graph.reliability), or why it is not registered (:func:`unregistered_why`)."""
    why = unregistered_why(result, n_frames)
    sol = result.solution
    if sol is None:
        return why
    sig = sol.residuals.get("frame_sigma_rel") or [None] * n_frames
    doubt = sol.residuals.get("frame_doubtful_why") or [None] * n_frames
    out = []
    for i in range(n_frames):
        if not sol.registered[i]:
            out.append(why[i])
            continue
        text = "registered" + (f" (std {100 * sig[i]:.2f} % of the spin's diameter)" if sig[i] is not None else "")
        out.append(text + (f"; doubtful: {doubt[i]}" if doubt[i] else ""))
    return out


def _linear_residuals(result: RunResult) -> dict | None:
    """Returns the residuals of the linear solve the result rests on (the steady one where the auto style chose it)."""
    sol = result.solution
    if sol is not None and isinstance(sol.residuals, dict) and "linear_steady" in sol.residuals:
        return sol.residuals["linear_steady"]
    return result.linear.residuals if result.linear is not None else None


def build_summary(capture: Capture, segments: Segments, result: RunResult, config: Config,
             timings: dict[str, float], resumed: list[str], t_start: float) -> dict:
    """Returns ``summary.json``'s content for a run (capture-format.md): frames, why each unregistered one is,
    relations, scale, focal length, residuals, seconds, memory, the config and versions."""
    from .export import package_versions

    sol = result.solution
    pre = result.preprocessed
    n = capture.n_frames
    registered = int(sol.registered.sum()) if sol is not None else 0
    why = unregistered_why(result, n)
    # floor lines holding a metric scale: few of them (one is common) make it fragile (README)
    linear_res = _linear_residuals(result)
    n_floor = int(linear_res.get("floor_count", 0) or 0) if linear_res is not None else 0
    if linear_res is not None:
        linear_res = dict(linear_res)
        linear_res.pop("unregistered_reason_codes", None)
    summary: dict[str, Any] = {
        "panosfm_version": __version__,
        "capture": str(Path(capture.root).resolve()),
        "frames": {"total": n, "registered": registered, "registered_ratio": registered / max(n, 1),
                   "unregistered": [capture.frame_names[i] for i in np.flatnonzero(~sol.registered)]
                   if sol is not None else list(capture.frame_names),
                   # why each unregistered frame is (aligned with "unregistered"), and how many per reason
                   "unregistered_why": [why[i] for i in np.flatnonzero(~sol.registered)] if sol is not None else [],
                   "unregistered_reasons": dict(Counter(why[i] for i in np.flatnonzero(~sol.registered)))
                   if sol is not None else {},
                   # how each frame's position was obtained ("lines", "steady circle", "motion model", "shared
                   # centre", null: none) and, for frames the motion model placed or tried, its centre's largest std
                   # over the spin's diameter
                   **_frame_sources(sol, n, bool(((result.linear.residuals if result.linear is not None else {})
                                                   .get("zero_baseline") or {}).get("detected")),
                                    run_doubt=(focal_reason(result.focal_check) if result.focal_check is not None
                                               and not result.focal_check["agrees"] else None))},
        "segments": {"total": segments.n,
                     "manhattan": int(np.sum(pre.labels >= 0)) if pre is not None else 0},
        "tracks": result.tracks.n if result.tracks is not None else 0,
        "lines": int(sol.lines.valid.sum()) if sol is not None else 0,
        "relations": (result.relations.counts() if result.relations is not None
                      else {k: 0 for k in RELATION_NAMES}),
        "relations_kept": _relations_kept(result.relations, sol),
        "metric": bool(sol.metric) if sol is not None else False,
        "scale": (_scale_text(config.linear.camera_height_m, n_floor, sol.residuals)
                  if sol is not None and sol.metric else _arbitrary_scale_text(sol, config)),
        # the focal length: given by camera.json, or estimated from the Manhattan vanishing points (lines/focal.py);
        # focal_px is the one the outputs use (the bundle adjustment may refine it)
        "focal": _focal_summary(capture, result, sol),
        # the parallax test (linear/baseline.py): detected -> one shared centre, no translation solved
        "zero_baseline": (result.linear.residuals.get("zero_baseline") if result.linear is not None else None),
        "spin_style": (sol.residuals.get("spin_style") if sol is not None and sol is not result.linear else None),
        # the run checked against its independent solutions (graph.reliability): "trusted", or "doubtful" and why
        "verdict": verdict(sol, result.focal_check),
        "residuals": {"linear": linear_res,
                      "bundle_adjust": ({k: v for k, v in sol.residuals.items()
                                         if k not in ("linear_steady", "frame_source", "frame_sigma_rel",
                                                      "frame_doubtful", "frame_doubtful_why", "frame_gap_rel",
                                                      "frame_other_gap_rel", "frame_model_sigma_rel")}
                                        if sol is not None and sol is not result.linear else None)},
        "seconds": {k: round(v, 3) for k, v in timings.items()},
        "resumed_stages": resumed,
        "peak_memory_mb": round(peak_memory_mb(), 1),
        "config": config.to_dict(),
        "versions": {"python": platform.python_version(), **package_versions()},
    }
    if result.batches:
        summary["incremental_batches"] = [int(b.registered.sum()) for b in result.batches]
        summary["incremental_batch_seconds"] = [round(float(b.residuals.get("batch_seconds", 0.0)), 3)
                                                for b in result.batches]
        if "stage_seconds" in result.batches[0].residuals:  # streamed (stream.py): each batch's seconds per stage;
            # batch seconds are latencies: from the batch's last frame read to its estimate
            summary["incremental_stage_seconds"] = [b.residuals["stage_seconds"] for b in result.batches]
            lat = summary["incremental_batch_seconds"]
            summary["incremental_latency_seconds"] = {"median": round(float(np.median(lat)), 3), "max": max(lat)}
    summary["seconds"]["total"] = round(time.perf_counter() - t_start, 3)
    return summary


def _frame_sources(sol: Solution | None, n: int, zero_baseline: bool = False, run_doubt: str | None = None
                   ) -> dict[str, Any]:
    """Returns summary.json's per-frame sources and motion-model stds, and the count per source ("shared centre":
    a zero-baseline spin's frames, every one at the one centre); ``run_doubt``: a reason that makes every registered
    frame doubtful (a focal length the vanishing points contradict)."""
    if sol is None:
        return {"by_source": {}, "source": [None] * n, "sigma_rel": [None] * n}
    fixed = "shared centre" if zero_baseline else "lines"
    src = sol.residuals.get("frame_source") or [fixed if r else None for r in sol.registered]
    sig = sol.residuals.get("frame_sigma_rel") or [None] * n
    r5 = lambda v: None if v is None else round(float(v), 5)  # noqa: E731
    out = {"by_source": dict(Counter(s for s in src if s is not None)), "source": list(src),
           "sigma_rel": [r5(v) for v in sig]}
    if "frame_doubtful" in sol.residuals:  # graph.reliability: every frame checked against independent solutions
        out["doubtful"] = list(sol.residuals["frame_doubtful"])
        out["doubtful_why"] = list(sol.residuals.get("frame_doubtful_why") or [None] * n)
        out["doubtful_count"] = int(sum(out["doubtful"]))
        out["evidence_gap_rel"] = [r5(v) for v in sol.residuals.get("frame_other_gap_rel") or [None] * n]
        out["nearest_gap_rel"] = [r5(v) for v in sol.residuals.get("frame_gap_rel") or [None] * n]
        out["model_sigma_rel"] = [r5(v) for v in sol.residuals.get("frame_model_sigma_rel") or [None] * n]
    if run_doubt is not None:
        why = out.get("doubtful_why") or [None] * n
        out["doubtful"] = [bool(r) for r in sol.registered]
        out["doubtful_why"] = [(f"{w}; {run_doubt}" if w else run_doubt) if r else w for w, r in zip(why, sol.registered)]
        out["doubtful_count"] = int(sum(out["doubtful"]))
    return out


def verdict(sol: Solution | None, focal_check: dict | None = None) -> dict:
    """Returns summary.json's ``verdict``: {"status": "trusted" | "doubtful" | "unchecked", "reasons": [...]}: the
    reliability check's (graph.reliability), doubtful also where camera.json's focal length disagrees with the
    vanishing points' (``focal_check``); "unchecked" where there is no solution or nothing checked it."""
    v = (sol.residuals or {}).get("verify") if sol is not None else None
    reasons = list(v["reasons"]) if v else []
    if focal_check is not None and not focal_check["agrees"]:
        reasons.insert(0, focal_reason(focal_check))
    if not v and not reasons:
        return {"status": "unchecked", "reasons": []}
    return {"status": "doubtful" if reasons else "trusted", "reasons": reasons}


def focal_reason(check: dict) -> str:
    """Returns the verdict's reason for a given focal length the vanishing points contradict."""
    return (f"camera.json's focal length {check['given_px']:.1f} px is {100 * abs(check['off']):.0f} % from the "
            f"vanishing points' {check['estimated_px']:.1f} px")


def _focal_summary(capture: Capture, result: RunResult, sol: Solution | None) -> dict[str, Any]:
    """Returns where the focal length came from and its value (px, and as a horizontal field of view)."""
    from .capture.camera import hfov_deg

    cam = sol.camera if sol is not None else capture.camera
    out: dict[str, Any] = {"given": bool(capture.focal_given), "focal_px": float(cam.K[0, 0]),
                           "hfov_deg": hfov_deg(float(cam.K[0, 0]), cam.width)}
    est = result.focal
    if est is not None:
        out["estimated"] = {"focal_px": est.focal_px, "hfov_deg": est.hfov_deg, "cost": est.cost,
                            "sharpness": est.sharpness, "frames": est.frames, "segments": est.segments}
    if result.focal_stitched is not None:
        out["stitched"] = dataclasses.asdict(result.focal_stitched)
    return out


def _relations_kept(relations: Relations | None, sol: Solution | None) -> dict[str, int]:
    """Returns the count by type of the relations the solution rests on: kept by it (``Solution.relations_kept``:
    the floor the linear solve verified, the BA's verification and rejection) between lines it placed."""
    if relations is None or sol is None:
        return {k: 0 for k in RELATION_NAMES}
    kept = sol.relations_kept if len(sol.relations_kept) == relations.n else np.ones(relations.n, bool)
    return relations.subset(kept & relations.between(sol.lines.valid)).counts()


def _scale_text(camera_height_m: float, n_floor: int, residuals: dict) -> str:
    """Returns how the metric scale was set, for ``summary.json`` and ``panosfm run``."""
    lowered = float(residuals.get("floor_lowered_by", 1.0) or 1.0) if isinstance(residuals, dict) else 1.0
    source = (f"floor lowered to the deepest horizontal line (model scaled by 1/{lowered:.2f})" if lowered > 1.0
              else f"floor from {n_floor} line{'' if n_floor == 1 else 's'}")
    return f"metric (camera height {camera_height_m:.3f} m, {source})"


def _arbitrary_scale_text(sol: Solution | None, config: Config) -> str:
    """Returns ``arbitrary``, with why where the bundle adjustment took the scale from the spin's arm."""
    res = sol.residuals if sol is not None and isinstance(sol.residuals, dict) else {}
    if (res.get("motion_model") or {}).get("anchor_free"):
        return (f"arbitrary (units about metres: no line fixes a frame, the point tracks place them with the spin's "
                f"arm taken as {config.graph.metric_arm_fallback_m:g} m forward)")
    if "scale_from_arm" not in res:
        return "arbitrary"
    lo, hi = config.graph.metric_arm_range_m
    return (f"arbitrary (units about metres: with the floor lines the spin's arm came out "
            f"{res['spin_arm_m_from_floor']:.2f} m, outside {lo:g}-{hi:g} m, so they were likely not the floor; "
            f"the arm taken as {config.graph.metric_arm_fallback_m:g} m)")
