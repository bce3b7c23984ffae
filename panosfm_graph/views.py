"""PNG images of the paper's three views of a line model (paper §4, Fig. 'results').

* ``quarter.png``: a perspective view from above one corner of the model,
  each line in its average image colour (paper: "quarter view");
* ``height.png``: the same view, lines coloured by height above the floor
  with a heat map and a colour bar (paper: "height-field view");
* ``topdown.png``: an orthographic view from the top with the recovered
  camera centres as green dots and the ratio of registered frames
  (paper: "top-down view").

All three are drawn in the Manhattan frame (turned about the vertical so that
walls run along the pictures' axes). Only OpenCV drawing; no viewer needed. Everything is auto-framed to a robust
extent of the model (percentiles), so a few wild lines cannot shrink the room
to a dot. Images are BGR, ``IMAGE_SIZE`` pixels.
"""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from .data import LineModel, Segments, Tracks

log = logging.getLogger(__name__)

IMAGE_SIZE = (1024, 768)  # width, height in pixels
QUARTER_ELEVATION_DEG = 35.0  # the quarter view looks down at this angle
ROBUST_PERCENT = 2.0  # percentile for the floor height; framing uses 5x this (see robust_box)
LIGHT_BG = (245, 245, 245)
DARK_BG = (40, 36, 32)
TEXT_DARK = (30, 30, 30)
TEXT_LIGHT = (235, 235, 235)
# Manhattan axis colours (BGR) for the top-down view; camera centres are green.
AXIS_BGR = np.array([[40, 40, 200], [190, 110, 30], [90, 90, 90]], dtype=np.uint8)
UNLABELLED_BGR = (150, 150, 150)
CAMERA_BGR = (40, 190, 40)
_FONT = cv2.FONT_HERSHEY_SIMPLEX


# ----------------------------------------------------------------------------- helpers


def track_colors(segments: Segments, tracks: Tracks) -> np.ndarray:
    """Returns (T, 3) uint8 BGR: each track's average image colour over its segments (paper §4 quarter view).

    Tracks without segments get mid grey.
    """
    seg = np.flatnonzero(tracks.track_of >= 0)
    t = tracks.track_of[seg]
    sums = np.zeros((tracks.n, 3), dtype=np.float64)
    np.add.at(sums, t, segments.colors[seg].astype(np.float64))
    counts = np.bincount(t, minlength=tracks.n).astype(np.float64)
    out = np.full((tracks.n, 3), 128.0)
    has = counts > 0
    out[has] = sums[has] / counts[has, None]
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def valid_line_mask(lines: LineModel) -> np.ndarray:
    """Returns (T,) bool: lines that are ``valid`` and have finite endpoints."""
    ends = lines.endpoints
    return np.asarray(lines.valid, dtype=bool) & np.all(np.isfinite(ends), axis=1)


def robust_box(points: np.ndarray, percent: float = ROBUST_PERCENT * 5) -> tuple[np.ndarray, np.ndarray]:
    """Returns (lo, hi): the bounding box of the finite rows of ``points`` (N, D) that are not outliers.

    A row is an outlier when a coordinate lies more than one inter-percentile
    span (``percent`` .. ``100 - percent``) beyond those percentiles: a few wild
    lines cannot shrink the room to a dot, while the room itself is kept whole.
    Degenerate extents are widened to at least 1e-3 of the largest extent (or 1).
    """
    pts = np.asarray(points, dtype=np.float64)
    d = pts.shape[1] if pts.ndim == 2 else 3
    pts = pts.reshape(-1, d)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) == 0:
        return -np.ones(d), np.ones(d)
    q_lo = np.percentile(pts, percent, axis=0)
    q_hi = np.percentile(pts, 100.0 - percent, axis=0)
    fence = np.maximum(q_hi - q_lo, 0.5 * float(np.max(q_hi - q_lo)))
    inlier = np.all((pts >= q_lo - fence) & (pts <= q_hi + fence), axis=1)
    pts = pts[inlier] if inlier.any() else pts
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    span = hi - lo
    min_span = max(1e-3 * float(span.max()), 1e-6) if span.max() > 0 else 1.0
    grow = np.maximum(min_span - span, 0.0) / 2
    return lo - grow, hi + grow


