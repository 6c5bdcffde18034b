"""Closed-loop supervised fine-tuning: the model trained at the states its own rollouts reach (CAT-K's recipe).

A model trained one step at a time on logged histories (teacher forcing) meets, in its own rollouts, states it never
saw: it drifts, leaves the road and runs into other agents. CAT-K (closest among top-K) trains it where its rollouts
go while keeping the targets meaningful: roll the model out from the logged history (traffic simulation: the map
from the log, ego and agents generated) and, at every future frame, of the model's K most likely next states keep
the one closest to the log. The reached sequence stays near the log (so the log's next state is still the right
target from it) but is the model's own (its errors, its discretisation). The loss is then taken at the states
reached: a teacher-forced pass over the reached frames whose targets are the log's next frames, i.e. from where the
rollout is, return toward the log.

Here the candidates are the top-K cells of the sampling head's categorical (`model.agent_bins`: cells of 0.5 m over
the next 1 Hz position's offset from the regressed one), each with its centre's heading and velocity (`Modes`), so
the choice is deterministic (no key: a resumed run is the same run). Validity follows the log, agents that appear
enter at their logged state (as in `gpd_jax.training.step.free_running_inputs`), and the map tokens are the log's.

The rollout is the cached one every evaluation uses (`gpd_jax.decoding.prefill` / `advance`), run with frozen
(stop-gradient) parameters inside the same compiled train step as the loss, vmapped over the batch: one
`jax.lax.scan` over the future frames. `train.closed_loop_top_k` = K > 0 switches it on
(`gpd_jax.training.step.loss_terms`).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
from flax import nnx

from gpd_jax.decoding import (DecodeState, Frame, advance, context_at, given_inputs, prefill, sample_agents,
                              top_cells)
from gpd_jax.geometry import RoadGeometry, on_road
from gpd_jax.metrics.realism import nearest_object_distance
from gpd_jax.model import GPD, LaneContext, Modes
from gpd_jax.options import Sampling
from gpd_jax.scene import Scene
from gpd_jax.tasks import make_task

# (the sampling head's Modes of frame t [A, ...], the given log frames [T, ...], t, own bool[A]) -> frame t's Frame
Chooser = Callable[[Modes, Frame, jax.Array, jax.Array], Frame]


def top_k_candidates(modes: Modes, k: int):
    """The `k` most likely cells of a sampling head's next-state distribution of one frame (leading dims [A]).

    Returns (xy f32[A, k, 2], heading f32[A, k], velocity f32[A, k, 2] or None): each cell's centre."""
    top = top_cells(modes, k)
    return top.xy, top.heading, top.velocity


def closest_of_k(candidates_xy: jax.Array, target_xy: jax.Array) -> jax.Array:
    """Index i32[A] of the candidate (f32[A, K, 2]) nearest each target position (f32[A, 2])."""
    return jnp.argmin(jnp.sum(jnp.square(candidates_xy - target_xy[:, None, :]), -1), axis=-1)


def closest_frame(modes: Modes, log: Frame, t, own: jax.Array, k: int) -> Frame:
    """Frame t's inputs of a closed-loop rollout: where `own` (bool[A]: the agent is valid at t and t-1), the
    candidate of the top `k` cells nearest the log's state at t (xy, heading, velocity of that cell); elsewhere
    the log's frame t. `modes`: the prediction of frame t (leading dims [A]); `log`: the given frames (leading T)."""
    xy, heading, vel = top_k_candidates(modes, k)
    pick = closest_of_k(xy, log.xy[t])
    choose = lambda a: jnp.take_along_axis(a, pick.reshape((-1, 1) + (1,) * (a.ndim - 2)), axis=1)[:, 0]  # noqa: E731
    xy_t = jnp.where(own[:, None], choose(xy), log.xy[t])
    heading_t = jnp.where(own, choose(heading), log.heading[t])
    vel_t = log.velocity[t] if vel is None else jnp.where(own[:, None], choose(vel), log.velocity[t])
    return Frame(xy=xy_t, heading=heading_t, valid=log.valid[t], valid_logit=log.valid_logit[t],
                 map_tokens=log.map_tokens[t], velocity=vel_t)


def _frozen(model: GPD) -> GPD:
    """`model` behind a stop-gradient: what a rollout that only generates training inputs runs."""
    graphdef, state = nnx.split(model)
    return nnx.merge(graphdef, jax.lax.stop_gradient(state))


