"""Spin captures cut from an equirectangular panorama (panosfm_graph.synth.panorama, ``panosfm synth --panorama``)."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from panosfm_graph.capture import load_capture
from panosfm_graph.cli import main
from panosfm_graph.errors import InputError
from panosfm_graph.geometry import quat_wxyz_to_matrix, rotation_angle_deg
from panosfm_graph.synth import cut_spin
from panosfm_graph.synth.panorama import (
    imu_attitude, pano_direction, pano_pixel, pano_spin_params, pinhole_intrinsics, read_layout, spin_pose,
)

REAL = Path(__file__).resolve().parents[2] / "shared" / "real"
PANO_W, PANO_H = 512, 256
N, SIZE, HFOV = 16, (160, 90), 65.0
DRIFT, NOISE, SEED = 4.0, 0.3, 5
CELL = 16  # panorama colour cells (px)


def _cell_colour(iu: np.ndarray, iv: np.ndarray) -> np.ndarray:
    """Returns (..., 3) uint8 BGR of colour cell (iu, iv): distinct per cell, far apart between neighbours."""
    return np.stack([(iu * 53 + iv * 17) % 200 + 30, (iu * 29 + iv * 71) % 200 + 30, (iv * 97 + iu * 7) % 200 + 30],
                    axis=-1).astype(np.uint8)


def _panorama() -> np.ndarray:
    """A 512x256 procedural panorama: flat-coloured 16x16 px cells separated by dark vertical/horizontal lines."""
    v, u = np.mgrid[0:PANO_H, 0:PANO_W]
    img = _cell_colour(u // CELL, v // CELL)
    img[(u % CELL == 0) | (v % CELL == 0)] = 0  # grid lines: meridians (vertical) and parallels (horizontal)
    return img


def _layout(path: Path) -> Path:
    pts = [[2.0, 0.0, -1.0], [2.0, 0.0, 1.5], [-1.0, 0.0, 1.5], [-1.0, 0.0, -1.0]]  # PanoAnnotator: x, y up, z
    path.write_text(json.dumps({"cameraHeight": 1.5, "layoutHeight": 2.6,
                                "layoutPoints": {"num": 4, "points": [{"coords": [0, 0.5], "xyz": p} for p in pts]}}))
    return path


@pytest.fixture(scope="module")
def pano_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("pano") / "grid.png"
    cv2.imwrite(str(path), _panorama())
    return path


@pytest.fixture(scope="module")
def capture(pano_file, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cut")
    return cut_spin(pano_file, root / "cap", n_frames=N, size=SIZE, hfov_deg=HFOV, seed=SEED, imu_drift_deg=DRIFT,
                    imu_noise_deg=NOISE, layout=_layout(root / "layout.json"))


def _rows(path: Path) -> tuple[list[str], list[list[str]]]:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    return rows[0], rows[1:]


def _gt(capture: Path) -> tuple[np.ndarray, np.ndarray]:
    _, rows = _rows(capture / "ground_truth" / "poses.csv")
    vals = np.array([[float(x) for x in r[1:]] for r in rows])
    return quat_wxyz_to_matrix(vals[:, :4]), vals[:, 4:]


def test_pixel_direction_convention_round_trips():
    shape = (PANO_H, PANO_W)
    # README: column centre u + 0.5 -> lon ((u + 0.5) / W - 0.5) 2 pi;
    # direction (cos lat sin lon, cos lat cos lon, sin lat)
    np.testing.assert_allclose(pano_direction(PANO_W / 2 - 0.5, PANO_H / 2 - 0.5, shape), [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(pano_direction(3 * PANO_W / 4 - 0.5, PANO_H / 2 - 0.5, shape), [1, 0, 0], atol=1e-12)
    u, v = np.random.default_rng(0).uniform([0, 1], [PANO_W - 1, PANO_H - 2], (200, 2)).T
    uu, vv = pano_pixel(pano_direction(u, v, shape), shape)
    np.testing.assert_allclose(np.column_stack([uu, vv]), np.column_stack([u, v]), atol=1e-9)


def test_frames_show_the_panorama_colour_of_each_pixel_direction(capture):
    """A frame pixel whose ray hits the interior of a panorama cell has that cell's colour."""
    R, _ = _gt(capture)
    K = pinhole_intrinsics(SIZE, HFOV)
    pano = _panorama()
    checked = 0
    for i in (0, 5, N - 1):
        img = cv2.imread(str(capture / "frames" / f"{i:06d}.png"))
        assert img.shape == (SIZE[1], SIZE[0], 3)
        y, x = np.mgrid[0:SIZE[1], 0:SIZE[0]]
        rays = np.stack([(x - K[0, 2]) / K[0, 0], (y - K[1, 2]) / K[1, 1], np.ones(x.shape)], axis=-1)
        u, v = pano_pixel(rays @ R[i].T, pano.shape)
        u = np.mod(u, PANO_W)
        du, dv = np.mod(u, CELL), np.mod(v, CELL)
        inner = (du > 4) & (du < CELL - 4) & (dv > 4) & (dv < CELL - 4)  # away from the cell's grid lines
        want = _cell_colour((u // CELL).astype(int), (v // CELL).astype(int))
        np.testing.assert_array_equal(img[inner], want[inner])
        checked += int(inner.sum())
        # and the dark grid lines land where the rays cross a meridian or a parallel
        on_line = (du < 0.05) | (dv < 0.05)
        dark, cell = img[on_line].astype(float).sum(axis=1), want[on_line].astype(float).sum(axis=1)
        assert on_line.sum() > 20 and np.median(dark) < 0.5 * np.median(cell)
    assert checked > 1000


def test_ground_truth_rotations_are_the_spin_and_all_centres_equal(capture):
    R, C = _gt(capture)
    p = pano_spin_params(N, SEED)
    R_true, _ = spin_pose(p, np.arange(N) / 30.0)
    assert np.max(rotation_angle_deg(R, R_true)) < 1e-5
    np.testing.assert_array_equal(C, np.broadcast_to(C[0], C.shape))
    np.testing.assert_allclose(C[0], [0, 0, 1.5])  # the layout's camera height above the floor z = 0
    yaw = np.degrees(np.unwrap(np.arctan2(R[:, 0, 2], R[:, 1, 2])))  # optical axis heading
    assert abs(yaw[-1] - yaw[0]) == pytest.approx(380.0, abs=0.5)  # a 380 deg turn, first to last frame
    pitch = np.degrees(np.arcsin(R[:, 2, 2]))
    assert -12 < pitch.min() and pitch.max() < 0 and np.ptp(pitch) > 1  # looking a little down, wobbling
    for i, (rv, rt) in enumerate(zip(R, R_true)):
        assert np.allclose(rv.T @ rv, np.eye(3), atol=1e-9) and np.linalg.det(rv) > 0, i


def test_imu_is_truth_with_the_drift_and_noise_asked(capture):
    head, rows = _rows(capture / "imu.csv")
    assert head == ["timestamp_s", "qw", "qx", "qy", "qz"]
    imu = np.array(rows, dtype=np.float64)
    assert np.allclose(np.diff(imu[:, 0]), 0.01) and imu[0, 0] < 0 and imu[-1, 0] > (N - 1) / 30.0
    t, R_imu = imu[:, 0], quat_wxyz_to_matrix(imu[:, 1:])
    R_true, _ = spin_pose(pano_spin_params(N, SEED), t)
    # heading drift: the rotation about world z between the IMU and the truth, grows linearly to DRIFT
    D = R_imu @ np.transpose(R_true, (0, 2, 1))
    heading = np.degrees(np.arctan2(D[:, 1, 0], D[:, 0, 0]))
    fit = np.polyfit(t, heading, 1)
    assert fit[0] * (N - 1) / 30.0 == pytest.approx(DRIFT, rel=0.1)
    # the noise: RMS angle between the IMU and the drifted truth per sample
    drift = np.radians(np.polyval(fit, t))
    Rz = np.array([[[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]] for a in drift])
    resid = rotation_angle_deg(Rz @ R_true, R_imu)
    assert np.sqrt(np.mean(resid**2)) == pytest.approx(NOISE, rel=0.25)
    # and the same model as imu_attitude
    t2, R2 = imu_attitude(pano_spin_params(N, SEED), N, seed=SEED, imu_drift_deg=DRIFT, noise_deg=NOISE)
    assert np.max(rotation_angle_deg(R2, R_imu)) < 1e-5


def test_load_capture_reads_it_with_the_layout_lines(capture):
    cap = load_capture(capture)
    assert cap.n_frames == N and (cap.camera.width, cap.camera.height) == SIZE
    gt = cap.ground_truth
    R, C = _gt(capture)
    assert np.max(rotation_angle_deg(gt.R_wc, R)) < 1e-6
    assert gt.camera_height_m == pytest.approx(1.5)
    # IMU at the frames: within the drift (+ noise) of the truth
    err = rotation_angle_deg(cap.R_wc_imu, gt.R_wc)
    assert err.max() < DRIFT + 1.5 and np.median(err) > 0.05
    # 4 corners -> 4 floor + 4 ceiling + 4 vertical edges, axis-labelled; PanoAnnotator (x, y, z) -> world (x, -z, y)
    assert gt.lines.shape == (12, 6)
    assert sorted(gt.line_labels.tolist()) == [0] * 4 + [1] * 4 + [2] * 4
    np.testing.assert_allclose(gt.lines[0], [2.0, 1.0, 0.0, 2.0, -1.5, 0.0])
    assert set(np.round(gt.lines[:, [2, 5]].ravel(), 6)) == {0.0, 2.6}
    assert gt.scene["room"] == {"min": [-1.0, -1.5, 0.0], "max": [2.0, 1.0, 2.6]}
    synth = json.loads((capture / "ground_truth" / "synth.json").read_text())
    assert synth["generator"] == "panosfm_graph.synth.panorama" and synth["panorama"] == "grid.png"


def test_layout_corners_project_where_the_layout_coords_say(tmp_path):
    """A layout point's xyz lies at the longitude its coords u give (the README's convention)."""
    lay = read_layout(_layout(tmp_path / "l.json"))
    lon = np.degrees(np.arctan2(lay["corners"][:, 0], lay["corners"][:, 1]))
    np.testing.assert_allclose(lon, np.degrees(np.arctan2([2, 2, -1, -1], [1, -1.5, -1.5, 1])))
    if (REAL / "bathroom-layout.json").is_file():
        d = json.loads((REAL / "bathroom-layout.json").read_text())
        u = np.array([pt["coords"][0] for pt in d["layoutPoints"]["points"]])
        real = read_layout(REAL / "bathroom-layout.json")
        lon_xyz = np.arctan2(real["corners"][:, 0], real["corners"][:, 1])
        d_lon = np.angle(np.exp(1j * (lon_xyz - (u - 0.5) * 2 * np.pi)))
        assert np.degrees(np.abs(d_lon)).max() < 0.5


def test_bad_input_is_one_line_input_error(tmp_path, pano_file, capsys):
    with pytest.raises(InputError, match="not found"):
        cut_spin(tmp_path / "missing.png", tmp_path / "o1")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    with pytest.raises(InputError, match="cannot be read as an image"):
        cut_spin(tmp_path / "bad.png", tmp_path / "o2")
    cv2.imwrite(str(tmp_path / "square.png"), np.zeros((64, 64, 3), np.uint8))
    with pytest.raises(InputError, match="twice as wide"):
        cut_spin(tmp_path / "square.png", tmp_path / "o3")
    (tmp_path / "lay.json").write_text("{}")
    with pytest.raises(InputError, match="PanoAnnotator"):
        cut_spin(pano_file, tmp_path / "o4", layout=tmp_path / "lay.json")
    with pytest.raises(InputError, match="n_frames"):
        cut_spin(pano_file, tmp_path / "o5", n_frames=1)
    assert not any(p.name.startswith(("o", ".o")) for p in tmp_path.iterdir())  # nothing half-written
    assert main(["synth", str(tmp_path / "o6"), "--panorama", str(tmp_path / "square.png")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "twice as wide" in err
    assert main(["synth", str(tmp_path / "o7"), "--panorama", str(pano_file), "--scene", "office"]) == 2
    assert main(["synth", str(tmp_path / "o8"), "--layout", str(tmp_path / "lay.json")]) == 2


def test_cli_cuts_a_spin(tmp_path, pano_file, capsys):
    out = tmp_path / "cap"
    assert main(["synth", str(out), "--panorama", str(pano_file), "--frames", "6", "--size", "64x36", "--seed", "2",
                 "--imu-drift", "1.5"]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    cam = json.loads((out / "camera.json").read_text())
    assert (cam["width"], cam["height"]) == (64, 36) and len(list((out / "frames").iterdir())) == 6
    synth = json.loads((out / "ground_truth" / "synth.json").read_text())
    assert synth["seed"] == 2 and synth["imu_drift_deg"] == 1.5 and synth["layout"] is None
    assert not (out / "ground_truth" / "lines.csv").exists()


def test_cut_real_bedroom(tmp_path):
    if not (REAL / "bedroom.png").is_file():
        pytest.skip(f"no real panorama at {REAL}")
    cap = load_capture(cut_spin(REAL / "bedroom.png", tmp_path / "bed", n_frames=24, size=(320, 180)))
    assert cap.n_frames == 24
    img = cap.frame(0)
    assert img.shape[:2] == (180, 320) and img.std() > 10  # a real image, not a blank
    assert np.all(np.isfinite(cap.ground_truth.R_wc))


def test_eval_of_a_zero_baseline_capture_scores_rotations_only(capture, tmp_path):
    """The true centres coincide: eval aligns rotations only, counts frames within 1 degree as accurate and
    reports how far apart the estimated centres lie (a translation the pipeline would have invented)."""
    from scipy.spatial.transform import Rotation

    from panosfm_graph.evaluate import evaluate_reconstruction, format_metrics
    from panosfm_graph.export import write_colmap_text

    cap = load_capture(capture)
    gt = cap.ground_truth
    turn = Rotation.from_euler("z", 30, degrees=True).as_matrix()  # any common turn is aligned away
    R = np.einsum("ij,njk->nik", turn, gt.R_wc)
    R[2] = Rotation.from_rotvec(np.radians(2.0) * np.array([0.0, 0.6, 0.8])).as_matrix() @ R[2]
    c = np.zeros((len(R), 3))
    c[5] = [0.0, 0.3, 0.4]  # one invented translation
    write_colmap_text(tmp_path / "rec" / "sparse", cap.camera, cap.frame_names, R, c, np.ones(len(R), bool))
    m = evaluate_reconstruction(cap, tmp_path / "rec")
    assert m["zero_baseline"] and m["trajectory_diameter_m"] == 0.0
    assert m["accurate"] == len(R) - 1  # the frame turned by 2 degrees
    assert m["rotation_error_rotalign_deg"]["median"] < 0.2
    assert abs(m["estimated_centre_spread"] - 0.5) < 1e-9
    assert m["reprojection_px"] is None and "zero baseline" in format_metrics(m)
