"""Benchmark of relation detection (paper §3.2) on REAL pipeline output: precision / recall per type and normal source.

For each scene a synthetic capture is written (``panosfm synth``, unless it
already exists under ``--root``), the real pipeline runs up to the tracks
(``run_pipeline(..., stop_after="track", resume=True)``; cached), then every
normal source estimates its maps and :func:`detect_relations` runs on the
pipeline's own segments, labels, rotations and tracks.

Judging (:func:`panosfm_graph.relations.track_gt_edges` and
:func:`~panosfm_graph.relations.judge_relations`): each track is mapped to
the ground-truth edge its segments project nearest to (GT poses, majority of
the segments, within 3 px); a pair relation with normal axis ``k`` is
correct when both GT edges lie on one face plane ``x_k = c`` of the scene
(shell or box) within ``--tol`` (default 2 cm: posters 1.2 cm, a door leaf
2 cm and window glass 1 cm off their wall count as on it; TV screens, door
jambs and window trims 3.5-5 cm do not); FLOOR is correct when the GT edge
lies at the floor height; ``floor_verified`` scores the floor relations the
linear solve keeps (``linear.floor_verified`` drops those above the lowest
horizontal plane of a first solve: the tops of furniture). Relations of tracks without a GT edge are left
out of the precision (``unk`` counts them). Recall is against the pairs of
mapped tracks seen in a common frame whose GT edges lie on a common face
rectangle (orthogonal / parallel), share an endpoint (junction), or lie on
the floor (floor).

``kept`` scores the relations the product's result rests on: the whole
pipeline runs with the normal source (true camera height, ``--graph-set``; the
product's relation types, so parallel pairs only with ``--set
parallel=true``), and the relations its final solution keeps
(``Solution.relations_kept``: the linear solve drops floor relations above the
floor and its robust outliers, the bundle adjustment those its residuals
contradict) between lines it placed are scored.

    python tools/bench_relations.py --scenes living bedroom office --frames 200 --size 640x360
    python tools/bench_relations.py --seeds 3 --no-solve   # 9 captures, pooled precision with 95 % intervals
    python tools/bench_relations.py --set junction_dist_frac=0.05   # RelationsConfig overrides
    python tools/bench_relations.py --graph-set verify_relations=true   # GraphConfig overrides for 'kept'
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from panosfm_graph.cli import section_settings
from panosfm_graph.config import Config, GraphConfig, LinearConfig, NormalsConfig, RelationsConfig
from panosfm_graph.data import FLOOR, JUNCTION, ORTHOGONAL, PARALLEL, RELATION_NAMES
from panosfm_graph.errors import InputError
from panosfm_graph.linear import floor_verified
from panosfm_graph.normals import estimate_normals, normal_accuracy
from panosfm_graph.pipeline import run_pipeline
from panosfm_graph.relations import detect_relations, judge_relations, track_gt_edges
from panosfm_graph.synth.scenes import scene_from_json


def ensure_capture(root: Path, scene: str, frames: int, size: str, seed: int) -> Path:
    """Returns the capture directory of ``scene``, synthesising it first when missing."""
    cap = root / f"cap_{scene}_{frames}_{size}_{seed}"
    if not (cap / "camera.json").exists():
        subprocess.run([sys.executable, "-m", "panosfm_graph", "synth", str(cap), "--scene", scene,
                        "--frames", str(frames), "--size", size, "--seed", str(seed)], check=True,
                       stdout=subprocess.DEVNULL)
    return cap


@dataclasses.dataclass
class GroundTruthView:
    """What judging needs: each track's GT edge, the edges and faces in the room frame, axis maps."""

    track_edge: np.ndarray  # (T,) GT edge index or -1
    edges_room: np.ndarray  # (M, 6)
    edge_axis_room: np.ndarray  # (M,)
    face_axis: np.ndarray
    face_offset: np.ndarray
    face_lo: np.ndarray
    face_hi: np.ndarray
    axis_to_room: np.ndarray  # (3,) pipeline Manhattan axis -> room axis
    floor_z: float
    shell_min: np.ndarray
    shell_max: np.ndarray


