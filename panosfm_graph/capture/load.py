"""load_capture: a capture directory -> a validated :class:`~panosfm_graph.data.Capture`; capture_warnings.

The steps, each in its module: ``camera.json`` (:mod:`.camera`), ``imu.csv``
(:mod:`.imu`), the frames and their timestamps (:mod:`.frames`), the IMU
slerped to the taken frames, ``ground_truth/`` (:mod:`.ground_truth`).
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..config import CaptureConfig, Config
from ..data import Capture
from ..errors import InputError
from .camera import PROVISIONAL_HFOV_DEG, _Warp, focal_from_hfov, focal_known, read_camera, with_focal, working_camera
from .frames import _frame_reader, _read_source, _timestamps
from .ground_truth import _read_ground_truth
from .imu import check_imu_rate, imu_at_frames, read_imu, turn_span_deg
from .validate import _check_config, _root

log = logging.getLogger("panosfm.capture")


def load_capture(path: str | Path, config: CaptureConfig | Config = CaptureConfig()) -> Capture:
    """Returns the validated :class:`Capture` of a capture directory (``capture-format.md``).

    Frames are taken every ``config.every_k``, at most ``config.max_frames``,
    downscaled by ``config.scale`` (images and intrinsics alike) and, for
    OPENCV cameras, undistorted (``Capture.camera`` is then PINHOLE). The IMU
    attitude is slerped to each taken frame's timestamp. Raises
    :class:`InputError` (one line naming the file) for any bad input,
    including taken frames outside the IMU's time span.
    """
    config = getattr(config, "capture", config)  # a whole Config works too
    _check_config(config)
    root = _root(path)
    camera_json = root / "camera.json"
    raw_camera, fps = read_camera(camera_json)
    imu_path = root / "imu.csv"
    t_imu, R_imu = read_imu(imu_path)
    source = _read_source(root, raw_camera, camera_json)
    t_all, t_from, frame_rate = _timestamps(root, source, fps)
    check_imu_rate(imu_path, t_imu, frame_rate, config.min_imu_rate_hz)

    take = np.arange(0, len(source.names), config.every_k)
    if config.max_frames is not None:
        take = take[: config.max_frames]
    t = t_all[take]
    R_wc = imu_at_frames(imu_path, t_imu, R_imu, t, t_from)

    work = working_camera(raw_camera, config.scale)
    if not focal_known(work):  # a provisional focal length until the pipeline estimates it (lines/focal.py)
        work = with_focal(work, focal_from_hfov(PROVISIONAL_HFOV_DEG, work.width))
    warp = _Warp(raw_camera, work)
    reader = _frame_reader(source, take, raw_camera, warp, camera_json)
    stems = tuple(source.stems[k] for k in take)
    gt_dir = root / "ground_truth"
    gt = _read_ground_truth(gt_dir, stems, warp) if gt_dir.is_dir() else None
    log.info("capture %s: %d of %d frames (%s), %dx%d %s, timestamps from %s, IMU %d rows",
             root, len(take), len(source.names), source.kind, work.width, work.height, raw_camera.model,
             t_from, len(t_imu))
    return Capture(root=root, camera=work, frame_names=tuple(source.names[k] for k in take), timestamps=t,
                   R_wc_imu=R_wc, ground_truth=gt, reader=reader, focal_given=focal_known(raw_camera))


def capture_warnings(capture: Capture, config: CaptureConfig | Config = CaptureConfig()) -> list[str]:
    """Returns the warnings about a loaded capture as a spin to reconstruct (also logged); InputError if hopeless.

    * the IMU yaw span over the taken frames (:func:`turn_span_deg`) below
      ``config.min_turn_deg``: InputError (no turn to reconstruct); below
      ``config.full_turn_deg``: a warning, the result covers part of the room;
    * dropped frames: a timestamp gap longer than ``config.max_gap_intervals``
      median frame intervals (a warning: the frames on both sides are still
      used, but tracking across the gap is weaker).
    """
    config = getattr(config, "capture", config)
    imu_path = Path(capture.root) / "imu.csv"
    warnings: list[str] = []
    n = capture.n_frames
    span = turn_span_deg(capture.R_wc_imu)
    if span < config.min_turn_deg:
        raise InputError(f"the IMU heading turns only {span:.1f} deg over the {n} frames; a spin capture needs at "
                         f"least {config.min_turn_deg:g} deg (ideally a full turn)", imu_path)
    if span < config.full_turn_deg:
        warnings.append(f"{imu_path}: partial turn: the IMU heading spans {span:.1f} deg (< "
                        f"{config.full_turn_deg:g} deg): the reconstruction covers only part of the room")
    t = np.asarray(capture.timestamps, dtype=np.float64)
    if n >= 3:
        dt = np.diff(t)
        med = float(np.median(dt))
        gaps = np.flatnonzero(dt > config.max_gap_intervals * med)
        if len(gaps):
            k = int(gaps[np.argmax(dt[gaps])])
            warnings.append(f"{capture.root}: {len(gaps)} gap(s) in the frame timestamps longer than "
                            f"{config.max_gap_intervals:g} frame intervals ({med * 1e3:.1f} ms), e.g. "
                            f"{dt[k]:.3f} s between {capture.frame_names[k]} and {capture.frame_names[k + 1]} "
                            f"(dropped frames?)")
    for w in warnings:
        log.warning("%s", w)
    return warnings
