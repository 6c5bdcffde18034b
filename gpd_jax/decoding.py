"""Autoregressive scene rollout: KV-cached (ours) and full-prefix recompute (the official method).

Both are single-scenario pure functions of the model; `rollout_batch` vmaps the cached one over scenarios and
tasks, so one compiled function runs a batch that mixes tasks.

Cached rollout: the history frames [0, H) are embedded and pushed through the transformer in one call that
fills a preallocated KV cache; then a `lax.scan` over future frames forms each frame from the previous
frame's prediction and the log (per the task mask), embeds its N tokens, appends their keys/values at the
frame's offset and attends only to the filled part of the cache (chunked; see attention.py).

Feedback: predicted positions and headings (and velocities, for a `velocity_inputs` model) are re-tokenized as
regressed; valid = logit > 0; a map token is the argmax of its logits (temperature 0, the default) or sampled at
a temperature with an explicit key (`gpd_jax.options.Sampling`: temperature, top-k, top-p). A model with a sampling
agent head (`model.agent_bins`) samples each agent's next state at temperature > 0 too (`sample_agents`: a cell,
then its Laplace noise times the temperature); at temperature 0 its agents are regressed as any model's.
`RolloutOptions.samples` = N draws N futures of every (scenario, task) pair in the same compiled rollout, each with
its own key (a sample axis: outputs [S, K, N, ...]).

The log's map around a generated ego: the logged map tokens of frame t were encoded around the *logged* ego pose.
In tasks that take the map from the log but generate the ego (traffic simulation, motion planning), a rollout
may instead re-encode the log's lanes around the ego it generated (`LogLanes` + a `map_encoder`, e.g.
`gpd_jax.map_tokenizer.MapTokenizer.pose_encoder`): rasterize and tokenize inside the compiled step, so the map
stays where the log's roads are relative to the generated ego. Without them (the default, as the paper and the
official code do) the logged tokens are used as they are.

A generated map that moves with the ego (`map_warp`, e.g. `gpd_jax.map_tokenizer.MapTokenizer.warper`): where the
map is generated, frame t's map tokens are the map of the last frame whose map was given (the anchor: the last
history frame in the six tasks) decoded into lanes, moved to frame t's ego pose and encoded again, and the
model's own tokens are kept only in the token cells the anchor did not see (the new ground ahead). Moving the
anchor rather than the previous generated frame keeps the tokenizer's loss from compounding frame after frame.
Without it (the default, the paper's) every generated map token is the model's.

Prompts (`gpd_jax.prompts.Prompt`, conditional generation): wherever a task is taken, a prompt may be given
instead: its from-log mask is per frame, its agent states and map tokens override the log where it says so, its
agent cap removes slots like hidden agents, and its own vector map (`Prompt.lanes`) is encoded with the
`map_encoder` around the ego of every frame, history included. A task is converted with `as_prompt` and rolls
out to the same arrays.

Lanes (`model.agent_lane_residual`, `lane_context`): such a model's agents read vector lanes in the history frames
and every frame whose map is given: the prompt's own lanes where it has them, else the scene's polylines
(`Scene.polylines`; a rollout handed a scene without them runs as if no frame had lanes), and predict over a step
along them.

Entry points: `rollout_model(model, view, tasks, key, options)` for a loaded model and scenes it prepared
(`Model.prepare`): the one way every caller rolls out; `rollout_jit` the compiled program under it;
`rollout_prepared` its body (what `gpd_jax.make_rollout_fn` wraps); `prefill` / `advance` the halves the simulator
steps through.
"""

from __future__ import annotations

import functools
from typing import Callable

import flax.struct
import jax
import jax.numpy as jnp
from flax import nnx

from gpd_jax import parallel
from gpd_jax.model import autotune
from gpd_jax.model import GPD, KVCache, LaneContext, Modes, Prediction, forward, forward_cached, reads_lanes, \
    samples_agents
from gpd_jax.geometry import RoadGeometry, rotate
from gpd_jax.metrics.agents import box_corners
from gpd_jax.metrics.realism import box_signed_distance, orient_edges, road_edge_distance
from gpd_jax.options import RolloutOptions, Sampling
from gpd_jax.prompts import Prompt, as_prompt
from gpd_jax.scene import Scene, wrap_angle
from gpd_jax.spec import EvalError
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
# (map tokens i32[M] seen from an anchor pose f32[3], new pose f32[3]) -> (tokens i32[M] seen from the new pose,
# bool[M] cells the anchor did not see)
MapWarp = Callable[[jax.Array, jax.Array, jax.Array], tuple[jax.Array, jax.Array]]


@flax.struct.dataclass
class Frame:
    """One frame's model inputs (or a stack of them: leading dims `...`).

    xy: f32[..., A, 2], heading: f32[..., A], valid: bool[..., A], valid_logit: f32[..., A] (the model's logit
    where generated, 0 where taken from the log), map_tokens: i32[..., M], velocity: f32[..., A, 2] (zeros for a
    model without velocity inputs).
    """

    xy: jax.Array
    heading: jax.Array
    valid: jax.Array
    valid_logit: jax.Array
    map_tokens: jax.Array
    velocity: jax.Array


@flax.struct.dataclass
class Given:
    """What a rollout of one scenario is given: the log's frames as model inputs (`Frame` with a leading T:
    hidden agents removed, velocities zero for a model without velocity inputs; a prompt's given agent states and
    map tokens in place), the prompt (`task`: a `Prompt`, a task converted by `as_prompt`), optionally the
    log's lanes to re-encode the map around a generated ego, and for a model that reads lanes the lanes its
    agents read (`context`, with `on` bool[T]: `lane_context`), and the agents' boxes (`size` f32[A, 2], length and
    width) and drivable area (`road`, or None): what collision-aware decoding tests."""

    log: Frame
    task: Prompt
    lanes: LogLanes | None = None
    context: LaneContext | None = None
    size: jax.Array | None = None
    road: RoadGeometry | None = None


