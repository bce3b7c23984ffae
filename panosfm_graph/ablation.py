"""Ablations over relation and factor types (paper §4, Fig. 'Contributions of the coplanarities').

An ablation is a list of named :class:`Config` variants run on one capture;
stages whose inputs do not change (detection, rotations, tracks, normals) are
shared through one cache. ``run_ablation`` writes ``ablation.md``,
``ablation.json`` and ``topdown_sets.png`` (each set's top-down view side by
side) into the output directory.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from .config import Config, with_overrides
from .errors import InputError

log = logging.getLogger("panosfm")

COPLANARITIES = ("orthogonal", "parallel", "junction", "floor")
FACTOR_TYPES = ("colinearity", "orthogonal", "parallel", "junction", "floor", "reprojection", "imu", "spin")


def _coplanarity_set(cfg: Config, enabled: set[str]) -> Config:
    rel = {k: (k in enabled) for k in COPLANARITIES}
    graph = {f"coplanarity_{k}": (k in enabled) for k in COPLANARITIES}
    return with_overrides(cfg, relations=rel, graph=graph)


def _enabled_coplanarities(cfg: Config) -> set[str]:
    """Returns the coplanarity types both detected and used by the bundle adjustment in ``cfg``."""
    return {k for k in COPLANARITIES if getattr(cfg.relations, k) and getattr(cfg.graph, f"coplanarity_{k}")}


def _factor_off(cfg: Config, factor: str) -> Config:
    if factor in COPLANARITIES:
        return _coplanarity_set(cfg, _enabled_coplanarities(cfg) - {factor})
    if factor == "spin":  # the spin model in both solves (linear rows, BA factors)
        return with_overrides(cfg, linear={"spin_weight": 0.0}, graph={"spin_sigma_m": 0.0})
    key = {"colinearity": "colinearity", "reprojection": "reprojection", "imu": "imu_prior"}[factor]
    return with_overrides(cfg, graph={key: False})


def ablation_sets(sets: str | list[str], base: Config = Config()) -> dict[str, Config]:
    """Returns named configs: ``"paper"``, ``"factors"``, or a list/comma list of factor types to keep."""
    if isinstance(sets, str) and sets == "paper":
        return {
            "junction": _coplanarity_set(base, {"junction"}),
            "junction+orthogonal+parallel": _coplanarity_set(base, {"junction", "orthogonal", "parallel"}),
            "all four": _coplanarity_set(base, set(COPLANARITIES)),
            "no coplanarity": _coplanarity_set(base, set()),
            "zero translation": with_overrides(base, linear={"zero_translation": True}),
        }
    if isinstance(sets, str) and sets == "factors":  # each type of the default switched off (or on, if it is off)
        out = {"all": base}
        on = _enabled_coplanarities(base)
        for f in FACTOR_TYPES:
            if f in COPLANARITIES and f not in on:
                out[f"with {f}"] = _coplanarity_set(base, on | {f})
            else:
                out[f"no {f}"] = _factor_off(base, f)
        return out
    names = [s.strip() for s in (sets.split(",") if isinstance(sets, str) else sets) if s.strip()]
    unknown = [n for n in names if n not in FACTOR_TYPES]
    if unknown:
        raise InputError(f"unknown factor type(s) {', '.join(unknown)}; choose from {', '.join(FACTOR_TYPES)}, "
                         "or the sets 'paper' / 'factors'")
    cfg = _coplanarity_set(base, {n for n in names if n in COPLANARITIES})
    for f in ("colinearity", "reprojection", "imu", "spin"):
        if f not in names:
            cfg = _factor_off(cfg, f)
    return {"+".join(names): cfg}


def run_ablation(capture_dir: str | Path, out_dir: str | Path, sets: str | list[str] = "paper",
                 config: Config = Config()) -> str:
    """Returns the markdown table of metrics per set; writes each set's reconstruction under ``out_dir``."""
    import cv2

    from .evaluate import evaluate_reconstruction
    from .pipeline import check_output_dir, run_pipeline

    out_dir = Path(out_dir)
    check_output_dir(out_dir)
    configs = ablation_sets(sets, config)
    rows = {}
    cache_dir = out_dir / "cache"
    for name, cfg in configs.items():
        slug = name.replace(" ", "_").replace("+", "-")
        log.info("ablation set %r", name)
        res = run_pipeline(capture_dir, out_dir / slug, cfg, resume=True, rerun=False, cache_dir=cache_dir)
        row = {"registered_ratio": res.summary["frames"]["registered_ratio"],
               "relations": res.summary["relations"], "seconds": res.summary["seconds"].get("total")}
        try:
            row["metrics"] = evaluate_reconstruction(capture_dir, out_dir / slug)
        except InputError as exc:  # no ground truth: report what the run itself knows
            row["metrics"] = None
            log.warning("no evaluation for %s: %s", name, exc)
        rows[name] = row
    from .export import to_jsonable

    (out_dir / "ablation.json").write_text(json.dumps(to_jsonable(rows), indent=2))
    table = format_ablation(rows)
    (out_dir / "ablation.md").write_text(table + "\n")
    tiles = []
    for name in configs:
        p = out_dir / name.replace(" ", "_").replace("+", "-") / "views" / "topdown.png"
        img = cv2.imread(str(p)) if p.exists() else None
        if img is not None:
            img = cv2.resize(img, (480, int(480 * img.shape[0] / img.shape[1])), interpolation=cv2.INTER_AREA)
            img = cv2.copyMakeBorder(img, 36, 0, 0, 0, cv2.BORDER_CONSTANT, value=(255, 255, 255))
            cv2.putText(img, name, (10, 26), cv2.FONT_HERSHEY_SIMPLEX, 0.75, (0, 0, 0), 2, cv2.LINE_AA)
            tiles.append(img)
    if tiles:
        h = max(t.shape[0] for t in tiles)
        tiles = [cv2.copyMakeBorder(t, 0, h - t.shape[0], 0, 4, cv2.BORDER_CONSTANT, value=(255, 255, 255))
                 for t in tiles]
        cv2.imwrite(str(out_dir / "topdown_sets.png"), np.hstack(tiles))
    return table


