"""Metric sums of one batch of rollouts: every task and baseline, both metric variants, under one `jit`.

Sums and counts, never means, so batches add exactly on the host (`add_sums`) and ratios are formed once at the
end (`gpd_jax.evaluation.reduce`).
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from gpd_jax.decoding import RolloutOutput
from gpd_jax.evaluation.baselines import Trajectories, constant_velocity, follow_lanes
from gpd_jax.evaluation.keys import LANE_BASELINE, MAP_PERSISTENCE, TOKENIZER_CEILING
from gpd_jax.metrics import VARIANTS, map_metric_sums
from gpd_jax.metrics.agents import agent_sum_rows, agent_sum_table, name_agent_sums
from gpd_jax.scene import Scene, backward_difference
from gpd_jax.spec import ModelSpec
from gpd_jax.tasks import map_task_names


# ------------------------------------------------------------------------------------------------ scoring
def scored_mask(scene: Scene, spec: ModelSpec, weight) -> jax.Array:
    """bool[B, A]: the slots scored in each scenario (valid at the current frame; none in padded scenarios)."""
    return scene.valid[..., spec.current, :] & jnp.asarray(weight, bool)[..., None]


def current_speed(full: Scene, spec: ModelSpec) -> jax.Array:
    """f32[..., A] each model slot's speed (m/s) at the current frame, NaN where it is unknown.

    The stored-rate backward difference at the current stored frame c (the model's last history frame) to the
    slot's last valid frame before it (`gpd_jax.scene.backward_difference`): the velocity a `velocity_inputs`
    model is given (`Scene.with_velocity` at the stored rate) and the one `constant_velocity` extrapolates.
    Slots with no valid frame before c (first seen at the current frame) have no measured speed (NaN); with one
    history frame, none does.
    """
    return current_motion(full, spec)[0]


def current_motion(full: Scene, spec: ModelSpec) -> tuple[jax.Array, jax.Array]:
    """(`current_speed` f32[..., A], the unit direction of the same backward difference f32[..., A, 2]: zero
    where the speed is unknown or zero)."""
    c, a = spec.full_history - 1, spec.num_agents
    if c < 1:
        shape = full.valid.shape[:-2] + (a,)
        return jnp.full(shape, jnp.nan, jnp.float32), jnp.zeros(shape + (2,), jnp.float32)
    steps, frames, known = backward_difference(full.xy[..., :c + 1, :a, :], full.valid[..., :c + 1, :a])
    step, frames, known = steps[..., c, :, :], frames[..., c, :], known[..., c, :]
    length = jnp.linalg.norm(step, axis=-1)
    direction = jnp.where((known & (length > 0))[..., None], step / jnp.maximum(length, 1e-12)[..., None], 0.0)
    return (jnp.where(known, length / (frames * spec.stored_period_s), jnp.nan).astype(jnp.float32),
            direction.astype(jnp.float32))


def agent_sums(pred_xy, pred_heading, pred_valid, scene: Scene, scored, spec: ModelSpec, speed=None,
               direction=None) -> dict[str, Any]:
    """{variant: `agent_sum_table`(...) f32[R]} for both variants (`agent_rows` names the entries), scoring
    `scored: bool[..., A]` slots only; with `speed` (f32[..., A], `current_speed`) ADE / FDE split by motion at the
    current frame too, and with `direction` (f32[..., A, 2], `current_motion`) the moving class's along- and
    cross-track errors.

    Ground-truth validity is restricted to the scored slots, so unscored slots are not obstacles either.
    """
    gv = scene.valid & scored[..., None, :]
    return {v: agent_sum_table(pred_xy, pred_heading, scene.xy, gv, scene.size, num_history=spec.num_history,
                               pred_valid=pred_valid, eval_mask=scored, horizons=spec.horizons, variant=v,
                               dt=spec.frame_period_s, current_speed=speed, current_direction=direction)
            for v in VARIANTS}


def agent_rows(spec: ModelSpec, speed: bool = False, direction: bool = False) -> dict[str, tuple]:
    """{variant: `agent_sum_rows`}: what each entry of `agent_sums`' tables is (`speed` / `direction`: given)."""
    return {v: agent_sum_rows(spec.horizons, v, spec.frame_period_s, speed, direction) for v in VARIANTS}


def subsample_trajectories(xy, heading, valid, spec: ModelSpec):
    """Full-rate arrays [..., T_stored, A_stored, ...] -> the model's frames and slots."""
    fr = slice(0, spec.stored_frames_needed, spec.frame_stride)
    a = spec.num_agents
    return xy[..., fr, :a, :], heading[..., fr, :a], valid[..., fr, :a]


AGENT_BASELINES = ("constant_velocity", "constant_velocity_model_rate", "log_replay")  # + LANE_BASELINE with lanes


def baseline_names(with_lanes: bool) -> tuple[str, ...]:
    """The keys of `baseline_predictions`, in its order (`with_lanes`: the scenes carry lane polylines)."""
    return AGENT_BASELINES + ((LANE_BASELINE,) if with_lanes else ())


def baseline_predictions(full: Scene, spec: ModelSpec, with_lanes: bool = True
                         ) -> dict[str, tuple[jax.Array, jax.Array, jax.Array]]:
    """{baseline: (xy, heading, valid)} at the model's frames.

    `constant_velocity` is computed on the full-rate scene (its velocity is the last stored-frame difference,
    the most recent there is); `constant_velocity_model_rate` on the model's frames (the velocity between the
    last two model frames: exactly the information the model gets). They coincide when the stride is 1.
    Where the scenes carry their lane polylines (`Scene.polylines`, one leading batch dim) and `with_lanes`,
    also `constant_velocity_lanes`: `constant_velocity` moved along the lanes (`follow_lanes`); callers that only
    need constant velocity (training's validation) skip its lane walks with `with_lanes=False`. Keys in the order
    of `baseline_names`."""
    cv = constant_velocity(full, spec.full_history)
    log = subsample_trajectories(full.xy, full.heading, full.valid, spec)
    xy, heading, valid = log
    cvm = constant_velocity(full.replace(xy=xy, heading=heading, valid=valid), spec.num_history)
    out = dict(zip(AGENT_BASELINES, (subsample_trajectories(cv.xy, cv.heading, cv.valid, spec),
                                     (cvm.xy, cvm.heading, cvm.valid), log)))
    if with_lanes and full.polylines is not None:
        lanes = jax.vmap(lambda c, p, v: follow_lanes(c, spec.num_history, p, v))(
            Trajectories(*out["constant_velocity"]), full.polylines, full.polyline_valid)
        out[LANE_BASELINE] = (lanes.xy, lanes.heading, lanes.valid)
    return out


def map_sums(pred_points, pred_logits, gt_points, gt_valid, weight, count_exact_hits=False) -> dict[str, jax.Array]:
    """Map-metric sums per (scenario, task, future step), padded scenarios weighted out.

    Args:
      pred_points: f32[B, K, F, Q, P, 2] decoded lines of K map-generating tasks at F future frames.
      pred_logits: f32[B, K, F, Q]; gt_points: f32[B, F, L, P, 2]; gt_valid: bool[B, F, L]; weight: bool[B].
      count_exact_hits: as in `map_metric_sums` (False: the paper's F1, where a point exactly on the GT is a miss),
        or bool[K]: per task.

    Returns:
      {key: f32[B, K, F]} (`map_metric_sums` keys), zero in the padded scenarios.
    """
    b, k, f = pred_logits.shape[:3]
    gp = jnp.broadcast_to(gt_points[:, None], (b, k) + gt_points.shape[1:])
    gv = jnp.broadcast_to(gt_valid[:, None], (b, k) + gt_valid.shape[1:])
    flat = lambda x, n: x.reshape((b * k * f,) + x.shape[n:])  # noqa: E731
    if not isinstance(count_exact_hits, bool):
        count_exact_hits = flat(jnp.broadcast_to(jnp.asarray(count_exact_hits, bool)[None, :, None], (b, k, f)), 3)
    # One "step" per (scenario, task, frame): per-frame sums come back, which are weighted here.
    s = map_metric_sums(flat(pred_points, 3), flat(pred_logits, 3), flat(gp, 3), flat(gv, 3), step_axis=0,
                        count_exact_hits=count_exact_hits)
    w = jnp.asarray(weight, jnp.float32)[:, None, None]
    return {key: v.reshape(b, k, f) * w for key, v in s.items()}


def score_batch(pred: RolloutOutput, scene: Scene, full: Scene, weight, spec: ModelSpec,
                task_names: tuple[str, ...], map_pred=None, gt_lanes=None, kept_lanes=None,
                per_scenario: bool = False) -> dict[str, Any]:
    """Metric sums of one batch: every task and both baselines, both variants (host numpy, float32).

    One compiled call (`_score_stacked`: compiled once per batch shape) returns every metric stacked over the
    tasks and baselines; they are named here, on the host.

    With `per_scenario`, every leaf keeps a leading [B] (each scenario's own sums, which add up to the batch's):
    what per-group figures (e.g. per network layout) are summed from on the host.

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
    task_names = tuple(task_names)
    maps = map_task_names(task_names)
    if not (maps and map_pred is not None):
        map_pred = gt_lanes = kept_lanes = None
    s = jax.device_get(_score_stacked(pred, scene.replace(road=None), full, weight, spec, task_names, map_pred,
                                      gt_lanes, kept_lanes, per_scenario))
    # agents: f32[(B,) N, R] per variant over the tasks then the baselines; map: f32[(B,) slots, F] per key
    rows = agent_rows(spec, speed=True, direction=True)
    names = task_names + baseline_names(full.polylines is not None)
    agents = {name: {v: name_agent_sums(t[..., i, :], rows[v]) for v, t in s["agents"].items()}
              for i, name in enumerate(names)}
    out: dict[str, Any] = {"tasks": {name: agents[name] for name in task_names},
                           "baselines": {name: agents[name] for name in names[len(task_names):]},
                           "counts": s["counts"]}
    if map_pred is not None:
        slot = lambda j: jax.tree.map(lambda x: x[..., j, :], s["map"])  # noqa: E731
        for j, name in enumerate(maps):
            out["tasks"][name]["map"] = slot(j)
        if map_pred[0].shape[1] > len(maps):  # the logged tokens decoded: the map tokenizer's own reconstruction
            out["baselines"][TOKENIZER_CEILING] = {"map": slot(len(maps))}
        if kept_lanes is not None:  # after every slot of map_pred
            out["baselines"][MAP_PERSISTENCE] = {"map": slot(map_pred[0].shape[1])}
    return out


# Scored once per batch, so its compile time outweighs its run time: without LLVM's expensive passes it compiles
# about a third faster on the CPU (18 -> 13 s for the tiny test config) and gives bit-identical sums.
@functools.partial(jax.jit, static_argnames=("spec", "task_names", "per_scenario"),
                   compiler_options={"xla_llvm_disable_expensive_passes": True})
def _score_stacked(pred: RolloutOutput, scene: Scene, full: Scene, weight, spec: ModelSpec,
                   task_names: tuple[str, ...], map_pred=None, gt_lanes=None, kept_lanes=None,
                   per_scenario: bool = False) -> dict[str, Any]:
    """`score_batch`'s sums, stacked: {"agents": {variant: f32[(B,) N, R]} (`agent_sums`' tables of the N tasks
    then baselines, `baseline_names`), "map": {key: f32[(B,) Km (+1), F]} over the map tasks, the tokenizer
    ceiling and the persistence baseline, "counts": {...}}. Stacked, not split by name here: a slice per name and
    leaf is a kernel of its own (1400 of them were most of the compile time)."""
    scored = scored_mask(scene, spec, weight)
    # Tasks and baselines stacked on axis 1 and scored under one vmap (one traced metric graph, not K + 4).
    base = baseline_predictions(full, spec)
    stack = lambda i, x: jnp.concatenate([x] + [b[i][:, None] for b in base.values()], axis=1)  # noqa: E731
    preds = (stack(0, pred.xy), stack(1, pred.heading), stack(2, pred.valid))
    speed, direction = current_motion(full, spec)

    def agents(xy, hd, v, sc, sm, sp, dr):  # [b, N, ...] -> {variant: f32[N, R]}
        return jax.vmap(lambda x, h, m: agent_sums(x, h, m, sc, sm, spec, sp, dr), in_axes=1)(xy, hd, v)

    gt = scene.replace(map_tokens=None, map_valid=None, ego_pose=None, velocity=None)
    args = (*preds, gt, scored, speed, direction)
    if per_scenario:  # each scenario as a batch of one: [B, ...] -> [B, 1, ...] and vmapped over the B
        out: dict[str, Any] = {"agents": jax.vmap(agents)(*jax.tree.map(lambda a: a[:, None], args))}
    else:
        out = {"agents": agents(*args)}
    total = (lambda x: x) if per_scenario else (lambda x: jnp.sum(x, axis=0))  # noqa: E731
    if map_pred is not None:
        f = spec.max_horizon
        pts, logits = (x[:, :, :f] for x in map_pred)
        exact = [False] * pts.shape[1]
        if kept_lanes is not None:
            # Its lines are cut from the same polylines as the ground truth, so a line inside both windows is
            # bit-identical to it: the paper's F1 (which misses points at distance exactly 0) would score such a
            # perfect line 0. Exact hits count here.
            kp, kv = kept_lanes
            pts = jnp.concatenate([pts, kp[:, None, :f]], axis=1)
            logits = jnp.concatenate([logits, jnp.where(kv, 10.0, -10.0)[:, None, :f]], axis=1)
            exact.append(True)
        ms = map_sums(pts, logits, gt_lanes[0][:, :f], gt_lanes[1][:, :f], weight, jnp.asarray(exact))
        out["map"] = {key: total(v) for key, v in ms.items()}
    w = jnp.asarray(weight, bool)
    out["counts"] = {"scenarios": total(w.astype(jnp.float32)),
                     "scored_agents": total(jnp.sum(scored[:, 1:], axis=-1).astype(jnp.float32))}
    return out


def add_sums(acc, sums):
    """Exact host-side accumulation of sums pytrees (float64); `acc` may be None."""
    sums = jax.tree.map(lambda x: np.asarray(x, np.float64), jax.device_get(sums))
    return sums if acc is None else jax.tree.map(np.add, acc, sums)
