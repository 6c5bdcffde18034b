"""The closed-loop simulator: pure `reset` / `step` over the KV-cached GPD, `run` (one `lax.scan` of a policy,
vmapped over scenarios, compiled once per batch shape) and `run_host` (a plain-Python planner in the loop, called
with the batch's numpy observations [B, ...] each model frame).

    sim = make_sim_scenes(model, gpd_jax.load_scenes(store, indices=range(8)))   # SimScene [8, ...] (host)
    out = run(model, sim, constant_velocity_policy(model.spec), jax.random.key(0), agents="gpd")
    out.fine_xy                                # f32[8, 101, A, 2]: the closed-loop scene at the stored rate

    state = reset(model, one_scene, key, agents="idm")     # frames [0, H) from the log, the KV cache prefilled
    obs = observe(model, state)                             # what a policy sees
    state, obs = step(model, state, ego)                    # append one model frame with the ego placed by `ego`

Each step appends one model frame (1 s for the shipped model) and the S = frame_stride stored frames before it:
the ego from the policy (`gpd_jax.sim.dynamics`: a pose, pose + velocity, an action through the bicycle model, or
the S stored-rate poses), the other slots from the agent model:

* ``"gpd"``: the model's own prediction of the frame (reactive: it attended to the ego the policy placed); the
  stored frames in between are cubic Hermite curves between the two frames' positions and velocities (the model's
  predicted velocities), headings along the shorter arc;
* ``"log"``: the log (non-reactive), at the stored rate;
* ``"idm"``: IDM along each agent's logged path (`gpd_jax.sim.agents`), simulated at the stored rate.

The map of every frame the model reads is the log's lanes encoded around the ego's *actual* pose by the model's map
tokenizer (the rollout's lane re-encoding), never the logged tokens (which would leak where the ego should be).
The velocity a velocity-input model reads is the instantaneous (stored-rate backward-difference) velocity of what
was placed, as in training. Slots are the model's A slots (the nearest A - 1 vehicles) in every agent model.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from gpd_jax.checkpoint import Model
from gpd_jax.decoding import DecodeState, Frame, advance, prefill, sample_agents
from gpd_jax.model import LaneContext
from gpd_jax.scene import Scene
from gpd_jax.sim.agents import IDMParams, IDMState, Paths, idm_poses, idm_substep, make_paths
from gpd_jax.sim.dynamics import BicycleLimits, bicycle_path, hermite, lerp_heading, pose_path
from gpd_jax.sim.tracker import Plan, Tracker, TrackState, extend, plan_path, track
from gpd_jax.options import Sampling
from gpd_jax.spec import EvalError, ModelSpec

AGENT_MODELS = ("gpd", "log", "idm")


class SimError(EvalError):
    """Bad simulator input (an unknown agent model, a policy returning NaN or wrong shapes, a store without what
    the scores need); the message names what and where."""


@flax.struct.dataclass
class SimScene:
    """What a simulation of one scenario (or a batch: leading dims `...`) is given.

    view: Scene [..., T, A, ...] at the model's rate (velocities, map tokens of the history, no polylines);
    log_xy f32[..., Ts, A, 2], log_heading f32[..., Ts, A], log_valid bool[..., Ts, A], log_velocity
    f32[..., Ts, A, 2]: the log at the stored rate (Ts = stride * (T - 1) + 1 frames, the model's A slots);
    polylines f32[..., L, P, 2], polyline_valid bool[..., L, P]: the log's lane centrelines (scene frame);
    road: optional `gpd_jax.geometry.RoadGeometry` (drivable area, edges, directed lanes) for the scores.
    """

    view: Scene
    log_xy: jax.Array
    log_heading: jax.Array
    log_valid: jax.Array
    log_velocity: jax.Array
    polylines: jax.Array
    polyline_valid: jax.Array
    road: Any = None

    @property
    def size(self):
        return self.view.size


@flax.struct.dataclass
class SimState:
    """The simulator's state of one scenario (the carry of `run`'s scan).

    t: i32[] the last appended model frame. xy f32[T, A, 2], heading f32[T, A], valid bool[T, A], velocity
    f32[T, A, 2] (instantaneous, scene frame), map_tokens i32[T, M]: the simulated frames at the model's rate
    (frames > t are empty). fine_xy f32[Ts, A, 2], fine_heading f32[Ts, A], fine_valid bool[Ts, A]: the same at
    the stored rate (frames > stride * t empty). decode: the KV cache and the model's prediction of frame t + 1
    (None when no model is needed). idm: IDM agents' arc positions and speeds. paths: every slot's logged path
    (slot 0: the logged ego's route). control: the ego's speed, acceleration and steering angle (what the tracker
    carries from one model frame to the next). scene: what the simulation was given. agents: the agent model
    (static).
    """

    t: jax.Array
    xy: jax.Array
    heading: jax.Array
    valid: jax.Array
    velocity: jax.Array
    map_tokens: jax.Array
    fine_xy: jax.Array
    fine_heading: jax.Array
    fine_valid: jax.Array
    decode: DecodeState | None
    idm: IDMState
    paths: Paths
    control: TrackState
    scene: SimScene
    agents: str = flax.struct.field(pytree_node=False, default="gpd")


@flax.struct.dataclass
class Observation:
    """What a policy sees at model frame t: one scenario's jax arrays (the shapes below) in `run` / `step`; in
    `run_host` numpy arrays with a leading batch axis B on every field (ego_pose f32[B, 3], ...).

    t: i32[] current model frame. ego_pose f32[3] (x, y, heading), ego_velocity f32[2]: the ego now (scene frame).
    xy f32[T, A, 2], heading f32[T, A], valid bool[T, A], velocity f32[T, A, 2]: the simulated frames so far
    (frames > t invalid; slot 0 the ego). cur_xy f32[A, 2], cur_heading f32[A], cur_valid bool[A], cur_velocity
    f32[A, 2]: frame t. size f32[A, 2]. map_tokens i32[T, M]: the frames' map tokens so far (the log's lanes
    encoded around the ego); cur_map_tokens i32[M]: frame t's. polylines f32[L, P, 2],
    polyline_valid bool[L, P]: the log's lanes. route_xy f32[R, 2], route_heading f32[R], route_s f32[R]: the
    logged ego's path from the current frame on (no timing; a route, as nuPlan gives its planners).
    pred_pose f32[3], pred_velocity f32[2]: the model's prediction of the ego's next frame (zeros without a model).
    hidden f32[N, d] or None: frame t's output tokens (what a head on the ego token reads).
    log_ego f32[Ts, 3], log_ego_valid bool[Ts]: the logged ego at the stored rate (for the expert policy only).
    road: the `gpd_jax.geometry.RoadGeometry` the scores read (drivable area, directed lanes), or None (a planner
    may score its candidates on it as the simulator scores the run).
    log_xy f32[Ts, A, 2], log_heading f32[Ts, A], log_valid bool[Ts, A]: every slot's log at the stored rate
    (the future included: for oracle baselines only, such as the world planner scored on the log's future).
    """

    t: jax.Array
    ego_pose: jax.Array
    ego_velocity: jax.Array
    xy: jax.Array
    heading: jax.Array
    valid: jax.Array
    velocity: jax.Array
    cur_xy: jax.Array
    cur_heading: jax.Array
    cur_valid: jax.Array
    cur_velocity: jax.Array
    size: jax.Array
    map_tokens: jax.Array
    cur_map_tokens: jax.Array
    polylines: jax.Array
    polyline_valid: jax.Array
    route_xy: jax.Array
    route_heading: jax.Array
    route_s: jax.Array
    pred_pose: jax.Array
    pred_velocity: jax.Array
    hidden: jax.Array | None
    log_ego: jax.Array
    log_ego_valid: jax.Array
    road: Any = None
    log_xy: jax.Array | None = None
    log_heading: jax.Array | None = None
    log_valid: jax.Array | None = None


@dataclasses.dataclass(frozen=True, eq=False)
class Policy:
    """A policy as pure functions (a Waymax-style actor): `select(params, obs, policy_state, key) -> (ego,
    policy_state)` each frame, `init(params, obs) -> policy_state` once, and optionally `plan(params, obs, key) ->
    f32[F, 3]` its open-loop plan (poses at the next F model frames, scene frame) for the open-loop score.

    ego: f32[3] the next model frame's pose, f32[5] pose and velocity there, f32[2] an action (acceleration,
    steering angle) for the bicycle model, f32[N, 3] stored-rate poses from the next stored frame on (N >= S: the
    S up to the next model frame, and beyond for the tracker to look ahead), or a
    `Plan` (poses at the next F model frames). Each but the action is the reference a `Tracker` follows (see
    `gpd_jax.sim.tracker`); without a tracker the ego is placed on it.
    needs_model: whether it reads the model's prediction or hidden tokens (the model then runs with any agents).
    needs_map: whether it reads the frames' map tokens (encoded then even when the model does not run).
    params: passed to every call (traced; e.g. a network's weights).
    """

    name: str
    select: Callable
    init: Callable = lambda params, obs: ()
    plan: Callable | None = None
    needs_model: bool = False
    needs_map: bool = False
    params: Any = None


def as_policy(policy) -> Policy:
    if isinstance(policy, Policy):
        return policy
    if callable(policy):
        return _wrap_callable(policy)
    raise SimError(f"a policy must be a gpd_jax.sim.Policy or a callable (params, obs, state, key) -> (ego, state); "
                   f"got {type(policy).__name__}")


@functools.lru_cache(maxsize=64)
def _wrap_callable(fn) -> Policy:
    return Policy(name=getattr(fn, "__name__", "policy"), select=fn, needs_model=True)


# ------------------------------------------------------------------------------------------------ scenes
def make_sim_scenes(model: Model, scenes: Scene, road: Any = None) -> SimScene:
    """Stored-rate scenes Scene [B, Ts', A', ...] (`gpd_jax.load_scenes`, with polylines) -> SimScene [B, ...]
    (host numpy work; map tokens of the model's frames encoded by its tokenizer from the lanes where missing)."""
    spec = model.spec
    if scenes.polylines is None:
        raise SimError("the scenes have no lane polylines (Scene.polylines): the simulator encodes the map around "
                       "the ego from them")
    if model.tokenizer is None:
        raise SimError("the model has no map tokenizer: the simulator encodes the log's lanes around the ego with it")
    if np.shape(scenes.xy)[-3] < spec.stored_frames_needed:
        raise SimError(f"the scenes have {np.shape(scenes.xy)[-3]} stored frames; the model needs "
                       f"{spec.stored_frames_needed}")
    view = model.prepare(scenes)
    if view.velocity is None:  # the simulator tracks velocities whatever the model reads
        view = view.replace(velocity=np.asarray(scenes.with_velocity(spec.stored_period_s).velocity)[
            ..., spec.model_frames(), : spec.num_agents, :])
    view = view.replace(map_tokens=np.asarray(view.map_tokens).astype(np.int32), polylines=None,
                        polyline_valid=None, lanes=None, lanes_valid=None)
    ts, a = spec.stored_frames_needed, spec.num_agents
    full_vel = np.asarray(scenes.with_velocity(spec.stored_period_s).velocity)
    sl = lambda x, tail=0: np.asarray(x)[(Ellipsis, slice(0, ts), slice(0, a)) + (slice(None),) * tail]
    road = getattr(scenes, "road", None) if road is None else road
    return jax.tree.map(jnp.asarray, SimScene(
        view=view, log_xy=sl(scenes.xy, 1), log_heading=sl(scenes.heading), log_valid=sl(scenes.valid),
        log_velocity=full_vel[..., :ts, :a, :], polylines=np.asarray(scenes.polylines, np.float32),
        polyline_valid=np.asarray(scenes.polyline_valid), road=road))


# ------------------------------------------------------------------------------------------------ internals
@dataclasses.dataclass(frozen=True)
class _Parts:
    """The model's pieces inside a traced function: the NNX module (None without a model), the map encoder."""

    module: Any
    encoder: Any
    spec: ModelSpec
    with_model: bool


def _parts(model: Model, params=None, rest=None, tok_params=None, with_model: bool = True,
           with_map: bool = False) -> _Parts:
    module = nnx.merge(model.graphdef, model.params if params is None else params,
                       model.rest if rest is None else rest) if with_model else None
    tok = model.tokenizer
    encoder = (tok.pose_encoder(tok.params if tok_params is None else tok_params)
               if (tok is not None and (with_model or with_map)) else None)
    return _Parts(module=module, encoder=encoder, spec=model.spec, with_model=with_model)


def _log_frame(parts: _Parts, view: Scene) -> Frame:
    vel = view.velocity if parts.module is None else parts.module.input_velocity(view.velocity)
    vel = jnp.zeros_like(view.xy) if vel is None else vel
    return Frame(xy=view.xy, heading=view.heading, valid=view.valid,
                 valid_logit=jnp.zeros(view.valid.shape, jnp.float32), map_tokens=view.map_tokens, velocity=vel)


def _lanes(parts: _Parts, polylines: jax.Array, polyline_valid: jax.Array, frames: int) -> LaneContext | None:
    """What a model that reads lanes (`GPD.reads_lanes`) uses in `frames` frames: the log's lanes in every frame
    (the simulator's map is always the log's, encoded around the ego). None for other models."""
    if parts.module is None or not parts.module.reads_lanes:
        return None
    return LaneContext(polylines=polylines, valid=polyline_valid, on=jnp.ones((frames,), bool))


def _reset(parts: _Parts, scene: SimScene, agents: str) -> SimState:
    if agents not in AGENT_MODELS:
        raise SimError(f"unknown agent model {agents!r}; known: {', '.join(AGENT_MODELS)}")
    spec = parts.spec
    h, t_total = spec.num_history, spec.num_frames
    c = spec.full_history - 1
    view = scene.view
    hist = (jnp.arange(t_total) < h)
    fhist = (jnp.arange(scene.log_xy.shape[0]) <= c)
    decode = (prefill(parts.module, _log_frame(parts, view), h, t_total,
                      _lanes(parts, scene.polylines, scene.polyline_valid, h))
              if parts.with_model else None)
    speed = jnp.linalg.norm(scene.log_velocity[c:], axis=-1)
    paths = make_paths(scene.log_xy[c:], scene.log_heading[c:], scene.log_valid[c:], speed)
    idm = IDMState(s=jnp.zeros(paths.v0.shape), v=jnp.where(scene.log_valid[c], speed[0], 0.0),
                   active=paths.spawn == 0)
    m2 = lambda x, mask: jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, jnp.zeros_like(x))
    h0, v0 = view.heading[h - 1, 0], view.velocity[h - 1, 0]
    control = TrackState.at_rest().replace(speed=jnp.maximum(v0[0] * jnp.cos(h0) + v0[1] * jnp.sin(h0), 0.0))
    return SimState(t=jnp.asarray(h - 1, jnp.int32), xy=m2(view.xy, hist), heading=m2(view.heading, hist),
                    valid=m2(view.valid, hist), velocity=m2(view.velocity, hist),
                    map_tokens=m2(view.map_tokens, hist), fine_xy=m2(scene.log_xy, fhist),
                    fine_heading=m2(scene.log_heading, fhist), fine_valid=m2(scene.log_valid, fhist),
                    decode=decode, idm=idm, paths=paths, control=control, scene=scene, agents=agents)


def _observe(parts: _Parts, state: SimState) -> Observation:
    t = state.t
    at = lambda x: jax.lax.dynamic_index_in_dim(x, t, 0, keepdims=False)
    cur_xy, cur_h, cur_v, cur_vel = at(state.xy), at(state.heading), at(state.valid), at(state.velocity)
    if state.decode is not None:
        pred = state.decode.pred
        pred_pose = jnp.concatenate([pred.xy[0, 0], pred.heading[0, :1]])
        pred_vel = (pred.velocity[0, 0] if pred.velocity is not None
                    else (pred.xy[0, 0] - cur_xy[0]) / parts.spec.frame_period_s)
        hidden = state.decode.hidden
    else:
        pred_pose, pred_vel, hidden = jnp.zeros(3), jnp.zeros(2), None
    sc = state.scene
    log_ego = jnp.concatenate([sc.log_xy[:, 0], sc.log_heading[:, :1]], -1)
    return Observation(
        t=t, ego_pose=jnp.concatenate([cur_xy[0], cur_h[:1]]), ego_velocity=cur_vel[0], xy=state.xy,
        heading=state.heading, valid=state.valid, velocity=state.velocity, cur_xy=cur_xy, cur_heading=cur_h,
        cur_valid=cur_v, cur_velocity=cur_vel, size=sc.view.size, map_tokens=state.map_tokens,
        cur_map_tokens=at(state.map_tokens),
        polylines=sc.polylines, polyline_valid=sc.polyline_valid, route_xy=state.paths.xy[0],
        route_heading=state.paths.heading[0], route_s=state.paths.s[0], pred_pose=pred_pose,
        pred_velocity=pred_vel, hidden=hidden, log_ego=log_ego, log_ego_valid=sc.log_valid[:, 0], road=sc.road,
        log_xy=sc.log_xy, log_heading=sc.log_heading, log_valid=sc.log_valid)


def _ego_array(ego, name: str) -> jax.Array:
    ego = jnp.asarray(ego)
    if not jnp.issubdtype(ego.dtype, jnp.floating):
        raise SimError(f"policy {name!r} returned an ego of dtype {ego.dtype}; expected floats")
    return ego.astype(jnp.float32)


def _shape_error(ego, spec: ModelSpec, name: str) -> SimError:
    s = spec.frame_stride
    return SimError(f"policy {name!r} returned an ego of shape {tuple(ego.shape)}; expected f32[3] (pose), f32[5] "
                    f"(pose, velocity), f32[2] (acceleration, steering), f32[N >= {s}, 3] (stored-rate poses) or a "
                    f"sim.Plan of poses f32[F, 3]")


def _stored_rate(ego, s: int) -> bool:
    return ego.ndim == 2 and ego.shape[1] == 3 and ego.shape[0] >= s


def is_action(ego) -> bool:
    """Whether a policy's ego output is an action (acceleration, steering): integrated as it is, never tracked."""
    return not isinstance(ego, Plan) and tuple(jnp.shape(ego)) == (2,)


def ego_reference(ego, pose0: jax.Array, vel0: jax.Array, spec: ModelSpec, name: str = "policy") -> jax.Array:
    """The stored-rate reference of a policy's output (not an action): f32[R, 3], the poses at the R stored frames
    after now (R = S for a pose or pose and velocity, N for N stored-rate poses, F x S for a `Plan` of F poses)."""
    s, period = spec.frame_stride, spec.frame_period_s
    if isinstance(ego, Plan):
        poses = _ego_array(ego.poses, name)
        if poses.ndim != 2 or poses.shape[-1] != 3 or poses.shape[0] < 1:
            raise SimError(f"policy {name!r} returned a Plan of shape {tuple(poses.shape)}; expected f32[F, 3] "
                           f"(F >= 1 poses at the next model frames)")
        return plan_path(pose0, vel0, poses, period, s)
    ego = _ego_array(ego, name)
    if ego.shape == (3,):
        return pose_path(pose0, vel0, ego, None, period, s)[0]
    if ego.shape == (5,):
        return pose_path(pose0, vel0, ego[:3], ego[3:], period, s)[0]
    if _stored_rate(ego, s):
        return ego
    raise _shape_error(ego, spec, name)


def ego_path(ego, pose0: jax.Array, vel0: jax.Array, length: jax.Array, spec: ModelSpec,
             limits: BicycleLimits = BicycleLimits(), name: str = "policy") -> tuple[jax.Array, jax.Array]:
    """The ego placed on a policy's output without a tracker: its S stored-rate poses up to the next model frame and
    its velocity there (shapes as `Policy` says; dispatched on the static shape). Raises SimError for any other
    shape."""
    s, dt, period = spec.frame_stride, spec.stored_period_s, spec.frame_period_s
    if isinstance(ego, Plan):
        path = ego_reference(ego, pose0, vel0, spec, name)
        nxt = path[2 * s - 1, :2] if path.shape[0] > s else 2 * path[s - 1, :2] - pose0[:2]
        return path[:s], (nxt - pose0[:2]) / (2 * period)
    ego = _ego_array(ego, name)
    if ego.shape == (3,):
        return pose_path(pose0, vel0, ego, None, period, s)
    if ego.shape == (5,):
        return pose_path(pose0, vel0, ego[:3], ego[3:], period, s)
    if ego.shape == (2,):
        path = bicycle_path(pose0, vel0, ego, length, s, dt, limits)
    elif _stored_rate(ego, s):
        path = ego[:s]
    else:
        raise _shape_error(ego, spec, name)
    prev = jnp.concatenate([pose0[None, :2], path[:-1, :2]], 0)[-1]
    return path, (path[-1, :2] - prev) / dt


@flax.struct.dataclass
class Follow:
    """The reference the tracker holds between replans: reference f32[R + 1, 3] (its pose at the frame it was made
    and at the R stored frames after), made_at i32[] (that model frame)."""

    reference: jax.Array
    made_at: jax.Array


def new_follow(spec: ModelSpec, tracker: Tracker | None, t) -> Follow:
    """An empty held reference (room for a plan over every future frame, or `replan_every` frames, plus the
    look-ahead), due for a replan at model frame `t`."""
    s, dt = spec.frame_stride, spec.stored_period_s
    r = 0 if tracker is None else tracker.reference_length(spec.num_future * s, s, dt)
    every = 1 if tracker is None else tracker.replan_every
    return Follow(reference=jnp.zeros((r + 1, 3), jnp.float32), made_at=jnp.asarray(t, jnp.int32) - every)


def _move_ego(spec: ModelSpec, state: SimState, ego, follow: Follow, tracker: Tracker | None,
              limits: BicycleLimits, name: str) -> tuple[jax.Array, jax.Array, TrackState, Follow]:
    """The ego's S stored-rate poses up to the next model frame, its velocity there and its control state, from a
    policy's output: placed on it (no tracker, or an action), or the held reference followed by the tracker (the
    output replacing the reference when a replan is due)."""
    s, dt, period = spec.frame_stride, spec.stored_period_s, spec.frame_period_s
    t = state.t
    at = lambda x: jax.lax.dynamic_index_in_dim(x, t, 0, keepdims=False)
    pose0 = jnp.concatenate([at(state.xy)[0], at(state.heading)[:1]])
    vel0 = at(state.velocity)[0]
    length = state.scene.view.size[0, 0]
    if tracker is None or is_action(ego):
        path, vel = ego_path(ego, pose0, vel0, length, spec, limits, name)
        speed = jnp.maximum(vel[0] * jnp.cos(path[-1, 2]) + vel[1] * jnp.sin(path[-1, 2]), 0.0)
        control = TrackState(speed=speed, accel=(speed - state.control.speed) / period, steer=jnp.zeros(()))
        return path, vel, control, follow
    reference = ego_reference(ego, pose0, vel0, spec, name)
    fresh = jnp.concatenate([pose0[None], extend(reference, pose0, follow.reference.shape[0] - 1)], 0)
    replan = t - follow.made_at >= tracker.replan_every
    follow = Follow(reference=jnp.where(replan, fresh, follow.reference),
                    made_at=jnp.where(replan, t, follow.made_at))
    window = jax.lax.dynamic_slice_in_dim(follow.reference, (t - follow.made_at) * s,
                                          s + tracker.lookahead_steps(dt) + 1, axis=0)
    path, control = track(window, pose0, state.control, length, s, dt, tracker, limits)
    vel = control.speed * jnp.stack([jnp.cos(path[-1, 2]), jnp.sin(path[-1, 2])])
    return path, vel, control, follow


def predicted_agents(pred, xy_t, h_t, v_t, vel_t, period: float, num_steps: int, key: jax.Array | None = None,
                     sampling: Sampling | None = None) -> tuple[Frame, tuple[jax.Array, jax.Array, jax.Array]]:
    """Every slot's next model frame from the model's prediction `pred` (a `Prediction` of one frame, leading dim 1),
    and the `num_steps` stored frames up to it: cubic Hermite curves between the two frames' positions and
    velocities, headings along the shorter arc; a slot is valid in between where it is valid at both ends.

    xy_t f32[A, 2], h_t f32[A], v_t bool[A], vel_t f32[A, 2]: the slots now. With `key` and a random `sampling` (a
    model with a sampling agent head) the next states are drawn (`gpd_jax.decoding.sample_agents`); otherwise
    the regressed ones. Returns (the next frame as a `Frame` (map_tokens None, velocity the slots' own, not the
    model's input form), (xy f32[S, A, 2], heading f32[S, A], valid bool[S, A]))."""
    axy, ah, logit = pred.xy[0], pred.heading[0], pred.valid_logit[0]
    avel = pred.velocity[0] if pred.velocity is not None else None
    if key is not None and sampling is not None and sampling.random and pred.modes is not None:
        axy, ah, avel = sample_agents(jax.tree.map(lambda a: a[0], pred.modes), key, sampling)
    avel = (axy - xy_t) / period if avel is None else avel
    av = logit > 0
    fxy = hermite(xy_t, vel_t, axy, avel, period, num_steps)                               # [S, A, 2]
    fh = lerp_heading(h_t, ah, num_steps)
    last = (jnp.arange(num_steps) == num_steps - 1)[:, None]
    fv = av[None] & (v_t[None] | last)
    return Frame(xy=axy, heading=ah, valid=av, valid_logit=logit, map_tokens=None, velocity=avel), (fxy, fh, fv)


def append_frame(parts: _Parts, decode: DecodeState | None, frame: Frame, ego_pose: jax.Array, ego_vel: jax.Array,
                 t, polylines: jax.Array, polyline_valid: jax.Array, tokens: jax.Array | None = None
                 ) -> tuple[Frame, DecodeState | None]:
    """Frame t with the ego placed at `ego_pose` f32[3] (velocity `ego_vel` f32[2]) in slot 0 and the map the lanes
    `polylines` encoded around it (zeros without an encoder; `frame.map_tokens` gives their shape and dtype),
    appended to the model's KV cache `decode` when the model runs. Returns (the frame, velocities the slots' own,
    the decode state after it). `tokens` i32[M]: those map tokens when already encoded (the same pose)."""
    f = frame
    f = f.replace(xy=f.xy.at[0].set(ego_pose[:2]), heading=f.heading.at[0].set(ego_pose[2]),
                  valid=f.valid.at[0].set(True), velocity=f.velocity.at[0].set(ego_vel),
                  valid_logit=f.valid_logit.at[0].set(0.0))
    like = f.map_tokens
    if tokens is None:
        tokens = (parts.encoder(polylines, polyline_valid, ego_pose) if parts.encoder is not None
                  else jnp.zeros_like(like))
    f = f.replace(map_tokens=tokens.astype(like.dtype))
    if parts.with_model:
        in_vel = parts.module.input_velocity(f.velocity)
        in_vel = jnp.zeros_like(f.xy) if in_vel is None else in_vel
        decode = advance(parts.module, decode, f.replace(velocity=in_vel), t,
                         _lanes(parts, polylines, polyline_valid, 1))
    return f, decode


def _step(parts: _Parts, state: SimState, epath: jax.Array, evel: jax.Array, control: TrackState,
          idm_params: IDMParams = IDMParams()) -> SimState:
    """Appends the next model frame: the ego on `epath` f32[S, 3] (its velocity `evel` f32[2] at the end), the other
    slots from the agent model."""
    spec = parts.spec
    s_n, dt, period = spec.frame_stride, spec.stored_period_s, spec.frame_period_s
    c = spec.full_history - 1
    t = state.t
    t1 = t + 1
    g0 = s_n * t
    sc = state.scene
    at = lambda x, i: jax.lax.dynamic_index_in_dim(x, i, 0, keepdims=False)
    xy_t, h_t, v_t, vel_t = at(state.xy, t), at(state.heading, t), at(state.valid, t), at(state.velocity, t)
    a_n = xy_t.shape[0]
    fine_slice = lambda x: jax.lax.dynamic_slice_in_dim(x, g0 + 1, s_n, axis=0)
    logit = jnp.zeros((a_n,), jnp.float32)
    idm = state.idm
    if state.agents == "gpd":
        nxt, (fxy, fh, fv) = predicted_agents(state.decode.pred, xy_t, h_t, v_t, vel_t, period, s_n)
        axy, ah, av, avel, logit = nxt.xy, nxt.heading, nxt.valid, nxt.velocity, nxt.valid_logit
    elif state.agents == "log":
        axy, ah, av, avel = at(sc.view.xy, t1), at(sc.view.heading, t1), at(sc.view.valid, t1), at(sc.view.velocity, t1)
        fxy, fh, fv = fine_slice(sc.log_xy), fine_slice(sc.log_heading), fine_slice(sc.log_valid)
    else:  # idm
        prev_vel = jnp.where((state.fine_valid[g0] & state.fine_valid[g0 - 1])[:, None],
                            (state.fine_xy[g0] - state.fine_xy[g0 - 1]) / dt, 0.0)
        slots = jnp.arange(a_n) > 0

        def sub(carry, k):
            st, pxy, pv, pvel = carry
            st = idm_substep(state.paths, st, g0 - c + k + 1, sc.view.size, pxy, pvel, pv, dt, idm_params, slots)
            nxy, nh, nv = idm_poses(state.paths, st)
            nxy = nxy.at[0].set(epath[k, :2])
            nh = nh.at[0].set(epath[k, 2])
            nv = nv.at[0].set(True)
            nvel = jnp.where((nv & pv)[:, None], (nxy - pxy) / dt, 0.0)
            return (st, nxy, nv, nvel), (nxy, nh, nv, nvel)

        init = (idm, state.fine_xy[g0], state.fine_valid[g0], prev_vel)
        (idm, _, _, _), (fxy, fh, fv, fvel) = jax.lax.scan(sub, init, jnp.arange(s_n))
        axy, ah, av, avel = fxy[-1], fh[-1], fv[-1], fvel[-1]
    # the ego
    fxy, fh, fv = fxy.at[:, 0].set(epath[:, :2]), fh.at[:, 0].set(epath[:, 2]), fv.at[:, 0].set(True)
    frame, decode = append_frame(parts, state.decode, Frame(xy=axy, heading=ah, valid=av, valid_logit=logit,
                                                             map_tokens=state.map_tokens[0], velocity=avel),
                                 epath[-1], evel, t1, sc.polylines, sc.polyline_valid)
    axy, ah, av, avel, tokens = frame.xy, frame.heading, frame.valid, frame.velocity, frame.map_tokens
    put = lambda arr, val, i: jax.lax.dynamic_update_index_in_dim(arr, val.astype(arr.dtype), i, 0)
    putf = lambda arr, val: jax.lax.dynamic_update_slice_in_dim(arr, val.astype(arr.dtype), g0 + 1, 0)
    return state.replace(t=t1, xy=put(state.xy, axy, t1), heading=put(state.heading, ah, t1),
                         valid=put(state.valid, av, t1), velocity=put(state.velocity, avel, t1),
                         map_tokens=put(state.map_tokens, tokens, t1), fine_xy=putf(state.fine_xy, fxy),
                         fine_heading=putf(state.fine_heading, fh), fine_valid=putf(state.fine_valid, fv),
                         decode=decode, idm=idm, control=control)


# ------------------------------------------------------------------------------------------------ public pure API
def reset(model: Model, scene: SimScene, key: jax.Array | None = None, *, agents: str = "gpd",
          with_model: bool = True) -> SimState:
    """The state after the log's history frames [0, H) (the KV cache prefilled; `with_model=False` skips the
    model, for log or IDM agents with a policy that does not read it). One unbatched SimScene; `key` is accepted
    for a uniform signature (every agent model here is deterministic). Pure: jit/vmap it freely."""
    del key
    return _reset(_parts(model, with_model=with_model), scene, agents)


def step(model: Model, state: SimState, ego, *, limits: BicycleLimits = BicycleLimits(),
         tracker: Tracker | None = Tracker()) -> tuple[SimState, Observation]:
    """Appends the next model frame with the ego moved by `ego` (see `Policy`): `state, obs = step(...)`. Pure.
    The tracker follows `ego` as a fresh reference (a replan every call; `run` and `run_host` hold a reference
    over `Tracker.replan_every` frames); `tracker=None` places the ego on it."""
    parts = _parts(model, with_model=state.decode is not None)
    follow = new_follow(model.spec, tracker, state.t)
    epath, evel, control, _ = _move_ego(model.spec, state, ego, follow, tracker, limits, "policy")
    state = _step(parts, state, epath, evel, control)
    return state, _observe(parts, state)


def observe(model: Model, state: SimState) -> Observation:
    """What a policy sees now (`Observation`)."""
    return _observe(_parts(model, with_model=state.decode is not None), state)


@flax.struct.dataclass
class SimResult:
    """A batch of closed-loop runs. fine_xy f32[B, Ts, A, 2], fine_heading f32[B, Ts, A], fine_valid bool[B, Ts, A]:
    the simulated scenes at the stored rate (history from the log); xy, heading, valid, velocity [B, T, A, ...] at
    the model's rate (velocity: instantaneous, scene frame); map_tokens i32[B, T, M]; plan f32[B, F, 3] or None:
    the policy's open-loop plan at the current frame; nonfinite bool[B, T]: model frames whose ego output was not
    finite."""

    fine_xy: jax.Array
    fine_heading: jax.Array
    fine_valid: jax.Array
    xy: jax.Array
    heading: jax.Array
    valid: jax.Array
    velocity: jax.Array
    map_tokens: jax.Array
    plan: jax.Array | None
    nonfinite: jax.Array


@flax.struct.dataclass
class RunCarry:
    """The scan carry of `run`: the simulator state, the policy's state, the tracker's held reference, the key, and
    which frames' ego outputs were not finite (bool[T])."""

    state: SimState
    policy_state: Any
    follow: Follow
    key: jax.Array
    nonfinite: jax.Array


def _run_one(parts: _Parts, policy: Policy, pparams, scene: SimScene, key, agents: str, limits: BicycleLimits,
             tracker: Tracker | None):
    spec = parts.spec
    state = _reset(parts, scene, agents)
    obs = _observe(parts, state)
    pstate = policy.init(pparams, obs)
    key, pkey = jax.random.split(key)
    plan = None if policy.plan is None else policy.plan(pparams, obs, pkey)

    def body(carry: RunCarry, _):
        k, sub = jax.random.split(carry.key)
        o = _observe(parts, carry.state)
        ego, ps = policy.select(pparams, o, carry.policy_state, sub)
        leaves = jax.tree.leaves(ego)
        bad = ~jnp.all(jnp.stack([jnp.all(jnp.isfinite(jnp.asarray(x))) for x in leaves]))
        nonfinite = carry.nonfinite.at[carry.state.t + 1].set(bad)
        epath, evel, control, follow = _move_ego(spec, carry.state, ego, carry.follow, tracker, limits, policy.name)
        st = _step(parts, carry.state, epath, evel, control)
        return RunCarry(state=st, policy_state=ps, follow=follow, key=k, nonfinite=nonfinite), None

    init = RunCarry(state=state, policy_state=pstate, follow=new_follow(spec, tracker, state.t), key=key,
                    nonfinite=jnp.zeros(spec.num_frames, bool))
    final, _ = jax.lax.scan(body, init, None, length=spec.num_future)
    st = final.state
    return SimResult(fine_xy=st.fine_xy, fine_heading=st.fine_heading, fine_valid=st.fine_valid, xy=st.xy,
                     heading=st.heading, valid=st.valid, velocity=st.velocity, map_tokens=st.map_tokens, plan=plan,
                     nonfinite=final.nonfinite)


@functools.partial(jax.jit, static_argnames=("static",))
def _run_jit(params, rest, tok_params, pparams, scenes, keys, static):
    model, policy, agents, with_model, limits, tracker = static
    parts = _parts(model, params, rest, tok_params, with_model, policy.needs_map)
    return jax.vmap(lambda sc, k: _run_one(parts, policy, pparams, sc, k, agents, limits, tracker))(scenes, keys)


@functools.lru_cache(maxsize=16)
def _static_model_cached(graphdef, tokenizer, spec):
    return Model(config=None, graphdef=graphdef, params=None, rest=None, spec=spec, tokenizer=tokenizer, path=None)


def needs_model(policy: Policy, agents: str) -> bool:
    return agents == "gpd" or policy.needs_model


def run(model: Model, scenes: SimScene, policy, key: jax.Array, *, agents: str = "gpd", policy_params: Any = None,
        limits: BicycleLimits = BicycleLimits(), tracker: Tracker | None = Tracker(), check: bool = True
        ) -> SimResult:
    """Closed-loop runs of `policy` on a batch of scenarios (SimScene [B, ...]) over the model's future frames,
    one `lax.scan` vmapped over the batch, compiled once per batch shape, policy and agent model.

    `policy_params` (default `policy.params`) is what the policy's functions receive as `params`: traced, so other
    values of the same shapes (new weights, a different setting) reuse the compiled run. The ego follows the
    policy's output with `tracker` (replanning every `tracker.replan_every` model frames; `gpd_jax.sim.tracker`);
    `tracker=None` places it on the output each frame.

    With `check`, a policy output that is not finite raises SimError naming the policy, the scenarios and frames.
    """
    policy = as_policy(policy)
    if agents not in AGENT_MODELS:
        raise SimError(f"unknown agent model {agents!r}; known: {', '.join(AGENT_MODELS)}")
    b = np.shape(scenes.log_xy)[0]
    keys = jax.random.split(key, b)
    with_model = needs_model(policy, agents)
    static = (_static_model_cached(model.graphdef, model.tokenizer, model.spec), policy, agents, with_model, limits,
              _check_tracker(tracker))
    tok_params = model.tokenizer.params if model.tokenizer is not None else None
    pparams = policy.params if policy_params is None else policy_params
    out = _run_jit(model.params, model.rest, tok_params, pparams, scenes, keys, static)
    if check:
        check_finite(out, policy.name)
    return out


def _check_tracker(tracker):
    if tracker is not None and not isinstance(tracker, Tracker):
        raise SimError(f"tracker must be a gpd_jax.sim.Tracker or None; got {type(tracker).__name__}")
    if tracker is not None and (not isinstance(tracker.replan_every, int) or tracker.replan_every < 1):
        raise SimError(f"Tracker.replan_every must be an integer >= 1 (model frames), got {tracker.replan_every!r}")
    return tracker


def check_finite(out: SimResult, name: str) -> None:
    bad = np.asarray(out.nonfinite)
    if bad.any():
        where = [f"scenario {i} frame {t}" for i, t in zip(*np.nonzero(bad))][:5]
        raise SimError(f"policy {name!r} returned a non-finite ego at {', '.join(where)}"
                       + (" ..." if bad.sum() > 5 else ""))


# ------------------------------------------------------------------------------------------------ host loop
@functools.partial(jax.jit, static_argnames=("static",))
def _reset_obs_jit(params, rest, tok_params, scenes, static):
    model, agents, with_model = static
    parts = _parts(model, params, rest, tok_params, with_model)
    state = jax.vmap(lambda sc: _reset(parts, sc, agents))(scenes)
    return state, jax.vmap(lambda st: _observe(parts, st))(state)


@functools.partial(jax.jit, static_argnames=("static",))
def _step_obs_jit(params, rest, tok_params, state, ego, follow, static):
    model, with_model, limits, tracker = static
    parts = _parts(model, params, rest, tok_params, with_model)

    def one(st, e, f):
        epath, evel, control, f = _move_ego(model.spec, st, e, f, tracker, limits, "planner")
        return _step(parts, st, epath, evel, control), f

    state, follow = jax.vmap(one)(state, ego, follow)
    return state, follow, jax.vmap(lambda st: _observe(parts, st))(state)


def _host_ego(raw, b: int, s: int, shapes: dict, name: str):
    """A host planner's output as numpy floats (an array, or a Plan of one), its shape checked against the batch."""
    if isinstance(raw, Plan):
        try:
            poses = np.asarray(raw.poses, np.float32)
        except (TypeError, ValueError) as e:
            raise SimError(f"planner {name!r} returned a Plan whose poses are not an array of floats: {e}") from None
        if poses.ndim != 3 or poses.shape[0] != b or poses.shape[2] != 3 or poses.shape[1] < 1:
            raise SimError(f"planner {name!r} returned a Plan of shape {tuple(poses.shape)}; expected f32[{b}, F, 3] "
                           f"(the batch's poses at the next F model frames)")
        return Plan(poses=poses)
    try:
        ego = np.asarray(raw, np.float32)
    except (TypeError, ValueError) as e:
        raise SimError(f"planner {name!r} returned {type(raw).__name__}, not an array of floats: {e}") from None
    if ego.shape[:1] != (b,) or (tuple(ego.shape[1:]) not in shapes and not (
            ego.ndim == 3 and ego.shape[2] == 3 and ego.shape[1] >= s)):
        expected = ", ".join(f"[{b}, {', '.join(map(str, k))}] ({v})" for k, v in shapes.items())
        raise SimError(f"planner {name!r} returned an array of shape {tuple(ego.shape)}; expected one ego per "
                       f"scenario of the batch of {b}: {expected} (or more than {s} poses), or a sim.Plan")
    return ego


def run_host(model: Model, scenes: SimScene, planner: Callable[[Observation], Any], *, agents: str = "gpd",
             with_model: bool = True, limits: BicycleLimits = BicycleLimits(), tracker: Tracker | None = Tracker(),
             progress: bool = False) -> SimResult:
    """Closed-loop runs of a batch of scenarios (SimScene [B, ...]) with a plain-Python planner in the loop.

    The planner is called once per model frame (`model.spec.num_future` calls) with the whole batch:
    `planner(obs)` receives one `Observation` whose fields are numpy arrays with a leading batch axis B (the
    unbatched shapes of `Observation` with B in front): t i32[B] (the same frame in every scenario), ego_pose
    f32[B, 3], ego_velocity f32[B, 2], xy f32[B, T, A, 2], heading f32[B, T, A], valid bool[B, T, A], velocity
    f32[B, T, A, 2], cur_xy f32[B, A, 2], cur_heading f32[B, A], cur_valid bool[B, A], cur_velocity f32[B, A, 2],
    size f32[B, A, 2], map_tokens i32[B, T, M], cur_map_tokens i32[B, M], polylines f32[B, L, P, 2],
    polyline_valid bool[B, L, P], route_xy f32[B, R, 2], route_heading f32[B, R], route_s f32[B, R], pred_pose
    f32[B, 3], pred_velocity f32[B, 2], hidden f32[B, N, d] or None, log_ego f32[B, Ts, 3], log_ego_valid
    bool[B, Ts], road (RoadGeometry [B, ...] or None), log_xy f32[B, Ts, A, 2], log_heading f32[B, Ts, A],
    log_valid bool[B, Ts, A] (the log, for oracles only). It returns the B egos as one float array, one of (S = `model.spec.frame_stride`):

    * f32[B, 3]: each scenario's next model-frame pose (x, y, heading; scene frame);
    * f32[B, 5]: pose and velocity (vx, vy) there;
    * f32[B, 2]: an action (acceleration m/s^2, steering angle rad) for the bicycle model (`limits`);
    * f32[B, N, 3]: stored-rate poses from the next stored frame on (N >= S);
    * `Plan(poses=f32[B, F, 3])`: poses at the next F model frames.

    The ego follows them with `tracker` as in `run` (the planner is called every frame; its output is taken every
    `tracker.replan_every` frames); `tracker=None` places the ego on them.

    Batched, so the model's reset and step are each jitted once (per batch shape) and serve the whole batch; the
    planner runs on the host in between. A planner for one scenario at a time loops over B itself. Example, a
    constant-velocity planner::

        def cv(obs):                                       # obs.ego_pose: numpy f32[B, 3]
            period = model.spec.frame_period_s             # seconds between model frames
            nxt = obs.ego_pose[:, :2] + obs.ego_velocity * period
            return np.concatenate([nxt, obs.ego_pose[:, 2:], obs.ego_velocity], -1)      # f32[B, 5]

        out = sim.run_host(model, sims, cv, agents="idm", with_model=False)
        scores = sim.score(model, sims, out)               # {"CLS": f32[B], ...}

    `with_model=False` skips the model for log or IDM agents when the planner does not read `pred_pose`,
    `pred_velocity` or `hidden` (GPD agents always run it). Raises SimError naming the planner when it returns
    another shape or a non-finite ego. The result has no open-loop plan (`plan` None).
    """
    if agents not in AGENT_MODELS:
        raise SimError(f"unknown agent model {agents!r}; known: {', '.join(AGENT_MODELS)}")
    with_model = with_model or agents == "gpd"
    sm = _static_model_cached(model.graphdef, model.tokenizer, model.spec)
    tok_params = model.tokenizer.params if model.tokenizer is not None else None
    b = np.shape(scenes.log_xy)[0]
    s = model.spec.frame_stride
    shapes = {(3,): "pose", (5,): "pose, velocity", (2,): "acceleration, steering", (s, 3): "stored-rate poses"}
    state, obs = _reset_obs_jit(model.params, model.rest, tok_params, scenes, (sm, agents, with_model))
    nonfinite = np.zeros((b, model.spec.num_frames), bool)
    frames = range(model.spec.num_future)
    if progress:
        from tqdm import tqdm
        frames = tqdm(frames, desc="closed loop (host planner)")
    name = getattr(planner, "__name__", "planner")
    _check_tracker(tracker)
    follow = None
    for _ in frames:
        raw = planner(jax.device_get(obs))
        ego = _host_ego(raw, b, s, shapes, name)
        flat = np.asarray(ego.poses if isinstance(ego, Plan) else ego)
        t1 = int(np.asarray(obs.t)[0]) + 1
        nonfinite[:, t1] = ~np.isfinite(flat.reshape(b, -1)).all(-1)
        if nonfinite[:, t1].any():
            break
        ego = jax.tree.map(jnp.asarray, ego)
        if follow is None:
            one = new_follow(model.spec, tracker, t1 - 1)
            follow = jax.tree.map(lambda x: jnp.broadcast_to(x, (b,) + x.shape), one)
        state, follow, obs = _step_obs_jit(model.params, model.rest, tok_params, state, ego, follow,
                                           (sm, with_model, limits, tracker))
    out = SimResult(fine_xy=state.fine_xy, fine_heading=state.fine_heading, fine_valid=state.fine_valid,
                    xy=state.xy, heading=state.heading, valid=state.valid, velocity=state.velocity,
                    map_tokens=state.map_tokens, plan=None,
                    nonfinite=jnp.asarray(nonfinite))
    check_finite(out, name)
    return out
