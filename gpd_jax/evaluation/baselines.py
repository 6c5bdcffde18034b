"""Non-learned baselines producing the same predicted arrays as a rollout (xy, heading, valid over all T frames).

* `log_replay`: the recorded scene itself (its metrics are the ground-truth floor: zero ADE/FDE, and the log's
  own collision rate).
* `constant_velocity`: every agent continues from its last valid history frame at the velocity of its last two
  valid history frames, keeping its last observed heading.
* `follow_lanes` (not in the paper; `constant_velocity_lanes` in `metrics.json`): constant velocity's speed, but
  along the lane the agent is on (`gpd_jax.geometry.lane_trace`), keeping its offset from the lane: what a map
  gives a predictor that knows nothing else. Agents more than `LANE_SNAP_M` from a lane keep constant velocity.

History frames [0, num_history) are copied from the log, as a rollout does; the current frame is
`num_history - 1`. Both are pure jit/vmap-able functions of a `Scene` (any leading batch dims).
"""

from __future__ import annotations

import functools

import flax.struct
import jax
import jax.numpy as jnp

from gpd_jax.geometry import lane_follow
from gpd_jax.scene import Scene, backward_difference


@flax.struct.dataclass
class Trajectories:
    """Predicted agent states over the whole scene (the fields a rollout outputs).

    xy: f32[..., T, A, 2], heading: f32[..., T, A], valid: bool[..., T, A].
    """

    xy: jax.Array
    heading: jax.Array
    valid: jax.Array


def log_replay(scene: Scene, num_history: int) -> Trajectories:
    """The recorded future. `num_history` is accepted for a uniform signature (history is the log either way)."""
    del num_history
    return Trajectories(xy=scene.xy, heading=scene.heading, valid=scene.valid)


@functools.partial(jax.jit, static_argnames="num_history")
def constant_velocity(scene: Scene, num_history: int) -> Trajectories:
    """Constant-velocity, constant-heading extrapolation of every slot (ego included).

    For each agent, t2 is its last valid history frame and t1 the valid one before it; the velocity is
    (xy[t2] - xy[t1]) / (t2 - t1) per frame (zero with a single valid history frame), and future positions are
    xy[t2] + v * (t - t2) with heading[t2]. Future validity is the log's (so metrics score the frames the log
    has), except that agents not valid at the current frame `num_history - 1` stay invalid for the whole future
    (their positions are still extrapolated from whatever history they had, or zero if none).

    Args:
      scene: a Scene with `xy: f32[..., T, A, 2]`, `heading: f32[..., T, A]`, `valid: bool[..., T, A]`.
      num_history: number of history frames H (frames [0, H) are observed; 21 in the paper).

    Returns:
      Trajectories over all T frames: history frames from the log, future frames extrapolated.
    """
    xy, heading, valid = scene.xy, scene.heading, scene.valid
    t_total = xy.shape[-3]
    h = num_history
    hv = valid[..., :h, :]  # [..., H, A]
    t2 = jnp.max(jnp.where(hv, jnp.arange(h)[:, None], -1), axis=-2)  # [..., A] last valid history frame
    has2 = t2 >= 0

    def at_t2(a):  # f32[..., H, A, C] -> f32[..., A, C] at each agent's frame t2
        return jnp.take_along_axis(a, jnp.maximum(t2, 0)[..., None, :, None], axis=-3)[..., 0, :, :]

    # the step from the valid frame before t2 (t1): `backward_difference`, what a velocity-input model reads
    step, gap, known = backward_difference(xy[..., :h, :, :], hv)
    p2 = jnp.where(has2[..., None], at_t2(xy[..., :h, :, :]), 0.0)  # [..., A, 2]
    vel = jnp.where(at_t2(known[..., None]), at_t2(step / gap[..., None]), 0.0)  # per frame
    hd = jnp.where(has2, at_t2(heading[..., :h, :, None])[..., 0], 0.0)  # [..., A]

    fut = jnp.arange(h, t_total)  # [F]
    dt = (fut[:, None] - t2[..., None, :]).astype(xy.dtype)  # [..., F, A]
    fxy = p2[..., None, :, :] + vel[..., None, :, :] * dt[..., None]
    fhead = jnp.broadcast_to(hd[..., None, :], dt.shape)
    alive = valid[..., h - 1, :] if h > 0 else jnp.zeros(valid.shape[:-2] + valid.shape[-1:], bool)
    fvalid = valid[..., h:, :] & alive[..., None, :]

    cat = lambda a, b, axis: jnp.concatenate([a, b], axis=axis)
    return Trajectories(xy=cat(xy[..., :h, :, :], fxy, -3), heading=cat(heading[..., :h, :], fhead, -2),
                        valid=cat(valid[..., :h, :], fvalid, -2))


def follow_lanes(cv: Trajectories, num_history: int, polylines: jax.Array, polyline_valid: jax.Array,
                 stride: int = 4) -> Trajectories:
    """Constant velocity moved onto the lanes (one scene; vmap for batches).

    `cv`: constant velocity's prediction of one scene at evenly spaced frames (xy f32[T, A, 2], ...; frames
    [0, num_history) the log's). Each agent valid at the current frame `num_history - 1` covers the same distance
    per frame as there (|cv.xy[H] - cv.xy[H - 1]|), but along the lane it is on: from its current position it walks
    the lanes (`lane_trace` from its direction of motion, or its heading when it stands), and frame H - 1 + k
    is the walk's point after k steps plus the agent's current offset from the lane turned with the lane,
    heading along the lane there. Where the walk runs off the lanes (a lane clipped at the sample's edge), it
    goes on straight (`lane_trace`'s `max_gap_m`). Agents with no lane within `LANE_SNAP_M` of them keep
    constant velocity. polylines f32[L, P, 2] / polyline_valid bool[L, P]: the scene's lane centrelines in the
    scene frame; `stride`: every stride-th point (coarser segments)."""
    h = num_history
    t_total = cv.xy.shape[-3]
    if t_total <= h:
        return cv
    p0, d = cv.xy[h - 1], cv.xy[h] - cv.xy[h - 1]  # [A, 2]
    speed = jnp.linalg.norm(d, axis=-1)
    direction = jnp.where(speed > 1e-6, jnp.arctan2(d[:, 1], d[:, 0]), cv.heading[h - 1])
    xy, _, lane_h, near = lane_follow(polylines, polyline_valid, p0, direction, speed, t_total - h, stride=stride)
    use = cv.valid[h - 1] & near  # [A]
    xy = jnp.swapaxes(xy, 0, 1)  # [F, A, 2]
    moving = speed > 1e-6
    heading = jnp.where(moving[None], jnp.swapaxes(lane_h, 0, 1), cv.heading[h:])
    fut_xy = jnp.where(use[None, :, None], xy, cv.xy[h:])
    fut_heading = jnp.where(use[None], heading, cv.heading[h:])
    return Trajectories(xy=jnp.concatenate([cv.xy[:h], fut_xy.astype(cv.xy.dtype)], 0),
                        heading=jnp.concatenate([cv.heading[:h], fut_heading.astype(cv.heading.dtype)], 0),
                        valid=cv.valid)


BASELINES = {"log_replay": log_replay, "constant_velocity": constant_velocity}
