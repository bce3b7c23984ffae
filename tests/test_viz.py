"""rerun recording: written with hand-built stage outputs, read back with ``rerun.chunk.RrdReader``."""
from __future__ import annotations

from collections import defaultdict
from types import SimpleNamespace

import numpy as np
import pytest

rr = pytest.importorskip("rerun")
import rerun.chunk  # noqa: E402

from panosfm_graph.data import (  # noqa: E402
    FLOOR,
    JUNCTION,
    Camera,
    ManhattanFrame,
    Preprocessed,
    Relations,
    Segments,
    Solution,
    Tracks,
)
from panosfm_graph.viz import AXIS_RGB, ViewerError, log_recording, view_recording  # noqa: E402
from test_views import ROOM, box_room, line_model  # noqa: E402

W, H, FOCAL = 320, 240, 120.0


def spin(F: int = 8, n_noise: int = 2, seed: int = 0):
    """Returns (capture, pre, tracks, relations, solution) of a camera turning in the box room.

    Segments are the projections of the room's lines (near-plane clipped); each
    line is one track; ``n_noise`` unlabelled untracked segments per frame;
    junctions between lines sharing an endpoint, floor relations for floor lines.
    Frame F // 2 is not registered.
    """
    rng = np.random.default_rng(seed)
    ends, colors, _ = box_room()
    lines = line_model(ends)
    cam = Camera("PINHOLE", W, H, np.array([FOCAL, FOCAL, W / 2, H / 2]))
    yaw = 2 * np.pi * np.arange(F) / F
    R_wc = np.stack([np.stack([np.sin(yaw), -np.cos(yaw), 0 * yaw], 1),
                     np.tile([0.0, 0.0, -1.0], (F, 1)),
                     np.stack([np.cos(yaw), np.sin(yaw), 0 * yaw], 1)], axis=2)
    centers = 0.1 * np.stack([np.cos(yaw), np.sin(yaw), 0 * yaw], 1)
    E, fr, col, lab, tr = [], [], [], [], []
    near = 0.3
    for f in range(F):
        a = (ends[:, :3] - centers[f]) @ R_wc[f]
        b = (ends[:, 3:] - centers[f]) @ R_wc[f]
        ok = (a[:, 2] > near) | (b[:, 2] > near)
        ta = np.clip((near - a[:, 2]) / np.where(b[:, 2] != a[:, 2], b[:, 2] - a[:, 2], 1), 0, 1)[:, None]
        tb = np.clip((near - b[:, 2]) / np.where(a[:, 2] != b[:, 2], a[:, 2] - b[:, 2], 1), 0, 1)[:, None]
        a, b = np.where(a[:, 2:] < near, a + ta * (b - a), a), np.where(b[:, 2:] < near, b + tb * (a - b), b)
        pa = a[:, :2] / a[:, 2:] * FOCAL + [W / 2, H / 2]
        pb = b[:, :2] / b[:, 2:] * FOCAL + [W / 2, H / 2]
        mid = (pa + pb) / 2
        ok &= (mid[:, 0] > 0) & (mid[:, 0] < W) & (mid[:, 1] > 0) & (mid[:, 1] < H)
        idx = np.flatnonzero(ok)
        E.append(np.concatenate([pa[idx], pb[idx]], 1))
        E.append(rng.uniform([0, 0, 0, 0], [W, H, W, H], (n_noise, 4)))
        fr.append(np.full(len(idx) + n_noise, f))
        col += [colors[idx], np.full((n_noise, 3), 128, np.uint8)]
        lab += [lines.axis[idx], np.full(n_noise, -1)]
        tr += [idx, np.full(n_noise, -1)]
    frame = np.concatenate(fr).astype(np.int32)
    segs = Segments(endpoints=np.concatenate(E).astype(np.float32), frame=frame,
                    frame_offsets=np.r_[0, np.cumsum(np.bincount(frame, minlength=F))].astype(np.int64),
                    colors=np.concatenate(col).astype(np.uint8))
    pre = Preprocessed(segments=segs, manhattan=ManhattanFrame(np.eye(3)),
                       labels=np.concatenate(lab).astype(np.int8), R_wc=R_wc, R_wc_imu=R_wc)
    tracks = Tracks(track_of=np.concatenate(tr).astype(np.int32), axis=lines.axis.copy())
    P = np.r_[ends[:, :3], ends[:, 3:]]
    owner = np.r_[np.arange(len(ends)), np.arange(len(ends))]
    close = np.linalg.norm(P[:, None] - P[None], axis=2) < 1e-9
    i, j = np.nonzero(close & (owner[:, None] < owner[None, :]))
    pairs = np.unique(np.stack([owner[i], owner[j]], 1), axis=0)
    floor = np.flatnonzero((ends[:, 2] == ROOM["z0"]) & (ends[:, 5] == ROOM["z0"]))
    kind = np.r_[np.full(len(pairs), JUNCTION), np.full(len(floor), FLOOR)].astype(np.int8)
    rel = Relations(kind=kind, track_a=np.r_[pairs[:, 0], floor].astype(np.int32),
                    track_b=np.r_[pairs[:, 1], -np.ones(len(floor))].astype(np.int32),
                    normal_axis=np.zeros(len(kind), np.int8), support=np.ones(len(kind), np.int32))
    reg = np.ones(F, bool)
    reg[F // 2] = False
    c = centers.copy()
    c[~reg] = np.nan
    sol = Solution(R_wc=R_wc, centers=c, registered=reg, lines=lines, camera=cam, metric=True, residuals={})
    images = rng.integers(0, 255, (F, H, W, 3), dtype=np.uint8)
    capture = SimpleNamespace(camera=cam, n_frames=F, frame=lambda k: images[k])
    return capture, pre, tracks, rel, sol


def read_back(path) -> tuple[dict, dict]:
    """Returns ({entity: rows}, {entity: [record batches]}) of the temporal + static data in an RRD."""
    rows: dict[str, int] = defaultdict(int)
    batches: dict[str, list] = defaultdict(list)
    for ch in rerun.chunk.RrdReader(path).store().stream().to_chunks():
        rows[ch.entity_path] += ch.num_rows
        batches[ch.entity_path].append(ch.to_record_batch())
    return rows, batches


def column(batches: list, name: str) -> list:
    """Returns the rows of one component column, in frame order when the entity has a frame timeline."""
    out = []
    for rb in batches:
        vals = rb.column(name).to_pylist()
        keys = rb.column("frame").to_pylist() if "frame" in rb.schema.names else range(len(vals))
        out += list(zip(keys, vals))
    return [v for _, v in sorted(out, key=lambda kv: kv[0])]


def test_recording_entities_rows_and_final_views(tmp_path):
    F = 8
    capture, pre, tracks, rel, sol = spin(F)
    colors = np.tile(np.array([10, 20, 250], np.uint8), (tracks.n, 1))
    status = ["registered"] * F
    status[F // 2] = "no tracked Manhattan line"
    path = log_recording(tmp_path / "rec.rrd", capture, pre, tracks, rel, sol, batches=[sol, sol, sol],
                         image_width=160, line_colors=colors, frame_status=status)
    rows, data = read_back(path)
    # why a frame has no pose, on the frame timeline
    texts = [t[0] if isinstance(t, list) else t for t in column(data["/status"], "TextLog:text")]
    assert len(texts) == F and texts[F // 2] == f"frame {F // 2}: not registered: no tracked Manhattan line"
    assert texts[0] == "frame 0: registered"
    for ent in ("/world/camera", "/world/camera/image/segments", "/world/camera/image/relations",
                "/world/camera/image/floor", "/world/cameras"):
        assert rows[ent] == F, ent
    assert rows["/world/camera/image"] == F + 1  # F JPEGs + the static Pinhole
    assert rows["/batch/lines"] == 3 and rows["/batch/cameras"] == 3
    # segments per frame: as many strips as the frame has segments, in pixels scaled by 160 / W
    strips = column(data["/world/camera/image/segments"], "LineStrips2D:strips")
    assert [len(s) for s in strips] == list(np.diff(pre.segments.frame_offsets))
    np.testing.assert_allclose(np.array(strips[0][0]).ravel(), pre.segments.endpoints[0] * 160 / W, atol=1e-3)
    # the growing model: monotone, ends with every line whose track was seen
    seen = np.unique(tracks.track_of[tracks.track_of >= 0])
    counts = [len(s) for s in column(data["/world/lines"], "LineStrips3D:strips")]
    assert counts == sorted(counts) and counts[-1] == len(seen)
    # camera centres so far: registered frames only
    cams = [len(p) for p in column(data["/world/cameras"], "Points3D:positions")]
    assert cams == list(np.cumsum(sol.registered))
    # final views: every valid line, quarter view in the given colours (BGR -> RGB)
    q = column(data["/final/quarter/lines"], "LineStrips3D:strips")[0]
    assert len(q) == int(sol.lines.valid.sum())
    np.testing.assert_allclose(np.array(q[0]).ravel(), sol.lines.endpoints[0], atol=1e-5)
    rgba = column(data["/final/quarter/lines"], "LineStrips3D:colors")[0]
    assert set(rgba) == {(250 << 24) | (20 << 16) | (10 << 8) | 255}
    assert len(column(data["/final/height/lines"], "LineStrips3D:strips")[0]) == 8 * len(q)
    n_vertical = int(np.sum(sol.lines.axis == 2))
    assert len(column(data["/final/topdown/lines"], "LineStrips2D:strips")[0]) == len(q) - n_vertical
    assert len(column(data["/final/topdown/vertical"], "Points2D:positions")[0]) == n_vertical
    assert len(column(data["/final/topdown/cameras"], "Points2D:positions")[0]) == F - 1
    # the blueprint holds the per-frame views and the paper's three views
    reader = rerun.chunk.RrdReader(path)
    origins = []
    for ch in reader.store(store=reader.blueprints()[0]).stream().to_chunks():
        rb = ch.to_record_batch()
        if "ViewBlueprint:space_origin" in rb.schema.names:
            origins += [o[0] if isinstance(o, list) else o
                        for o in rb.column("ViewBlueprint:space_origin").to_pylist()]
    assert sorted(o.lstrip("/") for o in origins) == sorted(
        ["world", "world/camera/image", "status", "batch", "final/quarter", "final/height", "final/topdown"])


def test_segment_colours_and_relation_links_match_the_frame(tmp_path):
    F = 6
    capture, pre, tracks, rel, sol = spin(F)
    path = log_recording(tmp_path / "rec.rrd", capture, pre, tracks, rel, sol, image_width=W)
    _, data = read_back(path)
    colors = column(data["/world/camera/image/segments"], "LineStrips2D:colors")
    links = column(data["/world/camera/image/relations"], "LineStrips2D:strips")
    floor_pts = column(data["/world/camera/image/floor"], "Points2D:positions")
    for f in range(F):
        sl = pre.segments.of_frame(f)
        want_rgb = AXIS_RGB[np.where(pre.labels[sl] >= 0, pre.labels[sl], 3)]
        got = np.array(colors[f], dtype=np.uint32)
        np.testing.assert_array_equal(np.stack([got >> 24, (got >> 16) & 255, (got >> 8) & 255], 1), want_rgb)
        here = set(tracks.track_of[sl][tracks.track_of[sl] >= 0].tolist())
        n_pairs = sum(1 for k, a, b in zip(rel.kind, rel.track_a, rel.track_b)
                      if k != FLOOR and a in here and b in here)
        n_floor = sum(1 for k, a in zip(rel.kind, rel.track_a) if k == FLOOR and a in here)
        assert len(links[f]) == n_pairs, f
        assert len(floor_pts[f]) == n_floor, f
        # each link joins the midpoints of two segments of this frame
        mids = pre.segments.midpoints[sl]
        for strip in links[f]:
            for p in strip:
                assert np.min(np.linalg.norm(mids - np.array(p), axis=1)) < 1e-3
    assert sum(len(x) for x in links) > 0


def test_minimal_recording_and_many_recordings_in_one_process(tmp_path):
    F = 4
    capture, pre, _, _, _ = spin(F)
    paths = [log_recording(tmp_path / f"r{k}.rrd", capture, pre, None, None, None, image_width=80) for k in range(3)]
    ids = set()
    for p in paths:
        reader = rerun.chunk.RrdReader(p)
        ids.add(reader.recordings()[0].recording_id)
        rows, _ = read_back(p)
        assert rows["/world/camera/image/segments"] == F
        assert rows["/world/camera"] == F
        assert not any(e.startswith("/final") or e == "/world/lines" for e in rows)
    assert len(ids) == 3  # fresh RecordingStream each time, each file finalised


def test_empty_model_is_logged_without_error(tmp_path):
    capture, pre, tracks, rel, sol = spin(3)
    lines = line_model(np.array([[0, 0, 0, 1, 0, 0.0]]), valid=np.zeros(1, bool))
    empty = Solution(R_wc=sol.R_wc, centers=np.full((3, 3), np.nan), registered=np.zeros(3, bool), lines=lines,
                     camera=sol.camera, metric=False, residuals={})
    rows, data = read_back(log_recording(tmp_path / "e.rrd", capture, pre, None, None, empty))
    assert rows["/world/camera"] == 3
    assert len(column(data["/final/quarter/lines"], "LineStrips3D:strips")[0]) == 0


def test_view_recording_errors_are_one_line(tmp_path, monkeypatch):
    with pytest.raises(ViewerError, match="no such recording"):
        view_recording(tmp_path / "missing.rrd")
    bad = tmp_path / "bad.rrd"
    bad.write_text("hello")
    with pytest.raises(ViewerError, match="not a rerun recording"):
        view_recording(bad)
    capture, pre, *_ = spin(2)
    good = log_recording(tmp_path / "ok.rrd", capture, pre, None, None, None, image_width=64)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    with pytest.raises(ViewerError, match="no display") as exc:
        view_recording(good)
    assert "\n" not in str(exc.value) and str(good) in str(exc.value)


@pytest.mark.slow
def test_logging_300_frames_is_cheap(tmp_path):
    import time

    capture, pre, tracks, rel, sol = spin(300, n_noise=20)
    t0 = time.perf_counter()
    log_recording(tmp_path / "big.rrd", capture, pre, tracks, rel, sol)
    dt = time.perf_counter() - t0
    assert dt < 300 * 0.02  # under 20 ms a frame (measured ~3 ms at 1280x720 -> 480 wide)



def test_thumbnails_replace_frame_reads(tmp_path):
    """Thumbnails made during detection are logged as they are; the capture's frames are never read."""
    from panosfm_graph.data import Thumbnails
    from panosfm_graph.thumbnails import jpeg_thumbnail

    F = 6
    capture, pre, tracks, rel, sol = spin(F)
    thumbs = Thumbnails.from_list([jpeg_thumbnail(capture.frame(i), 80) for i in range(F)], 80)
    assert thumbs.n == F and all(thumbs.get(i)[:2] == b"\xff\xd8" for i in range(F))  # JPEG magic

    def no_reads(k):
        raise AssertionError("a frame was decoded although thumbnails were given")

    blind = SimpleNamespace(camera=capture.camera, n_frames=F, frame=no_reads)
    rows, data = read_back(log_recording(tmp_path / "rec.rrd", blind, pre, tracks, rel, sol, thumbnails=thumbs))
    assert rows["/world/camera/image"] >= F
    images = [rb for rb in data["/world/camera/image"] if "EncodedImage:blob" in rb.schema.names]
    blobs = column(images, "EncodedImage:blob")
    assert len(blobs) == F
    first = blobs[0][0] if isinstance(blobs[0], list) and len(blobs[0]) == 1 else blobs[0]
    assert bytes(first) == thumbs.get(0)
