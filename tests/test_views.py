"""PNG views (paper §4): framing, colours and geometry checked against a hand-built box room."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from panosfm_graph.data import LineModel, Segments, Tracks
from panosfm_graph.views import (
    AXIS_BGR,
    CAMERA_BGR,
    IMAGE_SIZE,
    _Perspective,
    _prepare,
    floor_height,
    height_colors,
    height_top,
    manhattan_alignment,
    nice_step,
    render_height,
    render_quarter,
    render_topdown,
    render_views,
    track_colors,
)

ROOM = dict(x0=-2.0, x1=3.0, y0=-1.5, y1=2.5, z0=-1.5, z1=1.1)  # 5 m x 4 m x 2.6 m
DOOR_BGR = (0, 0, 255)
WALL_BGR = (190, 205, 215)


def line_model(ends: np.ndarray, valid: np.ndarray | None = None) -> LineModel:
    """Returns a LineModel (Taylor form) holding the axis-aligned segments ``ends`` (N, 6)."""
    d = ends[:, 3:] - ends[:, :3]
    axis = np.argmax(np.abs(d), axis=1).astype(np.int8)
    direction = np.eye(3)[axis]
    s_a = np.sum(ends[:, :3] * direction, axis=1)
    s_b = np.sum(ends[:, 3:] * direction, axis=1)
    taylor = ends[:, :3] - s_a[:, None] * direction
    extent = np.stack([np.minimum(s_a, s_b), np.maximum(s_a, s_b)], axis=1)
    return LineModel(taylor=taylor, direction=direction, axis=axis, extent=extent,
                     valid=np.ones(len(ends), bool) if valid is None else valid)


def box_room() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (ends (N, 6), colours (N, 3) BGR, door mask (N,)) of a box room with a door and a table."""
    x0, x1, y0, y1, z0, z1 = (ROOM[k] for k in ("x0", "x1", "y0", "y1", "z0", "z1"))
    e = []
    for z in (z0, z1):
        e += [[x0, y0, z, x1, y0, z], [x0, y1, z, x1, y1, z], [x0, y0, z, x0, y1, z], [x1, y0, z, x1, y1, z]]
    e += [[x, y, z0, x, y, z1] for x in (x0, x1) for y in (y0, y1)]
    n_room = len(e)
    e += [[x0 + 1, y1, z0, x0 + 1, y1, z0 + 2], [x0 + 1.9, y1, z0, x0 + 1.9, y1, z0 + 2],
          [x0 + 1, y1, z0 + 2, x0 + 1.9, y1, z0 + 2]]
    tz = z0 + 0.75
    e += [[-0.5, 1.0, tz, 0.7, 1.0, tz], [-0.5, 1.8, tz, 0.7, 1.8, tz], [-0.5, 1.0, tz, -0.5, 1.8, tz],
          [0.7, 1.0, tz, 0.7, 1.8, tz]]
    ends = np.array(e, dtype=np.float64)
    door = np.zeros(len(ends), bool)
    door[n_room:n_room + 3] = True
    colors = np.tile(np.array(WALL_BGR, np.uint8), (len(ends), 1))
    colors[door] = DOOR_BGR
    colors[n_room + 3:] = (30, 30, 160)
    return ends, colors, door


def spin_centers(n: int = 40, radius: float = 0.15) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([radius * np.cos(a), radius * np.sin(a), np.zeros(n)], axis=1)


def with_junk(ends: np.ndarray, colors: np.ndarray) -> tuple[LineModel, np.ndarray]:
    """Returns the room plus a far outlier, a NaN line and an invalid line."""
    junk = np.array([[100, 100, 0, 100, 100, 1], [np.nan, 0, 0, np.nan, 0, 1], [0, 0, 50, 1, 0, 50]])
    valid = np.r_[np.ones(len(ends), bool), True, True, False]
    cols = np.r_[colors, np.zeros((3, 3), np.uint8)]
    return line_model(np.r_[ends, junk], valid), cols


def color_mask(img: np.ndarray, bgr, tol: int = 40) -> np.ndarray:
    return np.all(np.abs(img.astype(int) - np.array(bgr)) <= tol, axis=2)


