"""Reliability: bad input, interrupted runs, resume, and what a result may hold.

Every bad input ends in one line on stderr naming the file, exit status 2, no
traceback, and the previous result byte-identical (the stage cache under
``<out>/cache/`` excepted: a failed run may leave cache entries of the stages
it completed, which ``--resume`` then reuses). Killed runs (SIGKILL from
outside during detection; self-inflicted SIGKILL inside bundle adjustment,
inside export and between the two renames of the output swap) leave either
the previous complete result or the new complete one, and the next run
recovers the leftovers and resumes from the last complete stage.
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from panosfm_graph.capture import capture_warnings, load_capture, turn_span_deg
from panosfm_graph.cli import main
from panosfm_graph.errors import InputError
from panosfm_graph.export import read_colmap_text, read_lines_ply
from panosfm_graph.pipeline import STAGES

N_FRAMES, SIZE = 100, (320, 180)
# The orientation map, not the ONNX model: results must not depend on whether models/normals.onnx exists.
# parallel coplanarity on (off by default): this small spin registers 2 frames with it and none without, and
# the tests that kill a run during the bundle adjustment need one
RUN_FLAGS = ["--no-rerun", "--normals", "orientation-map", "--set", "relations.parallel=true"]


# --------------------------------------------------------------------------- helpers


def snapshot(d: Path, skip: tuple[str, ...] = ("cache",)) -> dict[str, str]:
    """Returns {relative path: sha1} of every file under ``d`` (top-level entries in ``skip`` left out)."""
    out = {}
    if not d.exists():
        return out
    for p in sorted(d.rglob("*")):
        rel = p.relative_to(d)
        if p.is_file() and rel.parts[0] not in skip:
            out[str(rel)] = hashlib.sha1(p.read_bytes()).hexdigest()
    return out


def leftovers(out: Path) -> list[str]:
    """Returns the names of temporary / backup directories an output swap left next to ``out``."""
    return sorted(p.name for p in out.parent.glob(f".{out.name}.*"))


def check_result(out: Path, capture: Path) -> dict:
    """Returns summary.json after checking the result is complete and self-consistent (no NaN, counts agree)."""
    summary = json.loads((out / "summary.json").read_text())
    for name in ("sparse/cameras.txt", "sparse/images.txt", "sparse/points3D.txt", "lines.ply"):
        assert (out / name).is_file(), name
    for name in ("sparse/images.txt", "sparse/points3D.txt"):
        text = (out / name).read_text().lower()
        assert "nan" not in text and "inf" not in text, name
    model = read_colmap_text(out / "sparse")
    assert len(model["images"]) == summary["frames"]["registered"]
    assert summary["frames"]["registered"] + len(summary["frames"]["unregistered"]) == summary["frames"]["total"]
    assert not set(model["images"]) & set(summary["frames"]["unregistered"])
    why = summary["frames"]["unregistered_why"]  # every unregistered frame says why, in words
    assert len(why) == len(summary["frames"]["unregistered"]) and "registered" not in why
    assert sum(summary["frames"]["unregistered_reasons"].values()) == len(why)
    for im in model["images"].values():
        assert np.all(np.isfinite(im["R_wc"])) and np.all(np.isfinite(im["center"]))
    ends, _, _ = read_lines_ply(out / "lines.ply")
    assert np.all(np.isfinite(ends)) and len(ends) == summary["lines"]
    # the relations the result rests on are some of those detected, none where nothing is registered
    kept, found = summary["relations_kept"], summary["relations"]
    assert kept.keys() == found.keys() and all(0 <= kept[k] <= found[k] for k in found), (kept, found)
    assert summary["frames"]["registered"] > 0 or not any(kept.values()), kept
    frames = set(os.listdir(capture / "frames"))
    assert set(model["images"]) <= frames
    ba = summary["residuals"]["bundle_adjust"]
    if ba is not None:  # which spin style the result is, and where auto chose steady, why
        assert summary["spin_style"] in ("hand-held", "steady", "steady (auto)"), summary["spin_style"]
        check = ba.get("steady_check")
        assert (summary["spin_style"] == "steady (auto)") == bool(check and check["kept"]), check
    return summary


def cli(args: list[str], capsys) -> tuple[int, list[str]]:
    """Returns (exit status, stderr lines) of the CLI run in this process."""
    capsys.readouterr()
    code = main(args)
    return code, capsys.readouterr().err.strip().splitlines()


def assert_one_line_error(code: int, err: list[str], *words: str) -> None:
    assert code == 2, err
    assert len(err) == 1, err
    assert err[0].startswith("panosfm: error:") and "Traceback" not in err[0], err
    for w in words:
        assert w in err[0], (w, err[0])


def copy_capture(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("ground_truth"))
    return dst


def spawn(args: list[str], script: str | None = None, extra: list[str] = ()) -> subprocess.Popen:
    """Returns a ``panosfm`` process in its own session (so its worker processes can be killed with it)."""
    cmd = [sys.executable, "-c", script, *extra, *args] if script else [sys.executable, "-m", "panosfm_graph", *args]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


# A run that SIGKILLs itself at one chosen moment: "bundle_adjust" (as the solve starts), "export"
# (after sparse/ is written into the temporary directory), "swap" (the old result already renamed
# to the backup, the new one not yet in place). Shared with tools/bench_reliability.py.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from bench_reliability import KILLER, reap  # noqa: E402


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("reliability")


@pytest.fixture(scope="module")
def spin(work) -> Path:
    """A 100-frame 320x180 synthetic full spin (380 deg)."""
    from panosfm_graph.synth import synthesize

    return synthesize(work / "spin", n_frames=N_FRAMES, size=SIZE, seed=0, gt_maps=False)


@pytest.fixture(scope="module")
def baseline(work, spin) -> Path:
    """A complete, uninterrupted result of ``spin`` (run in this process through the CLI)."""
    out = work / "baseline"
    assert main(["run", str(spin), str(out), *RUN_FLAGS]) == 0
    return out


@pytest.fixture
def previous(baseline, tmp_path) -> Path:
    """A copy of the baseline result to be (not) replaced by a failing run."""
    out = tmp_path / "out"
    shutil.copytree(baseline, out)
    return out


# --------------------------------------------------------------------------- capture checks (no pipeline)


def test_turn_span_of_a_known_spin():
    yaw = np.radians(np.linspace(10.0, 190.0, 50))
    c, s = np.cos(yaw), np.sin(yaw)
    z = np.stack([c, s, np.full_like(c, -0.1)], axis=1)  # optical axis, 6 deg below the horizon
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x = np.stack([s, -c, np.zeros_like(c)], axis=1)
    R = np.stack([x, np.cross(z, x), z], axis=2)  # columns: camera x, y, z in the world
    assert turn_span_deg(R) == pytest.approx(180.0, abs=1e-6)
    assert turn_span_deg(R[::-1]) == pytest.approx(180.0, abs=1e-6)


def test_dropped_frames_warn_but_load(spin, tmp_path):
    cap = copy_capture(spin, tmp_path / "cap")
    rows = (cap / "frames.csv").read_text().splitlines()
    for r in rows[41:51]:  # drop 10 frames in the middle: a 11-interval gap
        (cap / "frames" / r.split(",")[0]).unlink()
    (cap / "frames.csv").write_text("\n".join(rows[:41] + rows[51:]) + "\n")
    capture = load_capture(cap)
    warnings = capture_warnings(capture)
    assert capture.n_frames == N_FRAMES - 10
    assert len(warnings) == 1 and "1 gap" in warnings[0] and "dropped" in warnings[0]
    assert rows[40].split(",")[0] in warnings[0] and rows[51].split(",")[0] in warnings[0]


def test_input_error_survives_pickling():
    """Worker processes hand exceptions back pickled: the message must come back whole."""
    import pickle

    e = pickle.loads(pickle.dumps(InputError("cannot be read as an image", Path("cap/frames/000007.png"))))
    assert isinstance(e, InputError) and str(e) == "cap/frames/000007.png: cannot be read as an image"


# --------------------------------------------------------------------------- bad input through the CLI


def _truncate_png(cap: Path) -> str:
    p = sorted((cap / "frames").iterdir())[37]
    b = p.read_bytes()
    p.write_bytes(b[: len(b) // 2])
    return p.name, "truncated"


def _jpeg_capture_truncated(cap: Path) -> str:
    rows = (cap / "frames.csv").read_text().splitlines()
    for p in sorted((cap / "frames").iterdir()):
        cv2.imwrite(str(p.with_suffix(".jpg")), cv2.imread(str(p)), [cv2.IMWRITE_JPEG_QUALITY, 90])
        p.unlink()
    (cap / "frames.csv").write_text("\n".join([rows[0]] + [r.replace(".png", ".jpg") for r in rows[1:]]) + "\n")
    p = sorted((cap / "frames").iterdir())[52]
    b = p.read_bytes()
    p.write_bytes(b[: int(len(b) * 0.7)])  # OpenCV would decode this silently with a grey bottom
    return p.name, "truncated"


def _duplicate_timestamp(cap: Path) -> str:
    rows = (cap / "frames.csv").read_text().splitlines()
    rows[31] = rows[31].split(",")[0] + "," + rows[30].split(",")[1]
    (cap / "frames.csv").write_text("\n".join(rows) + "\n")
    return "must increase"


def _slow_imu(cap: Path) -> str:
    rows = (cap / "imu.csv").read_text().splitlines()
    body = rows[1:]
    t = np.array([float(r.split(",")[0]) for r in body])
    keep = np.unique(np.concatenate([[0], np.flatnonzero(np.diff(np.floor(t / 0.5)) > 0) + 1, [len(body) - 1]]))
    (cap / "imu.csv").write_text("\n".join([rows[0]] + [body[k] for k in keep]) + "\n")  # ~2 Hz
    return "IMU rate"


def _camera(cap: Path, **params) -> None:
    cam = json.loads((cap / "camera.json").read_text())
    fx, fy, cx, cy = cam["params"]
    vals = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, **params}
    cam["params"] = [vals["fx"], vals["fy"], vals["cx"], vals["cy"]]
    (cap / "camera.json").write_text(json.dumps(cam))


def _blank_frames(cap: Path) -> str:
    grey = np.full((SIZE[1], SIZE[0], 3), 128, np.uint8)
    for p in (cap / "frames").iterdir():
        cv2.imwrite(str(p), grey)
    return "segments"


BAD_INPUT = [
    # (id, mutation returning a word the message must hold, the file the message must name)
    ("truncated png mid-sequence", _truncate_png, None),
    ("truncated jpeg mid-sequence", _jpeg_capture_truncated, None),
    ("duplicate timestamps", _duplicate_timestamp, "frames.csv"),
    ("imu far slower than frames", _slow_imu, "imu.csv"),
    ("principal point outside", lambda c: _camera(c, cx=SIZE[0] + 40.0) or "principal point", "camera.json"),
    ("focal too short", lambda c: _camera(c, fx=0.1 * SIZE[0], fy=0.1 * SIZE[0]) or "focal", "camera.json"),
    ("focal too long", lambda c: _camera(c, fx=12.0 * SIZE[0], fy=12.0 * SIZE[0]) or "focal", "camera.json"),
    ("too few manhattan lines", _blank_frames, "cap"),
]


@pytest.mark.parametrize("name,mutate,file", BAD_INPUT, ids=[b[0] for b in BAD_INPUT])
def test_bad_input_is_one_line_exit_2_and_keeps_the_previous_result(spin, previous, tmp_path, capsys, name,
                                                                        mutate, file):
    cap = copy_capture(spin, tmp_path / "cap")
    words = mutate(cap)
    words = (words,) if isinstance(words, str) else words
    before = snapshot(previous)
    code, err = cli(["run", str(cap), str(previous), *RUN_FLAGS], capsys)
    assert_one_line_error(code, err, *words, file or "")
    assert snapshot(previous) == before
    assert leftovers(previous) == []


def test_corrupt_frame_found_when_read(spin, previous, tmp_path, capsys):
    """A PNG damaged inside (header and end intact) passes the load check; reading it names it."""
    cap = copy_capture(spin, tmp_path / "cap")
    p = sorted((cap / "frames").iterdir())[61]
    b = bytearray(p.read_bytes())
    b[200:-100:97] = bytes(x ^ 0x55 for x in b[200:-100:97])
    p.write_bytes(bytes(b))
    load_capture(cap)  # the cheap load-time check cannot see it
    before = snapshot(previous)
    code, err = cli(["run", str(cap), str(previous), *RUN_FLAGS], capsys)
    assert_one_line_error(code, err, p.name, "cannot be read")
    assert snapshot(previous) == before and leftovers(previous) == []


def _failing_detect_frame(image, config, K=None, distortion=None):
    raise InputError("cannot be decoded (raised in a worker)", "cap/frames/000042.png")


def test_input_error_from_a_worker_process_is_exit_2(spin, previous, capsys, monkeypatch):
    import panosfm_graph.lines.detect as detect

    monkeypatch.setattr(detect, "detect_frame", _failing_detect_frame)
    before = snapshot(previous)
    code, err = cli(["run", str(spin), str(previous), "--set", "detect.workers=2", *RUN_FLAGS], capsys)
    assert_one_line_error(code, err, "000042.png", "raised in a worker")
    assert snapshot(previous) == before


def test_video_that_ends_early(spin, previous, tmp_path, capsys):
    cap = copy_capture(spin, tmp_path / "cap")
    frames = sorted((cap / "frames").iterdir())
    writer = cv2.VideoWriter(str(cap / "video.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, SIZE)
    if not writer.isOpened():
        pytest.skip("this OpenCV cannot write mp4v video")
    for p in frames[:-6]:  # the recording stopped 6 frames before frames.csv's end
        writer.write(cv2.imread(str(p)))
    writer.release()
    shutil.rmtree(cap / "frames")
    rows = (cap / "frames.csv").read_text().splitlines()
    (cap / "frames.csv").write_text("\n".join([rows[0]] + [f"{k:06d},{r.split(',')[1]}"
                                                           for k, r in enumerate(rows[1:])]) + "\n")
    before = snapshot(previous)
    code, err = cli(["run", str(cap), str(previous), *RUN_FLAGS], capsys)
    assert_one_line_error(code, err, "frames.csv", f"{N_FRAMES} rows", f"{N_FRAMES - 6} frames")
    assert snapshot(previous) == before


def test_too_short_turn_is_exit_2_with_the_span(work, previous, capsys):
    from panosfm_graph.synth import synthesize

    cap = synthesize(work / "short_turn", n_frames=24, size=SIZE, turn_deg=60.0, seed=2, gt_maps=False)
    before = snapshot(previous)
    code, err = cli(["run", str(cap), str(previous), *RUN_FLAGS], capsys)
    assert_one_line_error(code, err, "imu.csv", "turns only")
    span = float(err[0].split("turns only ")[1].split(" deg")[0])
    assert 50.0 < span < 70.0  # a 60 deg turn, 3 deg of IMU drift
    assert snapshot(previous) == before


def test_output_path_problems(spin, tmp_path, capsys):
    f = tmp_path / "result"
    f.write_text("precious")
    code, err = cli(["run", str(spin), str(f), *RUN_FLAGS], capsys)
    assert_one_line_error(code, err, str(f), "not a directory")
    assert f.read_text() == "precious"
    code, err = cli(["run", str(spin), str(f / "out"), *RUN_FLAGS], capsys)  # parent is a file
    assert_one_line_error(code, err, str(f))
    other = tmp_path / "photos"
    other.mkdir()
    (other / "holiday.jpg").write_bytes(b"\xff\xd8 not ours")
    code, err = cli(["run", str(spin), str(other), *RUN_FLAGS], capsys)
    assert_one_line_error(code, err, "refusing to replace")
    assert (other / "holiday.jpg").read_bytes() == b"\xff\xd8 not ours"


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes to read-only directories")
def test_unwritable_output_parent(spin, tmp_path, capsys):
    parent = tmp_path / "ro"
    parent.mkdir()
    parent.chmod(0o555)
    try:
        code, err = cli(["run", str(spin), str(parent / "out"), *RUN_FLAGS], capsys)
    finally:
        parent.chmod(0o755)
    assert_one_line_error(code, err, "not writable")


def test_disk_full_while_writing_the_summary(spin, previous, capsys, monkeypatch):
    import panosfm_graph.export as export

    def full(path, summary):
        Path(path).write_text('{"half": ')
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(export, "write_summary", full)
    before = snapshot(previous)
    code, err = cli(["run", str(spin), str(previous), "--resume", *RUN_FLAGS], capsys)
    assert_one_line_error(code, err, str(previous), "No space left")
    assert snapshot(previous) == before and leftovers(previous) == []


def test_disk_full_while_writing_the_cache(spin, previous, capsys, monkeypatch):
    import panosfm_graph.cache as cache

    def full(fh, **arrays):
        fh.write(b"PK\x03\x04 partial")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(cache.np, "savez", full)
    shutil.rmtree(previous / "cache")
    before = snapshot(previous)
    code, err = cli(["run", str(spin), str(previous), *RUN_FLAGS], capsys)
    assert_one_line_error(code, err, "No space left")
    assert snapshot(previous) == before
    assert list((previous / "cache").glob("*")) == []  # the half-written entry was removed


# --------------------------------------------------------------------------- results, resume, kills


def test_full_result_is_consistent(baseline, spin):
    s = check_result(baseline, spin)
    assert s["resumed_stages"] == [] and s["warnings"] == []
    assert s["frames"]["total"] == N_FRAMES


def test_partial_turn_warns_and_gives_a_partial_result(work, tmp_path, capsys):
    from panosfm_graph.synth import synthesize

    cap = synthesize(work / "half_turn", n_frames=100, size=SIZE, turn_deg=180.0, seed=3, gt_maps=False)
    out = tmp_path / "out"
    code, _ = cli(["run", str(cap), str(out), *RUN_FLAGS], capsys)
    assert code == 0
    s = check_result(out, cap)
    assert len(s["warnings"]) == 1 and "partial turn" in s["warnings"][0]


def test_changed_settings_rerun_only_what_they_affect(spin, previous, baseline):
    from panosfm_graph.config import Config, with_overrides
    from panosfm_graph.pipeline import run_pipeline

    base = with_overrides(Config(), normals={"source": "orientation-map"}, relations={"parallel": True})
    same = run_pipeline(spin, previous, base, resume=True, rerun=False)
    assert same.summary["resumed_stages"] == list(STAGES)
    assert (previous / "sparse" / "images.txt").read_bytes() == (baseline / "sparse" / "images.txt").read_bytes()
    no_floor = with_overrides(base, relations={"floor": False})
    res = run_pipeline(spin, previous, no_floor, resume=True, rerun=False)
    assert res.summary["resumed_stages"] == ["detect", "preprocess", "track", "normals"]
    assert res.summary["relations"]["floor"] == 0
    check_result(previous, spin)


def test_edited_code_reruns_its_stage_and_the_later_ones(spin, previous, monkeypatch):
    """--resume after an edit of linear.py (the same version number) must not return the old code's result."""
    from panosfm_graph import pipeline
    from panosfm_graph.cache import stage_code_hash
    from panosfm_graph.config import Config, with_overrides

    base = with_overrides(Config(), normals={"source": "orientation-map"}, relations={"parallel": True})
    edited = {"linear": "an edited linear.py"}
    monkeypatch.setattr(pipeline, "stage_code_hash", lambda stage: edited.get(stage) or stage_code_hash(stage))
    res = pipeline.run_pipeline(spin, previous, base, resume=True, rerun=False)
    assert res.summary["resumed_stages"] == ["detect", "preprocess", "track", "normals", "relations"]
    check_result(previous, spin)