@flax.struct.dataclass
class DecodeState:
    """The carry of the cached rollout's scan: the KV cache, the prediction made at the previous frame (leading
    dim 1), the previous frame's xy f32[A, 2] and valid bool[A] (what displacement heads are relative to), and
    its output tokens hidden f32[N, d] (map slots first, then ego, then agents: what a head on the ego token,
    such as a fine-tuned planner, reads)."""

    cache: KVCache
    pred: Prediction
    last_xy: jax.Array
    last_valid: jax.Array
    hidden: jax.Array


@flax.struct.dataclass
class PrefillCarry:
    """The carry of `prefill`'s scan over history frames: the KV cache and the last frame's output tokens
    hidden f32[N, d]."""

    cache: KVCache
    hidden: jax.Array


@flax.struct.dataclass
class RolloutCarry:
    """The carry of `rollout`'s scan: the decoder state and the last frame whose map was given (`Frame`,
    unbatched: the anchor a warped map is moved from)."""

    decode: DecodeState
    anchor: Frame


def lane_context(model: GPD, scene: Scene, prompt: Prompt, num_history: int) -> LaneContext | None:
    """The lanes a model that reads lanes (`GPD.reads_lanes`) uses in a rollout (None for other models, or with no
    lanes at all): the prompt's own lanes where it uses them, else the scene's polylines (`Scene.polylines`), in
    the history frames and the frames whose every map slot comes from the given data (`on` bool[T]); frames whose
    map is generated get none, since the log's lanes would tell the model the map it is asked to generate."""
    if not model.reads_lanes:
        return None
    own = prompt.lanes is not None
    if scene.polylines is None and not own:
        return None
    num_map = prompt.from_log.shape[-1] - prompt.hidden.shape[-1]
    on = jnp.all(jnp.asarray(prompt.from_log)[:, :num_map], axis=-1) | (jnp.arange(scene.num_frames) < num_history)
    if not own:
        return LaneContext(polylines=scene.polylines, valid=scene.polyline_valid, on=on)
    use = jnp.asarray(prompt.use_lanes, bool)
    polys, valid = prompt.lanes, prompt.lanes_valid & use
    if scene.polylines is not None:  # both kinds, one masked out: the shapes stay fixed under vmap
        p = max(polys.shape[-2], scene.polylines.shape[-2])
        pad = lambda a, v: (jnp.pad(a, ((0, 0), (0, p - a.shape[-2]), (0, 0))),
                            jnp.pad(v, ((0, 0), (0, p - v.shape[-1]))))
        (pa, va), (pb, vb) = pad(polys, valid), pad(scene.polylines, scene.polyline_valid & ~use)
        polys, valid = jnp.concatenate([pa, pb.astype(pa.dtype)], 0), jnp.concatenate([va, vb], 0)
    return LaneContext(polylines=polys, valid=valid, on=on)


def context_at(ctx: LaneContext | None, frames) -> LaneContext | None:
    """`ctx` for a block of frames (`frames`: an index array, or a traced scalar for one frame)."""
    if ctx is None:
        return None
    return ctx.replace(on=jnp.reshape(jnp.asarray(ctx.on)[frames], (-1,)))


def given_inputs(model: GPD, scene: Scene, task: Task | Prompt, lanes: LogLanes | None = None,
                 map_encoder: MapEncoder | None = None, num_history: int = 0) -> Given:
    """The log of `scene` as model inputs under `task` (a Task or a Prompt): hidden and capped agents removed, a
    prompt's given agent states and map tokens in place (velocities of given states: backward differences over
    the model's frame period), and with a prompt's own lanes and `map_encoder` every frame's map tokens encoded
    from those lanes around that frame's given ego. `num_history`: the history frames, whose map is always
    given (`lane_context`)."""
    prompt = jax.tree.map(jnp.asarray, as_prompt(task, scene.num_frames))
    xy, heading, valid = scene.xy, scene.heading, scene.valid
    vel = model.input_velocity(scene.velocity)  # raises if the model needs velocities and the scene has none
    if prompt.agent_given is not None:
        g = prompt.agent_given
        xy = jnp.where(g[..., None], prompt.xy.astype(xy.dtype), xy)
        heading = jnp.where(g, prompt.heading.astype(heading.dtype), heading)
        valid = jnp.where(g, prompt.valid, valid)
        if vel is not None:
            diff = (xy[1:] - xy[:-1]) / model.frame_period_s
            ok = (valid[1:] & valid[:-1])[..., None]
            redo = jnp.concatenate([jnp.zeros_like(diff[:1]), jnp.where(ok, diff, 0.0)], 0).astype(vel.dtype)
            touched = g | jnp.concatenate([jnp.zeros_like(g[:1]), g[:-1]], 0)
            vel = jnp.where(touched[..., None], redo, vel)
    valid = valid & ~prompt.removed()[None, :]
    vel = jnp.zeros_like(scene.xy) if vel is None else vel
    map_tokens = scene.map_tokens
    if prompt.map_given is not None:
        map_tokens = jnp.where(prompt.map_given[:, None], prompt.map_tokens.astype(map_tokens.dtype), map_tokens)
    if prompt.lanes is not None and map_encoder is not None:
        poses = jnp.where(valid[:, :1], jnp.concatenate([xy[:, 0], heading[:, :1]], -1), scene.ego_pose)
        enc = jax.vmap(lambda p: map_encoder(prompt.lanes, prompt.lanes_valid, p))(poses).astype(map_tokens.dtype)
        map_tokens = jnp.where(prompt.use_lanes, enc, map_tokens)
    log = Frame(xy=xy, heading=heading, valid=valid, valid_logit=jnp.zeros(valid.shape, jnp.float32),
                map_tokens=map_tokens, velocity=vel)
    return Given(log=log, task=prompt, lanes=lanes, context=lane_context(model, scene, prompt, num_history),
                 size=scene.size, road=scene.road)


