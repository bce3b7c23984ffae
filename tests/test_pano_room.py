"""Hand-held spins inside a panorama's room (panosfm_graph.synth.pano_room, ``panosfm synth --panorama --layout
--sway``): issue #63's real image texture with parallax."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from panosfm_graph.capture import load_capture
from panosfm_graph.cli import main
from panosfm_graph.errors import InputError
from panosfm_graph.evaluate import evaluate_reconstruction
from panosfm_graph.export import write_colmap_text
from panosfm_graph.synth.render import OPTICS_SIGMA_PX
from panosfm_graph.synth.panorama import _pad, pano_pixel, pinhole_intrinsics, render_view
from panosfm_graph.synth.pano_room import (
    distance_to_room, raycast_room, read_room_layout, render_room_frame, room_axes, room_spin,
)

PANO_H, PANO_W = 256, 512
CAM_H = 1.6
# an L-shaped room about the panorama's centre (0, 0), counter-clockwise, and its ceiling
L_ROOM = np.array([[-2.0, -1.5], [2.5, -1.5], [2.5, 1.0], [0.8, 1.0], [0.8, 2.2], [-2.0, 2.2]])
CEIL = 2.7


def _panorama() -> np.ndarray:
    v, u = np.mgrid[0:PANO_H, 0:PANO_W]
    img = np.stack([(u * 7 + v * 3) % 200 + 30, (u * 3 + v * 11) % 200 + 30, (v * 5 + u) % 200 + 30], -1)
    img[(u % 16 == 0) | (v % 16 == 0)] = 0
    return img.astype(np.uint8)


def _corner_file(path: Path, corners: np.ndarray, ceiling: float) -> Path:
    """Writes a HorizonNet corner file of a room seen from (0, 0, CAM_H) in a PANO_W x PANO_H panorama."""
    lines = []
    for x, y in corners:
        d = np.hypot(x, y)
        lon = np.arctan2(x, y)
        u = (lon / (2 * np.pi) + 0.5) * PANO_W - 0.5
        for z in (ceiling - CAM_H, -CAM_H):
            v = (0.5 - np.arctan2(z, d) / np.pi) * PANO_H - 0.5
            lines.append(f"{u:.6f} {v:.6f}")
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("pano_room")
    cv2.imwrite(str(d / "room.png"), _panorama())
    _corner_file(d / "room-corners.txt", L_ROOM, CEIL)
    return d / "room.png", d / "room-corners.txt"


def test_corner_file_gives_the_room(files):
    lay = read_room_layout(files[1], (PANO_H, PANO_W))
    assert lay["camera_height"] == CAM_H
    assert lay["ceiling_z"] == pytest.approx(CEIL, abs=0.01)
    np.testing.assert_allclose(lay["corners"], L_ROOM, atol=0.01)
    yaw, labels = room_axes(lay["corners"])
    assert abs(yaw) < 0.5 and list(labels) == [0, 1, 0, 1, 0, 1]


def test_at_the_panoramas_centre_a_frame_is_the_panorama(files):
    """From the panorama's own centre every surface point shows the panorama's colour in its direction."""
    pano = cv2.imread(str(files[0]))
    lay = read_room_layout(files[1], pano.shape)
    K, size = pinhole_intrinsics((160, 90), 70.0), (160, 90)
    yaw = np.radians(30.0)
    R = np.array([[np.cos(yaw), 0.0, np.sin(yaw)], [-np.sin(yaw), 0.0, np.cos(yaw)], [0.0, -1.0, 0.0]])
    img, depth, normals = render_room_frame(_pad(pano), pano.shape, lay, K, R, np.array([0, 0, CAM_H]), size)
    ref = cv2.GaussianBlur(render_view(pano, K, R, size).astype(np.float32), (0, 0), OPTICS_SIGMA_PX)  # as finish()
    assert np.mean(np.abs(img.astype(float) - ref)) < 1.0
    assert np.all(np.isfinite(depth)) and np.all(depth > 0)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=2), 1.0, atol=1e-5)


def test_raycast_hits_the_walls_and_planes():
    K, size = pinhole_intrinsics((64, 36), 60.0), (64, 36)
    R = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # columns: camera x, y (down), z (along +y) in the world
    hits = raycast_room(L_ROOM, CEIL, K, R, np.array([-1.0, 0.0, 1.5]), size)
    assert hits["depth"][18, 32] == pytest.approx(2.2, abs=1e-3)  # the wall y = 2.2, straight ahead
    np.testing.assert_allclose(hits["normal_cam"][18, 32], [0, 0, -1], atol=1e-3)  # facing the camera
    down = np.diag([1.0, -1.0, -1.0])  # looking straight down
    hits = raycast_room(L_ROOM, CEIL, K, down, np.array([-1.0, 0.0, 1.5]), size)
    np.testing.assert_allclose(hits["depth"], 1.5, atol=1e-6)
    p = hits["points"].reshape(-1, 3)
    assert np.abs(distance_to_room(p, L_ROOM, 0.0, CEIL)).max() < 1e-6
    assert distance_to_room(np.array([[0.0, 0.0, 1.0]]), L_ROOM, 0.0, CEIL)[0] == pytest.approx(1.0)
    assert distance_to_room(np.array([[2.0, 0.0, 1.5]]), L_ROOM, 0.0, CEIL)[0] == pytest.approx(0.5)


def test_room_spin_writes_a_capture_with_parallax_and_exact_ground_truth(files, tmp_path):
    cap = room_spin(*files, tmp_path / "cap", n_frames=24, size=(160, 90), seed=2, sway_m=0.04)
    c = load_capture(cap)
    gt = c.ground_truth
    assert c.n_frames == 24 and gt.has_depth
    spread = np.ptp(gt.centers, axis=0)
    assert spread[:2].max() > 0.3  # the camera moves on the arm: parallax
    lay = read_room_layout(files[1], (PANO_H, PANO_W))
    clear = np.min([np.min(np.hypot(*(gt.centers[:, :2] - q).T)) for q in lay["corners"]])
    assert clear > 0.2 and np.all(gt.centers[:, 2] < CEIL)
    scene = json.loads((cap / "ground_truth" / "scene.json").read_text())
    assert scene["room_polygon"]["ceiling_z"] == pytest.approx(CEIL, abs=0.01)
    assert sorted(set(gt.line_labels.tolist())) == [0, 1, 2]
    # every frame's depth map holds its pixels' surface: a pixel's ray at that depth lies on the room
    K = c.camera.K
    d = gt.depth(5)
    v, u = 40, 100
    ray = np.linalg.inv(K) @ [u, v, 1.0]
    X = gt.centers[5] + gt.R_wc[5] @ (ray * d[v, u])
    assert distance_to_room(X[None], lay["corners"], 0.0, lay["ceiling_z"])[0] < 1e-3
    # the true poses written as a reconstruction score as perfect
    write_colmap_text(tmp_path / "rec" / "sparse", c.camera, c.frame_names, gt.R_wc, gt.centers,
                      np.ones(24, bool))
    m = evaluate_reconstruction(cap, tmp_path / "rec")
    assert m["accurate"] == 24 and m["center_error_rel"]["max"] < 1e-6
    # the same settings write the same capture
    again = room_spin(*files, tmp_path / "again", n_frames=24, size=(160, 90), seed=2, sway_m=0.04)
    assert (again / "frames" / "000007.png").read_bytes() == (cap / "frames" / "000007.png").read_bytes()


def test_cli_spins_inside_the_room_with_sway(files, tmp_path, capsys):
    pano, lay = files
    assert main(["synth", str(tmp_path / "a"), "--panorama", str(pano), "--layout", str(lay), "--sway", "0.03",
                 "--frames", "6", "--size", "64x36"]) == 0
    meta = json.loads((tmp_path / "a" / "ground_truth" / "synth.json").read_text())
    assert meta["generator"] == "panosfm_graph.synth.pano_room" and meta["sway_m"] == 0.03
    assert main(["synth", str(tmp_path / "b"), "--panorama", str(pano), "--sway", "0.03"]) == 2  # no layout
    assert "--layout" in capsys.readouterr().err
    assert main(["synth", str(tmp_path / "c"), "--panorama", str(pano), "--layout", str(lay), "--sway", "0.03",
                 "--wobble", "2"]) == 2
    bad = tmp_path / "bad-corners.txt"
    bad.write_text("1 2\n3 4\n5\n")
    with pytest.raises(InputError):
        read_room_layout(bad, (PANO_H, PANO_W))
