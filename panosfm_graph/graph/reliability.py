"""Every result checked against independent evidence, and a std a user can trust (our addition; issue #63).

The solvers' own stds (the motion model's marginals, :mod:`.motion_model`) say how well a pose is fixed *if the
model is right*: on 50 procedural rooms they claimed a median 0.56 % of the spin's diameter where frames were 1.5
times that off (5 times at the 95th percentile), and the lines' frames had none at all. :func:`verify_solution`
gives every registered frame a std from what can be checked (:func:`combine_evidence`):

* its model std (``frame_sigma_rel``: the motion model's marginal, where it placed the frame);
* its distance to the nearest of the independent solutions of the same capture, after the alignment the
  evaluation uses (:func:`aligned_gap`): the lines' own bundle adjustment (``lines``: its line-fixed frames) and the
  point tracks' own placement (``points``: every frame, made for the check where the pipeline did not); the larger
  of the frame's own distance and its median over ``verify.evidence_window`` of the frames about it;
* its distance to the one independent of the frame's own source (a points-placed frame: the lines'; a line-fixed
  frame: the points'), unless the point tracks refute the lines' solution (:func:`lines_refuted`);

each scaled to a median predictor of the error (``verify.model_ratio``, ``gap_ratio``, ``other_ratio``), the first
two combined by their geometric mean, never under the third (a contradiction is not averaged away), times a scale
per source (``verify.lines_scale``, ``points_scale``, ``motion_scale``) so that 3 stds cover 95 % of the errors;
all calibrated on the procedural rooms against the truth (``tools/calibrate_sigma.py``).

A frame is *doubtful* where its std exceeds ``verify.flag_sigma_rel`` (a third of the 5 % that makes a frame
accurate), it lies more than ``verify.max_gap_rel`` from the nearest independent solution whatever its std (the
geometric mean of the evidence discounts one large gap: two estimates that far apart leave one of them near or past
the 5 %), its rotation lies more than ``verify.max_rotation_gap_deg`` from every other estimate of it (the refined
and the independent solutions'), or it turns more than ``verify.max_imu_gap_deg`` off the IMU's relative rotation to
its neighbours (:func:`imu_gap_deg`); one whose std exceeds ``verify.max_sigma_rel`` is left out. The run is
*doubtful* where more than ``verify.max_doubtful_share`` of its frames are doubtful or the lines' and the points'
solutions lie more than ``verify.max_lines_points_rel`` apart (the lines not refuted); otherwise *trusted*, its few
doubtful frames left out, so that a trusted run vouches for every frame it outputs. A doubtful run vouches only for
frames the solution independent of their own source places (``verify.doubt_unchecked``): the others are doubtful
too. ``verify.strict`` (``--strict``)
keeps only frames the independent solution confirms within 3 x ``flag_sigma_rel``. ``residuals["verify"]`` holds
the verdict, its reasons and every check's figure; ``frame_sigma_rel`` / ``frame_doubtful`` /
``frame_doubtful_why`` and the evidences (``frame_gap_rel``, ``frame_other_gap_rel``, ``frame_model_sigma_rel``)
the per-frame results (summary.json ``frames``).
"""
from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
from scipy.ndimage import median_filter
from scipy.spatial.distance import pdist

from ..config import VerifyConfig
from ..data import PointTracks, Preprocessed, Solution
from ..geometry import rotation_alignment, rotation_angle_deg
from .motion_model import pose_fits_px

log = logging.getLogger("panosfm.graph")

MIN_COMMON = 6  # frames two solutions must share to be compared
TRUSTED, DOUBTFUL = "trusted", "doubtful"


