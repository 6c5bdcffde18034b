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

import jax
import jax.numpy as jnp
from flax import nnx

from gpd_jax.decoding import DecodeState, Frame, advance, context_at, given_inputs, prefill
from gpd_jax.model import GPD, LaneContext, Modes
from gpd_jax.scene import Scene
from gpd_jax.tasks import make_task


def top_k_candidates(modes: Modes, k: int):
    """The `k` most likely cells of a sampling head's next-state distribution of one frame (leading dims [A]).

    Returns (xy f32[A, k, 2], heading f32[A, k], velocity f32[A, k, 2] or None): each cell's centre."""
    _, idx = jax.lax.top_k(modes.logits, k)

    def take(a):
        return jnp.take_along_axis(a, idx.reshape(idx.shape + (1,) * (a.ndim - idx.ndim)), axis=idx.ndim - 1)

    return take(modes.xy), take(modes.heading), None if modes.velocity is None else take(modes.velocity)


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


def closed_loop_inputs(model: GPD, scene: Scene, num_history: int, top_k: int, lanes: LaneContext | None = None):
    """The model inputs of frames [0, T-1) along the model's own closest-of-`top_k` rollout of `scene` (unbatched).

    History frames [0, num_history) are the log's; every later frame t < T-1 holds the reached state (`closest_frame`)
    where the agent is valid at t and t-1 in the log. The rollout runs on the model's parameters behind a
    stop-gradient (CAT-K's: no gradient flows through the chosen states). `lanes`: what a model that reads lanes
    uses (`gpd_jax.training.step.lane_context_of`).
    Returns (xy f32[T-1, A, 2], heading f32[T-1, A], velocity f32[T-1, A, 2] or None, map tokens i32[T-1, M]), as
    `gpd_jax.training.step.free_running_inputs`."""
    if model.mode_head is None:
        raise ValueError("closed-loop fine-tuning (train.closed_loop_top_k > 0) keeps the closest of the sampling "
                         "head's top-K cells: set model.agent_bins > 0")
    t_total, h = scene.num_frames, num_history
    graphdef, state = nnx.split(model)
    frozen = nnx.merge(graphdef, jax.lax.stop_gradient(state))
    task = make_task("traffic_simulation", scene.map_tokens.shape[-1], scene.xy.shape[-2])
    given = given_inputs(frozen, scene, task, num_history=h)
    log = given.log

    def step(carry: DecodeState, t):
        own = log.valid[t] & log.valid[t - 1]
        frame = closest_frame(jax.tree.map(lambda a: a[0], carry.pred.modes), log, t, own, top_k)
        return advance(frozen, carry, frame, t, context_at(lanes, t)), frame

    start = prefill(frozen, log, h, t_total, lanes)
    _, frames = jax.lax.scan(step, start, jnp.arange(h, t_total - 1))
    cat = lambda a, b: jax.lax.stop_gradient(jnp.concatenate([a[:h], b.astype(a.dtype)], 0))  # noqa: E731
    xy, heading, vel = cat(log.xy, frames.xy), cat(log.heading, frames.heading), cat(log.velocity, frames.velocity)
    return xy, heading, None if model.input_velocity(scene.velocity) is None else vel, scene.map_tokens[:-1]