def _get(m: dict | None, *path: str) -> float | None:
    for p in path:
        if not isinstance(m, dict) or p not in m:
            return None
        m = m[p]
    return m


def format_ablation(rows: dict) -> str:
    """Returns a markdown table: registered ratio, accuracy and relation counts per set.

    Errors as ``panosfm eval`` states them: camera centres after a similarity
    (Umeyama) alignment, relative to the true trajectory's diameter; rotations
    after a rotation-only alignment; corner reprojection by the paper's protocol.
    """
    head = ("| set | registered | centre err. median (% diam.) | rotation err. median (deg) "
            "| corner reproj. mean (px) | line-surface median (m) | relations (o/p/j/f) |")
    lines = [head, "|" + "---|" * 7]

    def fmt(v, spec, k=1.0):
        return "n/a" if v is None else format(k * v, spec)

    for name, r in rows.items():
        m = r.get("metrics")
        rel = r["relations"]
        lines.append(
            f"| {name} | {100 * r['registered_ratio']:.1f} % "
            f"| {fmt(_get(m, 'center_error_rel', 'median'), '.2f', 100.0)} "
            f"| {fmt(_get(m, 'rotation_error_rotalign_deg', 'median'), '.3f')} "
            f"| {fmt(_get(m, 'reprojection_px', 'mean'), '.2f')} "
            f"| {fmt(_get(m, 'lines', 'distance_m', 'median'), '.3f')} "
            f"| {rel.get('orthogonal', 0)}/{rel.get('parallel', 0)}/{rel.get('junction', 0)}/{rel.get('floor', 0)} |")
    return "\n".join(lines)
