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
from gpd_jax.decoding import DecodeState, Frame, advance, prefill
from gpd_jax.model import LaneContext
from gpd_jax.scene import Scene
from gpd_jax.sim.agents import IDMParams, IDMState, Paths, idm_poses, idm_substep, make_paths
from gpd_jax.sim.dynamics import BicycleLimits, bicycle_path, hermite, lerp_heading, pose_path
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
    (slot 0: the logged ego's route). scene: what the simulation was given. agents: the agent model (static).
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


@dataclasses.dataclass(frozen=True, eq=False)
class Policy:
    """A policy as pure functions (a Waymax-style actor): `select(params, obs, policy_state, key) -> (ego,
    policy_state)` each frame, `init(params, obs) -> policy_state` once, and optionally `plan(params, obs, key) ->
    f32[F, 3]` its open-loop plan (poses at the next F model frames, scene frame) for the open-loop score.

    ego: f32[3] the next model frame's pose, f32[5] pose and velocity there, f32[2] an action (acceleration,
    steering angle) for the bicycle model, or f32[S, 3] the S stored-rate poses up to the next model frame.
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


def _lanes(parts: _Parts, scene: SimScene, frames: int) -> LaneContext | None:
    """What a model that reads lanes (`GPD.reads_lanes`) uses in `frames` frames: the log's lanes in every frame
    (the simulator's map is always the log's, encoded around the ego). None for other models."""
    if parts.module is None or not parts.module.reads_lanes:
        return None
    return LaneContext(polylines=scene.polylines, valid=scene.polyline_valid, on=jnp.ones((frames,), bool))


def _reset(parts: _Parts, scene: SimScene, agents: str) -> SimState:
    if agents not in AGENT_MODELS:
        raise SimError(f"unknown agent model {agents!r}; known: {', '.join(AGENT_MODELS)}")
    spec = parts.spec
    h, t_total = spec.num_history, spec.num_frames
    c = spec.full_history - 1
    view = scene.view
    hist = (jnp.arange(t_total) < h)
    fhist = (jnp.arange(scene.log_xy.shape[0]) <= c)
    decode = (prefill(parts.module, _log_frame(parts, view), h, t_total, _lanes(parts, scene, h))
              if parts.with_model else None)
    speed = jnp.linalg.norm(scene.log_velocity[c:], axis=-1)
    paths = make_paths(scene.log_xy[c:], scene.log_heading[c:], scene.log_valid[c:], speed)
    idm = IDMState(s=jnp.zeros(paths.v0.shape), v=jnp.where(scene.log_valid[c], speed[0], 0.0),
                   active=paths.spawn == 0)
    m2 = lambda x, mask: jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, jnp.zeros_like(x))
    return SimState(t=jnp.asarray(h - 1, jnp.int32), xy=m2(view.xy, hist), heading=m2(view.heading, hist),
                    valid=m2(view.valid, hist), velocity=m2(view.velocity, hist),
                    map_tokens=m2(view.map_tokens, hist), fine_xy=m2(scene.log_xy, fhist),
                    fine_heading=m2(scene.log_heading, fhist), fine_valid=m2(scene.log_valid, fhist),
                    decode=decode, idm=idm, paths=paths, scene=scene, agents=agents)


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
        pred_velocity=pred_vel, hidden=hidden, log_ego=log_ego, log_ego_valid=sc.log_valid[:, 0])


def ego_path(ego: jax.Array, pose0: jax.Array, vel0: jax.Array, length: jax.Array, spec: ModelSpec,
             limits: BicycleLimits = BicycleLimits(), name: str = "policy") -> tuple[jax.Array, jax.Array]:
    """The ego's S stored-rate poses up to the next model frame and its velocity there, from a policy's output
    (shapes as `Policy` says; dispatched on the static shape). Raises SimError for any other shape."""
    s, dt, period = spec.frame_stride, spec.stored_period_s, spec.frame_period_s
    ego = jnp.asarray(ego)
    if not jnp.issubdtype(ego.dtype, jnp.floating):
        raise SimError(f"policy {name!r} returned an ego of dtype {ego.dtype}; expected floats")
    ego = ego.astype(jnp.float32)
    if ego.shape == (3,):
        return pose_path(pose0, vel0, ego, None, period, s)
    if ego.shape == (5,):
        return pose_path(pose0, vel0, ego[:3], ego[3:], period, s)
    if ego.shape == (2,):
        path = bicycle_path(pose0, vel0, ego, length, s, dt, limits)
    elif ego.shape == (s, 3):
        path = ego
    else:
        raise SimError(f"policy {name!r} returned an ego of shape {tuple(ego.shape)}; expected f32[3] (pose), "
                       f"f32[5] (pose, velocity), f32[2] (acceleration, steering) or f32[{s}, 3] (stored-rate poses)")
    prev = jnp.concatenate([pose0[None, :2], path[:-1, :2]], 0)[-1]
    return path, (path[-1, :2] - prev) / dt


def _step(parts: _Parts, state: SimState, ego: jax.Array, limits: BicycleLimits = BicycleLimits(),
          idm_params: IDMParams = IDMParams(), name: str = "policy") -> SimState:
    spec = parts.spec
    s_n, dt, period = spec.frame_stride, spec.stored_period_s, spec.frame_period_s
    c = spec.full_history - 1
    t = state.t
    t1 = t + 1
    g0 = s_n * t
    sc = state.scene
    at = lambda x, i: jax.lax.dynamic_index_in_dim(x, i, 0, keepdims=False)
    xy_t, h_t, v_t, vel_t = at(state.xy, t), at(state.heading, t), at(state.valid, t), at(state.velocity, t)
    pose0 = jnp.concatenate([xy_t[0], h_t[:1]])
    epath, evel = ego_path(ego, pose0, vel_t[0], sc.view.size[0, 0], spec, limits, name)
    a_n = xy_t.shape[0]
    fine_slice = lambda x: jax.lax.dynamic_slice_in_dim(x, g0 + 1, s_n, axis=0)
    logit = jnp.zeros((a_n,), jnp.float32)
    idm = state.idm
    if state.agents == "gpd":
        pred = state.decode.pred
        axy, ah, logit = pred.xy[0], pred.heading[0], pred.valid_logit[0]
        av = logit > 0
        avel = pred.velocity[0] if pred.velocity is not None else (axy - xy_t) / period
        fxy = hermite(xy_t, vel_t, axy, avel, period, s_n)                                   # [S, A, 2]
        fh = lerp_heading(h_t, ah, s_n)
        last = (jnp.arange(s_n) == s_n - 1)[:, None]
        fv = av[None] & (v_t[None] | last)
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
    axy, ah, av, avel = axy.at[0].set(epath[-1, :2]), ah.at[0].set(epath[-1, 2]), av.at[0].set(True), avel.at[0].set(evel)
    fxy, fh, fv = fxy.at[:, 0].set(epath[:, :2]), fh.at[:, 0].set(epath[:, 2]), fv.at[:, 0].set(True)
    logit = logit.at[0].set(0.0)
    decode = state.decode
    if parts.encoder is not None:
        tokens = parts.encoder(sc.polylines, sc.polyline_valid, epath[-1]).astype(state.map_tokens.dtype)
    else:
        tokens = jnp.zeros_like(state.map_tokens[0])
    if parts.with_model:
        in_vel = parts.module.input_velocity(avel)
        in_vel = jnp.zeros_like(axy) if in_vel is None else in_vel
        frame = Frame(xy=axy, heading=ah, valid=av, valid_logit=logit, map_tokens=tokens, velocity=in_vel)
        decode = advance(parts.module, decode, frame, t1, _lanes(parts, sc, 1))
    put = lambda arr, val, i: jax.lax.dynamic_update_index_in_dim(arr, val.astype(arr.dtype), i, 0)
    putf = lambda arr, val: jax.lax.dynamic_update_slice_in_dim(arr, val.astype(arr.dtype), g0 + 1, 0)
    return state.replace(t=t1, xy=put(state.xy, axy, t1), heading=put(state.heading, ah, t1),
                         valid=put(state.valid, av, t1), velocity=put(state.velocity, avel, t1),
                         map_tokens=put(state.map_tokens, tokens, t1), fine_xy=putf(state.fine_xy, fxy),
                         fine_heading=putf(state.fine_heading, fh), fine_valid=putf(state.fine_valid, fv),
                         decode=decode, idm=idm)


# ------------------------------------------------------------------------------------------------ public pure API
def reset(model: Model, scene: SimScene, key: jax.Array | None = None, *, agents: str = "gpd",
          with_model: bool = True) -> SimState:
    """The state after the log's history frames [0, H) (the KV cache prefilled; `with_model=False` skips the
    model, for log or IDM agents with a policy that does not read it). One unbatched SimScene; `key` is accepted
    for a uniform signature (every agent model here is deterministic). Pure: jit/vmap it freely."""
    del key
    return _reset(_parts(model, with_model=with_model), scene, agents)


def step(model: Model, state: SimState, ego: jax.Array, *, limits: BicycleLimits = BicycleLimits()
         ) -> tuple[SimState, Observation]:
    """Appends the next model frame with the ego placed by `ego` (see `Policy`): `state, obs = step(...)`. Pure."""
    parts = _parts(model, with_model=state.decode is not None)
    state = _step(parts, state, ego, limits)
    return state, _observe(parts, state)


def observe(model: Model, state: SimState) -> Observation:
    """What a policy sees now (`Observation`)."""
    return _observe(_parts(model, with_model=state.decode is not None), state)


@flax.struct.dataclass
class SimResult:
    """A batch of closed-loop runs. fine_xy f32[B, Ts, A, 2], fine_heading f32[B, Ts, A], fine_valid bool[B, Ts, A]:
    the simulated scenes at the stored rate (history from the log); xy, heading, valid [B, T, A, ...] at the
    model's rate; map_tokens i32[B, T, M]; plan f32[B, F, 3] or None: the policy's open-loop plan at the current
    frame; nonfinite bool[B, T]: model frames whose ego output was not finite."""

    fine_xy: jax.Array
    fine_heading: jax.Array
    fine_valid: jax.Array
    xy: jax.Array
    heading: jax.Array
    valid: jax.Array
    map_tokens: jax.Array
    plan: jax.Array | None
    nonfinite: jax.Array


@flax.struct.dataclass
class RunCarry:
    """The scan carry of `run`: the simulator state, the policy's state, the key, and which frames' ego outputs
    were not finite (bool[T])."""

    state: SimState
    policy_state: Any
    key: jax.Array
    nonfinite: jax.Array


def _run_one(parts: _Parts, policy: Policy, pparams, scene: SimScene, key, agents: str, limits: BicycleLimits):
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
        bad = ~jnp.all(jnp.isfinite(jnp.asarray(ego)))
        nonfinite = carry.nonfinite.at[carry.state.t + 1].set(bad)
        st = _step(parts, carry.state, ego, limits, name=policy.name)
        return RunCarry(state=st, policy_state=ps, key=k, nonfinite=nonfinite), None

    init = RunCarry(state=state, policy_state=pstate, key=key, nonfinite=jnp.zeros(spec.num_frames, bool))
    final, _ = jax.lax.scan(body, init, None, length=spec.num_future)
    st = final.state
    return SimResult(fine_xy=st.fine_xy, fine_heading=st.fine_heading, fine_valid=st.fine_valid, xy=st.xy,
                     heading=st.heading, valid=st.valid, map_tokens=st.map_tokens, plan=plan,
                     nonfinite=final.nonfinite)


@functools.partial(jax.jit, static_argnames=("static",))
def _run_jit(params, rest, tok_params, pparams, scenes, keys, static):
    model, policy, agents, with_model, limits = static
    parts = _parts(model, params, rest, tok_params, with_model, policy.needs_map)
    return jax.vmap(lambda sc, k: _run_one(parts, policy, pparams, sc, k, agents, limits))(scenes, keys)


@functools.lru_cache(maxsize=16)
def _static_model_cached(graphdef, tokenizer, spec):
    return Model(config=None, graphdef=graphdef, params=None, rest=None, spec=spec, tokenizer=tokenizer, path=None)


def needs_model(policy: Policy, agents: str) -> bool:
    return agents == "gpd" or policy.needs_model


def run(model: Model, scenes: SimScene, policy, key: jax.Array, *, agents: str = "gpd", policy_params: Any = None,
        limits: BicycleLimits = BicycleLimits(), check: bool = True) -> SimResult:
    """Closed-loop runs of `policy` on a batch of scenarios (SimScene [B, ...]) over the model's future frames,
    one `lax.scan` vmapped over the batch, compiled once per batch shape, policy and agent model.

    `policy_params` (default `policy.params`) is what the policy's functions receive as `params`: traced, so other
    values of the same shapes (new weights, a different setting) reuse the compiled run.

    With `check`, a policy output that is not finite raises SimError naming the policy, the scenarios and frames.
    """
    policy = as_policy(policy)
    if agents not in AGENT_MODELS:
        raise SimError(f"unknown agent model {agents!r}; known: {', '.join(AGENT_MODELS)}")
    b = np.shape(scenes.log_xy)[0]
    keys = jax.random.split(key, b)
    with_model = needs_model(policy, agents)
    static = (_static_model_cached(model.graphdef, model.tokenizer, model.spec), policy, agents, with_model, limits)
    tok_params = model.tokenizer.params if model.tokenizer is not None else None
    pparams = policy.params if policy_params is None else policy_params
    out = _run_jit(model.params, model.rest, tok_params, pparams, scenes, keys, static)
    if check:
        check_finite(out, policy.name)
    return out


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
def _step_obs_jit(params, rest, tok_params, state, ego, static):
    model, with_model, limits = static
    parts = _parts(model, params, rest, tok_params, with_model)
    state = jax.vmap(lambda st, e: _step(parts, st, e, limits))(state, ego)
    return state, jax.vmap(lambda st: _observe(parts, st))(state)


def run_host(model: Model, scenes: SimScene, planner: Callable[[Observation], Any], *, agents: str = "gpd",
             with_model: bool = True, limits: BicycleLimits = BicycleLimits(), progress: bool = False) -> SimResult:
    """Closed-loop runs of a batch of scenarios (SimScene [B, ...]) with a plain-Python planner in the loop.

    The planner is called once per model frame (`model.spec.num_future` calls) with the whole batch:
    `planner(obs)` receives one `Observation` whose fields are numpy arrays with a leading batch axis B (the
    unbatched shapes of `Observation` with B in front): t i32[B] (the same frame in every scenario), ego_pose
    f32[B, 3], ego_velocity f32[B, 2], xy f32[B, T, A, 2], heading f32[B, T, A], valid bool[B, T, A], velocity
    f32[B, T, A, 2], cur_xy f32[B, A, 2], cur_heading f32[B, A], cur_valid bool[B, A], cur_velocity f32[B, A, 2],
    size f32[B, A, 2], map_tokens i32[B, T, M], cur_map_tokens i32[B, M], polylines f32[B, L, P, 2],
    polyline_valid bool[B, L, P], route_xy f32[B, R, 2], route_heading f32[B, R], route_s f32[B, R], pred_pose
    f32[B, 3], pred_velocity f32[B, 2], hidden f32[B, N, d] or None, log_ego f32[B, Ts, 3], log_ego_valid
    bool[B, Ts]. It returns the B egos as one float array, one of (S = `model.spec.frame_stride`):

    * f32[B, 3]: each scenario's next model-frame pose (x, y, heading; scene frame);
    * f32[B, 5]: pose and velocity (vx, vy) there;
    * f32[B, 2]: an action (acceleration m/s^2, steering angle rad) for the bicycle model (`limits`);
    * f32[B, S, 3]: the S stored-rate poses up to the next model frame.

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
    for _ in frames:
        raw = planner(jax.device_get(obs))
        try:
            ego = np.asarray(raw, np.float32)
        except (TypeError, ValueError) as e:
            raise SimError(f"planner {name!r} returned {type(raw).__name__}, not an array of floats: {e}") from None
        if ego.shape[:1] != (b,) or tuple(ego.shape[1:]) not in shapes:
            expected = ", ".join(f"[{b}, {', '.join(map(str, k))}] ({v})" for k, v in shapes.items())
            raise SimError(f"planner {name!r} returned an array of shape {tuple(ego.shape)}; expected one ego per "
                           f"scenario of the batch of {b}: {expected}")
        t1 = int(np.asarray(obs.t)[0]) + 1
        nonfinite[:, t1] = ~np.isfinite(ego.reshape(b, -1)).all(-1)
        if nonfinite[:, t1].any():
            break
        state, obs = _step_obs_jit(model.params, model.rest, tok_params, state, jnp.asarray(ego),
                                   (sm, with_model, limits))
    out = SimResult(fine_xy=state.fine_xy, fine_heading=state.fine_heading, fine_valid=state.fine_valid,
                    xy=state.xy, heading=state.heading, valid=state.valid, map_tokens=state.map_tokens, plan=None,
                    nonfinite=jnp.asarray(nonfinite))
    check_finite(out, name)
    return out
