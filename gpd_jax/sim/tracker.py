"""Plan execution as nuPlan does it: a planner's trajectory is a *reference* that a controller follows on the
kinematic bicycle model between replans, at the stored rate, inside the compiled simulator step.

Every ego form a policy returns (`gpd_jax.sim.Policy`) becomes a time-stamped reference at the stored rate, from the
current frame on:

* a pose f32[3] or pose and velocity f32[5] at the next model frame: the cubic Hermite curve to it
  (`gpd_jax.sim.dynamics.pose_path`);
* stored-rate poses f32[N, 3] (N >= S): themselves (the shipped expert and IDM give two model frames, so the
  look-ahead near the end of a frame reads where they go next);
* a `Plan` (poses at the next F model frames, f32[F, 3]): the Hermite curves through the current pose and the F
  poses (velocities at the knots by central differences), so a plan is followed beyond the next model frame;
* an action f32[2] (acceleration, steering) is a control already and is integrated as it is, untracked.

Past its end a reference goes on at its last velocity (straight, constant speed), so look-ahead and plans held
over several model frames are always defined.

The `Tracker` follows the reference on the bicycle model of `gpd_jax.sim.dynamics` (the `BicycleLimits`):

* **steering** by pure pursuit: the target is the reference `lookahead_s` ahead in time, the arc through it tangent
  to the heading gives the curvature 2 sin(alpha) / d (d at least `min_lookahead_m`), the steering angle
  atan(wheelbase x curvature), moved towards at most `max_steer_rate`;
* **speed** by a PD law on the reference's timing: acceleration = the reference's own acceleration + `speed_gain` x
  (reference speed - speed) + `position_gain` x (how far the reference point of now lies ahead along the heading),
  its change limited to `max_jerk` per second, then clipped by the limits (no reversing).

A policy is called every model frame (its state sees every frame); its output replaces the held reference every
`replan_every` model frames (1: every frame, as nuPlan replans every step) and is otherwise dropped.
"""

from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp

from gpd_jax.scene import wrap_angle
from gpd_jax.sim.dynamics import BicycleLimits, hermite, lerp_heading


@flax.struct.dataclass(frozen=True)
class Tracker:
    """How the ego follows its planner's reference (static numbers; `flax.struct` so they hash as jit statics).

    lookahead_s: pure-pursuit look-ahead along the reference, in seconds; min_lookahead_m: the least look-ahead
    distance; speed_gain (1/s), position_gain (1/s^2): the speed law's gains; max_jerk (m/s^3): the largest change
    of acceleration per second; max_steer_rate (rad/s): the largest change of steering angle per second;
    replan_every: model frames between replans (>= 1).
    """

    lookahead_s: float = flax.struct.field(pytree_node=False, default=1.0)
    min_lookahead_m: float = flax.struct.field(pytree_node=False, default=4.0)
    speed_gain: float = flax.struct.field(pytree_node=False, default=2.0)
    position_gain: float = flax.struct.field(pytree_node=False, default=1.0)
    max_jerk: float = flax.struct.field(pytree_node=False, default=8.0)
    max_steer_rate: float = flax.struct.field(pytree_node=False, default=0.5)
    replan_every: int = flax.struct.field(pytree_node=False, default=1)

    def lookahead_steps(self, dt: float) -> int:
        return max(1, int(round(self.lookahead_s / dt)))

    def reference_length(self, given: int, num_steps: int, dt: float) -> int:
        """Stored-rate points a held reference keeps (after its point of now): enough for `replan_every` model
        frames of `num_steps` steps plus the look-ahead, at least what the policy gave."""
        return max(given, self.replan_every * num_steps) + self.lookahead_steps(dt)


@flax.struct.dataclass
class Plan:
    """A policy's trajectory to be followed: poses f32[..., F, 3] (x, y, heading; scene frame) at the next F model
    frames (F >= 1). Returned by `Policy.select` (or a `run_host` planner, with the batch axis in front) in place
    of a single pose, it is followed by the tracker for as long as it is held (`Tracker.replan_every`)."""

    poses: jax.Array


@flax.struct.dataclass
class TrackState:
    """The tracker's vehicle state between model frames: speed f32[] (m/s, along the heading), accel f32[]
    (m/s^2), steer f32[] (rad)."""

    speed: jax.Array
    accel: jax.Array
    steer: jax.Array

    @staticmethod
    def at_rest() -> "TrackState":
        z = jnp.zeros((), jnp.float32)
        return TrackState(speed=z, accel=z, steer=z)


