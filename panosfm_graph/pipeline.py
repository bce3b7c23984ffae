"""The pipeline: stages in order, each cached, the result written atomically.

``run_pipeline(capture, out)`` runs (paper §3): line segment detection →
Manhattan frame + rotation refinement → line tracking → surface normals →
geometric relationship detection → linear SfM → bundle adjustment → export
(COLMAP text model, ``lines.ply``, ``summary.json``, PNG views, rerun
recording). Each stage's output is cached under ``<out>/cache/`` keyed by a
hash of its inputs and its part of the :class:`Config`; ``resume=True`` reuses
every stage whose key is unchanged, so a changed setting reruns only the
stages it affects.
"""
from __future__ import annotations

import dataclasses
import importlib
import logging
import re
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from . import __version__
from .cache import StageCache, stable_hash, stage_code_hash
from .config import Config, with_overrides
from .data import (Capture, NormalMaps, PointTracks, Preprocessed, Relations, Segments, Solution,
                   Thumbnails, Tracks)
from .errors import InputError
from .progress import stage
from .summary import build_summary, frame_status, peak_memory_mb, unregistered_why

log = logging.getLogger("panosfm")

THUMBNAIL_WIDTH = 480  # frames on the rerun timeline
CACHE_KEEP = ("cache",)  # entries of an old result carried into the new one
STAGES = ("detect", "preprocess", "track", "normals", "relations", "linear", "bundle_adjust")