def test_render_views_writes_three_legible_pngs(tmp_path):
    ends, colors, _ = box_room()
    lines, cols = with_junk(ends, colors)
    centers = spin_centers(300)  # many centres on a small circle must not shrink the framing
    reg = np.ones(len(centers), bool)
    reg[::7] = False
    paths = render_views(tmp_path / "views", lines, cols, centers, reg, metric=True, title="box")
    assert set(paths) == {"quarter", "height", "topdown"}
    for name, p in paths.items():
        img = cv2.imread(str(p))
        assert img.shape == (IMAGE_SIZE[1], IMAGE_SIZE[0], 3), name
        # the model fills the picture: drawn pixels spread over most of it despite the outlier
        bg = img[5, -5].astype(int)
        drawn = np.any(np.abs(img.astype(int) - bg) > 30, axis=2)
        ys, xs = np.nonzero(drawn[60:-60])
        assert xs.max() - xs.min() > 0.6 * IMAGE_SIZE[0], name
        assert ys.max() - ys.min() > 0.5 * (IMAGE_SIZE[1] - 120), name


def test_quarter_view_draws_each_line_in_its_colour_where_it_projects():
    ends, colors, door = box_room()
    lines = line_model(ends)
    centers = spin_centers()
    reg = np.ones(len(centers), bool)
    img = render_quarter(lines, colors, centers, reg, metric=True)
    _, _, _, lo, hi = _prepare(lines, centers, reg)
    cam = _Perspective(lo, hi, IMAGE_SIZE)
    px, _, keep = cam.project_segments(ends[:, :3], ends[:, 3:])
    assert keep.all()
    red = color_mask(img, DOOR_BGR, 60)
    ys, xs = np.nonzero(red)
    assert len(xs) > 300  # the door frame is drawn in its colour
    # every red pixel lies within a few pixels of one of the projected door segments
    p = px[door]
    a, b = p[:, None, :2], p[:, None, 2:]
    q = np.stack([xs, ys], axis=1)[None].astype(float)
    t = np.clip(np.sum((q - a) * (b - a), axis=2) / np.sum((b - a) ** 2, axis=2), 0, 1)
    dist = np.linalg.norm(q - (a + t[..., None] * (b - a)), axis=2).min(axis=0)
    assert np.percentile(dist, 99) < 4.0
    # and the door's projected midpoints are red
    mid = np.round(0.5 * (p[:, :2] + p[:, 2:])).astype(int)
    assert all(red[m[1] - 2:m[1] + 3, m[0] - 2:m[0] + 3].any() for m in mid)


def test_height_view_colours_follow_height_above_floor():
    ends, _, _ = box_room()
    lines = line_model(ends)
    centers = spin_centers()
    reg = np.ones(len(centers), bool)
    z_floor = floor_height(lines)
    assert z_floor == pytest.approx(ROOM["z0"], abs=1e-9)
    img = render_height(lines, centers, reg, metric=True)
    _, _, _, lo, hi = _prepare(lines, centers, reg)
    cam = _Perspective(lo, hi, IMAGE_SIZE, right_margin_px=110)
    top = height_top(ends, z_floor)
    assert top == pytest.approx(ROOM["z1"] - ROOM["z0"])
    floor_col = height_colors(np.array([0.0]), top)[0].astype(int)
    ceil_col = height_colors(np.array([top]), top)[0].astype(int)
    # sample the midpoints of the 4 floor and 4 ceiling lines (rows 0-7 of box_room)
    px, _, _ = cam.project_segments(ends[:8, :3], ends[:8, 3:])
    mid = np.round(0.5 * (px[:, :2] + px[:, 2:])).astype(int)
    for k, m in enumerate(mid):
        patch = img[m[1] - 2:m[1] + 3, m[0] - 2:m[0] + 3].reshape(-1, 3).astype(int)
        want = floor_col if k < 4 else ceil_col
        assert np.min(np.abs(patch - want).sum(axis=1)) < 40, (k, patch, want)
    assert np.abs(floor_col - ceil_col).sum() > 200  # the two ends of the heat map differ clearly


def turned(lines: LineModel, points: np.ndarray, yaw_deg: float) -> tuple[LineModel, np.ndarray]:
    """Returns the line model and points turned by ``yaw_deg`` about the vertical (a room whose walls are not
    along the world's axes, as when the IMU's heading is arbitrary)."""
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (LineModel(taylor=lines.taylor @ R.T, direction=lines.direction @ R.T, axis=lines.axis,
                      extent=lines.extent, valid=lines.valid), points @ R.T)


