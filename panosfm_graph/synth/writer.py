"""Writes a synthetic spin capture in the format of ``capture-format.md``.

Layout written by :func:`synthesize`::

    camera.json            PINHOLE, fx = fy = 0.8 * width, principal point at the centre, fps
    frames/000000.png ...  BGR PNG (compression 1)
    frames.csv             file,timestamp_s
    imu.csv                timestamp_s,qw,qx,qy,qz   100 Hz drifting attitude (world_from_camera)
    ground_truth/
      poses.csv            file,qw,qx,qy,qz,tx,ty,tz  world_from_camera, t = camera centre (m)
      lines.csv            x1,y1,z1,x2,y2,z2,label    world metres; label = ROOM Manhattan
                                                      axis 0/1/2 of the edge (2 = vertical)
      scene.json           boxes in the room frame + room yaw + room-to-world (see scenes.py)
      synth.json           the generator's settings (scene, seed, drift, ...), to reproduce
      normals/<stem>.npy   H x W x 3 float16 camera-frame unit normals towards the camera
      depth/<stem>.npy     H x W float32 depth along the optical axis (m), 0 where no surface

Everything is written into a temporary directory next to ``out_dir`` and
renamed into place at the end, so a failed run leaves nothing half-written.
"""
from __future__ import annotations

import contextlib
import json
import logging

import os
import shutil
import tempfile
from concurrent.futures import as_completed
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from ..errors import InputError
from ..geometry import matrix_to_quat_wxyz, rotation_angle_deg
from ..parallel import process_pool
from ..progress import progress
from .render import intrinsics, render_frame
from .scenes import SCENES, Scene, make_scene
from .trajectory import imu_stream, spin_trajectory

log = logging.getLogger("panosfm")

PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1]
CHUNK_FRAMES = 8  # frames per worker task


def frame_name(i: int) -> str:
    """Returns the file name of frame ``i`` (``000123.png``)."""
    return f"{i:06d}.png"


def _render_chunk(scene: Scene, K: np.ndarray, R_wc: np.ndarray, centers: np.ndarray, indices: list[int],
                  size: tuple[int, int], texture: float, blur: np.ndarray, noise: float, seed: int,
                  root: str, gt_maps: bool) -> int:
    """Renders and writes frames ``indices`` (one worker task; ``blur`` (px) per frame); returns how many were
    written."""
    cv2.setNumThreads(1)
    root_p = Path(root)
    for j, i in enumerate(indices):
        img, depth, normals = render_frame(scene, K, R_wc[j], centers[j], size, texture=texture, blur=float(blur[j]),
                                           noise=noise, seed=int(seed) * 1_000_003 + int(i))
        name = frame_name(i)
        if not cv2.imwrite(str(root_p / "frames" / name), img, PNG_PARAMS):
            raise OSError(f"could not write {root_p / 'frames' / name}")
        if gt_maps:
            stem = Path(name).stem
            np.save(root_p / "ground_truth" / "normals" / f"{stem}.npy", normals.astype(np.float16))
            np.save(root_p / "ground_truth" / "depth" / f"{stem}.npy", depth.astype(np.float32))
    return len(indices)


def motion_blur_px(K: np.ndarray, R_wc: np.ndarray, ts: np.ndarray, exposure_s: float) -> np.ndarray:
    """Returns (F,) each frame's motion blur length (px): ``exposure_s`` times the camera's angular speed there
    (central differences of the rotations over the timestamps), times the focal length: how far the image centre
    moves during the exposure (0 for ``exposure_s`` 0 or a single frame)."""
    F = len(R_wc)
    if exposure_s <= 0 or F < 2:
        return np.zeros(F)
    speed = np.radians(rotation_angle_deg(R_wc[:-1], R_wc[1:])) / np.maximum(np.diff(ts), 1e-9)  # rad/s between frames
    at_frame = np.concatenate([speed[:1], 0.5 * (speed[1:] + speed[:-1]), speed[-1:]])
    return exposure_s * at_frame * float(K[0, 0])


def _or(value, default):
    return default if value is None else value


def _write_csv(path: Path, header: str, rows: list[str]) -> None:
    path.write_text(header + "\n" + "".join(r + "\n" for r in rows))


def _fmt(a: np.ndarray) -> list[str]:
    return [",".join(f"{x:.9g}" for x in row) for row in np.asarray(a, dtype=np.float64)]


