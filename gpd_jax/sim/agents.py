"""IDM agents along their logged paths (nuPlan's reactive baseline), in JAX, at the stored rate.

Each agent keeps to the path it drove in the log (its logged positions from the current frame on, as a polyline
parametrised by arc length, extended 200 m straight on past its last logged point) and chooses only its speed,
by the Intelligent Driver Model

    a = a_max [1 - (v / v0)^delta - (s* / gap)^2],   s* = s0 + max(0, v T + v dv / (2 sqrt(a_max b)))

with nuPlan's IDM-agent constants (min gap s0 1 m, headway T 1.5 s, a_max 1 m/s^2, b 2 m/s^2, delta 4). nuPlan
takes the target speed v0 from the lane's speed limit; the stores carry none, so v0 is the agent's highest logged
speed (at least 0.5 m/s). The leader is the nearest box ahead on the path: another agent or the ego whose centre
lies within half the two widths of the path, ahead in arc length (its speed taken along the path); the gap is the
arc difference less half the two lengths. Because the stores carry no traffic lights, an agent also treats the
place where its logged self was standing still (logged speed < 0.5 m/s) as a stopped leader while the log stands
there, so it waits where the log waited (at lights and yields) and otherwise drives freely.

An agent enters when it first appears in the log (at its logged place and speed) and leaves when it reaches the
arc length at which the log lost it (never, when the log keeps it to the end of the window).
"""

from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp

from gpd_jax.geometry import pose_on_path, project_on_path

EXTENSION_M = 200.0
ROUTE_SPEED = 13.89  # m/s: the target speed of IDM along the ego's route (SUMO's default lane speed; no speed limits)


@flax.struct.dataclass(frozen=True)
class IDMParams:
    """nuPlan's IDM-agent constants (static)."""

    min_gap: float = flax.struct.field(pytree_node=False, default=1.0)
    headway: float = flax.struct.field(pytree_node=False, default=1.5)
    accel_max: float = flax.struct.field(pytree_node=False, default=1.0)
    decel_comfort: float = flax.struct.field(pytree_node=False, default=2.0)
    decel_max: float = flax.struct.field(pytree_node=False, default=9.0)
    exponent: float = flax.struct.field(pytree_node=False, default=4.0)
    stop_speed: float = flax.struct.field(pytree_node=False, default=0.5)


@flax.struct.dataclass
class Paths:
    """Every slot's logged path from the current stored frame on (slot 0: the logged ego's route).

    xy: f32[A, P, 2] points (P = future stored frames + 2: the current frame, the future, one extension point);
    heading: f32[A, P]; s: f32[A, P] arc length at each point (non-decreasing, 0 at the first);
    log_s: f32[A, P-1] arc length of the logged agent at each stored frame; log_speed: f32[A, P-1];
    spawn: i32[A] first stored frame (relative to the current one) where the log has the agent (P-1 if never);
    end_s: f32[A] arc length where the log lost it (+inf when it is kept to the end); v0: f32[A] target speed.
    """

    xy: jax.Array
    heading: jax.Array
    s: jax.Array
    log_s: jax.Array
    log_speed: jax.Array
    spawn: jax.Array
    end_s: jax.Array
    v0: jax.Array


@flax.struct.dataclass
class IDMState:
    """s f32[A] arc position, v f32[A] speed, active bool[A] entered (and not yet left the log's path)."""

    s: jax.Array
    v: jax.Array
    active: jax.Array


def make_paths(xy: jax.Array, heading: jax.Array, valid: jax.Array, speed: jax.Array) -> Paths:
    """Paths of the log from the current frame on: xy f32[F, A, 2], heading f32[F, A], valid bool[F, A], speed
    f32[F, A] (F stored frames, the current one first; unbatched)."""
    f = xy.shape[0]
    idx = jnp.arange(f)[:, None]
    last = jax.lax.cummax(jnp.where(valid, idx, -1), axis=0)                     # last valid frame <= k
    first = jnp.min(jnp.where(valid, idx, f), axis=0)                            # [A]
    src = jnp.where(last >= 0, last, jnp.minimum(first, f - 1)[None])            # forward, then backward fill
    take = lambda a: jnp.take_along_axis(a, src.reshape(src.shape + (1,) * (a.ndim - 2)), axis=0)
    pxy, ph = take(xy), take(heading)                                             # [F, A, 2], [F, A]
    ext = pxy[-1] + EXTENSION_M * jnp.stack([jnp.cos(ph[-1]), jnp.sin(ph[-1])], -1)
    pxy = jnp.concatenate([pxy, ext[None]], 0).transpose(1, 0, 2)                 # [A, P, 2]
    ph = jnp.concatenate([ph, ph[-1:]], 0).T                                      # [A, P]
    seg = jnp.linalg.norm(pxy[:, 1:] - pxy[:, :-1], axis=-1)
    s = jnp.concatenate([jnp.zeros_like(seg[:, :1]), jnp.cumsum(seg, axis=1)], 1)
    last_valid = jnp.max(jnp.where(valid, idx, -1), axis=0)                       # [A]
    end_s = jnp.where(last_valid >= f - 1, jnp.inf, jnp.take_along_axis(s, jnp.maximum(last_valid, 0)[:, None], 1)[:, 0])
    spd = jnp.where(valid, speed, 0.0)
    v0 = jnp.maximum(jnp.max(spd, axis=0), 0.5)
    return Paths(xy=pxy, heading=ph, s=s, log_s=s[:, :-1], log_speed=spd.T, spawn=first.astype(jnp.int32),
                 end_s=end_s, v0=v0)