def ground_truth_view(capture, pre, tracks, max_px: float = 3.0) -> GroundTruthView:
    """Returns the :class:`GroundTruthView` of a capture's ground truth for the pipeline's tracks."""
    gt = capture.ground_truth
    scene = scene_from_json(gt.scene)
    E_room, lab_room = scene.edges(min_length_m=0.05, frame="room")
    E_world = np.concatenate([scene.to_world(E_room[:, :3]), scene.to_world(E_room[:, 3:])], axis=1)
    # pipeline axis i is the room axis its direction is nearest to (the IMU world is the GT world up to drift)
    axis_to_room = np.abs(pre.manhattan.directions @ scene.manhattan_directions.T).argmax(axis=1)
    room_to_axis = np.argsort(axis_to_room)
    edge, _ = track_gt_edges(pre, tracks, capture.camera, gt.R_wc, gt.centers, E_world,
                             room_to_axis[lab_room], max_px=max_px)
    fc = scene.faces()
    return GroundTruthView(edge, E_room, lab_room, fc.axis.astype(np.int64), fc.offset, fc.lo, fc.hi,
                           axis_to_room, float(scene.room_min[2]), scene.room_min, scene.room_max)


def gt_relation_sets(pre, tracks, g: GroundTruthView, tol: float) -> dict[int, set]:
    """Returns {kind: set of (track_a, track_b, pipeline normal axis)} the detector should find (for recall)."""
    T = tracks.n
    F = pre.R_wc.shape[0]
    seg = np.flatnonzero(tracks.track_of >= 0)
    vis = np.zeros((T, F), np.float32)
    vis[tracks.track_of[seg], pre.segments.frame[seg]] = 1.0
    co = (vis @ vis.T) > 0
    mapped = g.track_edge >= 0
    e = np.maximum(g.track_edge, 0)
    L = g.edges_room[e]
    lab = g.edge_axis_room[e]
    room_to_axis = np.argsort(g.axis_to_room)
    out: dict[int, set] = {ORTHOGONAL: set(), PARALLEL: set(), JUNCTION: set(), FLOOR: set()}
    # edge-on-face-rectangle incidence (T, NF)
    other = np.array([[1, 2], [0, 2], [0, 1]])[g.face_axis]  # (NF, 2)
    P0, P1 = L[:, :3], L[:, 3:]
    on = np.ones((T, len(g.face_axis)), bool)
    ax = g.face_axis
    on &= np.abs(P0[:, ax] - g.face_offset[None]) < tol
    on &= np.abs(P1[:, ax] - g.face_offset[None]) < tol
    for c in range(2):
        oc = other[:, c]
        lo, hi = g.face_lo[:, c][None] - tol, g.face_hi[:, c][None] + tol
        on &= (P0[:, oc] >= lo) & (P0[:, oc] <= hi) & (P1[:, oc] >= lo) & (P1[:, oc] <= hi)
    on &= mapped[:, None]
    upper = np.triu(co & mapped[:, None] & mapped[None], 1) & (e[:, None] != e[None])
    for k in range(3):
        Ok = on[:, ax == k].astype(np.float32)
        common = (Ok @ Ok.T) > 0
        both = upper & common
        same = lab[:, None] == lab[None]
        kp = room_to_axis[k]
        ortho = both & ~same & (lab[:, None] != k) & (lab[None] != k)
        par = both & same & (lab[:, None] != k)
        out[ORTHOGONAL] |= {(int(a), int(b), int(kp)) for a, b in zip(*np.nonzero(ortho))}
        out[PARALLEL] |= {(int(a), int(b), int(kp)) for a, b in zip(*np.nonzero(par))}
    ends = np.stack([P0, P1], axis=1)  # (T, 2, 3)
    dmin = np.linalg.norm(ends[:, None, :, None] - ends[None, :, None, :], axis=-1).min(axis=(2, 3))
    junc = upper & (lab[:, None] != lab[None]) & (dmin < tol)
    for a, b in zip(*np.nonzero(junc)):
        out[JUNCTION].add((int(a), int(b), int(room_to_axis[3 - lab[a] - lab[b]])))
    fl = mapped & (lab != 2) & (np.abs(P0[:, 2] - g.floor_z) < tol) & (np.abs(P1[:, 2] - g.floor_z) < tol)
    out[FLOOR] = {(int(t), -1, int(room_to_axis[2])) for t in np.flatnonzero(fl)}
    return out


def score(rel, g: GroundTruthView, truth: dict[int, set], tol: float, fixture: float = 0.05) -> dict:
    """Returns per relation type: n, unk (unjudged), n_true, precision (at ``tol``, fixtures at ``fixture``),
    recall (n_found of n_gt)."""
    ok = judge_relations(rel, g.track_edge, g.edges_room, g.face_axis, g.face_offset, g.axis_to_room,
                         g.floor_z, tol, g.shell_min, g.shell_max, fixture)
    out = {}
    for k, name in enumerate(RELATION_NAMES):
        m = rel.kind == k
        j = m & (ok >= 0)
        found = {(a, b, c) for a, b, c, o in zip(rel.track_a[m].tolist(), rel.track_b[m].tolist(),
                                                 rel.normal_axis[m].tolist(), ok[m].tolist()) if o == 1}
        out[name] = {"n": int(m.sum()), "unk": int((m & (ok < 0)).sum()), "n_true": int((ok[j] == 1).sum()),
                     "precision": round(float((ok[j] == 1).mean()), 3) if j.any() else None,
                     "recall": round(len(found & truth[k]) / len(truth[k]), 3) if truth[k] else None,
                     "n_found": len(found & truth[k]), "n_gt": len(truth[k])}
    return out, ok


