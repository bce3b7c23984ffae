"""The peer: COLMAP (incremental) or GLOMAP (global) through pycolmap, in panosfm's output format.

    python tools/peer_colmap.py CAPTURE OUT [--mapper incremental|global] [--every K]

SIFT features, sequential matching, then COLMAP's incremental mapper or
pycolmap's global mapper (GLOMAP), with the capture's intrinsics fixed. The
largest model is written to ``OUT/sparse`` (COLMAP text) with a
``summary.json``, so ``panosfm eval CAPTURE OUT`` scores it exactly like a
panosfm result. Needs the ``peer`` extra (``pip install -e '.[peer]'``).
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
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
        reader.camera_params = f"{fx},{fy},{cx},{cy}"
        pycolmap.extract_features(db, images, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, device=pycolmap.Device.cpu)
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
        elif mapper == "global":
            opts = pycolmap.GlobalPipelineOptions()
            opts.mapper.bundle_adjustment.refine_focal_length = False
            opts.mapper.bundle_adjustment.refine_extra_params = False
            opts.mapper.global_positioning.use_gpu = False
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
        summary = {
            "peer": f"pycolmap {pycolmap.__version__} {mapper} mapper",
            "frames": {"total": capture.n_frames, "registered": int(n_reg),
                       "registered_ratio": n_reg / max(capture.n_frames, 1)},
            "models": len(models),
            "max_mapping_minutes": max_mapping_minutes,
            "metric": False,
            "scale": "arbitrary",
            "seconds": {"features": round(t_feat, 2), "matching": round(t_match, 2),
                        "mapping": round(t_map, 2), "total": round(time.perf_counter() - t0, 2)},
        }
        (staging / "summary.json").write_text(json.dumps(summary, indent=2))
        if out_dir.exists():
            shutil.rmtree(out_dir)
        staging.rename(out_dir)
    return summary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("capture")
    p.add_argument("out")
    p.add_argument("--mapper", choices=["incremental", "global"], default="incremental")
    p.add_argument("--every", type=int, default=1)
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--max-mapping-minutes", type=float, default=None,
                   help="stop COLMAP's incremental mapper after this long (it can grind on degenerate spins)")
    args = p.parse_args(argv)
    try:
        import pycolmap  # noqa: F401
    except ImportError:
        print("peer_colmap: needs pycolmap (pip install -e '.[peer]')", file=sys.stderr)
        return 2
    summary = run_peer(args.capture, args.out, args.mapper, args.every, args.max_frames,
                       max_mapping_minutes=args.max_mapping_minutes)
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
