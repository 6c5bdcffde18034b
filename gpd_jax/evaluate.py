"""Multi-task evaluation of a GPD model on a data split: rollouts, metrics at 3 / 5 / 8 s, baselines, tables.

What `evaluate` does (the command line is `rollout.py` at the repository root):

1. Reads the first N scenarios of a split in store order (10 Hz, 101 frames, 33 slots) and gives the model
   `EvalSpec.view(scene)` (`scene.subsample(frame_stride, num_frames, num_agents)`, plus stored-rate velocities
   for a `velocity_inputs` model): the model's frame period is
   `frame_stride * frame_period_s` (1 s for configs/gpd_sumo.py, 0.1 s for the paper), and the horizons
   3, 5 and 8 s become that many model frames (6 / 10 / 16 at 2 Hz, 30 / 50 / 80 at 10 Hz), labelled "3s" ...
2. Map tokens come from the store where it has them (`map_valid`); otherwise the model's map tokenizer encodes
   the needed frames on the fly (rasterized polylines at each frame's `ego_pose`, as
   `python -m gpd_jax.map_tokenizer encode` does), so a freshly built split needs no encode step.
3. Every task runs in one compiled `rollout_tasks` call per batch of scenarios (the last batch is padded with
   copies of its last scenario, weighted out of every sum, so the shapes and the compile stay the same).
   `log_map="lanes"` re-encodes the logged map around the generated ego in tasks that take the map from the
   log but generate the ego (traffic simulation, motion planning) inside that compiled rollout; the default,
   "tokens", feeds the logged tokens (encoded around the logged ego), as the paper does.
4. Metrics per task (`score_batch`, jitted): ego ADE / FDE / collision rate where the task generates the ego,
   agent ADE / FDE / collision rate where it generates the agents, map F1 / precision / recall / lateral /
   Chamfer where it generates the map. Map metrics decode the predicted tokens of the future frames with the
   tokenizer's decoder and compare them, frame by frame in that frame's ego frame, with the ground-truth SLEDGE
   vector lanes of those frames (`gpd_jax.data.lanes`).
5. Baselines in the same run, on the same slots: constant velocity and log replay, computed on the full-rate
   (10 Hz) scene and then subsampled to the model's frames (so constant velocity takes its velocity from the
   last two 10 Hz history frames: more recent motion than a model at a lower frame rate ever sees), and
   `constant_velocity_model_rate`, whose velocity is the difference of the last two *model* frames (the same
   information the model gets; identical to the former at stride 1). Log replay has zero ADE / FDE; its
   collision rate is the log's own, the floor a generator should not exceed.
   Two map baselines where a task generates the map: `map_tokenizer_reconstruction` (the logged tokens
   decoded: the ceiling of any generated map) and `map_persistence` (the current frame's ground-truth lanes
   carried into each future frame with the logged ego pose: the map seen now, kept, never extended; the map
   analogue of constant velocity; its F1 counts points exactly on the ground truth as hits, which the paper's
   F1 does not). The paper's F1 aligns points by index along each matched line, so a lane cut by an earlier
   window edge scores low even where it lies on the right road.

**Scored agents**: those valid at the current frame (the last history frame), for the model and the baselines
alike. Slots not valid at the current frame are neither scored nor obstacles (they are removed from the
ground-truth validity before scoring). Slots a task takes from the log are not scored but stay obstacles for
the collision test of the generated ones.

**Variants** (`gpd_jax.metrics`): "paper" reproduces the official code's definitions (quirks included), "corrected"
normalises properly. Both are computed in every run; the chosen one fills the main keys (`ego_ade`,
`map_chamfer`, ...) and the other one is written beside it with its name as a suffix (`ego_ade_corrected` when
the main variant is "paper", `ego_ade_paper` when it is "corrected"). For the map only the Chamfer distance has
two definitions (paper: index-aligned squared distances, m^2; corrected: set-based, metres); F1, precision,
recall and lateral distance have the paper's single definition.

Aggregation is exact: every batch yields sums and counts (`agent_metric_sums`, `map_metric_sums`) which are
added in float64 on the host, and ratios are formed once at the end (`reduce_results`). Map metrics are formed
per future step and averaged over the steps up to the horizon, as the official code does.

metrics.json (written by rollout.py; NaN written as null)::

    {"checkpoint", "data", "split", "scenarios": n, "variant": "paper", "other_variant_suffix": "_corrected",
     "frame_period_s": 0.5, "frame_stride", "stored_frame_period_s", "num_history", "num_future", "num_agents",
     "horizons": {"3s": 6, "5s": 10, "8s": 16},                  # label -> model frames
     "scored_agents": "valid at the current frame", "num_scored_agents": ...,
     "task_generates": {task: ["ego", "agent", "map"]}, "map_tokens": {"from_store": n1, "encoded": n2},
     "log_map": "tokens" | "lanes",
     "temperature", "seed",
     "tasks": {task: {"3s": {"ego_ade", "ego_fde", "ego_collision",        # where the task generates the ego
                             "agent_ade", "agent_fde", "agent_collision",  # ... the agents
                             "<same>_corrected",                           # the other variant
                             "map_f1", "map_precision", "map_recall", "map_lateral",
                             "map_chamfer", "map_chamfer_corrected", "map_chamfer_corrected_skipped"}}},
     "baselines": {"constant_velocity": {"3s": {ego_* and agent_* as above}},
                   "constant_velocity_model_rate": {...}, "log_replay": {...},
                   "map_tokenizer_reconstruction": {"3s": {map_* as above}},  # logged tokens decoded
                   "map_persistence": {"3s": {map_* as above}}},  # current lanes carried forward
     "ratios": {"traffic_simulation_agent_ade_over_constant_velocity": {"3s": r, "5s": r, "8s": r},
                "traffic_simulation_agent_ade_over_constant_velocity_model_rate": {...}},
     "ratio_targets": {...: {"3s": 0.8, "5s": 0.75, "8s": 0.7}},
     "timing_s": {...}, "render": {...}}                           # render: only with --render

ADE / FDE in metres, collision rates in percent, map lateral distance in metres, map Chamfer in m^2 (paper) or
metres (corrected).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from gpd_jax.baselines import constant_velocity
from gpd_jax.metrics import (VARIANTS, agent_metric_sums, horizon_label, map_metric_sums, reduce_agent_metrics,
                             reduce_map_metrics)
from gpd_jax.rollout import LogLanes, RolloutOutput, rollout_tasks
from gpd_jax.scene import Scene
from gpd_jax.tasks import TASKS, make_tasks, resolve_task_names

HORIZONS_S = (3.0, 5.0, 8.0)
LOG_MAP_SOURCES = ("tokens", "lanes")  # what a task that takes the map from the log feeds (see `evaluate`)
BASELINE_NAMES = ("constant_velocity", "constant_velocity_model_rate", "log_replay")
# The logged map tokens decoded and scored like a map task: the ceiling any generated map can reach.
TOKENIZER_CEILING = "map_tokenizer_reconstruction"
# The current frame's ground-truth lanes carried into each future frame with the logged ego pose, nothing added:
# the map analogue of constant velocity (what a generator gets by keeping the map it sees and predicting nothing).
MAP_PERSISTENCE = "map_persistence"
MAP_BASELINES = (TOKENIZER_CEILING, MAP_PERSISTENCE)
SCORED_AGENTS = "valid at the current frame"
AGENT_METRICS = ("ade", "fde", "collision")
MAP_METRICS = ("map_f1", "map_precision", "map_recall", "map_lateral")
# The paper-table targets of the traffic-simulation agent ADE relative to constant velocity.
RATIO_TARGETS = {"3s": 0.8, "5s": 0.75, "8s": 0.7}
RATIO_KEY = "traffic_simulation_agent_ade_over_constant_velocity"
RATIO_KEY_MODEL_RATE = "traffic_simulation_agent_ade_over_constant_velocity_model_rate"


class EvalError(ValueError):
    """Bad evaluation input (missing data, unknown task, shape mismatch); the message names what and where."""


# ------------------------------------------------------------------------------------------------ spec
@dataclasses.dataclass(frozen=True)
class EvalSpec:
    """Static description of an evaluation (hashable: a jit static argument).

    num_frames, num_history, num_agents, num_map_tokens: the model's T, H, A, M.
    frame_stride: model frame k is stored frame k * stride; stored_period_s: seconds between stored frames.
    horizons: future model frames of each horizon (e.g. (6, 10, 16) at 2 Hz).
    velocity_inputs: whether the model's scenes carry instantaneous velocities (see `view`).
    """

    num_frames: int
    num_history: int
    num_agents: int
    num_map_tokens: int
    frame_stride: int = 1
    stored_period_s: float = 0.1
    horizons: tuple[int, ...] = (30, 50, 80)
    velocity_inputs: bool = False

    def view(self, full: Scene) -> Scene:
        """The model's frames and slots of a full-rate scene (with stored-rate velocities if the model takes them)."""
        period = self.stored_period_s if self.velocity_inputs else None
        return full.subsample(self.frame_stride, self.num_frames, self.num_agents, velocity_period_s=period)

    @property
    def frame_period_s(self) -> float:
        return self.frame_stride * self.stored_period_s

    @property
    def num_future(self) -> int:
        return self.num_frames - self.num_history

    @property
    def current(self) -> int:
        """The current frame (last history frame), model-rate index."""
        return self.num_history - 1

    @property
    def labels(self) -> tuple[str, ...]:
        return tuple(horizon_label(h, self.frame_period_s) for h in self.horizons)

    @property
    def max_horizon(self) -> int:
        return max(self.horizons)

    @property
    def stored_frames_needed(self) -> int:
        return self.frame_stride * (self.num_frames - 1) + 1

    @property
    def full_history(self) -> int:
        """History frames of the full-rate scene: stored frames [0, stride * (H - 1)] (the same current frame)."""
        return self.frame_stride * (self.num_history - 1) + 1

    def future_stored_frames(self, count: int | None = None) -> np.ndarray:
        """Stored-frame indices of the first `count` (default: max horizon) future model frames."""
        count = self.max_horizon if count is None else count
        return self.frame_stride * (self.num_history + np.arange(count))