def bench_scene(cap: Path, work: Path, sources, width: int, tol: float, cfg: RelationsConfig,
                normals_cache: dict, graph_cfg: GraphConfig | None = None,
                parallel_kept: bool = RelationsConfig().parallel) -> list[dict]:
    """Returns one result row per normal source for the capture ``cap``.

    With ``graph_cfg`` the whole pipeline also runs with each source (true camera height, ``graph_cfg``,
    parallel pairs as ``parallel_kept``) and the relations its final solution rests on
    (``Solution.relations_kept``, between lines it placed) are scored as ``kept``.
    """
    res = run_pipeline(cap, work / cap.name, Config(), resume=True, rerun=False, views=False, stop_after="track")
    capture, pre, tracks = res.capture, res.preprocessed, res.tracks
    g = ground_truth_view(capture, pre, tracks)
    height = capture.ground_truth.camera_height_m
    truth = gt_relation_sets(pre, tracks, g, tol)
    rows = []
    for source in sources:
        key = (cap.name, source, width)
        t0 = time.perf_counter()
        if key not in normals_cache:
            normals_cache[key] = estimate_normals(capture, pre, NormalsConfig(source=source, width=width))
        nm = normals_cache[key]
        t_norm = time.perf_counter() - t0
        t0 = time.perf_counter()
        rel = detect_relations(pre, tracks, nm, capture.camera, cfg)
        t_rel = time.perf_counter() - t0
        sc, _ = score(rel, g, truth, tol)
        # the floor relations the solver keeps: linear.floor_verified drops those above the lowest plane
        kept = rel.subset(floor_verified(pre, tracks, rel, capture.camera, LinearConfig()))
        vf, _ = score(kept, g, truth, tol)
        sc["floor_verified"] = vf["floor"]
        if graph_cfg is not None:
            # the whole pipeline with this normal source (the product's relation types: parallel pairs only if
            # --set parallel=true asked for them), scored on the relations its final solution rests on
            t0 = time.perf_counter()
            pcfg = dataclasses.replace(
                Config(), normals=NormalsConfig(source=source, width=width),
                relations=dataclasses.replace(cfg, parallel=parallel_kept),
                linear=dataclasses.replace(LinearConfig(), camera_height_m=height), graph=graph_cfg)
            full = run_pipeline(cap, work / f"{cap.name}-{source}", pcfg, resume=True, rerun=False, views=False)
            rp, sol = full.relations, full.solution
            on = (sol.relations_kept if len(sol.relations_kept) == rp.n else np.ones(rp.n, bool)) & rp.between(
                sol.lines.valid)
            kept, _ = score(rp.subset(on), g, truth, tol)
            sc["kept"] = {**kept, "registered": int(sol.registered.sum()), "seconds": round(time.perf_counter() - t0, 2)}
        acc = normal_accuracy(nm, capture, pre.R_wc)
        rows.append({"scene": cap.name, "frames": capture.n_frames, "tracks": tracks.n,
                     "tracks_mapped": round(float(np.mean(g.track_edge >= 0)), 3), "source": nm.source,
                     "normals_s": round(t_norm, 2), "relations_s": round(t_rel, 3),
                     "normals_median_deg": round(acc["median_deg"], 2), "normals_coverage": round(acc["coverage"], 3),
                     **sc})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["living", "bedroom", "office"])
    ap.add_argument("--sources", nargs="+", default=None, help="default: oracle orientation-map (+ model if shipped)")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--size", default="640x360")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seeds", type=int, default=1, help="captures per scene (seeds SEED .. SEED + n - 1); with more "
                    "than one capture the pooled precision and recall per source follow, with 95 %% Wilson intervals")
    ap.add_argument("--width", type=int, default=NormalsConfig().width, help="normal-map width (px)")
    ap.add_argument("--tol", type=float, default=0.02, help="coplanarity tolerance (m)")
    ap.add_argument("--root", default="/tmp/bench_relations", help="captures and pipeline caches go here")
    ap.add_argument("--set", nargs="*", help="RelationsConfig overrides key=value")
    ap.add_argument("--graph-set", nargs="*", help="GraphConfig overrides key=value for the solve of the 'kept' scores")
    ap.add_argument("--no-solve", action="store_true", help="detection scores only (no linear solve and BA)")
    ap.add_argument("--json", help="also write the results here")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    sources = args.sources
    if sources is None:
        sources = ["oracle", "orientation-map"]
        if (Path(__file__).resolve().parents[1] / "panosfm_graph" / "models" / "normals.onnx").exists():
            sources.append("model")
    # all four of the paper's tests, also parallel (off in the pipeline's default: config.RelationsConfig)
    try:
        sets = section_settings(RelationsConfig(), args.set, "relations")
    except InputError as exc:
        ap.error(str(exc))
    cfg = dataclasses.replace(RelationsConfig(), **{"parallel": True, **sets})
    try:
        graph_cfg = None if args.no_solve else dataclasses.replace(
            GraphConfig(), **section_settings(GraphConfig(), args.graph_set, "graph"))
    except InputError as exc:
        ap.error(str(exc))
    root = Path(args.root)
    root.mkdir(parents=True, exist_ok=True)
    results, cache = [], {}
    for scene, seed in ((sc, args.seed + k) for sc in args.scenes for k in range(max(args.seeds, 1))):
        cap = ensure_capture(root, scene, args.frames, args.size, seed)
        name = scene if args.seeds <= 1 else f"{scene}#{seed}"
        for r in bench_scene(cap, root / "runs", sources, args.width, args.tol, cfg, cache, graph_cfg,
                             bool(sets.get("parallel", RelationsConfig().parallel))):
            results.append(r)
            cells = [f"{_short(n)} n={r[n]['n']} P={r[n]['precision']} R={r[n]['recall']}/{r[n]['n_gt']}"
                     for n in (*RELATION_NAMES, "floor_verified")]
            print(f"{name:8s} {r['source']:15s} tracks={r['tracks']} mapped={r['tracks_mapped']} | "
                  + " | ".join(cells) + f" | {r['relations_s']}s")
            if "kept" in r:
                k = r["kept"]
                print(f"{'':8s} {'  kept by solves':15s} registered={k['registered']}/{r['frames']} | "
                      + " | ".join(f"{n[:5]} n={k[n]['n']} P={k[n]['precision']} R={k[n]['recall']}" for n in RELATION_NAMES)
                      + f" | {k['seconds']}s")
    pooled = pool(results) if len(results) > len(sources) else {}
    for source, by_type in pooled.items():
        print(f"{'pooled':8s} {source:15s} " + " | ".join(
            f"{_short(n)} P={v['precision']} [{v['low']}, {v['high']}] "
            f"({v['n_true']}/{v['n_judged']}) R={v['recall']}"
            for n, v in by_type.items()))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"rows": results, "pooled": pooled} if pooled else results, fh, indent=1)