@dataclass
class RunResult:
    """What a run produced: the output directory, its summary, and the in-memory results."""

    out_dir: Path
    summary: dict
    capture: Capture | None = None
    preprocessed: Preprocessed | None = None
    tracks: Tracks | None = None
    points: PointTracks | None = None  # point tracks (points/): the motion model's texture corners
    relations: Relations | None = None
    linear: Solution | None = None
    solution: Solution | None = None
    batches: list[Solution] = field(default_factory=list)
    thumbnails: Thumbnails | None = None
    focal: Any = None  # lines.focal.FocalEstimate where the focal length was estimated
    focal_stitched: Any = None  # points.stitch.StitchedFocal where the point tracks were fitted for it
    focal_check: dict | None = None  # a given focal length against the vanishing points' (graph.reliability)

    def report(self) -> str:
        """Returns a short human-readable account of the run."""
        s = self.summary
        lines = [f"panosfm: wrote {self.out_dir}"]
        fr = s.get("frames", {})
        if fr:
            by = fr.get("by_source") or {}
            names = {"steady circle": "on the steady spin's circle", "points": "placed by point tracks",
                     "motion model": "placed by the motion model"}
            how = (f": {by.get('lines', 0)} fixed by lines, " + ", ".join(f"{by[k]} {v}" for k, v in names.items()
                                                                           if by.get(k))
                   if any(by.get(k) for k in names) else "")
            lines.append(f"  frames      {fr.get('registered', 0)}/{fr.get('total', 0)} registered "
                         f"({100.0 * fr.get('registered_ratio', 0.0):.1f} %){how}")
            for count, why in _grouped_reasons(fr.get("unregistered_reasons", {})):
                lines.append(f"              {count} not: {why}")
            mm = ((s.get("residuals") or {}).get("bundle_adjust") or {}).get("motion_model") or {}
            v = s.get("verdict") or {}
            if v.get("status") in ("trusted", "doubtful"):
                sig = [x for x in fr.get("sigma_rel") or [] if x is not None]
                med = f", std median {100 * float(np.median(sig)):.2f} % of the spin's diameter" if sig else ""
                lines.append(f"  verdict     {v['status'].upper()}{med}" + (f": {'; '.join(v['reasons'])}"
                                                                          if v["reasons"] else ""))
                first = next((i for i, w in enumerate(fr.get("doubtful_why") or []) if w), None)
                if first is not None:
                    lines.append(f"              e.g. frame {first}: {fr['doubtful_why'][first]}")
            if mm.get("lines_replaced"):
                lines.append(f"              the line-fixed frames lay {100 * mm['lines_vs_points_rel']:.1f} % of the "
                             "spin's diameter from the point tracks' poses: the points' poses kept, lines retriangulated")
        if "segments" in s:
            lines.append(f"  segments    {s['segments']['total']} ({s['segments']['manhattan']} Manhattan), "
                         f"{s.get('tracks', 0)} tracks, {s.get('lines', 0)} 3D lines")
        if "relations" in s:
            kept = s.get("relations_kept", {})
            lines.append("  relations   " + ", ".join(f"{k} {v}" + (f" ({kept[k]} kept)" if k in kept else "")
                                                  for k, v in s["relations"].items()))
        linear = (s.get("residuals") or {}).get("linear") or {}
        linear_cfg = s.get("config", {}).get("linear", {})
        arm = linear_cfg.get("spin_arm_m")
        by_arm = linear.get("scale") == "spin_arm" and arm is not None
        units = f"; units about metres: the spin's arm taken as {arm:g} m" if by_arm else ""
        ba = (s.get("residuals") or {}).get("bundle_adjust") or {}
        if s.get("metric") or "scale_from_arm" in ba or (ba.get("motion_model") or {}).get("anchor_free"):
            lines.append(f"  scale       {s.get('scale', 'metric')}")
        elif linear_cfg.get("camera_height_m") is not None:
            lines.append(f"  scale       arbitrary (no floor line verified for --camera-height{units})")
        else:
            lines.append(f"  scale       arbitrary (no --camera-height{units})")
        foc = s.get("focal") or {}
        if "estimated" in foc:
            e = foc["estimated"]
            refined = (f", {foc['focal_px']:.1f} px after the bundle adjustment"
                       if abs(foc["focal_px"] - e["focal_px"]) > 0.05 else "")
            lines.append(f"  focal       estimated {e['focal_px']:.1f} px (HFOV {e['hfov_deg']:.1f} deg) from the "
                         f"Manhattan vanishing points{refined}")
            st = foc.get("stitched")
            if st:
                arm = st.get("model") == "arm"
                verdict = "taken" if st["accepted"] else ("not taken" if arm else "not taken: the spin has parallax")
                how = (f"with the camera on the spin's circle (as bearings about one centre: 90 % within "
                       f"{st['centre_p90_px']:.2f} px, parallax)" if arm else "as bearings about one centre")
                lines.append(f"              {st['focal_px']:.1f} px from {st['tracks']} point tracks {how} "
                             f"(90 % within {st['p90_px']:.2f} px; {verdict})")
        zb = s.get("zero_baseline")
        if zb and zb.get("parallax_px") is not None:
            verdict = ("ZERO: no measurable parallax, every frame at one shared centre, no translation solved"
                       if zb.get("detected") else "measured")
            lines.append(f"  baseline    {verdict} (lines drift {zb['parallax_px']:.2f} px off their plane through "
                         f"the camera, median of {zb['tracks']} tracks; zero under {zb['threshold_px']:g} px)")
        if ba.get("zero_baseline") and "reprojection_rms" in ba:
            pts = f" and {ba['point_tracks']} point tracks" if ba.get("point_tracks") else ""
            kept = (f": the {'lines and points' if pts else 'lines'} fitted worse, the preprocessed rotations kept"
                    if ba.get("kept_preprocessed") else "")
            lines.append(f"  rotations   adjusted about the shared centre by {ba['lines']} lines{pts}{kept}")
        style, check = s.get("spin_style"), ba.get("steady_check")
        if style:
            why = ""
            if check and check.get("rms_arm") is not None:
                verdict = "kept" if check.get("kept") else "not kept"
                why = (f" (steady solve {verdict}: {check['registered']} frames, centres "
                       f"{100 * check['rms_arm']:.1f} % of the arm off one circle, at most "
                       f"{100 * check['max_rms_arm']:.1f} %)")
            lines.append(f"  spin        {style}{why}")
        secs = s.get("seconds", {})
        if secs:
            lines.append("  seconds     " + ", ".join(f"{k} {v:.1f}" for k, v in secs.items()))
        if s.get("peak_memory_mb"):
            lines.append(f"  peak memory {s['peak_memory_mb']:.0f} MB")
        return "\n".join(lines)


