"""tools/peer_colmap.py: the IMU gravity the GLOMAP peer is given (global-gravity) and that GLOMAP uses it.

The gravity tests need no pycolmap; the mapper test is skipped without it (CI does not install the peer extra).
"""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from peer_colmap import MAPPERS, gravity_in_camera  # noqa: E402


def _angle_deg(a, b):
    cos = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


@pytest.fixture(scope="module")
def tiny_capture(tmp_path_factory):
    from panosfm_graph.synth import synthesize

    # a hand-held spin (sway), small and fast: 20 frames at 320x180
    return synthesize(tmp_path_factory.mktemp("peer") / "cap", scene="living", n_frames=20, size=(320, 180),
                      seed=0, sway_m=0.05, gt_maps=False)


def test_gravity_in_camera_axes():
    """Down in the world (-z, capture-format.md) seen from an upright OpenCV camera is its +y (image down);
    a camera looking straight down sees it along its optical axis +z."""
    level = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # columns: camera x, y, z in the world
    assert np.allclose(level[:, 1], [0, 0, -1]) and np.isclose(np.linalg.det(level), 1.0)
    down = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # optical axis along world -z
    g = gravity_in_camera(np.stack([level, down]))
    assert np.allclose(g, [[0, 1, 0], [0, 0, 1]])


def test_gravity_from_imu_matches_ground_truth(tiny_capture):
    """What the peer writes as each image's gravity prior (from imu.csv) is the truth's gravity in that camera
    within the IMU's noise, it is unit, and it points down the image (OpenCV +y), not up."""
    from panosfm_graph.capture import load_capture
    from panosfm_graph.config import CaptureConfig

    cap = load_capture(tiny_capture, CaptureConfig())
    g_imu = gravity_in_camera(cap.R_wc_imu)
    g_true = np.einsum("fji,j->fi", cap.ground_truth.R_wc, [0.0, 0.0, -1.0])
    assert g_imu.shape == (cap.n_frames, 3)
    assert np.allclose(np.linalg.norm(g_imu, axis=1), 1.0, atol=1e-12)
    assert np.max(_angle_deg(g_imu, g_true)) < 0.5  # synthetic IMU noise is 0.1 deg
    assert np.all(g_imu[:, 1] > 0.9)  # a hand-held spin is roughly level: gravity is down the image
    # the sway tilts the camera: the priors are not all the same vector (a constant would pass the checks above)
    assert np.max(_angle_deg(g_imu, g_imu[:1])) > 1.0


def test_cli_lists_the_gravity_mapper():
    assert MAPPERS == ("incremental", "global", "global-gravity")


def test_global_gravity_writes_priors_and_glomap_aligns_to_them(tiny_capture, tmp_path):
    """Every image gets a gravity prior in the database; with the rotation averaging alone, GLOMAP's model has
    world +y along each registered image's prior (the 1-DOF gravity-aligned mode); the full peer records it."""
    pycolmap = pytest.importorskip("pycolmap", minversion="4.0")
    from peer_colmap import run_peer, write_gravity_priors

    import cv2
    from panosfm_graph.capture import load_capture
    from panosfm_graph.config import CaptureConfig

    cap = load_capture(tiny_capture, CaptureConfig())
    images = tmp_path / "images"
    images.mkdir()
    names = []
    for i, name in enumerate(cap.frame_names):
        cv2.imwrite(str(images / Path(name).name), cap.frame(i))
        names.append(Path(name).name)
    gravity = dict(zip(names, gravity_in_camera(cap.R_wc_imu)))
    db = tmp_path / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    K = cap.camera.K
    reader.camera_params = f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}"
    pycolmap.extract_features(db, images, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, device=pycolmap.Device.cpu)
    assert write_gravity_priors(db, gravity) == len(names)
    d = pycolmap.Database.open(str(db))
    try:
        by_id = {im.image_id: im.name for im in d.read_all_images()}
        priors = d.read_all_pose_priors()
    finally:
        d.close()
    assert len(priors) == len(names)
    for p in priors:
        assert p.has_gravity() and not p.has_position()
        assert np.allclose(p.gravity, gravity[by_id[p.corr_data_id.id]])

    pycolmap.match_sequential(db, device=pycolmap.Device.cpu)
    opts = pycolmap.GlobalPipelineOptions()
    opts.mapper.rotation_averaging.use_gravity = True
    opts.mapper.skip_global_positioning = True  # rotations only: bundle adjustment may tilt them afterwards
    opts.mapper.skip_bundle_adjustment = True
    opts.mapper.skip_retriangulation = True
    (tmp_path / "sparse").mkdir()
    models = pycolmap.global_mapping(db, images, tmp_path / "sparse", options=opts)
    best = max(models.values(), key=lambda r: r.num_reg_images())
    assert best.num_reg_images() >= 5
    posed = [im for im in best.images.values() if im.has_pose]
    y_in_cam = np.array([im.cam_from_world().rotation.matrix()[:, 1] for im in posed])
    assert np.max(_angle_deg(y_in_cam, np.array([gravity[im.name] for im in posed]))) < 0.01

    out = tmp_path / "out"
    summary = run_peer(tiny_capture, out, mapper="global-gravity")
    assert summary["gravity"]["priors"] == summary["gravity"]["images"] == cap.n_frames
    assert "gravity" in summary["peer"] and f"{cap.n_frames}/{cap.n_frames} images" in summary["peer"]
    assert json.loads((out / "summary.json").read_text())["gravity"]["use_gravity"] is True
    assert (out / "sparse" / "images.txt").exists()
