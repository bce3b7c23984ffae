"""The rerun recording of a run: per-frame inputs and results, incremental batches, the paper's three views.

Entities (world frame: right-handed, metres, +z up):

``frame`` timeline
  ``world/camera``                Transform3D (solution pose when registered, else refined rotation)
  ``world/camera/image``          Pinhole (static) + JPEG of the downscaled frame
  ``world/camera/image/segments`` LineStrips2D: segments coloured by Manhattan axis
                                  (x red, y green, z blue, unlabelled grey); tracked ones thick
  ``world/camera/image/relations``LineStrips2D: this frame's relations, midpoint to midpoint
  ``world/camera/image/floor``    Points2D: midpoints of segments on the floor (floor relations)
  ``world/lines``                 LineStrips3D: the 3D lines whose tracks were seen so far
  ``world/cameras``               Points3D: registered camera centres so far (green: fixed by lines, blue: placed
                                  by point tracks, orange: by the motion model alone)
  ``status``                      TextLog: "registered" with its std (WARN where doubtful), or why the frame is not (WARN);
                                  the run's verdict (static: "trusted", or "doubtful" and why)
``batch`` timeline (incremental solves)
  ``batch/lines``, ``batch/cameras``
static (the final model, paper §4 'three views')
  ``final/quarter/lines``   lines in their average image colour
  ``final/height/lines``    lines coloured by height above the floor (heat map)
  ``final/topdown/lines``, ``final/topdown/vertical``, ``final/topdown/cameras``: a 2D
                            orthographic projection with camera centres in green

The blueprint shows the per-frame views on top and the three final views below.
"""
from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .data import FLOOR, RELATION_NAMES, Preprocessed, Relations, Solution, Thumbnails, Tracks
from .errors import InputError
from .thumbnails import jpeg_thumbnail
from .views import (
    _model_box,
    _Perspective,
    floor_height,
    height_colors,
    height_top,
    is_horizontal,
    subdivide,
    track_colors,
    valid_line_mask,
)

log = logging.getLogger(__name__)

# RGB colours: Manhattan axes x, y, z, then unlabelled (index -1 maps to the last row).
AXIS_RGB = np.array([[230, 50, 50], [50, 200, 50], [60, 110, 240], [150, 150, 150]], dtype=np.uint8)
# RGB colours per relation kind: orthogonal, parallel, junction, floor.
RELATION_RGB = np.array([[255, 0, 255], [0, 230, 230], [255, 220, 0], [255, 140, 0]], dtype=np.uint8)
CAMERA_RGB = (40, 200, 40)
MOTION_MODEL_RGB = (240, 150, 30)  # frames placed by the spin's motion model (graph.place_by_motion_model)
POINTS_RGB = (40, 170, 230)  # frames placed by point tracks in the motion model's graph
DOUBTFUL_RGB = (230, 30, 30)  # frames the reliability check doubts (graph.reliability), whatever placed them


def camera_colors(solution: Solution) -> np.ndarray:
    """Returns (F, 3) uint8 RGB per frame: green where the lines fix the frame, blue where point tracks and orange
    where the motion model alone placed it; red where the reliability check doubts it."""
    src = (solution.residuals or {}).get("frame_source") or [None] * len(solution.registered)
    out = np.tile(np.array(CAMERA_RGB, np.uint8), (len(solution.registered), 1))
    out[[s == "motion model" for s in src]] = MOTION_MODEL_RGB
    out[[s == "points" for s in src]] = POINTS_RGB
    doubt = (solution.residuals or {}).get("frame_doubtful")
    if doubt is not None and len(doubt) == len(out):
        out[np.asarray(doubt, bool)] = DOUBTFUL_RGB
    return out
MODEL_UPDATES = 60  # the growing 3D model is logged at most this many times on the frame timeline


class ViewerError(InputError):
    """The rerun viewer could not be started (no display, no ``rerun`` executable, a bad file)."""


def _axis_rgb(axis: np.ndarray) -> np.ndarray:
    a = np.asarray(axis, dtype=np.int64)
    return AXIS_RGB[np.where((a >= 0) & (a <= 2), a, 3)]


def _strips3d(ends: np.ndarray) -> np.ndarray:
    return np.asarray(ends, dtype=np.float32).reshape(-1, 2, 3)