def idm_accel(v, v0, gap, dv, p: IDMParams):
    """The IDM acceleration (clipped to [-decel_max, accel_max]); gap = +inf for a free road."""
    s_star = p.min_gap + jnp.maximum(0.0, v * p.headway + v * dv / (2 * jnp.sqrt(p.accel_max * p.decel_comfort)))
    inter = jnp.where(jnp.isfinite(gap), (s_star / jnp.maximum(gap, 0.1)) ** 2, 0.0)
    a = p.accel_max * (1 - (v / jnp.maximum(v0, 0.1)) ** p.exponent - inter)
    return jnp.clip(a, -p.decel_max, p.accel_max)


def lead_gaps(paths: Paths, state_s: jax.Array, size: jax.Array, others_xy: jax.Array, others_vel: jax.Array,
              others_valid: jax.Array, self_mask: jax.Array):
    """Gap (m) and closing speed to each slot's leader among `others` (slot j is never its own leader).

    paths for A slots, state_s f32[A], size f32[A, 2]; others_xy f32[B, 2], others_vel f32[B, 2], others_valid
    bool[B] (B = A: the same slots), self_mask bool[A, B] pairs to skip. -> (gap f32[A], lead speed f32[A]).
    """
    arc, lat, tan = jax.vmap(lambda pxy, ps: project_on_path(pxy, ps, others_xy))(paths.xy, paths.s)   # [A, B]
    width = 0.5 * (size[:, None, 1] + size[None, :, 1])
    ahead = arc > state_s[:, None]
    cand = others_valid[None] & ~self_mask & (lat < width) & ahead
    gap = arc - state_s[:, None] - 0.5 * (size[:, None, 0] + size[None, :, 0])
    gap = jnp.where(cand, gap, jnp.inf)
    j = jnp.argmin(gap, axis=1)
    g = jnp.take_along_axis(gap, j[:, None], 1)[:, 0]
    along = jnp.sum(others_vel[None] * tan, -1)                                                # [A, B]
    return g, jnp.take_along_axis(along, j[:, None], 1)[:, 0]


def idm_substep(paths: Paths, st: IDMState, k, size: jax.Array, others_xy, others_vel, others_valid, dt: float,
                p: IDMParams, slots: jax.Array) -> IDMState:
    """One stored-rate step to relative stored frame k (1-based from the current frame) of the slots `slots`
    bool[A] (the others are left as they are). Leaders are `others` at the previous stored frame."""
    a_n = paths.s.shape[0]
    spawn_now = slots & ~st.active & (paths.spawn == k)
    kk = jnp.clip(k, 0, paths.log_s.shape[1] - 1)
    s = jnp.where(spawn_now, paths.log_s[:, kk], st.s)
    v = jnp.where(spawn_now, paths.log_speed[:, kk], st.v)
    self_mask = jnp.eye(a_n, dtype=bool)
    gap, lead_v = lead_gaps(paths, st.s, size, others_xy, others_vel, others_valid, self_mask)
    # the log's own stops as stopped leaders (see the module docstring)
    km = jnp.clip(k - 1, 0, paths.log_s.shape[1] - 1)
    ghost = (paths.log_speed[:, km] < p.stop_speed) & (paths.log_s[:, km] >= st.s - 0.5)
    ghost_gap = jnp.where(ghost, paths.log_s[:, km] - st.s + p.min_gap, jnp.inf)
    use_ghost = ghost_gap < gap
    gap = jnp.where(use_ghost, ghost_gap, gap)
    lead_v = jnp.where(use_ghost, 0.0, lead_v)
    acc = idm_accel(st.v, paths.v0, gap, st.v - lead_v, p)
    v_new = jnp.maximum(st.v + acc * dt, 0.0)
    s_new = st.s + v_new * dt
    move = slots & st.active
    s = jnp.where(move, s_new, s)
    v = jnp.where(move, v_new, v)
    active = (st.active | spawn_now) & slots
    return IDMState(s=s, v=v, active=jnp.where(slots, active, st.active))


def idm_poses(paths: Paths, st: IDMState):
    """Poses of every slot at its arc: (xy f32[A, 2], heading f32[A], valid bool[A])."""
    xy, h = jax.vmap(pose_on_path)(paths.xy, paths.heading, paths.s, st.s)
    return xy, h, st.active & (st.s <= paths.end_s)


