"""``panosfm batch``: many captures on a local Dask cluster, an index, resume, a killed worker, no Dask."""
from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from panosfm_graph.cli import build_parser, config_from_args, main
from panosfm_graph.config import Config, with_overrides
from panosfm_graph.errors import InputError

FRAMES, SIZE = 40, (320, 180)  # a full turn: the pipeline runs through (few frames register: enough here)


@pytest.fixture(scope="module")
def spin(tmp_path_factory) -> Path:
    """One small synthetic capture (with ground-truth poses), copied by the tests that need several."""
    from panosfm_graph.synth import synthesize

    return synthesize(tmp_path_factory.mktemp("batch") / "spin", "living", FRAMES, SIZE, seed=1, gt_maps=False,
                      workers=1)


def _captures(spin: Path, root: Path) -> Path:
    """Returns a folder holding captures ``a``, ``b`` (copies of ``spin``) and ``bad`` (its imu.csv corrupt)."""
    caps = root / "caps"
    for name in ("a", "b", "bad"):
        shutil.copytree(spin, caps / name)
    (caps / "bad" / "imu.csv").write_text("timestamp_s,qw,qx,qy,qz\n0.0,1,0,0\nnot a number\n")
    return caps


def _index(out: Path) -> dict[str, dict]:
    with open(out / "index.csv") as f:
        return {row["capture"]: row for row in csv.DictReader(f)}


def _outputs(out: Path) -> dict[str, float]:
    """Returns {file: mtime} of everything under ``out`` but the index."""
    return {str(p.relative_to(out)): p.stat().st_mtime_ns for p in out.rglob("*")
            if p.is_file() and not p.name.startswith("index.")}


def test_two_workers_three_captures_one_corrupt_then_resume_reruns_nothing(spin, tmp_path, capsys):
    pytest.importorskip("distributed")
    caps = _captures(spin, tmp_path)
    out = tmp_path / "out"
    code = main(["batch", str(caps), str(out), "--workers", "2", "--no-rerun"])
    text = capsys.readouterr().out
    assert code == 1, text  # a capture failed
    rows = _index(out)
    assert set(rows) == {"a", "b", "bad"}
    for name in ("a", "b"):
        row = rows[name]
        assert row["status"] == "ok" and row["error"] == "" and row["reused"] == "false"
        assert int(row["frames"]) == FRAMES and int(row["registered"]) >= int(row["accurate"]) >= 0
        assert float(row["seconds"]) > 0 and float(row["peak_memory_mb"]) > 0 and row["worker"].startswith("tcp://")
        for f in ("summary.json", "sparse/images.txt", "lines.ply", "eval.json", "batch.json"):
            assert (out / name / f).is_file(), f
        assert json.loads((out / name / "summary.json").read_text())["capture"] == str(caps / name)
    bad = rows["bad"]
    assert bad["status"] == "failed" and bad["error_kind"] == "input" and "imu.csv" in bad["error"]
    assert "\n" not in bad["error"] and not (out / "bad").exists()
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []  # no temporary leftovers
    # two workers ran the captures, each capture's detection in-process (2 cores here: one each)
    assert len({rows[n]["worker"] for n in rows}) >= 1
    assert "failed bad:" in text and "2/3 captures ok" in text
    index = json.loads((out / "index.json").read_text())
    assert index["workers"] == 2 and len(index["captures"]) == 3

    before = _outputs(out)
    code = main(["batch", str(caps), str(out), "--workers", "2", "--no-rerun", "--resume"])
    text = capsys.readouterr().out
    assert code == 1  # the corrupt capture is still failed: unchanged input, not run again
    rows = _index(out)
    assert all(r["reused"] == "true" for r in rows.values()) and rows["bad"]["status"] == "failed"
    assert _outputs(out) == before  # nothing rewritten
    assert "3 reused" in text and "ran " not in text


def _busy_worker(since: float):
    """Returns a Dask worker process of this test (spawned after ``since``) whose detection pool is up, or None."""
    import psutil

    for c in psutil.Process().children():
        try:
            if c.create_time() >= since and "spawn_main" in " ".join(c.cmdline()) and any(
                    "forkserver" in " ".join(k.cmdline()) for k in c.children()):
                return c
        except psutil.Error:
            pass
    return None


def _kill_worker_mid_run(spin: Path, tmp_path: Path, retries: int):
    """Runs a one-worker batch of one capture and SIGKILLs the worker once detection's pool has started."""
    pytest.importorskip("distributed")
    psutil = pytest.importorskip("psutil")
    from panosfm_graph.batch import run_batch

    out = tmp_path / "out"
    result: dict = {}
    thread = threading.Thread(target=lambda: result.setdefault(
        "r", run_batch([spin], out, rerun=False, workers=1, pool=2, retries=retries)))
    since = time.time() - 1.0
    thread.start()
    killed, deadline = None, time.monotonic() + 120
    while thread.is_alive() and killed is None and time.monotonic() < deadline:
        w = _busy_worker(since)  # its detection pool (a fork server) is up: the capture is mid-run
        if w is not None:
            killed = (out / spin.name / "summary.json").exists()
            try:
                w.send_signal(signal.SIGKILL)
            except psutil.Error:
                killed = None
        time.sleep(0.02)
    thread.join(timeout=180)
    assert killed is False, "the worker was not killed mid-run"
    assert "r" in result, "run_batch raised (see the thread's exception above)"
    return out, result["r"]


