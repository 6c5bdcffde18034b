"""Teacher-forced losses, the optimizer and a jitted train step for the GPD transformer.

Inputs are frames [0, T-1), targets frames [1, T): every slot's output at frame t predicts the same slot at
frame t+1. With `train.rollout_passes` = k > 0 the agent inputs of the future frames are the model's own
predictions instead (k teacher-forced passes without gradient; exact for the first k future frames), the
targets still the log's: training then sees the inputs a rollout sees and learns to recover from its own
errors. With `train.map_feedback` = f > 0 as well, the future map tokens of a fraction f of each batch's scenes
are the model's own (argmax) too, as in the tasks that generate the map. Losses (weights from `config.loss`;
official values 5, 5.73, 1, 1):

* position: smooth-L1 (beta 1, metres), summed over x and y, averaged over valid target agents;
* heading: smooth-L1 of the *wrapped* difference (radians), averaged over valid target agents;
* valid: binary cross-entropy of the validity logit over every agent slot;
* map: cross-entropy of the K-way map logits over map tokens of frames whose map is known;
* velocity (only for `velocity_inputs` models, weight `loss.velocity`): smooth-L1 (m/s) summed over vx and vy,
  averaged over agents valid at both frames;
* modes (only for `agent_bins` models, weight `loss.modes`): the negative log-likelihood of the logged next state
  under the sampling head (`gpd_jax.model.Modes.log_prob`; the velocity where the agent is valid at both frames),
  averaged over valid target agents.

`train.trainable` = "sampling_head" trains the sampling head alone: the gradient is taken with respect to its
parameters only (no backward pass through the transformer) and every other parameter stays where `train.init_from`
left it, so the model's temperature-0 rollouts stay that model's.

`loss.agent_norm` = "euclidean" (not in the paper or the official code; default "smooth_l1", theirs) replaces the
position and velocity smooth-L1 by the pseudo-Huber of the error vector's length, sqrt(|e|^2 + delta^2) - delta
(`loss.agent_norm_delta`, metres and m/s). ADE and FDE average that length, and the point that minimises an
expected length is the geometric median of the futures, where smooth-L1 (quadratic below 1 m) pulls a prediction
towards their mean below a metre: for a car stopped at a light that mostly stays and sometimes goes, the mean
creeps forward every frame and the median stays put.

A model that reads lanes (`agent_lane_residual`) reads the scenes' lane polylines
(`lane_context_of`, the batches must carry `Scene.polylines`) in every input frame, its own rollout passes
included; `train.lane_context_drop` = f drops them from the future frames of the last round(f * B) scenes of each
batch, as in the tasks that generate the map.

`train.reward_samples` = G > 0 (reward fine-tuning, gpd_jax/training/closed_loop.py) adds a policy-gradient loss
over G sampled rollouts of each scene with group-relative advantages of collision, off-road and progress rewards
(`reward_terms`), beside the supervised loss on the log that anchors the model to human driving; its rollouts' key is
the run's seed folded with the step, so a resumed run is the same run.

`train.closed_loop_top_k` = K > 0 (closed-loop supervised fine-tuning, CAT-K: gpd_jax/training/closed_loop.py)
takes the future frames' inputs from the model's own rollout, keeping at each frame the closest to the log of its
sampling head's top-K cells; the targets stay the log's next frames, so the model learns to return to the log from
the states it reaches.

The step is a pure function of (params, opt_state, batch); NNX only defines the parameter tree.
"""

from __future__ import annotations

import copy
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import nnx

from gpd_jax.model import GPD, MODE_HEAD, LaneContext, Prediction, forward, samples_agents
from gpd_jax.scene import Scene, wrap_angle
from gpd_jax.training.closed_loop import (RewardOptions, agent_rewards, closed_loop_inputs, group_advantages,
                                          rollout_inputs, sampled_rollouts)
from gpd_jax.training.common import compiled_once, step_key


def _smooth_l1(x, beta: float = 1.0):
    ax = jnp.abs(x)
    return jnp.where(ax < beta, 0.5 * ax * ax / beta, ax - 0.5 * beta)


AGENT_NORMS = ("smooth_l1", "euclidean")
NORM_DELTA = 0.05  # the euclidean loss's default width (m, m/s): `loss.agent_norm_delta`