def as_sampling(sampling: Sampling | float) -> Sampling:
    """A `Sampling`, or a bare temperature as one."""
    return sampling if isinstance(sampling, Sampling) else Sampling(temperature=sampling)


def sample_categorical(key: jax.Array, logits: jax.Array, sampling: Sampling) -> jax.Array:
    """Indices i32[...] drawn from logits f32[..., C] / temperature (> 0) after the top-k and top-p cuts."""
    logits = logits / sampling.temperature
    if 0 < sampling.top_k < logits.shape[-1]:
        kth = jax.lax.top_k(logits, sampling.top_k)[0][..., -1:]
        logits = jnp.where(logits >= kth, logits, -jnp.inf)
    if sampling.top_p < 1:  # the smallest set of the most likely whose probability reaches top_p
        order = -jnp.sort(-logits, axis=-1)
        probs = jax.nn.softmax(order, axis=-1)
        before = jnp.cumsum(probs, axis=-1) - probs
        least = jnp.min(jnp.where(before < sampling.top_p, order, jnp.inf), axis=-1, keepdims=True)
        logits = jnp.where(logits >= least, logits, -jnp.inf)
    return jax.random.categorical(key, logits, axis=-1)


def sample_agents(modes: Modes, key: jax.Array, sampling: Sampling):
    """One draw of every agent's next state from a sampling head's `Modes` of one frame (leading dims [A]): a
    component (a cell) from its logits (`sample_categorical`), then the component's Laplace noise times the
    temperature.
    Returns (xy f32[A, 2], heading f32[A], velocity f32[A, 2] or None)."""
    k_mode, k_noise = jax.random.split(key)
    pick = sample_categorical(k_mode, modes.logits, sampling)

    def chosen(a):
        idx = pick.reshape(pick.shape + (1,) * (a.ndim - pick.ndim))
        return jnp.take_along_axis(a, idx, axis=pick.ndim)[:, 0]

    scale = chosen(modes.scale)
    noise = jax.random.laplace(k_noise, scale.shape, scale.dtype) * scale * sampling.temperature
    xy = chosen(modes.xy) + rotate(noise[..., 0:2], modes.axes)
    heading = wrap_angle(chosen(modes.heading) + noise[..., 2])
    vel = None if modes.velocity is None else chosen(modes.velocity) + rotate(noise[..., 3:5], modes.axes)
    return xy, heading, vel


AVOID_PASSES = 2  # rounds of collision-aware decoding: the second sees the first's choices


def top_cells(modes: Modes, k: int) -> Modes:
    """The `k` most likely cells of a sampling head's prediction of one frame (leading dims [A]), most likely
    first: `Modes` with C = k."""
    _, idx = jax.lax.top_k(modes.logits, k)

    def take(a):
        return jnp.take_along_axis(a, idx.reshape(idx.shape + (1,) * (a.ndim - idx.ndim)), axis=idx.ndim - 1)

    return Modes(logits=take(modes.logits), xy=take(modes.xy), heading=take(modes.heading),
                 velocity=None if modes.velocity is None else take(modes.velocity), scale=take(modes.scale),
                 axes=modes.axes)


