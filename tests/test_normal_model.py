"""The shipped normal network (``panosfm_graph/models/normals.onnx``, paper §3.2) on held-out rendered rooms.

The model was trained on seeded ``random`` rooms only (tools/train_normals.py);
the named presets used here were never seen in training. Frames are rendered
with the project's ray caster and scored against its GT normals.
"""
from __future__ import annotations

import numpy as np
import pytest

from panosfm_graph.config import NormalsConfig
from panosfm_graph.data import Capture, GroundTruth
from panosfm_graph.data import NormalMaps
from panosfm_graph.normals import estimate_normals, normal_accuracy, resize_normals
from panosfm_graph.normals.onnx import SHIPPED_MODEL, load_session, model_input_size, run_model
from panosfm_graph.synth import render_frame
from panosfm_graph.synth.problem import make_problem

pytestmark = pytest.mark.skipif(not SHIPPED_MODEL.is_file(), reason="no shipped normal model")

SIZE = (480, 270)
# the shipped model on these 4-frame spins: median 7.2 (living) / 11.0 (office) deg, 85 / 77 % within 20 deg;
# the previous, underfitted one (17.9 / 26.4 deg, 55 / 37 %) fails these bounds
MEDIAN_MAX_DEG = 14.0
WITHIN_20_MIN = 0.7
BEAT_PRIOR_DEG = 8.0
WALL_HORIZONTAL_MIN = 0.85
FLOOR_MARGIN = 0.2


def _rendered_capture(scene: str, n_frames: int, seed: int = 0):
    """Returns (SyntheticProblem, Capture) of ``n_frames`` rendered views of a spin in ``scene``, with GT normals."""
    P = make_problem(scene, n_frames=n_frames, size=SIZE, seed=seed)
    cache = {}

    def render(i):
        if i not in cache:
            cache[i] = render_frame(P.scene, P.camera.K, P.gt_R_wc[i], P.gt_centers[i], SIZE, seed=i)
        return cache[i]

    gt = GroundTruth(R_wc=P.gt_R_wc, centers=P.gt_centers, lines=np.zeros((0, 6)), line_labels=np.zeros(0, np.int8),
                     scene={}, normals=lambda i: render(i)[2], depth=lambda i: render(i)[1],
                     has_normals=True, has_depth=True)
    cap = Capture(root=None, camera=P.camera, frame_names=tuple(map(str, range(n_frames))),
                  timestamps=np.arange(n_frames) / 30.0, R_wc_imu=P.preprocessed.R_wc_imu, ground_truth=gt,
                  reader=lambda i: render(i)[0])
    return P, cap


@pytest.fixture(scope="module", params=["living", "office"])
def held_out(request):
    """Model normal maps of 4 frames of a held-out preset room and the capture they came from."""
    P, cap = _rendered_capture(request.param, 4)
    nm = estimate_normals(cap, P.preprocessed, NormalsConfig(source="model", width=256))
    return P, cap, nm


def test_shipped_model_contract():
    sess = load_session(SHIPPED_MODEL)
    assert SHIPPED_MODEL.stat().st_size < 20e6
    inp = sess.get_inputs()[0]
    assert inp.type == "tensor(float)" and len(inp.shape) == 4
    H, W = model_input_size(sess, 256, 9 / 16)
    assert (H, W) == (144, 256)  # dynamic H x W: the runner feeds NormalsConfig.width wide
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (270, 480, 3), dtype=np.uint8)
    n = run_model(sess, img, (H, W))
    assert n.shape == (144, 256, 3) and n.dtype == np.float32
    assert np.all(np.isfinite(n))
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-3)  # unit normals


def _constant_prior(nm, R_wc):
    """Returns NormalMaps of the trivial guess "every pixel faces the camera" (camera-frame (0, 0, -1))."""
    F, h, w = nm.valid.shape
    n_w = np.einsum("fij,j->fi", R_wc, np.array([0.0, 0.0, -1.0]))
    maps = np.broadcast_to(n_w[:, None, None, :], (F, h, w, 3)).astype(np.float16)
    return NormalMaps(maps=maps, valid=np.ones((F, h, w), bool), scale=nm.scale, source="constant")


def test_model_accuracy_on_held_out_room(held_out):
    P, cap, nm = held_out
    assert nm.source == "model"
    assert nm.maps.shape == (4, 144, 256, 3)
    acc = normal_accuracy(nm, cap, P.preprocessed.R_wc)
    base = normal_accuracy(_constant_prior(nm, P.preprocessed.R_wc), cap, P.preprocessed.R_wc)
    # bounds from the shipped model's measured accuracy (MEDIAN_MAX_DEG etc. above; tools/README.md)
    assert acc["coverage"] > 0.99
    assert acc["median_deg"] < MEDIAN_MAX_DEG
    assert acc["within_20deg"] > WITHIN_20_MIN
    assert acc["median_deg"] < base["median_deg"] - BEAT_PRIOR_DEG


def test_model_tells_walls_from_floor(held_out):
    """Floor pixels get world normals tilted towards +z, wall pixels near-horizontal ones."""
    P, cap, nm = held_out
    F, h, w = nm.valid.shape
    z_floor, z_wall = [], []
    for f in range(F):
        g, g_ok = resize_normals(cap.ground_truth.normals(f), h, w)
        gz = (g.reshape(-1, 3) @ P.gt_R_wc[f].T)[:, 2]  # GT world-frame vertical component
        mz = nm.maps[f].astype(np.float32).reshape(-1, 3)[:, 2]
        z_floor.append(mz[g_ok.ravel() & (gz > 0.99)])
        z_wall.append(mz[g_ok.ravel() & (np.abs(gz) < 0.05)])
    z_floor, z_wall = np.concatenate(z_floor), np.concatenate(z_wall)
    assert len(z_floor) > 500 and len(z_wall) > 5000
    assert np.mean(np.abs(z_wall) < np.sin(np.radians(25))) > WALL_HORIZONTAL_MIN
    assert np.median(z_floor) - np.median(np.abs(z_wall)) > FLOOR_MARGIN
