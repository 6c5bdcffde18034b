"""Realism of K sampled rollouts per scenario in the evaluation (`run_evaluation(..., samples=K)`, `rollout.py
--samples K`): the WOSAC-form metric of `gpd_jax.metrics.realism` for every task that generates agents or the
ego, and for the baselines on the same scenarios, agents and frames.

How the model's frames meet the 10 Hz features: a model that reads every `frame_stride`-th stored frame
predicts at its own rate; its rollouts are brought to the stored rate (`upsample_frames`: cubic Hermite
between model frames), the history frames are the log's stored frames, and the features are computed at the
stored rate (10 Hz) against the log at 10 Hz. Baselines are computed at the stored rate directly.

Who is scored (`evaluated`): in a task, the slots it generates (the ego, the agents) that are valid in the log at
the current frame; the slots a task takes from the log are replayed and only interact. The baselines are scored
on the agents (slots 1..) valid at the current frame, the traffic-simulation set:

* `constant_velocity`: K identical copies of constant velocity at the stored rate;
* `constant_velocity_lanes`: K copies of constant velocity along the lanes (where the scenes have lanes);
* `log`: K copies of the log itself (what a perfect single-future model scores; not 1: the histograms of one
  future are not the spread of all the futures the scene allows).

Both counting rules (`gpd_jax.metrics.realism.RULES`) are computed in the same compiled call: `metrics.json`
carries `"realism"` (the corrected rules) and `"realism_official"` (the official code's rules), each saying which.
Under the official rules an agent a rollout, a baseline or the log lacks at a future frame goes on at constant
velocity from its last state (`continue_missing`), as the official format has every agent at every frame.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from gpd_jax.evaluation.baselines import Trajectories, constant_velocity, follow_lanes
from gpd_jax.metrics.realism import (OFFICIAL_HISTORY_FRAMES, RULES, continue_missing, reduce_realism, rescore,
                                     scenario_realism, upsample_frames)
from gpd_jax.scene import TYPE_ID, Scene
from gpd_jax.spec import ModelSpec
from gpd_jax.tasks import generated

BASELINES = ("constant_velocity", "constant_velocity_lanes", "log")
RULES_NOTE = {
    "corrected": "counts only what a rollout has: simulated values where the rollout has the agent and the value "
                 "is finite; speeds and accelerations from the history on (docs/evaluation.md)",
    "official": "the official code's counting: agents valid at the current frame, every one present at every "
                "future frame (constant velocity where a rollout or the log lacks it), the NaN padding of the "
                "central differences in the top bin, the kinematic validity of the future frames alone, time to "
                "collision of vehicles only, ADE over the log's frames history included (docs/evaluation.md)",
}


def _evaluated(gen: Sequence[str], valid_now: jax.Array) -> jax.Array:
    """bool[..., A]: the generated slots (ego = slot 0, agents = 1..) valid at the current frame."""
    a = valid_now.shape[-1]
    slot = jnp.arange(a)
    mask = jnp.zeros(a, bool)
    if "ego" in gen:
        mask = mask | (slot == 0)
    if "agent" in gen:
        mask = mask | (slot > 0)
    return valid_now & mask


def group_names(task_names: Sequence[str], with_lanes: bool) -> list[str]:
    """The groups scored, in order: the tasks that generate agents or the ego, then the baselines."""
    tasks = [t for t in task_names if {"ego", "agent"} & set(generated(t))]
    return tasks + [b for b in BASELINES if with_lanes or b != "constant_velocity_lanes"]


def _groups(pred_xy, pred_heading, pred_valid, full: Scene, spec: ModelSpec, task_names: tuple[str, ...],
            with_lanes: bool):
    """Every group's K rollouts at the stored rate, stacked: `(xy f32[B, G, K, ts, A, 2], heading f32[B, G, K, ts,
    A], valid bool[B, G, K, ts, A])`, the agents each scores `evaluated bool[B, G, A]`, and the log
    (`Trajectories [B, ts, A]`); groups as `group_names` lists them."""
    k = pred_xy.shape[1]
    a, ts, h = spec.num_agents, spec.stored_frames_needed, spec.full_history
    log = Trajectories(full.xy[:, :ts, :a], full.heading[:, :ts, :a], full.valid[:, :ts, :a])
    valid_now = log.valid[:, h - 1]

    def stored_rate(xy, heading, valid):  # [B, K, T, A] at the model's frames -> [B, K, ts, A], log history
        xy, heading, valid = upsample_frames(xy, heading, valid, spec.frame_stride)
        keep = (jnp.arange(ts) < h)[None, None, :, None]
        return (jnp.where(keep[..., None], log.xy[:, None], xy), jnp.where(keep, log.heading[:, None], heading),
                jnp.where(keep, log.valid[:, None], valid))

    def copies(t: Trajectories):
        return tuple(jnp.broadcast_to(x[:, None], (x.shape[0], k) + x.shape[1:]) for x in (t.xy, t.heading, t.valid))

    sims, evaluated = [], []
    for n, task in enumerate(task_names):
        gen = generated(task)
        if "ego" in gen or "agent" in gen:
            sims.append(stored_rate(pred_xy[:, :, n], pred_heading[:, :, n], pred_valid[:, :, n]))
            evaluated.append(_evaluated(gen, valid_now))
    agents = _evaluated(("agent",), valid_now)
    cv_full = constant_velocity(full, h)
    cv = Trajectories(cv_full.xy[:, :ts, :a], cv_full.heading[:, :ts, :a], cv_full.valid[:, :ts, :a])
    baselines = {"constant_velocity": cv, "log": log}
    if with_lanes:
        baselines["constant_velocity_lanes"] = jax.vmap(lambda c, p, v: follow_lanes(c, h, p, v))(
            cv, full.polylines, full.polyline_valid)
    for name in BASELINES:
        if name in baselines:
            sims.append(copies(baselines[name]))
            evaluated.append(agents)
    stacked = tuple(jnp.stack([g[i] for g in sims], axis=1) for i in range(3))  # [B, G, K, ts, A, ...]
    return stacked, jnp.stack(evaluated, axis=1), log


@partial(jax.jit, static_argnames=("spec", "task_names", "config", "max_edge_segments", "with_lanes"))
def realism_batch(pred_xy, pred_heading, pred_valid, full: Scene, spec: ModelSpec, task_names: tuple[str, ...],
                  config: str, max_edge_segments: int | None, with_lanes: bool
                  ) -> dict[str, dict[str, dict[str, jax.Array]]]:
    """Per-scenario realism of a batch under each counting rule: `{rules: {group: {metric: f32[B]}}}` for every
    task and baseline.

    Args:
      pred_xy: f32[B, K, N, T, A, 2] K sampled rollouts of the N tasks at the model's frames (T, A: the model's);
        pred_heading: f32[B, K, N, T, A]; pred_valid: bool[B, K, N, T, A].
      full: the stored-rate scenes (`Scene [B, ...]` with `road`, and `polylines` for the lane baseline).
    """
    a, h = spec.num_agents, spec.full_history
    stacked, evaluated, log = _groups(pred_xy, pred_heading, pred_valid, full, spec, task_names, with_lanes)
    groups = group_names(task_names, with_lanes)
    size, road, agent_type = full.size[:, :a], full.road, full.agent_type[:, :a]
    # every group (task or baseline) through one vmapped metric: one compiled copy of it, whatever the groups
    # traffic lights (stores of format 2 with signals): states on the stored frames scored, with the lanes
    ts = spec.stored_frames_needed
    signals = None if full.signals is None else full.signals.replace(state=full.signals.state[:, :ts])
    lanes = None if signals is None or full.polylines is None else (full.polylines, full.polyline_valid)
    out = {}
    for rules in RULES:
        fn = lambda sx, sh, sv, ev, lx, lh, lv, sz, rd, at, sg, ln, r=rules: scenario_realism(  # noqa: E731
            sx, sh, sv, lx, lh, lv, sz, h, rd, ev, spec.stored_period_s, config, max_edge_segments, signals=sg,
            lanes=None if ln is None else ln[0], lane_valid=None if ln is None else ln[1], rules=r, agent_type=at)
        per_group = jax.vmap(fn, in_axes=(0, 0, 0, 0) + (None,) * 8)
        res = jax.vmap(per_group)(*stacked, evaluated, log.xy, log.heading, log.valid, size, road, agent_type,
                                  signals, lanes)
        out[rules] = {g: {m: v[:, i] for m, v in res.items()} for i, g in enumerate(groups)}
    return out


OFFICIAL_FUTURE_FRAMES = 80  # the official format: 11 history frames and 80 future frames at 10 Hz


@partial(jax.jit, static_argnames=("spec", "task_names", "with_lanes"))
def official_rollouts(pred_xy, pred_heading, pred_valid, full: Scene, spec: ModelSpec, task_names: tuple[str, ...],
                      with_lanes: bool):
    """Every group's rollouts as the official mode scores them, in the official format's frames: the future
    frames with every agent present (`continue_missing`), `(xy f32[B, G, K, 80, A, 2], heading f32[B, G, K, 80,
    A], evaluated bool[B, G, A])`, groups as `group_names`; what `write_official_scenes` hands the official code."""
    h = spec.full_history
    (xy, heading, valid), evaluated, _ = _groups(pred_xy, pred_heading, pred_valid, full, spec, task_names,
                                                 with_lanes)
    xy, heading = continue_missing(xy, heading, valid, h)
    fut = slice(h, h + OFFICIAL_FUTURE_FRAMES)
    return xy[:, :, :, fut], heading[:, :, :, fut], evaluated


SIGNAL_EXPORT_KEYS = ("official_lanes", "official_lane_valid", "signal_row", "signal_present", "signal_stop")


def write_official_scenes(directory: str, groups: Sequence[str], names: Sequence[str], parts: Sequence[dict],
                          history: int) -> list[str]:
    """One `.npz` per group in `directory` (`<group>.npz`), in the format `tests/conformance/run_official.py`
    reads, from the batches' `parts` (host arrays: "sub_xy" [B, G, K, 80, A, 2], "sub_heading", "evaluated"
    [B, G, A] from `official_rollouts`; "log_xy" [B, ts, A, 2], "log_heading", "log_valid", "size" [B, A, 2],
    "agent_type" [B, A]; "edges": per scene the `edge_polylines`; where the store has traffic signals,
    `official_signal_arrays` with "signal_state" [B, ts, S] and "signal_stop"), the log and the signal states cut
    to the official format's 11 history and 80 future frames. Returns the paths written."""
    cat = lambda key: np.concatenate([p[key] for p in parts])  # noqa: E731
    frames = slice(history - OFFICIAL_HISTORY_FRAMES, history + OFFICIAL_FUTURE_FRAMES)
    lines = [q for p in parts for q in p["edges"]]
    e, pts = max(1, max(len(x) for x in lines)), max([2] + [len(q) for x in lines for q in x])
    edges, edge_valid = np.zeros((len(lines), e, pts, 2), np.float32), np.zeros((len(lines), e, pts), bool)
    for i, x in enumerate(lines):
        for j, q in enumerate(x):
            edges[i, j, :len(q)], edge_valid[i, j, :len(q)] = q, True
    signals = {}  # traffic signals as the official mode hands them over (`official_signal_arrays`), where present
    if all("signal_row" in p for p in parts):
        signals = {k: cat(k) for k in SIGNAL_EXPORT_KEYS}
        signals["signal_state"] = cat("signal_state")[:, frames]
    os.makedirs(directory, exist_ok=True)
    paths = []
    for g, group in enumerate(groups):
        path = os.path.join(directory, f"{group}.npz")
        np.savez_compressed(
            path, names=np.array(list(names)), log_xy=cat("log_xy")[:, frames],
            log_heading=cat("log_heading")[:, frames], log_valid=cat("log_valid")[:, frames], size=cat("size"),
            is_vehicle=cat("agent_type") != TYPE_ID["other"],
            evaluated=cat("evaluated")[:, g], sub_xy=cat("sub_xy")[:, g], sub_heading=cat("sub_heading")[:, g],
            edges=edges, edge_valid=edge_valid, **signals)
        paths.append(path)
    return paths


RESULT_KEYS = {"corrected": "realism", "official": "realism_official"}  # rules -> metrics.json's key


MAX_LOG_OFFROAD = 0.05  # the most the log's own offroad rate may be on lane-union road edges for the map terms


def reduce_groups(per_scene: dict[str, dict[str, np.ndarray]], task_names: Sequence[str], samples: int,
                  config: str, has_road: bool, has_signals: bool = False,
                  edge_sources: Sequence[str] | None = None, rules: str = "corrected") -> dict:
    """metrics.json's "realism" (or "realism_official"): {"config", "rules", "samples", "weights", "left_out",
    "road_edges", "tasks": {task: figures}, "baselines": {name: figures}} from each scenario's figures
    (`{group: {metric: f64[n]}}`) under `rules`.

    `edge_sources`: per scene, where its road edges come from (`gpd_jax.geometry.edge_source_names`), counted in
    "road_edges". Where some scenes have only the lane union's outline ("lane_union": a map without road edges),
    the map terms stay only if the log keeps to that outline: the log's own offroad rate over those scenes at most
    `MAX_LOG_OFFROAD`; otherwise they are left out of every group (meta-metric renormalised, `rescore`) and
    "left_out" says why. "road_edges" holds the counts, the log's offroad rate there and the decision."""
    road_reason, edges = "no road geometry", {}
    if edge_sources is not None:
        src = np.asarray(edge_sources, dtype=object)
        edges = {"scenes": {str(k): int(c) for k, c in zip(*np.unique(src.astype(str), return_counts=True))}}
        lane_union = src == "lane_union"
        if has_road and lane_union.any() and "log" in per_scene:
            rate = float(np.nanmean(np.asarray(per_scene["log"]["offroad_rate"], np.float64)[lane_union]))
            edges["log_offroad_rate_on_lane_union"] = rate
            edges["map_terms"] = "kept" if rate <= MAX_LOG_OFFROAD else "left out"
            if not rate <= MAX_LOG_OFFROAD:
                has_road = False
                road_reason = (f"road edges are the lane union's outline (the map has none) and the log itself is "
                               f"off it for {rate:.1%} of agents (> {MAX_LOG_OFFROAD:.0%})")
                per_scene = {g: rescore(v, config, has_road, has_signals) for g, v in per_scene.items()}
    groups = {g: reduce_realism(v, config, has_road=has_road, has_signals=has_signals, road_reason=road_reason,
                                rules=rules) for g, v in per_scene.items()}
    first = next(iter(groups.values()))
    strip = lambda r: {k: v for k, v in r.items() if k not in ("config", "rules", "weights", "left_out")}
    return {"config": config, "rules": rules, "rules_note": RULES_NOTE[rules], "samples": samples,
            "weights": first["weights"], "left_out": first["left_out"], "road_edges": edges,
            "evaluated": "tasks: the slots each task generates, valid at the current frame; baselines: the agents "
                         "(slots 1..) valid at the current frame",
            "frame_rate": "rollouts at the model's frames are brought to the stored rate by cubic Hermite "
                          "interpolation (gpd_jax.metrics.realism.upsample_frames); features at the stored rate",
            "tasks": {t: strip(groups[t]) for t in task_names if t in groups},
            "baselines": {b: strip(groups[b]) for b in BASELINES if b in groups}}
