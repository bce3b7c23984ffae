"""Preprocessing benchmark (paper §3.1): segments, Manhattan frame, rotations, labels, tracks vs ground truth.

    python tools/bench_preprocess.py --scenes living,bedroom,office --frames 300 --size 960x540 \
        --out /tmp/bench_pre [--json /tmp/bench_pre/bench_preprocess.json]

Per synthetic scene (synthesised into ``OUT/captures`` unless already there):

* rotation error per frame (deg) of the IMU and of the refined rotations,
  each after the best global rotation A (chordal L2: A = argmin sum
  |A R_est - R_gt|_F^2, SVD): the heading gauge is arbitrary (the Manhattan
  frame / the IMU's start fix it), so only the rotations relative to each
  other are compared;
* Manhattan frame error (deg): the largest angle between an estimated
  direction, mapped by the same A, and the matching GT room axis
  (``scene.json``), and the vertical's angle to world +z without alignment;
* labelling accuracy: detected segments matched to a projected GT edge
  (both endpoints within ``--gt-px`` px of it, angle < 2 deg) whose
  predicted label (mapped onto GT axes) equals the GT edge's axis; also the
  fraction of those matched segments that got any label (recall);
* track purity: per track, the largest fraction of its members (those on a
  GT edge) lying on one GT 3D line (colinear GT edges, and parallel ones
  within 3 cm, count as one line; a segment within ``--gt-px`` of two GT
  lines -- a trim's two edges seen head-on project 2-3 px apart -- lies on
  both; GT matching ignores occlusion, so a segment may be credited to a
  hidden edge nearby); mean track length, and
  tracks obtained with larger frame-pair windows (``--windows``);
* seconds per stage, peak memory (ru_maxrss of this process and children).
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

from panosfm_graph.config import Config, with_overrides
from panosfm_graph.geometry import rotation_angle_deg


def align_rotation(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """Returns the 3x3 rotation A minimising sum |A R_est[i] - R_gt[i]|_F^2 (chordal L2 alignment)."""
    M = np.einsum("fij,fkj->ik", R_gt, R_est)
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def rotation_errors(R_est: np.ndarray, R_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns (per-frame errors in degrees after global alignment, the alignment A)."""
    A = align_rotation(R_est, R_gt)
    return rotation_angle_deg(np.einsum("ij,fjk->fik", A, R_est), R_gt), A


def gt_edge_distances(segments, K, R_gt, c_gt, lines, tol_px: float, angle_deg: float = 2.0):
    """Returns (segment ids, GT edge ids, distances px) of every segment / GT 3D edge pair that fit.

    GT edges are clipped to the front of each camera (z > 0.05 m) and
    projected; a segment fits an edge when both its endpoints lie within
    ``tol_px`` of the projected edge and their directions differ < ``angle_deg``.
    A segment may fit several edges (a trim's two edges 4 cm apart in depth
    project 2-3 px apart when seen head-on).
    """
    out_s, out_e, out_d = [], [], []
    A, B = lines[:, :3], lines[:, 3:6]
    for f in range(len(R_gt)):
        sl = segments.of_frame(f)
        if sl.stop == sl.start:
            continue
        a = (A - c_gt[f]) @ R_gt[f]
        b = (B - c_gt[f]) @ R_gt[f]
        za, zb = a[:, 2], b[:, 2]
        vis = (za > 0.05) | (zb > 0.05)
        t = np.clip((0.05 - za) / np.where(np.abs(zb - za) > 1e-12, zb - za, 1e-12), 0.0, 1.0)
        a2 = np.where((za < 0.05)[:, None], a + t[:, None] * (b - a), a)
        t2 = np.clip((0.05 - zb) / np.where(np.abs(za - zb) > 1e-12, za - zb, 1e-12), 0.0, 1.0)
        b2 = np.where((zb < 0.05)[:, None], b + t2[:, None] * (a - b), b)
        pa = (a2 @ K.T)[:, :2] / np.maximum(a2[:, 2:], 1e-9)
        pb = (b2 @ K.T)[:, :2] / np.maximum(b2[:, 2:], 1e-9)
        e = segments.endpoints[sl].astype(np.float64)
        d_gt = pb - pa
        L2 = np.maximum(np.sum(d_gt**2, axis=1), 1e-12)

        def seg_dist(p):  # (S_f, M) distance of points p (S_f, 2) to GT segments
            t = np.clip(((p[:, None, :] - pa[None]) * d_gt[None]).sum(-1) / L2[None], 0.0, 1.0)
            q = pa[None] + t[..., None] * d_gt[None]
            return np.linalg.norm(p[:, None, :] - q, axis=-1)

        dist = np.maximum(seg_dist(e[:, :2]), seg_dist(e[:, 2:]))
        d_seg = e[:, 2:] - e[:, :2]
        cos = np.abs(d_seg @ d_gt.T) / (np.linalg.norm(d_seg, axis=1)[:, None] * np.sqrt(L2)[None] + 1e-12)
        s, m = np.nonzero(vis[None] & (dist < tol_px) & (cos > np.cos(np.radians(angle_deg))))
        out_s.append(sl.start + s)
        out_e.append(m)
        out_d.append(dist[s, m])
    if not out_s:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(out_s), np.concatenate(out_e), np.concatenate(out_d)


