"""Plain-text tables shaped like the paper's (Table 1: trajectories and map; Table 2: map prediction) and strict
JSON of the results."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from gpd_jax.evaluation.keys import (BASELINE_NAMES, MAP_PERSISTENCE, MOTION_RATIOS, MOTION_SPLIT, OPTIONAL_BASELINES,
                                     RATIO_KEY, RATIO_KEY_LANES, RATIO_KEY_MODEL_RATE, RATIO_TARGETS,
                                     TOKENIZER_CEILING)

MOTION_RATIO_KEY = MOTION_RATIOS[0][0]  # traffic simulation over constant velocity (stored rate)
from gpd_jax.evaluation.reduce import other_variant
from gpd_jax.tasks import generated


# ------------------------------------------------------------------------------------------------ tables
def _fmt(v) -> str:
    if isinstance(v, int):
        return str(v)
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.3f}" if abs(v) < 100 else f"{v:.1f}"


def _title(name: str) -> str:
    return name.replace("_", " ")


def format_tables(results: dict[str, Any], variant: str = "paper") -> str:
    """Plain-text tables shaped like the paper's Table 1 (trajectories + map, tasks and baselines) and Table 2
    (map prediction), plus the traffic-simulation / constant-velocity ADE ratio line."""
    cols1 = [("ego ADE", "ego_ade"), ("ego FDE", "ego_fde"), ("ego Col%", "ego_collision"),
             ("ego Cf%", "ego_collision_frames"), ("ag ADE", "agent_ade"), ("ag FDE", "agent_fde"),
             ("ag Col%", "agent_collision"), ("ag Cf%", "agent_collision_frames"),
             ("map F1", "map_f1"), ("map Lat", "map_lateral"), ("map Ch", "map_chamfer")]
    cols2 = [("F1", "map_f1"), ("Prec", "map_precision"), ("Rec", "map_recall"), ("F1 cutfr", "map_f1_cutfree"),
             ("F1 cfdir", "map_f1_cutfree_directed"), ("Lat", "map_lateral"),
             ("Ch", "map_chamfer"), ({"paper": "Ch paper", "corrected": "Ch corr"}[other_variant(variant)], f"map_chamfer_{other_variant(variant)}")]

    def table(title, rows: list[tuple[str, dict]], cols) -> list[str]:
        w0 = max([8] + [len(r) for r, _ in rows]) + 2
        head = "".join(f"{c:>9}" for c, _ in cols)
        lines = [title, f"{'':<{w0}}{head}", "-" * (w0 + len(head))]
        for r, d in rows:
            lines.append(f"{r:<{w0}}" + "".join(f"{_fmt(d.get(k)) if d is not None else '':>9}" for _, k in cols))
        return lines

    tasks, base = results["tasks"], results["baselines"]
    traj = [n for n in tasks if any(g in generated(n) for g in ("ego", "agent"))]
    maps = [n for n in tasks if generated(n) == ("map",)]
    labels = list(base[BASELINE_NAMES[0]].keys())
    rows1: list[tuple[str, Any]] = []
    for n in traj:
        rows1.append((_title(n) + ":", None))
        rows1 += [(f"  {lb}", tasks[n][lb]) for lb in labels]
    for n in BASELINE_NAMES + tuple(b for b in OPTIONAL_BASELINES if b in base):
        rows1.append((_title(n) + " (baseline):", None))
        rows1 += [(f"  {lb}", base[n][lb]) for lb in labels]
    out = table(f"Table 1 - trajectories and map ({variant} metrics; ADE/FDE m; Col% = share of agents with a "
                f"collision within the horizon, Cf% = per-frame rate; Ch m^2 paper / m corrected)", rows1, cols1)
    if maps:
        rows2: list[tuple[str, Any]] = []
        for n in maps:
            rows2.append((_title(n) + ":", None))
            rows2 += [(f"  {lb}", tasks[n][lb]) for lb in labels]
        for name, title in ((TOKENIZER_CEILING, "logged tokens decoded (tokenizer ceiling):"),
                            (MAP_PERSISTENCE, "current lanes carried forward (map persistence):")):
            if name in base:
                rows2.append((title, None))
                rows2 += [(f"  {lb}", base[name][lb]) for lb in labels]
        out += [""] + table(f"Table 2 - map prediction ({variant} Chamfer in 'Ch')", rows2, cols2)
    for key, what, targeted in ((RATIO_KEY, "constant velocity (stored rate)", True),
                                (RATIO_KEY_MODEL_RATE, "constant velocity (model rate)", True),
                                (RATIO_KEY_LANES, "constant velocity along the lanes", False)):
        ratio = results.get("ratios", {}).get(key)
        if ratio:
            parts = [f"{lb} {_fmt(v)}" + (f" (target <= {RATIO_TARGETS.get(lb, float('nan')):g})" if targeted else "")
                     for lb, v in ratio.items()]
            out += [f"traffic simulation agent ADE / {what} agent ADE: " + ", ".join(parts)]
    for key in ("realism", "realism_official"):
        if results.get(key):
            out += [""] + format_realism_table(results[key])
    if results.get(MOTION_SPLIT):
        out += [""] + format_motion_table(results, variant)
    if results.get("by_layout"):
        out += [""] + format_layout_table(results)
    return "\n".join(out)


def format_realism_table(realism: dict[str, Any]) -> list[str]:
    """The realism table (`results["realism"]` or `["realism_official"]`): meta-metric, its buckets and terms,
    minADE, per task and baseline, and the counting rules it was computed under."""
    cols = [("meta", "metametric"), ("kinem", "kinematic"), ("inter", "interactive"), ("map", "map_based"),
            ("speed", "linear_speed_likelihood"), ("accel", "linear_acceleration_likelihood"),
            ("yawrate", "angular_speed_likelihood"), ("yawacc", "angular_acceleration_likelihood"),
            ("dist", "distance_to_nearest_object_likelihood"), ("coll", "collision_indication_likelihood"),
            ("ttc", "time_to_collision_likelihood"), ("edge", "distance_to_road_edge_likelihood"),
            ("offroad", "offroad_indication_likelihood"), ("minADE", "min_ade"), ("coll%", "collision_rate"),
            ("off%", "offroad_rate")]
    rows = [(_title(t), d) for t, d in realism["tasks"].items()]
    rows += [(_title(b) + " (baseline)", d) for b, d in realism["baselines"].items()]
    w0 = max([8] + [len(r) for r, _ in rows]) + 2
    head = "".join(f"{c:>9}" for c, _ in cols)
    left = "; ".join(f"{k} left out ({why})" for k, why in realism["left_out"].items())
    lines = [f"Realism, {realism.get('rules', 'corrected')} rules ({realism['samples']} rollouts per scenario, "
             f"WOSAC {realism['config']} form, weights "
             f"renormalised{'; ' + left if left else ''}; minADE m; coll% / off% = share of rollouts x agents)",
             f"{'':<{w0}}{head}", "-" * (w0 + len(head))]
    for r, d in rows:
        vals = {**d, "collision_rate": 100 * d.get("collision_rate", float("nan")),
                "offroad_rate": 100 * d.get("offroad_rate", float("nan"))}
        lines.append(f"{r:<{w0}}" + "".join(f"{_fmt(vals.get(k)):>9}" for _, k in cols))
    return lines


def format_motion_table(results: dict[str, Any], variant: str = "paper", task: str = "traffic_simulation"
                        ) -> list[str]:
    """Markdown table of `task`'s agent and ego ADE split by motion at the current frame, against both
    constant-velocity baselines: n at the first horizon, ADE at every horizon, and the ratios. Rows of
    unknown speed only where there are any. [] when the task or the split is missing."""
    ms = results.get(MOTION_SPLIT) or {}
    t = ms.get("tasks", {}).get(task)
    cv, cvm = (ms.get("baselines", {}).get(b) for b in ("constant_velocity", "constant_velocity_model_rate"))
    if not t or not cv or not cvm:
        return []
    labels = list(t)
    secs = " / ".join(lb.rstrip("s") for lb in labels) + " s"
    row = lambda d, key: " / ".join(f"{d[lb].get(key, float('nan')):.2f}" if _finite(d[lb].get(key)) else "-"
                                    for lb in labels)
    ratio = lambda key, b: " / ".join(f"{t[lb][key] / b[lb][key]:.2f}"
                                      if _finite(t[lb].get(key)) and _finite(b[lb].get(key)) and b[lb][key] else "-"
                                      for lb in labels)
    lines = [f"Motion at the current frame ({_title(task)} against constant velocity, {variant} ADE; speed: the "
             f"stored-rate difference of the last two frames, stationary below {ms['stationary_below_mps']:g} m/s)",
             f"| | n at {labels[0].rstrip('s')} s | model {secs} (m) | constant velocity (m) | model / CV | "
             "CV model rate (m) | model / CV model rate |",
             "|---|---|---|---|---|---|---|"]
    for g, gname in (("agent", "agents"), ("ego", "ego")):
        for k in ms["classes"]:
            key = f"{g}_ade_{k}"
            if key not in t[labels[0]]:
                continue
            n = t[labels[0]][f"{g}_n_{k}"]
            if k == "speed_unknown" and not any(t[lb][f"{g}_n_{k}"] for lb in labels):
                continue
            name = {"stationary": f"stationary (< {ms['stationary_below_mps']:g} m/s)", "moving": "moving",
                    "speed_unknown": "speed unknown"}[k]
            lines.append(f"| {gname} {name} | {n} | {row(t, key)} | {row(cv, key)} | {ratio(key, cv)} | "
                         f"{row(cvm, key)} | {ratio(key, cvm)} |")
            for comp, what in (("along", "along-track"), ("cross", "cross-track")):
                key = f"{g}_ade_{comp}_{k}"
                if key in t[labels[0]]:
                    lines.append(f"| · {what} | | {row(t, key)} | {row(cv, key)} | {ratio(key, cv)} | "
                                 f"{row(cvm, key)} | {ratio(key, cvm)} |")
    return lines


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def format_layout_table(results: dict[str, Any]) -> list[str]:
    """Per road-network layout (and overall): the traffic-simulation agents against constant velocity (all, and
    stationary / moving at the current frame), the paper's collision rate of the generated agents and of the log
    itself, and scene generation's map F1 against map persistence, at the longest horizon (the map at the
    shortest)."""
    rows = [("all", results)] + list(results["by_layout"].items())
    labels = list(results["baselines"]["constant_velocity"])
    lo, hi = labels[0], labels[-1]
    get = lambda d, *ks: _dig(d, *ks)
    cols = [("scn", lambda r: r.get("scenarios")),
            (f"TS ADE {hi}", lambda r: get(r, "tasks", "traffic_simulation", hi, "agent_ade")),
            (f"CV ADE {hi}", lambda r: get(r, "baselines", "constant_velocity", hi, "agent_ade")),
            (f"TS/CV {hi}", lambda r: get(r, "ratios", RATIO_KEY, hi)),
            (f"stat/CV {hi}", lambda r: get(r, MOTION_SPLIT, "ratios", MOTION_RATIO_KEY, "agent_stationary", hi)),
            (f"mov/CV {hi}", lambda r: get(r, MOTION_SPLIT, "ratios", MOTION_RATIO_KEY, "agent_moving", hi)),
            (f"TS Col% {hi}", lambda r: get(r, "tasks", "traffic_simulation", hi, "agent_collision")),
            (f"log Col% {hi}", lambda r: get(r, "baselines", "log_replay", hi, "agent_collision")),
            (f"SG F1 {lo}", lambda r: get(r, "tasks", "scene_generation", lo, "map_f1")),
            (f"keep F1 {lo}", lambda r: get(r, "baselines", MAP_PERSISTENCE, lo, "map_f1"))]
    w0 = max(8, *(len(n) for n, _ in rows)) + 2
    head = "".join(f"{c:>13}" for c, _ in cols)
    lines = ["Per road-network layout (TS: traffic simulation agents, CV: constant velocity, log: log replay, "
             "SG: scene generation, keep: map persistence; Col% = share of agents with a collision; stat / mov: "
             "TS / CV for agents stationary / moving at the current frame)",
             f"{'':<{w0}}{head}", "-" * (w0 + len(head))]
    for name, r in rows:
        lines.append(f"{name:<{w0}}" + "".join(f"{_fmt(f(r)):>13}" for _, f in cols))
    return lines


def _dig(d, *keys):
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def to_json_compatible(x):
    """NaN / inf -> None, numpy scalars -> Python numbers, tuples -> lists (for strict JSON)."""
    if isinstance(x, dict):
        return {str(k): to_json_compatible(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_json_compatible(v) for v in x]
    if isinstance(x, (np.floating, float)):
        x = float(x)
        return x if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x