def horizon_frames(seconds: Sequence[float], frame_period_s: float, num_future: int
                   ) -> tuple[tuple[int, ...], tuple[float, ...]]:
    """Horizons in seconds -> (model frame counts that fit in `num_future`, the seconds that do not fit).

    Raises EvalError if a horizon is not a whole number of frames or none fits.
    """
    frames, skipped = [], []
    for s in seconds:
        f = s / frame_period_s
        n = int(round(f))
        if n <= 0 or abs(f - n) > 1e-6:
            raise EvalError(f"horizon {s:g} s is not a positive whole number of model frames "
                            f"(frame period {frame_period_s:g} s)")
        (frames if n <= num_future else skipped).append(n if n <= num_future else s)
    if not frames:
        raise EvalError(f"no horizon among {', '.join(f'{s:g} s' for s in seconds)} fits in the model's "
                        f"{num_future} future frames ({num_future * frame_period_s:g} s)")
    return tuple(sorted(set(frames))), tuple(skipped)


def spec_from_config(config, horizons_s: Sequence[float] = HORIZONS_S) -> tuple[EvalSpec, tuple[float, ...]]:
    """The EvalSpec of a model config (its `model` and `data` sections) and the horizons (s) that do not fit."""
    m = config.model
    d = config.get("data") or {}
    stride = int(d.get("frame_stride", 1))
    period = float(d.get("frame_period_s", 0.1))
    if stride < 1:
        raise EvalError(f"config data.frame_stride must be >= 1, got {stride}")
    t, h = int(m.num_frames), int(m.num_history)
    frames, skipped = horizon_frames(horizons_s, stride * period, t - h)
    spec = EvalSpec(num_frames=t, num_history=h, num_agents=int(m.num_agents), num_map_tokens=int(m.num_map_tokens),
                    frame_stride=stride, stored_period_s=period, horizons=frames,
                    velocity_inputs=bool(m.get("velocity_inputs", False)))
    return spec, skipped


