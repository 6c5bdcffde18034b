"""Fine-tuning GPD for planning: the paper's single decoder layer on the ego token (`gpd_jax.model.planning_head`)
trained on the logged ego's future (`python train.py --config configs/gpd_planner.py ...`).

A config with a `plan_head` section (configs/gpd_planner.py) builds the GPD with the head attached
(`gpd_jax.checkpoint.build_model`); `train.py` then runs `train_and_evaluate` here instead of the stage-2 loop.

* Targets: for every frame t from `plan_head.first_frame` (default: the current frame, H - 1) to T - 2, the
  logged ego at frames t + 1 .. t + F expressed in the ego frame of frame t, masked where the ego is invalid at
  t or at the target frame and where t + k runs past the scene. The head reads the teacher-forced backbone's
  output tokens of frame t, so one pass trains the plans of every such frame, as a closed-loop simulator asks
  for them (at frame t the ego is no longer at the scene origin).
* Loss: smooth-L1 (beta 1 m) of the positions summed over x and y, plus `plan_head.heading_weight` x smooth-L1
  of the wrapped heading difference, averaged over valid (frame, waypoint) pairs; optionally plus
  `train.gpd_loss_weight` x the GPD's own teacher-forced loss (`gpd_jax.training.step.batch_loss`, a second
  backbone pass) to keep its agent and map predictions while the backbone moves.
* Backbone: `train.backbone_lr_scale` x the learning rate (0: frozen; no gradient flows into it). The head
  always trains at `train.learning_rate` (AdamW, warm-up + cosine, clipping: `step.make_optimizer`). With a
  frozen backbone, `train.cache_features` runs it once per training and validation scene (`cache_features`:
  `PlanFeatures` in host memory) and the steps run the head alone on batches drawn by `feature_batches`
  (configs/gpd_planner.py:frozen).
* Initialisation: `train.init_from` (an exported GPD or a workdir) gives
  the backbone's parameters and must have the same `model` config (a planning-head model gives its head too);
  empty trains everything from scratch (the paper's "without pre-training" ablation,
  configs/gpd_planner.py:scratch).
* Route (`plan_head.route_points` > 0, cached features): the head also reads where the logged ego's path goes
  from each source frame, and a head with `plan_head.candidates = "idm"` chooses among IDM's plans along the route
  from it (`plan_inputs`, as the simulator's observation gives them): its loss is then the cross-entropy of its
  scores against the candidate closest to the log's future (the position and heading losses, and the ADE, are
  reported for the candidate it chooses itself).
* Closed-loop rounds (`plan_head.closed_loop_rounds`, cached features): DAgger; the head drives the simulator on
  training scenes, and the states it reached, labelled with the log's future, join the training scenes
  (`closed_loop_rounds`, `closed_loop_features`; configs/gpd_planner.py:idm_choice).
* Checkpoints, resume, SIGTERM, metrics.jsonl and the export to WORKDIR/export work as in the stage-2 loop
  (`gpd_jax.training.loop`); validation every `train.eval_every` steps over `train.eval_batches` batches of
  `data.val_dir` (default: the first store of `data.dir`) / `data.val_split`: the loss and the ego ADE / FDE of
  the current frame's plan at 3 / 5 / 8 s.

`evaluate_planning` scores an exported plan-head model open loop against the zero-shot GPD (the
`motion_planning` rollout) and constant velocity: `python -m gpd_jax.training.planning evaluate ...`.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import functools
import json
import os
import sys
import time
from typing import Any, Callable

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
import tqdm
from flax import nnx, struct

from gpd_jax.checkpoint import Model, build_model, load_model, model_spec, resolve_tokenizer_path
from gpd_jax.config import config_differences
from gpd_jax.data import loader as data_loader
from gpd_jax.data.errors import DataError
from gpd_jax.fsutil import atomic_write_json, atomic_write_text
from gpd_jax.geometry import route_ahead
from gpd_jax.map_tokenizer import load_tokenizer
from gpd_jax.model import count_params, forward
from gpd_jax.model.planning_head import PlanningHead, to_ego_frame
from gpd_jax.parallel import replicate
from gpd_jax.scene import Scene, wrap_angle
from gpd_jax.spec import EvalError
from gpd_jax.training.common import (MetricsLog, checkpoint_manager, compiled_once, graft_params, restore_state,
                                     step_key)
from gpd_jax.training.loop import check_token_sources, prepare_run, run_steps, store_dirs, validation_dir
from gpd_jax.training.step import TrainState, _smooth_l1, batch_loss, make_optimizer

HEAD = "plan_head"


def is_head_path(path) -> bool:
    """Whether a params-tree path lies in the planning head."""
    return bool(path) and getattr(path[0], "key", getattr(path[0], "name", None)) == HEAD


def split_labels(params):
    """'head' / 'backbone' per leaf of a GPD-with-head params tree (for `optax.multi_transform`)."""
    return jax.tree_util.tree_map_with_path(lambda p, _: "head" if is_head_path(p) else "backbone", params)


# ----------------------------------------------------------------------------------------------- targets, loss
def plan_targets(scene: Scene, num_future: int, first_frame: int, expert: Scene | None = None):
    """The logged ego's next `num_future` poses from every frame, in that frame's ego frame.

    scene: one unbatched Scene [T, A, ...] at the model's rate. expert: the scene whose ego gives the future poses
    (default `scene` itself; a closed-loop run's scene is labelled with its log's ego: `closed_loop_features`).
    Returns (target f32[T-1, F, 3] for source frames t = 0 .. T-2, mask bool[T-1, F]: the ego valid at t and the
    expert's at t + 1 + k, t + 1 + k < T and t >= first_frame)."""
    expert = scene if expert is None else expert
    t_total = scene.xy.shape[-3]
    xy, heading, valid = expert.xy[:, 0], expert.heading[:, 0], expert.valid[:, 0]
    src = jnp.arange(t_total - 1)
    idx = src[:, None] + 1 + jnp.arange(num_future)[None, :]          # [T-1, F]
    inside = idx < t_total
    idx_c = jnp.minimum(idx, t_total - 1)
    pose = jnp.concatenate([scene.xy[:-1, 0], scene.heading[:-1, 0, None]], axis=-1)    # [T-1, 3]
    target = to_ego_frame(xy[idx_c], heading[idx_c], pose)
    mask = inside & valid[idx_c] & scene.valid[:-1, 0, None] & (src >= first_frame)[:, None]
    return target, mask


def backbone_hidden(model, scene: Scene):
    """Teacher-forced output tokens of frames [0, T-1) of one scene: f32[T-1, N, d]."""
    vel = model.input_velocity(scene.velocity)
    tokens = model.embed(scene.xy[:-1], scene.heading[:-1], scene.valid[:-1], scene.map_tokens[:-1],
                         jnp.arange(scene.xy.shape[-3] - 1), None if vel is None else vel[:-1])
    return forward(model, tokens)


def plan_terms(head: PlanningHead, hidden: jax.Array, target: jax.Array, mask: jax.Array,
               current: int, route: jax.Array | None = None,
               candidates: jax.Array | None = None) -> dict[str, jax.Array]:
    """Sums and counts of the planning loss of one scene's plans, and the current frame's ADE.

    hidden f32[K, N, d] output tokens of K source frames; target f32[K, F, 3] and mask bool[K, F] their logged
    ego futures (`plan_targets`); `current`: the index among the K frames of the scene's current frame; route
    f32[K, R, 2] where the route goes from each and candidates f32[K, C, F, 3] the candidate plans from each (a
    route head / a choosing head only: `plan_inputs`). A choosing head's terms add the cross-entropy of its
    scores against the candidate closest to the target (mean distance over the valid waypoints) and how often it
    chose that one; its plan is the candidate it chooses."""
    m = mask.astype(jnp.float32)
    extra = {}
    if candidates is None:
        plan = head(hidden, route)                                                       # [K, F, 3]
    else:
        logits = head.scores(hidden, route, candidates)                                  # [K, C]
        dist = jnp.linalg.norm(candidates[..., :2] - target[:, None, :, :2], axis=-1)    # [K, C, F]
        label = jnp.argmin(jnp.sum(dist * m[:, None], -1), axis=-1)                      # [K]
        pick = jnp.argmax(logits, -1)
        plan = jnp.take_along_axis(candidates, pick[:, None, None, None], axis=1)[:, 0]
        frames = jnp.any(mask, -1).astype(jnp.float32)                                   # frames with a target
        ce = jax.nn.logsumexp(logits, -1) - jnp.take_along_axis(logits, label[:, None], -1)[:, 0]
        extra = {"select_sum": jnp.sum(ce * frames), "select_hits": jnp.sum((pick == label) * frames),
                 "select_count": jnp.sum(frames)}
    pos = jnp.sum(_smooth_l1(plan[..., :2] - target[..., :2]), axis=-1)
    hd = _smooth_l1(wrap_angle(plan[..., 2] - target[..., 2]))
    err = jnp.linalg.norm(plan[..., :2] - target[..., :2], axis=-1)
    cur = m[current]
    return {"position_sum": jnp.sum(pos * m), "heading_sum": jnp.sum(hd * m), "count": jnp.sum(m),
            "ade_sum": jnp.sum(err[current] * cur), "ade_count": jnp.sum(cur), **extra}


def plan_loss_terms(model, scene: Scene, first_frame: int) -> dict[str, jax.Array]:
    """`plan_terms` of one unbatched scene (model view) through the teacher-forced backbone."""
    head: PlanningHead = model.plan_head
    target, mask = plan_targets(scene, head.num_future, first_frame)
    return plan_terms(head, backbone_hidden(model, scene), target, mask, first_frame)


def _weighted(terms: dict[str, jax.Array], config) -> tuple[jax.Array, dict[str, jax.Array]]:
    ph = config.plan_head
    n = jnp.maximum(terms["count"], 1.0)
    parts = {"plan_position": terms["position_sum"] / n, "plan_heading": terms["heading_sum"] / n,
             "plan_ade_current": terms["ade_sum"] / jnp.maximum(terms["ade_count"], 1.0)}
    if "select_sum" in terms:  # a choosing head: its plan is a candidate, its loss the choice's cross-entropy
        k = jnp.maximum(terms["select_count"], 1.0)
        parts["plan_select"], parts["plan_select_accuracy"] = terms["select_sum"] / k, terms["select_hits"] / k
        return parts["plan_select"], parts
    total = float(ph.position_weight) * parts["plan_position"] + float(ph.heading_weight) * parts["plan_heading"]
    return total, parts


def plan_batch_loss(model, scenes: Scene, config) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Weighted planning loss over a batch (leading dim B) and its parts (plus the GPD's own loss with
    `train.gpd_loss_weight` > 0)."""
    first = first_frame(config)
    terms = jax.tree.map(jnp.sum, jax.vmap(lambda s: plan_loss_terms(model, s, first))(scenes))
    total, parts = _weighted(terms, config)
    gw = float(config.train.gpd_loss_weight)
    if gw > 0:
        gpd_total, gpd_parts = batch_loss(model, scenes, config.loss, int(config.model.num_history))
        parts.update({f"gpd_{k}": v for k, v in gpd_parts.items()})
        total = total + gw * gpd_total
    parts["loss"] = total
    return total, parts


@struct.dataclass
class PlanFeatures:
    """A frozen backbone's teacher-forced output tokens, cached with the plan targets read from them
    (`train.cache_features`: the head trains on these, never running the backbone again).

    Attributes:
      hidden: f32[..., K, N, d] output tokens of source frames first_frame .. T-2 (K = T-1-first_frame).
      target: f32[..., K, F, 3] the logged ego's next F poses in each source frame's ego frame.
      mask: bool[..., K, F] valid targets (`plan_targets`).
      route: f32[..., K, R, 2] where the route goes from each source frame (`plan_inputs`; a route head only).
      candidates: f32[..., K, C, F, 3] the candidate plans from each source frame (`plan_inputs`; a choosing head
        only).
    """

    hidden: jax.Array
    target: jax.Array
    mask: jax.Array
    route: jax.Array | None = None
    candidates: jax.Array | None = None


def feature_batch_loss(model, feats: PlanFeatures, config) -> tuple[jax.Array, dict[str, jax.Array]]:
    """`plan_batch_loss` of cached features (leading dim B): the head alone runs."""
    terms = jax.tree.map(jnp.sum, jax.vmap(lambda h, t, m, r, b: plan_terms(model.plan_head, h, t, m, 0, r, b))(
        feats.hidden, feats.target, feats.mask, feats.route, feats.candidates))
    total, parts = _weighted(terms, config)
    parts["loss"] = total
    return total, parts


@jax.jit
def _features_jit(graphdef, params, rest, scenes: Scene, expert: Scene | None = None):
    """Teacher-forced output tokens, plan targets and masks of every source frame: Scene [B, T, ...] ->
    (f32[B, T-1, N, d], f32[B, T-1, F, 3], bool[B, T-1, F]); targets from `expert`'s ego where given."""
    module = nnx.merge(graphdef, params, rest)
    num_future = module.plan_head.num_future

    def one(s, e):
        target, mask = plan_targets(s, num_future, 0, e)
        return backbone_hidden(module, s), target, mask

    return jax.vmap(one)(scenes, scenes if expert is None else expert)


@functools.partial(jax.jit, static_argnames=("spec", "num_points", "spacing_m", "speeds", "num_future"))
def _inputs_jit(stored: Scene, view: Scene, spec, num_points: int, spacing_m: float, speeds: tuple,
                num_future: int):
    """`plan_inputs` of a batch (stored Scene [B, Ts, ...], view Scene [B, T, ...]): (route f32[B, T-1, R, 2] or
    None, candidates f32[B, T-1, C, F, 3] or None; C = len(speeds), none without speeds)."""
    from gpd_jax.sim.agents import idm_route_plan, make_paths

    c = spec.full_history - 1

    def one(sx, sh, sv, x, h, v, vel, size):
        path = make_paths(sx[c:, :1], sh[c:, :1], sv[c:, :1], jnp.zeros(sv[c:, :1].shape, sx.dtype))
        rxy, rh, rs = path.xy[0], path.heading[0], path.s[0]
        poses = jnp.concatenate([x[:-1, 0], h[:-1, 0, None]], -1)                       # [T-1, 3]
        route = (jax.vmap(lambda q: route_ahead(rxy, rs, q, num_points, spacing_m))(poses)
                 if num_points else None)
        if not speeds:
            return route, None
        plan = jax.vmap(lambda q, cx, cvel, cv: idm_route_plan(
            rxy, rh, rs, q, cx, cvel, cv, size, num_future, spec.frame_stride, spec.stored_period_s,
            jnp.asarray(speeds, jnp.float32)))(poses, x[:-1], vel[:-1], v[:-1])          # [T-1, C, F, 3]
        return route, to_ego_frame(plan[..., :2], plan[..., 2], poses[:, None])

    return jax.vmap(one)(stored.xy, stored.heading, stored.valid, view.xy, view.heading, view.valid, view.velocity,
                         view.size)


def plan_inputs(stored: Scene, view: Scene, spec, config) -> tuple[np.ndarray | None, np.ndarray | None]:
    """What a planning head reads beside the tokens at each model frame but the last, as the simulator's
    observation gives it (`gpd_jax.sim.Observation`; the route is the logged ego's path from the current frame
    on): stored Scene [B, Ts, ...] at the stored rate, view Scene [B, T, ...] at the model's rate (the ego where
    it is, which in a closed-loop round is where the head drove it) ->

    * route f32[B, T-1, R, 2]: where the route goes from each frame's ego pose, in its frame
      (`gpd_jax.geometry.route_ahead`), or None for a head without a route (`plan_head.route_points` = 0);
    * candidates f32[B, T-1, C, F, 3]: IDM's plans along the route from each frame at the C target speeds
      `plan_head.idm_speeds` (`gpd_jax.sim.agents.idm_route_plan`, leaders the view's slots at that frame) in the
      ego's frame, or None for a head that draws its plan (`plan_head.candidates` empty)."""
    ph = config.plan_head
    r, choose = int(ph.route_points), str(ph.candidates)
    if r == 0 and not choose:
        return None, None
    if choose and view.velocity is None:
        raise ValueError("plan_head.candidates: IDM's plans start from the ego's velocity; the model reads none "
                         "(model.velocity_inputs = False)")
    arrays = lambda sc: jax.tree.map(jnp.asarray, sc.replace(polylines=None, polyline_valid=None))
    speeds = tuple(float(v) for v in ph.idm_speeds) if choose else ()
    route, cands = _inputs_jit(arrays(stored), arrays(view), spec, r, float(ph.route_spacing_m), speeds,
                               int(ph.num_future))
    return (None if route is None else np.asarray(route)), (None if cands is None else np.asarray(cands))


def _from(first: int, *arrays):
    """Source frames `first` .. T-2 of each [B, T-1, ...] array (None stays None)."""
    return tuple(None if a is None else a[:, first:] for a in arrays)


def cache_features(model, config, data_dir: str, split: str, batch_size: int = 32,
                   quiet: bool = False) -> PlanFeatures:
    """Teacher-forced backbone outputs and plan targets of every scene of `data_dir/split` (numpy, host memory:
    S x K x N x d floats, 0.33 MB per scene for the shipped models' size), for a frozen backbone."""
    first = first_frame(config)
    spec = model_spec(config)
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    n = len(data_loader.SplitSource(data_dir, split))
    out: list[PlanFeatures] = []
    bar = tqdm.tqdm(total=n, disable=quiet, desc=f"features {split}", dynamic_ncols=True, mininterval=2.0)
    for lo in range(0, n, batch_size):
        stored = data_loader.load_split(data_dir, split, indices=range(lo, min(n, lo + batch_size)))
        view = spec.view(stored)
        if not np.all(view.map_valid):
            raise DataError(os.path.join(data_dir, split), "no map tokens at some of the model's frames; encode "
                            f"them: python -m gpd_jax.map_tokenizer encode --data {data_dir} --frame-stride "
                            f"{config.data.frame_stride}")
        h, t, m = jax.device_get(_features_jit(graphdef, params, rest, jax.tree.map(jnp.asarray, view)))
        out.append(PlanFeatures(h[:, first:], t[:, first:], m[:, first:],
                                *_from(first, *plan_inputs(stored, view, spec, config))))
        bar.update(view.xy.shape[0])
    bar.close()
    return jax.tree.map(lambda *xs: np.concatenate(xs), *out)


def closed_loop_features(world: Model, policy, params, scenes: Scene, key: jax.Array, first: int,
                         batch_size: int = 16) -> PlanFeatures:
    """The planning head drives the closed-loop simulator and is labelled where it went (DAgger): states the head
    reaches itself, with the log's future as their targets.

    world: the GPD-with-head as a `Model` (its spec and map tokenizer; its backbone is the head's); policy: its
    `gpd_jax.sim.gpd_head_policy`, run with `params` (so every round reuses one compiled run); scenes: Scene [n,
    ...] at the stored rate with lane polylines. Each scene runs with log-replay agents and the plan tracker
    (`gpd_jax.sim.run`); the model-rate frames it reached (the ego where the head drove it, the map encoded around
    it) go through the frozen backbone, and the targets of frame t are the logged ego's next poses in the reached
    ego's frame at t (`plan_targets` with the log as the expert). Returns PlanFeatures [n, K, ...] of source frames
    first .. T-2, as `cache_features` (numpy)."""
    from gpd_jax import sim

    n = int(np.shape(scenes.xy)[0])
    batch_size = min(batch_size, n)
    graphdef, _, rest = nnx.split(world.module, nnx.Param, ...)
    out: list[PlanFeatures] = []
    for lo in range(0, n, batch_size):
        hi = min(n, lo + batch_size)
        sub = jax.tree.map(lambda x: np.asarray(x)[lo:hi], scenes)
        if hi - lo < batch_size:  # one batch shape: one compiled run
            sub = jax.tree.map(lambda x: np.concatenate([x, np.repeat(x[-1:], batch_size - (hi - lo), 0)]), sub)
        sims = sim.make_sim_scenes(world, sub)
        run = sim.run(world, sims, policy, jax.random.fold_in(key, lo), agents="log", policy_params=params)
        reached = sims.view.replace(xy=run.xy, heading=run.heading, valid=run.valid, velocity=run.velocity,
                                    map_tokens=run.map_tokens)
        h, t, m = jax.device_get(_features_jit(graphdef, params, rest, reached, sims.view))
        k = hi - lo
        inputs = plan_inputs(sub, reached, world.spec, world.config)
        out.append(PlanFeatures(h[:k, first:], t[:k, first:], m[:k, first:],
                                *_from(first, *(None if x is None else x[:k] for x in inputs))))
    return jax.tree.map(lambda *xs: np.concatenate(xs), *out)


def closed_loop_steps(config) -> list[int]:
    """The steps at which the closed-loop rounds run: round r of R at r x steps / (R + 1) (r = 1 .. R)."""
    rounds, steps = int(config.plan_head.closed_loop_rounds), int(config.train.steps)
    return [r * steps // (rounds + 1) for r in range(1, rounds + 1)]


def first_frame(config) -> int:
    """The first frame whose plan is trained (`plan_head.first_frame`; -1: the current frame, H - 1)."""
    f = int(config.plan_head.first_frame)
    h = int(config.model.num_history)
    f = h - 1 if f < 0 else f
    if not 0 <= f < int(config.model.num_frames) - 1:
        raise ValueError(f"plan_head.first_frame {f} outside [0, {int(config.model.num_frames) - 2}]")
    return f


# ----------------------------------------------------------------------------------------------- optimizer, step
def make_plan_optimizer(config) -> optax.GradientTransformation:
    """The head at `train.learning_rate`, the backbone at `train.backbone_lr_scale` x it (0: frozen)."""
    tc = config.train
    scale = float(tc.backbone_lr_scale)
    if scale < 0:
        raise ValueError(f"train.backbone_lr_scale must be >= 0, got {scale}")
    head_tx = make_optimizer(tc)
    if scale == 0:
        backbone_tx = optax.set_to_zero()
    else:
        bc = ml_collections.ConfigDict(tc.to_dict())
        bc.learning_rate = float(tc.learning_rate) * scale
        bc.min_learning_rate = float(tc.min_learning_rate) * scale
        backbone_tx = make_optimizer(bc)
    return optax.multi_transform({"head": head_tx, "backbone": backbone_tx}, split_labels)


class PlanTrainer:
    """The jitted planning train / eval steps of a GPD-with-head (`train_step(state, batch)`,
    `eval_step(params, batch)`), pure functions of (params, opt_state, batch). The batch is a Scene [B, ...] in the
    model's view, or with `features` (frozen backbone only) `PlanFeatures` [B, ...] of `cache_features`."""

    def __init__(self, model, config, donate: bool = True, features: bool = False):
        if not isinstance(getattr(model, HEAD, None), PlanningHead):
            raise ValueError("the model has no planning head: the config needs a `plan_head` section")
        self.graphdef, params, self.rest = nnx.split(model, nnx.Param, ...)
        self.tx = make_plan_optimizer(config)
        frozen = float(config.train.backbone_lr_scale) == 0
        if frozen and float(config.train.gpd_loss_weight) > 0:
            raise ValueError("train.gpd_loss_weight keeps the backbone's own predictions while it moves; with a "
                             "frozen backbone (train.backbone_lr_scale = 0) it does nothing: set it to 0")
        if features and not frozen:
            raise ValueError("train.cache_features needs a frozen backbone (train.backbone_lr_scale = 0): cached "
                             "backbone outputs go stale when the backbone moves")
        steps = compiled_once(("plan_head", self.graphdef, step_key(config), donate, features),
                              lambda: _plan_steps(self.graphdef, config, self.tx, frozen, features, donate))
        self.train_step = lambda state, batch: steps[0](state, batch, self.rest)
        self.eval_step = lambda params, batch: steps[1](params, batch, self.rest)
        self.initial_params = params

    def init_state(self, params) -> TrainState:
        return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=self.tx.init(params))


def _plan_steps(graphdef, config, tx, frozen: bool, features: bool, donate: bool):
    """The jitted (train step, eval step) of `PlanTrainer`: (state, batch, rest) -> (state, metrics) and
    (params, batch, rest) -> metrics (the frozen state `rest` an argument, so runs share them: `compiled_once`).
    The steps close over a copy of `config`: they are traced later, and a config changed after this call must not
    reach steps cached under the config they were built for."""
    config = copy.deepcopy(config)
    batch_loss_fn = feature_batch_loss if features else plan_batch_loss

    def loss_of(p, rest, batch):
        if frozen:  # no gradient into the backbone: XLA drops its backward pass
            p = jax.tree_util.tree_map_with_path(lambda k, x: x if is_head_path(k) else jax.lax.stop_gradient(x), p)
        return batch_loss_fn(nnx.merge(graphdef, p, rest), batch, config)

    def train_step(state: TrainState, batch, rest):
        (_, parts), grads = jax.value_and_grad(loss_of, has_aux=True)(state.params, rest, batch)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        parts["grad_norm"] = optax.tree.norm(grads)
        return TrainState(step=state.step + 1, params=optax.apply_updates(state.params, updates),
                          opt_state=opt_state), parts

    return (jax.jit(train_step, donate_argnums=(0,) if donate else ()),
            jax.jit(lambda p, batch, rest: loss_of(p, rest, batch)[1]))


def pretrained_params(path: str, config, template):
    """`template` (a GPD-with-head params tree) with every backbone leaf taken from the GPD at `path` (exported or
    a workdir; same `model` config, map tokenizer path aside). The head keeps its initialisation, unless `path` is
    a planning-head model of the same head shape (a head that chooses among candidate plans, `plan_head.candidates`,
    and one that draws its plan are different heads): then its head goes on training (closed-loop rounds on a
    trained head), a route input it lacks starting from its initialisation."""
    src = load_model(path)
    diff = config_differences(config.model, src.config.model, ignore=("map_tokenizer",))
    if diff:
        raise ValueError(f"train.init_from {path}: its model config differs in {diff}")
    shape_keys = ("num_future", "num_heads", "ffn_dim", "position_scale")
    choosing = lambda h: (str(h.candidates), tuple(map(float, h.idm_speeds)) if h.candidates else ())
    with_head = HEAD in src.config and all(src.config[HEAD][k] == config[HEAD][k] for k in shape_keys) and (
        choosing(src.config[HEAD]) == choosing(config[HEAD]))
    new_route = with_head and int(src.config[HEAD].route_points) != int(config[HEAD].route_points)

    def fresh(p) -> bool:  # leaves that keep their initialisation
        if not with_head:
            return is_head_path(p)
        return new_route and is_head_path(p) and "route_" in jax.tree_util.keystr(p)

    out, missing = graft_params(template, src.params, fresh)
    if missing:
        raise ValueError(f"train.init_from {path}: no parameters for {missing[:5]}")
    return out


# ----------------------------------------------------------------------------------------------- validation
class PlanValidator:
    """Loss and current-frame ego ADE / FDE of the plans over fixed validation batches."""

    def __init__(self, config, trainer: PlanTrainer, data_dir: str):
        tc = config.train
        split = config.data.val_split
        if not os.path.isdir(os.path.join(data_dir, split)):
            raise DataError(os.path.join(data_dir, split), "no validation split (set data.val_dir / "
                            "data.val_split, or train.eval_every=0)")
        n_val = len(data_loader.SplitSource(data_dir, split))
        bs = int(tc.batch_size)
        n = min(int(tc.eval_batches), n_val // bs)
        spec = model_spec(config)
        self.trainer, self.batches = trainer, []
        if n:
            it = data_loader.make_loader(data_dir, split, bs, seed=12345, num_epochs=1, num_threads=2, prefetch=0)
            self.batches = [jax.tree.map(jnp.asarray, spec.view(next(it))) for _ in range(n)]
            it.close()

    @classmethod
    def of_features(cls, trainer: PlanTrainer, feats: PlanFeatures, batch_size: int) -> "PlanValidator":
        """A validator over every scene of cached features (the last partial batch dropped)."""
        self = cls.__new__(cls)
        n = feats.hidden.shape[0] // batch_size
        self.trainer = trainer
        self.batches = [jax.tree.map(lambda x: jnp.asarray(x[i * batch_size:(i + 1) * batch_size]), feats)
                        for i in range(n)]
        return self

    def __call__(self, params) -> dict[str, float]:
        acc: dict[str, float] = {}
        for b in self.batches:
            for k, v in jax.device_get(self.trainer.eval_step(params, b)).items():
                acc[k] = acc.get(k, 0.0) + float(v) / len(self.batches)
        return acc


class FeaturePool:
    """Training scenes as cached features: the logged ones, then those of each closed-loop round as it comes
    (`add`); `take(indices)` gathers scenes across the parts without copying the pool."""

    def __init__(self, feats: PlanFeatures):
        self.parts = [feats]

    def __len__(self) -> int:
        return sum(p.hidden.shape[0] for p in self.parts)

    def add(self, feats: PlanFeatures) -> None:
        self.parts.append(feats)

    def take(self, indices: np.ndarray) -> PlanFeatures:
        got, lo = [], 0
        for p in self.parts:
            n = p.hidden.shape[0]
            sel = indices[(indices >= lo) & (indices < lo + n)] - lo
            if sel.size:
                got.append(jax.tree.map(lambda x: x[sel], p))
            lo += n
        return jax.tree.map(lambda *xs: np.concatenate(xs), *got)


def feature_batches(pool: FeaturePool | PlanFeatures, batch_size: int, seed: int,
                    before: Callable[[int, Any], None] | None = None) -> Callable[[int, Any], PlanFeatures]:
    """`next_batch(step, params)` for `run_steps`: `batch_size` scenes of the pool drawn without replacement by a
    generator seeded with (seed, step), so a resumed run draws exactly the batches it would have. `before(step,
    params)` runs first (the closed-loop rounds grow the pool there)."""
    pool = pool if isinstance(pool, FeaturePool) else FeaturePool(pool)
    if len(pool) < batch_size:
        raise ValueError(f"train.batch_size {batch_size} is larger than the {len(pool)} training scenes")

    def next_batch(step: int, params=None) -> PlanFeatures:
        if before is not None:
            before(step, params)
        idx = np.sort(np.random.default_rng([int(seed), int(step)]).choice(len(pool), batch_size, replace=False))
        return pool.take(idx)

    return next_batch


def closed_loop_rounds(config, pool: FeaturePool, world: Model, data_dir: str, workdir: str, lead: bool,
                       quiet: bool) -> Callable[[int, Any], None]:
    """`before(step, params)` for `feature_batches`: at each closed-loop step (`closed_loop_steps`) the head of
    that step drives `plan_head.closed_loop_scenes` training scenes (a seeded draw per round) and the reached
    states join the pool (`closed_loop_features`). Each round is kept in WORKDIR/closed_loop/round_R.npz, so a
    resumed run reloads the rounds it passed and redoes none (the head of a later step cannot redo them)."""
    from gpd_jax import sim

    ph, split = config.plan_head, config.data.train_split
    steps = closed_loop_steps(config)
    n_scenes = int(ph.closed_loop_scenes)
    total = len(data_loader.SplitSource(data_dir, split))
    first = first_frame(config)
    policy = sim.gpd_head_policy(world)
    folder = os.path.join(workdir, "closed_loop")
    done: set[int] = set()

    def path(r: int) -> str:
        return os.path.join(folder, f"round_{r}.npz")

    def before(step: int, params) -> None:
        for r, at in enumerate(steps, 1):
            if r in done or step < at:
                continue
            if os.path.exists(path(r)):
                with np.load(path(r), allow_pickle=False) as z:
                    feats = PlanFeatures(**{f.name: z[f.name] if f.name in z else None
                                            for f in dataclasses.fields(PlanFeatures)})
            elif step == at:
                t0 = time.perf_counter()
                idx = np.sort(np.random.default_rng([int(config.seed), 7, r]).choice(
                    total, min(n_scenes, total), replace=False))
                scenes = data_loader.load_split(data_dir, split, with_polylines=True, indices=idx)[0]
                feats = closed_loop_features(world, policy, params, scenes,
                                             jax.random.fold_in(jax.random.key(int(config.seed)), r), first)
                if lead:
                    os.makedirs(folder, exist_ok=True)
                    tmp = path(r) + ".tmp.npz"
                    np.savez(tmp, **{f.name: getattr(feats, f.name) for f in dataclasses.fields(feats)
                                     if getattr(feats, f.name) is not None})
                    os.replace(tmp, path(r))
                if lead and not quiet:
                    print(f"step {step}: closed-loop round {r}: the head drove {len(idx)} scenes "
                          f"({time.perf_counter() - t0:.0f} s); {len(pool) + len(idx)} training scenes")
            else:
                raise DataError(path(r), f"closed-loop round {r} (step {at}) is missing and the run is past it "
                                f"(step {step}); start a new workdir")
            pool.add(feats)
            done.add(r)

    return before


# ----------------------------------------------------------------------------------------------- training
def train_and_evaluate(config: ml_collections.ConfigDict, workdir: str, stop_after: int | None = None,
                       quiet: bool = False) -> dict[str, Any]:
    """Trains the planning head of `config` (and the backbone, unless frozen) in `workdir`, resuming from its
    latest checkpoint. Same arguments and return value as `gpd_jax.training.loop.train_and_evaluate`."""
    tc = config.train
    if HEAD not in config:
        raise ValueError("the config has no plan_head section (configs/gpd_planner.py)")
    use_features = bool(tc.cache_features)
    if int(config.plan_head.route_points) > 0 and not use_features:
        raise ValueError("plan_head.route_points: the route is read from the stored-rate log when the backbone's "
                         "outputs are cached: set train.cache_features = True (and train.backbone_lr_scale = 0)")
    if config.plan_head.candidates and not use_features:
        raise ValueError("plan_head.candidates: the candidate plans are computed from the stored-rate log when the "
                         "backbone's outputs are cached: set train.cache_features = True (and "
                         "train.backbone_lr_scale = 0)")
    if int(config.plan_head.closed_loop_rounds) > 0 and not use_features:
        raise ValueError("plan_head.closed_loop_rounds trains the head on states it reaches itself over a frozen "
                         "backbone: it needs train.cache_features = True (and train.backbone_lr_scale = 0)")
    if int(config.plan_head.closed_loop_rounds) > 0 and not config.model.map_tokenizer:
        raise ValueError("plan_head.closed_loop_rounds: the simulator encodes the map around the ego with the "
                         "model's map tokenizer, and model.map_tokenizer is empty")
    data_dir, n_train, mesh, pindex = prepare_run(config)
    val_dir = validation_dir(config, data_dir)
    first_frame(config)
    check_token_sources(config, data_dir)

    lead = pindex == 0
    os.makedirs(workdir, exist_ok=True)
    cfg_path = os.path.join(workdir, "config.json")
    mine = json.loads(config.to_json())
    if lead:
        if os.path.exists(cfg_path):
            with open(cfg_path) as f:
                old = json.load(f)
            if old.get("model") != mine.get("model") or old.get(HEAD) != mine.get(HEAD):
                raise ValueError(f"{cfg_path}: the workdir holds a run with a different model or plan_head config; "
                                 "use a new --workdir")
        atomic_write_text(cfg_path, config.to_json(indent=2))

    spec = model_spec(config)
    model = build_model(config)
    trainer = PlanTrainer(model, config, features=use_features)
    state = trainer.init_state(trainer.initial_params)
    mgr = checkpoint_manager(workdir, int(tc.keep_checkpoints))
    if mgr.latest_step() is not None:
        state = TrainState(**restore_state(mgr, state._asdict()))
    elif tc.init_from:
        state = trainer.init_state(pretrained_params(str(tc.init_from), config, trainer.initial_params))
    start = int(state.step)
    next_batch, validator = None, None
    if use_features:  # the frozen backbone runs once per scene, here; the steps run the head alone
        if len(store_dirs(data_dir)) > 1:
            raise ValueError(f"train.cache_features reads one store, not the mixture {data_dir}; build one store "
                             "or train without cached features")
        backbone = nnx.merge(trainer.graphdef, state.params, trainer.rest)
        t0 = time.perf_counter()
        feats = cache_features(backbone, config, data_dir, config.data.train_split, quiet=quiet or not lead)
        pool = FeaturePool(feats)
        before = None
        if int(config.plan_head.closed_loop_rounds) > 0:
            tok = load_tokenizer(resolve_tokenizer_path(config.model.map_tokenizer))
            world = Model.from_module(backbone, config, tokenizer=tok)
            before = closed_loop_rounds(config, pool, world, data_dir, workdir, lead, quiet)
        next_batch = feature_batches(pool, int(tc.batch_size), int(config.seed), before)
        if int(tc.eval_every) > 0:
            validator = PlanValidator.of_features(
                trainer, cache_features(backbone, config, val_dir, config.data.val_split, quiet=quiet or not lead),
                int(tc.batch_size))
        if lead and not quiet:
            print(f"cached the frozen backbone's outputs in {time.perf_counter() - t0:.0f} s "
                  f"({feats.hidden.nbytes / 2**20:.0f} MiB for {feats.hidden.shape[0]} training scenes)")
    state = replicate(state, mesh)
    log = MetricsLog(workdir, enabled=lead)
    if lead:
        head_n = count_params(model.plan_head)
        print(f"resumed {workdir} at step {start}" if start else
              f"training a planning head of {head_n:,} parameters on a backbone of {count_params(model) - head_n:,} "
              f"({'frozen' if float(tc.backbone_lr_scale) == 0 else f'lr x {float(tc.backbone_lr_scale):g}'}, "
              f"{'pre-trained: ' + str(tc.init_from) if tc.init_from else 'from scratch'}) on {n_train} scenes")

    if not use_features and int(tc.eval_every) > 0:
        validator = PlanValidator(config, trainer, val_dir)
    return run_steps(config, trainer, state, data_dir=data_dir, workdir=workdir, mesh=mesh, spec=spec, mgr=mgr,
                     log=log, start=start, stop_after=stop_after, lead=lead, quiet=quiet, desc="plan head",
                     validate=None if validator is None else (lambda params, _step: validator(params)),
                     postfix=lambda parts: {"ade": f"{parts['plan_ade_current']:.2f}"},
                     summary=lambda ev: (f"loss={ev.get('loss', float('nan')):.4g} "
                                         f"plan_ade_current={ev.get('plan_ade_current', float('nan')):.3f} m"),
                     next_batch=next_batch)


# ----------------------------------------------------------------------------------------------- evaluation
def current_frame_plans(model: Model, view: Scene, params=None, route=None, candidates=None) -> jax.Array:
    """The head's plan from the current frame of scenes in the model's view (only history frames are read):
    Scene [S, ...] -> f32[S, F, 3] in the scene frame (the current ego frame). route f32[S, R, 2], candidates
    f32[S, C, F, 3]: where the route goes and the candidate plans from the current frame (a route head / a
    choosing head only: `plan_inputs`)."""
    h = model.spec.num_history
    params = model.params if params is None else params
    as_j = lambda x: None if x is None else jnp.asarray(x)
    return _plans_jit(model.graphdef, params, model.rest, jax.tree.map(jnp.asarray, view.slice_frames(0, h + 1)),
                      as_j(route), as_j(candidates))


@jax.jit
def _plans_jit(graphdef, params, rest, scenes: Scene, route=None, candidates=None):
    module = nnx.merge(graphdef, params, rest)
    h = scenes.xy.shape[-3] - 1
    # Frames [0, H) are pushed through; the extra frame only gives backbone_hidden its T - 1 = H frames.
    hidden = jax.vmap(lambda s: backbone_hidden(module, s))(scenes)[:, h - 1]
    return module.plan_head(hidden, route, candidates)


def evaluate_planning(head_model: Model, view: Scene, full: Scene, baseline: Model | None = None,
                      key: jax.Array | None = None, batch_size: int = 32) -> dict[str, dict[str, dict[str, float]]]:
    """Open-loop ego ADE / FDE (m) and ego collision rate (%, against the logged agents, own boxes) at the
    model's horizons, scenes whose ego is valid at the current frame, for: the head's plan from the current
    frame ("plan_head"), the zero-shot GPD's `motion_planning` rollout of `baseline` (map and agents from the
    log, the ego generated; "gpd_motion_planning") and constant velocity at the stored rate.

    view: Scene [S, ...] in the model's view with map tokens (`Model.prepare`); full: the same scenes at the
    stored rate. Raises EvalError if the baseline reads other frames. Returns {predictor: {horizon label: {ego_ade, ego_fde, ego_collision}}}.
    """
    from gpd_jax.decoding import rollout_model
    from gpd_jax.evaluation.scoring import baseline_predictions
    from gpd_jax.tasks import make_tasks
    from gpd_jax.metrics.agents import accumulate, agent_metric_sums, reduce_agent_metrics

    spec = head_model.spec
    h, f = spec.num_history, spec.num_future
    s_total = view.xy.shape[0]
    key = jax.random.key(0) if key is None else key
    sums: dict[str, Any] = {}

    def score(name, xy, heading, v):
        mask = np.zeros(v.valid.shape[:1] + v.valid.shape[-1:], bool)
        mask[:, 0] = np.asarray(v.valid[:, spec.current, 0])
        s = agent_metric_sums(jnp.asarray(xy), jnp.asarray(heading), v.xy, v.valid, v.size, num_history=h,
                              eval_mask=mask, horizons=spec.horizons, variant="corrected", dt=spec.frame_period_s)
        sums[name] = accumulate(sums.get(name), s)

    for lo in range(0, s_total, batch_size):
        sl = lambda x: x[lo:lo + batch_size]
        v = jax.tree.map(lambda x: jnp.asarray(sl(x)), view.replace(polylines=None, polyline_valid=None))
        fb = jax.tree.map(sl, full)
        route, cands = (None if x is None else x[:, h - 1] for x in plan_inputs(fb, v, spec, head_model.config))
        plan = np.asarray(current_frame_plans(head_model, v, route=route, candidates=cands))[:, :f]
        xy, heading = np.array(v.xy), np.array(v.heading)
        xy[:, h:h + plan.shape[1], 0] = plan[..., :2]
        heading[:, h:h + plan.shape[1], 0] = plan[..., 2]
        score("plan_head", xy, heading, v)
        if baseline is not None:
            bspec = baseline.spec
            if (bspec.num_frames, bspec.num_history, bspec.frame_stride) != (spec.num_frames, h, spec.frame_stride):
                raise EvalError("the baseline GPD reads other frames than the plan-head model")
            tasks = jax.tree.map(jnp.asarray, make_tasks(["motion_planning"], bspec.num_map_tokens,
                                                         bspec.num_agents))
            out = rollout_model(baseline, baseline.prepare(fb), tasks, jax.random.fold_in(key, lo))
            bxy, bh = np.array(v.xy), np.array(v.heading)  # the baseline may read fewer agent slots
            bxy[:, h:, 0], bh[:, h:, 0] = np.asarray(out.xy[:, 0, h:, 0]), np.asarray(out.heading[:, 0, h:, 0])
            score("gpd_motion_planning", bxy, bh, v)
        cv_xy, cv_heading, _ = baseline_predictions(fb, spec, with_lanes=False)["constant_velocity"]
        score("constant_velocity", cv_xy, cv_heading, v)
    keep = ("ego_ade", "ego_fde", "ego_collision")
    return {name: {hl: {k: val for k, val in d.items() if k in keep} for hl, d in reduce_agent_metrics(s).items()}
            for name, s in sums.items()}


def main(argv=None) -> int:
    """`python -m gpd_jax.training.planning evaluate --checkpoint DIR [DIR ...] --data STORE [--split val]
    [--baseline NAME_OR_DIR] [--num N] [--out JSON]`: open-loop ego ADE / FDE of plan-head models."""
    p = argparse.ArgumentParser(prog="python -m gpd_jax.training.planning", description=main.__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("evaluate", help="open-loop ego ADE / FDE of plan heads, zero-shot GPD, constant velocity")
    e.add_argument("--checkpoint", nargs="+", required=True, help="exported plan-head models or workdirs")
    e.add_argument("--data", required=True)
    e.add_argument("--split", default="val")
    e.add_argument("--baseline", default=None, help="the zero-shot GPD (default: the shipped model)")
    e.add_argument("--num", type=int, default=None, help="first N scenes (default: the whole split)")
    e.add_argument("--out", default=None, help="write the figures here as JSON")
    args = p.parse_args(argv)
    try:
        models = {c: load_model(c) for c in args.checkpoint}
        for c, m in models.items():
            if not isinstance(getattr(m.module, HEAD, None), PlanningHead):
                raise ValueError(f"{c}: not a plan-head model (its config has no plan_head section)")
        baseline = load_model(args.baseline)
        if not os.path.isdir(os.path.join(args.data, args.split)):
            raise FileNotFoundError(f"split {args.split!r} not found in {args.data}")
        n = len(data_loader.SplitSource(args.data, args.split))
        full = data_loader.load_split(args.data, args.split, indices=range(n if args.num is None else min(n, args.num)))
        views = {c: m.prepare(full) for c, m in models.items()}
    except (FileNotFoundError, ValueError, DataError) as err:  # EvalError is a ValueError
        print(f"error: {err}", file=sys.stderr)
        return 2
    results: dict[str, Any] = {"data": os.path.abspath(args.data), "split": args.split,
                               "scenarios": int(full.xy.shape[0]), "baseline": baseline.path, "models": {}}
    first = True
    for c, m in models.items():
        t0 = time.perf_counter()
        r = evaluate_planning(m, views[c], full, baseline if first else None)
        if first:
            results["gpd_motion_planning"] = r.pop("gpd_motion_planning")
            results["constant_velocity"] = r.pop("constant_velocity")
        else:
            r.pop("constant_velocity")
        results["models"][c] = r["plan_head"]
        print(f"{c}: {time.perf_counter() - t0:.1f} s")
        first = False
    rows = [(f"plan head: {c}", r) for c, r in results["models"].items()]
    rows += [("GPD zero-shot (motion_planning)", results["gpd_motion_planning"]),
             ("constant velocity (10 Hz)", results["constant_velocity"])]
    labels = list(rows[0][1])
    print(f"{results['scenarios']} scenes of {args.data}/{args.split}; ego ADE / FDE (m), ego collision (%)")
    print("| predictor | " + " | ".join(f"ADE {l}" for l in labels) + " | " + " | ".join(f"FDE {l}" for l in labels)
          + " | " + " | ".join(f"coll. {l}" for l in labels) + " |")
    print("|---" * (1 + 3 * len(labels)) + "|")
    for name, r in rows:
        print(f"| {name} | " + " | ".join(f"{r[l]['ego_ade']:.2f}" for l in labels) + " | "
              + " | ".join(f"{r[l]['ego_fde']:.2f}" for l in labels) + " | "
              + " | ".join(f"{r[l]['ego_collision']:.1f}" for l in labels) + " |")
    if args.out:
        atomic_write_json(args.out, results, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