def plan_path(pose0: jax.Array, vel0: jax.Array, poses: jax.Array, period: float, num_steps: int) -> jax.Array:
    """The stored-rate reference of a plan: pose0 f32[3], vel0 f32[2], poses f32[F, 3] at the next F model frames
    (`period` s apart) -> f32[F * num_steps, 3] (Hermite curves through the knots, velocities by central
    differences, the last by the backward difference)."""
    knots = jnp.concatenate([pose0[None, :2], poses[:, :2]], 0)                         # [F + 1, 2]
    mid = (knots[2:] - knots[:-2]) / (2 * period)                                       # [F - 1, 2]
    end = (knots[-1:] - knots[-2:-1]) / period
    vel = jnp.concatenate([vel0[None], mid, end], 0)                                    # [F + 1, 2]
    heads = jnp.concatenate([pose0[None, 2], poses[:, 2]], 0)
    seg = jax.vmap(lambda p0, v0, p1, v1: hermite(p0, v0, p1, v1, period, num_steps))(
        knots[:-1], vel[:-1], knots[1:], vel[1:])                                       # [F, S, 2]
    h = jax.vmap(lambda h0, h1: lerp_heading(h0, h1, num_steps))(heads[:-1], heads[1:])  # [F, S]
    f = poses.shape[0]
    return jnp.concatenate([seg.reshape(f * num_steps, 2), h.reshape(f * num_steps, 1)], -1)


def extend(path: jax.Array, start: jax.Array, length: int) -> jax.Array:
    """A reference f32[R, 3] (the poses after `start` f32[3]) continued to `length` points at its last velocity
    (straight on, constant speed); cut to `length` when longer."""
    r = path.shape[0]
    if r >= length:
        return path[:length]
    prev = path[-2] if r > 1 else start
    step = path[-1, :2] - prev[:2]
    k = jnp.arange(1, length - r + 1, dtype=path.dtype)[:, None]
    tail = jnp.concatenate([path[-1, :2] + k * step, jnp.broadcast_to(path[-1, 2], (length - r, 1))], -1)
    return jnp.concatenate([path, tail], 0)


def track(reference: jax.Array, pose0: jax.Array, state: TrackState, length: jax.Array, num_steps: int, dt: float,
          tracker: Tracker, limits: BicycleLimits = BicycleLimits()) -> tuple[jax.Array, TrackState]:
    """Follows a reference for `num_steps` stored-rate steps of `dt` seconds.

    reference f32[R + 1, 3]: the reference's pose now (index 0) and at each following step (R >= num_steps +
    look-ahead); pose0 f32[3] the ego now; state: its speed, acceleration and steering now; length f32[] its box
    length. Returns (path f32[num_steps, 3], the state after the last step).
    """
    n_la = tracker.lookahead_steps(dt)
    wheelbase = jnp.maximum(limits.wheelbase_ratio * length, 0.5)
    last = reference.shape[0] - 1

    def sub(carry, k):
        x, y, h, st = carry
        ref_now, ref_next = reference[k], reference[k + 1]
        ref_after = reference[jnp.minimum(k + 2, last)]
        v_ref = jnp.linalg.norm(ref_next[:2] - ref_now[:2]) / dt
        a_ref = (jnp.linalg.norm(ref_after[:2] - ref_next[:2]) / dt - v_ref) / dt
        heading_vec = jnp.stack([jnp.cos(h), jnp.sin(h)])
        ahead = jnp.dot(ref_now[:2] - jnp.stack([x, y]), heading_vec)
        a_cmd = a_ref + tracker.speed_gain * (v_ref - st.speed) + tracker.position_gain * ahead
        jerk = tracker.max_jerk * dt
        accel = jnp.clip(st.accel + jnp.clip(a_cmd - st.accel, -jerk, jerk), -limits.max_decel, limits.max_accel)
        target = reference[jnp.minimum(k + n_la, last), :2]
        d = target - jnp.stack([x, y])
        dist = jnp.linalg.norm(d)
        alpha = wrap_angle(jnp.arctan2(d[1], d[0]) - h)
        curvature = jnp.where(dist > 1e-3, 2.0 * jnp.sin(alpha) / jnp.maximum(dist, tracker.min_lookahead_m), 0.0)
        steer_cmd = jnp.arctan(wheelbase * curvature)
        rate = tracker.max_steer_rate * dt
        steer = jnp.clip(st.steer + jnp.clip(steer_cmd - st.steer, -rate, rate), -limits.max_steer, limits.max_steer)
        v = jnp.clip(st.speed + accel * dt, 0.0, limits.max_speed)
        h = wrap_angle(h + v * jnp.tan(steer) / wheelbase * dt)
        x, y = x + v * jnp.cos(h) * dt, y + v * jnp.sin(h) * dt
        return (x, y, h, TrackState(speed=v, accel=accel, steer=steer)), jnp.stack([x, y, h])

    (_, _, _, st), path = jax.lax.scan(sub, (pose0[0], pose0[1], pose0[2], state), jnp.arange(num_steps))
    return path, st
