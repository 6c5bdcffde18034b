"""Planning with the world model (`gpd_world`): candidate plans scored on the futures a GPD imagines for each.

PDM's step (Dauner et al. 2023: IDM candidates scored on a forecast of the other agents) with the forecast made by
the generative world model, closed loop: for every candidate the model rolls the other agents out with the ego
following that candidate, K sampled futures, and each future is scored with the simulator's own nuPlan terms
(`gpd_jax.sim.scores.cls_scores`). Per replan (every model frame the policy is called):

1. **Candidates** f32[C, N, 3] (stored-rate poses from the next stored frame on, N = the model's future frames x
   stride, scene frame): IDM along the route (`gpd_jax.sim.agents.idm_along_route`, leaders the current agents at
   constant velocity) at the target speeds `speeds`; IDM along the route shifted sideways by +-`nudges_m` and, where
   the map has a lane there in the same direction, by +-`lane_width_m` (the neighbouring lanes), each at
   `side_speeds`; a shifted route blends from the ego's own offset to the target offset over max(`shift_min_m`,
   `shift_time_s` x speed) metres (smoothstep). The IDM candidates start at the ego's acceleration and change it
   by at most `max_jerk` a second, braking at most `max_decel`; one more candidate brakes as IDM does (the
   emergency stop). With a planning-head model, the head's own plan is one more candidate (`gpd_head_policy`, its
   own backbone and KV cache); with `hold`, so is the plan chosen at the previous replan, moved on one model frame.
2. **Futures** of the other agents over `horizon` model frames, by the scorer:
   * ``gpd``: the world model (its own KV cache of the simulated frames, in the policy state) appends, for every
     candidate and each of K = `samples` keys, the frames with the ego on the candidate, the lanes encoded around
     it, the agents drawn from its prediction at `temperature` (`gpd_jax.sim.core.predicted_agents`, as the
     simulator's GPD agents but sampled), the stored frames in between Hermite curves as in the simulator. One
     compiled computation: vmap over candidates x K of a `lax.scan` over the horizon. The K keys are shared by the
     candidates (common random numbers). Frames past the model's last frame go on at constant velocity;
   * ``cv``: every agent at constant velocity from now (PDM's forecast; K = 1);
   * ``log``: the log's own future (an oracle; exact for log-replay agents; K = 1).
3. **Scores** of each (candidate, future) over the stored frames from now to the horizon, with nuPlan's terms
   (`cls_scores`): multipliers at-fault collisions x drivable area x driving direction, times the weighted mean of
   progress (5; along the route, relative to the best candidate that passes the multipliers, PDM's way; 1 when no
   candidate makes `min_progress_m`), time to collision (5) and comfort (2). Reduced over the K futures by `reduce`
   (``mean``, the default, chosen on dev scenes where the worst case cost comfort and points; ``min``: the worst
   case). The previous replan's plan gains `hysteresis` (fewer switches: the ego's executed path stays one plan's
   unless another is better by more, or the held one becomes unsafe).
4. **The plan** is the best candidate's stored-rate poses (the tracker follows them; its open-loop plan is the same
   candidate at the model's frames from the current frame).

    policy = world_planner_policy(gpd_jax.load_model("gpd_sampling"), head=gpd_jax.load_model("gpd_planner"),
                                  options=WorldPlannerOptions(samples=4))
    out = sim.run(model, sims, policy, key, agents="idm")
"""

from __future__ import annotations

import dataclasses
import math

import flax.struct
import jax
import jax.numpy as jnp

from gpd_jax.checkpoint import Model
from gpd_jax.decoding import DecodeState, advance, prefill
from gpd_jax.geometry import RoadGeometry, lane_direction, pose_on_path, project_on_path
from gpd_jax.options import Sampling
from gpd_jax.scene import wrap_angle
from gpd_jax.sim.agents import idm_along_route
from gpd_jax.sim.core import Observation, Policy, SimError, _lanes, _parts, append_frame, predicted_agents
from gpd_jax.sim.policies import gpd_head_policy, observed_frames
from gpd_jax.sim.scores import CLS_WEIGHTS, cls_scores, road_queries
from gpd_jax.sim.tracker import extend, plan_path
from gpd_jax.spec import ModelSpec

