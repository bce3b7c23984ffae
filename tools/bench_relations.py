"""Benchmark of relation detection (paper §3.2): precision / recall per relation type and normal source.

Scenes come from :func:`panosfm_graph.synth.problem.make_problem` (tracks of
the scene's GT edges projected along a spin, so every track's GT 3D edge is
known) with normal maps ray-cast from the scene (``oracle``) or computed from
the segments (``orientation-map``); ``model`` runs when a model exists.

A detected relation is correct when the two tracks' GT edges lie in one plane
``x_k = const`` of the detected normal axis ``k`` within ``--tol`` metres
(FLOOR: the edge lies on the floor). Precision is reported at 1 cm and at
``--tol`` (default 5 cm: thin wall fixtures -- posters, door and window frames
1-5 cm deep -- are "coplanar" with their wall within that). Recall is against
the generator's GT relations (pairs on a common face seen in a common frame).

    python tools/bench_relations.py --scenes living bedroom office --frames 60
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from panosfm_graph.config import NormalsConfig, RelationsConfig
from panosfm_graph.data import RELATION_NAMES, Capture, GroundTruth
from panosfm_graph.normals import estimate_normals, normal_accuracy
from panosfm_graph.relations import detect_relations, relations_true
from panosfm_graph.synth.problem import make_problem
from panosfm_graph.synth.render import raycast


def problem_capture(P) -> Capture:
    """Returns a frame-less Capture whose ground truth normals are ray-cast from the problem's scene."""
    cam, sc = P.camera, P.scene

    def hits(i):
        return raycast(sc, cam.K, P.gt_R_wc[i], P.gt_centers[i], (cam.width, cam.height))

    gt = GroundTruth(
        R_wc=P.gt_R_wc, centers=P.gt_centers, lines=P.gt_track_lines, line_labels=P.tracks.axis,
        scene=sc.to_json(), normals=lambda i: hits(i)["normal_cam"], depth=lambda i: hits(i)["depth"],
        has_normals=True, has_depth=True,
    )
    F = P.n_frames
    return Capture(root=None, camera=cam, frame_names=tuple(str(i) for i in range(F)),
                   timestamps=np.arange(F) / 30.0, R_wc_imu=P.preprocessed.R_wc_imu, ground_truth=gt,
                   reader=lambda i: (_ for _ in ()).throw(RuntimeError("no images in a synthetic problem")))


def bench_one(P, source: str, width: int, tol: float, cfg: RelationsConfig) -> dict:
    """Returns the metrics of one (scene, normal source) run."""
    cap = problem_capture(P)
    t0 = time.perf_counter()
    nm = estimate_normals(cap, P.preprocessed, NormalsConfig(source=source, width=width))
    t_norm = time.perf_counter() - t0
    t0 = time.perf_counter()
    rel = detect_relations(P.preprocessed, P.tracks, nm, P.camera, cfg)
    t_rel = time.perf_counter() - t0
    sc = P.scene
    L = np.concatenate([sc.to_room(P.gt_track_lines[:, :3]), sc.to_room(P.gt_track_lines[:, 3:])], axis=1)
    ok_tol = relations_true(rel, L, float(sc.room_min[2]), tol)
    ok_1cm = relations_true(rel, L, float(sc.room_min[2]), 0.01)
    out = {"source": nm.source, "normals_s": round(t_norm, 2), "relations_s": round(t_rel, 3),
           "normals": {k: round(v, 3) for k, v in normal_accuracy(nm, cap, P.preprocessed.R_wc).items() if k != "source"}}
    g = P.relations
    for k, name in enumerate(RELATION_NAMES):
        m = rel.kind == k
        gm = g.kind == k
        truth = set(zip(g.track_a[gm].tolist(), g.track_b[gm].tolist(), g.normal_axis[gm].tolist()))
        found = set(zip(rel.track_a[m].tolist(), rel.track_b[m].tolist(), rel.normal_axis[m].tolist()))
        out[name] = {
            "n": int(m.sum()),
            "precision_1cm": round(float(ok_1cm[m].mean()), 3) if m.any() else None,
            f"precision_{int(round(tol * 100))}cm": round(float(ok_tol[m].mean()), 3) if m.any() else None,
            "recall": round(len(found & truth) / len(truth), 3) if truth else None,
            "n_gt": len(truth),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["living", "bedroom", "office"])
    ap.add_argument("--sources", nargs="+", default=["oracle", "orientation-map"])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--size", type=int, nargs=2, default=(480, 270), metavar=("W", "H"))
    ap.add_argument("--width", type=int, default=240, help="normal-map width (px)")
    ap.add_argument("--tol", type=float, default=0.05, help="coplanarity tolerance (m)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", help="also write the results here")
    args = ap.parse_args()
    results = []
    for scene in args.scenes:
        P = make_problem(scene, n_frames=args.frames, size=tuple(args.size), seed=args.seed)
        for source in args.sources:
            r = {"scene": scene, "frames": P.n_frames, "tracks": P.tracks.n,
                 **bench_one(P, source, args.width, args.tol, RelationsConfig())}
            results.append(r)
            cells = []
            for name in RELATION_NAMES:
                d = r[name]
                cells.append(f"{name} n={d['n']} P1={d['precision_1cm']} P{int(args.tol * 100)}="
                             f"{d[f'precision_{int(round(args.tol * 100))}cm']} R={d['recall']}")
            print(f"{scene:8s} {r['source']:16s} normals med={r['normals']['median_deg']}° "
                  f"<20°={r['normals']['within_20deg']} cov={r['normals']['coverage']} | "
                  + " | ".join(cells) + f" | {r['normals_s']}s + {r['relations_s']}s")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)


if __name__ == "__main__":
    main()
