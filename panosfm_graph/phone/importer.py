"""``panosfm import``: a phone video and its raw sensor logs -> a capture directory (``capture-format.md``).

The steps, each in its module: read the sensor log (:mod:`.logs`), the
camera's turn between consecutive frames from feature flow
(:mod:`.video_rotation`), the time offset and the camera's axes in the
phone's (:mod:`.sync`), the attitude at every frame from a GTSAM AHRS
smoother (:mod:`.attitude`); where the images' turns leave the offset
loose (a spin without tremor), the offset again from the lines' rotations
(:mod:`.line_timing`) and the attitude at it. Written: ``video.<ext>`` (a copy),
``camera.json`` (without ``params`` when the focal length is not given: the
pipeline estimates it), ``imu.csv`` (one attitude per frame, on the video's
clock) and ``import.json`` (what the import found). Nothing is written when
any step fails; an existing non-empty ``out`` is never touched.
"""
from __future__ import annotations

import json
import logging
import math
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..capture.camera import PROVISIONAL_HFOV_DEG, focal_from_hfov, read_camera
from ..capture.frames import _read_source, _timestamps
from ..capture.video import _scan_video
from ..errors import InputError
from ..geometry import matrix_to_quat_wxyz
from ..synth.writer import atomic_capture_dir
from .attitude import Attitude, smooth_attitude
from .line_timing import LineTiming, retime_by_lines
from .logs import RawSensors, read_sensors
from .sync import Sync, covering_offsets, estimate_sync
from .video_rotation import frame_rotations

log = logging.getLogger("panosfm.phone")

MIN_CORRELATION = 0.5  # a weaker best fit of gyroscope and image turns: the log and the video do not match
MAX_OFFSET_SIGMA_S = 0.005  # a looser time offset is warned about
DISAGREE_SIGMAS = 3.0  # the two timings further apart than this many combined sigmas are warned about


@dataclass(frozen=True)
class ImportResult:
    """What :func:`import_capture` wrote and found."""

    path: Path
    n_frames: int
    sensors: str  # the log's layout and files
    sync: Sync
    attitude: Attitude
    focal_px: float | None  # None: not given, left to the pipeline
    warnings: tuple[str, ...]
    line_timing: LineTiming | None = None  # where the lines' rotations re-timed a loose offset (written)

    @property
    def offset_s(self) -> float:
        """The time offset written (sensor clock minus video clock): the lines' where they re-timed it."""
        return (self.line_timing or self.sync).offset_s

    @property
    def offset_sigma_s(self) -> float:
        """The written time offset's sigma."""
        return (self.line_timing or self.sync).offset_sigma_s


def _epoch_from_name(video: Path) -> float | None:
    """Returns UNIX seconds from a video named by its start time in epoch milliseconds (Sensor Logger), else None."""
    m = re.fullmatch(r"(\d{13})", video.stem)
    return int(m.group(1)) / 1000.0 if m else None