def vector_loss(err, norm: str = "smooth_l1", delta: float = NORM_DELTA):
    """Per-vector loss of errors f32[..., 2] -> f32[...]: "smooth_l1" (beta 1) summed over the components (the
    official loss), or "euclidean", the pseudo-Huber sqrt(|err|^2 + delta^2) - delta of the error's length (its
    gradient is the unit error vector beyond delta: the minimiser of its expectation is the geometric median)."""
    if norm == "smooth_l1":
        return jnp.sum(_smooth_l1(err), axis=-1)
    if norm == "euclidean":
        return jnp.sqrt(jnp.sum(err * err, axis=-1) + delta * delta) - delta
    raise ValueError(f"loss.agent_norm must be one of {AGENT_NORMS}, got {norm!r}")


def previous_frames(xy, valid):
    """Each frame's previous frame: xy f32[F, A, 2], valid bool[F, A] -> the same shifted by one frame, with
    frame 0's previous frame invalid."""
    return (jnp.concatenate([xy[:1], xy[:-1]], 0),
            jnp.concatenate([jnp.zeros_like(valid[:1]), valid[:-1]], 0))


def teacher_forced(model: GPD, xy, heading, valid, map_tokens, velocity=None,
                   lanes: LaneContext | None = None) -> Prediction:
    """One teacher-forced pass: next-frame predictions from every frame's inputs.

    xy f32[F, A, 2], heading f32[F, A], valid bool[F, A], map_tokens i32[F, M], velocity f32[F, A, 2] or None
    (frames [0, F) of a scene), lanes: what a model that reads lanes uses -> Prediction of frames
    [1, F + 1)."""
    tokens = model.embed(xy, heading, valid, map_tokens, jnp.arange(xy.shape[0]), velocity)
    hidden = forward(model, tokens)
    prev_xy, prev_valid = previous_frames(xy, valid)
    return model.predict(hidden, xy, heading, valid, prev_xy, prev_valid, velocity, lanes)


def free_running_inputs(model: GPD, scene: Scene, num_history: int, passes: int, feed_map=False,
                        lanes: LaneContext | None = None):
    """The inputs a rollout would see, approximated by `passes` teacher-forced passes without gradient.

    Frames [num_history, T-1) of agents valid there and in the previous frame take the model's own prediction
    from the previous frame (xy, heading and, for a `velocity_inputs` model, velocity); with `feed_map`
    (bool[], may be traced) so do the map tokens of those frames where the map is known (argmax of the previous
    frame's map logits, as a rollout at temperature 0 feeds them back). Everything else (validity, history
    frames, agents that just appeared, and the map without `feed_map`) stays the log's. The model is causal
    over frames, so after k passes the first k future frames equal a free-running rollout exactly (validity
    kept from the log) and later frames approximate it. With `passes` = 0 these are the log's inputs.
    Returns (xy f32[T-1, A, 2], heading f32[T-1, A], velocity f32[T-1, A, 2] or None, map tokens i32[T-1, M]).
    """
    logged = (scene.xy[:-1], scene.heading[:-1],
              None if model.input_velocity(scene.velocity) is None else scene.velocity[:-1], scene.map_tokens[:-1])
    if passes <= 0:
        return logged
    valid = scene.valid[:-1]
    future = (jnp.arange(valid.shape[0]) >= num_history)[:, None]
    own = future & valid & previous_frames(logged[0], valid)[1]
    map_known = scene.map_valid[:-1]
    own_map = future & (map_known & jnp.concatenate([jnp.zeros_like(map_known[:1]), map_known[:-1]]))[:, None] \
        & jnp.asarray(feed_map, bool)
    # The passes see frozen parameters: no tangents flow into the loop, which compiles once (not per pass).
    graphdef, state = nnx.split(model)
    frozen = nnx.merge(graphdef, jax.lax.stop_gradient(state))

    def take(log, predicted, where=own):
        shifted = jnp.concatenate([log[:1], predicted[:-1]], 0)
        return jnp.where(where.reshape(where.shape + (1,) * (log.ndim - where.ndim)), shifted, log)

    def one_pass(_, inputs):
        xy, heading, vel, maps = inputs
        pred = teacher_forced(frozen, xy, heading, valid, maps, vel, lanes)
        return (take(logged[0], pred.xy), take(logged[1], pred.heading),
                None if vel is None else take(logged[2], pred.velocity),
                take(logged[3], jnp.argmax(pred.map_logits, -1).astype(maps.dtype), own_map))

    return jax.lax.fori_loop(0, passes, one_pass, logged)


