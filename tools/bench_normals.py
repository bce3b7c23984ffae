"""Normal-source benchmark (paper §3.2): model vs orientation map vs oracle against ray-cast ground truth.

    python tools/bench_normals.py --scenes living,bedroom,office --frames 40 --size 480x270 \
        --out /tmp/bench_normals [--json /tmp/bench_normals/bench_normals.json]

Per held-out synthetic scene (the named presets; the shipped model was
trained on ``random`` rooms only), synthesised into ``OUT/captures`` unless
already there: segments are detected and the rotations refined (as the
pipeline does; the orientation map needs them), then every source in
``--sources`` estimates the normal maps at ``--width`` and is scored with
:func:`panosfm_graph.normals.normal_accuracy` (median angular error in
degrees and share of pixels within 20 deg, over pixels valid in both the
estimate and the GT, in the camera frame; ``coverage`` = share of GT-valid
pixels the source labels; ``good_of_all`` = within_20deg x coverage, the share
of all GT-valid pixels labelled within 20 deg). ``s_per_frame`` is the wall time of
``estimate_normals`` per frame (frame decoding included; segment detection
and rotation refinement, shared pipeline stages, excluded).

``model_s_per_960x540`` is the shipped model alone on one 960x540 frame
(resize to the model's input, inference, renormalisation; median of 20 runs,
onnxruntime on the CPU with its default threads).
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

SOURCES = ("model", "orientation-map", "oracle")


def model_speed(model_path: Path, width: int = 256, size=(960, 540), runs: int = 20, threads: int = 0) -> float:
    """Returns the median seconds the ONNX model takes on one ``size`` BGR frame (resize + run + renormalise)."""
    import cv2
    import onnxruntime as ort

    from panosfm_graph.normals.onnx import model_input_size, run_model

    opts = ort.SessionOptions()
    if threads:
        opts.intra_op_num_threads = threads
    sess = ort.InferenceSession(str(model_path), sess_options=opts, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8), (0, 0), 3)
    hw = model_input_size(sess, width, size[1] / size[0])
    ts = []
    for _ in range(runs + 2):
        t = time.perf_counter()
        n = run_model(sess, img, hw)
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
        ts.append(time.perf_counter() - t)
    return float(np.median(ts[2:]))


def bench_scene(cap_dir: Path, sources, width: int) -> list[dict]:
    """Returns one accuracy/timing row per source for the capture at ``cap_dir``."""
    from panosfm_graph.capture import load_capture
    from panosfm_graph.config import Config, NormalsConfig
    from panosfm_graph.lines import detect_segments, refine_manhattan_and_rotations
    from panosfm_graph.normals import estimate_normals, normal_accuracy

    cfg = Config()
    capture = load_capture(cap_dir)
    segments = detect_segments(capture, cfg.detect)
    pre = refine_manhattan_and_rotations(segments, capture, cfg)
    rows = []
    for src in sources:
        t = time.perf_counter()
        nm = estimate_normals(capture, pre, NormalsConfig(source=src, width=width))
        dt = (time.perf_counter() - t) / capture.n_frames
        acc = normal_accuracy(nm, capture, pre.R_wc)
        rows.append({"requested": src, **acc, "good_of_all": acc["within_20deg"] * acc["coverage"], "s_per_frame": dt})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="living,bedroom,office")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--size", default="480x270")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--width", type=int, default=256, help="normal-map width (NormalsConfig.width)")
    ap.add_argument("--sources", default=",".join(SOURCES))
    ap.add_argument("--out", default="/tmp/bench_normals")
    ap.add_argument("--json", default=None, help="default: OUT/bench_normals.json")
    ap.add_argument("--workers", type=int, default=2, help="synthesis processes")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    from panosfm_graph.normals.onnx import SHIPPED_MODEL
    from panosfm_graph.synth import synthesize

    w, h = (int(v) for v in args.size.lower().split("x"))
    out = Path(args.out)
    sources = [s for s in args.sources.split(",") if s]
    results = {"settings": vars(args), "scenes": {}}
    for scene in [s for s in args.scenes.split(",") if s]:
        cap = out / "captures" / f"{scene}_{args.frames}_{w}x{h}_s{args.seed}"
        if not (cap / "frames.csv").is_file():
            synthesize(cap, scene, n_frames=args.frames, size=(w, h), seed=args.seed, workers=args.workers)
        results["scenes"][scene] = bench_scene(cap, sources, args.width)
    if SHIPPED_MODEL.is_file():
        results["model_s_per_960x540"] = model_speed(SHIPPED_MODEL, args.width)
        results["model_s_per_960x540_2threads"] = model_speed(SHIPPED_MODEL, args.width, threads=2)

    # table: per scene and source, then the mean over scenes
    print(f"{'scene':10s} {'source':16s} {'used':16s} {'median_deg':>10s} {'within20':>9s} {'coverage':>9s} {'good/all':>9s} {'s/frame':>8s}")
    per_src: dict[str, list[dict]] = {}
    for scene, rows in results["scenes"].items():
        for r in rows:
            per_src.setdefault(r["requested"], []).append(r)
            print(f"{scene:10s} {r['requested']:16s} {r['source']:16s} {r['median_deg']:10.2f} "
                  f"{r['within_20deg']:9.3f} {r['coverage']:9.3f} {r['good_of_all']:9.3f} {r['s_per_frame']:8.3f}")
    results["mean"] = {}
    for src, rows in per_src.items():
        m = {k: float(np.mean([r[k] for r in rows])) for k in ("median_deg", "within_20deg", "coverage", "good_of_all", "s_per_frame")}
        results["mean"][src] = m
        print(f"{'MEAN':10s} {src:16s} {'':16s} {m['median_deg']:10.2f} {m['within_20deg']:9.3f} "
              f"{m['coverage']:9.3f} {m['good_of_all']:9.3f} {m['s_per_frame']:8.3f}")
    if "model_s_per_960x540" in results:
        print(f"model alone, one 960x540 frame: {results['model_s_per_960x540'] * 1e3:.1f} ms "
              f"({results['model_s_per_960x540_2threads'] * 1e3:.1f} ms with 2 threads)")
    js = Path(args.json) if args.json else out / "bench_normals.json"
    js.parent.mkdir(parents=True, exist_ok=True)
    js.write_text(json.dumps(results, indent=1) + "\n")
    print(f"wrote {js}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