def generated(task: str) -> tuple[str, ...]:
    """What a task generates (and is scored on): a subset of ("ego", "agent", "map")."""
    map_log, ego_log, agents_log, hidden = TASKS[task]
    out = []
    if not ego_log:
        out.append("ego")
    if not (agents_log or hidden):
        out.append("agent")
    if not map_log:
        out.append("map")
    return tuple(out)


def map_task_names(task_names: Sequence[str]) -> tuple[str, ...]:
    return tuple(n for n in task_names if "map" in generated(n))


# ------------------------------------------------------------------------------------------------ scoring
def scored_mask(scene: Scene, spec: EvalSpec, weight) -> jax.Array:
    """bool[B, A]: the slots scored in each scenario (valid at the current frame; none in padded scenarios)."""
    return scene.valid[..., spec.current, :] & jnp.asarray(weight, bool)[..., None]


def agent_sums(pred_xy, pred_heading, pred_valid, scene: Scene, scored, spec: EvalSpec) -> dict[str, Any]:
    """{variant: agent_metric_sums(...)} for both variants, scoring `scored: bool[..., A]` slots only.

    Ground-truth validity is restricted to the scored slots, so unscored slots are not obstacles either.
    """
    gv = scene.valid & scored[..., None, :]
    return {v: agent_metric_sums(pred_xy, pred_heading, scene.xy, gv, scene.size, num_history=spec.num_history,
                                 pred_valid=pred_valid, eval_mask=scored, horizons=spec.horizons, variant=v,
                                 dt=spec.frame_period_s)
            for v in VARIANTS}


def subsample_trajectories(xy, heading, valid, spec: EvalSpec):
    """Full-rate arrays [..., T_stored, A_stored, ...] -> the model's frames and slots."""
    fr = slice(0, spec.stored_frames_needed, spec.frame_stride)
    a = spec.num_agents
    return xy[..., fr, :a, :], heading[..., fr, :a], valid[..., fr, :a]


def baseline_predictions(full: Scene, spec: EvalSpec) -> dict[str, tuple[jax.Array, jax.Array, jax.Array]]:
    """{baseline: (xy, heading, valid)} at the model's frames.

    `constant_velocity` is computed on the full-rate scene (its velocity is the last stored-frame difference,
    the most recent there is); `constant_velocity_model_rate` on the model's frames (the velocity between the
    last two model frames: exactly the information the model gets). They coincide when the stride is 1."""
    cv = constant_velocity(full, spec.full_history)
    log = subsample_trajectories(full.xy, full.heading, full.valid, spec)
    xy, heading, valid = log
    cvm = constant_velocity(full.replace(xy=xy, heading=heading, valid=valid), spec.num_history)
    return {"constant_velocity": subsample_trajectories(cv.xy, cv.heading, cv.valid, spec),
            "constant_velocity_model_rate": (cvm.xy, cvm.heading, cvm.valid),
            "log_replay": log}


def map_sums(pred_points, pred_logits, gt_points, gt_valid, weight, count_exact_hits: bool = False
             ) -> dict[str, jax.Array]:
    """Map-metric sums per (task, future step), padded scenarios weighted out.

    Args:
      pred_points: f32[B, K, F, Q, P, 2] decoded lines of K map-generating tasks at F future frames.
      pred_logits: f32[B, K, F, Q]; gt_points: f32[B, F, L, P, 2]; gt_valid: bool[B, F, L]; weight: bool[B].
      count_exact_hits: as in `map_metric_sums` (False: the paper's F1, where a point exactly on the GT is a miss).

    Returns:
      {key: f32[K, F]} (`map_metric_sums` keys) summed over the real scenarios.
    """
    b, k, f = pred_logits.shape[:3]
    gp = jnp.broadcast_to(gt_points[:, None], (b, k) + gt_points.shape[1:])
    gv = jnp.broadcast_to(gt_valid[:, None], (b, k) + gt_valid.shape[1:])
    flat = lambda x, n: x.reshape((b * k * f,) + x.shape[n:])
    # One "step" per (scenario, task, frame): per-frame sums come back, which are weighted and summed here.
    s = map_metric_sums(flat(pred_points, 3), flat(pred_logits, 3), flat(gp, 3), flat(gv, 3), step_axis=0,
                        count_exact_hits=count_exact_hits)
    w = jnp.asarray(weight, jnp.float32)[:, None, None]
    return {key: jnp.sum(v.reshape(b, k, f) * w, axis=0) for key, v in s.items()}


