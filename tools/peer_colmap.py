"""The peer: COLMAP (incremental) or GLOMAP (global) through pycolmap, in panosfm's output format.

    python tools/peer_colmap.py CAPTURE OUT [--mapper incremental|global|global-gravity] [--every K]

SIFT features, sequential matching, then COLMAP's incremental mapper or
pycolmap's global mapper (GLOMAP), with the capture's intrinsics fixed.
``global-gravity`` is GLOMAP given what panosfm is given: each image's gravity
direction from the capture's IMU attitude, written to the database as a pose
prior (``PosePrior.gravity``), and gravity-aligned rotation averaging
(``rotation_averaging.use_gravity``: one yaw angle per image instead of a full
rotation). The largest model is written to ``OUT/sparse`` (COLMAP text) with a
``summary.json``, so ``panosfm eval CAPTURE OUT`` scores it exactly like a
panosfm result. Needs the ``peer`` extra (``pip install -e '.[peer]'``,
pycolmap 4 or later).
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

MAPPERS = ("incremental", "global", "global-gravity")
DOWN_WORLD = np.array([0.0, 0.0, -1.0])  # gravity in the capture's world frame (capture-format.md: +z up)


def gravity_in_camera(R_wc: np.ndarray) -> np.ndarray:
    """Returns the (F, 3) unit gravity directions in the camera frames of the (F, 3, 3) ``world_from_camera``
    rotations: COLMAP's ``PosePrior.gravity`` (the camera-frame direction that points down; OpenCV axes, so an
    upright camera gives about (0, 1, 0)). GLOMAP's gravity-aligned rotation averaging makes that direction the
    reconstruction's world +y."""
    g = np.einsum("fji,j->fi", np.asarray(R_wc, dtype=np.float64), DOWN_WORLD)  # R_wc^T down
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def write_gravity_priors(database, gravity_by_name: dict[str, np.ndarray]) -> int:
    """Writes a gravity-only pose prior (position left unknown) for each image of ``database`` named in
    ``gravity_by_name``; returns how many were written."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        n = 0
        for image in db.read_all_images():
            g = gravity_by_name.get(image.name)
            if g is None or not np.all(np.isfinite(g)):
                continue
            prior = pycolmap.PosePrior()
            prior.corr_data_id = image.data_id  # (camera sensor, image id): how the rotation averager finds it
            prior.gravity = np.asarray(g, dtype=np.float64) / np.linalg.norm(g)  # must be unit (COLMAP checks)
            db.write_pose_prior(prior)
            n += 1
    finally:
        db.close()
    return n


def gravity_residual_deg(reconstruction, gravity_by_name: dict[str, np.ndarray]) -> float | None:
    """Returns the median angle (degrees) between each registered image's prior gravity and the reconstruction's
    world +y seen from that image (small: the model is gravity aligned as GLOMAP's gravity mode makes it)."""
    angles = []
    for image in reconstruction.images.values():
        g = gravity_by_name.get(image.name)
        if g is None or not image.has_pose:
            continue
        R_cw = image.cam_from_world().rotation.matrix()
        y = R_cw[:, 1]
        angles.append(np.degrees(np.arccos(np.clip(float(y @ g) / np.linalg.norm(g), -1.0, 1.0))))
    return round(float(np.median(angles)), 3) if angles else None


def run_peer(capture_dir: str | Path, out_dir: str | Path, mapper: str = "incremental",
             every_k: int = 1, max_frames: int | None = None, overlap: int = 10,
             max_mapping_minutes: float | None = None) -> dict:
    """Returns the peer's summary after writing its reconstruction to ``out_dir``."""
    import cv2
    import pycolmap

    from panosfm_graph.capture import load_capture
    from panosfm_graph.config import CaptureConfig

    capture = load_capture(capture_dir, CaptureConfig(every_k=every_k, max_frames=max_frames))
    cam = capture.camera
    out_dir = Path(out_dir)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="panosfm-peer-") as tmp:
        tmp = Path(tmp)
        images = tmp / "images"
        images.mkdir()
        names = []
        for i, name in enumerate(capture.frame_names):
            # frames are written undistorted at working resolution, so PINHOLE intrinsics hold
            fname = Path(name.replace("#", "_")).name
            if not fname.lower().endswith((".png", ".jpg", ".jpeg")):
                fname += ".png"
            cv2.imwrite(str(images / fname), capture.frame(i))
            names.append(fname)
        db = tmp / "database.db"
        gravity_by_name = {}
        if mapper == "global-gravity":
            gravity_by_name = dict(zip(names, gravity_in_camera(capture.R_wc_imu)))
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
        reader.camera_params = f"{fx},{fy},{cx},{cy}"
        pycolmap.extract_features(db, images, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, device=pycolmap.Device.cpu)
        n_priors = write_gravity_priors(db, gravity_by_name) if gravity_by_name else 0
        t_feat = time.perf_counter() - t0
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = overlap
        pycolmap.match_sequential(db, pairing_options=pairing, device=pycolmap.Device.cpu)
        t_match = time.perf_counter() - t0 - t_feat
        sparse_tmp = tmp / "sparse"
        sparse_tmp.mkdir()
        if mapper == "incremental":
            opts = pycolmap.IncrementalPipelineOptions()
            opts.ba_refine_focal_length = False
            opts.ba_refine_principal_point = False
            opts.ba_refine_extra_params = False
            if max_mapping_minutes:
                opts.max_runtime_seconds = int(60 * max_mapping_minutes)
            models = pycolmap.incremental_mapping(db, images, sparse_tmp, options=opts)
        elif mapper in ("global", "global-gravity"):
            opts = pycolmap.GlobalPipelineOptions()
            opts.mapper.bundle_adjustment.refine_focal_length = False
            opts.mapper.bundle_adjustment.refine_extra_params = False
            opts.mapper.global_positioning.use_gpu = False
            opts.random_seed = 0  # repeatable: GLOMAP's default seed is the clock's (the same capture: 26.9 / 46.1 %)
            # 1-DOF (yaw) rotation averaging for images with a gravity prior; without priors it is ignored
            opts.mapper.rotation_averaging.use_gravity = mapper == "global-gravity"
            models = pycolmap.global_mapping(db, images, sparse_tmp, options=opts)
        else:
            raise ValueError(f"unknown mapper {mapper!r}")
        t_map = time.perf_counter() - t0 - t_feat - t_match
        best = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
        staging = out_dir.with_name(out_dir.name + ".peer-tmp")
        shutil.rmtree(staging, ignore_errors=True)
        (staging / "sparse").mkdir(parents=True)
        n_reg = 0
        if best is not None:
            best.write_text(str(staging / "sparse"))
            n_reg = best.num_reg_images()
        peer = f"pycolmap {pycolmap.__version__} {mapper} mapper"
        if mapper == "global-gravity":
            peer = (f"pycolmap {pycolmap.__version__} global mapper (GLOMAP) with IMU gravity pose priors on "
                    f"{n_priors}/{len(names)} images and gravity-aligned rotation averaging")
        summary = {
            "peer": peer,
            "frames": {"total": capture.n_frames, "registered": int(n_reg),
                       "registered_ratio": n_reg / max(capture.n_frames, 1)},
            "models": len(models),
            "max_mapping_minutes": max_mapping_minutes,
            "metric": False,
            "scale": "arbitrary",
            "seconds": {"features": round(t_feat, 2), "matching": round(t_match, 2),
                        "mapping": round(t_map, 2), "total": round(time.perf_counter() - t0, 2)},
        }
        if mapper == "global-gravity":
            summary["gravity"] = {"source": "imu.csv attitude", "priors": n_priors, "images": len(names),
                                  "use_gravity": True,
                                  "residual_deg_median": None if best is None
                                  else gravity_residual_deg(best, gravity_by_name)}
        (staging / "summary.json").write_text(json.dumps(summary, indent=2))
        if out_dir.exists():
            shutil.rmtree(out_dir)
        staging.rename(out_dir)
    return summary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("capture")
    p.add_argument("out")
    p.add_argument("--mapper", choices=list(MAPPERS), default="incremental",
                   help="global-gravity: GLOMAP with each image's IMU gravity as a pose prior")
    p.add_argument("--every", type=int, default=1)
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--max-mapping-minutes", type=float, default=None,
                   help="stop COLMAP's incremental mapper after this long (it can grind on degenerate spins; "
                        "the global mappers ignore it)")
    args = p.parse_args(argv)
    try:
        import pycolmap
    except ImportError:
        print("peer_colmap: needs pycolmap (pip install -e '.[peer]')", file=sys.stderr)
        return 2
    if args.mapper != "incremental" and int(pycolmap.__version__.split(".")[0]) < 4:
        print(f"peer_colmap: --mapper {args.mapper} needs pycolmap 4 or later (GLOMAP, gravity priors), "
              f"found {pycolmap.__version__}", file=sys.stderr)
        return 2
    summary = run_peer(args.capture, args.out, args.mapper, args.every, args.max_frames,
                       max_mapping_minutes=args.max_mapping_minutes)
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
