"""Procedural rooms and spins (panosfm_graph.synth.procedural, ``panosfm synth --scene random``): issue #63."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from panosfm_graph.synth import intrinsics, make_scene, random_spin, render_frame, spin_trajectory, synthesize
from panosfm_graph.synth.scenes import STRUCTURE, _Builder, crease_pieces

SEEDS = range(40)


@pytest.fixture(scope="module")
def photo_dir(tmp_path_factory):
    """Two 2:1 'photos': saturated colour bands (red / green rows) a noise texture never makes."""
    d = tmp_path_factory.mktemp("photos")
    v, u = np.mgrid[0:128, 0:256]
    red = np.zeros((128, 256, 3), np.uint8)
    red[..., 2] = 220
    red[(v // 8) % 2 == 0] = (0, 0, 90)
    cv2.imwrite(str(d / "a.png"), red)
    green = np.zeros((128, 256, 3), np.uint8)
    green[..., 1] = 220
    green[(u // 8) % 2 == 0] = (0, 90, 0)
    cv2.imwrite(str(d / "b.png"), green)
    (d / "notes.txt").write_text("not a photo")
    return d


def test_rooms_and_spins_cover_the_ranges_and_leave_room_to_spin():
    kinds, aspects, heights = set(), [], []
    for s in SEEDS:
        sc, sp = make_scene("random", s), random_spin(s)
        W, D, H = sc.room_max
        assert 2.0 - 1e-9 <= min(W, D) and max(W, D) <= 10.0 + 1e-9 and max(W, D) / min(W, D) <= 5.0 + 1e-6
        assert 2.2 <= H <= 5.0
        assert 0.25 <= sp.arm_m <= 0.5 and 0.0 <= sp.sway_m <= 0.08 and 324.0 <= sp.turn_deg <= 468.0
        assert 60 <= sp.frames_per_turn <= 600 and 50.0 <= sp.hfov_deg <= 90.0
        assert sc.n_boxes - sum(k == STRUCTURE for k in sc.box_kinds) <= 15 + 4 * 3 + 5 * 3 + 4  # furniture, doors..
        x, y = sc.stand_point[:2]
        assert min(x, W - x, y, D - y) >= 0.6 - 1e-9  # at least 0.6 m from the walls
        R, c, _ = spin_trajectory(sc, 120, seed=s, turn_deg=sp.turn_deg, sway_m=sp.sway_m, arm_m=sp.arm_m)
        assert sc.distance_to_surfaces(c).min() > 0.1  # the phone never touches a surface
        room = sc.to_room(c)
        assert np.all((room > sc.room_min) & (room < sc.room_max))
        kinds |= {n.rstrip("0123456789") for n, k in zip(sc.box_names, sc.box_kinds) if k == STRUCTURE}
        aspects.append(max(W, D) / min(W, D))
        heights.append(H)
    assert {"l_corner", "gallery", "pillar", "beam", "chimney"} <= kinds | {"chimney"} and "alcove_wall" in kinds
    assert max(aspects) > 3.0 and max(heights) > 3.6 and min(heights) < 2.6
    assert sum(random_spin(s).sway_m == 0 for s in SEEDS) >= 4  # ideal circles among the hand-held spins


def test_deterministic_per_seed(photo_dir):
    for s in (3, 11):
        a, b = make_scene("random", s, photo_dir), make_scene("random", s, photo_dir)
        assert json.dumps(a.to_json()) == json.dumps(b.to_json())
        assert random_spin(s) == random_spin(s)
    assert json.dumps(make_scene("random", 3).to_json()) != json.dumps(make_scene("random", 4).to_json())
    # the photo folder changes the textures, not the room or the spin
    plain, photo = make_scene("random", 5), make_scene("random", 5, photo_dir)
    np.testing.assert_array_equal(plain.boxes_min, photo.boxes_min)
    np.testing.assert_array_equal(plain.stand_point, photo.stand_point)
    assert len(plain.textures.photos) == 0 and len(photo.textures.photos) > 0
    assert {p.name for p in photo.textures.photos} <= {"a.png", "b.png"}


def test_synthesize_takes_the_seeds_spin_and_writes_the_same_capture_twice(tmp_path, photo_dir):
    seed = next(s for s in range(60) if random_spin(s).n_frames <= 90)
    sp = random_spin(seed)
    a = synthesize(tmp_path / "a", "random", size=(96, 54), seed=seed, gt_maps=False, workers=1, photo_dir=photo_dir)
    b = synthesize(tmp_path / "b", "random", size=(96, 54), seed=seed, gt_maps=False, workers=2, photo_dir=photo_dir)
    meta = json.loads((a / "ground_truth" / "synth.json").read_text())
    assert meta["n_frames"] == sp.n_frames and meta["turn_deg"] == sp.turn_deg and meta["sway_m"] == sp.sway_m
    assert meta["arm_m"] == sp.arm_m and meta["hfov_deg"] == sp.hfov_deg
    assert len(list((a / "frames").iterdir())) == sp.n_frames
    cam = json.loads((a / "camera.json").read_text())
    assert abs(2 * np.degrees(np.arctan(48 / cam["params"][0])) - sp.hfov_deg) < 1e-6
    for rel in ["ground_truth/poses.csv", "ground_truth/scene.json", "ground_truth/lines.csv", "frames/000000.png",
                f"frames/{sp.n_frames - 1:06d}.png"]:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    c = synthesize(tmp_path / "c", "random", n_frames=20, size=(96, 54), seed=seed, gt_maps=False, workers=1)
    assert len(list((c / "frames").iterdir())) == 20  # given settings override the seed's


def test_photo_surfaces_show_the_photo(photo_dir):
    seed = next(s for s in range(80) if 0 <= make_scene("random", s, photo_dir).textures.photo[4])  # a photo floor
    sc = make_scene("random", seed, photo_dir)
    K = intrinsics((160, 90))
    R = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # looking straight down
    c = sc.stand_point_world + [0, 0, 1.2]
    img, depth, _ = render_frame(sc, K, R, c, (160, 90))
    floor = np.abs(depth - 1.2) < 0.01
    assert floor.mean() > 0.5
    b, g, r = (img[..., k].astype(float) for k in range(3))
    colourful = (r > 2 * (g + b) + 20) | (g > 2 * (r + b) + 20)
    assert colourful[floor].mean() > 0.8  # the saturated photo, not a noise-textured grey


def test_l_shaped_room_edges_are_its_creases():
    """An L-shaped room (a solid corner) keeps the inner corner's edges and drops those hidden in the walls."""
    b = _Builder((6.0, 4.0, 2.5))
    b.box("l_corner", STRUCTURE, (4.0, 2.5, 0.0), (6.0, 4.0, 2.5), (0.8, 0.8, 0.8))
    mins, maxs = np.array([np.zeros(3), *b.mins]), np.array([b.size, *b.maxs])
    sc = b.build("l", 0, 0.0, [(0.8, 0.8, 0.8)] * 6, (2.0, 2.0))
    L, lab = sc.edges(frame="room")
    assert len(L) == 18  # the L's floor and ceiling outlines (6 + 6) and its 6 vertical edges
    verticals = {tuple(np.round(e[:2], 3)) for e, a in zip(L, lab) if a == 2}
    assert verticals == {(0, 0), (6, 0), (6, 2.5), (4, 2.5), (4, 4), (0, 4)}
    assert np.all(np.abs(L[lab == 2][:, 5] - L[lab == 2][:, 2]) == pytest.approx(2.5))
    # the shell's edge along y = 4 at the floor stops where the solid corner begins
    e = L[(lab == 0) & (np.abs(L[:, 1] - 4.0) < 1e-9) & (np.abs(L[:, 2]) < 1e-9)]
    assert len(e) == 1 and sorted([e[0, 0], e[0, 3]]) == [0.0, 4.0]
    # a free-standing box on the floor keeps all its 12 edges
    lo, hi = (1.0, 1.0, 0.0), (2.0, 1.5, 0.7)
    lines, _ = crease_pieces(*_box_edges(lo, hi), np.vstack([mins, [lo]]), np.vstack([maxs, [hi]]))
    assert len(lines) == 12
    assert len(crease_pieces(*_box_edges(lo, hi), mins, maxs)[0]) == 0  # the same edges in free air: none


def _box_edges(lo, hi):
    """Returns the 12 edges (room frame) and labels of the box lo..hi (Scene.edges of a room holding it alone)."""
    b = _Builder((6.0, 4.0, 2.5))
    b.box("t", "furniture", lo, hi, (0.5, 0.5, 0.5))
    L, lab = b.build("t", 0, 0.0, [(0.8, 0.8, 0.8)] * 6, (3.0, 3.0)).edges(frame="room")
    return L[1::2], lab[1::2]  # shell and box alternate (1 + B rows per edge of a box)