def _first_seen(pre: Preprocessed, tracks: Tracks | None) -> np.ndarray:
    """Returns (T,) the first frame in which each track has a segment (large where none)."""
    if tracks is None:
        return np.zeros(0, dtype=np.int64)
    first = np.full(tracks.n, np.iinfo(np.int64).max, dtype=np.int64)
    seg = np.flatnonzero(tracks.track_of >= 0)
    np.minimum.at(first, tracks.track_of[seg], pre.segments.frame[seg].astype(np.int64))
    return first


def _frame_images(capture: Any, n: int):
    """Yields the capture's frames in order: sequential reads when the capture offers them."""
    if hasattr(capture, "frames"):
        yield from capture.frames()
    else:
        for i in range(n):
            yield capture.frame(i)


def _encode(img_bgr: np.ndarray, width: int) -> bytes:
    return jpeg_thumbnail(img_bgr, width)


def _scene_box(solution: Solution | None) -> tuple[np.ndarray, np.ndarray]:
    if solution is None:
        return -np.ones(3), np.ones(3)
    ends = solution.lines.endpoints[valid_line_mask(solution.lines)]
    cams = solution.centers[np.asarray(solution.registered, bool)]
    return _model_box(ends, cams[np.all(np.isfinite(cams), axis=1)])


def _blueprint(solution: Solution | None, batches: list[Solution] | None, lo: np.ndarray, hi: np.ndarray,
               frame_status: bool = False):
    import rerun.blueprint as rrb

    top = [rrb.Spatial3DView(origin="world", name="scene (frame timeline)"),
           rrb.Spatial2DView(origin="world/camera/image", name="image, segments, relations")]
    if frame_status:
        top.append(rrb.TextLogView(origin="status", name="frame status"))
    if batches:
        top.append(rrb.Spatial3DView(origin="batch", name="incremental solve (batch timeline)"))
    rows = [rrb.Horizontal(*top)]
    if solution is not None:
        cam = _Perspective(lo, hi, (1024, 768))
        target = (lo + hi) / 2

        def eye() -> Any:
            return rrb.EyeControls3D(position=cam.eye, look_target=target, eye_up=[0.0, 0.0, 1.0])

        n_reg = int(np.sum(solution.registered))
        n_all = len(solution.registered)
        pct = 100.0 * n_reg / max(n_all, 1)
        pad = 0.08 * float(max(hi[0] - lo[0], hi[1] - lo[1]))
        bounds = rrb.VisualBounds2D(x_range=[lo[0] - pad, hi[0] + pad], y_range=[-hi[1] - pad, -lo[1] + pad])
        rows.append(rrb.Horizontal(
            rrb.Spatial3DView(origin="final/quarter", name="quarter view (average colour)", eye_controls=eye()),
            rrb.Spatial3DView(origin="final/height", name="height above floor (heat map)", eye_controls=eye()),
            rrb.Spatial2DView(origin="final/topdown", visual_bounds=bounds,
                              name=f"top-down: registered {n_reg}/{n_all} ({pct:.1f} %)"),
        ))
    return rrb.Blueprint(rrb.Vertical(*rows), collapse_panels=False)