def floor_height(lines: LineModel) -> float:
    """Returns the floor's z: a low percentile of the heights of the valid lines' endpoints.

    The floor is the lowest horizontal surface; its lines are among the lowest
    endpoints. 0.0 when there are no valid lines.
    """
    ends = lines.endpoints[valid_line_mask(lines)]
    if len(ends) == 0:
        return 0.0
    z = np.concatenate([ends[:, 2], ends[:, 5]])
    return float(np.percentile(z, ROBUST_PERCENT))


def height_top(ends: np.ndarray, z_floor: float) -> float:
    """Returns the height above the floor mapped to the hot end of the heat map (98th percentile of endpoint z)."""
    if len(ends) == 0:
        return 1.0
    top = float(np.percentile(np.concatenate([ends[:, 2], ends[:, 5]]), 100.0 - ROBUST_PERCENT) - z_floor)
    return top if top > 1e-9 else 1.0


def is_horizontal(ends: np.ndarray) -> np.ndarray:
    """Returns (N,) bool: segments (N, 6) closer to horizontal than to vertical (drawn as lines from the top)."""
    return np.abs(ends[:, 2] - ends[:, 5]) < np.hypot(ends[:, 0] - ends[:, 3], ends[:, 1] - ends[:, 4]) + 1e-12


def nice_step(span: float, target_count: float = 5.0) -> float:
    """Returns a 'nice' step (1, 2 or 5 times a power of ten) dividing ``span`` into about ``target_count`` parts."""
    if not np.isfinite(span) or span <= 0:
        return 1.0
    raw = span / target_count
    p = 10.0 ** np.floor(np.log10(raw))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * p >= raw:
            return float(m * p)
    return float(10.0 * p)


def _fmt(value: float, step: float) -> str:
    digits = max(0, -int(np.floor(np.log10(step)))) if step > 0 else 0
    return f"{value:.{digits}f}"


def _put_text(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.55,
              color=TEXT_DARK, thickness: int = 1) -> None:
    cv2.putText(img, text, (int(org[0]), int(org[1])), _FONT, scale, color, thickness, cv2.LINE_AA)


def _header(img: np.ndarray, title: str, view_name: str, color=TEXT_DARK) -> None:
    text = f"{title} - {view_name}" if title else view_name
    _put_text(img, text, (12, 26), 0.7, color, 2 if color == TEXT_DARK else 1)


# ----------------------------------------------------------------------------- perspective


class _Perspective:
    """A pinhole camera above a corner of ``box`` looking down at the model (the quarter view)."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, size: tuple[int, int],
                 elevation_deg: float = QUARTER_ELEVATION_DEG, top_margin_px: int = 44,
                 right_margin_px: int = 0):
        w, h = size
        center = (lo + hi) / 2
        diag = float(np.linalg.norm(hi - lo))
        corner = np.array([lo[0], lo[1]]) - center[:2]  # the (min x, min y) corner
        corner = corner / max(np.linalg.norm(corner), 1e-12)
        # rotate 10 degrees off the diagonal so walls are not seen edge-on symmetrically
        a = np.radians(10.0)
        corner = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ corner
        el = np.radians(elevation_deg)
        self.dist = 1.6 * max(diag, 1e-6)
        eye = center + self.dist * np.array([np.cos(el) * corner[0], np.cos(el) * corner[1], np.sin(el)])
        fwd = (center - eye) / np.linalg.norm(center - eye)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        self.R_wc = np.stack([right, down, fwd], axis=1)  # columns: camera axes in the world
        self.eye = eye
        self.near = 0.05 * self.dist
        # fit the 8 corners of the box into the image
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        uvn = self._normalised(corners)
        umin, vmin = uvn.min(axis=0)
        umax, vmax = uvn.max(axis=0)
        margin = 24
        avail_w = w - 2 * margin - right_margin_px
        avail_h = h - 2 * margin - top_margin_px
        self.f = min(avail_w / max(umax - umin, 1e-9), avail_h / max(vmax - vmin, 1e-9))
        self.cx = margin + avail_w / 2 - self.f * (umin + umax) / 2
        self.cy = top_margin_px + margin + avail_h / 2 - self.f * (vmin + vmax) / 2

    def camera_coords(self, X: np.ndarray) -> np.ndarray:
        return (X - self.eye) @ self.R_wc

    def _normalised(self, X: np.ndarray) -> np.ndarray:
        Xc = self.camera_coords(X)
        return Xc[:, :2] / np.maximum(Xc[:, 2:], 1e-9)

    def project_segments(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Returns (pixels (N, 4), depth (N,), keep (N,) bool) after clipping to the near plane."""
        ca, cb = self.camera_coords(a), self.camera_coords(b)
        za, zb = ca[:, 2], cb[:, 2]
        keep = (za > self.near) | (zb > self.near)
        # move the endpoint behind the near plane onto it
        t = np.clip((self.near - za) / np.where(np.abs(zb - za) > 1e-12, zb - za, 1e-12), 0.0, 1.0)
        ca = np.where((za < self.near)[:, None], ca + t[:, None] * (cb - ca), ca)
        t = np.clip((self.near - zb) / np.where(np.abs(za - zb) > 1e-12, za - zb, 1e-12), 0.0, 1.0)
        cb = np.where((zb < self.near)[:, None], cb + t[:, None] * (ca - cb), cb)
        pa = ca[:, :2] / np.maximum(ca[:, 2:], 1e-9) * self.f + [self.cx, self.cy]
        pb = cb[:, :2] / np.maximum(cb[:, 2:], 1e-9) * self.f + [self.cx, self.cy]
        px = np.clip(np.concatenate([pa, pb], axis=1), -30000, 30000)
        depth = 0.5 * (ca[:, 2] + cb[:, 2])
        return px, depth, keep


