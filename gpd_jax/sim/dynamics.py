"""Ego motion between two model frames, at the stored rate: a kinematic bicycle model with limits (actions), cubic
Hermite curves (poses), and the same curves for interpolating generated agents.

The simulator's model runs at its own frame rate (1 Hz for the shipped model) but every score is taken at the
stored rate (10 Hz), so each step fills the S = `frame_stride` stored frames after the current model frame:

* an **action** (acceleration m/s^2, steering angle rad) is held for the model period and integrated at the stored
  rate by a kinematic bicycle model on the box centre (yaw rate = v tan(steer) / wheelbase), with the limits of
  `BicycleLimits` (no reversing);
* a **pose** (x, y, heading) at the next model frame, with or without the velocity there, becomes a cubic Hermite
  curve from the current (position, velocity) to the target (position, velocity); without a target velocity the
  target speed is the constant-acceleration one, 2 |chord| / dt - |v0| (at least 0), along the target heading;
  headings are interpolated linearly along the shorter arc;
* a **path** f32[N, 3] (stored-rate poses, N >= S) is taken as it is (its first S without a tracker).
"""

from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp

from gpd_jax.scene import wrap_angle


@flax.struct.dataclass(frozen=True)
class BicycleLimits:
    """Limits of the kinematic bicycle model (static numbers; `flax.struct` so they hash as jit statics).

    max_accel, max_decel: m/s^2 (acceleration clipped to [-max_decel, max_accel]); max_steer: rad; max_speed: m/s;
    wheelbase_ratio: the wheelbase as a share of the box length.
    """

    max_accel: float = flax.struct.field(pytree_node=False, default=4.0)
    max_decel: float = flax.struct.field(pytree_node=False, default=8.0)
    max_steer: float = flax.struct.field(pytree_node=False, default=0.6)
    max_speed: float = flax.struct.field(pytree_node=False, default=40.0)
    wheelbase_ratio: float = flax.struct.field(pytree_node=False, default=0.6)


def bicycle_path(pose: jax.Array, velocity: jax.Array, action: jax.Array, length: jax.Array, num_steps: int,
                 dt: float, limits: BicycleLimits = BicycleLimits()) -> jax.Array:
    """Integrates an action held for `num_steps` steps of `dt` seconds.

    pose f32[3] (x, y, heading), velocity f32[2] (scene frame; its component along the heading is the speed,
    clipped at 0), action f32[2] (acceleration, steering angle), length f32[] (box length) -> f32[num_steps, 3].
    Semi-implicit Euler: speed first, then heading, then position.
    """
    accel = jnp.clip(action[0], -limits.max_decel, limits.max_accel)
    steer = jnp.clip(action[1], -limits.max_steer, limits.max_steer)
    wheelbase = jnp.maximum(limits.wheelbase_ratio * length, 0.5)
    v0 = jnp.maximum(velocity[0] * jnp.cos(pose[2]) + velocity[1] * jnp.sin(pose[2]), 0.0)

    def sub(carry, _):
        x, y, h, v = carry
        v = jnp.clip(v + accel * dt, 0.0, limits.max_speed)
        h = wrap_angle(h + v * jnp.tan(steer) / wheelbase * dt)
        x, y = x + v * jnp.cos(h) * dt, y + v * jnp.sin(h) * dt
        return (x, y, h, v), jnp.stack([x, y, h])

    _, path = jax.lax.scan(sub, (pose[0], pose[1], pose[2], v0), None, length=num_steps)
    return path


def hermite(p0: jax.Array, v0: jax.Array, p1: jax.Array, v1: jax.Array, period: float, num_steps: int) -> jax.Array:
    """Cubic Hermite positions at s = k / num_steps, k = 1 .. num_steps, between p0 (velocity v0) and p1 (velocity
    v1), `period` seconds apart. p0, v0, p1, v1 f32[..., 2] -> f32[num_steps, ..., 2] (the last equals p1)."""
    s = (jnp.arange(1, num_steps + 1, dtype=p0.dtype) / num_steps).reshape((num_steps,) + (1,) * p0.ndim)
    h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
    h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
    return h00 * p0 + h10 * period * v0 + h01 * p1 + h11 * period * v1


def lerp_heading(h0: jax.Array, h1: jax.Array, num_steps: int) -> jax.Array:
    """Headings at s = k / num_steps (k = 1 .. num_steps) along the shorter arc from h0 to h1: f32[num_steps, ...]."""
    s = (jnp.arange(1, num_steps + 1, dtype=h0.dtype) / num_steps).reshape((num_steps,) + (1,) * h0.ndim)
    return wrap_angle(h0 + s * wrap_angle(h1 - h0))


def target_speed(p0: jax.Array, v0: jax.Array, p1: jax.Array, period: float) -> jax.Array:
    """The constant-acceleration speed at the target: 2 |p1 - p0| / period - |v0|, at least 0. f32[...]."""
    chord = jnp.linalg.norm(p1 - p0, axis=-1)
    return jnp.maximum(2 * chord / period - jnp.linalg.norm(v0, axis=-1), 0.0)


def pose_path(pose0: jax.Array, vel0: jax.Array, target: jax.Array, vel1: jax.Array | None, period: float,
              num_steps: int) -> tuple[jax.Array, jax.Array]:
    """The stored-rate path to a target pose: pose0 f32[3], vel0 f32[2], target f32[3], vel1 f32[2] or None ->
    (path f32[num_steps, 3], velocity at the target f32[2]). See the module docstring."""
    if vel1 is None:
        speed = target_speed(pose0[:2], vel0, target[:2], period)
        vel1 = speed * jnp.stack([jnp.cos(target[2]), jnp.sin(target[2])])
    xy = hermite(pose0[:2], vel0, target[:2], vel1, period, num_steps)
    h = lerp_heading(pose0[2], target[2], num_steps)
    return jnp.concatenate([xy, h[:, None]], -1), vel1