def gt_edge_of_segments(segments, K, R_gt, c_gt, lines, tol_px: float, angle_deg: float = 2.0) -> np.ndarray:
    """Returns (S,) index of the GT 3D edge each detected segment lies on, the nearest that fits (-1: none)."""
    return nearest_edge(segments.n, *gt_edge_distances(segments, K, R_gt, c_gt, lines, tol_px, angle_deg))


def nearest_edge(n: int, s: np.ndarray, e: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Returns (n,) the nearest GT edge of each segment from :func:`gt_edge_distances`' pairs (-1: none)."""
    out = np.full(n, -1, dtype=np.int64)
    order = np.lexsort((d, s))
    first = np.r_[True, s[order][1:] != s[order][:-1]] if len(s) else np.zeros(0, bool)
    out[s[order][first]] = e[order][first]
    return out


def track_purity(track_of: np.ndarray, seg_ids: np.ndarray, line_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns (purity (T,), members on a GT line (T,)) of tracks given the (segment, GT line) pairs that fit.

    A track's purity is the largest share of its members (those that fit
    some GT line) that fit one and the same GT line; a segment fitting two
    lines (image-coincident in that frame) counts for both, since nothing
    in the image says which it is. NaN for a track with no such member.
    """
    T = int(track_of.max()) + 1 if len(track_of) and track_of.max() >= 0 else 0
    keep = track_of[seg_ids] >= 0
    pairs = np.unique(np.column_stack([track_of[seg_ids[keep]], seg_ids[keep], line_ids[keep]]), axis=0)
    known = np.bincount(np.unique(pairs[:, :2], axis=0)[:, 0], minlength=T)
    tl, cnt = np.unique(pairs[:, [0, 2]], axis=0, return_counts=True)
    best = np.zeros(T)
    np.maximum.at(best, tl[:, 0], cnt)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(known > 0, best / known, np.nan), known


def gt_line_groups(lines: np.ndarray, labels: np.ndarray, D_gt: np.ndarray, tol_m: float = 0.03) -> np.ndarray:
    """Returns (M,) id of the infinite GT 3D line of each GT edge.

    Colinear edges, and parallel edges closer than ``tol_m`` (a door leaf
    and its trim), share one id: one image segment cannot tell them apart.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    mid = 0.5 * (lines[:, :3] + lines[:, 3:6])
    coords = mid @ D_gt.T  # room-axis coordinates
    other = np.array([[1, 2], [0, 2], [0, 1]])[np.clip(labels, 0, 2)]
    key = np.concatenate([np.take_along_axis(coords, other, axis=1), 1e3 * labels[:, None]], axis=1)
    pairs = cKDTree(key).query_pairs(tol_m, output_type="ndarray").reshape(-1, 2)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(lines), len(lines)))
    return connected_components(g, directed=False)[1]