@functools.partial(jax.jit, static_argnames=("spec", "task_names"))
def score_batch(pred: RolloutOutput, scene: Scene, full: Scene, weight, spec: EvalSpec,
                task_names: tuple[str, ...], map_pred=None, gt_lanes=None, kept_lanes=None) -> dict[str, Any]:
    """Metric sums of one batch: every task and both baselines, both variants.

    Args:
      pred: rollout output with leading dims [B, K] (K = len(task_names)) at the model's frames.
      scene: the model-rate scenes [B] (`full.subsample(...)`); the ground truth.
      full: the full-rate scenes [B] (only xy / heading / valid / size are used), for the baselines.
      weight: bool[B], False for padding scenarios.
      map_pred: optional (points f32[B, Km, F, Q, P, 2], logits f32[B, Km, F, Q]) decoded predictions of the
        map-generating tasks (`map_task_names(task_names)` order) at the first F >= max horizon future frames;
        one more slot after them (Km = #map tasks + 1) holds the logged tokens decoded, scored as the
        `map_tokenizer_reconstruction` baseline (the ceiling any generated map can reach).
      gt_lanes: (points f32[B, F, L, P, 2], valid bool[B, F, L]) ground-truth lanes of the same frames.
      kept_lanes: optional, the same shapes: the current frame's lanes carried to those frames
        (`persistence_future_lanes`), scored as the `map_persistence` baseline.

    Returns:
      {"tasks": {name: {"paper": sums, "corrected": sums[, "map": {key: f32[F]}]}},
       "baselines": {name: {"paper": sums, "corrected": sums}}, "counts": {...}}.
    """
    scored = scored_mask(scene, spec, weight)
    # Tasks and baselines stacked on axis 1 and scored under one vmap (one traced metric graph, not K + 2).
    base = baseline_predictions(full, spec)
    stack = lambda i, x: jnp.concatenate([x] + [b[i][:, None] for b in base.values()], axis=1)
    preds = (stack(0, pred.xy), stack(1, pred.heading), stack(2, pred.valid))
    sums = jax.vmap(lambda xy, hd, v: agent_sums(xy, hd, v, scene, scored, spec), in_axes=1)(*preds)
    pick = lambda i: jax.tree.map(lambda x: x[i], sums)
    out: dict[str, Any] = {"tasks": {name: pick(k) for k, name in enumerate(task_names)},
                           "baselines": {name: pick(len(task_names) + j) for j, name in enumerate(base)}}
    maps = map_task_names(task_names)
    if maps and map_pred is not None:
        f = spec.max_horizon
        pts, logits = map_pred
        ms = map_sums(pts[:, :, :f], logits[:, :, :f], gt_lanes[0][:, :f], gt_lanes[1][:, :f], weight)
        for j, name in enumerate(maps):
            out["tasks"][name]["map"] = {key: v[j] for key, v in ms.items()}
        if pts.shape[1] > len(maps):  # the logged tokens decoded: the map tokenizer's own reconstruction
            out["baselines"][TOKENIZER_CEILING] = {"map": {key: v[len(maps)] for key, v in ms.items()}}
        if kept_lanes is not None:
            kp, kv = kept_lanes
            # Its lines are cut from the same polylines as the ground truth, so a line inside both windows is
            # bit-identical to it: the paper's F1 (which misses points at distance exactly 0) would score such a
            # perfect line 0. Exact hits count here.
            ms = map_sums(kp[:, None, :f], jnp.where(kv, 10.0, -10.0)[:, None, :f], gt_lanes[0][:, :f],
                          gt_lanes[1][:, :f], weight, count_exact_hits=True)
            out["baselines"][MAP_PERSISTENCE] = {"map": {key: v[0] for key, v in ms.items()}}
    w = jnp.asarray(weight, bool)
    out["counts"] = {"scenarios": jnp.sum(w).astype(jnp.float32),
                     "scored_agents": jnp.sum(scored[:, 1:]).astype(jnp.float32)}
    return out


def add_sums(acc, sums):
    """Exact host-side accumulation of sums pytrees (float64); `acc` may be None."""
    sums = jax.tree.map(lambda x: np.asarray(x, np.float64), jax.device_get(sums))
    return sums if acc is None else jax.tree.map(np.add, acc, sums)


# ------------------------------------------------------------------------------------------------ reduce
def _other(variant: str) -> str:
    return VARIANTS[1 - VARIANTS.index(variant)]


def _agent_entries(red: dict[str, dict[str, dict[str, float]]], label: str, groups: Sequence[str],
                   variant: str) -> dict[str, float]:
    other = _other(variant)
    d = {}
    for g in groups:
        for n in AGENT_METRICS:
            d[f"{g}_{n}"] = red[variant][label][f"{g}_{n}"]
    for g in groups:
        for n in AGENT_METRICS:
            d[f"{g}_{n}_{other}"] = red[other][label][f"{g}_{n}"]
    return d


def _map_entries(sums: dict[str, np.ndarray], h: int, variant: str) -> dict[str, float]:
    r = reduce_map_metrics({k: v[:h] for k, v in sums.items()})
    d = {k: r[k] for k in MAP_METRICS}
    cham = {"paper": r["map_chamfer"], "corrected": r["map_chamfer_corrected"]}
    d["map_chamfer"] = cham[variant]
    d[f"map_chamfer_{_other(variant)}"] = cham[_other(variant)]
    d["map_chamfer_corrected_skipped"] = r["map_chamfer_corrected_skipped"]
    return d