def idm_along_route(route_xy: jax.Array, route_heading: jax.Array, route_s: jax.Array, ego_pose: jax.Array,
                    cur_xy: jax.Array, cur_velocity: jax.Array, cur_valid: jax.Array, size: jax.Array,
                    num_steps: int, dt: float, target_speed=ROUTE_SPEED, p: IDMParams = IDMParams(),
                    accel0=0.0, max_jerk: float | None = None, max_decel: float | None = None) -> jax.Array:
    """The ego driven by IDM along a route for `num_steps` steps of `dt` seconds: f32[num_steps, 3] poses (scene
    frame). It starts at the ego's projection on the route at its current speed; its leaders are the other slots
    of the current frame whose box overlaps the route ahead, moved at constant velocity through the steps.
    With `max_jerk` (m/s^3) the acceleration starts at `accel0` f32[] (m/s^2, the ego's now) and moves towards
    IDM's by at most `max_jerk` x dt a step (a jerk-limited profile, continuous with the ego's motion); without,
    each step takes IDM's acceleration as it is. `max_decel` (m/s^2, > 0) bounds its braking (IDM's own bound is
    `p.decel_max`).

    route_xy f32[R, 2], route_heading f32[R], route_s f32[R]: the route (a path, `Paths`' slot 0); ego_pose f32[3];
    cur_xy f32[A, 2], cur_velocity f32[A, 2], cur_valid bool[A], size f32[A, 2]: the frame's slots, the ego at 0
    (its speed is |cur_velocity[0]|). target_speed f32[] or f32[C]: several target speeds drive C egos at once
    over one projection of the leaders per step -> f32[C, num_steps, 3]."""
    speeds = jnp.atleast_1d(jnp.asarray(target_speed, jnp.float32))                   # [C]
    s0, _, _ = project_on_path(route_xy, route_s, ego_pose[None, :2])
    length, width = size[0, 0], size[0, 1]
    others = cur_valid.at[0].set(False)
    pose_at = jax.vmap(pose_on_path, in_axes=(None, None, None, 0))

    def sub(carry, k):
        s, v, a_prev = carry                                                            # [C]
        q = cur_xy + cur_velocity * (k * dt)
        arc, lat, tan = project_on_path(route_xy, route_s, q)                           # [A]
        cand = (others & (lat < 0.5 * (width + size[:, 1])))[None] & (arc[None] > s[:, None])     # [C, A]
        gap = jnp.where(cand, arc[None] - s[:, None] - 0.5 * (length + size[:, 0])[None], jnp.inf)
        j = jnp.argmin(gap, axis=1)
        lead_v = jnp.sum(cur_velocity[j] * tan[j], -1)
        a = idm_accel(v, speeds, jnp.take_along_axis(gap, j[:, None], 1)[:, 0], v - lead_v, p)
        if max_decel is not None:
            a = jnp.maximum(a, -max_decel)
        if max_jerk is not None:
            a = a_prev + jnp.clip(a - a_prev, -max_jerk * dt, max_jerk * dt)
        v = jnp.maximum(v + a * dt, 0.0)
        a = jnp.where(v > 0.0, a, 0.0)                                                  # stopped: no acceleration
        s = s + v * dt
        xy, h = pose_at(route_xy, route_heading, route_s, s)
        return (s, v, a), jnp.concatenate([xy, h[:, None]], -1)                         # [C, 3]

    start = (jnp.full_like(speeds, s0[0]), jnp.full_like(speeds, jnp.linalg.norm(cur_velocity[0])),
             jnp.full_like(speeds, accel0))
    _, poses = jax.lax.scan(sub, start, jnp.arange(num_steps, dtype=jnp.float32))
    poses = jnp.moveaxis(poses, 0, 1)                                                   # [C, num_steps, 3]
    return poses if jnp.ndim(target_speed) else poses[0]


def idm_route_plan(route_xy: jax.Array, route_heading: jax.Array, route_s: jax.Array, ego_pose: jax.Array,
                   cur_xy: jax.Array, cur_velocity: jax.Array, cur_valid: jax.Array, size: jax.Array,
                   num_future: int, stride: int, dt: float, target_speed=ROUTE_SPEED) -> jax.Array:
    """`idm_along_route` at the model's frames: the ego's poses f32[num_future, 3] (scene frame) at the next
    `num_future` model frames of `stride` steps of `dt` seconds (the `idm` planner's plan); with target speeds
    f32[C] (`plan_head.idm_speeds`: the candidate plans of a planning head with `plan_head.candidates = "idm"`)
    f32[C, num_future, 3]."""
    poses = idm_along_route(route_xy, route_heading, route_s, ego_pose, cur_xy, cur_velocity, cur_valid, size,
                            stride * num_future, dt, target_speed)
    return poses[..., stride - 1:: stride, :]