def _grouped_reasons(reasons: dict[str, int]) -> list[tuple[int, str]]:
    """Returns (count, reason) by count: reasons that differ only in their figures (the reliability check's stds)
    counted as one, their figures' range given as 'a-b'."""
    groups: dict[str, list] = {}
    for why, count in reasons.items():
        key = re.sub(r"\d+(\.\d+)?", "#", why)
        g = groups.setdefault(key, [0, why, []])
        g[0] += count
        g[2].append([float(x) for x in re.findall(r"\d+(?:\.\d+)?", why)])
    out = []
    for key, (count, first, figures) in groups.items():
        if len(figures) > 1 and len({len(f) for f in figures}) == 1:
            cols = list(zip(*figures))
            parts = iter(f"{min(c):g}" if min(c) == max(c) else f"{min(c):g}-{max(c):g}" for c in cols)
            first = re.sub(r"\d+(\.\d+)?", lambda _: next(parts), key.replace("#", "0"))
        out.append((count, first))
    return sorted(out, key=lambda cw: -cw[0])


def capture_identity(capture: Capture) -> str:
    """Returns a hash identifying the capture's content as the pipeline sees it."""
    cam = capture.camera
    return stable_hash(str(capture.root.resolve()), list(capture.frame_names), capture.timestamps,
                       cam.model, cam.width, cam.height, cam.params, capture.R_wc_imu)


def check_output_dir(out_dir: Path) -> Path:
    """Returns the absolute ``out_dir`` after checking a result can be written there (InputError if not)."""
    from .export import check_output_dir as check

    return check(out_dir, keep=CACHE_KEEP)


def line_colors(pre: Preprocessed, tracks: Tracks) -> np.ndarray:
    """Returns (T, 3) uint8 BGR: each track's mean segment colour (the quarter view's colours)."""
    seg = np.flatnonzero(tracks.track_of >= 0)
    t = tracks.track_of[seg]
    sums = np.zeros((tracks.n, 3))
    np.add.at(sums, t, pre.segments.colors[seg].astype(np.float64))
    counts = np.maximum(np.bincount(t, minlength=tracks.n), 1)[:, None]
    return np.clip(sums / counts, 0, 255).astype(np.uint8)


def _cached(cache: StageCache, name: str, key: str, cls: type, compute: Callable[[], Any],
            timings: dict[str, float], resumed: list[str]) -> Any:
    obj = cache.load(name, key, cls)
    if obj is not None:
        log.info("%s: reused from cache", name)
        resumed.append(name)
        timings.setdefault(name, 0.0)
        return obj
    with stage(name, timings):
        obj = compute()
    cache.save(name, key, obj)
    return obj


def run_pipeline(capture_path: str | Path, out_dir: str | Path, config: Config = Config(), *,
                 resume: bool = False, rerun: bool = True, spawn: bool = False, views: bool = True,
                 stop_after: str | None = None, cache_dir: str | Path | None = None,
                 on_batch: Callable[[int, Solution], None] | None = None) -> RunResult:
    """Returns the reconstruction of a capture directory, written to ``out_dir``.

    The output directory is replaced atomically when everything is written;
    on an error the previous result stays as it was. ``stop_after`` names a
    stage in :data:`STAGES` to stop after (what exists so far is still
    exported). With ``graph.incremental_batch`` the stages run as frames are read, N at a time
    (:mod:`.stream`; the stage cache unused); ``on_batch(i, solution)`` sees every batch's estimate.
    ``cache_dir`` (default ``<out>/cache``) may be shared between runs, as
    ablations do.
    """
    from .capture import capture_warnings, load_capture
    from .export import atomic_output_dir

    t_start = time.perf_counter()
    out_dir = Path(out_dir)
    if stop_after is not None and stop_after not in STAGES:
        raise InputError(f"unknown stage {stop_after!r}; stages are {', '.join(STAGES)}")
    check_output_dir(out_dir)
    if rerun:  # importing rerun takes ~1 s of Python; do it while detection's workers keep the cores busy
        threading.Thread(target=importlib.import_module, args=("rerun",), daemon=True).start()
    timings: dict[str, float] = {}
    resumed: list[str] = []
    with stage("load", timings):
        capture = load_capture(capture_path, config.capture)
        warnings = capture_warnings(capture, config.capture)  # InputError when there is no turn
    cache = StageCache(Path(cache_dir) if cache_dir is not None else out_dir / "cache", enabled=resume)
    result = RunResult(out_dir=out_dir, summary={}, capture=capture)

    if config.graph.incremental_batch and stop_after is None:  # streamed: N frames at a time (stream.py)
        segments = _streamed(capture, config, result, timings, rerun, on_batch)
    else:
        segments = _stages(capture, config, cache, result, timings, resumed, stop_after, rerun, on_batch)
    capture = result.capture

    with stage("export", timings):
        with atomic_output_dir(out_dir, keep=CACHE_KEEP) as tmp:
            summary = build_summary(capture, segments, result, config, timings, resumed, t_start)
            solved = (result.solution.residuals or {}) if result.solution is not None else {}
            summary["warnings"] = warnings + list(solved.get("warnings", []))
            _export(tmp, capture, segments, result, summary, rerun=rerun, spawn=spawn, views=views)
    result.summary = summary
    return result


