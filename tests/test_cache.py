"""The stage cache: exact round trips, keys that change with their inputs, corrupt entries recomputed."""
import numpy as np
import pytest

from panosfm_graph.cache import StageCache, load_stage, save_stage, stable_hash
from panosfm_graph.config import Config, with_overrides
from panosfm_graph.data import Camera, LineModel, Relations, Solution


def _solution() -> Solution:
    rng = np.random.default_rng(0)
    lines = LineModel(rng.normal(size=(4, 3)), np.eye(3)[[0, 1, 2, 0]], np.array([0, 1, 2, 0], np.int8),
                      rng.normal(size=(4, 2)), np.array([True, True, False, True]))
    cam = Camera("PINHOLE", 64, 48, np.array([50.0, 51.0, 31.5, 23.5]))
    centers = rng.normal(size=(3, 3))
    centers[2] = np.nan
    return Solution(np.tile(np.eye(3), (3, 1, 1)), centers, np.array([True, True, False]), lines, cam, True,
                    {"colinearity_rms": 0.25, "phases": [1, 2]})


def test_solution_round_trip_is_exact(tmp_path):
    s = _solution()
    save_stage(tmp_path / "s.npz", s)
    t = load_stage(tmp_path / "s.npz", Solution)
    np.testing.assert_array_equal(t.centers, s.centers)
    np.testing.assert_array_equal(t.lines.taylor, s.lines.taylor)
    np.testing.assert_array_equal(t.lines.valid, s.lines.valid)
    assert t.camera.model == "PINHOLE" and t.camera.width == 64
    np.testing.assert_array_equal(t.camera.params, s.camera.params)
    assert t.metric is True and t.residuals == s.residuals


def test_empty_relations_round_trip(tmp_path):
    r = Relations(*(np.zeros(0, dt) for dt in (np.int8, np.int32, np.int32, np.int8, np.int32)))
    save_stage(tmp_path / "r.npz", r)
    t = load_stage(tmp_path / "r.npz", Relations)
    assert t.n == 0 and t.kind.dtype == np.int8


def test_keys_change_with_config_and_only_there():
    a = Config()
    b = with_overrides(a, relations={"floor": False})
    assert stable_hash(a.detect) == stable_hash(b.detect)
    assert stable_hash(a.relations) != stable_hash(b.relations)
    assert stable_hash(np.arange(3)) != stable_hash(np.arange(4))


def test_cache_disabled_and_corrupt_entries(tmp_path):
    cache = StageCache(tmp_path, enabled=True)
    cache.save("linear", "k1", _solution())
    assert cache.load("linear", "k1", Solution) is not None
    assert cache.load("linear", "k2", Solution) is None
    cache.save("linear", "k2", _solution())  # replaces the stale key
    assert not cache.path("linear", "k1").exists()
    cache.path("linear", "k2").write_bytes(b"not an npz")
    assert cache.load("linear", "k2", Solution) is None
    assert not cache.path("linear", "k2").exists()
    assert StageCache(tmp_path, enabled=False).load("linear", "k2", Solution) is None


def test_with_overrides_rejects_unknown_fields():
    with pytest.raises(TypeError):
        with_overrides(Config(), relations={"no_such_field": 1})
