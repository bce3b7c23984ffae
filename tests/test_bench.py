"""tools/bench.py: medians over the captures of a scene and their table (no pipeline run)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from bench import _medians, capture_dir, format_bench  # noqa: E402


def _run(reg, centre, reproj):
    return {"wall_s": 1.0, "metrics": {"registered_share": reg, "accurate_share": reg / 2, "center_error_rel": {"median": centre},
                                       "rotation_error_rotalign_deg": {"median": 0.1},
                                       "reprojection_px": {"mean": reproj},
                                       "lines": {"distance_m": {"median": 0.1}, "recovered_share": 0.5}}}


def test_medians_over_seeds_skip_failures():
    runs = {"living": {"panosfm": _run(0.9, 0.10, 2.0)},
            "living#1": {"panosfm": _run(0.5, 0.02, 1.0)},
            "living#2": {"panosfm": {"wall_s": 1.0, "error": "boom"}},
            "office": {"panosfm": _run(0.3, 0.01, 1.1)}}
    med = _medians(runs, ["living", "office"])
    liv = med["living"]["panosfm"]
    assert liv["captures"] == 3 and liv["failed"] == 1
    assert liv["registered"] == 0.7 and abs(liv["centre"] - 0.06) < 1e-12 and liv["reprojection"] == 1.5
    assert med["office"]["panosfm"]["captures"] == 1 and med["office"]["panosfm"]["centre"] == 0.01
    md = format_bench({"date": "d", "machine": "m", "frames": 3, "size": [9, 6], "scenes": runs,
                       "median_over_seeds": med})
    assert "| living | panosfm | 3 (1 failed) | 70.0 % | 35.0 % | 6.00 |" in md
    assert "| living#2 | panosfm | failed: boom |" in md


def test_drop_captures_deletes_each_capture_once_scored(tmp_path):
    from bench import bench

    record = bench(["living"], 40, (160, 90), tmp_path, [], seed=3, drop_captures=True)
    entry = record["scenes"]["living"]["panosfm"]
    assert entry["exit"] == 0 and "metrics" in entry  # it was run and scored ...
    assert list((tmp_path / "captures").iterdir()) == []  # ... and its capture is gone
    assert (tmp_path / "bench.json").exists() and (tmp_path / "runs" / "living" / "panosfm").is_dir()


def test_capture_names_are_shared_by_the_benchmarks():
    # tools/bench.py and tools/bench_tracking.py name captures alike, so one folder's captures serve the other
    assert capture_dir(Path("o"), "office", 300, (960, 540), 12) == Path("o/captures/office-300-960x540-s12")
    assert capture_dir(Path("o"), "living", 300, (960, 540), 0, 0.05).name == "living-300-960x540-s0-sway0.05"


def test_speeds_summary_time_exponent():
    """seconds = 0.1 * frames (linear) gives the exponent 1; quadratic seconds give 2; medians per speed kept."""
    from bench import format_speeds, speeds_summary

    def rec(n, power):
        runs = {name: {"panosfm": {**_run(0.9, 0.01, 1.0), "wall_s": 0.1 * n ** power}} for name in ("living", "living#1")}
        return {"scenes": runs, "median_over_seeds": _medians(runs, ["living"])}

    lin = speeds_summary({n: rec(n, 1.0) for n in (60, 150, 600)})
    assert abs(lin["time_exponent"] - 1.0) < 1e-9 and lin["seconds_median"][600] == 60.0
    assert lin["by_frames"][150]["living"]["registered"] == 0.9
    assert abs(speeds_summary({n: rec(n, 2.0) for n in (60, 600)})["time_exponent"] - 2.0) < 1e-9
    assert "| 60 | living | 90.0 % | 45.0 % |" in format_speeds(lin)