def _stages(capture: Capture, config: Config, cache: StageCache, result: RunResult, timings: dict[str, float],
            resumed: list[str], stop_after: str | None, rerun: bool,
            on_batch: Callable[[int, Solution], None] | None) -> Segments:
    """Runs the stages on all frames at once, each cached (module docstring), into ``result``; returns the segments."""

    def done(name: str) -> bool:
        return stop_after == name

    # the version and each stage's source are part of its key: a cache never outlives the code that wrote it
    code = stage_code_hash
    key = stable_hash(__version__, code("detect"), capture_identity(capture), config.capture, config.detect)
    thumbs: list[bytes] | None = [] if rerun else None
    segments = _cached(cache, "detect", key, Segments, lambda: _detect(capture, config, thumbs), timings, resumed)
    if thumbs:  # made while detection decoded the frames; the rerun timeline shows them
        result.thumbnails = Thumbnails.from_list(thumbs, min(THUMBNAIL_WIDTH, capture.camera.width))
        cache.save("thumbnails", key, result.thumbnails)
    elif rerun:
        result.thumbnails = cache.load("thumbnails", key, Thumbnails)
    if not done("detect") and (not capture.focal_given or config.focal.estimate):
        capture = _estimate_focal(capture, segments, config, timings, result)
    elif not done("detect") and config.verify.enabled and config.verify.focal_check:
        result.focal_check = _check_focal(capture, segments, config, timings)
    if not done("detect"):
        key = stable_hash(key, code("preprocess"), config.manhattan, config.rotation, capture.camera.params,
                          config.points.enabled, config.graph.motion_model)  # vertical edges only: points or stop
        pre = _cached(cache, "preprocess", key, Preprocessed,
                      lambda: _preprocess(capture, segments, config), timings, resumed)
        result.preprocessed = pre
        key_pre = key
        if not done("preprocess"):
            key = stable_hash(key_pre, code("track"), config.tracking)
            result.tracks = _cached(cache, "track", key, Tracks,
                                    lambda: _track(capture, pre, config), timings, resumed)
            key_tracks = key
        if result.tracks is not None and not done("track"):
            key_normals = stable_hash(key_pre, code("normals"), config.normals, _normal_model_identity(config))
            normals = _cached(cache, "normals", key_normals, NormalMaps,
                              lambda: _normals(capture, pre, config), timings, resumed)
            key = stable_hash(key_tracks, key_normals, code("relations"), config.relations)
            result.relations = _cached(cache, "relations", key, Relations,
                                       lambda: _relations(capture, pre, result.tracks, normals, config),
                                       timings, resumed)
            del normals
        if result.relations is not None and not done("relations"):
            key = stable_hash(key, code("linear"), config.linear)
            result.linear = _cached(cache, "linear", key, Solution,
                                    lambda: _linear(capture, pre, result.tracks, result.relations, config),
                                    timings, resumed)
            result.solution = result.linear
        if result.linear is not None and not done("linear"):
            key_points = stable_hash(key_pre, code("points"), config.points)

            def points() -> PointTracks:  # tracked only when the bundle adjustment leaves frames to place
                return _cached(cache, "points", key_points, PointTracks, lambda: _points(capture, pre, config),
                               timings, [])

            key = stable_hash(key, code("bundle_adjust"), config.graph, config.verify, key_points)
            result.solution = _cached(
                cache, "bundle_adjust", key, Solution,
                lambda: _bundle_adjust(pre, result, config, on_batch, points), timings, resumed)
            if result.points is not None and "points" in timings:  # its own line, not inside the adjustment's
                timings["bundle_adjust"] = max(timings["bundle_adjust"] - timings["points"], 0.0)
    return segments