def aligned_gap(c_alt: np.ndarray, R_alt: np.ndarray, c_ref: np.ndarray, R_ref: np.ndarray, common: np.ndarray,
                diameter: float) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((F,) centre distances over ``diameter``, (F,) rotation angles in degrees) between two solutions of
    the same frames (NaN outside ``common``), the alternative moved onto the reference as the evaluation moves an
    estimate onto the truth: the rotation of the orientations, then a scale and a shift of the centres (fitted again
    without the frames over 3 times the median distance, at most twice)."""
    F = len(c_ref)
    dist, ang = np.full(F, np.nan), np.full(F, np.nan)
    m = np.flatnonzero(common)
    A = rotation_alignment(R_alt[m], R_ref[m])
    xs = c_alt[m] @ A.T
    fit = np.ones(len(m), bool)
    for _ in range(3):  # a stretch where the alternative is far off does not move the rest: fitted without it
        mu_s, mu_d = xs[fit].mean(axis=0), c_ref[m][fit].mean(axis=0)
        xs0, xd0 = xs[fit] - mu_s, c_ref[m][fit] - mu_d
        den = float(np.sum(xs0 * xs0))
        s = max(float(np.sum(xd0 * xs0)) / den, 0.0) if den > 0 else 0.0
        d = np.linalg.norm(s * (xs - mu_s) + mu_d - c_ref[m], axis=1)
        keep = d <= max(3.0 * float(np.median(d)), 1e-3 * diameter)
        if keep.sum() < MIN_COMMON or np.array_equal(keep, fit):
            break
        fit = keep
    dist[m] = d / max(diameter, 1e-300)
    ang[m] = rotation_angle_deg(np.einsum("ij,njk->nik", A, R_alt[m]), R_ref[m])
    return dist, ang


def local_level(x: np.ndarray, valid: np.ndarray, window: int) -> np.ndarray:
    """Returns (F,) the median of ``x`` over the ``window`` valid frames about each frame (NaN where none is)."""
    idx = np.flatnonzero(valid)
    out = np.full(len(x), np.nan)
    if not len(idx):
        return out
    med = median_filter(x[idx], size=max(min(int(window), len(idx)), 1), mode="nearest")
    pos = np.clip(np.searchsorted(idx, np.arange(len(x))), 0, len(idx) - 1)  # nearest valid frame at or after
    before = np.clip(pos - 1, 0, len(idx) - 1)
    nearer = np.where(np.abs(idx[before] - np.arange(len(x))) < np.abs(idx[pos] - np.arange(len(x))), before, pos)
    out[:] = med[nearer]
    return out


@dataclasses.dataclass(frozen=True)
class Evidence:
    """One independent solution of the same frames: its name, centres (F, 3), rotations (F, 3, 3), registered (F,)."""

    name: str
    centers: np.ndarray
    R_wc: np.ndarray
    registered: np.ndarray
    refuted: bool = False  # the point tracks fit its poses far worse than their own (lines_refuted): no contradiction

    @classmethod
    def of(cls, name: str, sol: Solution) -> "Evidence":
        return cls(name, sol.centers.copy(), sol.R_wc.copy(), sol.registered.copy())


def imu_gap_deg(R_wc: np.ndarray, R_imu: np.ndarray, registered: np.ndarray, window: int) -> np.ndarray:
    """Returns (F,) each frame's largest angle (deg) between its rotation relative to the registered frames within
    ``window`` frames of it and the IMU's relative rotation over the same frames (NaN where none): the IMU is
    accurate over a short stretch, whatever its drift over the spin."""
    F = len(R_wc)
    out = np.full(F, np.nan)
    ok = np.asarray(registered, bool) & np.all(np.isfinite(R_wc), axis=(1, 2)) & np.all(np.isfinite(R_imu), axis=(1, 2))
    for k in range(1, max(int(window), 1) + 1):
        a = np.flatnonzero(ok[:-k] & ok[k:])
        if not len(a):
            continue
        rel = np.einsum("nji,njk->nik", R_wc[a], R_wc[a + k])
        rel_imu = np.einsum("nji,njk->nik", R_imu[a], R_imu[a + k])
        ang = rotation_angle_deg(rel, rel_imu)
        out[a] = np.fmax(out[a], ang)
        out[a + k] = np.fmax(out[a + k], ang)
    return out


def source_scale(source: list, config: VerifyConfig) -> np.ndarray:
    """Returns (F,) each frame's calibrated scale (``verify.lines_scale`` / ``points_scale`` / ``motion_scale``) by
    the source that placed it ("steady circle" counts as the motion model, "shared centre" as the lines)."""
    table = {"points": config.points_scale, "motion model": config.motion_scale, "steady circle": config.motion_scale}
    return np.array([table.get(s, config.lines_scale) for s in source], dtype=np.float64)


def combine_evidence(model: np.ndarray, gap: np.ndarray, other: np.ndarray, config: VerifyConfig,
                     scale: np.ndarray | float = 1.0) -> np.ndarray:
    """Returns (F,) stds from a frame's evidences (NaN: none): the marginal ``model`` and the distance ``gap`` to the
    nearest solution combined by their geometric mean (each scaled to a median predictor of the error), never less
    than the scaled distance ``other`` to the solution independent of the frame's own source (a contradiction is
    not averaged away), times ``scale`` (:func:`source_scale`); ``fallback_sigma_rel`` without any evidence; at
    least ``floor_sigma_rel``."""
    with np.errstate(invalid="ignore", divide="ignore"):
        logs = np.stack([np.log(config.model_ratio * np.where(model > 0, model, np.nan)),
                         np.log(config.gap_ratio * np.where(gap > 0, gap, np.nan))])
        have = np.isfinite(logs)
        geo = np.where(have.any(axis=0),
                       np.exp(np.nansum(np.where(have, logs, 0.0), axis=0) / np.maximum(have.sum(axis=0), 1)), np.nan)
        comb = np.fmax(geo, config.other_ratio * np.where(other > 0, other, np.nan))
    return np.maximum(np.where(np.isfinite(comb), scale * comb, config.fallback_sigma_rel), config.floor_sigma_rel)


def honest_sigma(centers: np.ndarray, R_wc: np.ndarray, registered: np.ndarray, sigma_model: np.ndarray,
                 source: list, evidence: list[Evidence], config: VerifyConfig,
                 R_refined: np.ndarray | None = None, R_imu: np.ndarray | None = None) -> dict:
    """Returns the per-frame stds and flags of :func:`verify_solution` from arrays (module docstring):
    {"sigma_rel" (F,), "doubtful" (F,) bool, "why" (F,) list, "gap_rel" (F,) the evidence's gap, "model_rel" (F,),
    "gaps": {name: median gap}, "rotation_gaps": {name: median degrees}, "diameter"}."""
    F = len(registered)
    reg = np.asarray(registered, bool)
    diameter = float(pdist(centers[reg]).max()) if reg.sum() >= 2 else 0.0
    why: list[str | None] = [None] * F
    doubtful = np.zeros(F, bool)
    gap = np.full(F, np.nan)
    out = {"sigma_rel": np.full(F, np.nan), "doubtful": doubtful, "why": why, "gap_rel": gap,
           "model_rel": np.full(F, np.nan), "other_rel": np.full(F, np.nan), "imu_gap_deg": np.full(F, np.nan),
           "gaps": {}, "rotation_gaps": {}, "diameter": diameter}
    if reg.sum() < 2 or diameter <= 0:
        return out
    src = [s or "" for s in source]
    other_of = np.array(["lines" if s in ("points", "motion model") else "points" for s in src])
    other = np.full(F, np.nan)
    window = max(int(round(config.evidence_window * reg.sum())), 1)
    rot_ok = np.zeros(F, bool)
    rot_checked = False
    gap_of = {}
    for ev in evidence:
        common = reg & np.asarray(ev.registered, bool) & np.all(np.isfinite(ev.centers), axis=1)
        if common.sum() < MIN_COMMON:
            continue
        dist, ang = aligned_gap(ev.centers, ev.R_wc, centers, R_wc, common, diameter)
        level = np.where(common, np.fmax(dist, local_level(dist, common, window)), np.nan)
        gap_of[ev.name] = level
        gap = np.fmin(gap, level)  # the nearest solution: the one the final most likely derives from
        if not ev.refuted:  # the solution independent of the frame's own source
            other = np.where(other_of == ev.name, level, other)
        out["gaps"][ev.name] = float(np.median(dist[common]))
        out["rotation_gaps"][ev.name] = float(np.median(ang[common]))
        rot_ok |= common & (ang <= config.max_rotation_gap_deg)
        rot_checked = True
    if R_refined is not None:
        ok = reg & np.all(np.isfinite(R_refined), axis=(1, 2))
        if ok.sum() >= MIN_COMMON:
            A = rotation_alignment(R_refined[ok], R_wc[ok])
            ang = np.full(F, np.inf)
            ang[ok] = rotation_angle_deg(np.einsum("ij,njk->nik", A, R_refined[ok]), R_wc[ok])
            out["rotation_gaps"]["refined"] = float(np.median(ang[ok]))
            rot_ok |= ang <= config.max_rotation_gap_deg
            rot_checked = True
    # each available evidence scaled to a median predictor of the error, combined by their geometric mean, then
    # scaled so that 3 stds cover all but 5 % of frames (calibrated: tools/calibrate_sigma.py)
    model = np.where(np.isfinite(sigma_model) & (sigma_model > 0), sigma_model, np.nan)
    sig = np.where(reg, combine_evidence(model, gap, other, config, source_scale(src, config)), np.nan)
    out["sigma_rel"], out["gap_rel"], out["model_rel"], out["other_rel"] = sig, gap, model, other
    imu = imu_gap_deg(R_wc, R_imu, reg, config.imu_window_frames) if R_imu is not None else np.full(F, np.nan)
    out["imu_gap_deg"] = imu

    def nearest(i: int) -> str:  # the solution whose gap is the frame's
        return min(gap_of, key=lambda k: np.nan_to_num(gap_of[k][i], nan=np.inf))

    for i in np.flatnonzero(reg):
        reasons = []
        if sig[i] > config.flag_sigma_rel:
            if np.isfinite(other[i]) and config.other_ratio * other[i] >= (
                    config.model_ratio * model[i] if np.isfinite(model[i]) else 0):
                reasons.append(f"its std is {100 * sig[i]:.1f} % of the spin's diameter: the {other_of[i]}' own "
                               f"solution puts it {100 * other[i]:.1f} % away")
            elif np.isfinite(gap[i]) and config.gap_ratio * gap[i] >= (
                    config.model_ratio * model[i] if np.isfinite(model[i]) else 0):
                reasons.append(f"its std is {100 * sig[i]:.1f} % of the spin's diameter: the {nearest(i)}' own "
                               f"solution puts it {100 * gap[i]:.1f} % away")
            elif np.isfinite(model[i]):
                reasons.append(f"its std is {100 * sig[i]:.1f} % of the spin's diameter ({src[i]})")
            else:
                reasons.append(f"its std is {100 * sig[i]:.1f} % of the spin's diameter: nothing independent "
                               f"checks it")
        if config.max_gap_rel > 0 and gap[i] > config.max_gap_rel:  # NaN (no evidence) compares False
            reasons.append(f"it lies {100 * gap[i]:.1f} % of the spin's diameter from every independent solution "
                           f"(the nearest: the {nearest(i)}')")
        if rot_checked and not rot_ok[i]:
            reasons.append(f"its rotation is over {config.max_rotation_gap_deg:g} deg from every other estimate")
        if imu[i] > config.max_imu_gap_deg:
            reasons.append(f"it turns {imu[i]:.1f} deg off the IMU's relative rotation to its neighbours")
        if reasons:
            doubtful[i] = True
            why[i] = "; ".join(reasons)
    return out


def lines_refuted(evidence: list[Evidence], points: PointTracks | None, K: np.ndarray, config: VerifyConfig
                  ) -> tuple[bool, float, float] | None:
    """Returns (whether the point tracks refute the lines' own solution, the tracks' median px residual at the
    lines' poses, at the points' own poses on the same frames), None where there is nothing to compare. Refuted:
    the residual at the lines' poses over ``verify.refute_ratio`` times the points' and ``refute_slack_px`` more
    (the test of graph.motion_model.lines_fit_points: the tracks are precise, their own placement only loosely held)."""
    ev = {e.name: e for e in evidence}
    if points is None or not len(points.frame) or "lines" not in ev or "points" not in ev:
        return None
    common = ev["lines"].registered & ev["points"].registered
    if common.sum() < MIN_COMMON:
        return None
    r_l, r_p = pose_fits_px(ev["lines"].R_wc, ev["lines"].centers, ev["points"].R_wc, ev["points"].centers, common,
                            points, K)
    if not (np.isfinite(r_l) and np.isfinite(r_p)):
        return None
    return bool(r_l > max(config.refute_ratio * r_p, r_p + config.refute_slack_px)), r_l, r_p


def verify_solution(pre: Preprocessed, sol: Solution, config: VerifyConfig, *, evidence: list[Evidence] = (),
                    points: PointTracks | None = None) -> Solution:
    """Returns ``sol`` with every registered frame's honest std, its doubt and the run's verdict (module docstring);
    frames whose std exceeds ``verify.max_sigma_rel`` are left out (``frame_source`` None, the reason in
    ``frame_doubtful_why``). ``points``: the point tracks, to tell whether they refute the lines' own solution
    (:func:`lines_refuted`; then it contradicts nothing)."""
    if not config.enabled:
        return sol
    t0 = time.perf_counter()
    F = len(sol.registered)
    res = dict(sol.residuals)
    refute = lines_refuted(list(evidence), points, sol.camera.K, config)
    if refute is not None and refute[0]:
        evidence = [dataclasses.replace(e, refuted=True) if e.name == "lines" else e for e in evidence]
    src = list(res.get("frame_source") or np.where(sol.registered, "lines", None).tolist())
    model = np.array([np.nan if v is None else float(v) for v in (res.get("frame_sigma_rel") or [None] * F)])
    out = honest_sigma(sol.centers, sol.R_wc, sol.registered, model, src, list(evidence), config, pre.R_wc,
                       getattr(pre, "R_wc_imu", None))
    sig, doubtful, why = out["sigma_rel"], out["doubtful"], list(out["why"])
    left = sol.registered & (sig > config.max_sigma_rel)
    for i in np.flatnonzero(left):
        why[i] = f"left out: its std is {100 * sig[i]:.1f} % of the spin's diameter ({why[i] or src[i]})"
    if config.strict:  # only frames the solution independent of their own source confirms, none doubtful
        unconfirmed = sol.registered & ~left & (~(out["other_rel"] <= 3.0 * config.flag_sigma_rel) | doubtful)
        for i in np.flatnonzero(unconfirmed):
            why[i] = "left out (--strict): " + (why[i] or "no independent solution places it")
        left |= unconfirmed
    doubtful &= sol.registered & ~left
    reasons = []
    gap_lp = _lines_points(out["gaps"], res)
    if gap_lp is not None and gap_lp > config.max_lines_points_rel and not (refute is not None and refute[0]):
        reasons.append(f"the lines and the points disagree by {100 * gap_lp:.1f} % of the spin's diameter")
        # two whole solutions disagree: every frame rests on which is right
        for i in np.flatnonzero(sol.registered & ~left):
            why[i] = "; ".join([*([why[i]] if why[i] else []), reasons[-1]])
        doubtful = sol.registered & ~left
    n_out = int((sol.registered & ~left).sum())
    if doubtful.any() and not reasons and doubtful.sum() <= config.max_doubtful_share * n_out:
        # a few doubtful frames in a run that otherwise checks out: left out, so that a trusted run vouches for
        # every frame it outputs
        for i in np.flatnonzero(doubtful):
            why[i] = f"left out: doubtful ({why[i]})"
        left |= doubtful
        doubtful[:] = False
    registered = sol.registered & ~left
    for i in np.flatnonzero(left):
        src[i] = None
    if config.doubt_unchecked and (reasons or doubtful.any() or registered.sum() < 2):
        # a doubtful run vouches only for frames a solution independent of their own source checks
        unchecked = registered & ~doubtful & ~np.isfinite(out["other_rel"])
        for i in np.flatnonzero(unchecked):
            why[i] = "the run is doubtful and no solution independent of the frame's own places it"
        doubtful |= unchecked
    if doubtful.any():
        reasons.append(f"{int(doubtful.sum())} of {int(registered.sum())} frames doubtful")
    if registered.sum() < 2:
        reasons.append("fewer than two frames placed")
    verdict = DOUBTFUL if reasons else TRUSTED
    res["frame_source"] = src
    res["frame_sigma_rel"] = [float(s) if r else None for s, r in zip(sig, registered)]
    res["frame_doubtful"] = [bool(d) for d in doubtful]
    res["frame_doubtful_why"] = [w if (d or l) else None for w, d, l in zip(why, doubtful, left)]
    fin = lambda a: [None if not (r and np.isfinite(v)) else float(v) for v, r in zip(a, registered)]  # noqa: E731
    res["frame_gap_rel"], res["frame_other_gap_rel"] = fin(out["gap_rel"]), fin(out["other_rel"])
    res["frame_model_sigma_rel"] = fin(out["model_rel"])
    res["verify"] = {"verdict": verdict, "reasons": reasons, "gaps_rel": out["gaps"],
                     "rotation_gaps_deg": out["rotation_gaps"], "lines_vs_points_rel": gap_lp,
                     "lines_refuted_by_points": None if refute is None else {"refuted": refute[0],
                                                                              "lines_px": refute[1],
                                                                              "points_px": refute[2]},
                     "imu_gap_deg_median": float(np.nanmedian(out["imu_gap_deg"])) if np.isfinite(
                         out["imu_gap_deg"]).any() else None,
                     "doubtful": int(doubtful.sum()), "left_out": int(left.sum()),
                     "sigma_rel_median": float(np.nanmedian(sig[registered])) if registered.any() else None,
                     "seconds": round(time.perf_counter() - t0, 3)}
    log.log(logging.WARNING if verdict == DOUBTFUL else logging.INFO, "verdict: %s%s", verdict,
            f" ({'; '.join(reasons)})" if reasons else "")
    centers = np.where(registered[:, None], sol.centers, np.nan)
    R = np.where(registered[:, None, None], sol.R_wc, np.nan)
    return dataclasses.replace(sol, registered=registered, centers=centers, R_wc=R, residuals=res)


def _lines_points(gaps: dict, residuals: dict) -> float | None:
    """Returns how far the lines' and the points' solutions lie apart (median over the diameter): as the motion
    model measured it where it compared them, else the larger of the two gaps to the final solution."""
    mm = (residuals.get("motion_model") or {}).get("lines_vs_points_rel")
    if mm is not None:
        return float(mm)
    if "lines" in gaps and "points" in gaps:
        return max(gaps["lines"], gaps["points"])
    return None
