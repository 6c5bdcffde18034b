"""Accumulated sums -> the metrics of `metrics.json` (per task, baseline and horizon; both variants; ratios)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from gpd_jax.evaluation.keys import (AGENT_METRICS, BASELINE_NAMES, LANE_BASELINE, MAP_BASELINES, MAP_CUTFREE_METRICS,
                                     MAP_METRICS, MOTION_RATIOS, MOTION_SPEED, MOTION_SPLIT, OPTIONAL_BASELINES,
                                     RATIO_KEY, RATIO_KEY_LANES, RATIO_KEY_MODEL_RATE)
from gpd_jax.metrics import (MOTION_CLASSES, STATIONARY_MPS, TRACK_COMPONENTS, VARIANTS, reduce_agent_metrics,
                             reduce_map_metrics)
from gpd_jax.spec import EvalError, ModelSpec
from gpd_jax.tasks import generated


# ------------------------------------------------------------------------------------------------ reduce
def other_variant(variant: str) -> str:
    """The metric variant that is not `variant`."""
    return VARIANTS[1 - VARIANTS.index(variant)]


def _agent_entries(red: dict[str, dict[str, dict[str, float]]], label: str, groups: Sequence[str],
                   variant: str) -> dict[str, float]:
    other = other_variant(variant)
    d = {}
    for g in groups:
        for n in AGENT_METRICS:
            d[f"{g}_{n}"] = red[variant][label][f"{g}_{n}"]
    for g in groups:
        for n in AGENT_METRICS:
            d[f"{g}_{n}_{other}"] = red[other][label][f"{g}_{n}"]
    return d


def _motion_entries(red: dict[str, dict[str, dict[str, float]]], label: str, groups: Sequence[str],
                    variant: str) -> dict[str, float]:
    """ADE / FDE (and the counts) of each motion class; {} when the sums have no motion split."""
    other = other_variant(variant)
    d: dict[str, float] = {}
    for g in groups:
        for k in MOTION_CLASSES:
            if f"{g}_n_{k}" not in red[variant][label]:
                return {}
            d[f"{g}_n_{k}"] = red[variant][label][f"{g}_n_{k}"]
            for n in ("ade", "fde"):
                d[f"{g}_{n}_{k}"] = red[variant][label][f"{g}_{n}_{k}"]
                d[f"{g}_{n}_{k}_{other}"] = red[other][label][f"{g}_{n}_{k}"]
        for n in ("ade", "fde"):
            for comp in TRACK_COMPONENTS:
                key = f"{g}_{n}_{comp}_moving"
                if key in red[variant][label]:
                    d[key], d[f"{key}_{other}"] = red[variant][label][key], red[other][label][key]
    return d


def _map_entries(sums: dict[str, np.ndarray], h: int, variant: str) -> dict[str, float]:
    r = reduce_map_metrics({k: v[:h] for k, v in sums.items()})
    d = {k: r[k] for k in MAP_METRICS}
    d.update({k: r[k] for k in MAP_CUTFREE_METRICS if k in r})
    cham = {"paper": r["map_chamfer"], "corrected": r["map_chamfer_corrected"]}
    d["map_chamfer"] = cham[variant]
    d[f"map_chamfer_{other_variant(variant)}"] = cham[other_variant(variant)]
    d["map_chamfer_corrected_skipped"] = r["map_chamfer_corrected_skipped"]
    return d


def reduce_results(acc: dict[str, Any], spec: ModelSpec, task_names: Sequence[str], variant: str = "paper"
                   ) -> dict[str, Any]:
    """Accumulated sums -> {"tasks": {task: {label: metrics}}, "baselines": {...}, "ratios": {...}}.

    Metrics a task does not generate are omitted; NaN where nothing was scored.
    """
    if variant not in VARIANTS:
        raise EvalError(f"variant must be one of {VARIANTS}, got {variant!r}")
    labels = spec.labels
    res: dict[str, Any] = {"tasks": {}, "baselines": {}}
    motion: dict[str, Any] = {"tasks": {}, "baselines": {}}
    for name in task_names:
        s = acc["tasks"][name]
        red = {v: reduce_agent_metrics(s[v]) for v in VARIANTS}
        groups = [g for g in ("ego", "agent") if g in generated(name)]
        res["tasks"][name] = {}
        for label, h in zip(labels, spec.horizons):
            d = _agent_entries(red, label, groups, variant)
            if "map" in generated(name) and "map" in s:
                d.update(_map_entries(s["map"], h, variant))
            res["tasks"][name][label] = d
        if groups:
            motion["tasks"][name] = {label: _motion_entries(red, label, groups, variant) for label in labels}
    for name in BASELINE_NAMES + tuple(b for b in OPTIONAL_BASELINES if b in acc["baselines"]):
        red = {v: reduce_agent_metrics(acc["baselines"][name][v]) for v in VARIANTS}
        res["baselines"][name] = {label: _agent_entries(red, label, ("ego", "agent"), variant) for label in labels}
        motion["baselines"][name] = {label: _motion_entries(red, label, ("ego", "agent"), variant)
                                     for label in labels}
    for name in MAP_BASELINES:
        if name in acc["baselines"]:
            s = acc["baselines"][name]["map"]
            res["baselines"][name] = {label: _map_entries(s, h, variant) for label, h in zip(labels, spec.horizons)}
    res["ratios"] = {}
    if "traffic_simulation" in res["tasks"]:
        ts = res["tasks"]["traffic_simulation"]
        for key, base in ((RATIO_KEY, "constant_velocity"), (RATIO_KEY_MODEL_RATE, "constant_velocity_model_rate"),
                          (RATIO_KEY_LANES, LANE_BASELINE)):
            if base not in res["baselines"]:
                continue
            cv = res["baselines"][base]
            res["ratios"][key] = {label: _ratio(ts[label]["agent_ade"], cv[label]["agent_ade"]) for label in labels}
    if all(d for part in ("tasks", "baselines") for per in motion[part].values() for d in per.values()):
        res[MOTION_SPLIT] = _motion_block(motion, labels)
    return res


def _motion_block(motion: dict[str, Any], labels: Sequence[str]) -> dict[str, Any]:
    """metrics.json's "motion_split": the split entries of every task and baseline, and the model / baseline
    ADE ratios of each group and motion class."""
    ratios: dict[str, Any] = {}
    for key, task, base in MOTION_RATIOS:
        if task not in motion["tasks"] or base not in motion["baselines"]:
            continue
        t, b = motion["tasks"][task], motion["baselines"][base]
        ratios[key] = {f"{g}_{k}": {lb: _ratio(t[lb][f"{g}_ade_{k}"], b[lb][f"{g}_ade_{k}"]) for lb in labels}
                       for g in ("agent", "ego") for k in MOTION_CLASSES if f"{g}_ade_{k}" in t[labels[0]]}
        ratios[key] |= {f"{g}_moving_{c}": {lb: _ratio(t[lb][f"{g}_ade_{c}_moving"], b[lb][f"{g}_ade_{c}_moving"])
                                            for lb in labels}
                        for g in ("agent", "ego") for c in TRACK_COMPONENTS if f"{g}_ade_{c}_moving" in t[labels[0]]}
    return {"stationary_below_mps": STATIONARY_MPS, "speed": MOTION_SPEED, "classes": list(MOTION_CLASSES),
            "track_components": {"along": "moving entities' |error . u|, u the unit direction of the current "
                                          "frame's speed difference (pace: braking, starting)",
                                 "cross": "|error x u| (path: turns, curves, lane changes)"},
            "tasks": motion["tasks"], "baselines": motion["baselines"], "ratios": ratios}


def _ratio(a: float, b: float) -> float:
    if not (math.isfinite(a) and math.isfinite(b)) or b == 0:
        return float("nan")
    return a / b