def _streamed(capture: Capture, config: Config, result: RunResult, timings: dict[str, float], rerun: bool,
              on_batch: Callable[[int, Solution], None] | None) -> Segments:
    """Runs the stages as frames arrive, ``graph.incremental_batch`` at a time (:func:`stream.stream_capture`),
    into ``result``; returns the segments. The stage cache is not used."""
    from .stream import stream_capture

    with stage("stream", timings):
        rec = stream_capture(capture, config, on_batch=on_batch, thumbnail_width=THUMBNAIL_WIDTH if rerun else None)
    timings.update(rec.stage_seconds)
    if rec.focal is not None:
        result.focal = rec.focal
        result.capture = dataclasses.replace(capture, camera=rec.camera)
    result.preprocessed, result.tracks, result.relations = rec.preprocessed, rec.tracks, rec.relations
    result.linear, result.solution, result.batches = rec.linear, rec.solution, list(rec.batches)
    result.thumbnails = rec.thumbnails
    return rec.segments


def _normal_model_identity(config: Config) -> str | None:
    """Returns size and mtime of the ONNX model the normals stage would run (part of its cache key)."""
    if config.normals.source != "model":
        return None
    from .normals.onnx import SHIPPED_MODEL

    path = Path(config.normals.model_path) if config.normals.model_path else Path(SHIPPED_MODEL)
    try:
        st = path.stat()
    except OSError:
        return f"{path}:missing"
    return f"{path.resolve()}:{st.st_size}:{st.st_mtime_ns}"


# --- stage adapters: plain calls into the stage modules -------------------------------------------

def _detect(capture: Capture, config: Config, thumbnails: list[bytes] | None) -> Segments:
    from .lines.detect import detect_segments

    return detect_segments(capture, config.detect, thumbnails=thumbnails, thumbnail_width=THUMBNAIL_WIDTH)


def _estimate_focal(capture: Capture, segments: Segments, config: Config, timings: dict[str, float],
                    result: RunResult) -> Capture:
    """Returns the capture with the focal length the Manhattan vanishing points give (``lines/focal.py``); the
    estimate goes into ``result.focal``."""
    from .capture.camera import with_focal
    from .lines.focal import estimate_focal

    with stage("focal", timings):
        est = estimate_focal(segments, capture.R_wc_imu, capture.camera, config.focal, config.manhattan)
    result.focal = est
    capture = dataclasses.replace(capture, camera=with_focal(capture.camera, est.focal_px))
    if config.points.enabled and config.focal.stitch_max_p90_px > 0:  # a turn about the camera: the point tracks
        from .points import spin_focal                                  # as a stitcher's (points/stitch.py)

        with stage("focal", timings):
            st = spin_focal(capture, config.points, config.focal.stitch_max_p90_px,
                            graph_config=config.graph if config.focal.stitch_arm else None)
        result.focal_stitched = st
        if st is not None and st.accepted:
            capture = dataclasses.replace(capture, camera=with_focal(capture.camera, st.focal_px))
    result.capture = capture
    return capture


def _check_focal(capture: Capture, segments: Segments, config: Config, timings: dict[str, float]) -> dict | None:
    """Returns the given focal length checked against the Manhattan vanishing points' (``lines/focal.py``;
    graph.reliability): {"given_px", "estimated_px", "sharpness", "off", "agrees"}; None where the lines cannot
    say (too few)."""
    from .errors import TooFewLinesError
    from .lines.focal import estimate_focal

    with stage("focal", timings):
        try:
            est = estimate_focal(segments, capture.R_wc_imu, capture.camera, config.focal, config.manhattan)
        except TooFewLinesError:
            return None
    given = float(capture.camera.K[0, 0])
    off = given / est.focal_px - 1.0
    sharp = bool(est.sharpness >= config.verify.focal_min_sharpness)
    check = {"given_px": given, "estimated_px": float(est.focal_px), "sharpness": float(est.sharpness),
             "off": float(off), "agrees": bool(not sharp or abs(off) <= config.verify.max_focal_gap)}
    if not check["agrees"]:
        log.warning("camera.json's focal length %.1f px is %.0f %% from what the vanishing points say (%.1f px): a "
                    "wrong focal length bends every line; the result is marked doubtful (--estimate-focal uses "
                    "theirs)", given, 100 * abs(off), est.focal_px)
    return check