def _short(name: str) -> str:
    """Returns a relation type's (or 'floor_verified''s) column label in the printed table."""
    return "fl.ver" if name == "floor_verified" else name[:5]


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Returns the Wilson score interval (low, high) of a binomial proportion k / n (95 % by default)."""
    if n == 0:
        return float("nan"), float("nan")
    p = k / n
    c = (p + z * z / (2 * n)) / (1 + z * z / n)
    h = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return c - h, c + h


def pool(rows: list[dict]) -> dict:
    """Returns {source: {type: pooled precision (true / judged over all captures), Wilson interval, recall}}.

    The relations the whole pipeline kept (``kept``) are pooled as source ``"<source> kept"``.
    """
    out: dict = {}
    for r in rows:
        for source, scores, names in ((r["source"], r, (*RELATION_NAMES, "floor_verified")),
                                      (f"{r['source']} kept", r.get("kept"), RELATION_NAMES)):
            for name in names if scores else ():
                v = out.setdefault(source, {}).setdefault(name, {"n_true": 0, "n_judged": 0, "n_found": 0, "n_gt": 0})
                c = scores[name]
                v["n_true"] += c["n_true"]
                v["n_judged"] += c["n"] - c["unk"]
                v["n_found"] += c["n_found"]
                v["n_gt"] += c["n_gt"]
    for by_type in out.values():
        for v in by_type.values():
            lo, hi = wilson(v["n_true"], v["n_judged"])
            v["precision"] = round(v["n_true"] / v["n_judged"], 3) if v["n_judged"] else None
            v["low"], v["high"] = (round(lo, 3), round(hi, 3)) if v["n_judged"] else (None, None)
            v["recall"] = round(v["n_found"] / v["n_gt"], 3) if v["n_gt"] else None
    return out


if __name__ == "__main__":
    main()