@pytest.mark.parametrize("yaw_deg", [0.0, 30.0, -100.0])
def test_topdown_is_orthographic_with_cameras_and_scale(yaw_deg):
    """The room is drawn in its Manhattan frame: turned about the vertical, its walls still run along the
    picture's axes and the picture is the same."""
    ends, colors, _ = box_room()
    lines, _ = with_junk(ends, colors)
    centers = spin_centers(60, 0.3) + [0.5, 0.5, 0.0]
    lines, centers = turned(lines, centers, yaw_deg)
    reg = np.ones(len(centers), bool)
    img = render_topdown(lines, centers, reg, metric=True)
    body = img[70:-70]
    # x lines (red) span the room's length; y lines (blue) its width: ratio 5 : 4 in pixels
    # (span between the centres of the outermost lines of each kind; ends may be overdrawn)
    xs_red = np.nonzero(color_mask(body, AXIS_BGR[0], 30))[1]
    ys_red = np.nonzero(color_mask(body, AXIS_BGR[0], 30))[0]
    xs_blue = np.nonzero(color_mask(body, AXIS_BGR[1], 30))[1]
    len_px = xs_blue.max() - xs_blue.min()
    wid_px = ys_red.max() - ys_red.min()
    assert wid_px / len_px == pytest.approx(4.0 / 5.0, rel=0.02)
    assert len_px > 0.6 * IMAGE_SIZE[0]  # auto-framed to the room, not to the outlier
    assert xs_red.max() - xs_red.min() == pytest.approx(len_px, abs=8)
    # the camera circle: green pixels centred where (0.5, 0.5) maps, radius 0.3 m
    gy, gx = np.nonzero(color_mask(body, CAMERA_BGR, 30))
    s = len_px / 5.0  # pixels per metre
    cx_expect = xs_blue.min() + (0.5 - ROOM["x0"]) * s
    cy_expect = ys_red.max() - (0.5 - ROOM["y0"]) * s
    assert gx.mean() == pytest.approx(cx_expect, abs=3)
    assert gy.mean() == pytest.approx(cy_expect, abs=3)
    r = np.hypot(gx - cx_expect, gy - cy_expect)
    assert np.median(r) == pytest.approx(0.3 * s, abs=3)


def test_topdown_with_no_lines_and_arbitrary_scale(tmp_path):
    ends, colors, _ = box_room()
    lines = line_model(ends, valid=np.zeros(len(ends), bool))
    centers = np.full((10, 3), np.nan)
    paths = render_views(tmp_path, lines, colors, centers, np.zeros(10, bool), metric=False)
    for p in paths.values():
        assert cv2.imread(str(p)).shape == (IMAGE_SIZE[1], IMAGE_SIZE[0], 3)


def test_track_colors_average_segment_colours():
    segs = Segments(endpoints=np.zeros((4, 4), np.float32), frame=np.array([0, 0, 1, 1], np.int32),
                    frame_offsets=np.array([0, 2, 4]),
                    colors=np.array([[10, 20, 30], [200, 200, 200], [30, 40, 50], [0, 0, 0]], np.uint8))
    tracks = Tracks(track_of=np.array([0, -1, 0, -1], np.int32), axis=np.array([0, 1], np.int8))
    tc = track_colors(segs, tracks)
    np.testing.assert_array_equal(tc, [[20, 30, 40], [128, 128, 128]])


@pytest.mark.parametrize("span,expected", [(10.0, 2.0), (2.6, 1.0), (0.07, 0.02), (4.0, 1.0), (7.0, 2.0)])
def test_nice_step(span, expected):
    assert nice_step(span, 5) == pytest.approx(expected)


def test_views_are_aligned_to_the_manhattan_frame():
    """manhattan_alignment undoes a turn of the room about the vertical (x lines along the view's x), and a
    model without horizontal lines is left as it is."""
    ends, colors, _ = box_room()
    lines = line_model(ends)
    for yaw in (0.0, 25.0, 89.0, -135.0):
        lt, _ = turned(lines, np.zeros((1, 3)), yaw)
        R = manhattan_alignment(lt)
        d = lt.direction[lt.axis == 0] @ R.T
        np.testing.assert_allclose(np.abs(d[:, 0]), 1.0, atol=1e-12)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(R[2], [0, 0, 1])
    only_y = line_model(ends[np.abs(ends[:, 1] - ends[:, 4]) > 0.1])
    lt, _ = turned(only_y, np.zeros((1, 3)), 40.0)
    d = lt.direction[lt.axis == 1] @ manhattan_alignment(lt).T
    np.testing.assert_allclose(np.abs(d[:, 1]), 1.0, atol=1e-12)
    vertical = line_model(ends[np.abs(ends[:, 2] - ends[:, 5]) > 0.1])
    np.testing.assert_array_equal(manhattan_alignment(vertical), np.eye(3))