def test_killed_worker_its_capture_is_retried_and_no_half_written_output(spin, tmp_path):
    out, res = _kill_worker_mid_run(spin, tmp_path, retries=1)
    row = res.captures[0]
    assert row.status == "ok", row.error
    assert (out / spin.name / "summary.json").is_file() and (out / spin.name / "batch.json").is_file()
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []


@pytest.mark.slow
def test_killed_worker_without_retries_is_reported_failed(spin, tmp_path):
    out, res = _kill_worker_mid_run(spin, tmp_path, retries=0)
    row = res.captures[0]
    assert row.status == "failed" and row.error_kind == "worker died" and not res.ok
    assert not (out / spin.name / "summary.json").exists() and not (out / spin.name / "batch.json").exists()
    assert _index(out)[spin.name]["status"] == "failed"


def test_resume_needs_the_same_capture_content_config_and_options(spin, tmp_path):
    """What ``--resume`` takes as complete and current (no cluster: the decision alone)."""
    from panosfm_graph.batch import STAMP, CaptureResult, _previous, capture_fingerprint, run_key

    cap = tmp_path / "cap"
    shutil.copytree(spin, cap)
    out = tmp_path / "out" / "cap"
    out.mkdir(parents=True)
    key, fp = run_key(Config(), True, True), capture_fingerprint(cap)
    row = CaptureResult(capture="cap", path=str(cap), out=str(out), status="ok", key=key, fingerprint=fp)
    (out / STAMP).write_text(json.dumps(row.__dict__))
    assert _previous(out, cap, key, fp, None) is None  # no summary.json: not a finished run
    (out / "summary.json").write_text("{}")
    assert _previous(out, cap, key, fp, None).reused
    assert run_key(with_overrides(Config(), relations={"floor": False}), True, True) != key
    assert run_key(Config(), False, True) != key  # without recording.rrd
    assert _previous(out, cap, run_key(Config(), False, True), fp, None) is None
    frame = sorted((cap / "frames").iterdir())[0]
    os.utime(frame, ns=(frame.stat().st_atime_ns, frame.stat().st_mtime_ns + 10**9))
    assert capture_fingerprint(cap) != fp
    # a failure on the input is kept while nothing changed; any other failure is run again
    failed = dict(row.__dict__, status="failed", error_kind="input", error="bad")
    assert _previous(tmp_path / "none", cap, key, fp, failed).status == "failed"
    assert _previous(tmp_path / "none", cap, key, fp, dict(failed, error_kind="worker died")) is None


def test_captures_are_directories_or_folders_of_them(tmp_path):
    from panosfm_graph.batch import find_captures, output_names

    for d in ("room1", "room2", "notes"):
        (tmp_path / "spins" / d).mkdir(parents=True)
    (tmp_path / "spins" / "room1" / "camera.json").write_text("{}")
    (tmp_path / "spins" / "room2" / "imu.csv").write_text("")
    (tmp_path / "other" / "room1").mkdir(parents=True)
    (tmp_path / "other" / "room1" / "camera.json").write_text("{}")
    found = find_captures([tmp_path / "spins", tmp_path / "spins" / "room2", tmp_path / "other" / "room1"])
    assert [p.relative_to(tmp_path).as_posix() for p in found] == ["spins/room1", "spins/room2", "other/room1"]
    assert output_names(found) == ["spins-room1", "room2", "other-room1"]
    with pytest.raises(InputError, match="no such capture"):
        find_captures([tmp_path / "missing"])


def test_batch_shares_runs_options(tmp_path, capsys):
    args = build_parser().parse_args(["batch", "a", "b", "out", "--workers", "2", "--camera-height", "1.6",
                                      "--set", "relations.floor=False", "--resume", "--no-rerun"])
    assert args.captures == ["a", "b"] and args.out == "out" and args.workers == 2 and args.resume and args.no_rerun
    cfg = config_from_args(args)
    assert cfg.linear.camera_height_m == 1.6 and cfg.relations.floor is False
    code = main(["batch", str(tmp_path), str(tmp_path / "out"), "--scheduler", "tcp://127.0.0.1:1", "--workers", "2"])
    assert code == 2 and len(capsys.readouterr().err.strip().splitlines()) == 1


def test_without_dask_batch_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    code = main(["batch", str(tmp_path), str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "pip install 'panosfm[cluster]'" in err[0]
    # and panosfm (its CLI and the batch module) imports without Dask
    probe = ("import sys; sys.modules['dask'] = sys.modules['distributed'] = None; "
             "import panosfm_graph.batch, panosfm_graph.cli, panosfm_graph.pipeline")
    subprocess.run([sys.executable, "-c", probe], check=True)