def avoid_overlaps(xy, heading, vel, modes: Modes, prev_xy, prev_valid, valid, size, movable, key,
                   sampling: Sampling, road: RoadGeometry | None = None):
    """Collision-aware decoding of one frame's agents (`Sampling.avoid_collisions`): other agents and the road edge.

    xy f32[A, 2], heading f32[A], vel f32[A, 2]: every slot's next state as chosen (regressed at temperature 0,
    drawn above it; the log's for given slots); `modes`: the sampling head's prediction of that frame (leading dims
    [A]); prev_xy f32[A, 2] / prev_valid bool[A]: the frame before; valid bool[A]: the slots present next; size
    f32[A, 2] (length, width); movable bool[A]: the generated slots that may be changed; key: for the draws above
    temperature 0 (None at 0); road: the scene's road geometry, or None.

    Agent i yields to agent j when j is present and its previous centre is not behind i's (along i's heading), unless
    their boxes (at the previous centres, with the next headings) already overlapped at the frame before: then i's
    next box must not overlap j's next box, nor the box halfway between their previous and next centres (a car that
    jumps through another between two frames). With `road`, an agent whose box was on the road at the frame before
    (no corner beyond the road edges: the realism metric's `road_edge_distance` <= 0) must stay on it. A movable
    agent whose state breaks either takes instead, of all the cells of its sampling head that keep both, the one
    whose centre is nearest its state (temperature 0: the cell's centre and heading; the least change to the
    regressed state) or a draw (above it: a cell from their logits at the temperature, then its noise, or the most
    likely one where the noise breaks them); where no cell keeps both, its state stays. Agents ahead keep their
    states: a car behind a queue brakes, the queue does not move back. `AVOID_PASSES` rounds, each against the
    others' states of the round before. A model without velocity cells keeps `vel`. Returns (xy, heading, vel) as
    given."""
    a, c = modes.logits.shape
    half = size / 2
    start = jnp.where(prev_valid[:, None], prev_xy, xy)
    u = jnp.stack([jnp.cos(heading), jnp.sin(heading)], -1)
    ahead = jnp.sum((start[None, :, :] - start[:, None, :]) * u[:, None, :], -1) >= 0  # [i, j]: j not behind i
    yields = ahead & valid[None, :] & ~jnp.eye(a, dtype=bool)
    # a pair whose boxes already overlapped at the frame before (a tight queue, a log with overlapping boxes) is not
    # tested: no cell undoes that overlap, and a free cell moved standing cars metres from their states
    before = box_signed_distance(start[:, None, :], heading[:, None], half[:, None, :], start[None, :, :],
                                 heading[None, :], half[None, :, :]) < 0
    yields = yields & ~(before & prev_valid[:, None] & prev_valid[None, :])
    if road is None:
        def on_the_road(cxy, ch):  # bool[A, C]
            return jnp.ones(cxy.shape[:2], bool)
    else:
        edges = orient_edges(road)

        def edge_distance(cxy, ch):  # f32[A, C]: the most off-road corner of candidate c of agent i (> 0: off)
            corners = box_corners(jnp.swapaxes(cxy, 0, 1), jnp.swapaxes(ch, 0, 1),
                                  jnp.broadcast_to(size, (cxy.shape[1],) + size.shape))  # [C, A, 4, 2]
            return jnp.swapaxes(road_edge_distance(edges, corners, jnp.ones(corners.shape[:2], bool))[0], 0, 1)

        was_on = edge_distance(start[:, None, :], heading[:, None])[:, 0] <= 0

        def on_the_road(cxy, ch):
            return (edge_distance(cxy, ch) <= 0) | ~was_on[:, None]

    def clear(cxy, ch, oxy, oh):  # bool[A, C]: candidate c of agent i (cxy [A, C, 2], ch [A, C]) overlaps no j
        def hits(p, q):
            d = box_signed_distance(p[:, :, None, :], ch[:, :, None], half[:, None, None, :],
                                    q[None, None, :, :], oh[None, None, :], half[None, None, :, :])
            return jnp.any((d < 0) & yields[:, None, :], -1)

        mid_c, mid_o = 0.5 * (cxy + start[:, None, :]), 0.5 * (oxy + start)
        return ~(hits(cxy, oxy) | hits(mid_c, mid_o))

    cells_on_road = on_the_road(modes.xy, modes.heading)

    def one_pass(i, state):
        cur_xy, cur_h, cur_v = state
        ok_now = (clear(cur_xy[:, None, :], cur_h[:, None], cur_xy, cur_h) & on_the_road(cur_xy[:, None, :],
                                                                                        cur_h[:, None]))[:, 0]
        ok_cells = clear(modes.xy, modes.heading, cur_xy, cur_h) & cells_on_road
        free = modes._replace(logits=jnp.where(ok_cells, modes.logits, -jnp.inf))
        if sampling.random:  # the most likely free cell: where a draw's noise breaks the rules
            best = top_cells(free, 1)
        else:  # the free cell nearest the regressed state: the least change to the model's own choice
            near = -jnp.sum((modes.xy - cur_xy[:, None, :]) ** 2, -1)
            best = top_cells(modes._replace(logits=jnp.where(ok_cells, near, -jnp.inf)), 1)
        new_xy, new_h = best.xy[:, 0], best.heading[:, 0]
        new_v = None if best.velocity is None else best.velocity[:, 0]
        if sampling.random:  # a draw among the free cells; where its noise breaks the rules, the best cell
            d_xy, d_h, d_v = sample_agents(free, jax.random.fold_in(key, i), sampling)
            fine = (clear(d_xy[:, None, :], d_h[:, None], cur_xy, cur_h) & on_the_road(d_xy[:, None, :],
                                                                                      d_h[:, None]))[:, 0]
            new_xy, new_h = jnp.where(fine[:, None], d_xy, new_xy), jnp.where(fine, d_h, new_h)
            new_v = None if new_v is None else jnp.where(fine[:, None], d_v, new_v)
        swap = movable & ~ok_now & jnp.any(ok_cells, -1)
        out_v = cur_v if new_v is None else jnp.where(swap[:, None], new_v, cur_v)
        return jnp.where(swap[:, None], new_xy, cur_xy), jnp.where(swap, new_h, cur_h), out_v

    state = (xy, heading, vel)
    for i in range(AVOID_PASSES):  # a fixed, small number of rounds (not a loop over time)
        state = one_pass(i, state)
    return state