@pytest.mark.slow
def test_changed_detection_setting_reruns_everything(spin, previous):
    from panosfm_graph.config import Config, with_overrides
    from panosfm_graph.pipeline import run_pipeline

    cfg = with_overrides(Config(), detect={"min_length_frac": 0.06}, normals={"source": "orientation-map"}, relations={"parallel": True})
    res = run_pipeline(spin, previous, cfg, resume=True, rerun=False)
    assert res.summary["resumed_stages"] == []


def _same_result(a: Path, b: Path) -> None:
    for name in ("sparse/images.txt", "sparse/points3D.txt", "lines.ply"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_sigkill_during_detection_then_resume(spin, baseline, tmp_path):
    out = tmp_path / "out"
    proc = spawn(["-v", "run", str(spin), str(out), *RUN_FLAGS])
    t0 = time.monotonic()
    for line in proc.stderr:  # kill as soon as detection has started
        if "panosfm: detect ..." in line:
            break
    time.sleep(0.3)
    os.killpg(proc.pid, signal.SIGKILL)
    code, _ = reap(proc, timeout=300)
    assert code == -signal.SIGKILL and time.monotonic() - t0 < 120
    assert not (out / "summary.json").exists() and not (out / "sparse").exists()  # no result, not half of one
    code, err = reap(spawn(["run", str(spin), str(out), "--resume", *RUN_FLAGS]), timeout=300)
    assert code == 0, err
    s = check_result(out, spin)
    assert s["resumed_stages"] == list(STAGES[: len(s["resumed_stages"])])  # a prefix: complete stages only
    assert leftovers(out) == []
    _same_result(out, baseline)


@pytest.mark.parametrize("moment", ["bundle_adjust", "export", "swap"])
def test_sigkill_keeps_the_previous_result_and_resume_finishes(spin, baseline, previous, moment):
    shutil.rmtree(previous / "cache")  # so that this run computes every stage again
    before = snapshot(previous)
    code, err = reap(spawn(["run", str(spin), str(previous), "--resume", *RUN_FLAGS], script=KILLER,
                           extra=[moment]), timeout=300)
    assert code == -signal.SIGKILL, err
    if moment == "swap":  # killed between the renames: the previous result sits in the backup
        backup = previous.parent / ".out.backup"
        assert not previous.exists() and snapshot(backup) == before
        assert any(".tmp-" in n for n in leftovers(previous))
    else:
        assert snapshot(previous) == before
    code, err = reap(spawn(["run", str(spin), str(previous), "--resume", *RUN_FLAGS]), timeout=300)
    assert code == 0, err
    s = check_result(previous, spin)
    assert leftovers(previous) == []
    if moment == "swap":
        # export.atomic_output_dir moves the cache into the temporary directory before the swap, so
        # recovery (which deletes a dead run's temporary directory) loses it: everything is recomputed.
        assert s["resumed_stages"] == list(STAGES[: len(s["resumed_stages"])])
    else:
        done = {"bundle_adjust": 6, "export": 7}[moment]  # stages complete before the kill
        assert s["resumed_stages"] == list(STAGES[:done])
    _same_result(previous, baseline)  # resuming gives what an uninterrupted run gives
