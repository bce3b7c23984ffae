"""Reconstruction files: COLMAP text round trips (ours and pycolmap), lines.ply, summary, atomic output."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from panosfm_graph.data import Camera, LineModel, Solution
from panosfm_graph.errors import InputError
from panosfm_graph.export import (
    atomic_output_dir,
    export_reconstruction,
    poses_for_frames,
    read_colmap_text,
    read_lines_ply,
    recover_output_dir,
    write_colmap_text,
    write_lines_ply,
    write_summary,
)


def _poses(n, seed=0):
    rng = np.random.default_rng(seed)
    R = Rotation.random(n, random_state=seed).as_matrix()
    c = rng.normal(0.0, 2.0, (n, 3))
    return R, c


CAM = Camera("PINHOLE", 640, 480, np.array([512.3, 511.7, 319.25, 240.5]))


def test_colmap_round_trip_only_registered(tmp_path):
    n = 7
    R, c = _poses(n)
    reg = np.array([1, 1, 0, 1, 0, 1, 1], bool)
    c[~reg] = np.nan
    names = [f"{i:06d}.png" for i in range(n)]
    pts = np.random.default_rng(1).normal(size=(5, 3))
    write_colmap_text(tmp_path / "sparse", CAM, names, R, c, reg, points3D=pts)
    m = read_colmap_text(tmp_path / "sparse")
    assert m["camera"].model == "PINHOLE" and (m["camera"].width, m["camera"].height) == (640, 480)
    np.testing.assert_allclose(m["camera"].params, CAM.params, atol=1e-12)
    assert list(m["images"]) == [names[i] for i in np.flatnonzero(reg)]
    R2, c2, reg2 = poses_for_frames(m, names)
    assert np.array_equal(reg2, reg)
    np.testing.assert_allclose(R2[reg], R[reg], atol=1e-9)
    np.testing.assert_allclose(c2[reg], c[reg], atol=1e-9)
    assert np.all(np.isnan(c2[~reg]))
    np.testing.assert_allclose(m["points3D"], pts, atol=1e-12)
    # image ids are frame index + 1; each image line is followed by an (empty) POINTS2D line
    text = (tmp_path / "sparse" / "images.txt").read_text().splitlines()
    data = [ln for ln in text if not ln.startswith("#")]
    assert len(data) == 2 * reg.sum() and all(ln == "" for ln in data[1::2])
    assert [int(ln.split()[0]) for ln in data[0::2]] == list(np.flatnonzero(reg) + 1)


def test_colmap_reader_tolerates_foreign_files(tmp_path):
    d = tmp_path / "sparse"
    d.mkdir()
    (d / "cameras.txt").write_text("# a comment\n\n2 SIMPLE_RADIAL 640 480 500 320 240 -0.05\n")
    R, c = _poses(3, seed=3)
    q = Rotation.from_matrix(np.transpose(R, (0, 2, 1))).as_quat()[:, [3, 0, 1, 2]] * 3.0  # unnormalised
    t = -np.einsum("nij,nj->ni", np.transpose(R, (0, 2, 1)), c)
    lines = ["# Image list", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"]
    for i in range(3):
        lines.append(f"{10 + i} " + " ".join(f"{v:.17g}" for v in (*q[i], *t[i])) + f" 2 frames/{i:06d}.png")
        if i == 0:
            lines.append("100.5 200.25 -1 30.0 40.0 7")  # a real POINTS2D line
        elif i == 1:
            lines.append("")
        # image 2: the writer left the POINTS2D line out
    (d / "images.txt").write_text("\n".join(lines) + "\n")
    m = read_colmap_text(d)
    cam = m["camera"]
    assert m["colmap_models"][2] == "SIMPLE_RADIAL" and cam.model == "OPENCV"
    np.testing.assert_allclose(cam.K, [[500, 0, 320], [0, 500, 240], [0, 0, 1]])
    np.testing.assert_allclose(cam.distortion, [-0.05, 0, 0, 0])
    R2, c2, reg = poses_for_frames(m, [f"{i:06d}.png" for i in range(3)])  # matched by base name
    assert reg.all()
    np.testing.assert_allclose(R2, R, atol=1e-9)
    np.testing.assert_allclose(c2, c, atol=1e-9)
    assert len(m["points3D"]) == 0  # points3D.txt missing is fine

    (d / "cameras.txt").write_text("1 FISHEYE_X 640 480 1 2 3\n")
    with pytest.raises(InputError, match="cameras.txt"):
        read_colmap_text(d)


def test_pycolmap_reads_ours_and_we_read_pycolmap(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    n = 5
    R, c = _poses(n, seed=5)
    reg = np.array([1, 0, 1, 1, 1], bool)
    names = [f"{i:06d}.png" for i in range(n)]
    write_colmap_text(tmp_path / "ours", CAM, names, R, c, reg, points3D=np.ones((2, 6)))
    rec = pycolmap.Reconstruction(str(tmp_path / "ours"))
    assert rec.num_images() == reg.sum() and rec.num_points3D() == 2
    for im in rec.images.values():
        i = names.index(im.name)
        assert im.image_id == i + 1
        np.testing.assert_allclose(im.projection_center(), c[i], atol=1e-9)
        np.testing.assert_allclose(im.cam_from_world().rotation.matrix(), R[i].T, atol=1e-9)
    cam = rec.cameras[1]
    assert cam.model.name == "PINHOLE"
    np.testing.assert_allclose(cam.params, CAM.params)
    (tmp_path / "theirs").mkdir()
    rec.write_text(str(tmp_path / "theirs"))  # COLMAP's own writer (also writes rigs.txt, frames.txt)
    m = read_colmap_text(tmp_path / "theirs")
    R2, c2, reg2 = poses_for_frames(m, names)
    assert np.array_equal(reg2, reg)
    np.testing.assert_allclose(R2[reg], R[reg], atol=1e-9)
    np.testing.assert_allclose(c2[reg], c[reg], atol=1e-9)


def test_lines_ply_round_trip_ascii_and_binary(tmp_path):
    rng = np.random.default_rng(2)
    E = rng.normal(0.0, 3.0, (9, 6))
    lab = np.array([0, 1, 2, -1, 0, 1, 2, 2, 0], np.int8)
    col = rng.integers(0, 256, (9, 3)).astype(np.uint8)
    write_lines_ply(tmp_path / "l.ply", E, lab, col)
    E2, lab2, col2 = read_lines_ply(tmp_path / "l.ply")
    np.testing.assert_allclose(E2, E, atol=1e-9, rtol=0)
    assert np.array_equal(lab2, lab) and np.array_equal(col2, col)
    header = (tmp_path / "l.ply").read_text().split("end_header")[0]
    assert "element vertex 18" in header and "element edge 9" in header and "property int vertex1" in header

    # a binary LineSet as Open3D writes it (double vertices, int edges, edge colours, no label)
    V = E.reshape(-1, 3)
    hdr = ("ply\nformat binary_little_endian 1.0\ncomment Created by Open3D\nelement vertex 18\n"
           "property double x\nproperty double y\nproperty double z\nelement edge 9\nproperty int vertex1\n"
           "property int vertex2\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    vt = np.zeros(18, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    vt["x"], vt["y"], vt["z"] = V.T
    et = np.zeros(9, dtype=[("a", "<i4"), ("b", "<i4"), ("r", "u1"), ("g", "u1"), ("bl", "u1")])
    et["a"], et["b"] = np.arange(9) * 2, np.arange(9) * 2 + 1
    et["r"], et["g"], et["bl"] = col.T
    (tmp_path / "b.ply").write_bytes(hdr.encode() + vt.tobytes() + et.tobytes())
    E3, lab3, col3 = read_lines_ply(tmp_path / "b.ply")
    np.testing.assert_array_equal(E3, E)
    assert np.all(lab3 == -1) and np.array_equal(col3, col)

    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n0\n1\n")
    with pytest.raises(InputError, match="bad.ply"):
        read_lines_ply(tmp_path / "bad.ply")


def test_summary_converts_numpy(tmp_path):
    write_summary(tmp_path / "s.json", {"a": np.float32(1.5), "b": np.arange(3), "c": np.int64(4),
                                        "d": float("nan"), "e": (np.bool_(True), tmp_path)})
    s = json.loads((tmp_path / "s.json").read_text())
    assert s == {"a": 1.5, "b": [0, 1, 2], "c": 4, "d": None, "e": [True, str(tmp_path)]}


def test_atomic_output_dir_keeps_old_result_on_error(tmp_path):
    out = tmp_path / "out"
    with atomic_output_dir(out) as d:
        (d / "summary.json").write_text("old")
    assert (out / "summary.json").read_text() == "old"
    with pytest.raises(RuntimeError):
        with atomic_output_dir(out) as d:
            (d / "summary.json").write_text("half-written")
            raise RuntimeError("boom")
    assert (out / "summary.json").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # temporary dir removed
    with atomic_output_dir(out) as d:
        (d / "summary.json").write_text("new")
    assert (out / "summary.json").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # backup removed


def test_atomic_output_dir_bad_targets_and_recovery(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a directory"):
        with atomic_output_dir(tmp_path / "file"):
            pass
    with pytest.raises(InputError):
        with atomic_output_dir(tmp_path / "file" / "out"):  # parent is a file
            pass
    foreign = tmp_path / "home"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("precious")
    with pytest.raises(InputError, match="refusing"):
        with atomic_output_dir(foreign):
            pass
    assert (foreign / "thesis.tex").read_text() == "precious"
    if os.geteuid() != 0:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        try:
            with pytest.raises(InputError, match="not writable"):
                with atomic_output_dir(ro / "out"):
                    pass
        finally:
            ro.chmod(0o700)

    # crash between the two renames: only the backup exists -> it is restored
    out = tmp_path / "out"
    backup = tmp_path / ".out.backup"
    backup.mkdir()
    (backup / "summary.json").write_text("previous")
    recover_output_dir(out)
    assert (out / "summary.json").read_text() == "previous" and not backup.exists()
    # crash after the new result moved in: stale backup is removed
    backup.mkdir()
    recover_output_dir(out)
    assert not backup.exists() and (out / "summary.json").exists()


def test_export_reconstruction(tmp_path):
    n = 4
    R, c = _poses(n, seed=7)
    reg = np.array([1, 1, 0, 1], bool)
    c[~reg] = np.nan
    T = 3
    lm = LineModel(taylor=np.array([[0, 1.0, 0], [2.0, 0, 0], [0, 0, 0.5]]), direction=np.eye(3),
                   axis=np.array([0, 1, 2], np.int8), extent=np.array([[-1, 1.0], [0, 2.0], [1, 3.0]]),
                   valid=np.array([True, False, True]))
    sol = Solution(R_wc=R, centers=c, registered=reg, lines=lm, camera=CAM, metric=False,
                   residuals={"phase1": np.float64(0.25)})
    names = tuple(f"{i:06d}.png" for i in range(n))
    colors = np.array([[1, 2, 3], [4, 5, 6], [7, 8, 9]], np.uint8)
    with atomic_output_dir(tmp_path / "out") as d:
        export_reconstruction(d, sol, names, colors, {"seconds": {"lines": 1.5}})
    out = tmp_path / "out"
    m = read_colmap_text(out / "sparse")
    assert list(m["images"]) == ["000000.png", "000001.png", "000003.png"]
    E, lab, col = read_lines_ply(out / "lines.ply")
    np.testing.assert_allclose(E, lm.endpoints[[0, 2]], atol=1e-12)
    assert np.array_equal(lab, [0, 2]) and np.array_equal(col, colors[[0, 2]])
    np.testing.assert_allclose(m["points3D"], lm.endpoints[[0, 2]].reshape(-1, 3), atol=1e-12)
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == n and s["registered_frames"] == 3 and s["lines"] == 2 and s["scale"] == "arbitrary"
    assert s["seconds"] == {"lines": 1.5} and s["residuals"] == {"phase1": 0.25}
    assert s["versions"]["numpy"] == np.__version__
    assert T == len(lm.axis)