def _preprocess(capture: Capture, segments: Segments, config: Config) -> Preprocessed:
    from .errors import TooFewLinesError
    from .lines import refine_manhattan_and_rotations

    try:
        return refine_manhattan_and_rotations(segments, capture, config)
    except TooFewLinesError as e:  # name the capture: the one line the user sees must say which input
        if e.path is not None:
            raise
        raise TooFewLinesError(str(e), capture.root) from None


def _track(capture: Capture, pre: Preprocessed, config: Config) -> Tracks:
    from .lines import track_lines

    return track_lines(capture, pre, config)


def _points(capture: Capture, pre: Preprocessed, config: Config) -> PointTracks:
    from .points import track_points

    return track_points(capture, pre.R_wc, config.points)


def _normals(capture: Capture, pre: Preprocessed, config: Config) -> NormalMaps:
    from .normals import estimate_normals

    return estimate_normals(capture, pre, config.normals)


def _relations(capture: Capture, pre: Preprocessed, tracks: Tracks, normals: NormalMaps,
               config: Config) -> Relations:
    from .relations import detect_relations

    return detect_relations(pre, tracks, normals, capture.camera, config.relations)


def _linear(capture: Capture, pre: Preprocessed, tracks: Tracks, relations: Relations,
            config: Config) -> Solution:
    from .linear import solve_linear

    return solve_linear(pre, tracks, relations, capture.camera, config.linear)


def _bundle_adjust(pre: Preprocessed, result: RunResult, config: Config,
                   on_batch: Callable[[int, Solution], None] | None,
                   points: Callable[[], PointTracks] | None = None, verify: bool = True) -> Solution:
    """The bundle adjustment stage (paper §3.4 and our additions: spin style, motion model, point tracks), its
    result checked against the lines' and the points' own solutions (``verify``: graph.reliability)."""
    from .graph import verify_solution

    cap = result.capture
    if cap is not None and cap.focal_given and not config.graph.refine_given_focal and 3 in config.graph.phases:
        # a focal length camera.json gives is an input: kept (phase 3 would move it; issue 64: a real cut's heading
        # ramped 4.5 deg each way when the BA moved a given 376.7 px to 386.4 px)
        config = with_overrides(config, graph={"phases": tuple(p for p in config.graph.phases if p != 3)})
    evidence: list = []
    sol = _adjust(pre, result, config, on_batch, points, evidence if verify else None)
    if not verify or (result.linear.residuals.get("zero_baseline") or {}).get("detected"):
        return sol
    return verify_solution(pre, sol, config.verify, evidence=evidence, points=result.points)