def _choose_frame(pred: Prediction, given: Given, t, key, sampling: Sampling,
                  map_encoder: MapEncoder | None = None, map_warp: MapWarp | None = None,
                  anchor: Frame | None = None, prev: tuple[jax.Array, jax.Array] | None = None) -> Frame:
    """Frame t's inputs: the given data where the prompt says so at frame t, the prediction elsewhere.

    `pred` holds the single-frame prediction made at frame t-1 (leading dim 1). With `given.lanes` and
    `map_encoder`, map tokens taken from the log while the ego is generated (and valid) are the log's lanes
    encoded around the generated ego pose instead of the logged tokens. With a prompt's own lanes (and
    `map_encoder`), the map slots taken from the given data are those lanes encoded around frame t's ego. With
    `map_warp` and the `anchor` frame, generated map slots are the anchor's map moved to frame t's ego, except
    in cells the anchor did not see (both egos valid; otherwise the model's tokens). With
    `sampling.avoid_collisions` (a sampling-head model), the generated agents are decoded collision-aware
    (`avoid_overlaps`; `prev`: frame t-1's xy f32[A, 2] and valid bool[A]).
    """
    log, task = given.log, given.task
    num_map = log.map_tokens.shape[-1]
    logits = pred.map_logits[0]
    agent_xy, agent_heading = pred.xy[0], pred.heading[0]
    agent_vel = None if pred.velocity is None else pred.velocity[0]
    if sampling.random:
        frame_key = jax.random.fold_in(key, t)
        sampled = sample_categorical(frame_key, logits, sampling)
        if pred.modes is not None:
            modes = jax.tree.map(lambda a: a[0], pred.modes)
            agent_xy, agent_heading, agent_vel = sample_agents(modes, jax.random.fold_in(frame_key, 1), sampling)
    else:
        sampled = jnp.argmax(logits, axis=-1)
    log_map = log.map_tokens[t]
    prompt = isinstance(task, Prompt)
    row = jnp.asarray(task.from_log)[t] if prompt else task.from_log
    removed = task.removed() if prompt else task.hidden
    fl_map, fl_agent = row[:num_map], row[num_map:]
    map_t = jnp.where(fl_map, log_map, sampled.astype(log_map.dtype))
    xy_t = jnp.where(fl_agent[:, None], log.xy[t], agent_xy)
    heading_t = jnp.where(fl_agent, log.heading[t], agent_heading)
    valid_t = jnp.where(fl_agent, log.valid[t], pred.valid_logit[0] > 0) & ~removed
    logit_t = jnp.where(fl_agent, 0.0, pred.valid_logit[0])
    if map_encoder is not None and given.lanes is not None:
        pose = jnp.stack([xy_t[0, 0], xy_t[0, 1], heading_t[0]])
        around_ego = map_encoder(given.lanes.polylines, given.lanes.valid, pose).astype(log_map.dtype)
        map_t = jnp.where(fl_map & ~fl_agent[0] & valid_t[0], around_ego, map_t)
    if map_encoder is not None and prompt and task.lanes is not None:
        pose = jnp.where(valid_t[0], jnp.stack([xy_t[0, 0], xy_t[0, 1], heading_t[0]]),
                         jnp.stack([log.xy[t, 0, 0], log.xy[t, 0, 1], log.heading[t, 0]]))
        own = map_encoder(task.lanes, task.lanes_valid, pose).astype(log_map.dtype)
        map_t = jnp.where(fl_map & task.use_lanes, own, map_t)
    if map_warp is not None:
        anchor_pose = jnp.stack([anchor.xy[0, 0], anchor.xy[0, 1], anchor.heading[0]])
        pose = jnp.stack([xy_t[0, 0], xy_t[0, 1], heading_t[0]])
        warped, new = map_warp(anchor.map_tokens, anchor_pose, pose)
        keep = ~fl_map & ~new & anchor.valid[0] & valid_t[0]
        map_t = jnp.where(keep, warped.astype(map_t.dtype), map_t)
    pred_vel = jnp.zeros_like(log.velocity[t]) if agent_vel is None else agent_vel
    vel_t = jnp.where(fl_agent[:, None], log.velocity[t], pred_vel)
    if sampling.avoid_collisions:
        if pred.modes is None:
            raise ValueError("avoid_collisions decodes among the sampling head's cells: a model with "
                             "model.agent_bins > 0 (gpd_sampling) is needed")
        modes = jax.tree.map(lambda a: a[0], pred.modes)
        prev_xy, prev_valid = prev
        movable = ~fl_agent & valid_t & prev_valid
        draw_key = jax.random.fold_in(jax.random.fold_in(key, t), 2) if sampling.random else None
        xy_t, heading_t, vel_t = avoid_overlaps(xy_t, heading_t, vel_t, modes, prev_xy, prev_valid, valid_t,
                                                given.size, movable, draw_key, sampling, given.road)
    return Frame(xy=xy_t, heading=heading_t, valid=valid_t, valid_logit=logit_t, map_tokens=map_t, velocity=vel_t)


def rollout(model: GPD, scene: Scene, task: Task | Prompt, key: jax.Array, num_history: int,
            sampling: Sampling | float = 0.0, lanes: LogLanes | None = None,
            map_encoder: MapEncoder | None = None, map_warp: MapWarp | None = None) -> RolloutOutput:
    """KV-cached rollout of one scenario under one task or prompt.

    Args:
      model: the GPD transformer.
      scene: a single (unbatched) scene with T frames at the model's rate; frames [0, num_history) are given.
      task: a single task (from_log bool[M + A], hidden bool[A]) or prompt (from_log bool[T, M + A], ...).
      key: PRNG key (used only when the temperature is > 0).
      num_history: H, the number of given frames (21 in the paper).
      sampling: how map tokens and a sampling head's agents are drawn (`Sampling`; a bare number is its temperature:
        0 for greedy map tokens and regressed agents, > 0 to sample them).
      lanes, map_encoder: the scene's logged lanes and a tokenizer's pose encoder, to re-encode the logged map
        around a generated ego (see the module docstring); a prompt with its own lanes needs the encoder.
      map_warp: move the last given map with the ego where the map is generated (module docstring).
    """
    t_total, h = scene.num_frames, num_history
    task = as_prompt(task, t_total)
    sampling = as_sampling(sampling)
    _check_map_encoder(lanes, map_encoder, task)
    given = given_inputs(model, scene, task, lanes, map_encoder, h)
    log = given.log

    def choose(carry: RolloutCarry, t) -> Frame:
        return _choose_frame(carry.decode.pred, given, t, key, sampling, map_encoder, map_warp, carry.anchor,
                             (carry.decode.last_xy, carry.decode.last_valid))

    def step(carry: RolloutCarry, t):
        f = choose(carry, t)
        anchor = carry.anchor
        if map_warp is not None:  # only a warp reads the anchor: no per-step selects otherwise
            anchor = jax.tree.map(lambda a, b: jnp.where(_map_given(given.task, t), a, b), f, anchor)
        return RolloutCarry(decode=advance(model, carry.decode, f, t, context_at(given.context, t)),
                            anchor=anchor), f

    start = RolloutCarry(decode=prefill(model, log, h, t_total, given.context),
                         anchor=jax.tree.map(lambda a: a[h - 1], log))
    final, frames = jax.lax.scan(step, start, jnp.arange(h, t_total - 1))
    last = choose(final, jnp.asarray(t_total - 1))
    frames = jax.tree.map(lambda a, b: jnp.concatenate([a, b[None]], axis=0), frames, last)
    return _assemble(log, frames, h)