def evaluate(capture, pre, tracks, gt_px: float) -> dict:
    """Returns the preprocessing metrics of one capture against its ground truth (see module docstring)."""
    gt = capture.ground_truth
    K = capture.camera.K
    D_gt = np.asarray(gt.scene.get("manhattan_directions_world"), dtype=np.float64)
    if D_gt.shape != (3, 3):
        D_gt = np.eye(3)
    e_imu, _ = rotation_errors(pre.R_wc_imu, gt.R_wc)
    e_ref, A = rotation_errors(pre.R_wc, gt.R_wc)
    M = pre.manhattan.directions @ A.T  # estimated directions in the GT world
    match = np.argmax(np.abs(M @ D_gt.T), axis=1)  # estimated axis -> GT axis
    mf_err = float(np.max(np.degrees(np.arccos(np.clip(np.abs(np.sum(M * D_gt[match], axis=1)), 0, 1)))))
    vert_err = float(np.degrees(np.arccos(min(1.0, abs(pre.manhattan.directions[2, 2])))))

    fit_s, fit_e, fit_d = gt_edge_distances(pre.segments, K, gt.R_wc, gt.centers, gt.lines, gt_px)
    seg_edge = nearest_edge(pre.segments.n, fit_s, fit_e, fit_d)
    has_gt = seg_edge >= 0
    gt_lab = np.where(has_gt, gt.line_labels[np.maximum(seg_edge, 0)], -1)
    pred = np.where(pre.labels >= 0, match[np.maximum(pre.labels, 0)], -1)
    labelled = has_gt & (pre.labels >= 0)
    acc = float(np.mean(pred[labelled] == gt_lab[labelled])) if labelled.any() else float("nan")

    line_id = gt_line_groups(gt.lines, gt.line_labels, D_gt)
    purity, known = track_purity(np.asarray(tracks.track_of), fit_s, line_id[fit_e])
    lengths = np.diff(tracks.members()[1])
    purities = purity[known > 0]
    known_frac = known / np.maximum(lengths, 1)
    return {
        "frames": capture.n_frames,
        "segments": int(pre.segments.n),
        "manhattan_segments": int(np.sum(pre.labels >= 0)),
        "rot_err_imu_deg": {"median": float(np.median(e_imu)), "max": float(e_imu.max())},
        "rot_err_refined_deg": {"median": float(np.median(e_ref)), "max": float(e_ref.max())},
        "improvement_x": float(np.median(e_imu) / max(np.median(e_ref), 1e-9)),
        "manhattan_err_deg": mf_err,
        "vertical_err_deg": vert_err,
        "labelling_accuracy": acc,
        "labelling_recall": float(np.mean(pre.labels[has_gt] >= 0)) if has_gt.any() else float("nan"),
        "segments_on_gt_edges": float(np.mean(has_gt)),
        "tracks": int(tracks.n),
        "track_purity_mean": float(np.mean(purities)) if len(purities) else float("nan"),
        "track_members_on_gt_edges": float(np.mean(known_frac)) if len(known_frac) else float("nan"),
        "track_length_mean": float(lengths.mean()) if len(lengths) else 0.0,
        "tracked_fraction": float(np.sum(tracks.track_of >= 0) / max(np.sum(pre.labels >= 0), 1)),
    }


