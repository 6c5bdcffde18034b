"""Autoregressive scene rollout: KV-cached (ours) and full-prefix recompute (the official method).

Both are single-scenario pure functions of the model; `rollout_batch` vmaps the cached one over scenarios and
tasks, so one compiled function runs a batch that mixes tasks.

Cached rollout: the history frames [0, H) are embedded and pushed through the transformer in one call that
fills a preallocated KV cache; then a `lax.scan` over future frames forms each frame from the previous
frame's prediction and the log (per the task mask), embeds its N tokens, appends their keys/values at the
frame's offset and attends only to the filled part of the cache (chunked; see attention.py).

Feedback: predicted positions and headings (and velocities, for a `velocity_inputs` model) are re-tokenized as
regressed; valid = logit > 0; a map token is the argmax of its logits (temperature 0, the default) or sampled at
a temperature with an explicit key.

The log's map around a generated ego: the logged map tokens of frame t were encoded around the *logged* ego pose.
In tasks that take the map from the log but generate the ego (traffic simulation, motion planning), a rollout
may instead re-encode the log's lanes around the ego it generated (`LogLanes` + a `map_encoder`, e.g.
`gpd_jax.map_tokenizer.MapTokenizer.pose_encoder`): rasterize and tokenize inside the compiled step, so the map
stays where the log's roads are relative to the generated ego. Without them (the default, as the paper and the
official code do) the logged tokens are used as they are.
"""

from __future__ import annotations

from typing import Callable

import flax.struct
import jax
import jax.numpy as jnp

from gpd_jax.model import GPD, Prediction, forward, forward_cached
from gpd_jax.scene import Scene
from gpd_jax.tasks import Task


@flax.struct.dataclass
class RolloutOutput:
    """A rolled-out scene. History frames are the log's (with the task's hidden agents removed).

    xy: f32[..., T, A, 2], heading: f32[..., T, A], valid: bool[..., T, A],
    valid_logit: f32[..., T, A] (the model's logit for generated frames, +/-inf-free 0 elsewhere),
    map_tokens: i32[..., T, M].
    """

    xy: jax.Array
    heading: jax.Array
    valid: jax.Array
    valid_logit: jax.Array
    map_tokens: jax.Array


@flax.struct.dataclass
class LogLanes:
    """The log's lane geometry of one scene (or a batch: leading dims `...`), to re-encode its map around a
    generated ego pose.

    polylines: f32[..., L, P, 2] lane points in the scene frame; valid: bool[..., L, P].
    """

    polylines: jax.Array
    valid: jax.Array


# (polylines f32[L, P, 2], valid bool[L, P], ego pose f32[3] in the scene frame) -> map tokens i32[M]
MapEncoder = Callable[[jax.Array, jax.Array, jax.Array], jax.Array]


def _log_inputs(model: GPD, scene: Scene, task: Task):
    """The log's frames as model inputs: xy, heading, valid (hidden agents removed), map tokens, velocity
    (zeros for a model without velocity inputs)."""
    valid = scene.valid & ~task.hidden[None, :]
    vel = model.input_velocity(scene.velocity)  # raises if the model needs velocities and the scene has none
    vel = jnp.zeros_like(scene.xy) if vel is None else vel
    return scene.xy, scene.heading, valid, scene.map_tokens, vel