def prefill(model: GPD, log: Frame, num_history: int, num_frames: int,
            lanes: LaneContext | None = None) -> DecodeState:
    """Pushes the history frames `log[:num_history]` (a `Frame` with a leading T >= num_history) through the
    transformer into a fresh KV cache for `num_frames` frames; the returned state holds the prediction of frame
    `num_history`. The first half of every cached rollout (and of `gpd_jax.sim.reset`). `lanes`: what a model that
    reads lanes uses (`on` over all T frames or the history's).

    One scenario pushes the history in one block (bigger matmuls); under `vmap` over a batch it goes frame by
    frame (a `lax.scan` whose temporaries are one frame's, as in `advance`), so a scenario's memory is its cache
    rather than [H, h * N, chunk] scores and [h * N, ffn] activations (docs/benchmarks.md has both measured)."""
    h = num_history
    tokens = model.embed(log.xy[:h], log.heading[:h], log.valid[:h], log.map_tokens[:h], jnp.arange(h),
                         log.velocity[:h])

    if autotune.batch_size(tokens) == 1:  # one scenario: the whole history in one block (bigger matmuls)
        hid, cache = forward_cached(model, tokens, model.init_cache(num_frames), 0)
        hidden = hid[-1]
    else:  # a batch: frame by frame, so no temporary holds [H, h * N, chunk] scores or [h * N, ffn] per scenario
        def push(carry: PrefillCarry, t):
            hid, cache = forward_cached(model, jax.lax.dynamic_index_in_dim(tokens, t, 0), carry.cache, t)
            return PrefillCarry(cache=cache, hidden=hid[0]), None

        start = PrefillCarry(cache=model.init_cache(num_frames), hidden=tokens[0])
        done, _ = jax.lax.scan(push, start, jnp.arange(h))
        cache, hidden = done.cache, done.hidden
    pred = model.predict(hidden[None], log.xy[h - 1:h], log.heading[h - 1:h], log.valid[h - 1:h],
                         *_prev(log.xy, log.valid, h - 1), log.velocity[h - 1:h], context_at(lanes, h - 1))
    return DecodeState(cache=cache, pred=pred, last_xy=log.xy[h - 1], last_valid=log.valid[h - 1],
                       hidden=hidden)


def advance(model: GPD, state: DecodeState, frame: Frame, t, lanes: LaneContext | None = None) -> DecodeState:
    """Appends frame t (`frame`, unbatched: what the scene holds at t, however chosen) to the KV cache and
    predicts frame t + 1. `t` may be traced. One step of every cached rollout (and of `gpd_jax.sim.step`).
    `lanes`: what a model that reads lanes uses at frame t (`on` of that one frame)."""
    f = frame
    tok = model.embed(f.xy[None], f.heading[None], f.valid[None], f.map_tokens[None], jnp.asarray(t)[None],
                      f.velocity[None])
    hid, cache = forward_cached(model, tok, state.cache, t)
    pred = model.predict(hid, f.xy[None], f.heading[None], f.valid[None], state.last_xy[None],
                         state.last_valid[None], f.velocity[None], lanes)
    return DecodeState(cache=cache, pred=pred, last_xy=f.xy, last_valid=f.valid, hidden=hid[0])


def _check_map_encoder(lanes, map_encoder, prompt: Prompt | None = None) -> None:
    own = prompt is not None and prompt.lanes is not None
    if own and map_encoder is None:
        raise ValueError("a prompt with its own lanes (Prompt.lanes) needs `map_encoder` (a map tokenizer's "
                         "pose_encoder) to encode them into map tokens")
    if (lanes is None) != (map_encoder is None) and not (own and lanes is None):
        raise ValueError("re-encoding the logged map around a generated ego needs both `lanes` (the log's lane "
                         f"polylines) and `map_encoder`; got lanes={'None' if lanes is None else 'given'}, "
                         f"map_encoder={map_encoder!r}")


def _map_given(prompt: Prompt, t) -> jax.Array:
    """bool[]: every map slot of frame t comes from the given data (t may be traced)."""
    num_map = prompt.from_log.shape[-1] - prompt.hidden.shape[-1]
    return jnp.all(jnp.asarray(prompt.from_log)[t, :num_map])


def _prev(xy, valid, t):
    """The frame before frame t as a 1-frame block (invalid when t is 0); t may be traced."""
    p = jnp.maximum(t - 1, 0)
    pxy = jax.lax.dynamic_slice_in_dim(xy, p, 1, axis=0)
    pv = jax.lax.dynamic_slice_in_dim(valid, p, 1, axis=0) & (t > 0)
    return pxy, pv


def _assemble(log: Frame, frames: Frame, h: int) -> RolloutOutput:
    """The log's history frames [0, h) followed by the generated `frames`."""
    cat = lambda given, gen: jnp.concatenate([given[:h], gen.astype(given.dtype)], 0)
    return RolloutOutput(xy=cat(log.xy, frames.xy), heading=cat(log.heading, frames.heading),
                         valid=cat(log.valid, frames.valid), valid_logit=cat(log.valid_logit, frames.valid_logit),
                         map_tokens=cat(log.map_tokens, frames.map_tokens))


def rollout_recompute(model: GPD, scene: Scene, task: Task | Prompt, key: jax.Array, num_history: int,
                      sampling: Sampling | float = 0.0, lanes: LogLanes | None = None,
                      map_encoder: MapEncoder | None = None, map_warp: MapWarp | None = None) -> RolloutOutput:
    """The official method: for every future frame, a full forward over the whole buffer (no cache).

    The buffer holds all T frames; frames not yet generated still hold log values, which the scene-level
    mask keeps from influencing the frame being predicted, so this equals a forward over the prefix only.
    Same arguments and outputs as `rollout`.
    """
    t_total, h = scene.num_frames, num_history
    task = as_prompt(task, t_total)
    sampling = as_sampling(sampling)
    _check_map_encoder(lanes, map_encoder, task)
    given = given_inputs(model, scene, task, lanes, map_encoder, h)

    def step(buf: Frame, t):
        tokens = model.embed(buf.xy, buf.heading, buf.valid, buf.map_tokens, jnp.arange(t_total), buf.velocity)
        hid = forward(model, tokens)
        prev = jnp.maximum(t - 1, 0)
        sl = lambda a: jax.lax.dynamic_slice_in_dim(a, prev, 1, axis=0)
        pred = model.predict(sl(hid), sl(buf.xy), sl(buf.heading), sl(buf.valid), *_prev(buf.xy, buf.valid, prev),
                             sl(buf.velocity), context_at(given.context, prev))
        anchor = None
        if map_warp is not None:
            frames = jnp.arange(t_total)
            given_map = jax.vmap(lambda s: _map_given(given.task, s))(frames) | (frames < h)
            a = jnp.max(jnp.where(given_map & (frames < t), frames, 0))
            anchor = jax.tree.map(lambda x: jax.lax.dynamic_index_in_dim(x, a, 0, keepdims=False), buf)
        frame = _choose_frame(pred, given, t, key, sampling, map_encoder, map_warp, anchor,
                              (buf.xy[prev], buf.valid[prev] & (t > 0)))
        buf = jax.tree.map(lambda b, f: jax.lax.dynamic_update_slice_in_dim(b, f[None].astype(b.dtype), t, axis=0),
                           buf, frame)
        return buf, None

    buf, _ = jax.lax.scan(step, given.log, jnp.arange(h, t_total))
    return RolloutOutput(xy=buf.xy, heading=buf.heading, valid=buf.valid, valid_logit=buf.valid_logit,
                         map_tokens=buf.map_tokens)