def own_rollout(model: GPD, scene: Scene, num_history: int, choose: Chooser,
                lanes: LaneContext | None = None) -> Frame:
    """The model's own traffic-simulation rollout of `scene` (unbatched: map from the log, ego and agents generated,
    validity the log's), on frozen parameters, each future frame's agent states picked by `choose(modes, log, t,
    own)` (`closest_frame`, `sampled_frame`: own bool[A] the agents valid at t and t-1 in the log) from the sampling
    head's prediction of that frame. Returns the `Frame`s [T, ...]: the log's history, then the chosen frames."""
    if model.mode_head is None:
        raise ValueError("closed-loop fine-tuning (train.closed_loop_top_k, train.reward_samples) rolls out the "
                         "sampling head's cells: set model.agent_bins > 0")
    t_total, h = scene.num_frames, num_history
    frozen = _frozen(model)
    task = make_task("traffic_simulation", scene.map_tokens.shape[-1], scene.xy.shape[-2])
    log = given_inputs(frozen, scene, task, num_history=h).log

    def step(carry: DecodeState, t):
        own = log.valid[t] & log.valid[t - 1]
        frame = choose(jax.tree.map(lambda a: a[0], carry.pred.modes), log, t, own)
        return advance(frozen, carry, frame, t, context_at(lanes, jnp.minimum(t, t_total - 2))), frame

    # the last frame's advance is not needed, but one scan keeps one body (the cache holds all T frames)
    _, frames = jax.lax.scan(step, prefill(frozen, log, h, t_total, lanes), jnp.arange(h, t_total))
    cat = lambda a, b: jax.lax.stop_gradient(jnp.concatenate([a[:h], b.astype(a.dtype)], 0))  # noqa: E731
    return jax.tree.map(cat, log, frames)


def rollout_inputs(model: GPD, scene: Scene, frames: Frame):
    """Frames [0, T-1) of a rollout as a teacher-forced pass's inputs (xy, heading, velocity or None, map tokens),
    as `gpd_jax.training.step.free_running_inputs` returns them."""
    vel = None if model.input_velocity(scene.velocity) is None else frames.velocity[:-1]
    return frames.xy[:-1], frames.heading[:-1], vel, scene.map_tokens[:-1]


def closed_loop_inputs(model: GPD, scene: Scene, num_history: int, top_k: int, lanes: LaneContext | None = None):
    """The model inputs of frames [0, T-1) along the model's own closest-of-`top_k` rollout of `scene` (unbatched).

    History frames [0, num_history) are the log's; every later frame t < T-1 holds the reached state (`closest_frame`)
    where the agent is valid at t and t-1 in the log. The rollout runs on the model's parameters behind a
    stop-gradient (CAT-K's: no gradient flows through the chosen states). `lanes`: what a model that reads lanes
    uses (`gpd_jax.training.step.lane_context_of`).
    Returns (xy f32[T-1, A, 2], heading f32[T-1, A], velocity f32[T-1, A, 2] or None, map tokens i32[T-1, M]), as
    `gpd_jax.training.step.free_running_inputs`."""
    choose = lambda modes, log, t, own: closest_frame(modes, log, t, own, top_k)  # noqa: E731
    return rollout_inputs(model, scene, own_rollout(model, scene, num_history, choose, lanes))


# ------------------------------------------------------------------------------------------------ reward fine-tuning
@flax.struct.dataclass(frozen=True)
class RewardOptions:
    """Reward fine-tuning (`train.reward_samples` > 0): `samples` G sampled rollouts of each scene at `temperature`
    (the sampling head's cells, as a sampled rollout draws them), each agent's reward (`agent_rewards`: weights of
    collision, off-road, progress), group-relative advantages over the G rollouts and the policy-gradient loss at
    `scale` beside the supervised loss on the log (the anchor)."""

    samples: int = flax.struct.field(pytree_node=False, default=0)
    temperature: float = flax.struct.field(pytree_node=False, default=1.0)
    collision: float = flax.struct.field(pytree_node=False, default=1.0)
    offroad: float = flax.struct.field(pytree_node=False, default=1.0)
    progress: float = flax.struct.field(pytree_node=False, default=0.5)
    scale: float = flax.struct.field(pytree_node=False, default=1.0)

    @classmethod
    def of(cls, train_cfg) -> "RewardOptions":
        """The options of a config's `train` section (checked: counts and weights non-negative)."""
        w = tuple(float(x) for x in train_cfg.reward_weights)
        opts = cls(samples=int(train_cfg.reward_samples), temperature=float(train_cfg.reward_temperature),
                   collision=w[0], offroad=w[1], progress=w[2], scale=float(train_cfg.reward_scale))
        if opts.samples < 0 or opts.samples == 1 or len(w) != 3 or min(w) < 0 or opts.temperature <= 0:
            raise ValueError(f"train.reward_samples must be 0 or >= 2 (a group), train.reward_weights three "
                             f"non-negative weights (collision, offroad, progress), train.reward_temperature > 0; "
                             f"got {opts.samples}, {w}, {opts.temperature}")
        return opts


