"""Streaming reconstruction (issue 42): frames arrive in batches, an estimate after each batch (paper §3).

``Reconstruction(camera, config).add_frames(images, timestamps, imu_rotations)`` returns the current
:class:`~panosfm_graph.data.Solution` of the frames so far. Per-frame work is done once, for the new
frames only, as they arrive: line segment detection (§3.1, the costliest stage, in a worker pool kept
across batches), the point tracks (extended into the new frames, :class:`points.PointTracker`) and the
surface normals (§3.2) of the new frames and of the old frames whose fusion neighbourhood they join
(``normals.fuse_deg``) or whose rotation moved (``normals.stream_keep_deg``). The Manhattan frame (refined,
not voted again) and the rotations (§3.1) are warm-started from the last batch (:func:`lines.refine_warm`);
tracking, relations (§3.2), the linear solve (§3.3) and the bundle adjustment (§3.4, the motion model with the
point tracks) run again over all frames so far. A batch before the last is a preview: no joint solve with the
point tracks (``graph.incremental_joint``; docs/decisions.md#previews-without-the-joint-solve). The last batch
(``add_frames(..., final=True)``) joins every observation; with ``graph.incremental_final_solve`` it is the final
full solve instead: every stage over all frames from the same segments, point tracks and (where the rotations
hardly moved) normals, as the one-shot :func:`pipeline.run_pipeline` (:meth:`Reconstruction.finish` solves so
after any batch). :func:`stream_capture` feeds a capture directory to it, N frames at a time
(``panosfm run --incremental N``). Figures: docs/benchmarks.md#streaming-with-point-tracks-2026-12-07.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections import deque
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import cv2
import numpy as np

from .config import Config
from .data import Camera, Capture, GroundTruth, LineModel, NormalMaps, PointTracks, Preprocessed, Relations, Segments, \
    Solution, Thumbnails, Tracks
from .errors import InputError, TooFewLinesError
from .progress import stage

log = logging.getLogger("panosfm.stream")


def empty_solution(camera: Camera, R_wc: np.ndarray, why: str) -> Solution:
    """Returns a Solution of ``len(R_wc)`` frames with none registered and no line (``residuals["why"]``)."""
    n = len(R_wc)
    lines = LineModel(taylor=np.zeros((0, 3)), direction=np.zeros((0, 3)), axis=np.zeros(0, np.int8),
                      extent=np.zeros((0, 2)), valid=np.zeros(0, bool))
    return Solution(R_wc=np.array(R_wc, np.float64), centers=np.full((n, 3), np.nan), registered=np.zeros(n, bool),
                    lines=lines, camera=camera, metric=False, residuals={"why": why})


class Reconstruction:
    """A reconstruction that grows as frames arrive (module docstring; paper §3 per batch).

    ``camera`` is at the working resolution of the images passed in. ``reader`` (index -> BGR image)
    gives old frames back where a stage needs them (the ``model`` normals, the point tracks' loop a turn back);
    without it the images are kept in memory for the ``model`` normals, and their grey levels for the point
    tracks (0.5 MB a frame at 960x540). ``frame_names``, ``root`` and ``ground_truth`` (all
    frames) describe a capture on disk (``oracle`` normals need the ground truth).
    ``thumbnail_width``: keep each frame's JPEG thumbnail (the rerun timeline).
    ``estimate_focal``: the focal length from the Manhattan vanishing points of the first batch
    (``lines/focal.py``), estimated again over all frames by :meth:`finish`.
    Use as a context manager, or call :meth:`close` (the detection workers).
    """

    def __init__(self, camera: Camera, config: Config = Config(), *, reader: Callable[[int], np.ndarray] | None = None,
                 frame_names: Sequence[str] | None = None, root: str | Path | None = None,
                 ground_truth: GroundTruth | None = None, thumbnail_width: int | None = None,
                 estimate_focal: bool = False):
        self.camera = camera
        self.config = dataclasses.replace(config, graph=dataclasses.replace(config.graph, incremental_batch=None))
        self._reader = reader
        self._names = tuple(frame_names) if frame_names is not None else None
        self._root = Path(root) if root is not None else Path("<stream>")
        self._gt = ground_truth
        self._thumb_width = thumbnail_width
        self._estimate_focal = estimate_focal
        self._keep_images = reader is None and config.normals.source == "model"
        self._images: list[np.ndarray] = []
        # the grey frames the point tracks read: without a reader all, with one the last batch's (read once, not twice)
        self._greys: dict[int, np.ndarray] = {}
        self._tracker = None  # points.PointTracker over the frames so far
        self._detected: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._thumbs: list[bytes] = []
        self._timestamps = np.zeros(0)
        self._imu = np.zeros((0, 3, 3))
        self._normals: NormalMaps | None = None
        self._made_axes = np.zeros((0, 3, 3))  # per frame: the camera-frame Manhattan axes its normal map was made with
        self._made_K = np.eye(3)  # ... and the camera (an estimated focal length may change)
        self._made_R = np.zeros((0, 3, 3))  # ... and the rotations its world normals are expressed with
        self._pool = None
        self.focal: Any = None  # lines.focal.FocalEstimate where estimated
        self.preprocessed: Preprocessed | None = None
        self.tracks: Tracks | None = None
        self.relations: Relations | None = None
        self.linear: Solution | None = None
        self.solution: Solution | None = None
        self.batches: list[Solution] = []  # one per add_frames, then the final solve
        self.stage_seconds: dict[str, float] = {}  # summed over the batches

    # --- the public surface -------------------------------------------------------------------------

    @property
    def n_frames(self) -> int:
        return len(self._detected)

    @property
    def segments(self) -> Segments:
        """Returns the segments of the frames so far (frame order)."""
        from .lines.detect import segments_of_frames

        return segments_of_frames(self._detected)

    @property
    def thumbnails(self) -> Thumbnails | None:
        if self._thumb_width is None or not self._thumbs:
            return None
        return Thumbnails.from_list(self._thumbs, min(self._thumb_width, self.camera.width))

    def add_frames(self, images: Iterable[np.ndarray], timestamps: np.ndarray, imu_rotations: np.ndarray,
                   final: bool = False) -> Solution:
        """Returns the estimate of all frames so far after adding a batch (BGR images, seconds, (k, 3, 3) R_wc).

        ``images`` may be a generator: each frame's detection starts as it arrives. The Solution's
        ``residuals["batch_seconds"]`` is the latency, from the batch's last frame's arrival to the
        estimate; ``["stage_seconds"]`` the call's time per stage (``detect`` while frames arrive).
        Before enough lines exist, the estimate registers no frame (``residuals["why"]``). ``final``:
        the last batch: every point observation joined, and with ``graph.incremental_final_solve`` solved as
        :meth:`finish` does (the final full solve in place of its estimate).
        A malformed batch raises InputError and leaves the reconstruction as it was.
        """
        ts, R = self._check(timestamps, imu_rotations)
        timings: dict[str, float] = {}
        with stage("detect", timings):
            detected, thumbs, kept, greys, t_last = self._detect(images, len(ts))
        self._detected.extend(detected)
        self._thumbs.extend(thumbs)
        self._images.extend(kept)
        if self._reader is not None:
            self._greys.clear()
        self._greys.update(zip(range(self.n_frames - len(greys), self.n_frames), greys))
        self._timestamps = np.concatenate([self._timestamps, ts])
        self._imu = np.concatenate([self._imu, R])
        sol = self._solve(full=final and self.config.graph.incremental_final_solve, last=final, timings=timings)
        if final:
            sol.residuals["incremental_batches"] = len(self.batches) + 1
        return self._record(sol, t_last, timings)

    def finish(self) -> Solution:
        """Returns the final full solve: every stage over all frames from the segments and point tracks so far
        (as one-shot)."""
        if not self.n_frames:
            raise InputError("no frames were added to the reconstruction", self._root)
        t0 = time.perf_counter()
        timings: dict[str, float] = {}
        sol = self._solve(full=True, last=True, timings=timings)
        sol.residuals["incremental_batches"] = len(self.batches) + 1
        return self._record(sol, t0, timings)

    def _record(self, sol: Solution, t0: float, timings: dict[str, float]) -> Solution:
        """Returns ``sol`` with its seconds since ``t0`` and per stage, appended to :attr:`batches`."""
        sol.residuals["batch_seconds"] = time.perf_counter() - t0
        sol.residuals["stage_seconds"] = {k: round(v, 3) for k, v in timings.items()}
        for k, v in timings.items():
            self.stage_seconds[k] = self.stage_seconds.get(k, 0.0) + v
        self.batches.append(sol)
        return sol

    def close(self) -> None:
        """Stops the detection workers."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __enter__(self) -> "Reconstruction":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- the work -----------------------------------------------------------------------------------

    def _check(self, timestamps: np.ndarray, imu_rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Returns the batch's timestamps and rotations as arrays; InputError on malformed ones."""
        ts = np.asarray(timestamps, np.float64).reshape(-1)
        R = np.asarray(imu_rotations, np.float64)
        k = len(ts)
        if k == 0:
            raise InputError("a batch needs at least one frame", self._root)
        if R.shape != (k, 3, 3):
            raise InputError(f"a batch of {k} timestamps needs ({k}, 3, 3) IMU rotations, got {R.shape}", self._root)
        last = self._timestamps[-1] if len(self._timestamps) else -np.inf
        if not np.all(np.diff(np.concatenate([[last], ts])) > 0):
            raise InputError("frame timestamps must increase across batches", self._root)
        return ts, R

    def _detect(self, images: Iterable[np.ndarray], k: int) -> tuple[list, list[bytes], list[np.ndarray],
                                                                     list[np.ndarray], float]:
        """Returns the new frames' :func:`lines.detect.detect_frame` results (paper §3.1), their thumbnails,
        the images and grey images to keep and when the last frame arrived; each frame goes to the worker pool as
        it arrives."""
        from .lines.detect import detect_frame
        from .parallel import process_pool
        from .thumbnails import jpeg_thumbnail

        cfg, K, dist = self.config.detect, self.camera.K, self.camera.distortion
        workers = max(1, min(int(cfg.workers), os.cpu_count() or 1))
        if workers > 1 and self._pool is None:
            self._pool = process_pool(workers)
        shape = (self.camera.height, self.camera.width)
        out: list = []
        pending: deque = deque()  # a sliding window of frames in the pool, as detect_segments keeps
        thumbs: list[bytes] = []
        kept: list[np.ndarray] = []
        greys: list[np.ndarray] = []
        count = 0
        for im in images:
            im = np.asarray(im)
            if im.shape[:2] != shape:
                raise InputError(f"frame {self.n_frames + count} is {im.shape[1]}x{im.shape[0]}, the camera "
                                 f"{shape[1]}x{shape[0]}", self._root)
            count += 1
            if self._thumb_width is not None:
                thumbs.append(jpeg_thumbnail(im, min(self._thumb_width, im.shape[1])))
            if self._keep_images:
                kept.append(im)
            if self._track_points:
                greys.append(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY))
            if self._pool is None:
                out.append(detect_frame(im, cfg, K, dist))
                continue
            pending.append(self._pool.submit(detect_frame, im, cfg, K, dist))
            if len(pending) > 4 * workers:
                out.append(pending.popleft().result())
        t_last = time.perf_counter()
        out.extend(f.result() for f in pending)
        if count != k:
            raise InputError(f"a batch of {k} timestamps got {count} images", self._root)
        return out, thumbs, kept, greys, t_last

    def _capture(self) -> Capture:
        """Returns the frames so far as a :class:`Capture` (the stages' input)."""
        n = self.n_frames
        names = self._names[:n] if self._names is not None else tuple(f"frame{i:06d}" for i in range(n))
        gt = self._gt
        if gt is not None:
            gt = dataclasses.replace(gt, R_wc=gt.R_wc[:n], centers=gt.centers[:n])
        return Capture(root=self._root, camera=self.camera, frame_names=names, timestamps=self._timestamps.copy(),
                       R_wc_imu=self._imu.copy(), ground_truth=gt, reader=self._read)

    def _read(self, i: int) -> np.ndarray:
        if self._reader is not None:
            return self._reader(i)
        if self._keep_images:
            return self._images[i]
        raise InputError("the stream keeps no images (only the 'model' normals read them again)", self._root)

    def _solve(self, *, full: bool, last: bool, timings: dict[str, float]) -> Solution:
        """Returns the estimate over the frames so far: stages after detection (module docstring).

        ``full``: every stage as the one-shot run does (preprocessing from the IMU, the focal length over all
        frames), from the point tracks so far; else warm-started. Either way the normals of the frames the batch
        changed (:meth:`_normals_of`). ``last``: the joint solve with every point observation (else a preview:
        ``graph.incremental_joint``, ``incremental_points_per_frame``, ``incremental_steady``, ``incremental_anchored``).
        """
        from .lines import refine_manhattan_and_rotations, refine_warm, track_lines
        from .linear import solve_linear
        from .pipeline import RunResult, _bundle_adjust
        from .relations import detect_relations

        cfg = self.config
        if not last:  # a preview: no joint solve, or one with the motion model's few observations per frame
            cfg = dataclasses.replace(cfg, points=dataclasses.replace(
                cfg.points, per_frame_joint=int(cfg.graph.incremental_points_per_frame)))
            g = cfg.graph
            if not g.incremental_joint:
                g = dataclasses.replace(g, points_joint_max_line_rms_ratio=0.0)
            if not g.incremental_steady and cfg.points.enabled:  # the points place what the lines leave
                g = dataclasses.replace(g, steady_auto=False)
            if not g.incremental_anchored:
                g = dataclasses.replace(g, motion_anchored=False)
            cfg = dataclasses.replace(cfg, graph=g)
        segments = self.segments
        try:
            if self._estimate_focal and (full or self.focal is None):
                self._focal(segments, timings)
            cap = self._capture()
            with stage("preprocess", timings):
                if full or self.preprocessed is None:
                    pre = refine_manhattan_and_rotations(segments, cap, cfg)
                else:  # the rotations warm-started
                    pre = refine_warm(segments, cap, cfg, self.preprocessed)
        except TooFewLinesError as e:
            if full:
                raise
            log.info("batch of %d frames: no estimate yet (%s)", self.n_frames, e)
            return empty_solution(self.camera, self._imu, str(e))
        with stage("track", timings):
            tracks = track_lines(cap, pre, cfg)
        with stage("normals", timings):
            normals = self._normals_of(cap, pre)
        with stage("relations", timings):
            relations = detect_relations(pre, tracks, normals, cap.camera, cfg.relations)
        with stage("linear", timings):
            linear = solve_linear(pre, tracks, relations, cap.camera, cfg.linear)
        held = RunResult(out_dir=self._root, summary={}, capture=cap, preprocessed=pre, tracks=tracks,
                         relations=relations, linear=linear)
        points = None
        if self._track_points:
            with stage("points", timings):
                points = self._points(cap, pre)
        with stage("bundle_adjust", timings):
            sol = _bundle_adjust(pre, held, cfg, None, (lambda: points) if points is not None else None, verify=full)
        self.preprocessed, self.tracks, self.relations, self.linear, self.solution = pre, tracks, relations, linear, sol
        return sol

    @property
    def _track_points(self) -> bool:
        return bool(self.config.points.enabled)

    def _grey(self, i: int) -> np.ndarray:
        g = self._greys.get(i)
        return g if g is not None else cv2.cvtColor(self._reader(i), cv2.COLOR_BGR2GRAY)

    def _points(self, cap: Capture, pre: Preprocessed) -> PointTracks:
        """Returns the point tracks of the frames so far (``points/tracking.py``): the new frames' steps added to
        the tracks so far, each predicted by the rotations of its batch (docs/decisions.md#streamed-point-tracks)."""
        from .points import PointTracker

        if self._tracker is None:
            self._tracker = PointTracker(self.config.points)
        self._tracker.extend(cap, pre.R_wc, grey=self._grey)
        return self._tracker.tracks()

    def _normals_of(self, cap: Capture, pre: Preprocessed) -> NormalMaps:
        """Returns the normal maps (paper §3.2): of the new frames, of the old ones whose fusion neighbourhood
        (``normals.fuse_deg``) they join and of those whose camera-frame Manhattan axes moved more than
        ``normals.stream_keep_deg`` since their map was made; the other old frames keep theirs, turned with their
        camera where it turned more than that (the final solve's rotations may lie a heading away from a warm
        start's; docs/decisions.md#streamed-normals)."""
        from .normals import estimate_normals

        cfg = self.config.normals
        keep = np.cos(np.radians(max(float(cfg.stream_keep_deg), 0.0)))
        axes = np.einsum("fji,kj->fik", pre.R_wc, pre.manhattan.directions)  # (F, 3, 3), column k: R^T d_k
        same_camera = np.array_equal(self._made_K, cap.camera.K)
        old = 0 if self._normals is None or not same_camera else self._normals.maps.shape[0]
        F, frames, previous, turn_frames = cap.n_frames, None, None, np.zeros(0, np.int64)
        made_axes, made_R = axes, pre.R_wc.copy()  # axes: a fresh array
        if old:
            optical = pre.R_wc[:, :, 2]
            deg = max(float(cfg.fuse_deg), 0.0)
            near = ((optical[:old] @ optical[old:].T).max(axis=1) >= np.cos(np.radians(deg)) if deg > 0
                    and old < F else np.zeros(old, bool))
            # each axis as made against its nearest axis now (the Manhattan frame's labels may have changed)
            agree = np.abs(np.einsum("fik,fij->fkj", self._made_axes[:old], axes[:old])).max(axis=2).min(axis=1)
            again = near | (agree < keep)
            frames = np.concatenate([np.flatnonzero(again), np.arange(old, F)])
            kept = np.flatnonzero(~again)
            made_axes[kept], made_R[kept] = self._made_axes[kept], self._made_R[kept]
            turn = np.einsum("fij,fkj->fik", pre.R_wc[kept], self._made_R[kept])  # R_now R_then^T
            turned = (np.trace(turn, axis1=1, axis2=2) - 1.0) / 2.0 < keep
            turn_frames, turn = kept[turned], turn[turned].astype(np.float32)
            made_R[turn_frames] = pre.R_wc[turn_frames]
            previous = self._normals
            log.info("normals: %d new frames, %d old ones made again (%d joined by the new), %d kept (%d turned)",
                     F - old, int(again.sum()), int(near.sum()), len(kept), int(turned.sum()))
        normals = estimate_normals(cap, pre, cfg, frames=frames, previous=previous)
        if len(turn_frames):  # turned in place, frame by frame: the maps are new, copied from the previous
            maps = normals.maps
            for f, T in zip(turn_frames, turn):
                maps[f] = (maps[f].reshape(-1, 3) @ T.T).reshape(maps.shape[1:])
        self._normals = normals
        self._made_axes, self._made_R, self._made_K = made_axes, made_R, cap.camera.K.copy()
        return self._normals

    def _focal(self, segments: Segments, timings: dict[str, float]) -> None:
        """Estimates the focal length from the frames so far (``lines/focal.py``) and takes it."""
        from .capture.camera import with_focal
        from .lines.focal import estimate_focal

        with stage("focal", timings):
            est = estimate_focal(segments, self._imu, self.camera, self.config.focal, self.config.manhattan)
        self.focal = est
        self.camera = with_focal(self.camera, est.focal_px)


def stream_capture(capture: Capture, config: Config, *, on_batch: Callable[[int, Solution], None] | None = None,
                   thumbnail_width: int | None = None) -> Reconstruction:
    """Returns the :class:`Reconstruction` of a capture fed ``config.graph.incremental_batch`` frames at a time.

    Frames are read batch by batch (as they would arrive); ``on_batch(k, solution)`` sees each
    batch's estimate. The last batch is added with ``final=True``: with ``graph.incremental_final_solve`` the
    final full solve (every stage as the one-shot run, from the streamed segments, point tracks and normals).
    """
    n = int(config.graph.incremental_batch or 0)
    if n < 1:
        raise InputError(f"--incremental needs a batch of at least 1 frame, got {n}", capture.root)
    rec = Reconstruction(capture.camera, config, reader=capture.reader, frame_names=capture.frame_names,
                         root=capture.root, ground_truth=capture.ground_truth, thumbnail_width=thumbnail_width,
                         estimate_focal=not capture.focal_given or config.focal.estimate)
    starts = range(0, capture.n_frames, n)
    with rec:
        for k, a in enumerate(starts):
            idx = np.arange(a, min(a + n, capture.n_frames))
            images = (capture.frame(int(i)) for i in idx)  # read as they arrive, detected as they are read
            sol = rec.add_frames(images, capture.timestamps[idx], capture.R_wc_imu[idx], final=k == len(starts) - 1)
            log.info("batch %d: %d frames, %d registered, %.1f s", k, rec.n_frames, int(sol.registered.sum()),
                     sol.residuals["batch_seconds"])
            if on_batch is not None:
                on_batch(k, sol)
    return rec