def rollout_batch(model: GPD, scenes: Scene, tasks: Task | Prompt, keys: jax.Array, num_history: int,
                  sampling: Sampling | float = 0.0, lanes: LogLanes | None = None,
                  map_encoder: MapEncoder | None = None, map_warp: MapWarp | None = None) -> RolloutOutput:
    """`rollout` vmapped over a leading batch dim shared by scenes, tasks or prompts, keys (and lanes; mixed
    tasks and prompts allowed)."""
    fn = lambda s, t, k, ln: rollout(model, s, t, k, num_history, sampling, ln, map_encoder, map_warp)
    return jax.vmap(fn)(scenes, tasks, keys, lanes)


def rollout_tasks(model: GPD, scenes: Scene, tasks: Task | Prompt, key: jax.Array, num_history: int,
                  sampling: Sampling | float = 0.0, lanes: LogLanes | None = None,
                  map_encoder: MapEncoder | None = None, map_warp: MapWarp | None = None) -> RolloutOutput:
    """Every scenario under every task or prompt: scenes [S, ...], tasks [K, ...] -> outputs [S, K, ...].

    Prompts may also be per scenario, Prompt [S, K, ...] (e.g. paths given in each scene's frame): scenario s
    then runs prompts[s, k]. The S x K pairs are flattened into one vmapped batch (so the attention kernel's
    per-scenario batching rule sees the whole batch); `key` is split per (scenario, task) (`task_keys`; or give
    those keys [S, K] yourself).
    """
    flat_scenes, flat_tasks, flat_lanes, s, k = _flat_pairs(scenes, tasks, lanes)
    out = rollout_batch(model, flat_scenes, flat_tasks, task_keys(key, s, k), num_history, sampling, flat_lanes,
                        map_encoder, map_warp)
    return jax.tree.map(lambda x: x.reshape((s, k) + x.shape[1:]), out)


def _pairs(scenes: Scene, tasks: Task | Prompt) -> tuple[Prompt, bool, int, int]:
    """(tasks as prompts, whether they are per scenario, S, K) of scenes [S, ...] under tasks or prompts [K, ...]
    or per-scenario prompts [S, K, ...]."""
    prompts = as_prompt(tasks, scenes.xy.shape[-3])
    per_scene = prompts.from_log.ndim == 4
    return prompts, per_scene, scenes.xy.shape[0], prompts.from_log.shape[1 if per_scene else 0]


def _flat_pairs(scenes: Scene, tasks: Task | Prompt, lanes: LogLanes | None):
    """The S x K (scenario, task) pairs as one batch: (scenes, prompts, lanes) [S * K, ...], S, K."""
    prompts, per_scene, s, k = _pairs(scenes, tasks)
    flat_scenes, flat_lanes = jax.tree.map(lambda x: jnp.repeat(x, k, axis=0), (scenes, lanes))
    if per_scene:
        if prompts.from_log.shape[0] != s:
            raise ValueError(f"per-scenario prompts [S, K, ...] with S = {prompts.from_log.shape[0]} for {s} scenes")
        flat_tasks = jax.tree.map(lambda x: x.reshape((s * k,) + x.shape[2:]), prompts)
    else:
        flat_tasks = jax.tree.map(lambda x: jnp.tile(x, (s,) + (1,) * (x.ndim - 1)), prompts)
    return flat_scenes, flat_tasks, flat_lanes, s, k


def _over_samples(run: Callable[[Prompt], RolloutOutput], scenes: Scene, tasks: Task | Prompt,
                  n: int) -> RolloutOutput:
    """`run` (a rollout of `scenes` under given tasks, outputs [S, K', ...]) under every task or prompt of `tasks`
    repeated `n` times in a row (so each copy gets its own key), its outputs [S, K * n, ...] as [S, K, n, ...]."""
    prompts, per_scene, s, k = _pairs(scenes, tasks)
    repeated = jax.tree.map(lambda x: jnp.repeat(x, n, axis=1 if per_scene else 0), prompts)
    return jax.tree.map(lambda x: x.reshape((s, k, n) + x.shape[2:]), run(repeated))


def task_keys(key: jax.Array, num_scenes: int, num_tasks: int) -> jax.Array:
    """The key of every (scenario, task) pair, flat [S * K]: `key` split S * K ways, or `key` itself when it already
    holds S x K keys (what a rollout sharded over devices hands each device: its scenarios' keys)."""
    if key.shape == (num_scenes, num_tasks):
        return key.reshape(num_scenes * num_tasks)
    if key.shape != ():
        raise ValueError(f"key of shape {key.shape}: expected one key or [S, K] = [{num_scenes}, {num_tasks}] keys")
    return jax.random.split(key, num_scenes * num_tasks)


