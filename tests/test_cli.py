"""The CLI maps flags onto Config and turns bad input into one line and exit status 2."""
import pytest

from panosfm_graph.cli import build_parser, config_from_args, main
from panosfm_graph.config import with_overrides


def test_flags_map_onto_config():
    args = build_parser().parse_args(
        ["run", "cap", "out", "--every", "2", "--normals", "oracle", "--camera-height", "1.6",
         "--set", "relations.floor=False", "--set", "graph.robust=cauchy", "--incremental", "25"])
    cfg = config_from_args(args)
    assert cfg.capture.every_k == 2
    assert cfg.normals.source == "oracle"
    assert cfg.linear.camera_height_m == 1.6
    assert cfg.relations.floor is False
    assert cfg.graph.robust == "cauchy"
    assert cfg.graph.incremental_batch == 25


def test_spin_style_sets_its_fields_and_set_still_wins():
    from panosfm_graph.config import SPIN_STYLES

    steady = config_from_args(build_parser().parse_args(["run", "cap", "out", "--spin", "steady"]))
    for section, values in SPIN_STYLES["steady"].items():
        for field, value in values.items():
            assert getattr(getattr(steady, section), field) == value
    assert steady.linear.motion_bridge_deg > 0 and steady.graph.spin_position
    default = config_from_args(build_parser().parse_args(["run", "cap", "out"]))
    assert config_from_args(build_parser().parse_args(["run", "cap", "out", "--spin", "auto"])) == default
    assert default.graph.steady_auto and not default.graph.spin_position
    hand = config_from_args(build_parser().parse_args(["run", "cap", "out", "--spin", "hand-held"]))
    assert hand == with_overrides(default, graph={"steady_auto": False})
    assert not steady.graph.steady_auto  # already steady: nothing to try
    over = config_from_args(build_parser().parse_args(
        ["run", "cap", "out", "--spin", "steady", "--set", "linear.motion_bridge_deg=20"]))
    assert over.linear.motion_bridge_deg == 20.0 and over.graph.spin_position


def test_set_values_take_the_fields_type():
    """``false`` is False, not the truthy string "false"; numbers, None and tuples parse as their field."""
    sets = ["relations.parallel=false", "relations.floor=No", "graph.verify_relations=TRUE", "graph.max_iterations=7",
            "graph.reject_sigma=4", "linear.camera_height_m=none", "graph.phases=(1, 2)", "normals.source=oracle"]
    args = build_parser().parse_args(["run", "cap", "out", *[a for s in sets for a in ("--set", s)]])
    cfg = config_from_args(args)
    assert cfg.relations.parallel is False and cfg.relations.floor is False and cfg.graph.verify_relations is True
    assert cfg.graph.max_iterations == 7 and isinstance(cfg.graph.max_iterations, int)
    assert cfg.graph.reject_sigma == 4.0 and isinstance(cfg.graph.reject_sigma, float)
    assert cfg.linear.camera_height_m is None and cfg.graph.phases == (1, 2) and cfg.normals.source == "oracle"


@pytest.mark.parametrize("bad", ["relations.nope=1", "floor=False", "nosection.x=1", "relations.parallel=maybe",
                                 "graph.max_iterations=lots", "linear.min_depth_m=deep"])
def test_bad_set_is_exit_2(bad, tmp_path, capsys):
    code = main(["run", str(tmp_path / "cap"), str(tmp_path / "out"), "--set", bad])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("panosfm: error:")


def test_missing_capture_is_exit_2(tmp_path, capsys):
    code = main(["run", str(tmp_path / "missing"), str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "missing" in err[0]
    assert not (tmp_path / "out").exists()


def test_output_that_is_a_file_is_exit_2(tmp_path, capsys):
    f = tmp_path / "out"
    f.write_text("precious")
    code = main(["run", str(tmp_path / "missing"), str(f)])
    assert code == 2
    assert f.read_text() == "precious"
    assert "not a directory" in capsys.readouterr().err


def test_report_says_how_an_arbitrary_scale_was_fixed(tmp_path):
    """``panosfm run`` prints the scale: metric, or arbitrary and why, with the units when the spin's arm set them."""
    from panosfm_graph.pipeline import RunResult

    def scale_line(summary):
        return next(line for line in RunResult(tmp_path, summary).report().splitlines() if "scale" in line)

    cfg = {"linear": {"camera_height_m": 1.5, "spin_arm_m": 0.35}}
    arm = {"metric": False, "config": cfg, "residuals": {"linear": {"scale": "spin_arm"}}}
    assert "no floor line verified" in scale_line(arm) and "arm taken as 0.35 m" in scale_line(arm)
    depth = {"metric": False, "config": {"linear": {"camera_height_m": None}},
             "residuals": {"linear": {"scale": "mean_depth"}}}
    assert scale_line(depth).endswith("arbitrary (no --camera-height)")
    assert scale_line({"metric": True, "scale": "metric", "config": cfg}).endswith("metric")
    # the bundle adjustment took the scale from the spin's arm (graph._check_arm): the summary's text, and why
    from types import SimpleNamespace

    from panosfm_graph.config import Config
    from panosfm_graph.summary import _arbitrary_scale_text

    res = {"scale_from_arm": 0.55, "spin_arm_m_from_floor": 0.64, "spin_arm_m": 0.35}
    text = _arbitrary_scale_text(SimpleNamespace(residuals=res), Config())  # only its residuals are read
    assert "arm came out 0.64 m, outside 0.15-0.55 m" in text and "the arm taken as 0.35 m" in text
    assert _arbitrary_scale_text(SimpleNamespace(residuals={"spin_arm_m": 0.35}), Config()) == "arbitrary"
    from_arm = {"metric": False, "scale": text, "config": cfg, "residuals": {"linear": {"scale": "metric"},
                                                                         "bundle_adjust": res}}
    assert scale_line(from_arm).endswith(text)  # not "no floor line verified"


def test_report_counts_each_reason_for_unregistered_frames(tmp_path):
    """The report lists why frames are not registered as "N not: reason", reasons differing only in their figures
    counted once with the figures' range."""
    from panosfm_graph.pipeline import RunResult

    reasons = {"no tracked Manhattan line": 99, "left out: its std is 11.2 % of the spin's diameter": 2,
               "left out: its std is 14.5 % of the spin's diameter": 3}
    summary = {"frames": {"registered": 28, "total": 132, "registered_ratio": 28 / 132,
                          "unregistered_reasons": reasons}}
    lines = RunResult(tmp_path, summary).report().splitlines()
    assert "99 not: no tracked Manhattan line" in [line.strip() for line in lines]
    assert "5 not: left out: its std is 11.2-14.5 % of the spin's diameter" in [line.strip() for line in lines]


def test_section_settings_parse_one_sections_fields():
    """The tools' ``--set FIELD=VALUE`` (one Config section): the field's type, and a one-line error otherwise."""
    from panosfm_graph.cli import section_settings
    from panosfm_graph.config import LinearConfig, RelationsConfig
    from panosfm_graph.errors import InputError

    got = section_settings(LinearConfig(), ["spin_links=off", "min_view_eig=0.01", "camera_height_m=none"], "linear")
    assert got == {"spin_links": False, "min_view_eig": 0.01, "camera_height_m": None}
    assert section_settings(RelationsConfig(), None, "relations") == {}
    for bad in (["nope=1"], ["spin_links=maybe"]):
        with pytest.raises(InputError, match="linear"):
            section_settings(LinearConfig(), bad, "linear")