def peak_memory_mb() -> float:
    """Returns the peak resident memory (MB) of this process plus its largest child."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return (own + kids) / 1024.0


def bench(scenes, frames, size, out: Path, windows, gt_px, seed=0, workers=2) -> dict:
    """Returns the record of all scenes (also written as JSON by :func:`main`)."""
    from panosfm_graph.capture import load_capture
    from panosfm_graph.lines import detect_segments, refine_manhattan_and_rotations, track_lines
    from panosfm_graph.synth import synthesize

    record = {"frames": frames, "size": list(size), "scenes": {}}
    for k, scene in enumerate(scenes):
        cap_dir = out / "captures" / f"{scene}-{frames}-{size[0]}x{size[1]}-s{seed + k}"
        if not (cap_dir / "imu.csv").exists():
            t0 = time.perf_counter()
            synthesize(cap_dir, scene=scene, n_frames=frames, size=size, seed=seed + k, gt_maps=False)
            print(f"[{scene}] synthesised in {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
        capture = load_capture(cap_dir)
        cfg = with_overrides(Config(), detect={"workers": workers})
        secs = {}
        t0 = time.perf_counter()
        segments = detect_segments(capture, cfg.detect)
        secs["detect"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        pre = refine_manhattan_and_rotations(segments, capture, cfg)
        secs["manhattan+rotations"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        tracks = track_lines(capture, pre, cfg)
        secs["tracking"] = time.perf_counter() - t0
        entry = evaluate(capture, pre, tracks, gt_px)
        entry["seconds"] = secs
        entry["seconds_total"] = sum(secs.values())
        entry["windows"] = {}
        for wdeg in windows:
            c = with_overrides(cfg, tracking={"axis_angle_deg": wdeg})
            t0 = time.perf_counter()
            tr = track_lines(capture, pre, c)
            ev = evaluate(capture, pre, tr, gt_px)
            entry["windows"][str(wdeg)] = {
                "tracks": ev["tracks"], "track_length_mean": ev["track_length_mean"],
                "track_purity_mean": ev["track_purity_mean"], "tracked_fraction": ev["tracked_fraction"],
                "seconds": time.perf_counter() - t0,
            }
        entry["peak_memory_mb"] = peak_memory_mb()
        record["scenes"][scene] = entry
    return record


def table(record: dict) -> str:
    """Returns a plain-text table of the record."""
    head = (f"{'scene':10s} {'segs':>6s} {'manh':>6s} {'imu med/max':>12s} {'ref med/max':>12s} {'x':>5s} "
            f"{'MF':>5s} {'vert':>5s} {'label':>6s} {'tracks':>6s} {'purity':>6s} {'len':>5s} {'sec':>6s} {'MB':>6s}")
    rows = [head]
    for name, e in record["scenes"].items():
        rows.append(
            f"{name:10s} {e['segments']:6d} {e['manhattan_segments']:6d} "
            f"{e['rot_err_imu_deg']['median']:5.2f}/{e['rot_err_imu_deg']['max']:5.2f} "
            f"{e['rot_err_refined_deg']['median']:5.2f}/{e['rot_err_refined_deg']['max']:5.2f} "
            f"{e['improvement_x']:5.1f} {e['manhattan_err_deg']:5.2f} {e['vertical_err_deg']:5.2f} "
            f"{100 * e['labelling_accuracy']:5.1f}% {e['tracks']:6d} {100 * e['track_purity_mean']:5.1f}% "
            f"{e['track_length_mean']:5.1f} {e['seconds_total']:6.1f} {e['peak_memory_mb']:6.0f}"
        )
        for w, v in e["windows"].items():
            rows.append(f"{'':10s}   window {w:>4s} deg: {v['tracks']} tracks, mean length "
                        f"{v['track_length_mean']:.1f}, purity {100 * v['track_purity_mean']:.1f}%, "
                        f"tracked {100 * v['tracked_fraction']:.0f}% of Manhattan segments")
    return "\n".join(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="living,bedroom,office")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--size", default="960x540")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_preprocess"))
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--windows", default="5,10", help="extra tracking frame-pair windows (deg) to report")
    ap.add_argument("--gt-px", type=float, default=None, help="GT edge tolerance (px; default 0.006 * min side)")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    gt_px = args.gt_px if args.gt_px is not None else max(1.5, 0.006 * min(w, h))
    windows = [float(v) for v in args.windows.split(",") if v]
    record = bench(args.scenes.split(","), args.frames, (w, h), args.out, windows, gt_px, workers=args.workers)
    record["gt_px"] = gt_px
    path = args.json or args.out / "bench_preprocess.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1) + "\n")
    print(table(record))
    print(f"written {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
