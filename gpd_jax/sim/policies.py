"""The policies shipped with the simulator (each a `Policy` of pure functions, built once per model so a batch
shape compiles once):

* ``log``: the expert: the logged ego at the stored rate (its open-loop plan is the logged future);
* ``cv``: constant velocity and heading from the ego's current velocity;
* ``idm``: IDM lane following along the logged ego's route (the route has no timing: nuPlan gives its planners
  the route, not the expert's speeds), target speed `sim.agents.ROUTE_SPEED` (the stores carry no speed limits:
  13.89 m/s, SUMO's default lane speed), leaders = the agents of the current frame projected on the route and
  moved at constant velocity through the step;
* ``gpd``: the GPD zero-shot: the model's own prediction of the ego's next frame (pose and velocity), as in the
  motion-planning task (no open-loop plan of its own: its open-loop score reads the run with GPD agents, the
  model's imagined future);
* ``gpd_head``: a fine-tuned planning head (`gpd_jax.model.planning_head`) on the ego token of the current frame,
  run by its own backbone (a KV cache in the policy state): its 8 s plan, a `Plan` the tracker follows (without a
  tracker, the ego is placed on the plan's first second); a head that reads the route gets it from the
  observation (`route_xy`), and a head with `plan_head.candidates = "idm"` chooses among IDM's plans at the target
  speeds `plan_head.idm_speeds` (`idm_route_plan` from the same observation); its open-loop plan is the same
  trajectory at the current frame; ``gpd_head_scratch`` is the same head trained without pre-training (the
  paper's ablation).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import nnx

from gpd_jax.checkpoint import Model
from gpd_jax.decoding import Frame, advance, prefill
from gpd_jax.geometry import route_ahead
from gpd_jax.sim.agents import ROUTE_SPEED, idm_along_route, idm_route_plan
from gpd_jax.sim.core import Observation, Policy, SimError
from gpd_jax.sim.tracker import Plan, extend
from gpd_jax.spec import ModelSpec

PLANNERS = ("log", "cv", "idm", "gpd", "gpd_head", "gpd_head_scratch")
HEAD_PLANNERS = ("gpd_head", "gpd_head_scratch")  # the planning head fine-tuned from GPD / trained from scratch


def _slice_fine(obs: Observation, start, count: int):
    """`count` logged ego poses from stored frame `start` on; past the log's end it goes on straight at its last
    velocity (the tracker looks ahead of the last frame too)."""
    log = obs.log_ego
    return jax.lax.dynamic_slice_in_dim(extend(log, log[0], log.shape[0] + count), start, count, axis=0)


def expert_policy(spec: ModelSpec) -> Policy:
    s, h = spec.frame_stride, spec.num_history

    def select(params, obs, state, key):  # two model frames of the log: the tracker looks a second ahead
        return _slice_fine(obs, s * obs.t + 1, 2 * s), state

    def plan(params, obs, key):
        return obs.log_ego[s * h:: s][: spec.num_future]

    return Policy(name="log", select=select, plan=plan)


def constant_velocity_policy(spec: ModelSpec) -> Policy:
    period = spec.frame_period_s

    def select(params, obs, state, key):
        nxt = obs.ego_pose[:2] + obs.ego_velocity * period
        return jnp.concatenate([nxt, obs.ego_pose[2:], obs.ego_velocity]), state

    def plan(params, obs, key):
        k = jnp.arange(1, spec.num_future + 1, dtype=jnp.float32)[:, None]
        xy = obs.ego_pose[:2] + k * period * obs.ego_velocity
        return jnp.concatenate([xy, jnp.broadcast_to(obs.ego_pose[2], (spec.num_future, 1))], -1)

    return Policy(name="cv", select=select, plan=plan)


def idm_policy(spec: ModelSpec) -> Policy:
    s, dt = spec.frame_stride, spec.stored_period_s

    def select(p, obs, state, key):  # two model frames: the tracker looks a second ahead
        return idm_along_route(obs.route_xy, obs.route_heading, obs.route_s, obs.ego_pose, obs.cur_xy,
                               obs.cur_velocity, obs.cur_valid, obs.size, 2 * s, dt), state

    def plan(p, obs, key):
        return _idm_plan(obs, spec, spec.num_future)

    return Policy(name="idm", select=select, plan=plan)


def _idm_plan(obs: Observation, spec: ModelSpec, num_future: int, target_speed=ROUTE_SPEED) -> jax.Array:
    """IDM's plan along the observation's route at the next `num_future` model frames: f32[num_future, 3] (f32[C,
    num_future, 3] for C target speeds)."""
    return idm_route_plan(obs.route_xy, obs.route_heading, obs.route_s, obs.ego_pose, obs.cur_xy, obs.cur_velocity,
                          obs.cur_valid, obs.size, num_future, spec.frame_stride, spec.stored_period_s, target_speed)


def gpd_policy(spec: ModelSpec) -> Policy:
    def select(params, obs, state, key):
        return jnp.concatenate([obs.pred_pose, obs.pred_velocity]), state

    return Policy(name="gpd", select=select, needs_model=True)


def observed_frames(module, obs: Observation) -> Frame:
    """The simulated frames so far of an observation as a model's inputs (`Frame` [T, ...]; the velocities in the
    form the model reads), for a policy that runs a model of its own over them."""
    vel = module.input_velocity(obs.velocity)
    vel = jnp.zeros_like(obs.xy) if vel is None else vel
    return Frame(xy=obs.xy, heading=obs.heading, valid=obs.valid,
                 valid_logit=jnp.zeros(obs.valid.shape, jnp.float32), map_tokens=obs.map_tokens, velocity=vel)


def gpd_head_policy(head_model: Model, name: str = "gpd_head") -> Policy:
    """The fine-tuned planning head of `head_model` (a GPD whose config has a `plan_head` section) as a policy
    that carries its own backbone's KV cache in its policy state: each frame it appends what the simulator
    placed (ego, agents, the map encoded around the ego) to its cache, reads the ego token's output and plans. So
    it runs beside any world model and agent model (its backbone may be fine-tuned away from the world model's)."""
    from gpd_jax.model import plan_trajectory, to_ego_frame

    if "plan_head" not in head_model.config:
        raise SimError(f"gpd_head needs a model with the fine-tuned planning head (a config with a plan_head "
                       f"section); {head_model.path or 'the given model'} has none")
    graphdef, rest, spec = head_model.graphdef, head_model.rest, head_model.spec
    h, t_total = spec.num_history, spec.num_frames

    frames = observed_frames

    def route(module, obs):
        head = module.plan_head
        if not head.route_points:
            return None
        return route_ahead(obs.route_xy, obs.route_s, obs.ego_pose, head.route_points, head.route_spacing_m)

    def candidates(module, obs):
        if not module.plan_head.candidates:
            return None
        speeds = jnp.asarray(head_model.config.plan_head.idm_speeds, jnp.float32)
        idm = _idm_plan(obs, spec, module.plan_head.num_future, speeds)                  # [C, F, 3]
        return to_ego_frame(idm[..., :2], idm[..., 2], obs.ego_pose[None])

    def init(params, obs):
        module = nnx.merge(graphdef, params, rest)
        return prefill(module, frames(module, obs), h - 1, t_total)

    def select(params, obs, state, key):
        module = nnx.merge(graphdef, params, rest)
        f = frames(module, obs)
        cur = jax.tree.map(lambda x: jax.lax.dynamic_index_in_dim(x, obs.t, 0, keepdims=False), f)
        state = advance(module, state, cur, obs.t)
        plan = plan_trajectory(module, state.hidden, obs.ego_pose, route(module, obs), candidates(module, obs))
        return Plan(poses=plan[: spec.num_future]), state

    def plan(params, obs, key):
        module = nnx.merge(graphdef, params, rest)
        st = prefill(module, frames(module, obs), h, t_total)
        return plan_trajectory(module, st.hidden, obs.ego_pose, route(module, obs), candidates(module, obs))[
            : spec.num_future]

    return Policy(name=name, select=select, init=init, plan=plan, needs_map=True, params=head_model.params)


@functools.lru_cache(maxsize=32)
def _cached(name: str, spec: ModelSpec) -> Policy:
    return {"log": expert_policy, "cv": constant_velocity_policy, "idm": idm_policy, "gpd": gpd_policy}[name](spec)


_HEADS: dict[tuple[str, int], Policy] = {}


def make_policy(name: str, model: Model) -> Policy:
    """A shipped policy by name (`PLANNERS`), built once per model (so repeated runs reuse one compile); for
    ``gpd_head`` / ``gpd_head_scratch`` `model` is the model with the planning head."""
    if name not in PLANNERS:
        raise SimError(f"unknown planner {name!r}; known planners: {', '.join(PLANNERS)}")
    if name in HEAD_PLANNERS:
        key = (name, id(model))
        if key not in _HEADS:
            _HEADS[key] = gpd_head_policy(model, name)
        return _HEADS[key]
    return _cached(name, model.spec)
