"""Ablation sets switch exactly the relation and factor types they name."""
import pytest

from panosfm_graph.ablation import COPLANARITIES, ablation_sets, format_ablation
from panosfm_graph.config import Config
from panosfm_graph.errors import InputError


def _on(cfg: Config) -> set[str]:
    return {k for k in COPLANARITIES if getattr(cfg.relations, k) and getattr(cfg.graph, f"coplanarity_{k}")}


DEFAULT_ON = {"orthogonal", "junction", "floor"}  # parallel coplanarity is off by default (config.py)


def test_paper_sets():
    sets = ablation_sets("paper")
    assert list(sets) == ["junction", "junction+orthogonal+parallel", "all four", "no coplanarity",
                          "zero translation"]
    assert _on(sets["junction"]) == {"junction"}
    assert _on(sets["junction+orthogonal+parallel"]) == {"junction", "orthogonal", "parallel"}
    assert _on(sets["all four"]) == set(COPLANARITIES)
    assert _on(sets["no coplanarity"]) == set()
    assert sets["zero translation"].linear.zero_translation is True
    assert all(not c.linear.zero_translation for n, c in sets.items() if n != "zero translation")


def test_factor_sets_turn_off_one_each():
    sets = ablation_sets("factors")
    assert _on(sets["all"]) == DEFAULT_ON
    assert _on(sets["no floor"]) == DEFAULT_ON - {"floor"}
    assert _on(sets["with parallel"]) == set(COPLANARITIES) and "no parallel" not in sets
    assert _on(ablation_sets("factors", ablation_sets("paper")["all four"])["no parallel"]) == DEFAULT_ON
    assert sets["no colinearity"].graph.colinearity is False
    assert sets["no reprojection"].graph.reprojection is False
    assert sets["no imu"].graph.imu_prior is False
    assert sets["no imu"].graph.reprojection is True
    assert sets["no spin"].graph.spin_sigma_m == 0 and sets["no spin"].linear.spin_weight == 0
    assert sets["all"].graph.spin_sigma_m > 0 and sets["no imu"].linear.spin_weight > 0


def test_custom_list_and_unknown_names():
    (name, cfg), = ablation_sets("junction,floor,reprojection").items()
    assert _on(cfg) == {"junction", "floor"}
    assert cfg.graph.reprojection and not cfg.graph.colinearity and not cfg.graph.imu_prior
    assert cfg.graph.spin_sigma_m == 0 and cfg.linear.spin_weight == 0
    with pytest.raises(InputError, match="unknown factor type"):
        ablation_sets("junction,walls")


def test_table_has_a_row_per_set():
    rows = {"a": {"registered_ratio": 0.5, "relations": {"orthogonal": 1, "parallel": 2, "junction": 3, "floor": 4},
                  "metrics": {"center_error_rel": {"median": 0.031}}},
            "b": {"registered_ratio": 1.0, "relations": {}, "metrics": None}}
    table = format_ablation(rows).splitlines()
    assert len(table) == 4
    assert "| a | 50.0 % |" in table[2] and "1/2/3/4" in table[2]
    assert "| b | 100.0 % |" in table[3] and "n/a" in table[3]
