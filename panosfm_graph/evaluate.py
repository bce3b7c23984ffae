"""Metrics of a reconstruction directory against a capture's ``ground_truth/``.

Works on any reconstruction in the format of ``capture-format.md`` (COLMAP
text model + optional ``lines.ply``), whoever wrote it. Every metric states
its alignment and units, in the manner of evo's ``--align --correct_scale``:

* registration: frames, registered frames (images in images.txt, matched to
  capture frames by file name, then base name, then stem) and their share;
* trajectory: a similarity (Umeyama, with scale) maps the estimated camera
  centres onto the true ones; centre error in metres and relative to the true
  trajectory's diameter (largest distance between two true centres); rotation
  error after the same similarity's rotation (and, separately, after the best
  rotation-only alignment of the orientations);
* the paper's protocol (§4, "manually clicked correspondences ... triangulated
  ... reprojection errors"), automated: true 3D corners (endpoints of the true
  edges) visible in at least ``min_views`` registered frames are "clicked"
  (projected with the TRUE poses, plus seeded Gaussian pixel noise),
  triangulated with the ESTIMATED poses (linear DLT over all clicks) and
  reprojected into the estimated cameras: mean / median / std in pixels;
* lines (``lines.ply``, after the similarity): distance of reconstructed lines
  to the true surfaces (``scene.json`` boxes) and the share of true edges
  recovered (covered over at least half their length by reconstructed
  segments within ``edge_dist_m`` and ``edge_angle_deg``).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.distance import pdist

from .data import Camera, Capture
from .errors import InputError
from .export import poses_for_frames, read_colmap_text, read_lines_ply
from .geometry import rotation_alignment, rotation_angle_deg, umeyama  # noqa: F401  (re-exported: evaluation API)
from .geometry import triangulate_dlt

log = logging.getLogger(__name__)
# a registered frame is accurate when its centre lies within this share of the true trajectory's diameter and its
# rotation within this many degrees, after the rotation of the orientations and the scale and shift of the centres
# (accurate_frames; see docs/decisions.md#accurate-frames-aligned-by-the-orientations)
ACCURATE_CENTER_REL = 0.05
ACCURATE_ROTATION_DEG = 1.0
ZERO_BASELINE_M = 1e-6  # true centres closer than this: a zero-baseline capture, rotations only


# --------------------------------------------------------------------------------------
# Alignment
# --------------------------------------------------------------------------------------


def similarity_alignment(c_est: np.ndarray, c_gt: np.ndarray, R_est: np.ndarray, R_gt: np.ndarray) -> dict:
    """Returns the similarity {"method", "scale", "R", "t"} taking estimated centres onto true ones.

    Umeyama with scale on the centres when they span at least a plane (second
    singular value > 1e-6 of the first); otherwise (fewer than 3 frames, colinear
    or coincident centres) the rotation comes from the orientations and only scale
    and translation from the centres.
    """
    xs = c_est - c_est.mean(axis=0)
    sv = np.linalg.svd(xs, compute_uv=False) if len(xs) >= 2 else np.zeros(1)
    if len(c_est) >= 3 and sv[0] > 0 and sv[1] > 1e-6 * sv[0]:
        s, R, t = umeyama(c_est, c_gt)
        method = "umeyama_sim3 (camera centres, with scale)"
    else:
        return {**orientation_alignment(c_est, c_gt, R_est, R_gt),
                "method": "rotation from orientations + scale/translation from centres (centres degenerate)"}
    return {"method": method, "scale": float(s), "R": R, "t": t}


def orientation_alignment(c_est: np.ndarray, c_gt: np.ndarray, R_est: np.ndarray, R_gt: np.ndarray) -> dict:
    """Returns the similarity {"method", "scale", "R", "t"} whose rotation comes from the orientations (chordal
    mean, :func:`rotation_alignment`) and whose scale and translation are the least-squares fit of the centres."""
    A = rotation_alignment(R_est, R_gt)
    xs, xd = c_est - c_est.mean(axis=0), c_gt - c_gt.mean(axis=0)
    den = float(np.sum(xs * xs))
    s = max(float(np.sum(xd * (xs @ A.T)) / den), 0.0) if den > 0 else 0.0
    return {"method": "rotation from orientations, scale and translation from centres", "scale": s, "R": A,
            "t": c_gt.mean(axis=0) - s * A @ c_est.mean(axis=0)}


def accurate_frames(c_est: np.ndarray, c_gt: np.ndarray, R_est: np.ndarray, R_gt: np.ndarray, diam: float) -> int:
    """Returns how many frames lie within ``ACCURATE_CENTER_REL`` * ``diam`` and ``ACCURATE_ROTATION_DEG`` of the
    truth after :func:`orientation_alignment`.

    Not after the centres' similarity (:func:`similarity_alignment`): a spin's centres lie on a circle of about
    0.35 m, so that alignment's heading is set by the centres' errors along the circle (1 cm there turns it by
    1.9 deg) and every rotation then carries it. Measured (synthetic spins, 100-150 frames): rotations 0.07-0.18
    deg off after the orientations' alignment read 0.5-2.6 deg after the centres', and a capture with every
    centre within 2.4 % of the diameter counted 0 accurate frames. Aligned by the orientations, each centre is
    judged without a rotation fitted to the centres themselves (stricter on them).
    """
    if len(c_est) == 0 or diam <= 0:
        return 0
    err, rot = frame_errors(c_est, c_gt, R_est, R_gt, diam)
    return int(np.sum((err <= ACCURATE_CENTER_REL) & (rot <= ACCURATE_ROTATION_DEG)))


def frame_errors(c_est: np.ndarray, c_gt: np.ndarray, R_est: np.ndarray, R_gt: np.ndarray, diam: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((N,) each centre's error over ``diam``, (N,) each rotation's error in degrees) after
    :func:`orientation_alignment` (the alignment :func:`accurate_frames` judges by)."""
    al = orientation_alignment(c_est, c_gt, R_est, R_gt)
    err = np.linalg.norm(al["scale"] * c_est @ al["R"].T + al["t"] - c_gt, axis=1) / diam
    return err, rotation_angle_deg(np.einsum("ij,njk->nik", al["R"], R_est), R_gt)