def _adjust(pre: Preprocessed, result: RunResult, config: Config, on_batch: Callable[[int, Solution], None] | None,
            points: Callable[[], PointTracks] | None, evidence: list | None) -> Solution:
    """The bundle adjustment, the motion model and the joint solve (:func:`_bundle_adjust`); ``evidence`` (a list, or
    None: not collected) receives the independent solutions the result is checked against."""
    from .graph import (Evidence, adjust_with_points, bundle_adjust, bundle_adjust_incremental, circle_rms_arm,
                        compares_points, drop_lines_beyond_room, place_by_motion_model, place_by_points_alone,
                        points_replace_lines, solve_at_final_scale, steady_or_hand_held, steady_tried)

    with_points = points is not None and config.points.enabled

    def place(sol: Solution, free: Solution | None = None) -> Solution:
        """The frames the lines leave without a pose placed by the motion model and the point tracks where the std
        is small enough (``free``: the points' own placement of ``sol``, made before), the BA with the point tracks
        joined (graph/joint_points.py), lines beyond the room dropped. The lines' solution ``sol`` and the points'
        own placement go to ``evidence`` (made here for it where the motion model would not compare them)."""
        joint = with_points and config.graph.points_joint_max_line_rms_ratio > 0
        check = evidence is not None and with_points and config.verify.enabled and config.verify.points_check
        if with_points and result.points is None and (joint or check or (config.graph.motion_model and
                                                                          not sol.registered.all())):
            result.points = points()
        if check and free is None:
            alone = place_by_points_alone(pre, result.tracks, sol, config.graph, result.points, config.points,
                                          always=True)
            free = alone if compares_points(sol, config.graph) else None
        else:
            alone = free
        if evidence is not None:
            evidence.extend([Evidence.of("lines", sol), *([Evidence.of("points", alone)] if alone is not None else [])])
        sol = place_by_motion_model(pre, result.tracks, sol, config.graph, points=result.points,
                                    points_config=config.points, relations=result.relations, free=free)
        sol = adjust_with_points(pre, result.tracks, result.relations, sol, result.points, config.graph,
                                 config.points) if joint else sol
        return drop_lines_beyond_room(sol, config.graph.max_line_distance_ratio)

    if not result.linear.registered.any():  # nothing to adjust: the point tracks alone may place the frames
        log.warning("the linear solve registered no frame: bundle adjustment skipped")
        if points is None or not (config.points.enabled and config.graph.motion_model):
            return result.linear
        return place(result.linear)
    if config.linear.zero_translation:
        # the paper's baseline keeps every camera centre at the origin; BA would move them
        log.info("zero-translation baseline: bundle adjustment skipped, the linear solve is the result")
        return result.linear
    if (result.linear.residuals.get("zero_baseline") or {}).get("detected"):
        # no parallax: the BA's translations would be noise fitted to noise (linear/baseline.py); the rotations
        # and lines are adjusted about the one shared centre
        if not config.graph.zero_baseline_rotations:
            log.info("zero baseline: bundle adjustment skipped, every frame at one shared centre")
            return result.linear
        from .graph import rotation_bundle_adjust

        if points is not None and config.points.enabled and config.points.zero_baseline:
            result.points = points()
        return rotation_bundle_adjust(pre, result.tracks, result.linear, config.graph, points=result.points,
                                      points_config=config.points, focal_free=3 in config.graph.phases)
    if config.graph.incremental_batch:
        batches = bundle_adjust_incremental(pre, result.tracks, result.relations, result.linear,
                                            config.graph, on_batch=on_batch)
        result.batches = list(batches)
        if not config.graph.incremental_final_solve:  # the last batch is the result: kept hand-held
            return result.batches[-1]
        sol = result.batches[-1]  # the final solve of all frames: as the one-shot solve, then the spin style
        resolved = True
    else:  # solved again at its final scale only if the spin style keeps it (docs/decisions.md#deferred-re-solve)
        sol = bundle_adjust(pre, result.tracks, result.relations, result.linear, config.graph, resolve=False)
        resolved = False
    hand = free = None
    if not resolved and with_points and config.graph.motion_model and steady_tried(sol, config.graph):
        # the point tracks first: where they place every frame off one circle and put the line-fixed frames
        # elsewhere, the steady style's solve would be rejected (docs/decisions.md#points-before-the-spin-style)
        hand = solve_at_final_scale(pre, result.tracks, result.relations, result.linear, config.graph, sol)
        result.points = points()
        free = place_by_points_alone(pre, result.tracks, hand, config.graph, result.points, config.points)
        rms = circle_rms_arm(free, pre.manhattan.directions, config.graph) if free is not None else None
        if rms is not None and rms > config.graph.steady_max_rms_arm and points_replace_lines(hand, free,
                                                                                               config.graph,
                                                                                               result.points):
            log.info("auto spin style: the point tracks place every frame %.1f %% of the arm off one circle: "
                     "hand-held, the steady solve not tried", 100 * rms)
            check = {"skipped": "the point tracks place every frame, off one circle", "points_rms_arm": rms,
                     "max_rms_arm": config.graph.steady_max_rms_arm}
            return place(*_styled({"spin_style": "hand-held", "steady_check": check}, hand, free))
    # the steady linear solve is not a stage of its own: its residuals ride in the result (_linear_residuals)
    sol, steady_linear = steady_or_hand_held(pre, result.tracks, result.relations, result.linear.camera,
                                             config.linear, config.graph, sol)
    if steady_linear is not None or resolved:
        return place(sol)
    if hand is None:
        return place(solve_at_final_scale(pre, result.tracks, result.relations, result.linear, config.graph, sol))
    return place(*_styled({k: sol.residuals[k] for k in ("spin_style", "steady_check") if k in sol.residuals},
                          hand, free))