def reduce_results(acc: dict[str, Any], spec: EvalSpec, task_names: Sequence[str], variant: str = "paper"
                   ) -> dict[str, Any]:
    """Accumulated sums -> {"tasks": {task: {label: metrics}}, "baselines": {...}, "ratios": {...}}.

    Metrics a task does not generate are omitted; NaN where nothing was scored.
    """
    if variant not in VARIANTS:
        raise EvalError(f"variant must be one of {VARIANTS}, got {variant!r}")
    labels = spec.labels
    res: dict[str, Any] = {"tasks": {}, "baselines": {}}
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
    for name in BASELINE_NAMES:
        red = {v: reduce_agent_metrics(acc["baselines"][name][v]) for v in VARIANTS}
        res["baselines"][name] = {label: _agent_entries(red, label, ("ego", "agent"), variant) for label in labels}
    for name in MAP_BASELINES:
        if name in acc["baselines"]:
            s = acc["baselines"][name]["map"]
            res["baselines"][name] = {label: _map_entries(s, h, variant) for label, h in zip(labels, spec.horizons)}
    res["ratios"] = {}
    if "traffic_simulation" in res["tasks"]:
        ts = res["tasks"]["traffic_simulation"]
        for key, base in ((RATIO_KEY, "constant_velocity"), (RATIO_KEY_MODEL_RATE, "constant_velocity_model_rate")):
            cv = res["baselines"][base]
            res["ratios"][key] = {label: _ratio(ts[label]["agent_ade"], cv[label]["agent_ade"]) for label in labels}
    return res


def _ratio(a: float, b: float) -> float:
    if not (math.isfinite(a) and math.isfinite(b)) or b == 0:
        return float("nan")
    return a / b


# ------------------------------------------------------------------------------------------------ tables
def _fmt(v) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.3f}" if abs(v) < 100 else f"{v:.1f}"


def _title(name: str) -> str:
    return name.replace("_", " ")


def format_tables(results: dict[str, Any], variant: str = "paper") -> str:
    """Plain-text tables shaped like the paper's Table 1 (trajectories + map, tasks and baselines) and Table 2
    (map prediction), plus the traffic-simulation / constant-velocity ADE ratio line."""
    cols1 = [("ego ADE", "ego_ade"), ("ego FDE", "ego_fde"), ("ego Col%", "ego_collision"),
             ("ag ADE", "agent_ade"), ("ag FDE", "agent_fde"), ("ag Col%", "agent_collision"),
             ("map F1", "map_f1"), ("map Lat", "map_lateral"), ("map Ch", "map_chamfer")]
    cols2 = [("F1", "map_f1"), ("Prec", "map_precision"), ("Rec", "map_recall"), ("Lat", "map_lateral"),
             ("Ch", "map_chamfer"), ({"paper": "Ch paper", "corrected": "Ch corr"}[_other(variant)], f"map_chamfer_{_other(variant)}")]

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
    for n in BASELINE_NAMES:
        rows1.append((_title(n) + " (baseline):", None))
        rows1 += [(f"  {lb}", base[n][lb]) for lb in labels]
    out = table(f"Table 1 - trajectories and map ({variant} metrics; ADE/FDE m, collisions %, Ch m^2 paper / m "
                f"corrected)", rows1, cols1)
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
    for key, what in ((RATIO_KEY, "constant velocity (stored rate)"),
                      (RATIO_KEY_MODEL_RATE, "constant velocity (model rate)")):
        ratio = results.get("ratios", {}).get(key)
        if ratio:
            parts = [f"{lb} {_fmt(v)} (target <= {RATIO_TARGETS.get(lb, float('nan')):g})" for lb, v in ratio.items()]
            out += [f"traffic simulation agent ADE / {what} agent ADE: " + ", ".join(parts)]
    return "\n".join(out)


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


# ------------------------------------------------------------------------------------------------ driver
@functools.partial(jax.jit, static_argnames=("graphdef", "num_history", "temperature", "tok"))
def rollout_all(graphdef, state, scenes: Scene, tasks, key, num_history: int, temperature: float = 0.0,
                tok=None, tok_params=None, lanes: LogLanes | None = None) -> RolloutOutput:
    """`rollout_tasks` of the model `nnx.merge(graphdef, state)`, jitted (one compile per shape).

    With a map tokenizer `tok` (its `tok_params`) and the scenes' `lanes` [S, ...], logged map tokens of tasks
    that generate the ego are re-encoded around the generated ego (`gpd_jax.rollout`).
    """
    encoder = None if tok is None else tok.pose_encoder(tok_params)
    return rollout_tasks(nnx.merge(graphdef, state), scenes, tasks, key, num_history, temperature, lanes, encoder)


@functools.partial(jax.jit, static_argnames=("tok",))
def decode_map_tokens(tok, params, tokens):
    """Vector lanes of map tokens i32[..., M] with the tokenizer `tok`: (f32[..., Q, P, 2], f32[..., Q])."""
    return tok.decode(params, tokens)


@functools.partial(jax.jit, static_argnames=("tok",))
def encode_map_frames(tok, params, polylines, polyline_valid, poses):
    """Map tokens of every pose: polylines f32[B, L, P, 2], bool[B, L, P], poses f32[B, T, 3] -> i32[B, T, M]."""
    return jax.lax.map(lambda a: tok.encode_lanes(params, *a), (polylines, polyline_valid, poses))