def _check_args(out: Path, scene: str, n_frames: int, size, workers: int, **nonneg: float) -> None:
    if scene not in SCENES:
        raise InputError(f"unknown scene {scene!r}; choose one of {', '.join(SCENES)}")
    if int(n_frames) < 2:
        raise InputError(f"n_frames must be at least 2, got {n_frames}")
    if len(size) != 2 or min(int(size[0]), int(size[1])) < 16:
        raise InputError(f"size must be (width, height) of at least 16 px, got {size}")
    if int(workers) < 1:
        raise InputError(f"workers must be at least 1, got {workers}")
    for k, v in nonneg.items():
        if not np.isfinite(v) or v < 0:
            raise InputError(f"{k} must be a finite number >= 0, got {v}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError("output path exists and is not an empty directory; choose another or remove it", out)


@contextlib.contextmanager
def atomic_capture_dir(out: Path) -> Iterator[Path]:
    """Yields a temporary folder beside ``out`` that becomes ``out`` when the block completes (``out`` absent or
    empty); on any error it is removed and ``out`` is left as it was."""
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    except OSError as e:
        raise InputError(f"cannot create the output directory ({e.strerror})", out) from None
    try:
        yield tmp
        if out.exists():
            out.rmdir()  # empty (checked by the caller)
        os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_capture_tables(root: Path, K: np.ndarray, size: tuple[int, int], fps: float, ts: np.ndarray,
                         t_imu: np.ndarray, R_imu: np.ndarray, R_wc: np.ndarray, centers: np.ndarray, synth: dict,
                         lines: np.ndarray | None = None, labels: np.ndarray | None = None,
                         scene: dict | None = None) -> None:
    """Writes a capture's tables (capture-format.md) under ``root``: camera.json, frames.csv, imu.csv and
    ground_truth/ poses.csv, synth.json (the generator's settings), with ``lines`` lines.csv, with ``scene``
    scene.json; makes the empty frames/ folder."""
    (root / "frames").mkdir()
    gt = root / "ground_truth"
    gt.mkdir()
    names = [frame_name(i) for i in range(len(ts))]
    w, h = size
    (root / "camera.json").write_text(json.dumps(
        {"model": "PINHOLE", "width": w, "height": h,
         "params": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], "fps": fps}, indent=1) + "\n")
    _write_csv(root / "frames.csv", "file,timestamp_s", [f"{n},{t:.9g}" for n, t in zip(names, ts)])
    _write_csv(root / "imu.csv", "timestamp_s,qw,qx,qy,qz", _fmt(np.column_stack([t_imu, matrix_to_quat_wxyz(R_imu)])))
    poses = np.column_stack([matrix_to_quat_wxyz(R_wc), np.broadcast_to(centers, (len(ts), 3))])
    _write_csv(gt / "poses.csv", "file,qw,qx,qy,qz,tx,ty,tz", [f"{n},{r}" for n, r in zip(names, _fmt(poses))])
    if lines is not None:
        _write_csv(gt / "lines.csv", "x1,y1,z1,x2,y2,z2,label",
                   [f"{r},{int(lab)}" for r, lab in zip(_fmt(lines), labels)])
    if scene is not None:
        (gt / "scene.json").write_text(json.dumps(scene, indent=1) + "\n")
    (gt / "synth.json").write_text(json.dumps(synth, indent=1) + "\n")


