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
  projections, compared along that segment; a position exactly at the stop point is neither).

The metric's term is a Bernoulli of "any violation over the rollout" per agent, like collision.

Where this differs from the official code (which has neither missing steps nor a budget):
* a crossing needs the agent valid at t - 1 and t (the official code asks validity at t only), and within
  `NEAR_STOP_M` of the stop point at t (a vehicle crossing its lane's stop line is; the official code also takes
  crossings of the stop line's extension far to the side, which its lane test then rejects);
* the nearest lane is sought among the lane segments within `CANDIDATE_RADIUS_M` of the stop point (at most
  `NUM_CANDIDATES`, per scene: `signal_geometry`), which holds every segment nearer than the agent's own lane
  for an agent within `CANDIDATE_RADIUS_M - NEAR_STOP_M` (7 m) of that lane;
* per agent only the `SLOTS_PER_AGENT` signals whose stop point it comes nearest are looked at (an agent within
  `NEAR_STOP_M` of more stop points is reported inexact);
* the lane test runs for the first `max_events` candidate crossings (a crossing under a stop state) of a
  trajectory, in frame-major order; any beyond are counted as violations (`red_light_violation` returns how
  many).

Cost: per (frame, agent, signal slot) one distance (to rank the slots), per (frame, agent, kept slot) a projection;
the lane test only for the candidate crossings, against the few segments around their stop point.
"""

from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp

from gpd_jax.geometry import STOP_STATES, TrafficSignals

LANE_TIE_M = 1e-3  # metres: the signal's lane is "the lane the agent is on" within this of the nearest lane
MAX_EVENTS = 32  # candidate crossings per trajectory whose lane test is exact
NEAR_STOP_M = 5.0  # a crossing counts only within this many metres of the stop point
CANDIDATE_RADIUS_M = 12.0  # lane segments within this of a stop point take part in its nearest-lane test
NUM_CANDIDATES = 256  # at most this many of them per signal (nearest first)
SLOTS_PER_AGENT = 12  # signals looked at per agent: those whose stop point it comes nearest


@flax.struct.dataclass(frozen=True)
class SignalGeometry:
    """What the violation test needs of one scene's signals, computed once per scene (`signal_geometry`).

    Attributes:
      state: i32[T, S] the states per frame.
      stop: f32[S, 2] stop points; start, direction: f32[S, 2] each signal lane's segment nearest its stop point
        (start, end - start); stop_u: f32[S] the stop point's projection on it (units of the segment);
        present: bool[S] slots with a lane.
      own_a, own_b: f32[S, Q-1, 2], own_ok: bool[S, Q-1] each slot's own lane segments.
      cand_a, cand_b: f32[S, C, 2], cand_ok: bool[S, C] the lane segments (the map's lanes and every signal's lane)
        within `CANDIDATE_RADIUS_M` of each stop point, the `NUM_CANDIDATES` nearest.
    """

    state: jax.Array
    stop: jax.Array
    start: jax.Array
    direction: jax.Array
    stop_u: jax.Array
    present: jax.Array
    own_a: jax.Array
    own_b: jax.Array
    own_ok: jax.Array
    cand_a: jax.Array
    cand_b: jax.Array
    cand_ok: jax.Array


def _segments(points, valid):
    """Segments of polylines f32[..., P, 2] / bool[..., P]: (a, b f32[..., P-1, 2], ok bool[..., P-1])."""
    return points[..., :-1, :], points[..., 1:, :], valid[..., :-1] & valid[..., 1:]


def _distance(p, a, b, ok):
    """f32[..., N]: distance of points p f32[..., 2] to segments (a, b f32[..., N, 2]); inf where not `ok`."""
    ab = b - a
    den = jnp.sum(ab * ab, -1)
    ap = p[..., None, :] - a
    u = jnp.clip(jnp.sum(ap * ab, -1) / jnp.where(den > 0, den, 1.0), 0.0, 1.0)
    d = jnp.linalg.norm(ap - u[..., None] * ab, axis=-1)
    return jnp.where(ok, d, jnp.inf)


def signal_geometry(signals: TrafficSignals, lanes, lane_valid,
                    num_candidates: int = NUM_CANDIDATES) -> SignalGeometry:
    """`SignalGeometry` of one scene: `signals` (unbatched, states on the scored frames) and the scene's lane
    centrelines `lanes f32[L, P, 2]`, `lane_valid bool[L, P]` (`Scene.polylines`, `polyline_valid`)."""
    lane = signals.lane.astype(jnp.float32)
    oa, ob, ook = _segments(lane, signals.lane_valid)  # [S, Q-1]
    stop = signals.stop.astype(jnp.float32)
    d = _distance(stop, oa, ob, ook)  # [S, Q-1]
    k = jnp.argmin(d, -1)  # the first nearest segment, as argmin
    start = jnp.take_along_axis(oa, k[:, None, None], 1)[:, 0]
    direction = jnp.take_along_axis(ob - oa, k[:, None, None], 1)[:, 0]
    dd = jnp.sum(direction * direction, -1)
    stop_u = jnp.sum((stop - start) * direction, -1) / jnp.where(dd > 0, dd, 1.0)
    la, lb, lok = _segments(lanes.astype(jnp.float32), lane_valid)
    all_a = jnp.concatenate([la.reshape(-1, 2), oa.reshape(-1, 2)])
    all_b = jnp.concatenate([lb.reshape(-1, 2), ob.reshape(-1, 2)])
    all_ok = jnp.concatenate([lok.reshape(-1), ook.reshape(-1)])
    dist = _distance(stop, all_a, all_b, all_ok)  # [S, N]
    c = min(num_candidates, all_ok.shape[0])
    neg, idx = jax.lax.top_k(-dist, c)
    return SignalGeometry(state=signals.state, stop=stop, start=start, direction=direction, stop_u=stop_u,
                          present=jnp.any(ook, -1) & (dd > 0), own_a=oa, own_b=ob, own_ok=ook,
                          cand_a=all_a[idx], cand_b=all_b[idx], cand_ok=-neg <= CANDIDATE_RADIUS_M)


def red_light_violation(xy, valid, geo: SignalGeometry, max_events: int = MAX_EVENTS,
                        slots_per_agent: int = SLOTS_PER_AGENT):
    """Where each agent runs a red light, for one trajectory set of one scene.

    Args:
      xy: f32[T, A, 2] box centres; valid: bool[T, A] (the frames of `geo.state`).
      geo: the scene's `signal_geometry`.
      max_events: static; candidate crossings whose lane test is exact (module docstring).
      slots_per_agent: static; the signals per agent looked at: those whose stop point it comes nearest.

    Returns (violation bool[T, A] (False at frame 0), inexact i32[]: candidate crossings past `max_events`, which
    are counted as violations, plus agents that come within `NEAR_STOP_M` of more than `slots_per_agent` stop
    points, whose farther ones are not looked at).
    """
    t_n, a_n = valid.shape
    # per agent, the `slots_per_agent` signals whose stop point it comes nearest (only those within NEAR_STOP_M
    # can count): the rest of the test runs on [T, A, k] instead of [T, A, S]
    d2 = jnp.sum((xy[:, :, None, :] - geo.stop[None, None]) ** 2, -1)  # [T, A, S]
    closest = jnp.min(jnp.where(valid[..., None] & geo.present[None, None], d2, jnp.inf), 0)  # [A, S]
    k = min(slots_per_agent, geo.stop.shape[0])
    neg, slot = jax.lax.top_k(-closest, k)  # [A, k]
    crowded = jnp.sum(closest <= NEAR_STOP_M ** 2, -1) > k  # near more stop points than kept
    start, direction = geo.start[slot], geo.direction[slot]  # [A, k, 2]
    stop_u, present = geo.stop_u[slot], geo.present[slot] & (-neg <= NEAR_STOP_M ** 2)  # [A, k]
    dd = jnp.sum(direction * direction, -1)
    rel = xy[:, :, None, :] - start[None]  # [T, A, k, 2]
    along = jnp.sum(rel * direction[None], -1)  # u * |direction|^2
    stop_along = (stop_u * dd)[None]
    off = rel - (stop_u[..., None] * direction)[None]  # from the stop point's projection: about the stop point
    near = jnp.sum(off * off, -1) <= NEAR_STOP_M ** 2
    crossed = (along[:-1] < stop_along) & (along[1:] > stop_along) & near[1:] & (valid[:-1] & valid[1:])[..., None]
    red = jnp.isin(geo.state[1:][:, slot], jnp.asarray(STOP_STATES))  # [T-1, A, k]
    event = crossed & red & present[None]  # [T-1, A, k]
    rank = jnp.cumsum(event.reshape(-1), dtype=jnp.int32)  # events up to and including each position
    count = rank[-1]
    idx = jnp.searchsorted(rank, jnp.arange(1, max_events + 1, dtype=jnp.int32))  # the e-th event's position
    idx = jnp.minimum(idx, rank.shape[0] - 1)
    used = jnp.arange(max_events) < count
    t_i = idx // (a_n * k) + 1
    a_i = (idx // k) % a_n
    s_i = slot[a_i, idx % k]
    p = xy[t_i, a_i]  # [E, 2]
    # the lane the agent is on: the nearest of the lane segments around the stop point (its own lane among them)
    d_own = jnp.min(_distance(p, geo.own_a[s_i], geo.own_b[s_i], geo.own_ok[s_i]), -1)
    d_all = jnp.min(_distance(p, geo.cand_a[s_i], geo.cand_b[s_i], geo.cand_ok[s_i]), -1)
    on_lane = d_own <= jnp.minimum(d_all, d_own) + LANE_TIE_M
    out = jnp.zeros((t_n, a_n), bool).at[t_i, a_i].max(used & on_lane)
    # candidate crossings beyond the budget: counted as violations
    beyond_mask = event & (rank.reshape(event.shape) > max_events)
    out = out.at[1:].max(jnp.any(beyond_mask, -1))
    return out, (jnp.maximum(count - max_events, 0) + jnp.sum(crowded)).astype(jnp.int32)
