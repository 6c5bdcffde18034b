"""The traffic-light violation feature of the 2025 WOSAC configuration (pure JAX, `jit` and `vmap` over rollouts).

Definition (the official sim-agents metric's, facts in `reference/wosac.md`): an agent violates a red light at
frame t when all of these hold:

* the lane it is on at t has a traffic signal: its position is nearest to that signal's lane among all lanes
  of the map (here: the scene's lane centrelines `Scene.polylines` and the signals' own lane pieces; the signal's
  lane counts as nearest when it is within `LANE_TIE_M` of the nearest, since the store holds the same lane
  twice: once among the polylines and once as the signal's piece);
* the signal's state at t is a stop state (`gpd_jax.geometry.STOP_STATES`: stop, arrow stop; not flashing
  stop, caution, go or unknown);
* the agent crossed the stop point between t - 1 and t: its projection on the line of the signal lane's segment
  nearest the stop point was behind the stop point's projection at t - 1 and ahead of it at t (unclamped
  projections, compared along that segment).

The metric's term is a Bernoulli of "any violation over the rollout" per agent, like collision.

Where this differs from the official code, both where the official format has no such thing: a crossing needs the
agent valid at t - 1 and t (the official code asks validity at t only: it has no missing steps); the lane test
is exact only for the first `max_events` candidate crossings (a crossing under a stop state) of a trajectory, in
frame-major order, and any beyond are counted as violations (`red_light_violation` returns how many were, which
`realism` reports; 0 with the defaults on every store here).

Cost: the projections are per (frame, agent, signal slot); the nearest-lane test, against every lane segment,
runs only for the candidate crossings (`max_events` of them), so the feature adds little to the realism metric.
"""

from __future__ import annotations

import jax.numpy as jnp

from gpd_jax.geometry import STOP_STATES, TrafficSignals

LANE_TIE_M = 1e-3  # metres: the signal's lane is "the lane the agent is on" within this of the nearest lane
MAX_EVENTS = 64  # candidate crossings per trajectory whose lane test is exact


def _segments(points, valid):
    """Segments of polylines f32[..., P, 2] / bool[..., P] flattened: (a f32[N, 2], b f32[N, 2], ok bool[N])."""
    a, b = points[..., :-1, :], points[..., 1:, :]
    ok = valid[..., :-1] & valid[..., 1:]
    return a.reshape(-1, 2), b.reshape(-1, 2), ok.reshape(-1)


def _distance(p, a, b, ok):
    """f32[M, N]: distance of points p f32[M, 2] to segments (a, b f32[N, 2]); inf where not `ok`."""
    ab = b - a
    den = jnp.sum(ab * ab, -1)
    ap = p[:, None, :] - a[None]
    u = jnp.clip(jnp.sum(ap * ab[None], -1) / jnp.where(den > 0, den, 1.0)[None], 0.0, 1.0)
    d = jnp.linalg.norm(ap - u[..., None] * ab[None], axis=-1)
    return jnp.where(ok[None], d, jnp.inf)


def stop_segments(signals: TrafficSignals):
    """Per signal slot of one scene, the segment of its lane nearest its stop point and the stop point's position
    along it: (start f32[S, 2], direction f32[S, 2] (end - start), stop_u f32[S] (projection, in units of the
    segment), present bool[S] (a lane of at least two points))."""
    lane, lv = signals.lane.astype(jnp.float32), signals.lane_valid
    a, b = lane[:, :-1], lane[:, 1:]
    ok = lv[:, :-1] & lv[:, 1:]
    ab = b - a
    den = jnp.sum(ab * ab, -1)
    ap = signals.stop[:, None, :] - a
    u = jnp.clip(jnp.sum(ap * ab, -1) / jnp.where(den > 0, den, 1.0), 0.0, 1.0)
    d = jnp.where(ok, jnp.linalg.norm(ap - u[..., None] * ab, axis=-1), jnp.inf)
    k = jnp.argmin(d, -1)  # the first nearest segment, as argmin
    start = jnp.take_along_axis(a, k[:, None, None], 1)[:, 0]
    direction = jnp.take_along_axis(ab, k[:, None, None], 1)[:, 0]
    dd = jnp.sum(direction * direction, -1)
    stop_u = jnp.sum((signals.stop - start) * direction, -1) / jnp.where(dd > 0, dd, 1.0)
    return start, direction, stop_u, jnp.any(ok, -1) & (dd > 0)


def red_light_violation(xy, valid, signals: TrafficSignals, lanes, lane_valid, max_events: int = MAX_EVENTS):
    """Where each agent runs a red light, for one trajectory set of one scene.

    Args:
      xy: f32[T, A, 2] box centres; valid: bool[T, A].
      signals: the scene's `TrafficSignals` (unbatched), `state i32[T, S]` on the same frames.
      lanes: f32[L, P, 2] the scene's lane centrelines (`Scene.polylines`); lane_valid: bool[L, P].
      max_events: static; candidate crossings whose lane test is exact (module docstring).

    Returns (violation bool[T, A] (False at frame 0), beyond i32[]: candidate crossings past `max_events`, which
    are counted as violations).
    """
    t_n, a_n = valid.shape
    start, direction, stop_u, present = stop_segments(signals)
    dd = jnp.sum(direction * direction, -1)
    u = jnp.einsum("tasd,sd->tas", xy[:, :, None, :] - start[None, None], direction) / jnp.where(dd > 0, dd, 1.0)
    behind, ahead = u < stop_u, u > stop_u
    crossed = behind[:-1] & ahead[1:] & (valid[:-1] & valid[1:])[..., None]  # [T-1, A, S]
    red = jnp.isin(signals.state[1:], jnp.asarray(STOP_STATES))  # [T-1, S]
    event = crossed & red[:, None, :] & present[None, None]
    flat = event.reshape(-1)
    count = jnp.sum(flat)
    (idx,) = jnp.nonzero(flat, size=max_events, fill_value=0)
    used = jnp.arange(max_events) < count
    t_i = idx // (a_n * event.shape[-1]) + 1
    a_i = (idx // event.shape[-1]) % a_n
    s_i = idx % event.shape[-1]
    p = xy[t_i, a_i]  # [E, 2]
    # the lane the agent is on: nearest over the map's lanes and every signal's lane piece
    la, lb, lok = _segments(lanes.astype(jnp.float32), lane_valid)
    sa, sb, sok = _segments(signals.lane.astype(jnp.float32), signals.lane_valid)
    d_slot = jnp.min(_distance(p, sa, sb, sok).reshape(max_events, signals.lane.shape[0], -1), -1)  # [E, S]
    d_all = jnp.minimum(jnp.min(_distance(p, la, lb, lok), -1), jnp.min(d_slot, -1))
    d_own = d_slot[jnp.arange(max_events), s_i]
    on_lane = d_own <= d_all + LANE_TIE_M
    out = jnp.zeros((t_n, a_n), bool).at[t_i, a_i].max(used & on_lane)
    # candidate crossings beyond the budget: counted as violations
    beyond_mask = event & (jnp.cumsum(flat).reshape(event.shape) > max_events)
    out = out.at[1:].max(jnp.any(beyond_mask, -1))
    return out, jnp.maximum(count - max_events, 0).astype(jnp.int32)