def _log_final(rec: Any, solution: Solution, line_colors: np.ndarray | None) -> None:
    """Logs the paper's three views of the final model as static entities (paper §4)."""
    import rerun as rr

    lines = solution.lines
    valid = valid_line_mask(lines)
    ends = lines.endpoints[valid]
    show = np.asarray(solution.registered, bool) & np.all(np.isfinite(solution.centers), axis=1)
    cams, cam_rgb = solution.centers[show], camera_colors(solution)[show]
    for view in ("final/quarter", "final/height"):
        rec.log(view, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log(f"{view}/cameras", rr.Points3D(cams, colors=cam_rgb, radii=rr.Radius.ui_points(3.0)), static=True)
    if line_colors is not None:
        rgb = np.asarray(line_colors, dtype=np.uint8)[valid][:, ::-1]
    else:
        rgb = np.full((len(ends), 3), 120, dtype=np.uint8)
    rec.log("final/quarter/lines", rr.LineStrips3D(_strips3d(ends), colors=rgb, radii=rr.Radius.ui_points(2.0)),
            static=True)
    z0 = floor_height(lines)
    top = height_top(ends, z0)
    sub = subdivide(ends, 8)
    heat = height_colors(0.5 * (sub[:, 2] + sub[:, 5]) - z0, top)[:, ::-1]
    rec.log("final/height/lines", rr.LineStrips3D(_strips3d(sub), colors=heat, radii=rr.Radius.ui_points(2.0)),
            static=True)
    # top-down: 2D coordinates (x, -y) so that +y points up on screen
    axis = np.asarray(lines.axis)[valid]
    horiz = is_horizontal(ends)
    flip = np.array([1.0, -1.0], dtype=np.float32)
    h2 = np.stack([ends[horiz][:, 0:2], ends[horiz][:, 3:5]], axis=1).astype(np.float32) * flip
    rec.log("final/topdown/lines", rr.LineStrips2D(h2, colors=_axis_rgb(axis[horiz]), radii=rr.Radius.ui_points(1.5)),
            static=True)
    v = ends[~horiz]
    rec.log("final/topdown/vertical", rr.Points2D((0.5 * (v[:, 0:2] + v[:, 3:5])).astype(np.float32) * flip,
                                                  colors=_axis_rgb(axis[~horiz]), radii=rr.Radius.ui_points(3.0)),
            static=True)
    rec.log("final/topdown/cameras", rr.Points2D(cams[:, :2].astype(np.float32) * flip, colors=cam_rgb,
                                                 radii=rr.Radius.ui_points(3.0), draw_order=10.0), static=True)


def log_recording(path: str | Path | None, capture: Any, pre: Preprocessed, tracks: Tracks | None,
                  relations: Relations | None, solution: Solution | None, *, spawn: bool = False,
                  batches: list[Solution] | None = None, image_width: int = 480,
                  line_colors: np.ndarray | None = None, model_updates: int = MODEL_UPDATES,
                  thumbnails: Thumbnails | None = None, frame_status: list[str] | None = None) -> Path | None:
    """Returns the path of the finalised rerun recording of a run (or None when only spawned).

    ``capture`` needs ``camera``, ``n_frames`` and ``frame(i)`` (BGR; ``frames()``
    is used when present). ``line_colors`` (T, 3) uint8 BGR defaults to the
    tracks' average segment colours. Frames are logged as JPEGs ``image_width``
    pixels wide (``thumbnails`` made during detection are used as they are,
    so frames are not decoded twice); the growing 3D model at most
    ``model_updates`` times.
    ``frame_status`` (one string per frame, e.g. :func:`summary.unregistered_why`) is logged on
    the frame timeline, so scrubbing shows why a frame has no pose.
    ``spawn`` also streams to a live viewer (skipped with a warning when none
    can start). The recording is finalised (``disconnect``) even on errors.
    """
    import rerun as rr

    if path is None and not spawn:
        raise ValueError("log_recording: give a path, spawn=True, or both")
    t_start = time.perf_counter()
    segs = pre.segments
    F = int(capture.n_frames)
    cam = solution.camera if solution is not None else capture.camera
    if thumbnails is not None and thumbnails.n == F:
        image_width = thumbnails.width
    else:
        thumbnails = None
    sc = image_width / float(cam.width)
    img_h = max(1, round(cam.height * sc))
    lo, hi = _scene_box(solution)
    if line_colors is None and tracks is not None and tracks.n:
        line_colors = track_colors(segs, tracks)
    blueprint = _blueprint(solution, batches, lo, hi, frame_status=bool(frame_status))

    rec = rr.RecordingStream("panosfm", recording_id=str(uuid.uuid4()))
    sinks = []
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(str(path)))
    if spawn:
        if _display_available():
            try:
                rr.spawn(connect=False, default_blueprint=blueprint)
                sinks.append(rr.GrpcSink())
            except Exception as exc:  # the viewer is optional: keep the file
                log.warning("could not start the rerun viewer (%s); recording to file only", exc)
        else:
            log.warning("no display: not opening the rerun viewer%s",
                        "; recording to file only" if sinks else "; nothing recorded")
    if not sinks:
        return None
    rec.set_sinks(*sinks, default_blueprint=blueprint)
    try:
        _log_frames(rec, capture, pre, tracks, relations, solution, F, sc, image_width, img_h, lo, hi,
                    model_updates, thumbnails, frame_status)
        if batches:
            rec.reset_time()
            rec.log("batch", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
            for b, sol in enumerate(batches):
                rec.set_time("batch", sequence=b)
                ok = valid_line_mask(sol.lines)
                rec.log("batch/lines", rr.LineStrips3D(_strips3d(sol.lines.endpoints[ok]),
                                                       colors=_axis_rgb(sol.lines.axis[ok]),
                                                       radii=rr.Radius.ui_points(1.5)))
                c = sol.centers[np.asarray(sol.registered, bool)]
                rec.log("batch/cameras", rr.Points3D(c, colors=CAMERA_RGB, radii=rr.Radius.ui_points(3.0)))
        if solution is not None:
            rec.reset_time()
            _log_final(rec, solution, line_colors)
            v = (solution.residuals or {}).get("verify")
            if v:  # graph.reliability's verdict, beside the frames' statuses
                text = f"verdict: {v['verdict']}" + (f" ({'; '.join(v['reasons'])})" if v["reasons"] else "")
                rec.log("status", rr.TextLog(text, level=rr.TextLogLevel.WARN if v["verdict"] != "trusted"
                                             else rr.TextLogLevel.INFO), static=True)
    finally:
        rec.flush()
        rec.disconnect()
    log.info("rerun recording: %d frames logged in %.2f s", F, time.perf_counter() - t_start)
    return path


def _log_frames(rec: Any, capture: Any, pre: Preprocessed, tracks: Tracks | None, relations: Relations | None,
                solution: Solution | None, F: int, sc: float, image_width: int, img_h: int,
                lo: np.ndarray, hi: np.ndarray, model_updates: int, thumbnails: Thumbnails | None = None,
                frame_status: list[str] | None = None) -> None:
    """Logs the ``frame`` timeline: image, segments, relations, camera, lines placed so far, status."""
    import rerun as rr

    segs = pre.segments
    K = (solution.camera if solution is not None else capture.camera).K * np.array([[sc], [sc], [1.0]])
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    plane = 0.1 * float(np.max(hi - lo))
    rec.log("world/camera/image", rr.Pinhole(image_from_camera=K, width=image_width, height=img_h,
                                             camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=plane),
            static=True)
    # per-segment constants
    seg_rgba = np.concatenate([_axis_rgb(pre.labels), np.full((segs.n, 1), 255, np.uint8)], axis=1)
    track_of = tracks.track_of if tracks is not None else np.full(segs.n, -1, np.int32)
    tracked = track_of >= 0
    seg_rgba[~tracked, 3] = 150  # untracked segments: thinner and translucent
    seg_radii = np.where(tracked, 1.6, 0.7).astype(np.float32) * max(sc * 2, 0.5)
    strips_all = (segs.endpoints.astype(np.float32) * sc).reshape(-1, 2, 2)
    mids_all = segs.midpoints.astype(np.float32) * sc
    T = tracks.n if tracks is not None else 0
    first = _first_seen(pre, tracks)
    rel_ok = relations is not None and relations.n > 0 and T > 0
    # the growing model
    if solution is not None:
        line_valid = valid_line_mask(solution.lines)
        line_ends = solution.lines.endpoints
        line_rgb = _axis_rgb(solution.lines.axis)
        if len(first) != len(line_valid):  # a model not built from these tracks: show it whole
            first = np.zeros(len(line_valid), dtype=np.int64)
        reg = np.asarray(solution.registered, bool)
        known = reg.copy()
        centers = solution.centers
        fallback_c = np.nanmean(centers[reg], axis=0) if reg.any() else np.zeros(3)
        cam_rgb = camera_colors(solution)
    every = max(1, int(np.ceil(F / max(model_updates, 1))))
    last_count = -1
    seg_in_frame = np.full(max(T, 1), -1, dtype=np.int64)

    images = (thumbnails.get(i) for i in range(F)) if thumbnails is not None else _frame_images(capture, F)
    for i, img in enumerate(images):
        if i >= F:
            break
        rec.set_time("frame", sequence=i)
        jpeg = img if isinstance(img, bytes) else _encode(img, image_width)
        rec.log("world/camera/image", rr.EncodedImage(contents=jpeg, media_type="image/jpeg"))
        if frame_status is not None and i < len(frame_status):
            ok = frame_status[i].startswith("registered")
            text = f"frame {i}: " + (frame_status[i] if ok else f"not registered: {frame_status[i]}")
            good = ok and "doubtful" not in frame_status[i]
            rec.log("status", rr.TextLog(text, level=rr.TextLogLevel.INFO if good else rr.TextLogLevel.WARN))
        if solution is not None and known[i]:
            rec.log("world/camera", rr.Transform3D(translation=centers[i], mat3x3=solution.R_wc[i]))
        else:
            c = fallback_c if solution is not None else np.zeros(3)
            rec.log("world/camera", rr.Transform3D(translation=c, mat3x3=pre.R_wc[i]))
        sl = segs.of_frame(i)
        rec.log("world/camera/image/segments",
                rr.LineStrips2D(strips_all[sl], colors=seg_rgba[sl], radii=seg_radii[sl]))
        if rel_ok:
            ids = np.arange(sl.start, sl.stop)
            t_here = track_of[sl]
            seg_in_frame[t_here[t_here >= 0]] = ids[t_here >= 0]
            a = seg_in_frame[relations.track_a]
            b = np.where(relations.track_b >= 0, seg_in_frame[np.maximum(relations.track_b, 0)], -1)
            pair = (a >= 0) & (b >= 0) & (relations.kind != FLOOR)
            links = np.stack([mids_all[a[pair]], mids_all[b[pair]]], axis=1)
            rec.log("world/camera/image/relations",
                    rr.LineStrips2D(links, colors=RELATION_RGB[relations.kind[pair]], radii=1.0,
                                    class_ids=relations.kind[pair].astype(np.uint16)))
            fl = (a >= 0) & (relations.kind == FLOOR)
            rec.log("world/camera/image/floor",
                    rr.Points2D(mids_all[a[fl]], colors=RELATION_RGB[FLOOR], radii=3.0))
            seg_in_frame[t_here[t_here >= 0]] = -1
        if solution is not None and (i % every == 0 or i == F - 1):
            placed = line_valid & (first <= i)
            count = int(placed.sum())
            if count != last_count:
                rec.log("world/lines", rr.LineStrips3D(_strips3d(line_ends[placed]), colors=line_rgb[placed],
                                                       radii=rr.Radius.ui_points(1.5)))
                last_count = count
            rec.log("world/cameras", rr.Points3D(centers[: i + 1][reg[: i + 1]], colors=cam_rgb[: i + 1][reg[: i + 1]],
                                                 radii=rr.Radius.ui_points(2.5)))


def relation_legend() -> dict[str, tuple[int, int, int]]:
    """Returns the RGB colour of each relation kind as drawn in ``world/camera/image/relations``."""
    return {name: tuple(int(c) for c in RELATION_RGB[k]) for k, name in enumerate(RELATION_NAMES)}


def _display_available() -> bool:
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _viewer_executable() -> str | None:
    exe = shutil.which("rerun")
    if exe is None:
        cand = Path(sys.executable).parent / "rerun"
        exe = str(cand) if cand.exists() else None
    return exe


def view_recording(path: str | Path, wait_s: float = 2.0) -> subprocess.Popen:
    """Returns the viewer process after opening a saved recording (``recording.rrd``) in the rerun viewer.

    Raises :class:`ViewerError` (an ``InputError``: one line, exit status 2 in
    the CLI) when the file is missing or not an RRD, when there is no display,
    or when the viewer exits within ``wait_s`` seconds.
    """
    path = Path(path)
    if not path.is_file():
        raise ViewerError("no such recording (expected a .rrd file or a run directory holding recording.rrd)", path)
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic not in (b"RRF2", b"RRF0", b"RRF1"):
        raise ViewerError("not a rerun recording (.rrd)", path)
    if not _display_available():
        raise ViewerError("cannot open the rerun viewer: no display (DISPLAY/WAYLAND_DISPLAY unset); "
                          "copy the file to a machine with a screen and run `rerun <file>` there", path)
    exe = _viewer_executable()
    if exe is None:
        raise ViewerError("cannot open the rerun viewer: the `rerun` executable is not installed "
                          "(pip install rerun-sdk)", path)
    proc = subprocess.Popen([exe, str(path)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        proc.wait(timeout=wait_s)
    except subprocess.TimeoutExpired:
        return proc  # still running: the viewer is up
    err = (proc.stderr.read() if proc.stderr else b"").decode(errors="replace").strip().splitlines()
    if proc.returncode != 0:
        raise ViewerError(f"the rerun viewer exited with status {proc.returncode}: "
                          f"{err[-1] if err else 'no message'}", path)
    return proc