def training_scene(batch, keep_road: bool = False) -> Scene:
    """A loader batch as the Scene a train or eval step takes: with polylines (`with_polylines` gives `(scene,
    polylines)`) the scene keeps them and drops the road geometry, which only the reward fine-tuning reads
    (`keep_road`: `uses_road(config)`)."""
    if isinstance(batch, tuple):
        return batch[0] if keep_road else batch[0].replace(road=None)
    return batch


def uses_road(config) -> bool:
    """Whether a config's train step reads the scenes' road geometry (reward fine-tuning's off-road reward)."""
    return int(config.train.reward_samples) > 0


def lane_context_of(model: GPD, scene: Scene, num_history: int, drop=False) -> LaneContext | None:
    """The lanes a model that reads lanes (`GPD.reads_lanes`) uses in training: the scene's polylines in every input
    frame, or with `drop` (bool[], may be traced) in the history frames only, as in a task that generates the
    map. None for other models. Such a model needs the polylines (`Scene.polylines`)."""
    if not model.reads_lanes:
        return None
    if scene.polylines is None or scene.polyline_valid is None:
        raise ValueError("a model that reads lanes (agent_lane_residual) trains on the scenes' "
                         "lane polylines (Scene.polylines): load the batches with them")
    frames = jnp.arange(scene.num_frames - 1)
    on = (frames < num_history) | ~jnp.asarray(drop, bool)
    return LaneContext(polylines=scene.polylines, valid=scene.polyline_valid, on=on)


def reward_terms(model: GPD, scene: Scene, num_history: int, options: RewardOptions, key: jax.Array,
                 lanes: LaneContext | None = None) -> dict[str, jax.Array]:
    """Sums and counts of the reward fine-tuning loss over one unbatched scene (`RewardOptions`): `options.samples`
    sampled rollouts (frozen parameters), each agent's reward (`agent_rewards`: the scene's road geometry where it
    has one), group-relative advantages over the rollouts (`group_advantages`), and the policy-gradient loss
    -sum(advantage * log-likelihood of the agent's sampled future states), the likelihoods from a teacher-forced
    pass (with gradient) over each rollout's frames. The sampled states carry the rollout temperature's noise,
    the likelihood is the model's own (temperature 1): a reward-weighted likelihood rather than an exact
    on-policy gradient at temperatures below 1."""
    h = num_history
    frames = sampled_rollouts(model, scene, h, key, options.samples, options.temperature, lanes)
    parts = jax.vmap(lambda f: agent_rewards(f.xy, f.heading, f.valid, scene.size, h, scene.xy, scene.valid,
                                             scene.road, options))(frames)
    ok = jnp.any(scene.valid[h:] & scene.valid[h - 1:-1], axis=0)
    adv = jax.lax.stop_gradient(group_advantages(parts.total, ok))

    def log_likelihood(f):
        xy, heading, vel, maps = rollout_inputs(model, scene, f)
        pred = teacher_forced(model, xy, heading, scene.valid[:-1], maps, vel, lanes)
        both = f.valid[1:] & f.valid[:-1]
        lp = pred.modes.log_prob(f.xy[1:], f.heading[1:], None if vel is None else f.velocity[1:], both)
        future = (jnp.arange(lp.shape[0]) >= h - 1)[:, None]
        return jnp.sum(jnp.where(future & both, lp, 0.0), axis=0)

    okf = ok.astype(jnp.float32)
    return {"reward_pg_sum": -jnp.sum(adv * jax.vmap(log_likelihood)(frames)),
            "reward_count": options.samples * jnp.sum(okf), "reward_sum": jnp.sum(parts.total * okf),
            "reward_collided_sum": jnp.sum(parts.collided * okf), "reward_offroad_sum": jnp.sum(parts.offroad * okf),
            "reward_progress_sum": jnp.sum(parts.progress * okf)}