def _choose_frame(pred: Prediction, log_vel, scene: Scene, task: Task, t, key, temperature: float, num_map: int,
                  lanes: LogLanes | None = None, map_encoder: MapEncoder | None = None):
    """Frame t's inputs (xy, heading, valid, valid logit, map tokens, velocity): the log where the task says so,
    the prediction elsewhere.

    `pred` holds the single-frame prediction made at frame t-1 (leading dim 1); `log_vel f32[T, A, 2]`. With
    `lanes` and `map_encoder`, map tokens taken from the log while the ego is generated (and valid) are the log's
    lanes encoded around the generated ego pose instead of the logged tokens.
    """
    logits = pred.map_logits[0]
    if temperature > 0:
        sampled = jax.random.categorical(jax.random.fold_in(key, t), logits / temperature, axis=-1)
    else:
        sampled = jnp.argmax(logits, axis=-1)
    log_map = scene.map_tokens[t]
    fl_map, fl_agent = task.from_log[:num_map], task.from_log[num_map:]
    map_t = jnp.where(fl_map, log_map, sampled.astype(log_map.dtype))
    xy_t = jnp.where(fl_agent[:, None], scene.xy[t], pred.xy[0])
    heading_t = jnp.where(fl_agent, scene.heading[t], pred.heading[0])
    valid_t = jnp.where(fl_agent, scene.valid[t], pred.valid_logit[0] > 0) & ~task.hidden
    logit_t = jnp.where(fl_agent, 0.0, pred.valid_logit[0])
    if map_encoder is not None:
        pose = jnp.stack([xy_t[0, 0], xy_t[0, 1], heading_t[0]])
        around_ego = map_encoder(lanes.polylines, lanes.valid, pose).astype(log_map.dtype)
        map_t = jnp.where(fl_map & ~fl_agent[0] & valid_t[0], around_ego, map_t)
    pred_vel = jnp.zeros_like(log_vel[t]) if pred.velocity is None else pred.velocity[0]
    vel_t = jnp.where(fl_agent[:, None], log_vel[t], pred_vel)
    return xy_t, heading_t, valid_t, logit_t, map_t, vel_t


def rollout(model: GPD, scene: Scene, task: Task, key: jax.Array, num_history: int,
            temperature: float = 0.0, lanes: LogLanes | None = None,
            map_encoder: MapEncoder | None = None) -> RolloutOutput:
    """KV-cached rollout of one scenario under one task.

    Args:
      model: the GPD transformer.
      scene: a single (unbatched) scene with T frames; frames [0, num_history) are given.
      task: a single task (from_log bool[M + A], hidden bool[A]).
      key: PRNG key (used only when temperature > 0).
      num_history: H, the number of given frames (21 in the paper).
      temperature: 0 for greedy map tokens, > 0 to sample them.
      lanes, map_encoder: the scene's logged lanes and a tokenizer's pose encoder, to re-encode the logged map
        around a generated ego (see the module docstring); both or neither.
    """
    t_total, h = scene.num_frames, num_history
    num_map = scene.num_map_tokens
    _check_map_encoder(lanes, map_encoder)
    xy, heading, valid, maps, vel = _log_inputs(model, scene, task)
    tokens = model.embed(xy[:h], heading[:h], valid[:h], maps[:h], jnp.arange(h), vel[:h])
    hidden, cache = forward_cached(model, tokens, model.init_cache(t_total), 0)
    pred = model.predict(hidden[-1:], xy[h - 1:h], heading[h - 1:h], valid[h - 1:h], *_prev(xy, valid, h - 1),
                         vel[h - 1:h])

    def step(carry, t):
        cache, pred, last_xy, last_valid = carry
        frame = _choose_frame(pred, vel, scene, task, t, key, temperature, num_map, lanes, map_encoder)
        fxy, fh, fv, _, fm, fvel = frame
        tok = model.embed(fxy[None], fh[None], fv[None], fm[None], t[None], fvel[None])
        hid, cache = forward_cached(model, tok, cache, t)
        pred = model.predict(hid, fxy[None], fh[None], fv[None], last_xy[None], last_valid[None], fvel[None])
        return (cache, pred, fxy, fv), frame

    carry = (cache, pred, xy[h - 1], valid[h - 1])
    (_, pred, _, _), frames = jax.lax.scan(step, carry, jnp.arange(h, t_total - 1))
    last = _choose_frame(pred, vel, scene, task, jnp.asarray(t_total - 1), key, temperature, num_map, lanes,
                         map_encoder)
    frames = jax.tree.map(lambda a, b: jnp.concatenate([a, b[None]], axis=0), frames, last)
    return _assemble(xy, heading, valid, maps, frames, h)


def _check_map_encoder(lanes, map_encoder) -> None:
    if (lanes is None) != (map_encoder is None):
        raise ValueError("re-encoding the logged map around a generated ego needs both `lanes` (the log's lane "
                         f"polylines) and `map_encoder`; got lanes={'None' if lanes is None else 'given'}, "
                         f"map_encoder={map_encoder!r}")


def _prev(xy, valid, t):
    """The frame before frame t as a 1-frame block (invalid when t is 0); t may be traced."""
    p = jnp.maximum(t - 1, 0)
    pxy = jax.lax.dynamic_slice_in_dim(xy, p, 1, axis=0)
    pv = jax.lax.dynamic_slice_in_dim(valid, p, 1, axis=0) & (t > 0)
    return pxy, pv


