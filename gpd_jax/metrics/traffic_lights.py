"""The traffic-light violation feature of the 2025 WOSAC configuration (pure JAX, `jit` and `vmap` over rollouts).

Two rules, as the realism metric's (`gpd_jax.metrics.realism`): `rules="official"` reproduces the official code
(`official_lanes`, `official_signal_geometry`, `official_red_light_violation`; checked against it by
`tests/test_realism_conformance.py`), `rules="corrected"` (`signal_geometry`, `red_light_violation`) is the
definition below with its corrections. The official code (`waymo-open-dataset-tf-2-12-0==1.6.7`,
`traffic_light_features.py`) differs from it in: the lane an agent is on is the one with the nearest segment
by a distance that adds the projection where the true distance subtracts it (`official_segment_distance`;
a point near a segment's end can be "nearer" to the next lane's segment starting beside it), over lanes padded
with zeros whose last point joins the origin; a crossing needs validity at t only and may be anywhere along the
stop line's extension; only vehicles are scored. Its lanes are ids: the store holds each signal's lane as a
piece around the stop point beside the map's centrelines, so the official mode hands over the centreline
through the stop point as the signal's lane (`official_lanes`), the piece only where none passes within
`MATCH_M`; handed both, the official lane test would pick one of two copies of the same lane by where their
points fall.

Definition under the corrected rules (the official sim-agents metric's, facts in `reference/wosac.md`): an agent
violates a red light at frame t when all of these hold:

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

Where this differs from the official code (which has neither missing steps nor a budget), besides the lane
distance and the vehicles above:
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


def _first_crossings(event, slot, max_events: int):
    """The first `max_events` candidate crossings of `event bool[T-1, A, k]` (frame t + 1, agent, the agent's k
    signal slots `slot i32[A, k]`) in frame-major order: (frame i32[E] (1..T-1), agent i32[E], signal i32[E],
    used bool[E] (fewer events than E), beyond bool[T-1, A] (an agent's crossings past the budget, counted as
    violations), over i32[] (how many crossings are past it))."""
    _, a_n, k = event.shape
    rank = jnp.cumsum(event.reshape(-1), dtype=jnp.int32)  # events up to and including each flat position
    count = rank[-1]
    idx = jnp.searchsorted(rank, jnp.arange(1, max_events + 1, dtype=jnp.int32))  # the e-th event's position
    idx = jnp.minimum(idx, rank.shape[0] - 1)
    a_i = (idx // k) % a_n
    beyond = jnp.any(event & (rank.reshape(event.shape) > max_events), -1)
    return (idx // (a_n * k) + 1, a_i, slot[a_i, idx % k], jnp.arange(max_events) < count, beyond,
            jnp.maximum(count - max_events, 0))


def _violations(shape, t_i, a_i, ok, beyond):
    """bool[T, A]: the crossings (t_i, a_i) that are violations (`ok`), and every agent-frame `beyond` the budget."""
    return jnp.zeros(shape, bool).at[t_i, a_i].max(ok).at[1:].max(beyond)


def signal_geometry(signals: TrafficSignals, lanes, lane_valid,
                    num_candidates: int = NUM_CANDIDATES) -> SignalGeometry:
    """`SignalGeometry` of one scene: `signals` (unbatched, states on the scored frames) and the scene's lane
    centrelines `lanes f32[L, P, 2]`, `lane_valid bool[L, P]` (`Scene.polylines`, `polyline_valid`; None: the
    signals' own lanes only)."""
    if lanes is None:
        lanes, lane_valid = signals.lane, signals.lane_valid
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
    t_i, a_i, s_i, used, beyond, over = _first_crossings(event, slot, max_events)
    p = xy[t_i, a_i]  # [E, 2]
    # the lane the agent is on: the nearest of the lane segments around the stop point (its own lane among them)
    d_own = jnp.min(_distance(p, geo.own_a[s_i], geo.own_b[s_i], geo.own_ok[s_i]), -1)
    d_all = jnp.min(_distance(p, geo.cand_a[s_i], geo.cand_b[s_i], geo.cand_ok[s_i]), -1)
    on_lane = d_own <= jnp.minimum(d_all, d_own) + LANE_TIE_M
    out = _violations(valid.shape, t_i, a_i, used & on_lane, beyond)  # crossings past the budget count
    return out, (over + jnp.sum(crowded)).astype(jnp.int32)


# ------------------------------------------------------------------------------------------------ official rules
OFFICIAL_FAR = 1e10  # the official code's distance to a segment that is not one
OFFICIAL_RADIUS_M = 24.0  # segments within this of a signal's lane piece take part in its official lane test
OFFICIAL_CANDIDATES = 512  # at most this many of them per signal
OFFICIAL_MAX_EVENTS = 16  # candidate crossings per trajectory whose official lane test runs
OFFICIAL_SLOTS_PER_AGENT = 12  # signals looked at per agent: those whose piece its trajectory comes nearest
RADIUS_HALVINGS = 4  # the candidate radius tried: OFFICIAL_RADIUS_M, its half, ... (the largest that fits in C)
MATCH_M = 0.5  # a signal's lane is the scene's centreline passing this near its stop point (`official_lanes`)


@flax.struct.dataclass(frozen=True)
class OfficialSignalGeometry:
    """What the official rules' violation test needs of one scene's signals (`official_signal_geometry`).

    The lanes are those the official code is handed (`official_lanes`; `tests/conformance/run_official.py`,
    `rollout.py --export-official`); the official code pads them with zeros to the longest and takes a segment
    wherever its first point is valid (the last point of a shorter lane joined to the origin), as here.

    Attributes:
      state: i32[T, S] the states; present: bool[S] signals handed over (a piece of at least 2 points).
      stop: f32[S, 2]; fence_a, fence_d: f32[S, 2] the start and (end - start) of the signal lane's segment
        nearest the stop point under the official nearest-segment rule (`official_segment_distance`); stop_t:
        f32[S] the stop point's coordinate along it (units of the segment).
      box_lo, box_hi: f32[S, 2] the bounding box of each signal's piece (its lane around the stop point).
      cand_a, cand_b: f32[S, C, 2], cand_ok: bool[S, C], cand_own: bool[S, C] (a segment of the signal's lane):
        the C segments whose bounding boxes come nearest each piece's box, in the official order of all segments
        (lanes, then points); radius: f32[S] every segment within this of the piece's box is among them
        (`OFFICIAL_RADIUS_M`, halved until they fit in C; 0 where they never do).
    """

    state: jax.Array
    present: jax.Array
    stop: jax.Array
    fence_a: jax.Array
    fence_d: jax.Array
    stop_t: jax.Array
    box_lo: jax.Array
    box_hi: jax.Array
    cand_a: jax.Array
    cand_b: jax.Array
    cand_ok: jax.Array
    cand_own: jax.Array
    radius: jax.Array


def official_segment_distance(p, a, b, ok):
    """f32[..., N]: the official code's distance of points p f32[..., 2] to segments (a, b f32[..., N, 2]) when it
    seeks the lane an agent is on: |p - a + t (b - a)|, t the projection clipped to [0, 1] (0 on a segment of no
    length). The official code adds the projection where the true distance subtracts it: its value is the
    distance to the projection mirrored through the segment's start (the true one where t = 0, more elsewhere).
    `OFFICIAL_FAR` where not `ok`."""
    d = b - a
    ap = p[..., None, :] - a
    den = jnp.sum(d * d, -1)
    t = jnp.clip(jnp.where(den > 0, jnp.sum(ap * d, -1) / jnp.where(den > 0, den, 1.0), 0.0), 0.0, 1.0)
    return jnp.where(ok, jnp.linalg.norm(ap + d * t[..., None], axis=-1), OFFICIAL_FAR)


def _box_gap(lo1, hi1, lo2, hi2):
    """Distance between axis-aligned boxes (0 where they overlap)."""
    gap = jnp.maximum(0.0, jnp.maximum(lo1 - hi2, lo2 - hi1))
    return jnp.linalg.norm(gap, axis=-1)


def official_lanes(signals: TrafficSignals, lanes=None, lane_valid=None):
    """The lanes and signal lanes the official code is handed for one scene (the export and the official rules
    read the same): the scene's lane centrelines, then each signal slot's lane piece; a signal's lane is the
    centreline that passes within `MATCH_M` of its stop point (the nearest; the first slot to claim a
    centreline keeps it), else its own piece. Rows with fewer than 2 points are not handed over (the official
    code skips them), nor the pieces of signals on a centreline.

    Args: `signals` (unbatched), `lanes f32[L, P, 2]`, `lane_valid bool[L, P]` (valid points a prefix; None:
    no centrelines). Returns (points f32[L + S, W, 2] (zero where not valid), valid bool[L + S, W] (the rows
    handed over; W = max(P, Q)), signal_row i32[S] (each signal's lane row), present bool[S] (signals handed
    over: a piece of at least 2 points)).
    """
    pieces, piece_valid = signals.lane.astype(jnp.float32), signals.lane_valid
    s_n = pieces.shape[0]
    if lanes is None:
        lanes, lane_valid = jnp.zeros((0, 2, 2), jnp.float32), jnp.zeros((0, 2), bool)
    l_n = lanes.shape[0]
    w = max(pieces.shape[1], lanes.shape[1])
    pad = lambda x: jnp.pad(x, ((0, 0), (0, w - x.shape[1])) + ((0, 0),) * (x.ndim - 2))  # noqa: E731
    present = jnp.sum(piece_valid, -1) >= 2
    stop = signals.stop.astype(jnp.float32)
    la, lb, lok = _segments(lanes.astype(jnp.float32), lane_valid)
    near = jnp.min(_distance(stop[:, None, :], la[None], lb[None], lok[None]), -1) if l_n else \
        jnp.full((s_n, 1), jnp.inf)  # [S, L]
    row = jnp.argmin(near, -1).astype(jnp.int32)
    claim = present & (jnp.min(near, -1) <= MATCH_M)
    earlier = (row[:, None] == row[None, :]) & claim[None, :] & (jnp.arange(s_n)[None, :] < jnp.arange(s_n)[:, None])
    on_lane = claim & ~jnp.any(earlier, -1)
    pts = jnp.concatenate([pad(lanes.astype(jnp.float32)), pad(pieces)])
    valid = jnp.concatenate([pad(lane_valid), pad(piece_valid & (present & ~on_lane)[:, None])])
    valid = valid & (jnp.sum(valid, -1) >= 2)[:, None]
    return (jnp.where(valid[..., None], pts, 0.0), valid,
            jnp.where(on_lane, row, l_n + jnp.arange(s_n, dtype=jnp.int32)), present)


def official_signal_geometry(signals: TrafficSignals, lanes=None, lane_valid=None,
                             num_candidates: int = OFFICIAL_CANDIDATES) -> OfficialSignalGeometry:
    """`OfficialSignalGeometry` of one scene: `signals` (unbatched, states on the scored frames) and the scene's
    lane centrelines `lanes f32[L, P, 2]`, `lane_valid bool[L, P]` (`official_lanes`)."""
    pts, valid, sig_row, present = official_lanes(signals, lanes, lane_valid)
    w = pts.shape[1]
    longest = jnp.max(jnp.sum(valid, -1))
    a, b = pts[:, :-1], pts[:, 1:]  # [R, W - 1]: padding joins a shorter lane's last point to the origin
    ok = valid[:, :-1] & (jnp.arange(1, w) < longest)[None]
    # each signal lane's segment nearest its stop point (the official "fence"), and the stop point along it
    stop = signals.stop.astype(jnp.float32)
    sa, sb, sok = a[sig_row], b[sig_row], ok[sig_row]
    k = jnp.argmin(official_segment_distance(stop, sa, sb, sok), -1)
    fence_a = jnp.take_along_axis(sa, k[:, None, None], 1)[:, 0]
    fence_d = jnp.take_along_axis(sb, k[:, None, None], 1)[:, 0] - fence_a
    den = jnp.sum(fence_d * fence_d, -1)
    stop_t = jnp.where(den > 0, jnp.sum((stop - fence_a) * fence_d, -1) / jnp.where(den > 0, den, 1.0), 0.0)
    # the segments around each signal's piece (its lane around the stop point), in the official order
    big = jnp.float32(OFFICIAL_FAR)
    pv = signals.lane_valid[..., None]
    box_lo = jnp.min(jnp.where(pv, signals.lane, big), 1)
    box_hi = jnp.max(jnp.where(pv, signals.lane, -big), 1)
    fa, fb, fok = a.reshape(-1, 2), b.reshape(-1, 2), ok.reshape(-1)
    gap = _box_gap(box_lo[:, None], box_hi[:, None], jnp.minimum(fa, fb)[None], jnp.maximum(fa, fb)[None])
    gap = jnp.where(fok[None], gap, jnp.inf)  # [S, N]
    n = fok.shape[0]
    c = min(num_candidates, n)
    # the largest of the radii whose segments fit in C slots; they are kept in the official order (its argmin
    # keeps the first of equal distances)
    radii = OFFICIAL_RADIUS_M / 2.0 ** jnp.arange(RADIUS_HALVINGS, dtype=jnp.float32)  # [R]
    fits = jnp.sum(gap[:, None, :] <= radii[None, :, None], -1) <= c  # [S, R]
    radius = jnp.max(jnp.where(fits, radii, 0.0), -1)
    idx = jax.vmap(lambda m: jnp.nonzero(m, size=c, fill_value=n - 1)[0])(gap <= radius[:, None])  # [S, C]
    inside = jnp.take_along_axis(gap, idx, 1) <= radius[:, None]
    lane_of = jnp.repeat(jnp.arange(pts.shape[0], dtype=jnp.int32), w - 1)
    return OfficialSignalGeometry(
        state=signals.state, present=present, stop=stop, fence_a=fence_a, fence_d=fence_d, stop_t=stop_t,
        box_lo=box_lo, box_hi=box_hi, cand_a=fa[idx], cand_b=fb[idx], cand_ok=fok[idx] & inside,
        cand_own=lane_of[idx] == sig_row[:, None], radius=radius)


def official_red_light_violation(xy, valid, geo: OfficialSignalGeometry, max_events: int = OFFICIAL_MAX_EVENTS,
                                 slots_per_agent: int = OFFICIAL_SLOTS_PER_AGENT):
    """Where each agent runs a red light under the official rules, for one trajectory set of one scene.

    The official definition (`waymo_open_dataset.wdl_limited.sim_agents_metrics.traffic_light_features`, 1.6.7):
    at frame t the agent is valid, the lane nearest to it (`official_segment_distance`, the first of equal ones)
    is a signal's lane, that signal's state is a stop state, and between t - 1 and t (whatever its validity at
    t - 1) its coordinate along the signal's fence segment went from below the stop point's to above it.

    The lane test runs for the first `max_events` candidate crossings (valid, crossing, stop state) of the
    trajectory in frame-major order whose agent is within half of `geo.radius` (12 m, 6 m where the map is too
    dense for 24 m) of the box of the signal's piece, against the segments within that radius of the box: exact
    where the nearest of them is nearer than (radius - the agent's gap to the box), which no segment left out
    can be (the official distance is never below the true one); counted in `inexact` (not a violation)
    otherwise. Crossings beyond the budget are counted as violations and in `inexact`. Per agent only the
    `slots_per_agent` signals whose piece its trajectory's bounding box comes nearest (within half the radius)
    are looked at; an agent near more of them counts in `inexact`. The one approximation:
    a crossing whose agent is farther from the box than half the radius is not a violation (the official code
    calls it one only where the agent's nearest lane is still the signal's: off every lane by that much).

    Args: xy f32[T, A, 2], valid bool[T, A] (the frames of `geo.state`). Returns (violation bool[T, A] (False at
    frame 0), inexact i32[]).
    """
    k = min(slots_per_agent, geo.stop.shape[0])
    # per agent, the signals whose piece's box its trajectory's box (valid frames) comes within half the radius
    # of, nearest first: the crossing test runs on [T, A, k] instead of [T, A, S]
    pv, vv = xy[1:], valid[1:]
    t_lo = jnp.min(jnp.where(vv[..., None], pv, OFFICIAL_FAR), 0)  # [A, 2]
    t_hi = jnp.max(jnp.where(vv[..., None], pv, -OFFICIAL_FAR), 0)
    g = jnp.maximum(0.0, jnp.maximum(geo.box_lo[None] - t_hi[:, None], t_lo[:, None] - geo.box_hi[None]))
    d2 = jnp.sum(g * g, -1)  # [A, S]
    ever_red = jnp.any(jnp.isin(geo.state[1:], jnp.asarray(STOP_STATES)), 0) & geo.present
    near_any = ever_red[None] & (d2 < (geo.radius / 2) ** 2)
    neg, slot = jax.lax.top_k(-jnp.where(near_any, d2, jnp.inf), k)  # [A, k]
    crowded = jnp.sum(near_any, -1) > k
    fa, fd, stop_t = geo.fence_a[slot], geo.fence_d[slot], geo.stop_t[slot]  # [A, k, ...]
    den = jnp.sum(fd * fd, -1)
    along = jnp.sum((xy[:, :, None, :] - fa) * fd, -1)  # [T, A, k]
    along = jnp.where(den > 0, along / jnp.where(den > 0, den, 1.0), 0.0)
    crossed = (along[:-1] < stop_t) & (along[1:] > stop_t)
    red = jnp.isin(geo.state[1:][:, slot], jnp.asarray(STOP_STATES)) & jnp.isfinite(neg)  # [T-1, A, k]
    # within half the radius of the piece's box (squared, per axis: the box gap without its square root)
    lo, hi, p = geo.box_lo[slot], geo.box_hi[slot], xy[1:, :, None, :]
    g = jnp.maximum(0.0, jnp.maximum(lo - p, p - hi))
    near = jnp.sum(g * g, -1) < (geo.radius[slot] / 2) ** 2
    event = crossed & red & valid[1:, :, None] & near
    t_i, a_i, s_i, used, beyond, over = _first_crossings(event, slot, max_events)
    d = official_segment_distance(xy[t_i, a_i], geo.cand_a[s_i], geo.cand_b[s_i], geo.cand_ok[s_i])  # [E, C]
    nearest = jnp.argmin(d, -1)
    on_lane = jnp.take_along_axis(geo.cand_own[s_i], nearest[:, None], 1)[:, 0]
    # a segment left out is farther than the radius from the piece's box, so at least (radius - the agent's gap
    # to that box) from the agent (the official distance is never below the true one): the nearest candidate is
    # the nearest segment of all where it is nearer than that
    gap = _box_gap(xy[t_i, a_i], xy[t_i, a_i], geo.box_lo[s_i], geo.box_hi[s_i])
    certain = jnp.take_along_axis(d, nearest[:, None], 1)[:, 0] + gap < geo.radius[s_i]
    out = _violations(valid.shape, t_i, a_i, used & on_lane & certain, beyond)
    return out, (over + jnp.sum(used & ~certain) + jnp.sum(crowded)).astype(jnp.int32)