SCORERS = ("gpd", "cv", "log")   # the agents' futures: the world model's samples, constant velocity, the log (oracle)
REDUCTIONS = ("min", "mean")


@dataclasses.dataclass(frozen=True)
class WorldPlannerOptions:
    """How `gpd_world` plans (static; hashable). See the module docstring.

    scorer: the agents' futures (`SCORERS`); samples: K futures per candidate (``gpd`` only); temperature: the
    sampling temperature (0: the world model's regressed future); horizon: model frames imagined (PDM: 4 s);
    reduce: over the K futures (`REDUCTIONS`); speeds: IDM target speeds along the route (m/s); side_speeds: the
    same for the shifted routes; nudges_m: sideways shifts within the lane (each + and -); lane_width_m: the
    neighbouring lanes' offset (0: none); shift_time_s, shift_min_m: how long a shift takes; min_progress_m: below
    this best progress every candidate's progress scores 1; hysteresis: the previous choice's bonus; use_head: the
    head's plan as a candidate (when a head model is given); max_jerk: m/s^3, the IDM candidates' acceleration
    starts at the ego's and changes by at most this per second (0: IDM's acceleration as it is); max_decel: m/s^2,
    the IDM candidates brake at most this hard, and one more candidate brakes as IDM does (its lowest speed,
    unbounded, no jerk limit: the emergency stop; 0: no bound, no such candidate); hold: the previous
    replan's chosen plan, moved on one model frame, is one more candidate and the previous choice is that plan (the
    hysteresis bonus goes to it; without, to the candidate of the same index).
    """

    scorer: str = "gpd"
    samples: int = 4
    temperature: float = 0.5
    horizon: int = 4
    reduce: str = "mean"
    speeds: tuple = (1.0, 3.0, 5.0, 7.0, 9.0, 11.0, 13.89)
    side_speeds: tuple = (3.0, 7.0, 11.0)
    nudges_m: tuple = (1.0,)
    lane_width_m: float = 3.2
    shift_time_s: float = 3.0
    shift_min_m: float = 15.0
    min_progress_m: float = 5.0
    hysteresis: float = 0.05
    use_head: bool = True
    max_jerk: float = 2.0
    max_decel: float = 3.0
    hold: bool = True

    def __post_init__(self):
        if self.scorer not in SCORERS:
            raise SimError(f"world planner: scorer {self.scorer!r} is not one of {', '.join(SCORERS)}")
        if self.reduce not in REDUCTIONS:
            raise SimError(f"world planner: reduce {self.reduce!r} is not one of {', '.join(REDUCTIONS)}")
        for name in ("samples", "horizon"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise SimError(f"world planner: {name} must be an integer >= 1, got {v!r}")
        if not self.speeds:
            raise SimError("world planner: speeds: at least one IDM target speed")
        for name in ("temperature", "lane_width_m", "shift_time_s", "shift_min_m", "min_progress_m", "hysteresis",
                     "max_jerk", "max_decel"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise SimError(f"world planner: {name} must be a number >= 0, got {v!r}")
        object.__setattr__(self, "speeds", tuple(float(v) for v in self.speeds))
        object.__setattr__(self, "side_speeds", tuple(float(v) for v in self.side_speeds))
        object.__setattr__(self, "nudges_m", tuple(float(v) for v in self.nudges_m))

    @property
    def futures(self) -> int:
        """Futures per candidate: K for the world model, one for the deterministic scorers."""
        return self.samples if self.scorer == "gpd" else 1

    @property
    def offsets(self) -> tuple[float, ...]:
        """The shifted routes' target offsets (m, + to the left): nudges, then the neighbouring lanes."""
        out = [s * d for d in self.nudges_m if d > 0 for s in (1.0, -1.0)]
        if self.lane_width_m > 0:
            out += [self.lane_width_m, -self.lane_width_m]
        return tuple(out)

    def num_candidates(self, with_head: bool) -> int:
        return (len(self.speeds) + len(self.offsets) * len(self.side_speeds) + int(self.max_decel > 0)
                + int(with_head) + int(self.hold))


@flax.struct.dataclass
class Candidates:
    """Candidate plans of one replan: poses f32[C, N, 3] (stored-rate, from the next stored frame on, scene frame),
    valid bool[C] (a neighbouring lane the map does not have is not a candidate)."""

    poses: jax.Array
    valid: jax.Array


@flax.struct.dataclass
class Futures:
    """The other agents' futures per candidate and sample at the stored rate from now (frame 0) to the horizon:
    xy f32[C, K, F, A, 2], heading f32[C, K, F, A], valid bool[C, K, F, A] (slot 0, the ego, included)."""

    xy: jax.Array
    heading: jax.Array
    valid: jax.Array


@flax.struct.dataclass
class WorldState:
    """The world planner's state between replans: decode, the world model's KV cache of the simulated frames (None
    for the cv and log scorers); head, the planning head's policy state (() without one); prev i32[], the candidate
    chosen last (-1 before the first); plan f32[N, 3], the plan chosen last (stored-rate poses from the stored frame
    after that replan on; zeros before the first)."""

    decode: DecodeState | None
    head: object
    prev: jax.Array
    plan: jax.Array


# ------------------------------------------------------------------------------------------------ candidates
def shifted_route(route_xy, route_heading, route_s, s0, d0, d1, ramp_m):
    """The route f32[R, 2] (headings f32[R], arc f32[R]) moved sideways (+ left) from offset `d0` at arc `s0` to `d1`
    over `ramp_m` metres (smoothstep), `d0` before: (xy f32[R, 2], heading f32[R], arc f32[R])."""
    u = jnp.clip((route_s - s0) / ramp_m, 0.0, 1.0)
    d = d0 + (d1 - d0) * u * u * (3.0 - 2.0 * u)
    slope = (d1 - d0) * 6.0 * u * (1.0 - u) / ramp_m
    normal = jnp.stack([-jnp.sin(route_heading), jnp.cos(route_heading)], -1)
    xy = route_xy + d[:, None] * normal
    heading = wrap_angle(route_heading + jnp.arctan(slope))
    seg = jnp.linalg.norm(xy[1:] - xy[:-1], axis=-1)
    return xy, heading, jnp.concatenate([jnp.zeros(1, xy.dtype), jnp.cumsum(seg)])


def _lane_there(road, xy, heading, s, s_from, s_last, tol_m: float = 1.0, max_angle: float = 0.5):
    """Whether a directed lane runs along a shifted route (xy f32[R, 2], heading f32[R], arc f32[R]) at 0, 10 and
    20 m past `s_from` (clipped to `s_last`): bool[]."""
    q = jnp.minimum(s_from + jnp.array([0.0, 10.0, 20.0]), s_last)
    qxy, qh = jax.vmap(lambda a: pose_on_path(xy, heading, s, a))(q)
    lh, dist = lane_direction(road, qxy)
    return jnp.all((dist < tol_m) & (jnp.abs(wrap_angle(lh - qh)) < max_angle))


def candidate_plans(obs: Observation, spec: ModelSpec, options: WorldPlannerOptions, accel0=0.0) -> Candidates:
    """The IDM candidates of one observation (module docstring), without the head's and the held plan:
    Candidates [C', ...]. accel0 f32[]: the ego's acceleration now (m/s^2; read with `options.max_jerk` > 0)."""
    n, dt = spec.num_future * spec.frame_stride, spec.stored_period_s
    rxy, rh, rs = obs.route_xy, obs.route_heading, obs.route_s
    jerk = options.max_jerk if options.max_jerk > 0 else None
    decel = options.max_decel if options.max_decel > 0 else None
    idm = lambda xy, h, s, speeds, **kw: idm_along_route(xy, h, s, obs.ego_pose, obs.cur_xy, obs.cur_velocity,
                                                         obs.cur_valid, obs.size, n, dt,
                                                         jnp.asarray(speeds, jnp.float32),
                                                         **({"accel0": accel0, "max_jerk": jerk, "max_decel": decel}
                                                            | kw))
    arc, _, tangent = project_on_path(rxy, rs, obs.ego_pose[None, :2])
    foot, _ = pose_on_path(rxy, rh, rs, arc[0])
    d0 = tangent[0, 0] * (obs.ego_pose[1] - foot[1]) - tangent[0, 1] * (obs.ego_pose[0] - foot[0])
    speed = jnp.linalg.norm(obs.ego_velocity)
    ramp = jnp.maximum(options.shift_min_m, options.shift_time_s * speed)
    targets = jnp.asarray((0.0,) + options.offsets, jnp.float32)
    routes = jax.vmap(lambda d1: shifted_route(rxy, rh, rs, arc[0], d0, d1, ramp))(targets)     # [1 + O, R, ...]
    centre = idm(*(r[0] for r in routes), options.speeds)                                      # [S0, N, 3]
    poses, valid = [centre], [jnp.ones(len(options.speeds), bool)]
    if options.offsets and options.side_speeds:
        side = jax.vmap(lambda xy, h, s: idm(xy, h, s, options.side_speeds))(*(r[1:] for r in routes))
        poses.append(side.reshape((-1,) + side.shape[2:]))
        nudges = len(options.offsets) - (2 if options.lane_width_m > 0 else 0)
        there = jnp.ones(nudges, bool)
        if options.lane_width_m > 0:
            lanes = jax.vmap(lambda xy, h, s: _lane_there(obs.road, xy, h, s, arc[0] + ramp, rs[-2]))(
                *(r[1 + nudges:] for r in routes))
            there = jnp.concatenate([there, lanes])
        valid.append(jnp.repeat(there, len(options.side_speeds)))
    if decel is not None:                                 # the emergency stop: IDM's own braking
        poses.append(idm(*(r[0] for r in routes), options.speeds[:1], max_jerk=None, max_decel=None))
        valid.append(jnp.ones(1, bool))
    return Candidates(poses=jnp.concatenate(poses, 0), valid=jnp.concatenate(valid, 0))


def held_plan(plan: jax.Array, spec: ModelSpec) -> jax.Array:
    """The plan chosen at the previous replan (stored-rate poses f32[N, 3] from the stored frame after it) moved on
    one model frame: its poses from the stored frame after now, continued at its last velocity to N poses."""
    s = spec.frame_stride
    return extend(plan[s:], plan[s - 1], plan.shape[0])


def ego_accel(obs: Observation, spec: ModelSpec, prev_plan: jax.Array, has_plan: jax.Array) -> jax.Array:
    """The ego's longitudinal acceleration now (m/s^2, f32[]): the previous plan's at this frame where there is one
    (the tracker follows it, its acceleration fed forward), else the change of speed over the last model frame."""
    s, dt = spec.frame_stride, spec.stored_period_s
    prev_t = jnp.maximum(obs.t - 1, 0)
    hist = (jnp.linalg.norm(obs.velocity[obs.t, 0]) - jnp.linalg.norm(obs.velocity[prev_t, 0])) / spec.frame_period_s
    hist = jnp.where(obs.t > 0, hist, 0.0)
    if s < 2:
        return hist
    pts = prev_plan[s - 2: s + 1, :2]                                # the stored frames before, at and after now
    v = jnp.linalg.norm(pts[1:] - pts[:-1], axis=-1) / dt
    return jnp.where(has_plan, (v[1] - v[0]) / dt, hist)


# ------------------------------------------------------------------------------------------------ futures
def _constant_velocity(xy, heading, valid, velocity, num_steps: int, dt: float):
    """Slots f32[A, 2] / f32[A] / bool[A] moved at `velocity` f32[A, 2] for `num_steps` steps: [num_steps, A, ...]."""
    k = jnp.arange(1, num_steps + 1, dtype=xy.dtype)[:, None, None] * dt
    return (xy[None] + k * velocity[None], jnp.broadcast_to(heading, (num_steps,) + heading.shape),
            jnp.broadcast_to(valid, (num_steps,) + valid.shape))


def _with_now(obs: Observation, xy, heading, valid):
    """The current frame put before future stored frames [F, A, ...] -> [F + 1, A, ...]."""
    cat = lambda a, b: jnp.concatenate([a[None], b], 0)
    return cat(obs.cur_xy, xy), cat(obs.cur_heading, heading), cat(obs.cur_valid, valid)


def cv_futures(obs: Observation, spec: ModelSpec, options: WorldPlannerOptions, num_candidates: int) -> Futures:
    """Every agent at constant velocity from now (PDM's forecast), the same for every candidate: Futures [C, 1]."""
    n = options.horizon * spec.frame_stride
    xy, h, v = _with_now(obs, *_constant_velocity(obs.cur_xy, obs.cur_heading, obs.cur_valid, obs.cur_velocity, n,
                                                  spec.stored_period_s))
    tile = lambda a: jnp.broadcast_to(a, (num_candidates, 1) + a.shape)
    return Futures(xy=tile(xy), heading=tile(h), valid=tile(v))


def log_futures(obs: Observation, spec: ModelSpec, options: WorldPlannerOptions, num_candidates: int) -> Futures:
    """The log's own future of every slot from now (an oracle), the same for every candidate: Futures [C, 1]; past
    the log's end at constant velocity."""
    if obs.log_xy is None:
        raise SimError("the world planner's log scorer reads the log's future (Observation.log_xy): run it in the "
                       "simulator (sim.run)")
    n, s, dt = options.horizon * spec.frame_stride, spec.frame_stride, spec.stored_period_s
    lx, lh, lv = obs.log_xy, obs.log_heading, obs.log_valid
    last_vel = jnp.where((lv[-1] & lv[-2])[:, None], (lx[-1] - lx[-2]) / dt, 0.0)
    ex, eh, ev = _constant_velocity(lx[-1], lh[-1], lv[-1], last_vel, n, dt)
    cat = lambda a, b: jnp.concatenate([a, b], 0)
    now = s * obs.t
    take = lambda a: jax.lax.dynamic_slice_in_dim(a, now, n + 1, axis=0)
    xy, h, v = take(cat(lx, ex)), take(cat(lh, eh)), take(cat(lv, ev))
    tile = lambda a: jnp.broadcast_to(a, (num_candidates, 1) + a.shape)
    return Futures(xy=tile(xy), heading=tile(h), valid=tile(v))


@flax.struct.dataclass
class _Imagined:
    """The scan carry of one imagined future: the world model's decode state and the frame now (slots f32[A, ...])."""

    decode: DecodeState
    xy: jax.Array
    heading: jax.Array
    valid: jax.Array
    velocity: jax.Array


def gpd_futures(parts, decode: DecodeState, obs: Observation, spec: ModelSpec, options: WorldPlannerOptions,
                poses: jax.Array, key: jax.Array) -> Futures:
    """The world model's K sampled futures of the other agents for every candidate (poses f32[C, N, 3]), the ego
    placed on the candidate: Futures [C, K]. `decode`: the world model's state after the current frame (its
    prediction of the next); `parts`: the world model's pieces (`gpd_jax.sim.core._parts`)."""
    s, dt, period = spec.frame_stride, spec.stored_period_s, spec.frame_period_s
    hz, last_frame = options.horizon, spec.num_frames - 1
    sampling = Sampling(temperature=options.temperature)
    keys = jax.random.split(key, options.samples)
    knots = jnp.arange(1, hz + 1) * s - 1                                                   # the model frames' poses

    def ego_at(path):                                                                        # [H, 3], [H, 2]
        prev = jnp.concatenate([obs.ego_pose[None], path[:-1]], 0)
        return path[knots], (path[knots, :2] - prev[knots, :2]) / dt

    def one_candidate(path):
        epose, evel = ego_at(path)
        if parts.encoder is not None:                    # the map around the ego depends on the candidate alone
            tokens = jax.vmap(lambda p: parts.encoder(obs.polylines, obs.polyline_valid, p))(epose)
        else:
            tokens = jnp.zeros((hz,) + obs.cur_map_tokens.shape, obs.cur_map_tokens.dtype)

        def one_future(k):
            def step(c: _Imagined, j):
                t1 = obs.t + 1 + j
                nxt, (fxy, fh, fv) = predicted_agents(c.decode.pred, c.xy, c.heading, c.valid, c.velocity, period,
                                                      s, jax.random.fold_in(k, j), sampling)
                cvx, cvh, cvv = _constant_velocity(c.xy, c.heading, c.valid, c.velocity, s, dt)
                inside = t1 <= last_frame                  # past the model's last frame: constant velocity
                pick = lambda a, b: jnp.where(inside, a, b)
                fxy, fh, fv = pick(fxy, cvx), pick(fh, cvh), pick(fv, cvv)
                nxt = nxt.replace(xy=pick(nxt.xy, cvx[-1]), heading=pick(nxt.heading, cvh[-1]),
                                  valid=pick(nxt.valid, cvv[-1]), velocity=pick(nxt.velocity, c.velocity),
                                  map_tokens=obs.cur_map_tokens)
                frame, dec = append_frame(parts, c.decode, nxt, epose[j], evel[j], jnp.minimum(t1, last_frame),
                                          obs.polylines, obs.polyline_valid, tokens[j])
                return (_Imagined(decode=dec, xy=frame.xy, heading=frame.heading, valid=frame.valid,
                                  velocity=frame.velocity), (fxy, fh, fv))

            start = _Imagined(decode=decode, xy=obs.cur_xy, heading=obs.cur_heading, valid=obs.cur_valid,
                              velocity=obs.cur_velocity)
            _, (fxy, fh, fv) = jax.lax.scan(step, start, jnp.arange(hz))
            flat = lambda a: a.reshape((hz * s,) + a.shape[2:])
            fxy, fh, fv = flat(fxy), flat(fh), flat(fv)                  # the ego on the candidate, as the simulator
            n = hz * s
            return _with_now(obs, fxy.at[:, 0].set(path[:n, :2]), fh.at[:, 0].set(path[:n, 2]), fv.at[:, 0].set(True))

        return jax.vmap(one_future)(keys)

    xy, h, v = jax.vmap(one_candidate)(poses)
    return Futures(xy=xy, heading=h, valid=v)


# ------------------------------------------------------------------------------------------------ scores
LOCAL_ROWS = {"polygons": 24, "edges": 24, "lanes": 32}   # rows of the road geometry kept around the ego


def local_road(road: RoadGeometry, centre: jax.Array) -> RoadGeometry:
    """The rows of `road` (drivable-area rings, edge polylines, lanes) with a point nearest `centre` f32[2], at most
    `LOCAL_ROWS` of each (all where fewer): a candidate's 4 s stay within them, so its road queries are the same
    at a fraction of the cost."""
    def nearest(points, valid, k):
        if points.shape[0] <= k:
            return jnp.arange(points.shape[0])
        d = jnp.min(jnp.where(valid, jnp.linalg.norm(points - centre, axis=-1), jnp.inf), axis=-1)
        return jax.lax.top_k(-d, k)[1]

    g = nearest(road.polygons, road.polygon_valid, LOCAL_ROWS["polygons"])
    e = nearest(road.edges, road.edge_valid, LOCAL_ROWS["edges"])
    ln = nearest(road.lanes, road.lane_valid, LOCAL_ROWS["lanes"])
    return road.replace(polygons=road.polygons[g], polygon_valid=road.polygon_valid[g],
                        polygon_kind=road.polygon_kind[g], edges=road.edges[e], edge_valid=road.edge_valid[e],
                        lanes=road.lanes[ln], lane_valid=road.lane_valid[ln])


def candidate_scores(obs: Observation, spec: ModelSpec, options: WorldPlannerOptions, cands: Candidates,
                     futures: Futures) -> dict[str, jax.Array]:
    """Each candidate's score on its futures (module docstring, step 3): {"score": f32[C] (reduced over K; -1 for
    an invalid candidate), "per_future": f32[C, K], and the terms f32[C, K]: "no_ego_at_fault_collisions",
    "drivable_area_compliance", "driving_direction_compliance", "time_to_collision_within_bound",
    "ego_is_comfortable", "ego_progress_m"}. The ego's frames are the candidate's from now to the horizon."""
    if obs.road is None:
        raise SimError("the world planner scores its candidates on the road geometry (Observation.road); the "
                       "scenes have none")
    n, dt = options.horizon * spec.frame_stride, spec.stored_period_s
    size = obs.size
    ego = jnp.concatenate([jnp.broadcast_to(obs.ego_pose, (cands.poses.shape[0], 1, 3)), cands.poses[:, :n]], 1)

    rqs = road_queries(local_road(obs.road, obs.ego_pose[:2]), ego[..., :2], ego[..., 2], size[0])   # all at once

    def per_candidate(e, rq, fxy, fh, fv):
        return jax.vmap(lambda x, h, v: cls_scores(e[:, :2], e[:, 2], size[0], x[:, 1:], h[:, 1:], v[:, 1:], size[1:],
                                                   obs.route_xy, obs.route_s, jnp.float32(0.0), dt, rq))(fxy, fh, fv)

    t = jax.vmap(per_candidate)(ego, rqs, futures.xy, futures.heading, futures.valid)        # {term: [C, K]}
    mult = (t["no_ego_at_fault_collisions"] * t["drivable_area_compliance"] * t["driving_direction_compliance"])
    progress = t["ego_progress_m"]
    passes = cands.valid & (jnp.mean(mult, -1) > 0)
    best = jnp.max(jnp.where(passes[:, None], progress, 0.0))
    rel = jnp.where(best > options.min_progress_m, jnp.clip(progress / jnp.maximum(best, 1e-3), 0.0, 1.0), 1.0)
    w = CLS_WEIGHTS
    weighted = (w["ego_progress_along_expert_route"] * rel + w["time_to_collision_within_bound"]
                * t["time_to_collision_within_bound"] + w["ego_is_comfortable"] * t["ego_is_comfortable"])
    per_future = mult * weighted / (w["ego_progress_along_expert_route"] + w["time_to_collision_within_bound"]
                                    + w["ego_is_comfortable"])
    reduced = jnp.min(per_future, -1) if options.reduce == "min" else jnp.mean(per_future, -1)
    keep = ("no_ego_at_fault_collisions", "drivable_area_compliance", "driving_direction_compliance",
            "time_to_collision_within_bound", "ego_is_comfortable", "ego_progress_m")
    return {"score": jnp.where(cands.valid, reduced, -1.0), "per_future": per_future, **{k: t[k] for k in keep}}


# ------------------------------------------------------------------------------------------------ the policy
def world_planner_policy(world: Model, head: Model | None = None,
                         options: WorldPlannerOptions = WorldPlannerOptions(), name: str = "gpd_world") -> Policy:
    """The world planner as a simulator policy (module docstring). `world`: the model that imagines the futures
    (``gpd_sampling`` for sampled futures; any GPD of the simulator's frames and slots: its spec is the
    simulator's; for the cv and log scorers only its spec is read); `head`: a planning-head model whose plan is a
    candidate (None: none). Its state carries the world model's KV cache (and the head's)."""
    spec = world.spec
    frames = lambda sp: (sp.num_frames, sp.num_history, sp.frame_stride, sp.num_agents)
    if head is not None and frames(head.spec) != frames(spec):
        raise SimError(f"world planner: the head model reads other frames than the world model (frames, history, "
                       f"stride, slots {frames(head.spec)} against {frames(spec)})")
    use_head = head is not None and options.use_head
    head_policy = gpd_head_policy(head, f"{name}_head") if use_head else None
    with_model = options.scorer == "gpd"
    if with_model and world.tokenizer is None:
        raise SimError("world planner: the world model has no map tokenizer (it encodes the lanes around each "
                       "candidate's ego)")
    h, t_total, s, period = spec.num_history, spec.num_frames, spec.frame_stride, spec.frame_period_s
    params = {"world": world.params if with_model else None,
              "tok": world.tokenizer.params if with_model else None,
              "head": head.params if use_head else None}

    def world_parts(p):
        return _parts(world, p["world"], world.rest, p["tok"], with_model=True)

    def frame_now(module, obs):
        f = observed_frames(module, obs)
        return jax.tree.map(lambda x: jax.lax.dynamic_index_in_dim(x, obs.t, 0, keepdims=False), f)

    def choose(p, obs, decode, head_poses, prev, prev_plan, key):
        has_plan = prev >= 0
        cands = candidate_plans(obs, spec, options, ego_accel(obs, spec, prev_plan, has_plan))
        extra, bonus = [], jnp.zeros(cands.valid.shape[0])
        if head_poses is not None:
            extra.append((plan_path(obs.ego_pose, obs.ego_velocity, head_poses, period, s), True, 0.0))
        if options.hold:
            extra.append((held_plan(prev_plan, spec), has_plan, options.hysteresis))
        for poses, ok, b in extra:
            cands = Candidates(poses=jnp.concatenate([cands.poses, poses[None]], 0),
                               valid=jnp.concatenate([cands.valid, jnp.asarray(ok, bool)[None]]))
            bonus = jnp.concatenate([bonus, jnp.full(1, b)])
        c = cands.poses.shape[0]
        if not options.hold:                             # the previous choice: the candidate of the same index
            bonus = bonus + jnp.where(jnp.arange(c) == prev, options.hysteresis, 0.0)
        if options.scorer == "gpd":
            futures = gpd_futures(world_parts(p), decode, obs, spec, options, cands.poses, key)
        elif options.scorer == "cv":
            futures = cv_futures(obs, spec, options, c)
        else:
            futures = log_futures(obs, spec, options, c)
        sc = candidate_scores(obs, spec, options, cands, futures)
        pick = jnp.argmax(sc["score"] + bonus)
        return pick, cands.poses[pick]

    def init(p, obs):
        decode = None
        if with_model:
            parts = world_parts(p)
            decode = prefill(parts.module, observed_frames(parts.module, obs), h - 1, t_total,
                             _lanes(parts, obs.polylines, obs.polyline_valid, h - 1))
        hstate = head_policy.init(p["head"], obs) if use_head else ()
        n = spec.num_future * s
        return WorldState(decode=decode, head=hstate, prev=jnp.asarray(-1, jnp.int32),
                          plan=jnp.zeros((n, 3), jnp.float32))

    def select(p, obs, state: WorldState, key):
        k_head, k_world = jax.random.split(key)
        decode = state.decode
        if with_model:
            parts = world_parts(p)
            decode = advance(parts.module, decode, frame_now(parts.module, obs), obs.t,
                             _lanes(parts, obs.polylines, obs.polyline_valid, 1))
        hstate, head_poses = state.head, None
        if use_head:
            plan, hstate = head_policy.select(p["head"], obs, state.head, k_head)
            head_poses = plan.poses
        pick, poses = choose(p, obs, decode, head_poses, state.prev, state.plan, k_world)
        return poses, WorldState(decode=decode, head=hstate, prev=pick.astype(jnp.int32), plan=poses)

    def plan(p, obs, key):
        k_head, k_world = jax.random.split(key)
        decode = None
        if with_model:
            parts = world_parts(p)
            decode = prefill(parts.module, observed_frames(parts.module, obs), h, t_total,
                             _lanes(parts, obs.polylines, obs.polyline_valid, h))
        head_poses = head_policy.plan(p["head"], obs, k_head) if use_head else None
        _, poses = choose(p, obs, decode, head_poses, jnp.asarray(-1), jnp.zeros((spec.num_future * s, 3)), k_world)
        return poses[s - 1:: s][: spec.num_future]

    return Policy(name=name, select=select, init=init, plan=plan, needs_map=with_model or use_head, params=params)


WORLD_PLANNERS = {"gpd_world": "gpd", "gpd_world_cv": "cv", "gpd_world_log": "log"}   # planner name: its scorer


def make_world_policy(name: str, world: Model, head: Model | None = None,
                      options: WorldPlannerOptions = WorldPlannerOptions()) -> Policy:
    """A world planner by name (`WORLD_PLANNERS`: ``gpd_world`` scores on the world model's sampled futures,
    ``gpd_world_cv`` on constant velocity (PDM's way), ``gpd_world_log`` on the log's future (an oracle)): the same
    candidates, `options` with the name's scorer."""
    if name not in WORLD_PLANNERS:
        raise SimError(f"unknown world planner {name!r}; known: {', '.join(WORLD_PLANNERS)}")
    return world_planner_policy(world, head, dataclasses.replace(options, scorer=WORLD_PLANNERS[name]), name)