# --------------------------------------------------------------------------------------
# Scene surfaces (scene.json)
# --------------------------------------------------------------------------------------


def scene_boxes(scene: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Returns (mins (B, 3), maxs (B, 3), R_world_room, t_world_room) of scene.json, shell first; None if none.

    Schema of ``panosfm_graph.synth`` (version 1): ``room`` {min, max} (inside-out shell),
    ``boxes`` [{min, max}] solid boxes, both in the room frame,
    ``p_world = R_world_room p_room + t_world_room`` (identity / zero when absent).
    """
    if not isinstance(scene, dict):
        return None
    mins, maxs = [], []
    room = scene.get("room")
    if isinstance(room, dict) and "min" in room and "max" in room:
        mins.append(room["min"])
        maxs.append(room["max"])
    for b in scene.get("boxes", []) or []:
        if isinstance(b, dict) and "min" in b and "max" in b:
            mins.append(b["min"])
            maxs.append(b["max"])
    if not mins:
        return None
    R = np.asarray(scene.get("R_world_room", np.eye(3)), dtype=np.float64).reshape(3, 3)
    t = np.asarray(scene.get("t_world_room", np.zeros(3)), dtype=np.float64).reshape(3)
    return np.asarray(mins, dtype=np.float64).reshape(-1, 3), np.asarray(maxs, dtype=np.float64).reshape(-1, 3), R, t


def distance_to_boxes(points_world: np.ndarray, boxes, chunk: int = 20000) -> np.ndarray:
    """Returns (N,) distances (m) from world points to the nearest box surface (inside or outside a box)."""
    mins, maxs, R, t = boxes
    p = (np.asarray(points_world, dtype=np.float64).reshape(-1, 3) - t) @ R
    out = np.empty(len(p))
    for a in range(0, len(p), chunk):
        q = np.maximum(mins[None] - p[a:a + chunk, None], p[a:a + chunk, None] - maxs[None])  # (n, B, 3)
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=2)
        inside = -np.minimum(q.max(axis=2), 0.0)
        out[a:a + chunk] = np.where(outside > 0, outside, inside).min(axis=1)
    return out


def segments_blocked(a_world: np.ndarray, b_world: np.ndarray, boxes, shrink_m: float = 1e-3,
                     chunk: int = 20000) -> np.ndarray:
    """Returns (N,) bool: segment a->b passes through the inside of a solid box (the shell excluded).

    Boxes are shrunk by ``shrink_m`` so a corner on a box's own surface is not hidden by it.
    """
    mins, maxs, R, t = boxes
    mins, maxs = mins[1:] + shrink_m, maxs[1:] - shrink_m  # [0] is the room shell
    a = (np.asarray(a_world, dtype=np.float64) - t) @ R
    d = (np.asarray(b_world, dtype=np.float64) - t) @ R - a
    out = np.zeros(len(a), dtype=bool)
    if len(mins) == 0:
        return out
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(0, len(a), chunk):
            o, v = a[k:k + chunk, None], d[k:k + chunk, None]
            inv = 1.0 / v
            t1, t2 = (mins[None] - o) * inv, (maxs[None] - o) * inv
            lo = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
            hi = np.where(np.isnan(t1), np.inf, np.maximum(t1, t2))
            # a zero direction component: inside the slab -> (-inf, inf), outside -> empty
            par = v == 0
            inside_slab = (o >= mins[None]) & (o <= maxs[None])
            lo = np.where(par, np.where(inside_slab, -np.inf, np.inf), lo)
            hi = np.where(par, np.where(inside_slab, np.inf, -np.inf), hi)
            tmin, tmax = lo.max(axis=2), hi.min(axis=2)
            out[k:k + chunk] = np.any((tmin < tmax) & (tmax > 0.0) & (tmin < 1.0), axis=1)
    return out


# --------------------------------------------------------------------------------------
# Clicked-corner protocol
# --------------------------------------------------------------------------------------


def _world_to_cam(R_wc: np.ndarray, centers: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Returns (F, N, 3) camera-frame coordinates of world points X (N, 3) in F cameras."""
    return np.einsum("fji,fnj->fni", R_wc, X[None] - centers[:, None])


def _pixels(camera: Camera, xn: np.ndarray) -> np.ndarray:
    """Returns (N, 2) image pixels (with the camera's distortion) of normalised coordinates (N, 2)."""
    from .capture import distort_points

    K = camera.K
    pin = xn * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    return distort_points(camera, pin) if np.any(camera.distortion) else pin


def _normalised(camera: Camera, pix: np.ndarray) -> np.ndarray:
    """Returns (N, 2) normalised coordinates of image pixels (N, 2), undoing the camera's distortion."""
    from .capture import undistort_points

    K = camera.K
    if np.any(camera.distortion):
        pix = undistort_points(camera, pix)
    return (pix - [K[0, 2], K[1, 2]]) / [K[0, 0], K[1, 1]]


def _rescale_pixels(pix: np.ndarray, src: Camera, dst: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Returns (pixels in dst's image, (sx, sy)) for pixels of src's image of another size."""
    s = np.array([dst.width / src.width, dst.height / src.height])
    return (pix + 0.5) * s - 0.5, s


def visible_corners(corners: np.ndarray, R_wc: np.ndarray, centers: np.ndarray, camera: Camera,
                    depth_of=None, boxes=None, min_depth_m: float = 0.05, margin_px: float = 1.0,
                    depth_tol: float = 0.02) -> tuple[np.ndarray, str]:
    """Returns ((F, N) bool visibility of corners in F true cameras, occlusion method used).

    Visible: in front (depth > ``min_depth_m``), inside the image by ``margin_px``,
    and not occluded: per the true depth map when ``depth_of(f)`` gives one (the
    farthest surface in the 3x3 pixels around the corner is not nearer than the
    corner by more than ``depth_tol`` relative), else per the scene's solid boxes,
    else not tested.
    """
    Xc = _world_to_cam(R_wc, centers, corners)
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = Xc[..., :2] / z[..., None]
    K = camera.K
    uv = uv * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    W, H = camera.width, camera.height
    vis = (z > min_depth_m) & (uv[..., 0] >= margin_px - 0.5) & (uv[..., 0] <= W - 0.5 - margin_px) \
        & (uv[..., 1] >= margin_px - 0.5) & (uv[..., 1] <= H - 0.5 - margin_px)
    method = "none"
    if depth_of is not None:
        maps = {}
        for f in np.flatnonzero(vis.any(axis=1)):
            d = depth_of(int(f))
            if d is not None:
                maps[f] = d
        if maps:
            method = "ground-truth depth"
            for f, d in maps.items():
                n = np.flatnonzero(vis[f])
                u = np.clip(np.rint(uv[f, n, 0]).astype(int), 0, d.shape[1] - 1)
                v = np.clip(np.rint(uv[f, n, 1]).astype(int), 0, d.shape[0] - 1)
                du, dv = np.meshgrid([-1, 0, 1], [-1, 0, 1])
                uu = np.clip(u[:, None] + du.ravel(), 0, d.shape[1] - 1)
                vv = np.clip(v[:, None] + dv.ravel(), 0, d.shape[0] - 1)
                dd = d[vv, uu].astype(np.float64)
                dd = np.where(dd > 0, dd, np.inf)  # no surface: nothing in front
                vis[f, n] = dd.max(axis=1) >= z[f, n] * (1.0 - depth_tol)
    if method == "none" and boxes is not None:
        method = "scene boxes"
        fi, ni = np.nonzero(vis)
        blocked = segments_blocked(centers[fi], corners[ni], boxes)
        vis[fi[blocked], ni[blocked]] = False
    return vis, method


def _project_h(R_wc: np.ndarray, centers: np.ndarray, Xh: np.ndarray) -> np.ndarray:
    """Returns (K, 2) normalised projections of homogeneous points Xh (K, 4) in cameras (K,)."""
    Xc = np.einsum("kji,kj->ki", R_wc, Xh[:, :3] - Xh[:, 3:] * centers)
    with np.errstate(divide="ignore", invalid="ignore"):
        return Xc[:, :2] / Xc[:, 2:]


def _stats(x: np.ndarray) -> dict:
    x = np.asarray(x, dtype=np.float64)
    if len(x) == 0:
        return {"mean": None, "median": None, "std": None, "rmse": None, "max": None}
    return {"mean": float(x.mean()), "median": float(np.median(x)), "std": float(x.std()),
            "rmse": float(np.sqrt(np.mean(x * x))), "max": float(x.max())}


# --------------------------------------------------------------------------------------
# Lines
# --------------------------------------------------------------------------------------


def _sample_segments(E: np.ndarray, step_m: float, max_per: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """Returns (points (N, 3), owner segment (N,)): bin centres every <= step_m along each segment."""
    L = np.linalg.norm(E[:, 3:] - E[:, :3], axis=1)
    n = np.clip(np.ceil(L / step_m).astype(int), 1, max_per)
    owner = np.repeat(np.arange(len(E)), n)
    start = np.concatenate([[0], np.cumsum(n)[:-1]])
    frac = (np.arange(len(owner)) - start[owner] + 0.5) / n[owner]
    pts = E[owner, :3] + frac[:, None] * (E[owner, 3:] - E[owner, :3])
    return pts, owner


def _point_segment_dist(p: np.ndarray, E: np.ndarray) -> np.ndarray:
    """Returns (N,) distances from points p (N, 3) to segments E (N, 6), row by row."""
    a, d = E[:, :3], E[:, 3:] - E[:, :3]
    t = np.clip(np.sum((p - a) * d, axis=1) / np.maximum(np.sum(d * d, axis=1), 1e-18), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * d), axis=1)


def edge_coverage(gt: np.ndarray, rec: np.ndarray, dist_m: float, angle_deg: float,
                  step_m: float = 0.01) -> np.ndarray:
    """Returns (M,) fraction of each true edge covered by reconstructed segments within dist_m and angle_deg.

    Both sets are sampled every ``step_m``; for each group of true edges sharing a
    direction, reconstructed segments within ``angle_deg`` go into a cKDTree of their
    samples and each true sample is covered when one of its nearby candidates' exact
    point-to-segment distance is within ``dist_m``.
    """
    cover = np.zeros(len(gt))
    if len(gt) == 0 or len(rec) == 0:
        return cover
    unit = lambda E: (E[:, 3:] - E[:, :3]) / np.maximum(np.linalg.norm(E[:, 3:] - E[:, :3], axis=1, keepdims=True), 1e-12)  # noqa: E731
    dg, dr = unit(gt), unit(rec)
    # group true edges by direction (sign-free), 1e-3 rad resolution
    big = np.argmax(np.abs(dg), axis=1)
    canon = dg * np.sign(dg[np.arange(len(dg)), big])[:, None]
    _, group = np.unique(np.round(canon, 3), axis=0, return_inverse=True)
    group = group.ravel()
    gp, gown = _sample_segments(gt, step_m)
    covered = np.zeros(len(gp), dtype=bool)
    cos_tol = np.cos(np.radians(angle_deg))
    k_nn = 8
    for g in np.unique(group):
        members = np.flatnonzero(group == g)
        mean_dir = canon[members].mean(axis=0)
        ok = np.abs(dr @ (mean_dir / np.linalg.norm(mean_dir))) >= cos_tol
        if not ok.any():
            continue
        cand = np.flatnonzero(ok)
        rp, rown = _sample_segments(rec[cand], step_m)
        tree = cKDTree(rp)
        q = np.flatnonzero(np.isin(gown, members))
        _, nn = tree.query(gp[q], k=min(k_nn, len(rp)), distance_upper_bound=dist_m + step_m)
        nn = nn.reshape(len(q), -1)
        hit = nn < len(rp)
        seg = cand[rown[np.where(hit, nn, 0)]]  # (Q, k)
        d = _point_segment_dist(np.repeat(gp[q], nn.shape[1], axis=0), rec[seg.ravel()]).reshape(seg.shape)
        covered[q] = np.any(hit & (d <= dist_m), axis=1)
    counts = np.bincount(gown, minlength=len(gt))
    return np.bincount(gown, weights=covered, minlength=len(gt)) / np.maximum(counts, 1)


# --------------------------------------------------------------------------------------
# The evaluation
# --------------------------------------------------------------------------------------


def _raw_camera(capture: Capture) -> Camera:
    """Returns the capture's camera as camera.json gives it (full size, with distortion), else the working one."""
    path = Path(capture.root) / "camera.json"
    if path.is_file():
        from .capture import read_camera

        return read_camera(path)[0]
    return capture.camera


def evaluate_reconstruction(capture: Capture | str | Path, recon_dir: str | Path, *, click_noise_px: float = 0.5,
                            seed: int = 0, min_views: int = 3, edge_dist_m: float = 0.05,
                            edge_angle_deg: float = 3.0, edge_cover_frac: float = 0.5,
                            min_gt_edge_m: float = 0.1, sample_step_m: float = 0.01) -> dict:
    """Returns the metrics of the reconstruction in ``recon_dir`` against the capture's ground truth.

    ``capture`` is a loaded :class:`Capture` or a capture directory (loaded with the
    default :class:`CaptureConfig`). Sections: registration, ``alignment`` (the
    similarity used), ``center_error_m`` / ``center_error_rel`` (over the true
    trajectory's diameter), ``rotation_error_deg`` (after the similarity's rotation)
    and ``rotation_error_rotalign_deg`` (after the best rotation-only alignment),
    ``reprojection_px`` (paper §4 click protocol: ``min_views`` registered frames,
    ``click_noise_px`` seeded noise, DLT with estimated poses; pixels of the
    reference image, see ``reprojection_px["image"]``) and ``lines`` (None without
    lines.ply: distance to true surfaces, share of true edges >= ``min_gt_edge_m``
    long covered over ``edge_cover_frac`` of their length within ``edge_dist_m`` and
    ``edge_angle_deg``). Metrics that cannot be computed are None.
    """
    if not isinstance(capture, Capture):
        from .capture import load_capture

        capture = load_capture(capture)
    recon_dir = Path(recon_dir)
    gt = capture.ground_truth
    if gt is None:
        raise InputError("the capture has no ground_truth/ to evaluate against", Path(capture.root) / "ground_truth")
    if not recon_dir.is_dir():
        raise InputError("reconstruction directory does not exist", recon_dir)
    model = read_colmap_text(recon_dir / "sparse")
    R_est, c_est, reg = poses_for_frames(model, capture.frame_names)
    F = capture.n_frames
    has_gt = np.all(np.isfinite(gt.centers), axis=1) & np.all(np.isfinite(gt.R_wc), axis=(1, 2))
    use = np.flatnonzero(reg & has_gt)
    out: dict = {
        "reconstruction": str(recon_dir),
        "capture": str(capture.root),
        "frames": F,
        "registered": int(reg.sum()),
        "registered_ratio": float(reg.sum() / F) if F else 0.0,
        "images_not_in_capture": int(len(model["images"]) - reg.sum()),
        "frames_with_gt_pose": int(has_gt.sum()),
        "alignment": None, "trajectory_diameter_m": None,
        "center_error_m": _stats([]), "center_error_rel": _stats([]),
        "rotation_error_deg": _stats([]), "rotation_error_rotalign_deg": _stats([]),
        "reprojection_px": None, "lines": None, "accurate": 0,
        "run_frames": _run_frames(recon_dir),
    }
    if len(use) == 0:
        log.warning("no registered frame has a ground-truth pose: nothing to align")
        out["lines"] = _line_metrics(recon_dir, gt, None, edge_dist_m, edge_angle_deg, edge_cover_frac,
                                     min_gt_edge_m, sample_step_m)
        return out

    diam = float(pdist(gt.centers[has_gt]).max()) if has_gt.sum() >= 2 else 0.0
    if has_gt.sum() >= 2 and diam <= ZERO_BASELINE_M:
        return _zero_baseline_metrics(out, R_est[use], gt.R_wc[use], c_est[use])

    # -- trajectory -------------------------------------------------------------------
    al = similarity_alignment(c_est[use], gt.centers[use], R_est[use], gt.R_wc[use])
    s, A, t = al["scale"], al["R"], al["t"]
    c_al = s * c_est[use] @ A.T + t
    R_al = np.einsum("ij,njk->nik", A, R_est[use])
    err = np.linalg.norm(c_al - gt.centers[use], axis=1)
    out["alignment"] = {"method": al["method"], "frames": int(len(use)), "scale": s, "R": A, "t": t}
    out["trajectory_diameter_m"] = diam
    out["center_error_m"] = _stats(err)
    out["center_error_rel"] = _stats(err / diam) if diam > 0 else _stats([])
    rot = rotation_angle_deg(R_al, gt.R_wc[use])
    out["rotation_error_deg"] = _stats(rot)
    if diam > 0:
        out["accurate_sim3"] = int(np.sum((err / diam <= ACCURATE_CENTER_REL) & (rot <= ACCURATE_ROTATION_DEG)))
        e_rel, e_rot = frame_errors(c_est[use], gt.centers[use], R_est[use], gt.R_wc[use], diam)
        good = (e_rel <= ACCURATE_CENTER_REL) & (e_rot <= ACCURATE_ROTATION_DEG)
        out["accurate"] = int(good.sum())
        out["uncertainty"] = uncertainty_metrics(recon_dir, use, e_rel, good, F)
    B = rotation_alignment(R_est[use], gt.R_wc[use])
    out["rotation_error_rotalign_deg"] = _stats(rotation_angle_deg(np.einsum("ij,njk->nik", B, R_est[use]), gt.R_wc[use]))

    # -- clicked corners (paper §4) ---------------------------------------------------
    out["reprojection_px"] = _click_metrics(capture, model["camera"], gt, use, R_al, c_al, click_noise_px, seed,
                                            min_views)

    # -- lines --------------------------------------------------------------------------
    out["lines"] = _line_metrics(recon_dir, gt, (s, A, t), edge_dist_m, edge_angle_deg, edge_cover_frac,
                                 min_gt_edge_m, sample_step_m)
    return out


def uncertainty_metrics(recon_dir: Path, use: np.ndarray, err_rel: np.ndarray, accurate: np.ndarray,
                        n_frames: int) -> dict | None:
    """Returns how honest the run's own uncertainty is (``summary.json`` ``frames``: each frame's source,
    ``sigma_rel`` and ``doubtful`` flag, and the run's ``verdict``), against the frames' errors.

    ``use``: the capture frames scored, ``err_rel`` their centre errors over the diameter, ``accurate`` whether
    each is accurate. Per source and over all: frames, share beyond 3 sigma (a frame without a sigma counts as
    beyond), median error over sigma. Confident frames: every scored frame of a run marked trusted, the frames
    not flagged doubtful in a run marked doubtful; ``confident_accurate_share`` is the share of them that are
    accurate (issue #63: at least 0.99), ``confident_wrong`` how many are not. None without summary.json's
    per-frame lists (or with another frame count).
    """
    try:
        summary = json.loads((recon_dir / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    fr = summary.get("frames") if isinstance(summary, dict) else None
    if not isinstance(fr, dict) or len(fr.get("sigma_rel") or []) != n_frames:
        return None
    src = [fr.get("source", [None] * n_frames)[i] or "none" for i in use]
    sig = np.array([np.nan if fr["sigma_rel"][i] is None else float(fr["sigma_rel"][i]) for i in use])
    flagged = np.array([bool((fr.get("doubtful") or [False] * n_frames)[i]) for i in use])
    verdict = (summary.get("verdict") or {}).get("status", "trusted")
    z = np.where(sig > 0, err_rel / np.where(sig > 0, sig, 1.0), np.inf)

    def block(m: np.ndarray) -> dict:
        return {"frames": int(m.sum()), "beyond_3sigma": float(np.mean(~(z[m] <= 3.0))) if m.any() else None,
                "z_median": float(np.median(z[m])) if m.any() else None,
                "sigma_median": float(np.nanmedian(sig[m])) if m.any() and np.isfinite(sig[m]).any() else None,
                "error_median": float(np.median(err_rel[m])) if m.any() else None}

    confident = ~flagged if verdict == "doubtful" else np.ones(len(use), bool)
    return {"verdict": verdict, "by_source": {s: block(np.array(src) == s) for s in sorted(set(src))},
            "all": block(np.ones(len(use), bool)), "flagged": int(flagged.sum()),
            "confident": int(confident.sum()), "confident_wrong": int(np.sum(confident & ~accurate)),
            "confident_accurate_share": float(np.mean(accurate[confident])) if confident.any() else None}


def _zero_baseline_metrics(out: dict, R_est: np.ndarray, R_gt: np.ndarray, c_est: np.ndarray) -> dict:
    """Returns the metrics of a capture whose true centres coincide (a spin cut from a panorama): rotations after
    the rotation-only alignment, and how far apart the estimated centres lie (they should not: no invented
    translation). Centre, corner and line metrics need a baseline and stay empty."""
    B = rotation_alignment(R_est, R_gt)
    rot = rotation_angle_deg(np.einsum("ij,njk->nik", B, R_est), R_gt)
    out["zero_baseline"] = True
    out["alignment"] = {"method": "rotation only (true centres coincide: zero baseline)", "frames": len(R_est),
                        "scale": float("nan"), "R": B, "t": np.zeros(3)}
    out["trajectory_diameter_m"] = 0.0
    out["rotation_error_deg"] = out["rotation_error_rotalign_deg"] = _stats(rot)
    out["estimated_centre_spread"] = float(pdist(c_est).max()) if len(c_est) >= 2 else 0.0
    out["accurate"] = int(np.sum(rot <= ACCURATE_ROTATION_DEG))
    return out


def _run_frames(recon_dir: Path) -> int | None:
    """Returns the frame count the run itself reports in summary.json (it may have taken every k-th frame)."""
    try:
        v = json.loads((recon_dir / "summary.json").read_text()).get("frames")
    except (OSError, ValueError, AttributeError):
        return None
    if isinstance(v, dict):  # summary.json's "frames": {"total": N, "registered": ...}
        v = v.get("total")
    return int(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def _click_metrics(capture: Capture, rec_cam: Camera, gt, use: np.ndarray, R_al: np.ndarray, c_al: np.ndarray,
                   noise_px: float, seed: int, min_views: int) -> dict:
    """Returns the clicked-corner reprojection metrics (paper §4), estimated poses already aligned.

    Reprojection errors are invariant to the similarity, so triangulating in the
    aligned frame only improves conditioning. Clicks are taken in the image the
    reconstruction's camera describes: the raw image (camera.json, with its
    distortion) when that camera has distortion, else the capture's undistorted
    working image; they are rescaled to the reconstruction camera's size.
    """
    res = {"points": 0, "clicks": 0, "noise_px": noise_px, "seed": seed, "min_views": min_views,
           "occlusion": None, "image": None, "mean": None, "median": None, "std": None, "max": None,
           "corner_error_m": None}
    if len(gt.lines) == 0:
        return res
    corners = np.unique(np.round(gt.lines.reshape(-1, 3), 5), axis=0)
    boxes = scene_boxes(gt.scene)
    vis, method = visible_corners(corners, gt.R_wc[use], gt.centers[use], capture.camera,
                                  depth_of=(lambda k: gt.depth(int(use[k]))) if gt.has_depth else None, boxes=boxes)
    res["occlusion"] = method
    keep = vis.sum(axis=0) >= min_views
    if not keep.any():
        return res
    corners, vis = corners[keep], vis[:, keep]
    fi, pi = np.nonzero(vis)  # fi indexes `use`
    Xc = np.einsum("kji,kj->ki", gt.R_wc[use[fi]], corners[pi] - gt.centers[use[fi]])
    xn_true = Xc[:, :2] / Xc[:, 2:]

    ref = _raw_camera(capture) if np.any(rec_cam.distortion) else capture.camera
    rng = np.random.default_rng(seed)
    click = _pixels(ref, xn_true) + rng.normal(0.0, noise_px, size=xn_true.shape)
    click_rec, scale = _rescale_pixels(click, ref, rec_cam)
    xn_rec = _normalised(rec_cam, click_rec)

    Xh = triangulate_dlt(R_al, c_al, pi, fi, xn_rec, len(corners))
    reproj = _pixels(rec_cam, _project_h(R_al[fi], c_al[fi], Xh[pi]))
    e = np.linalg.norm((reproj - click_rec) / scale, axis=1)  # in reference-image pixels
    e = np.where(np.isfinite(e), e, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:]
    cerr = np.linalg.norm(X - corners, axis=1)
    res.update({"points": int(len(corners)), "clicks": int(len(fi)), "image": f"{ref.width}x{ref.height}",
                **{k: v for k, v in _stats(e).items() if k != "rmse"},
                "corner_error_m": {"median": float(np.median(cerr)) if np.isfinite(cerr).any() else None,
                                   "mean": float(np.mean(cerr)) if np.all(np.isfinite(cerr)) else None}})
    return res


def _line_metrics(recon_dir: Path, gt, sim, dist_m: float, angle_deg: float, cover_frac: float,
                  min_gt_edge_m: float, step_m: float) -> dict | None:
    """Returns line metrics of lines.ply after the similarity ``sim`` = (s, R, t); None without lines.ply."""
    path = recon_dir / "lines.ply"
    if not path.is_file():
        return None
    E, labels, _ = read_lines_ply(path)
    E = E[np.all(np.isfinite(E), axis=1)]
    res = {"lines": int(len(E)), "aligned": sim is not None, "distance_m": None, f"within_{dist_m:g}m_share": None,
           "gt_edges": 0, "recovered": None, "recovered_share": None, "recovered_length_share": None,
           "criteria": f"within {dist_m:g} m and {angle_deg:g} deg over >= {cover_frac:.0%} of length; "
                       f"true edges >= {min_gt_edge_m:g} m"}
    if sim is None or len(E) == 0:
        return res
    s, A, t = sim
    E = np.concatenate([s * E[:, :3] @ A.T + t, s * E[:, 3:] @ A.T + t], axis=1)
    boxes = scene_boxes(gt.scene)
    polygon = (gt.scene or {}).get("room_polygon") if isinstance(gt.scene, dict) else None
    if boxes is not None or polygon is not None:
        pts, own = _sample_segments(E, step_m, max_per=200)
        if boxes is not None:
            d = distance_to_boxes(pts, boxes)
        else:  # a panorama's room (synth.pano_room): the extruded floor polygon
            from .synth.pano_room import distance_to_room

            d = distance_to_room(pts, np.asarray(polygon["corners_xy"], dtype=np.float64), float(polygon["floor_z"]),
                                 float(polygon["ceiling_z"]))
        per_line = np.bincount(own, weights=d, minlength=len(E)) / np.maximum(np.bincount(own, minlength=len(E)), 1)
        res["distance_m"] = {"median": float(np.median(per_line)), "mean": float(per_line.mean())}
        res[f"within_{dist_m:g}m_share"] = float(np.mean(per_line <= dist_m))
    G = gt.lines[np.linalg.norm(gt.lines[:, 3:] - gt.lines[:, :3], axis=1) >= min_gt_edge_m]
    res["gt_edges"] = int(len(G))
    if len(G):
        cov = edge_coverage(G, E, dist_m, angle_deg, step_m)
        rec = cov >= cover_frac
        Lg = np.linalg.norm(G[:, 3:] - G[:, :3], axis=1)
        res.update({"recovered": int(rec.sum()), "recovered_share": float(rec.mean()),
                    "recovered_length_share": float(np.sum(Lg * cov) / np.sum(Lg))})
    return res


def _f(v, fmt: str = ".4g") -> str:
    return "-" if v is None else format(v, fmt)


def format_metrics(m: dict) -> str:
    """Returns a readable table of :func:`evaluate_reconstruction`'s metrics (alignment and units stated)."""
    rows = [("frames registered", f"{m['registered']} / {m['frames']} ({m['registered_ratio']:.1%})"
             + (f"; the run took {m['run_frames']} frames" if m.get("run_frames") not in (None, m["frames"]) else ""))]
    if m.get("zero_baseline"):
        rr = m["rotation_error_rotalign_deg"]
        rows += [("zero baseline", "the true centres coincide: rotations only (no centre, corner or line metric)"),
                 ("frames accurate", f"{m.get('accurate', 0)} (rotation within {ACCURATE_ROTATION_DEG:g} deg)"),
                 ("rotation error (deg, rot-only)", f"median {_f(rr['median'])}  max {_f(rr['max'])}"),
                 ("estimated centres' spread", f"{_f(m['estimated_centre_spread'])} (model units; 0 = none invented)")]
        w = max(len(r[0]) for r in rows)
        return "\n".join(f"{k.ljust(w)}  {v}" for k, v in rows)
    if m.get("alignment"):
        rows.append(("frames accurate", f"{m.get('accurate', 0)} (centre within {ACCURATE_CENTER_REL:.0%} of the "
                                        f"diameter, rotation within {ACCURATE_ROTATION_DEG:g} deg, aligned by the orientations)"))
    al = m.get("alignment")
    if al:
        rows.append(("alignment", f"{al['method']}, {al['frames']} frames, scale {al['scale']:.4g}"))
    ce, cr, re_, rr = m["center_error_m"], m["center_error_rel"], m["rotation_error_deg"], m["rotation_error_rotalign_deg"]
    rows += [
        ("trajectory diameter (m)", _f(m.get("trajectory_diameter_m"))),
        ("centre error (m)", f"mean {_f(ce['mean'])}  median {_f(ce['median'])}  rmse {_f(ce['rmse'])}  max {_f(ce['max'])}"),
        ("centre error / diameter", f"mean {_f(cr['mean'], '.2%') if cr['mean'] is not None else '-'}  "
                                    f"max {_f(cr['max'], '.2%') if cr['max'] is not None else '-'}"),
        ("rotation error (deg, sim3 R)", f"median {_f(re_['median'])}  max {_f(re_['max'])}"),
        ("rotation error (deg, rot-only)", f"median {_f(rr['median'])}  max {_f(rr['max'])}"),
    ]
    rp = m.get("reprojection_px")
    if rp:
        rows.append(("clicked corners (paper §4)", f"{rp['points']} points, {rp['clicks']} clicks, noise "
                     f"{rp['noise_px']} px, >= {rp['min_views']} views, occlusion: {rp['occlusion']}"))
        rows.append((f"reprojection (px @ {rp['image']})", f"mean {_f(rp['mean'])}  median {_f(rp['median'])}  "
                     f"std {_f(rp['std'])}  max {_f(rp['max'])}"))
        if rp.get("corner_error_m"):
            rows.append(("corner 3D error (m, aligned)", f"median {_f(rp['corner_error_m']['median'])}"))
    un = m.get("uncertainty")
    if un:
        rows.append(("run's own verdict", f"{un['verdict']}; {un['confident']} confident frames, "
                     f"{_f(un['confident_accurate_share'], '.1%') if un['confident_accurate_share'] is not None else '-'}"
                     f" of them accurate ({un['confident_wrong']} wrong), {un['flagged']} flagged doubtful"))
        for src, b in un["by_source"].items():
            rows.append((f"  sigma honesty: {src}", f"{b['frames']} frames, {_f(b['beyond_3sigma'], '.1%')} beyond 3 "
                         f"sigma, error/sigma median {_f(b['z_median'], '.2f')}"))
    ln = m.get("lines")
    if ln is None:
        rows.append(("lines", "no lines.ply"))
    else:
        d = ln.get("distance_m")
        share = next((v for k, v in ln.items() if k.startswith("within_")), None)
        rows.append(("lines", f"{ln['lines']} segments"))
        rows.append(("line distance to surfaces (m)", "-" if d is None else
                     f"median {_f(d['median'])}  mean {_f(d['mean'])}  within: {_f(share, '.1%') if share is not None else '-'}"))
        rows.append(("true edges recovered", f"{_f(ln['recovered'], 'd') if ln['recovered'] is not None else '-'} / "
                     f"{ln['gt_edges']} ({_f(ln['recovered_share'], '.1%') if ln['recovered_share'] is not None else '-'}; "
                     f"by length {_f(ln['recovered_length_share'], '.1%') if ln['recovered_length_share'] is not None else '-'})"))
        rows.append(("  criteria", ln["criteria"]))
    w = max(len(r[0]) for r in rows)
    return "\n".join(f"{k.ljust(w)}  {v}" for k, v in rows)