def _model_box(ends: np.ndarray, centers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns (lo, hi): the robust box of the line endpoints joined with that of the camera centres.

    Each set is trimmed on its own: hundreds of camera centres on a small
    circle must not make the room's lines look like outliers.
    """
    boxes = []
    if len(ends):
        boxes.append(robust_box(np.concatenate([ends[:, :3], ends[:, 3:]], axis=0)))
    if len(centers):
        boxes.append(robust_box(centers))
    if not boxes:
        return -np.ones(3), np.ones(3)
    return np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)


def _inlier_lines(ends: np.ndarray, lo: np.ndarray, hi: np.ndarray, slack: float = 0.5) -> np.ndarray:
    """Returns (N,) bool: lines with both endpoints inside the box grown by ``slack`` times its size."""
    pad = slack * (hi - lo)
    inside = lambda P: np.all((P >= lo - pad) & (P <= hi + pad), axis=1)  # noqa: E731
    return inside(ends[:, :3]) & inside(ends[:, 3:])


def _draw_segments(img: np.ndarray, px: np.ndarray, depth: np.ndarray, colors: np.ndarray,
                   ref_depth: float, outline: tuple[int, int, int] | None, max_thick: int = 4) -> None:
    """Draws segments far to near (painter's order), thicker when nearer."""
    order = np.argsort(-depth, kind="stable")
    thick = np.clip(np.round(max_thick * (ref_depth / np.maximum(depth, 1e-9)) ** 1.5 * 0.5), 1, max_thick).astype(int)
    p = np.round(px).astype(np.int32)
    cols = colors.astype(int)
    for i in order:  # one cv2.line per line (not per pixel): OpenCV has no batched per-colour polyline
        a, b = (p[i, 0], p[i, 1]), (p[i, 2], p[i, 3])
        if outline is not None:
            cv2.line(img, a, b, outline, int(thick[i]) + 2, cv2.LINE_AA)
        cv2.line(img, a, b, tuple(int(c) for c in cols[i]), int(thick[i]), cv2.LINE_AA)


def _floor_grid(lo: np.ndarray, hi: np.ndarray, z: float, step: float) -> tuple[np.ndarray, np.ndarray]:
    xs = np.arange(np.floor(lo[0] / step), np.ceil(hi[0] / step) + 1) * step
    ys = np.arange(np.floor(lo[1] / step), np.ceil(hi[1] / step) + 1) * step
    a = np.concatenate([np.stack([xs, np.full_like(xs, ys[0]), np.full_like(xs, z)], 1),
                        np.stack([np.full_like(ys, xs[0]), ys, np.full_like(ys, z)], 1)])
    b = np.concatenate([np.stack([xs, np.full_like(xs, ys[-1]), np.full_like(xs, z)], 1),
                        np.stack([np.full_like(ys, xs[-1]), ys, np.full_like(ys, z)], 1)])
    return a, b


def subdivide(ends: np.ndarray, pieces: int) -> np.ndarray:
    """Returns (N * pieces, 6) sub-segments of (N, 6) segments, in order along each segment."""
    t0 = np.arange(pieces) / pieces
    t1 = (np.arange(pieces) + 1) / pieces
    a, b = ends[:, None, :3], ends[:, None, 3:]
    p0 = a + t0[None, :, None] * (b - a)
    p1 = a + t1[None, :, None] * (b - a)
    return np.concatenate([p0, p1], axis=2).reshape(-1, 6)


def height_colors(z_above_floor: np.ndarray, top: float) -> np.ndarray:
    """Returns (N, 3) uint8 BGR heat-map colours (OpenCV TURBO) for heights in [0, top]."""
    v = np.clip(np.asarray(z_above_floor, dtype=np.float64) / max(top, 1e-9), 0.0, 1.0)
    v = np.where(np.isfinite(v), v, 0.0)
    # start the ramp at 30/255: TURBO's darkest purple would vanish on the dark background
    table = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(256, 3)
    return table[np.round(30 + v * 225).astype(np.int64).reshape(-1)]


# ----------------------------------------------------------------------------- the three views


def manhattan_alignment(lines: LineModel) -> np.ndarray:
    """Returns the (3, 3) turn about the vertical that lays the Manhattan frame's x axis along the view's x.

    The views are drawn in the Manhattan frame (paper §3.1), so walls run
    horizontally and vertically in the pictures. The x direction is that of the
    lines labelled x (their ``direction`` is the Manhattan direction, paper
    §3.4), else that of the y lines turned back 90 degrees; the identity when
    neither is horizontal. The turn is taken in (-90, 90] degrees.
    """
    valid = np.asarray(lines.valid, dtype=bool) & np.all(np.isfinite(lines.direction), axis=1)
    axis = np.asarray(lines.axis)
    for k, offset in ((0, 0.0), (1, -np.pi / 2)):
        d = np.asarray(lines.direction, dtype=np.float64)[valid & (axis == k)]
        if len(d) and np.hypot(d[0, 0], d[0, 1]) > 0.5:
            yaw = np.arctan2(d[0, 1], d[0, 0]) + offset
            yaw = (yaw + np.pi / 2) % np.pi - np.pi / 2  # a line has no sign: (-90, 90] degrees
            c, s = np.cos(yaw), np.sin(yaw)
            return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.eye(3)


def _prepare(lines: LineModel, centers: np.ndarray, registered: np.ndarray):
    """Returns (ends, their line indices, camera centres, lo, hi) in the Manhattan-aligned view frame."""
    valid = valid_line_mask(lines)
    R = manhattan_alignment(lines)
    ends = (lines.endpoints[valid].reshape(-1, 3) @ R.T).reshape(-1, 6)
    idx = np.flatnonzero(valid)
    cams = np.asarray(centers, dtype=np.float64)[np.asarray(registered, dtype=bool)]
    cams = cams[np.all(np.isfinite(cams), axis=1)] @ R.T
    lo, hi = _model_box(ends, cams)
    keep = _inlier_lines(ends, lo, hi) if len(ends) else np.zeros(0, bool)
    return ends[keep], idx[keep], cams, lo, hi


def render_quarter(lines: LineModel, line_colors: np.ndarray, centers: np.ndarray, registered: np.ndarray,
                   metric: bool, title: str = "", size: tuple[int, int] = IMAGE_SIZE) -> np.ndarray:
    """Returns the quarter view (H, W, 3) BGR: lines in their average image colour, seen from above a corner.

    Paper §4 (results figure); depth-sorted, nearer lines thicker, a floor grid for scale.
    """
    ends, idx, cams, lo, hi = _prepare(lines, centers, registered)
    img = np.full((size[1], size[0], 3), LIGHT_BG, dtype=np.uint8)
    cam = _Perspective(lo, hi, size)
    z_floor = floor_height(lines)
    step = nice_step(float(max(hi[0] - lo[0], hi[1] - lo[1])), 8)
    ga, gb = _floor_grid(lo, hi, z_floor, step)
    gpx, gdepth, gkeep = cam.project_segments(ga, gb)
    _draw_segments(img, gpx[gkeep], gdepth[gkeep], np.full((int(gkeep.sum()), 3), 222), cam.dist, None, 1)
    if len(ends):
        px, depth, keep = cam.project_segments(ends[:, :3], ends[:, 3:])
        cols = np.asarray(line_colors)[idx] if line_colors is not None else np.full((len(idx), 3), 100)
        _draw_segments(img, px[keep], depth[keep], cols[keep], cam.dist, (70, 70, 70))
    _header(img, title, "quarter view (lines in average image colour)")
    unit = "m" if metric else "units"
    _put_text(img, f"{len(ends)} lines; floor grid {_fmt(step, step)} {unit}", (12, size[1] - 14), 0.5)
    if len(ends) == 0:
        _put_text(img, "no valid lines", (size[0] // 2 - 80, size[1] // 2), 0.9)
    return img


def render_height(lines: LineModel, centers: np.ndarray, registered: np.ndarray, metric: bool,
                  title: str = "", size: tuple[int, int] = IMAGE_SIZE, floor_z: float | None = None,
                  pieces: int = 12) -> np.ndarray:
    """Returns the height-field view (H, W, 3) BGR: lines coloured by height above the floor (paper §4)."""
    ends, _, cams, lo, hi = _prepare(lines, centers, registered)
    img = np.full((size[1], size[0], 3), DARK_BG, dtype=np.uint8)
    bar_w = 110
    cam = _Perspective(lo, hi, size, right_margin_px=bar_w)
    z0 = floor_height(lines) if floor_z is None else float(floor_z)
    top = height_top(ends, z0)
    if len(ends):
        sub = subdivide(ends, pieces)
        px, depth, keep = cam.project_segments(sub[:, :3], sub[:, 3:])
        cols = height_colors(0.5 * (sub[:, 2] + sub[:, 5]) - z0, top)
        _draw_segments(img, px[keep], depth[keep], cols[keep], cam.dist, None)
    # colour bar with height values
    x0, x1 = size[0] - bar_w + 20, size[0] - bar_w + 44
    y_top, y_bot = 80, size[1] - 60
    ramp = np.linspace(1.0, 0.0, y_bot - y_top)
    strip = height_colors(ramp * top, top).reshape(-1, 1, 3)
    img[y_top:y_bot, x0:x1] = np.repeat(strip, x1 - x0, axis=1)
    cv2.rectangle(img, (x0, y_top), (x1 - 1, y_bot - 1), TEXT_LIGHT, 1)
    step = nice_step(top, 5)
    for v in np.arange(0.0, top + 1e-9, step):
        y = int(round(y_bot - 1 - v / top * (y_bot - y_top - 1)))
        cv2.line(img, (x1, y), (x1 + 5, y), TEXT_LIGHT, 1)
        _put_text(img, _fmt(v, step), (x1 + 8, y + 5), 0.45, TEXT_LIGHT)
    unit = "m" if metric else "units"
    _put_text(img, f"height ({unit})", (x0 - 12, y_top - 14), 0.45, TEXT_LIGHT)
    _header(img, title, "height above the floor", TEXT_LIGHT)
    if len(ends) == 0:
        _put_text(img, "no valid lines", (size[0] // 2 - 80, size[1] // 2), 0.9, TEXT_LIGHT)
    return img


def render_topdown(lines: LineModel, centers: np.ndarray, registered: np.ndarray, metric: bool,
                   title: str = "", size: tuple[int, int] = IMAGE_SIZE) -> np.ndarray:
    """Returns the top-down orthographic view (H, W, 3) BGR with camera centres as green dots (paper §4).

    Horizontal lines are drawn by Manhattan label, vertical lines as dots;
    a scale bar (metres when ``metric``) and the registered-frame ratio are written on it.
    """
    ends, idx, cams, lo, hi = _prepare(lines, centers, registered)
    w, h = size
    img = np.full((h, w, 3), LIGHT_BG, dtype=np.uint8)
    top_m, bot_m, side_m = 70, 70, 30
    span = np.maximum(hi[:2] - lo[:2], 1e-9)
    s = min((w - 2 * side_m) / span[0], (h - top_m - bot_m) / span[1])
    mid = (lo[:2] + hi[:2]) / 2

    def to_px(P: np.ndarray) -> np.ndarray:
        u = w / 2 + (P[:, 0] - mid[0]) * s
        v = top_m + (h - top_m - bot_m) / 2 - (P[:, 1] - mid[1]) * s
        return np.clip(np.stack([u, v], axis=1), -30000, 30000)

    n_reg = int(np.sum(np.asarray(registered, dtype=bool)))
    n_all = int(len(registered))
    if len(ends):
        axis = np.asarray(lines.axis)[idx]
        pa, pb = np.round(to_px(ends[:, :3])).astype(np.int32), np.round(to_px(ends[:, 3:])).astype(np.int32)
        horiz = is_horizontal(ends)
        order = np.argsort(0.5 * (ends[:, 2] + ends[:, 5]), kind="stable")  # low first, high on top
        for i in order:
            col = tuple(int(c) for c in AXIS_BGR[axis[i]]) if 0 <= axis[i] <= 2 else UNLABELLED_BGR
            if horiz[i]:
                cv2.line(img, (int(pa[i, 0]), int(pa[i, 1])), (int(pb[i, 0]), int(pb[i, 1])), col, 2, cv2.LINE_AA)
            else:
                c = (pa[i] + pb[i]) // 2
                cv2.rectangle(img, (int(c[0]) - 3, int(c[1]) - 3), (int(c[0]) + 3, int(c[1]) + 3), col, -1)
    if len(cams):
        pc = np.round(to_px(cams)).astype(np.int32)
        for p in pc:  # outlines first, then fills, so dense trajectories stay green
            cv2.circle(img, (int(p[0]), int(p[1])), 4, (20, 90, 20), -1, cv2.LINE_AA)
        for p in pc:
            cv2.circle(img, (int(p[0]), int(p[1])), 3, CAMERA_BGR, -1, cv2.LINE_AA)
    _header(img, title, "top-down view")
    pct = 100.0 * n_reg / n_all if n_all else 0.0
    _put_text(img, f"registered {n_reg}/{n_all} ({pct:.1f} %)", (12, 54), 0.6, TEXT_DARK, 2)
    # scale bar: a nice length near a fifth of the width
    bar = nice_step((w / s) / 5.0, 1.0)
    bar_px = int(round(bar * s))
    y = h - 28
    cv2.line(img, (20, y), (20 + bar_px, y), TEXT_DARK, 3)
    for x in (20, 20 + bar_px):
        cv2.line(img, (x, y - 7), (x, y + 7), TEXT_DARK, 2)
    label = f"{_fmt(bar, bar)} m" if metric else f"{_fmt(bar, bar)} units (arbitrary scale)"
    _put_text(img, label, (30 + bar_px, y + 6), 0.55)
    # legend
    lx = w - 300
    items = [("x lines", tuple(int(c) for c in AXIS_BGR[0])), ("y lines", tuple(int(c) for c in AXIS_BGR[1])),
             ("vertical lines", tuple(int(c) for c in AXIS_BGR[2])), ("camera centres", CAMERA_BGR)]
    for k, (name, col) in enumerate(items):
        yy = h - 56 + 22 * (k % 2)
        xx = lx + 150 * (k // 2)
        cv2.rectangle(img, (xx, yy - 8), (xx + 14, yy + 4), col, -1)
        _put_text(img, name, (xx + 20, yy + 4), 0.45)
    if len(ends) == 0:
        _put_text(img, "no valid lines", (w // 2 - 80, h // 2), 0.9)
    return img


def render_views(out_dir: str | Path, lines: LineModel, line_colors: np.ndarray | None, centers: np.ndarray,
                 registered: np.ndarray, metric: bool, title: str = "",
                 floor_z: float | None = None) -> dict[str, Path]:
    """Returns {"quarter", "height", "topdown"} -> PNG path after writing the paper's three views (paper §4).

    ``line_colors`` (T, 3) uint8 BGR is each line's average image colour
    (:func:`track_colors`); ``centers`` (F, 3) and ``registered`` (F,) are the
    camera centres and which of them were placed; ``metric`` labels the scale
    bar in metres. ``floor_z`` (the floor's world z) defaults to a low
    percentile of the line endpoints' heights.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    images = {
        "quarter": render_quarter(lines, line_colors, centers, registered, metric, title),
        "height": render_height(lines, centers, registered, metric, title, floor_z=floor_z),
        "topdown": render_topdown(lines, centers, registered, metric, title),
    }
    paths = {}
    for name, img in images.items():
        p = out / f"{name}.png"
        if not cv2.imwrite(str(p), img):
            raise OSError(f"{p}: could not write PNG")
        paths[name] = p
    log.info("wrote %s", ", ".join(str(p) for p in paths.values()))
    return paths