def loss_terms(model: GPD, scene: Scene, num_history: int = 0, rollout_passes: int = 0,
               feed_map=False, agent_norm: str = "smooth_l1", norm_delta: float = NORM_DELTA,
               drop_lanes=False, closed_loop_k: int = 0, reward: RewardOptions | None = None,
               key: jax.Array | None = None) -> dict[str, jax.Array]:
    """Sums and counts of each loss over one unbatched scene (aggregate over a batch, then divide).

    `agent_norm` / `norm_delta`: the position and velocity loss (`vector_loss`).
    With `rollout_passes` > 0 the agent inputs of the future frames (from `num_history` on) are the model's own
    predictions (`free_running_inputs`; with `feed_map` the map tokens too) while the targets stay the log's:
    the model learns to recover from its own errors, as it must in a rollout. A model that reads lanes
    reads the scene's lanes (`lane_context_of`; with `drop_lanes` in the history frames only).
    With `closed_loop_k` = K > 0 instead, the inputs of the future frames are the states the model's own rollout
    reaches keeping, at every frame, the closest to the log of its top-K cells (`closed_loop_inputs`, CAT-K).
    With `reward` (`RewardOptions.samples` > 0) and a `key`, the reward fine-tuning terms too (`reward_terms`)."""
    lanes = lane_context_of(model, scene, num_history, drop_lanes)
    if closed_loop_k > 0:
        xy, heading, vel, maps = closed_loop_inputs(model, scene, num_history, closed_loop_k, lanes)
    else:
        xy, heading, vel, maps = free_running_inputs(model, scene, num_history, rollout_passes, feed_map, lanes)
    pred = teacher_forced(model, xy, heading, scene.valid[:-1], maps, vel, lanes)
    tv = scene.valid[1:].astype(jnp.float32)
    pos = vector_loss(pred.xy - scene.xy[1:], agent_norm, norm_delta)
    head = _smooth_l1(wrap_angle(pred.heading - scene.heading[1:]))
    bce = optax.sigmoid_binary_cross_entropy(pred.valid_logit, tv)
    ce = optax.softmax_cross_entropy_with_integer_labels(pred.map_logits, scene.map_tokens[1:])
    mv = jnp.broadcast_to(scene.map_valid[1:, None], ce.shape).astype(jnp.float32)
    terms = {}
    both = tv * scene.valid[:-1]
    if pred.velocity is not None:
        terms["velocity_sum"] = jnp.sum(vector_loss(pred.velocity - scene.velocity[1:], agent_norm, norm_delta) * both)
        terms["velocity_count"] = jnp.sum(both)
    if pred.modes is not None:
        vel = None if pred.velocity is None else scene.velocity[1:]
        log_p = pred.modes.log_prob(scene.xy[1:], scene.heading[1:], vel, both > 0)
        terms["modes_sum"] = -jnp.sum(jnp.where(tv > 0, log_p, 0.0))
    if reward is not None and reward.samples > 0:
        terms |= reward_terms(model, scene, num_history, reward, key, lanes)
    return terms | {
        "position_sum": jnp.sum(pos * tv), "heading_sum": jnp.sum(head * tv), "agent_count": jnp.sum(tv),
        "valid_sum": jnp.sum(bce), "valid_count": jnp.asarray(bce.size, jnp.float32),
        "map_sum": jnp.sum(ce * mv), "map_count": jnp.sum(mv),
        "map_correct": jnp.sum((jnp.argmax(pred.map_logits, -1) == scene.map_tokens[1:]) * mv),
    }


def agent_norm_of(loss_cfg) -> tuple[str, float]:
    """(`loss.agent_norm`, `loss.agent_norm_delta`) of a loss config; an unknown norm or a non-positive width is
    refused here, before anything compiles."""
    norm, delta = str(loss_cfg.agent_norm), float(loss_cfg.agent_norm_delta)
    if norm not in AGENT_NORMS:
        raise ValueError(f"loss.agent_norm must be one of {AGENT_NORMS}, got {norm!r}")
    if not delta > 0:
        raise ValueError(f"loss.agent_norm_delta must be > 0, got {delta}")
    return norm, delta


