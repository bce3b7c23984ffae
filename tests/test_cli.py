"""The CLI maps flags onto Config and turns bad input into one line and exit status 2."""
import pytest

from panosfm_graph.cli import build_parser, config_from_args, main


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


@pytest.mark.parametrize("bad", ["relations.nope=1", "floor=False", "nosection.x=1"])
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