def rollout_prepared(module: GPD, scenes: Scene, tasks: Task | Prompt, key: jax.Array, num_history: int,
                     options: RolloutOptions, tok=None, tok_params=None) -> RolloutOutput:
    """Every scenario of prepared scenes [S, ...] (`Model.prepare`) under every task or prompt [K, ...] (prompts
    also [S, K, ...]) -> outputs [S, K, ...], as `options` say: the body of every rollout entry (`rollout_jit`,
    `gpd_jax.make_rollout_fn`). `tok` (the model's map tokenizer) and its `tok_params` are needed where the options
    or a prompt's own lanes run it."""
    if options.samples is not None:
        return _over_samples(lambda ts: rollout_prepared(module, scenes, ts, key, num_history,
                                                         options.replace(samples=None), tok, tok_params),
                             scenes, tasks, options.samples)
    own = isinstance(tasks, Prompt) and tasks.lanes is not None
    if (options.needs_tokenizer or own) and tok is None:
        raise ValueError("this rollout runs the model's map tokenizer (log_map='lanes', gen_map='warp' or a prompt "
                         "with its own lanes): pass tok")
    lanes = None
    if options.log_map == "lanes":
        if scenes.polylines is None:
            raise ValueError("log_map='lanes' needs the scenes' lane polylines (Scene.polylines)")
        lanes = LogLanes(scenes.polylines, scenes.polyline_valid)
    encoder = tok.pose_encoder(tok_params) if lanes is not None or own else None
    warp = tok.warper(tok_params) if options.gen_map == "warp" else None
    h, sampling = num_history, options.sampling
    if options.method == "cached":
        return rollout_tasks(module, scenes, tasks, key, h, sampling, lanes, encoder, warp)
    flat_s, flat_t, flat_l, s, k = _flat_pairs(scenes, tasks, lanes)
    one = lambda sc, ta, ke, ln: rollout_recompute(module, sc, ta, ke, h, sampling, ln, encoder, warp)
    out = jax.vmap(one)(flat_s, flat_t, task_keys(key, s, k), flat_l)
    return jax.tree.map(lambda x: x.reshape((s, k) + x.shape[1:]), out)


@functools.partial(jax.jit, static_argnames=("graphdef", "num_history", "options", "tok"))
def rollout_jit(graphdef, params, rest, scenes: Scene, tasks: Task | Prompt, key, num_history: int,
                options: RolloutOptions = RolloutOptions(), tok=None, tok_params=None) -> RolloutOutput:
    """`rollout_prepared` of the model `nnx.merge(graphdef, params, rest)`, jitted: the one compiled rollout (one
    compile per shape, options and model structure). `rollout_model` calls it for a loaded model.

    With several local devices (GPUs; CPU devices where XLA is asked for them) the scenarios are split over as many
    as divide S (`gpd_jax.parallel`): each device rolls out its scenarios with their own keys, so the outputs are
    those of one device (to float rounding), in 1/devices of the time. With `options.samples` = N every task runs N
    times, each with its own key (outputs [S, K, N, ...]), in the same compiled call."""
    if options.samples is not None:
        return _over_samples(lambda ts: rollout_jit(graphdef, params, rest, scenes, ts, key, num_history,
                                                    options.replace(samples=None), tok, tok_params),
                             scenes, tasks, options.samples)
    _, per_scene, s, k = _pairs(scenes, tasks)
    keys = task_keys(key, s, k).reshape(s, k)

    def run(params, rest, tok_params, shared, scenes, keys, own):
        return rollout_prepared(nnx.merge(graphdef, params, rest), scenes, own if per_scene else shared, keys,
                                num_history, options, tok, tok_params)

    shared, own = (None, tasks) if per_scene else (tasks, None)
    ndev = parallel.devices_for_batch(s, jax.local_device_count())
    if ndev > 1:
        run = parallel.data_parallel(run, parallel.data_mesh(ndev, local=True), num_replicated=4)
    return run(params, rest, tok_params, shared, scenes, keys, own)


def rollout_model(model, scenes: Scene, tasks: Task | Prompt, key: jax.Array,
                  options: RolloutOptions = RolloutOptions(), params=None) -> RolloutOutput:
    """The one way a loaded model (`gpd_jax.checkpoint.Model`) rolls out prepared scenes [S, ...] (`model.prepare`)
    under tasks or prompts [K, ...] ([S, K, ...]): lane polylines and road geometry the rollout does not read are
    dropped (smaller jit arguments), the tokenizer goes in only where the options or a prompt's own lanes need it, and `rollout_jit`
    runs. `params`: other parameters of the same structure (default: the model's). Outputs [S, K, ...] ([S, K, N,
    ...] with `options.samples` = N)."""
    own = check_options(model, options, tasks)
    if not (reads_lanes(model.config.model) or options.log_map == "lanes"):
        scenes = scenes.replace(polylines=None, polyline_valid=None)
    if not options.avoid_collisions:  # only collision-aware decoding reads the drivable area
        scenes = scenes.replace(road=None)
    scenes = jax.tree.map(jnp.asarray, scenes)
    use_tok = options.needs_tokenizer or own
    tok = model.tokenizer if use_tok else None
    return rollout_jit(model.graphdef, model.params if params is None else params, model.rest, scenes, tasks, key,
                       model.spec.num_history, options, tok, None if tok is None else tok.params)


def check_options(model, options: RolloutOptions, tasks=None) -> bool:
    """Raises EvalError when `options` or the prompts `tasks` need what `model` lacks (its map tokenizer, a
    sampling head for collision-aware decoding); returns
    whether `tasks` are prompts with their own lanes."""
    own = isinstance(tasks, Prompt) and tasks.lanes is not None
    model.require_tokenizer(options, prompt_lanes=own)
    if options.avoid_collisions and not samples_agents(model.config.model):
        raise EvalError("avoid_collisions decodes among the sampling head's cells, and this model has none "
                        "(config.model.agent_bins is 0): use a sampling model such as gpd_sampling")
    return own