def batch_loss(model: GPD, scenes: Scene, weights, num_history: int = 0, rollout_passes: int = 0,
               map_feedback: float = 0.0, lane_drop: float = 0.0,
               closed_loop_k: int = 0, reward: RewardOptions | None = None,
               key: jax.Array | None = None) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Weighted total loss over a batch of scenes (leading dim B) and its parts (see `loss_terms`).

    With `rollout_passes` > 0 the first round(map_feedback * B) scenes of the batch (a random subset: batches
    are shuffled) also take their future map tokens from the model (`free_running_inputs`). For a model
    that reads lanes the last round(lane_drop * B) scenes read no lanes in their future frames. `closed_loop_k`:
    see `loss_terms`; `reward` (with `key`, split over the scenes): the reward fine-tuning loss at `reward.scale`
    (`reward_terms`), its mean reward and parts logged beside it."""
    b = scenes.xy.shape[0]
    idx = jnp.arange(b)
    feed = idx < round(float(map_feedback) * b)
    drop = idx >= b - round(float(lane_drop) * b)
    norm, delta = agent_norm_of(weights)
    keys = jax.random.split(jax.random.key(0) if key is None else key, b)
    terms = jax.vmap(lambda s, f, d, k: loss_terms(model, s, num_history, rollout_passes, f, norm, delta, d,
                                                   closed_loop_k, reward, k))(scenes, feed, drop, keys)
    terms = jax.tree.map(jnp.sum, terms)
    n_agents = jnp.maximum(terms["agent_count"], 1.0)
    n_map = jnp.maximum(terms["map_count"], 1.0)
    parts = {
        "position": terms["position_sum"] / n_agents,
        "heading": terms["heading_sum"] / n_agents,
        "valid": terms["valid_sum"] / jnp.maximum(terms["valid_count"], 1.0),
        "map": terms["map_sum"] / n_map,
    }
    total = (weights.position * parts["position"] + weights.heading * parts["heading"]
             + weights.valid * parts["valid"] + weights.map * parts["map"])
    if "velocity_sum" in terms:
        parts["velocity"] = terms["velocity_sum"] / jnp.maximum(terms["velocity_count"], 1.0)
        total = total + weights.velocity * parts["velocity"]
    if "modes_sum" in terms:
        parts["modes"] = terms["modes_sum"] / n_agents
        total = total + weights.modes * parts["modes"]
    if "reward_pg_sum" in terms:
        n_reward = jnp.maximum(terms["reward_count"], 1.0)
        for name in ("reward_pg", "reward", "reward_collided", "reward_offroad", "reward_progress"):
            parts[name] = terms[name + "_sum"] / n_reward
        total = total + reward.scale * parts["reward_pg"]
    parts["map_accuracy"] = terms["map_correct"] / n_map
    parts["loss"] = total
    return total, parts


def make_optimizer(train_cfg) -> optax.GradientTransformation:
    """AdamW with linear warm-up then cosine decay, global-norm clipping, and weight decay on kernels only."""
    schedule = optax.warmup_cosine_decay_schedule(
        init_value=0.0, peak_value=train_cfg.learning_rate, warmup_steps=train_cfg.warmup_steps,
        decay_steps=max(train_cfg.steps, train_cfg.warmup_steps + 1), end_value=train_cfg.min_learning_rate)

    def decay_mask(params):
        return jax.tree_util.tree_map_with_path(
            lambda path, x: getattr(path[-1], "key", getattr(path[-1], "name", None)) == "kernel", params)

    return optax.chain(
        optax.clip_by_global_norm(train_cfg.grad_clip),
        optax.adamw(schedule, weight_decay=train_cfg.weight_decay, mask=decay_mask),
    )


class TrainState(NamedTuple):
    """step: i32[]; params: the model's nnx.Param state; opt_state: optax state."""

    step: jax.Array
    params: Any
    opt_state: Any


class Trainer(NamedTuple):
    """A model's static structure with its pure, jitted train and eval steps.

    `train_step(state, scenes) -> (state, metrics)`; `eval_step(params, scenes) -> metrics` (compiled);
    `step_fn`: the train step uncompiled (to wrap or trace it yourself). `merge(params)` rebuilds an NNX model
    from a params state.
    """

    graphdef: Any
    rest: Any
    tx: optax.GradientTransformation
    train_step: Any
    eval_step: Any
    step_fn: Any = None

    def merge(self, params) -> GPD:
        return nnx.merge(self.graphdef, params, self.rest)

    def init_state(self, params) -> TrainState:
        return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=self.tx.init(params))


TRAINABLE = ("all", "sampling_head")


def _learned(config) -> bool:
    """Whether `train.trainable` trains the sampling head alone (checked: the model must have one)."""
    which = str(config.train.trainable)
    if which not in TRAINABLE:
        raise ValueError(f"train.trainable must be one of {TRAINABLE}, got {which!r}")
    if which == "sampling_head" and not samples_agents(config.model):
        raise ValueError("train.trainable = 'sampling_head' trains the sampling head: set model.agent_bins > 0")
    return which == "sampling_head"