def check_compatible(spec: EvalSpec, config, sample: dict[str, np.ndarray], where: str, tok=None) -> None:
    """Raises EvalError naming every mismatch between the model's shapes (and its map tokenizer's, if given)
    and a stored sample's."""
    t, a = sample["xy"].shape[0], sample["xy"].shape[1]
    m = sample["map_tokens"].shape[-1]
    problems = []
    if spec.stored_frames_needed > t:
        problems.append(f"the model needs {spec.stored_frames_needed} stored frames ({spec.num_frames} frames at "
                        f"stride {spec.frame_stride}) but the samples have {t}")
    if spec.num_agents > a:
        problems.append(f"the model has {spec.num_agents} agent slots but the samples have {a}")
    if spec.num_map_tokens != m:
        problems.append(f"the model has {spec.num_map_tokens} map tokens per frame but the store's frames have {m}")
    if tok is not None:
        if tok.num_tokens != spec.num_map_tokens:
            problems.append(f"the map tokenizer makes {tok.num_tokens} tokens per frame, the model takes "
                            f"{spec.num_map_tokens}")
        k_tok, k_model = int(tok.config.model.num_codes), int(config.model.codebook_size)
        if k_tok != k_model:
            problems.append(f"the map tokenizer has {k_tok} codes, the model's codebook_size is {k_model}")
    if problems:
        raise EvalError(f"model and data do not match ({where}): " + "; ".join(problems))


@dataclasses.dataclass
class Prepared:
    """What `preflight` checked and opened."""

    spec: EvalSpec
    task_names: tuple[str, ...]
    source: Any  # gpd_jax.data.loader.SplitSource (with polylines)
    num_scenarios: int
    skipped_horizons: tuple[float, ...]
    store_has_tokens: bool


def preflight(config, data_dir: str, split: str = "test", *, task_names: Sequence[str] = ("all",),
              num_scenarios: int | None = None, variant: str = "paper", horizons_s: Sequence[float] = HORIZONS_S,
              has_tokenizer: bool = True, tokenizer=None) -> Prepared:
    """Every check that needs only the config and the data (no model): raises EvalError naming the problem.

    Checks the variant, the task names, the horizons, that the split exists and is readable, that it has at
    least `num_scenarios` scenarios, that the model's frames / slots / map tokens fit the stored samples, and that
    a map tokenizer is available where one is needed (map tasks; stores without map tokens).
    """
    from gpd_jax.data.errors import DataError
    from gpd_jax.data.loader import SplitSource

    if variant not in VARIANTS:
        raise EvalError(f"variant must be one of {', '.join(VARIANTS)}, got {variant!r}")
    try:
        names = resolve_task_names(list(task_names) if not isinstance(task_names, str) else task_names)
    except KeyError as e:
        raise EvalError(str(e.args[0])) from None
    if not names:
        raise EvalError("no task given")
    spec, skipped = spec_from_config(config, horizons_s)
    split_dir = os.path.join(data_dir, split)
    if not os.path.isdir(data_dir):
        raise EvalError(f"data directory not found: {data_dir}")
    if not os.path.isdir(split_dir):
        from gpd_jax.data.store import list_splits
        raise EvalError(f"split {split!r} not found in {data_dir} "
                        f"(splits: {', '.join(list_splits(data_dir)) or 'none'})")
    try:
        src = SplitSource(data_dir, split, with_polylines=True)
        first = src[0]
    except DataError as e:
        raise EvalError(f"cannot read split {split!r}: {e}") from None
    available = len(src)
    n = available if num_scenarios is None else int(num_scenarios)
    if n < 1:
        raise EvalError(f"the number of scenarios must be >= 1, got {n}")
    if n > available:
        raise EvalError(f"{n} scenarios asked for, but {split_dir} has only {available}")
    check_compatible(spec, config, first, split_dir, tokenizer)
    has_tokenizer = has_tokenizer or tokenizer is not None
    model_frames = slice(0, spec.frame_stride * (spec.num_frames - 1) + 1, spec.frame_stride)
    store_has_tokens = bool(first["map_valid"][model_frames].all())
    maps = map_task_names(names)
    if maps and not has_tokenizer:
        raise EvalError(f"tasks {', '.join(maps)} generate the map, but the model has no map tokenizer to decode "
                        "it (config.model.map_tokenizer is empty); leave them out of the tasks")
    if not store_has_tokens and not has_tokenizer:
        raise EvalError(f"{split_dir} has no map tokens and the model has no map tokenizer to encode them "
                        "(config.model.map_tokenizer is empty); run `python -m gpd_jax.map_tokenizer encode` first")
    return Prepared(spec=spec, task_names=names, source=src, num_scenarios=n, skipped_horizons=skipped,
                    store_has_tokens=store_has_tokens)


def _records_to_scene(recs: list[dict[str, np.ndarray]]) -> tuple[Scene, np.ndarray, np.ndarray]:
    from gpd_jax.data.loader import to_scene

    batch = {k: np.stack([r[k] for r in recs]) for k in recs[0]}
    return to_scene(batch), batch["polylines"], batch["polyline_valid"]


def gt_future_lanes(polylines: np.ndarray, polyline_valid: np.ndarray, ego_pose_full: np.ndarray, spec: EvalSpec
                    ) -> tuple[np.ndarray, np.ndarray]:
    """SLEDGE vector lanes of the first max-horizon future model frames of every scenario (host numpy).

    polylines f32[B, L, P, 2], polyline_valid bool[B, L, P], ego_pose_full f32[B, T_stored, 3]
    -> (f32[B, F, 50, 20, 2], bool[B, F, 50]).
    """
    from gpd_jax.data.lanes import vector_lanes_frames

    fr = spec.future_stored_frames()
    res = [vector_lanes_frames(p, v, q[fr]) for p, v, q in zip(polylines, polyline_valid, ego_pose_full)]
    return np.stack([r[0] for r in res]), np.stack([r[1] for r in res])