def _assemble(xy, heading, valid, maps, frames, h) -> RolloutOutput:
    fxy, fh, fv, fl, fm, _ = frames
    return RolloutOutput(
        xy=jnp.concatenate([xy[:h], fxy], 0),
        heading=jnp.concatenate([heading[:h], fh], 0),
        valid=jnp.concatenate([valid[:h], fv], 0),
        valid_logit=jnp.concatenate([jnp.zeros(valid[:h].shape, fl.dtype), fl], 0),
        map_tokens=jnp.concatenate([maps[:h], fm.astype(maps.dtype)], 0),
    )


def rollout_recompute(model: GPD, scene: Scene, task: Task, key: jax.Array, num_history: int,
                      temperature: float = 0.0, lanes: LogLanes | None = None,
                      map_encoder: MapEncoder | None = None) -> RolloutOutput:
    """The official method: for every future frame, a full forward over the whole buffer (no cache).

    The buffer holds all T frames; frames not yet generated still hold log values, which the scene-level
    mask keeps from influencing the frame being predicted, so this equals a forward over the prefix only.
    Same arguments and outputs as `rollout`.
    """
    t_total, h = scene.num_frames, num_history
    num_map = scene.num_map_tokens
    _check_map_encoder(lanes, map_encoder)
    xy, heading, valid, maps, vel = _log_inputs(model, scene, task)
    logits0 = jnp.zeros(valid.shape, jnp.float32)

    def step(buf, t):
        bxy, bh, bv, bl, bm, bvel = buf
        tokens = model.embed(bxy, bh, bv, bm, jnp.arange(t_total), bvel)
        hid = forward(model, tokens)
        prev = jnp.maximum(t - 1, 0)
        sl = lambda a: jax.lax.dynamic_slice_in_dim(a, prev, 1, axis=0)
        pred = model.predict(sl(hid), sl(bxy), sl(bh), sl(bv), *_prev(bxy, bv, prev), sl(bvel))
        frame = _choose_frame(pred, vel, scene, task, t, key, temperature, num_map, lanes, map_encoder)
        buf = tuple(jax.lax.dynamic_update_slice_in_dim(b, f[None].astype(b.dtype), t, axis=0)
                    for b, f in zip(buf, frame))
        return buf, None

    buf, _ = jax.lax.scan(step, (xy, heading, valid, logits0, maps, vel), jnp.arange(h, t_total))
    bxy, bh, bv, bl, bm, _ = buf
    return RolloutOutput(xy=bxy, heading=bh, valid=bv, valid_logit=bl, map_tokens=bm)


def rollout_batch(model: GPD, scenes: Scene, tasks: Task, keys: jax.Array, num_history: int,
                  temperature: float = 0.0, lanes: LogLanes | None = None,
                  map_encoder: MapEncoder | None = None) -> RolloutOutput:
    """`rollout` vmapped over a leading batch dim shared by scenes, tasks, keys (and lanes; mixed tasks
    allowed)."""
    fn = lambda s, t, k, ln: rollout(model, s, t, k, num_history, temperature, ln, map_encoder)
    return jax.vmap(fn)(scenes, tasks, keys, lanes)


def rollout_tasks(model: GPD, scenes: Scene, tasks: Task, key: jax.Array, num_history: int,
                  temperature: float = 0.0, lanes: LogLanes | None = None,
                  map_encoder: MapEncoder | None = None) -> RolloutOutput:
    """Every scenario under every task: scenes [S, ...], tasks [K, ...] -> outputs with leading dims [S, K].

    The S x K pairs are flattened into one vmapped batch (so the attention kernel's per-scenario batching
    rule sees the whole batch); keys are split per (scenario, task).
    """
    s = scenes.xy.shape[0]
    k = tasks.from_log.shape[0]
    flat_scenes, flat_lanes = jax.tree.map(lambda x: jnp.repeat(x, k, axis=0), (scenes, lanes))
    flat_tasks = jax.tree.map(lambda x: jnp.tile(x, (s,) + (1,) * (x.ndim - 1)), tasks)
    keys = jax.random.split(key, s * k)
    out = rollout_batch(model, flat_scenes, flat_tasks, keys, num_history, temperature, flat_lanes, map_encoder)
    return jax.tree.map(lambda x: x.reshape((s, k) + x.shape[1:]), out)