def synthesize(out_dir: str | os.PathLike, scene: str = "living", n_frames: int | None = None,
               size: tuple[int, int] = (960, 540), seed: int = 0, *, imu_drift_deg: float = 3.0,
               turn_deg: float | None = None, texture: float = 1.0, blur: float = 0.0, noise: float = 0.0,
               gt_maps: bool = True, workers: int = 2, fps: float = 30.0,
               imu_noise_deg: float = 0.1, sway_m: float | None = None, exposure_s: float = 0.0,
               arm_m: float | None = None, hfov_deg: float | None = None, tremor_deg: float = 0.0,
               photo_dir: str | os.PathLike | None = None) -> Path:
    """Returns the path of a new synthetic spin capture of ``scene`` written to ``out_dir``.

    ``size`` is (width, height) px; ``seed`` seeds the spin, IMU noise, image
    noise and (for ``scene="random"``) the room. ``imu_drift_deg``: IMU heading
    drift accumulated from the first to the last frame. ``texture``: strength
    of the procedural surface texture (0 = textureless). ``blur``: horizontal
    motion blur length (px). ``noise``: image noise sigma (0..255 levels).
    ``gt_maps=False`` skips the per-frame normal and depth maps. ``sway_m``: how far
    the spin departs from an ideal circle (stand point wandering, arm length and
    angle varying; :mod:`panosfm_graph.synth.trajectory`), 0 = the ideal circle.
    ``exposure_s``: each frame's exposure time; its motion blur (added to ``blur``)
    is the exposure times the camera's angular speed at that frame, in pixels at the
    focal length (:func:`motion_blur_px`): a fast spin blurs, a slow one does not.
    ``arm_m``: the spin circle's radius (None: seeded 0.30-0.40 m); 0 is a tripod spin with
    one optical centre (zero baseline), which cannot sway. ``hfov_deg``: the camera's horizontal field of
    view (None: fx = 0.8 width, 64 degrees). ``tremor_deg``: RMS angle of a hand's rotational tremor (2-7 Hz;
    0: none).
    ``scene="random"``: a procedural room (:mod:`.procedural`) whose seed also draws the spin: ``n_frames``,
    ``turn_deg``, ``sway_m``, ``arm_m`` and ``hfov_deg`` left None take its values (given: they override);
    ``photo_dir``: equirectangular photos that room paints some surfaces with. Other scenes: None means 300
    frames, 380 deg, no sway, the seeded arm, 64 deg.
    Raises :class:`InputError` for an existing non-empty ``out_dir`` or bad settings.
    """
    out = Path(out_dir)
    if scene == "random":
        from .procedural import random_spin

        spec = random_spin(int(seed))
        n_frames, turn_deg = _or(n_frames, spec.n_frames), _or(turn_deg, spec.turn_deg)
        sway_m, arm_m, hfov_deg = _or(sway_m, spec.sway_m), _or(arm_m, spec.arm_m), _or(hfov_deg, spec.hfov_deg)
    n_frames, turn_deg, sway_m = _or(n_frames, 300), _or(turn_deg, 380.0), _or(sway_m, 0.0)
    if photo_dir is not None and not Path(photo_dir).is_dir():
        raise InputError("photo folder not found", photo_dir)
    _check_args(out, scene, n_frames, size, workers, imu_drift_deg=abs(imu_drift_deg), texture=texture,
                blur=blur, noise=noise, imu_noise_deg=imu_noise_deg, turn_deg=turn_deg, fps=fps, sway_m=sway_m,
                exposure_s=exposure_s, tremor_deg=tremor_deg)
    if fps <= 0 or turn_deg <= 0:
        raise InputError(f"fps and turn_deg must be > 0, got fps={fps}, turn_deg={turn_deg}")
    if arm_m is not None and not (np.isfinite(arm_m) and 0.0 <= arm_m <= 2.0):
        raise InputError(f"arm_m must be between 0 and 2 m, got {arm_m}")
    if arm_m == 0 and sway_m > 0:
        raise InputError("a tripod spin (arm 0) cannot sway: give --arm 0 or --sway, not both")
    n_frames, size, seed = int(n_frames), (int(size[0]), int(size[1])), int(seed)
    sc = make_scene(scene, seed, photo_dir)
    if hfov_deg is not None and not (np.isfinite(hfov_deg) and 10.0 <= hfov_deg <= 150.0):
        raise InputError(f"hfov_deg must be between 10 and 150 degrees, got {hfov_deg}")
    K = intrinsics(size) if hfov_deg is None else intrinsics(size, 0.5 / np.tan(np.radians(hfov_deg) / 2.0))
    R_wc, centers, ts = spin_trajectory(sc, n_frames, seed=seed, turn_deg=turn_deg, fps=fps, sway_m=sway_m,
                                        arm_m=arm_m, tremor_deg=tremor_deg)
    t_imu, R_imu = imu_stream(sc, n_frames, seed=seed, turn_deg=turn_deg, fps=fps, imu_drift_deg=imu_drift_deg,
                              noise_deg=imu_noise_deg, sway_m=sway_m, arm_m=arm_m, tremor_deg=tremor_deg)

    with atomic_capture_dir(out) as tmp:
        settings = dict(scene=scene, n_frames=n_frames, size=list(size), seed=seed, imu_drift_deg=imu_drift_deg,
                        imu_noise_deg=imu_noise_deg, turn_deg=turn_deg, texture=texture, blur=blur, noise=noise,
                        fps=fps, gt_maps=bool(gt_maps), sway_m=sway_m,
                        **({"exposure_s": exposure_s} if exposure_s > 0 else {}),
                        **({"arm_m": float(arm_m)} if arm_m is not None else {}),
                        **({"hfov_deg": float(hfov_deg)} if hfov_deg is not None else {}),
                        **({"tremor_deg": float(tremor_deg)} if tremor_deg > 0 else {}),
                        **({"photo_dir": str(Path(photo_dir).resolve())} if photo_dir is not None else {}))
        lines, labels = sc.edges()
        write_capture_tables(tmp, K, size, fps, ts, t_imu, R_imu, R_wc, centers,
                             {"generator": "panosfm_graph.synth", **settings}, lines, labels, sc.to_json())
        if gt_maps:
            (tmp / "ground_truth" / "normals").mkdir()
            (tmp / "ground_truth" / "depth").mkdir()
        chunks = [list(range(i, min(i + CHUNK_FRAMES, n_frames))) for i in range(0, n_frames, CHUNK_FRAMES)]
        blur_px = blur + motion_blur_px(K, R_wc, ts, exposure_s)
        args = [(sc, K, R_wc[c[0]:c[-1] + 1], centers[c[0]:c[-1] + 1], c, size, texture, blur_px[c[0]:c[-1] + 1],
                 noise, seed,
                 str(tmp), bool(gt_maps)) for c in chunks]
        if workers == 1 or len(chunks) == 1:
            for a in progress(args, "synth frames"):
                _render_chunk(*a)
        else:
            with process_pool(min(int(workers), len(chunks))) as ex:
                futures = [ex.submit(_render_chunk, *a) for a in args]
                for f in progress(as_completed(futures), "synth frames", total=len(futures)):
                    f.result()
    log.info("wrote synthetic capture %s (%s, %d frames, %dx%d)", out, scene, n_frames, *size)
    return out