def persistence_future_lanes(polylines: np.ndarray, polyline_valid: np.ndarray, ego_pose_full: np.ndarray,
                             spec: EvalSpec) -> tuple[np.ndarray, np.ndarray]:
    """The `map_persistence` baseline: the lanes visible at the current frame, in each of the frames of
    `gt_future_lanes` (logged ego poses; `gpd_jax.data.lanes.vector_lanes_carried`). Same shapes."""
    from gpd_jax.data.lanes import vector_lanes_carried

    fr, cur = spec.future_stored_frames(), spec.full_history - 1
    res = [vector_lanes_carried(p, v, q[cur], q[fr]) for p, v, q in zip(polylines, polyline_valid, ego_pose_full)]
    return np.stack([r[0] for r in res]), np.stack([r[1] for r in res])


@dataclasses.dataclass
class RenderItem:
    """What `gpd_jax.render` needs for one scenario (model-rate arrays, every task)."""

    index: int
    scenario_id: str
    pred: dict[str, np.ndarray]  # xy [K, T, A, 2], heading [K, T, A], valid [K, T, A], map_tokens [K, T, M]
    log: dict[str, np.ndarray]  # xy [T, A, 2], heading, valid, size [A, 2], agent_type, map_tokens [T, M], ego_pose


def evaluate(model, config, data_dir: str, split: str = "test", *, task_names: Sequence[str] = ("all",),
             num_scenarios: int | None = None, batch_size: int = 8, seed: int = 0, variant: str = "paper",
             tokenizer=None, horizons_s: Sequence[float] = HORIZONS_S, render_count: int = 0,
             log_map: str = "tokens", progress: bool = True, log: Callable[[str], None] = print
             ) -> tuple[dict[str, Any], list[RenderItem]]:
    """Rolls out every task on the first `num_scenarios` scenarios of a split and scores them.

    Args:
      model: a GPD model (`gpd_jax.checkpoint.load_model`); config: its full config.
      data_dir, split: the data store and split (read in store order, deterministic).
      task_names: task keys of `gpd_jax.tasks` or ["all"].
      num_scenarios: how many scenarios (None: the whole split).
      batch_size: scenarios per compiled rollout call (each runs every task).
      seed: PRNG seed of the rollout keys (used when the rollout temperature is > 0).
      variant: which metric variant fills the main keys ("paper" or "corrected").
      tokenizer: the model's map tokenizer (`load_tokenizer`), needed for map tasks and for stores without map
        tokens; None if the model has none.
      horizons_s: horizons in seconds (those longer than the model's future are skipped with a note).
      render_count: keep the arrays of the first this-many scenarios for `gpd_jax.render` (returned).
      log_map: "tokens" (the logged map tokens) or "lanes" (the log's lanes encoded around a generated ego;
        needs the tokenizer) for tasks that take the map from the log.

    Returns:
      (results dict as written to metrics.json, render items). Raises EvalError on bad input.
    """
    from tqdm import tqdm

    from gpd_jax.data.errors import DataError

    if log_map not in LOG_MAP_SOURCES:
        raise EvalError(f"log_map must be one of {LOG_MAP_SOURCES}, got {log_map!r}")
    if log_map == "lanes" and tokenizer is None:
        raise EvalError("log_map='lanes' re-encodes the log's lanes with the model's map tokenizer, and the model "
                        "has none (config.model.map_tokenizer is empty)")
    prep = preflight(config, data_dir, split, task_names=task_names, num_scenarios=num_scenarios, variant=variant,
                     horizons_s=horizons_s, has_tokenizer=tokenizer is not None, tokenizer=tokenizer)
    spec, names, src, n = prep.spec, prep.task_names, prep.source, prep.num_scenarios
    if prep.skipped_horizons:
        log(f"note: horizons {', '.join(f'{s:g} s' for s in prep.skipped_horizons)} exceed the model's future "
            f"({spec.num_future * spec.frame_period_s:g} s) and are skipped")
    split_dir = os.path.join(data_dir, split)
    maps = map_task_names(names)
    # Stored tokens made by another tokenizer mean other codes: those scenarios are encoded on the fly instead.
    foreign = np.zeros(len(src.counts), bool)
    if tokenizer is not None:
        from gpd_jax.data.store import foreign_map_token_shards
        foreign[foreign_map_token_shards(data_dir, split, tokenizer.fingerprint())] = True
    bs = max(1, min(int(batch_size), n))
    num_batches = -(-n // bs)
    temperature = float(config.get("rollout", {}).get("temperature", 0.0))
    graphdef, state = nnx.split(model)
    tasks = jax.tree.map(jnp.asarray, make_tasks(names, spec.num_map_tokens, spec.num_agents))
    key = jax.random.key(seed)
    meta_ids = _scenario_ids(src)

    acc = None
    render_items: list[RenderItem] = []
    n_store = n_encoded = 0
    t_roll = t_score = t_data = 0.0
    t0 = time.perf_counter()
    bar = tqdm(total=n, desc=f"rollout {len(names)} tasks", unit="scenario", disable=not progress)
    try:
        for b in range(num_batches):
            ta = time.perf_counter()
            idx = list(range(b * bs, min((b + 1) * bs, n)))
            real = len(idx)
            idx += [idx[-1]] * (bs - real)  # pad: same shapes, same compile
            weight = np.arange(bs) < real
            try:
                recs = [src[i] for i in idx]
            except DataError as e:
                raise EvalError(f"cannot read split {split!r}: {e}") from None
            full, polylines, poly_valid = _records_to_scene(recs)
            scene = spec.view(full)
            has = scene.map_valid.all(axis=-1) & ~foreign[np.searchsorted(src.offsets, idx, side="right") - 1]
            if not has[:real].all():
                if tokenizer is None:
                    raise EvalError(f"{split_dir} has no map tokens for some scenarios and the model has no map "
                                    "tokenizer to encode them")
                enc = np.asarray(encode_map_frames(tokenizer, tokenizer.params, polylines, poly_valid,
                                                   scene.ego_pose))
                scene = scene.replace(map_tokens=np.where(has[:, None, None], scene.map_tokens, enc).astype(np.int32),
                                      map_valid=np.ones_like(scene.map_valid))
            n_store += int(has[:real].sum())
            n_encoded += int((~has[:real]).sum())
            gt_lanes = kept_lanes = None
            if maps:
                gt_lanes = gt_future_lanes(polylines, poly_valid, full.ego_pose, spec)
                kept_lanes = persistence_future_lanes(polylines, poly_valid, full.ego_pose, spec)
            tb = time.perf_counter()
            t_data += tb - ta
            relane = {} if log_map == "tokens" else dict(
                tok=tokenizer, tok_params=tokenizer.params,
                lanes=LogLanes(jnp.asarray(polylines), jnp.asarray(poly_valid)))
            out = rollout_all(graphdef, state, jax.tree.map(jnp.asarray, scene), tasks, jax.random.fold_in(key, b),
                              spec.num_history, temperature, **relane)
            out = jax.block_until_ready(out)
            tc = time.perf_counter()
            t_roll += tc - tb
            map_pred = None
            if maps:
                mi = np.array([names.index(m_) for m_ in maps])
                fut = slice(spec.num_history, spec.num_history + spec.max_horizon)
                tokens = jnp.concatenate([out.map_tokens[:, mi, fut],
                                          jnp.asarray(scene.map_tokens)[:, None, fut]], axis=1)
                map_pred = decode_map_tokens(tokenizer, tokenizer.params, tokens)
            sums = score_batch(out, scene, _agents_only(full), weight, spec, names, map_pred, gt_lanes, kept_lanes)
            acc = add_sums(acc, sums)
            t_score += time.perf_counter() - tc
            for j in range(real):
                if idx[j] < render_count:
                    render_items.append(_render_item(idx[j], meta_ids, out, scene, j))
            bar.update(real)
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    if foreign.any():
        log(f"map tokens: {foreign.sum()} of {foreign.size} shards hold tokens of another tokenizer; not used")
    if n_encoded and n_store:
        source = f"read from the store for {n_store} scenarios, encoded on the fly for {n_encoded}"
    elif n_encoded:
        source = f"encoded on the fly with the model's map tokenizer (the store has none) for {n_encoded} scenarios"
    else:
        source = f"read from the store for {n_store} scenarios"
    log(f"map tokens: {source}")

    res = reduce_results(acc, spec, names, variant)
    results = {
        "variant": variant,
        "other_variant_suffix": f"_{_other(variant)}",
        "scenarios": n,
        "split": split,
        "data": os.path.abspath(data_dir),
        "frame_period_s": round(spec.frame_period_s, 9),
        "frame_stride": spec.frame_stride,
        "stored_frame_period_s": spec.stored_period_s,
        "num_history": spec.num_history,
        "num_future": spec.num_future,
        "num_agents": spec.num_agents,
        "horizons": {lb: h for lb, h in zip(spec.labels, spec.horizons)},
        "scored_agents": SCORED_AGENTS,
        "num_scored_agents": int(acc["counts"]["scored_agents"]),
        "task_generates": {t: list(generated(t)) for t in names},
        "map_tokens": {"from_store": n_store, "encoded": n_encoded},
        "log_map": log_map,
        "temperature": temperature,
        "seed": seed,
        **res,
        "ratio_targets": {k: RATIO_TARGETS for k in res["ratios"]},
        "timing_s": {"total": round(wall, 2), "rollout": round(t_roll, 2), "scoring": round(t_score, 2),
                     "data": round(t_data, 2), "batches": num_batches, "batch_size": bs},
    }
    return results, render_items


def _agents_only(full: Scene) -> Scene:
    """The full-rate scene without the fields the baselines do not use (smaller jit arguments)."""
    return jax.tree.map(jnp.asarray, full.replace(map_tokens=full.map_tokens[..., :1], lanes=None, lanes_valid=None))


def _scenario_ids(src) -> list[str]:
    import json

    ids: list[str] = []
    for p, c in zip(src.paths, src.counts):
        try:
            with open(os.path.join(p, "meta.json")) as f:
                got = list(json.load(f).get("scenario_ids", []))
        except (OSError, ValueError):
            got = []
        ids += (got + [""] * int(c))[: int(c)]
    return ids


def _render_item(i: int, ids: list[str], out: RolloutOutput, scene: Scene, j: int) -> RenderItem:
    pred = {k: np.asarray(getattr(out, k)[j]) for k in ("xy", "heading", "valid", "map_tokens")}
    log = {k: np.asarray(getattr(scene, k)[j]) for k in ("xy", "heading", "valid", "size", "agent_type",
                                                         "map_tokens", "ego_pose")}
    return RenderItem(index=i, scenario_id=ids[i] if i < len(ids) else "", pred=pred, log=log)