def sampled_frame(modes: Modes, log: Frame, t, own: jax.Array, key: jax.Array, sampling: Sampling) -> Frame:
    """Frame t's inputs of a sampled rollout: where `own`, one draw of the sampling head (`sample_agents`, as a
    rollout at that temperature draws it); elsewhere the log's frame t."""
    xy, heading, vel = sample_agents(modes, key, sampling)
    return Frame(xy=jnp.where(own[:, None], xy, log.xy[t]), heading=jnp.where(own, heading, log.heading[t]),
                 valid=log.valid[t], valid_logit=log.valid_logit[t], map_tokens=log.map_tokens[t],
                 velocity=log.velocity[t] if vel is None else jnp.where(own[:, None], vel, log.velocity[t]))


def sampled_rollouts(model: GPD, scene: Scene, num_history: int, key: jax.Array, samples: int, temperature: float,
                     lanes: LaneContext | None = None) -> Frame:
    """`samples` sampled traffic-simulation rollouts of `scene` (unbatched; `own_rollout`, frozen parameters), each
    with its own key: `Frame`s [G, T, ...]."""
    sampling = Sampling(temperature=temperature)

    def one(k):
        def pick(modes, log, t, own):
            return sampled_frame(modes, log, t, own, jax.random.fold_in(k, t), sampling)

        return own_rollout(model, scene, num_history, pick, lanes)

    return jax.vmap(one)(jax.random.split(key, samples))


class AgentRewards(NamedTuple):
    """Per-agent reward parts of one rollout: collided f32[A] (1 if its box overlaps another's at any future frame),
    offroad f32[A] (share of its valid future frames with its centre off the drivable area; 0 without road
    geometry), progress f32[A] (its future path length over the log's, at most 1), total f32[A] (weighted)."""

    collided: jax.Array
    offroad: jax.Array
    progress: jax.Array
    total: jax.Array


def agent_rewards(xy, heading, valid, size, num_history: int, log_xy, log_valid, road: RoadGeometry | None = None,
                  options: RewardOptions = RewardOptions()) -> AgentRewards:
    """The rewards of one rollout's agents, from the realism metrics' own features (the rounded-box distance of
    `nearest_object_distance`, `gpd_jax.geometry.on_road`).

    xy f32[T, A, 2], heading f32[T, A], valid bool[T, A] (the rollout), size f32[A, 2], log_xy f32[T, A, 2] and
    log_valid bool[T, A] (the log, for progress), road: the scene's drivable area or None."""
    fut = slice(num_history, None)
    v = valid[fut]
    dist = nearest_object_distance(xy[fut], heading[fut], v, jnp.broadcast_to(size, xy[fut].shape))
    collided = jnp.any((dist < 0) & v, axis=0).astype(jnp.float32)
    n = jnp.maximum(jnp.sum(v, axis=0), 1)
    if road is None:
        offroad = jnp.zeros(v.shape[-1], jnp.float32)
    else:
        offroad = jnp.sum(~on_road(road, xy[fut]) & v, axis=0) / n

    def path(p, ok):
        both = ok[num_history:] & ok[num_history - 1:-1]
        return jnp.sum(jnp.linalg.norm(p[num_history:] - p[num_history - 1:-1], axis=-1) * both, axis=0)

    progress = jnp.minimum(path(xy, valid), path(log_xy, log_valid)) / jnp.maximum(path(log_xy, log_valid), 1.0)
    total = -options.collision * collided - options.offroad * offroad + options.progress * progress
    return AgentRewards(collided=collided, offroad=offroad, progress=progress, total=total)


def group_advantages(rewards: jax.Array, ok: jax.Array) -> jax.Array:
    """Group-relative advantages f32[G, A] of rewards f32[G, A] over the G rollouts of one scene, per agent (GRPO):
    (r - mean) / (std + 0.1), zero where `ok` bool[A] is False or the group's rewards do not differ."""
    mean = jnp.mean(rewards, axis=0, keepdims=True)
    std = jnp.std(rewards, axis=0, keepdims=True)
    return jnp.where(ok[None, :], (rewards - mean) / (std + 0.1), 0.0)