def import_capture(video: str | Path, sensors: str | Path, out: str | Path, fmt: str = "auto",
                   focal_px: float | None = None, hfov_deg: float | None = None, offset_guess_s: float | None = None,
                   max_offset_s: float = 5.0, camera_from_device: np.ndarray | None = None,
                   line_timing: bool = True) -> ImportResult:
    """Builds the capture directory ``out`` from a phone ``video`` and its ``sensors`` log (folder or .zip).

    ``focal_px`` or ``hfov_deg`` give the focal length (else ``camera.json``
    has none and ``panosfm run`` estimates it); ``offset_guess_s`` (sensor
    clock minus video clock) centres the search of +- ``max_offset_s``
    (default: from the video's name when it is an epoch time and the log's
    clock is known, else 0); ``camera_from_device`` fixes the camera's axes
    in the phone's instead of estimating them; ``line_timing`` lets the
    lines' rotations time a spin the images' turns leave loose. Raises
    :class:`~panosfm_graph.errors.InputError` (one line) for bad input.
    """
    video, out = Path(video), Path(out)
    if not video.is_file():
        raise InputError("missing video", video)
    if focal_px is not None and hfov_deg is not None:
        raise InputError("give the focal length (--focal) or the field of view (--hfov), not both")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError("output path exists and is not an empty directory; choose another or remove it", out)
    if not (math.isfinite(max_offset_s) and max_offset_s > 0):
        raise InputError(f"max_offset_s must be > 0, got {max_offset_s}")
    raw = read_sensors(sensors, fmt)
    n, _, (w, h), fps = _scan_video(video)
    if n < 10:
        raise InputError(f"only {n} frames could be decoded (need at least 10)", video)
    if hfov_deg is not None:
        if not (math.isfinite(hfov_deg) and 10.0 <= hfov_deg <= 150.0):
            raise InputError(f"hfov_deg must be between 10 and 150 degrees, got {hfov_deg}")
        focal_px = focal_from_hfov(hfov_deg, w)
    if focal_px is not None and not (math.isfinite(focal_px) and focal_px > 0):
        raise InputError(f"the focal length must be > 0 px, got {focal_px}")
    f_flow = focal_px if focal_px is not None else focal_from_hfov(PROVISIONAL_HFOV_DEG, w)
    K = np.array([[f_flow, 0.0, (w - 1) / 2.0], [0.0, f_flow, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    warnings: list[str] = []
    with atomic_capture_dir(out) as tmp:
        cam = {"model": "PINHOLE", "width": int(w), "height": int(h)}
        if focal_px is not None:
            cam["params"] = [float(focal_px), float(focal_px), (w - 1) / 2.0, (h - 1) / 2.0]
        if fps > 0:
            cam["fps"] = float(fps)
        (tmp / "camera.json").write_text(json.dumps(cam, indent=1) + "\n")
        dst = tmp / f"video{video.suffix.lower() or '.mp4'}"
        shutil.copyfile(video, dst)
        camera, cam_fps = read_camera(tmp / "camera.json")
        source = _read_source(tmp, camera, tmp / "camera.json")
        t_frames, t_from, _ = _timestamps(tmp, source, cam_fps)
        guess = offset_guess_s
        if guess is None:
            epoch = _epoch_from_name(video)
            guess = epoch - raw.epoch_s if epoch is not None and raw.epoch_s is not None else 0.0
        theta = frame_rotations(dst, K)
        sync = estimate_sync(t_frames, theta, raw, guess, max_offset_s, camera_from_device)
        if sync.correlation < MIN_CORRELATION:
            raise InputError(f"the gyroscope's turns do not match the video's (best correlation {sync.correlation:.2f} "
                             f"at offset {sync.offset_s:+.3f} s): a log of another recording, or a wrong "
                             f"--offset-guess?", sensors)
        if not sync.axes_snapped:
            warnings.append("the camera's axes are not along the phone's (fitted rotation kept); check the log")
        raw, flipped = _orient_up(raw, t_frames + sync.offset_s, sync.camera_from_device)
        if flipped:
            warnings.append("the accelerometer pointed down in the images: its sign was flipped (an iOS log without "
                            "metadata.csv?)")
        att = smooth_attitude(raw, t_frames + sync.offset_s, sync.camera_from_device)
        _write_imu(tmp / "imu.csv", t_frames, att.R_wc)
        timing, tried = None, None
        if sync.offset_sigma_s > MAX_OFFSET_SIGMA_S and line_timing:
            tried, att_lines = _retime(tmp, raw, sync, att, t_frames, guess, max_offset_s, warnings)
            if tried is not None and tried.offset_sigma_s < sync.offset_sigma_s:  # the tighter of the two is kept
                timing, att = tried, att_lines
                _write_imu(tmp / "imu.csv", t_frames, att.R_wc)
            if tried is not None and (msg := timings_disagree(sync.offset_s, sync.offset_sigma_s, tried.offset_s,
                                                               tried.offset_sigma_s)):
                warnings.append(msg)
        written = timing or sync  # the offset written: the lines' where they re-timed it
        if written.offset_sigma_s > MAX_OFFSET_SIGMA_S:
            warnings.append(f"the time offset is loose (+- {1e3 * written.offset_sigma_s:.0f} ms): the spin is too "
                            f"smooth to time the video against the gyroscope")
        report = {
            "video": str(video), "sensors": str(sensors), "sensor_log": raw.source, "frames": int(n),
            "frame_times_from": t_from, "gyro_rate_hz": round(raw.gyro_rate_hz, 2),
            "time_offset_s": written.offset_s, "time_offset_sigma_s": written.offset_sigma_s,
            "time_offset_from": "lines' rotations" if timing else "images' turns", "offset_guess_s": guess,
            "turns_time_offset_s": sync.offset_s, "turns_time_offset_sigma_s": sync.offset_sigma_s,
            "turns_band": sync.band, "tremor_share": sync.tremor_share,
            "line_timing": None if tried is None else {
                "offset_s": tried.offset_s, "offset_sigma_s": tried.offset_sigma_s, "used": timing is not None,
                "offsets_s": list(tried.offsets_s), "frames": tried.frames, "seconds": round(tried.seconds, 2)},
            "sync_correlation": sync.correlation, "sync_residual_deg": sync.residual_deg, "image_turn_scale": sync.scale,
            "camera_from_device": sync.camera_from_device.tolist(), "camera_axes_snapped": sync.axes_snapped,
            "gyro_bias_rad_s": att.gyro_bias.tolist(), "still_s": att.still_s,
            "up_residual_deg": att.up_residual_deg, "focal_px": focal_px, "warnings": warnings,
        }
        (tmp / "import.json").write_text(json.dumps(report, indent=1) + "\n")
    for wmsg in warnings:
        log.info("%s", wmsg)
    return ImportResult(out, int(n), raw.source, sync, att, focal_px, tuple(warnings), timing)


def timings_disagree(turns_s: float, turns_sigma_s: float, lines_s: float, lines_sigma_s: float,
                     max_sigmas: float = DISAGREE_SIGMAS) -> str | None:
    """Returns a warning where the images' turns and the lines' rotations put the offset more than ``max_sigmas``
    combined sigmas apart (one of them is wrong by more than its sigma says), else None."""
    gap = abs(lines_s - turns_s)
    sigma = math.hypot(turns_sigma_s, lines_sigma_s)
    if not math.isfinite(sigma) or gap <= max_sigmas * sigma:
        return None
    return (f"the images' turns and the lines' rotations time the video {1e3 * gap:.0f} ms apart ({gap / sigma:.1f} "
            f"sigma): the offset may be further off than its sigma says")


def _write_imu(path: Path, t_frames: np.ndarray, R_wc: np.ndarray) -> None:
    """Writes ``imu.csv``: one attitude per frame, on the video's clock."""
    q = matrix_to_quat_wxyz(R_wc)
    rows = "".join(f"{t:.9f},{a:.9f},{b:.9f},{c:.9f},{d:.9f}\n" for t, (a, b, c, d) in zip(t_frames, q))
    path.write_text("timestamp_s,qw,qx,qy,qz\n" + rows)


def _retime(tmp: Path, raw: RawSensors, sync: Sync, att: Attitude, t_frames: np.ndarray, guess: float,
            max_offset_s: float, warnings: list[str]) -> tuple[LineTiming | None, Attitude | None]:
    """Returns the lines' timing of the capture being written in ``tmp`` and the attitude at it, or (None, None)
    with a warning where the lines cannot time it; ``att``: the attitude at the turns' offset."""
    from ..capture import load_capture

    lo, hi = covering_offsets(t_frames, raw, guess, max_offset_s)
    log.info("the images' turns leave the time offset loose (+- %.0f ms); timing it by the lines' rotations",
             1e3 * sync.offset_sigma_s)
    try:
        return retime_by_lines(load_capture(tmp), raw, sync.offset_s, sync.camera_from_device, lo, hi, attitude=att)
    except InputError as e:
        warnings.append(f"the lines could not time the video either ({e})")
        return None, None


def _orient_up(raw: RawSensors, t: np.ndarray, camera_from_device: np.ndarray) -> tuple[RawSensors, bool]:
    """Returns the log with its accelerometer's sign flipped if "up" points down the image (camera +y) on average."""
    up = np.column_stack([np.interp(t, raw.t_up, raw.up[:, j]) for j in range(3)]) @ np.asarray(camera_from_device).T
    if np.mean(up[:, 1]) <= 0:  # up is towards the image's top (camera -y): as it should be
        return raw, False
    return RawSensors(raw.t_gyro, raw.gyro, raw.t_up, -raw.up, raw.source + " (up flipped)", raw.epoch_s), True


def _ms(seconds: float) -> str:
    """Returns ``seconds`` in milliseconds with two significant digits (0.03, 1.3, 28)."""
    v = 1e3 * seconds
    return f"{v:.0f}" if not np.isfinite(v) or v >= 10 else f"{v:.1f}" if v >= 1 else f"{v:.2f}"


def format_import(res: ImportResult) -> str:
    """Returns the CLI report of an import: a few lines."""
    s, a = res.sync, res.attitude
    focal = f"{res.focal_px:.1f} px" if res.focal_px is not None else "not given (panosfm run estimates it)"
    lt = res.line_timing
    if lt is None:
        band = (f"their tremor band, {100 * s.tremor_share:.0f} % matched by the gyroscope's" if s.band == "tremor"
                else "every frequency: too little tremor to time them by it alone")
        how = (f"from the images' turns, {band}; correlation {s.correlation:.3f}, off-axis residual "
               f"{s.residual_deg:.3f} deg per frame, {s.intervals} frame pairs")
    else:
        how = (f"from the lines' rotations: {lt.frames} frames, {lt.seconds:.1f} s; the images' turns gave "
               f"{s.offset_s:+.4f} s +- {_ms(s.offset_sigma_s)} ms")
    lines = [
        f"wrote {res.path}: {res.n_frames} frames, sensors {res.sensors}",
        f"time offset   sensor clock = video clock {res.offset_s:+.4f} s +- {_ms(res.offset_sigma_s)} ms ({how})",
        "camera axes   " + ("along the phone's: " if s.axes_snapped else "fitted: ")
        + "; ".join(" ".join(f"{v:+.0f}" if s.axes_snapped else f"{v:+.2f}" for v in row)
                    for row in s.camera_from_device),
        f"gyro bias     {np.degrees(a.gyro_bias).round(3).tolist()} deg/s "
        + (f"(from {a.still_s:.1f} s still)" if a.still_s > 0 else "(no still moment: prior only)"),
        f"gravity       median residual {a.up_residual_deg:.2f} deg",
        f"focal length  {focal}",
    ]
    return "\n".join(lines + [f"warning: {w}" for w in res.warnings])
