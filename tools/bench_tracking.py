"""Tracking benchmark (supplement §3): how fragmented the tracks are, and what perfect joining would give end to end.

    python tools/bench_tracking.py --scenes living,bedroom,office --out /tmp/bench_tracking
    python tools/bench_tracking.py --scenes office --sway 0.05 --seeds 2 --out /tmp/bench_tracking

For each synthetic capture (300 frames 960x540 by default, written into ``OUT/captures`` unless there):

* fragmentation: the pipeline's tracks are mapped to ground-truth 3D lines
  (``bench_relations.ground_truth_view``; colinear GT edges are one
  line), and the table gives the tracks, the GT lines they cover, tracks per
  covered line and the fragment pairs (two tracks of one line that share no
  frame);
* an oracle ablation, end to end: the whole pipeline (true camera height, as
  ``tools/bench.py``) runs with its own tracks (``default``), with every
  fragment pair of one GT line joined (``oracle-join``: what a perfect
  fragment joiner would give, the spin's two ends included), with only the
  fragments that follow each other within 3 frames joined (``oracle-join-near``:
  what ``tracking.merge_fragments`` aims at) and with all
  tracks of one GT line joined (``oracle-join-all``: also two pieces of one
  line seen side by side, the longest segment per frame kept), each scored by
  :func:`panosfm_graph.evaluate.evaluate_reconstruction`.

The oracle modes replace the track stage's output inside this process (no
cache: each run is from scratch). Prints a line per run and writes ``OUT/bench_tracking.json`` (``--json``).
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

import panosfm_graph.pipeline as pipeline
from panosfm_graph.capture import load_capture
from panosfm_graph.config import Config
from panosfm_graph.data import Tracks
from panosfm_graph.evaluate import evaluate_reconstruction
from panosfm_graph.export import to_jsonable
from panosfm_graph.lines.tracking import join_tracks
from panosfm_graph.synth import synthesize

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench import capture_dir  # noqa: E402
from bench_relations import ground_truth_view  # noqa: E402

MODES = ("default", "oracle-join-near", "oracle-join", "oracle-join-all")
NEAR_FRAMES = 3  # oracle-join-near: fragments at most this many frames apart (tracking.merge_gap_frames)


def gt_line_of_tracks(capture, pre, tracks, colinear_m: float = 0.01) -> np.ndarray:
    """Returns (T,) the ground-truth 3D line of each track (-1 unknown); colinear GT edges share one id."""
    g = ground_truth_view(capture, pre, tracks)
    # a line is its axis and its two coordinates across it (colinear edges: the same)
    mid = 0.5 * (g.edges_room[:, :3] + g.edges_room[:, 3:])
    across = np.array([[1, 2], [0, 2], [0, 1]])[g.edge_axis_room]
    key = np.column_stack([g.edge_axis_room, np.rint(np.take_along_axis(mid, across, axis=1) / colinear_m)])
    _, line_of_edge = np.unique(key.astype(np.int64), axis=0, return_inverse=True)
    return np.where(g.track_edge >= 0, line_of_edge.ravel()[np.maximum(g.track_edge, 0)], -1)


def _frames_of(tracks: Tracks, frame: np.ndarray) -> list[set]:
    sets = [set() for _ in range(tracks.n)]
    to = np.asarray(tracks.track_of)
    for s in np.flatnonzero(to >= 0):
        sets[to[s]].add(int(frame[s]))
    return sets


def join_by_ground_truth(tracks: Tracks, frame: np.ndarray, length: np.ndarray, line: np.ndarray,
                         disjoint: bool, near_frames: int | None = None) -> tuple[Tracks, np.ndarray]:
    """Returns (``tracks`` with the tracks of one GT ``line`` joined, each old track's new id): with ``disjoint``
    only tracks that share no frame (longest first, greedily), otherwise all (the longest segment per frame kept,
    :func:`~panosfm_graph.lines.tracking.join_tracks`); with ``near_frames`` only a track that starts
    1..near_frames frames after the joined ones' last frame (a chain in time)."""
    T = tracks.n
    root = np.arange(T)
    frames = _frames_of(tracks, frame)
    for ln in np.unique(line[line >= 0]):
        members = np.flatnonzero(line == ln)
        if near_frames is not None:  # in time order: each joins the chain it follows closely enough
            members = members[np.argsort([min(frames[t]) for t in members], kind="stable")]
            for prev, t in zip(members[:-1], members[1:]):
                if 1 <= min(frames[t]) - max(frames[root[prev]]) <= near_frames:
                    root[t] = root[prev]
                    frames[root[t]] |= frames[t]
            continue
        members = members[np.argsort([-len(frames[t]) for t in members], kind="stable")]
        groups: list[tuple[set, int]] = []
        for t in members:
            for seen, r in groups:
                if not disjoint or not (seen & frames[t]):
                    seen |= frames[t]
                    root[t] = r
                    break
            else:
                groups.append((set(frames[t]), t))
    joined, _ = join_tracks(tracks, root, frame, length)
    return joined, np.unique(root, return_inverse=True)[1].ravel()


def fragmentation(tracks: Tracks, frame: np.ndarray, line: np.ndarray) -> dict:
    """Returns the fragmentation figures of ``tracks`` against their GT lines."""
    frames = _frames_of(tracks, frame)
    mapped = np.flatnonzero(line >= 0)
    lines, per_line = np.unique(line[mapped], return_counts=True)
    pairs = 0
    for ln in lines[per_line > 1]:
        m = np.flatnonzero(line == ln)
        pairs += sum(1 for i in range(len(m)) for j in range(i + 1, len(m)) if not frames[m[i]] & frames[m[j]])
    n_obs = np.array([len(f) for f in frames])
    return {"tracks": tracks.n, "tracks_mapped": int(len(mapped)), "gt_lines": int(len(lines)),
            "tracks_per_line": round(float(per_line.mean()), 2) if len(lines) else None,
            "lines_in_pieces": int((per_line > 1).sum()), "fragment_pairs": int(pairs),
            "frames_per_track_median": float(np.median(n_obs)) if len(n_obs) else None}


@contextlib.contextmanager
def tracks_replaced(mode: str, found: dict):
    """Within the block the pipeline's track stage returns the ``mode``'s tracks (and records fragmentation)."""
    original = pipeline._track

    def track(capture, pre, config):
        tracks = original(capture, pre, config)
        seg = pre.segments
        frame = seg.frame.astype(np.int64)
        line = gt_line_of_tracks(capture, pre, tracks)
        found["before"] = fragmentation(tracks, frame, line)
        if mode != "default":
            length = np.linalg.norm(seg.endpoints[:, 2:].astype(np.float64) - seg.endpoints[:, :2], axis=1)
            tracks, new = join_by_ground_truth(tracks, frame, length, line, disjoint=(mode != "oracle-join-all"),
                                               near_frames=NEAR_FRAMES if mode == "oracle-join-near" else None)
            joined_line = np.full(tracks.n, -1)
            joined_line[new] = line  # a joined track's members share their line (unmapped ones stay alone)
            found["after"] = fragmentation(tracks, frame, joined_line)
        return tracks

    pipeline._track = track
    try:
        yield
    finally:
        pipeline._track = original


def run_mode(cap: Path, out: Path, mode: str) -> dict:
    """Returns the metrics of one whole-pipeline run of ``mode`` on capture ``cap`` (true camera height)."""
    height = load_capture(cap).ground_truth.camera_height_m
    cfg = Config()
    cfg = dataclasses.replace(cfg, linear=dataclasses.replace(cfg.linear, camera_height_m=height))
    found: dict = {}
    t0 = time.perf_counter()
    with tracks_replaced(mode, found):
        pipeline.run_pipeline(cap, out, cfg, rerun=False, views=False)
    m = evaluate_reconstruction(cap, out)
    return {"seconds": round(time.perf_counter() - t0, 1), **found,
            "registered": m["registered_ratio"], "centre_median": m["center_error_rel"]["median"],
            "centre_mean": m["center_error_rel"]["mean"], "corner_px": m["reprojection_px"].get("mean"),
            "lines_median_m": m["lines"]["distance_m"]["median"], "lines_within": m["lines"]["within_0.05m_share"]}


def _pct(v) -> str:
    return "n/a" if v is None else f"{100 * v:.2f}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", default="living,bedroom,office")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--size", default="960x540")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seeds", type=int, default=1, help="captures per scene (seeds SEED + k + 10 j, as tools/bench.py)")
    p.add_argument("--sway", type=float, default=0.0, metavar="M", help="spins that depart from a circle (m RMS)")
    p.add_argument("--modes", default=",".join(MODES))
    p.add_argument("--out", default="/tmp/bench_tracking")
    p.add_argument("--json", help="write the rows here (default OUT/bench_tracking.json)")
    a = p.parse_args(argv)
    size = tuple(int(v) for v in a.size.lower().split("x"))
    modes = a.modes.split(",")
    if not set(modes) <= set(MODES):
        p.error(f"--modes: one or more of {', '.join(MODES)}")
    out = Path(a.out)
    scenes = a.scenes.split(",")
    rows = []
    for j in range(max(a.seeds, 1)):
        for k, scene in enumerate(scenes):
            seed = a.seed + k + 10 * j
            cap = capture_dir(out, scene, a.frames, size, seed, a.sway)
            if not (cap / "imu.csv").exists():
                synthesize(cap, scene=scene, n_frames=a.frames, size=size, seed=seed, sway_m=a.sway)
            for mode in modes:
                r = {"capture": cap.name, "mode": mode, **run_mode(cap, out / "runs" / cap.name / mode, mode)}
                rows.append(r)
                frag = r.get("after", r["before"])
                print(f"{cap.name:38s} {mode:16s} tracks {frag['tracks']:4d} ({frag['tracks_per_line']} per line, "
                      f"{frag['fragment_pairs']} fragment pairs) | registered {_pct(r['registered'])} % | centre "
                      f"median {_pct(r['centre_median'])} % mean {_pct(r['centre_mean'])} % | corners "
                      f"{r['corner_px']:.2f} px | lines {r['lines_median_m']:.3f} m, "
                      f"{_pct(r['lines_within'])} % within 5 cm | {r['seconds']} s", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    Path(a.json or out / "bench_tracking.json").write_text(json.dumps(to_jsonable({"sway_m": a.sway, "rows": rows}), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
