"""The stage cache: exact round trips, keys that change with their inputs, corrupt entries recomputed."""
import numpy as np
import pytest

import ast
import importlib.util
from pathlib import Path

from panosfm_graph.cache import KEYED_BY_VALUE, STAGE_SOURCES, StageCache, load_stage, module_files, save_stage, stable_hash, stage_code_hash
from panosfm_graph.config import Config, with_overrides
from panosfm_graph.data import Camera, LineModel, Relations, Solution

ROOT = Path(__file__).resolve().parents[1]


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


def _module_file(name: str) -> Path | None:
    """Returns the file that importing ``name`` runs (a package: its ``__init__.py``), None if not a module."""
    try:
        spec = importlib.util.find_spec(name)
    except (ModuleNotFoundError, ValueError):
        return None
    return Path(spec.origin) if spec is not None and spec.origin else None


def _imported_files(path: Path) -> set[Path]:
    """Returns the files of panosfm_graph / factors that importing the module at ``path`` runs directly."""
    rel = path.resolve().relative_to(ROOT).with_suffix("")
    parts = list(rel.parts[:-1]) if rel.name == "__init__" else list(rel.parts)
    package = parts if rel.name == "__init__" else parts[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            mod = ".".join(base + ([node.module] if node.module else []))
            names = [mod] + [f"{mod}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        for n in names:
            f = _module_file(n) if n.split(".")[0] in ("panosfm_graph", "factors") else None
            if f is not None:
                out |= {f} | {p / "__init__.py" for p in f.parents if (p / "__init__.py").exists() and ROOT in p.parents}
    return out


def test_every_module_a_stage_runs_is_in_its_code_hash():
    """A stage's key covers the source of every module it imports (else --resume keeps an edited stage's old result)."""
    covered: set[Path] = {f for m in KEYED_BY_VALUE for f in module_files(m)}
    for stage, modules in STAGE_SOURCES.items():
        for m in modules:
            covered |= set(module_files(m))
        todo = [f for m in modules if m != "panosfm_graph.pipeline" for f in module_files(m)]  # the driver
        seen: set[Path] = set()  # imports every stage lazily
        while todo:
            f = todo.pop()
            if f in seen:
                continue
            seen.add(f)
            for dep in _imported_files(f):
                assert dep in covered, f"stage {stage}: {f.name} imports {dep}, which is not in its key"
                todo.append(dep)


def test_code_hash_follows_the_source(tmp_path, monkeypatch):
    import panosfm_graph.cache as cache

    mod = tmp_path / "panosfm_probe_mod.py"
    mod.write_text("x = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(cache.STAGE_SOURCES, "probe", ("panosfm_probe_mod",))
    before = cache.stage_code_hash.__wrapped__("probe")
    mod.write_text("x = 2\n")
    assert cache.stage_code_hash.__wrapped__("probe") != before
    assert stage_code_hash("linear") != stage_code_hash("bundle_adjust")