def _styled(style: dict, *solutions: Solution | None) -> tuple[Solution | None, ...]:
    """Returns ``solutions`` with what the spin style decided in their residuals (the points' placement made before
    the style's trial carries it as the placement from the styled solution would)."""
    for s in solutions:
        if s is not None:
            s.residuals.update(style)
    return solutions


# --- outputs ----------------------------------------------------------------------------------------

def _export(tmp: Path, capture: Capture, segments: Segments, result: RunResult, summary: dict, *,
            rerun: bool, spawn: bool, views: bool) -> None:
    from .export import export_reconstruction, write_summary

    sol = result.solution
    colors = (line_colors(result.preprocessed, result.tracks) if result.tracks is not None
              else np.zeros((0, 3), np.uint8))
    if sol is not None:
        summary.update(export_reconstruction(tmp, sol, capture.frame_names, colors[:, ::-1], summary))
        if views:
            t0 = time.perf_counter()
            from .views import render_views

            title = Path(capture.root).name
            render_views(tmp / "views", sol.lines, colors, sol.centers, sol.registered, sol.metric, title=title)
            summary["seconds"]["views"] = round(time.perf_counter() - t0, 3)
    if rerun and result.preprocessed is not None:
        t0 = time.perf_counter()
        from .viz import log_recording

        log_recording(tmp / "recording.rrd", capture, result.preprocessed, result.tracks, result.relations,
                      sol, spawn=spawn, batches=result.batches or None, line_colors=colors,
                      thumbnails=result.thumbnails, frame_status=frame_status(result, capture.n_frames))
        summary["seconds"]["rerun"] = round(time.perf_counter() - t0, 3)
    summary["peak_memory_mb"] = round(peak_memory_mb(), 1)
    write_summary(tmp / "summary.json", summary)


def run_demo(out_dir: str | Path, *, scene: str = "living", n_frames: int = 300,
             size: tuple[int, int] = (960, 540), seed: int = 0, config: Config = Config(),
             spawn: bool = False) -> RunResult:
    """Returns the result of synthesising a small capture into ``out/capture`` and reconstructing it.

    The demo gives the camera height (metric scale) and scores the result
    against the synthetic ground truth (``out/reconstruction/eval.json``).
    The capture has no per-frame normal/depth maps (``gt_maps=False``), to
    keep it small: ``--normals oracle`` needs a capture from ``panosfm synth``.
    """
    from .evaluate import evaluate_reconstruction
    from .synth import synthesize

    out_dir = Path(out_dir)
    check_output_dir(out_dir)
    cap_dir = out_dir / "capture"
    marker = out_dir / "capture.json"
    wanted = {"scene": scene, "n_frames": n_frames, "size": list(size), "seed": seed}
    import json

    if not (cap_dir.exists() and marker.exists() and json.loads(marker.read_text()) == wanted):
        if cap_dir.exists():
            shutil.rmtree(cap_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        log.info("synthesising a %d-frame %dx%d capture of scene %r", n_frames, size[0], size[1], scene)
        synthesize(cap_dir, scene=scene, n_frames=n_frames, size=size, seed=seed, gt_maps=False)
        marker.write_text(json.dumps(wanted))
    if config.linear.camera_height_m is None:
        from .capture import load_capture

        gt = load_capture(cap_dir, config.capture).ground_truth
        height = gt.camera_height_m if gt is not None else 1.5
        config = dataclasses.replace(config, linear=dataclasses.replace(config.linear, camera_height_m=height))
    result = run_pipeline(cap_dir, out_dir / "reconstruction", config, spawn=spawn, resume=True)
    metrics = evaluate_reconstruction(cap_dir, out_dir / "reconstruction")
    from .export import to_jsonable

    (out_dir / "reconstruction" / "eval.json").write_text(json.dumps(to_jsonable(metrics), indent=2))
    result.summary["eval"] = metrics
    return result