def _gpd_steps(graphdef, config, tx, donate: bool):
    """The jitted (train step, eval step, uncompiled train step) of `make_trainer`: (state, scenes, rest) ->
    (state, metrics), (params, scenes, rest) -> metrics; the frozen state `rest` (the map codebook) is an argument,
    so runs of one model and config share them (`compiled_once`). They close over a copy of `config` (they are traced
    later, and a config changed after this call must not reach steps cached under the one they were built for)."""
    config = copy.deepcopy(config)
    weights = config.loss
    h, passes = int(config.model.num_history), int(config.train.rollout_passes)
    feed, drop = float(config.train.map_feedback), float(config.train.lane_context_drop)
    top_k, reward = int(config.train.closed_loop_top_k), RewardOptions.of(config.train)
    seed = int(config.seed)

    def loss_of(p, rest, scenes, step=0):
        # the rollouts' key: the run's seed and the step, so a resumed run draws the same futures
        key = jax.random.fold_in(jax.random.key(seed), step)
        return batch_loss(nnx.merge(graphdef, p, rest), scenes, weights, h, passes, feed, drop, top_k,
                          reward if reward.samples > 0 else None, key)

    head_only = _learned(config)

    def train_step(state: TrainState, scenes: Scene, rest):
        if head_only:  # the gradient of the sampling head alone: no backward pass through the transformer
            learn, keep = nnx.split_state(state.params, MODE_HEAD, ...)
            loss = lambda p: loss_of(nnx.merge_state(p, keep), rest, scenes, state.step)  # noqa: E731
            (_, parts), grads = jax.value_and_grad(loss, has_aux=True)(learn)
            grads = nnx.merge_state(grads, jax.tree.map(jnp.zeros_like, keep))
        else:
            (_, parts), grads = jax.value_and_grad(loss_of, has_aux=True)(state.params, rest, scenes, state.step)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        parts["grad_norm"] = optax.tree.norm(grads)
        return TrainState(step=state.step + 1, params=params, opt_state=opt_state), parts

    return (jax.jit(train_step, donate_argnums=(0,) if donate else ()),
            jax.jit(lambda p, scenes, rest: loss_of(p, rest, scenes)[1]), train_step)


def make_trainer(model: GPD, config, donate: bool = True) -> tuple[Trainer, TrainState]:
    """Splits `model` into a static graph and parameters and binds the jitted steps (shared by runs of one model
    structure and config: `gpd_jax.training.common.compiled_once`) to its frozen state. The config is checked
    here, before anything compiles. `donate`: the train step consumes its input state."""
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    agent_norm_of(config.loss)
    passes, feed = int(config.train.rollout_passes), float(config.train.map_feedback)
    drop = float(config.train.lane_context_drop)
    if not 0.0 <= drop <= 1.0:
        raise ValueError(f"train.lane_context_drop must be a fraction in [0, 1], got {drop}")
    if not 0.0 <= feed <= 1.0:
        raise ValueError(f"train.map_feedback must be a fraction in [0, 1], got {feed}")
    if feed > 0 and passes <= 0:
        raise ValueError("train.map_feedback feeds back the map tokens of the rollout passes: set "
                         "train.rollout_passes > 0")
    top_k = int(config.train.closed_loop_top_k)
    if top_k < 0 or (top_k > 0 and passes > 0):
        raise ValueError(f"train.closed_loop_top_k must be >= 0 and not combined with train.rollout_passes (both "
                         f"choose the future frames' inputs), got {top_k} with rollout_passes {passes}")
    if top_k > 0 and not samples_agents(config.model):
        raise ValueError("train.closed_loop_top_k keeps the closest of the sampling head's top-K cells: set "
                         "model.agent_bins > 0")
    if RewardOptions.of(config.train).samples > 0 and not samples_agents(config.model):
        raise ValueError("train.reward_samples samples the sampling head's cells: set model.agent_bins > 0")
    tx = make_optimizer(config.train)
    if _learned(config):  # the rest neither moves nor decays, and holds no optimizer state
        def labels(p):
            learn, keep = nnx.split_state(p, MODE_HEAD, ...)
            return nnx.merge_state(jax.tree.map(lambda _: "learn", learn), jax.tree.map(lambda _: "keep", keep))

        tx = optax.multi_transform({"learn": tx, "keep": optax.set_to_zero()}, labels)
    train, evaluate, step_fn = compiled_once(("gpd", graphdef, step_key(config), donate),
                                             lambda: _gpd_steps(graphdef, config, tx, donate))
    trainer = Trainer(graphdef=graphdef, rest=rest, tx=tx,
                      train_step=lambda state, scenes: train(state, scenes, rest),
                      eval_step=lambda p, scenes: evaluate(p, scenes, rest),
                      step_fn=lambda state, scenes: step_fn(state, scenes, rest))
    return trainer, trainer.init_state(params)
