"""Distributional realism of sampled rollouts in the form of the Waymo Open Sim Agents Challenge (WOSAC).

The WOSAC meta-metric judges a traffic model by many sampled futures of a scenario (32 rollouts of 8 s at 10 Hz):
for each feature below and each evaluated agent, the simulated values form a histogram (a Bernoulli for the
indicator features), the logged value's log-likelihood under it is averaged, exponentiated into [0, 1], and the
meta-metric is the weighted sum of the nine (2025: ten) likelihoods. The definitions follow the challenge's
published configuration and metric definitions (facts in `reference/wosac.md`); this is an independent, pure-JAX
implementation: `jit`, `vmap` over scenarios, no TensorFlow.

Features, per agent and future frame (`realism_features`; 10 Hz frames, `dt` = 0.1 s):

* **kinematics**: linear speed |central difference of the position| / dt, linear acceleration (central difference
  of the speed), angular speed (central difference of the heading, wrapped as the official code does: the
  two-step change is wrapped to [-pi, pi) before halving), angular acceleration. Computed over history and future
  together, so the first future frame has a difference; valid where both neighbours are valid (twice for
  accelerations; the official rules judge validity on the future frames alone, below).
* **distance to the nearest object**: signed distance between boxes with rounded corners (each box shrunk by
  `CORNER_ROUNDING_FACTOR` x half its smaller side, the distance between the shrunk "cores", minus both shrink
  radii; negative = overlap), against every other valid agent; **collision** where it is below 0.
* **time to collision** with the object ahead (the official "following" rule: ahead of the front, lateral
  overlap with the agent's straight trail, heading difference <= 75 deg, or <= 10 deg where the lateral overlap
  is under 0.5 m), at constant speeds, capped at 5 s.
* **distance to the road edge**: the most off-road of the box's four corners, signed like WOSAC (negative on the
  road, positive off it), from the scene's road-edge polylines (`Scene.road`). The official rule needs edges
  oriented with the road on their left; stores of format 2 carry the map's edges so (`RoadGeometry.map_edges`,
  read as they are); older stores' edges carry no orientation, so each polyline is oriented
  here by which side of it is drivable (`gpd_jax.geometry.on_road` probes beside every segment, majority vote);
  segments drivable on both sides (interior lines of real-road tiles) and slivers under 1 m are not edges.
  The sign of a point whose nearest edge point is a polyline vertex follows the official convexity rule.
  **Offroad** where it is above 0.

Likelihoods (`realism_metrics`, one scenario; `vmap` for many):

* histograms with the configuration's range, bins and pseudocount; the simulated values of an agent are pooled
  over its K rollouts and all future frames (`independent_timesteps`, true for every feature of both
  configurations); values outside the range are clipped into the end bins;
* per feature, the log-likelihood of the logged value is averaged over every (evaluated agent, frame) where the
  log has the feature (log validity as above), and exponentiated (the official scene-level reduction);
* collision and offroad: per agent "any over the frames where the log is valid", Bernoulli with pseudocount
  0.001, averaged over evaluated agents, exponentiated;
* meta-metric: the weighted sum over the features present. The 2025 configuration's traffic-light violation
  term (`gpd_jax.metrics.traffic_lights`, a Bernoulli of "any red light run" like collision) is scored where the
  store has traffic-signal states (`Scene.signals`, store format 2) and left out elsewhere; scenes without road
  geometry leave out the two map-based terms. The weights of what is left are renormalised to sum to 1 and
  `realism_weights` says which terms were used (what `reduce_realism` reports as `left_out`).
* minADE: the mean over evaluated agents of each rollout's average displacement error (over the frames the log
  has), minimum over the K rollouts; ADE: the same averaged over rollouts. Also the simulated collision and
  offroad rates (share of (rollout, agent) pairs with at least one such frame).

Counting rules (`rules=`, `RULES`), the same features and estimators under both:

* **"official"** reproduces the official code (`waymo-open-dataset-tf-2-12-0==1.6.7`, checked scene by scene in
  `tests/test_realism_conformance.py`): the simulated agents are those valid in the log at the current frame,
  each present at every future frame of every rollout (the official format has no per-step validity; where a
  rollout, a baseline or the log lacks one, `continue_missing` continues it at constant velocity from its last
  state), with the log's history; every simulated value counts in the histograms, the NaN padding of the central
  differences (the last future frame for speeds, the last two for accelerations) in the top bin, as
  `tfp.stats.histogram` puts NaN; the log's kinematic validity is computed on the future frames alone, so the
  first future frame is never scored for speeds nor the first two for accelerations; time to collision is
  scored for vehicles only (`agent_type`); ADE averages each agent's error over the log's valid frames with the
  history's (zero error) counted, the official format's 11 history frames (`OFFICIAL_HISTORY_FRAMES`; the
  features reach back two frames only).
* **"corrected"** (the metric as it was before the official mode) counts only what a rollout has: simulated
  values where the rollout has the agent and the value is finite; kinematic validity over history and future
  together (the first future frame has a speed); time to collision of every agent; ADE over the log's future
  frames.

Under both, a scenario with no evaluated agent gives NaN (left out by `reduce_realism`, which counts them).
Values within float rounding of a histogram bin edge may fall on either side of it in either implementation.

Model frame rates other than 10 Hz: the features are defined on 10 Hz trajectories. A model that predicts a frame
every `stride` stored frames is brought to 10 Hz by `upsample_frames` (cubic Hermite interpolation of the
positions and the unwrapped headings between model frames, validity where both neighbouring model frames are
valid), and the log is scored at its own 10 Hz. Baselines at the model's rate go through the same interpolation,
so comparisons stay fair; the absolute figures of a 1 Hz model include the interpolation's smoothness.

Shapes: `f32[..., T, A]` (frames, agents) as in `gpd_jax.scene.Scene`; K rollouts lead: `f32[K, T, A, 2]`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from gpd_jax.geometry import RoadGeometry, TrafficSignals, on_road
from gpd_jax.metrics.agents import box_corners
from gpd_jax.metrics.traffic_lights import (OfficialSignalGeometry, SignalGeometry, official_lanes,
                                            official_red_light_violation, official_signal_geometry,
                                            red_light_violation, signal_geometry)
from gpd_jax.scene import TYPE_ID, backward_difference, wrap_angle

# ------------------------------------------------------------------------------------------------ constants
CORNER_ROUNDING_FACTOR = 0.7  # 0: sharp rectangles, 1: capsules
MAX_TTC_S = 5.0
TTC_MAX_HEADING_DIFF = math.radians(75.0)
TTC_MAX_HEADING_DIFF_SMALL_OVERLAP = math.radians(10.0)
TTC_SMALL_OVERLAP_M = 0.5
FAR = 1e10  # the distance of "no other object" / "no road edge" (clipped into the top bin)
# Road-edge search (`road_edge_distance`): per (rollout, agent, chunk of EDGE_CHUNK_FRAMES frames) the
# EDGE_CANDIDATES segments nearest to the chunk's bounding box; `realism_metrics` reports how often an answer was
# not provably the nearest segment's ("road_edge_inexact_share": 0 on the SUMO test store at these settings).
EDGE_CANDIDATES = 32
EDGE_CHUNK_FRAMES = 10


@dataclasses.dataclass(frozen=True)
class FeatureConfig:
    """How one feature is scored. `estimator` "histogram" (range [min_val, max_val], `num_bins`) or "bernoulli"."""

    estimator: str
    weight: float
    min_val: float = 0.0
    max_val: float = 1.0
    num_bins: int = 2
    pseudocount: float = 0.001
    independent_timesteps: bool = True


def _hist(lo, hi, bins, weight):
    return FeatureConfig("histogram", weight, lo, hi, bins, 0.1)


# name -> bucket, in the official order
FEATURES = {
    "linear_speed": "kinematic", "linear_acceleration": "kinematic", "angular_speed": "kinematic",
    "angular_acceleration": "kinematic", "distance_to_nearest_object": "interactive",
    "collision_indication": "interactive", "time_to_collision": "interactive",
    "distance_to_road_edge": "map_based", "offroad_indication": "map_based",
    "traffic_light_violation": "map_based",
}
MAP_FEATURES = ("distance_to_road_edge", "offroad_indication")
SIGNAL_FEATURES = ("traffic_light_violation",)
# The counting rules (`scenario_realism(..., rules=)`): "official" reproduces the official code's, "corrected" counts
# only what a rollout has (module docstring). Reports name the rules they used.
RULES = ("official", "corrected")
OFFICIAL_HISTORY_FRAMES = 11  # the official format's history (current index 10): what its ADE counts

_COMMON = {
    "linear_speed": _hist(0.0, 25.0, 10, 0.05),
    "linear_acceleration": _hist(-12.0, 12.0, 11, 0.05),
    "angular_speed": _hist(-0.628, 0.628, 11, 0.05),
    "angular_acceleration": _hist(-3.14, 3.14, 11, 0.05),
    "distance_to_nearest_object": _hist(-5.0, 40.0, 10, 0.10),
    "collision_indication": FeatureConfig("bernoulli", 0.25),
    "time_to_collision": _hist(0.0, 5.0, 10, 0.10),
    "offroad_indication": FeatureConfig("bernoulli", 0.25),
}
# The challenge configurations (2024: nine terms; 2025: road edge 0.05 and traffic-light violation 0.05).
CONFIGS: dict[str, Mapping[str, FeatureConfig]] = {
    "2024": {**_COMMON, "distance_to_road_edge": _hist(-20.0, 40.0, 10, 0.10)},
    "2025": {**_COMMON, "distance_to_road_edge": _hist(-20.0, 40.0, 10, 0.05),
             "traffic_light_violation": FeatureConfig("bernoulli", 0.05)},
}


def realism_config(name: str) -> Mapping[str, FeatureConfig]:
    if name not in CONFIGS:
        raise ValueError(f"realism configuration {name!r}: expected one of {sorted(CONFIGS)}")
    return CONFIGS[name]


def realism_weights(config: str, has_road: bool = True, has_signals: bool = False) -> dict[str, float]:
    """The meta-metric's weights of `config` over the terms that can be scored, renormalised to sum to 1.

    Terms left out: traffic-light violation without signal states (`Scene.signals` None), the map-based terms
    without road geometry. `left_out_terms` names them.
    """
    cfg = realism_config(config)
    used = {k: c.weight for k, c in cfg.items() if k not in left_out_terms(config, has_road, has_signals)}
    total = sum(used.values())
    return {k: w / total for k, w in used.items()}


def left_out_terms(config: str, has_road: bool = True, has_signals: bool = False) -> tuple[str, ...]:
    cfg = realism_config(config)
    out = [k for k in cfg if (k in SIGNAL_FEATURES and not has_signals) or (k in MAP_FEATURES and not has_road)]
    return tuple(out)


# ------------------------------------------------------------------------------------------------ features
@flax.struct.dataclass(frozen=True)
class RealismFeatures:
    """Per-frame realism features of the future frames (F of them) of one trajectory set (or a batch: `...`).

    Attributes (all `[..., F, A]`):
      valid: bool whether the agent exists at the frame.
      speed_valid, accel_valid: bool where the kinematic differences have both neighbours (once, twice).
      linear_speed (m/s), linear_acceleration (m/s^2), angular_speed (rad/s), angular_acceleration (rad/s^2): f32.
      distance_to_nearest_object: f32 metres between rounded boxes (negative: overlap; `FAR` without another).
      collision: bool distance below 0.
      time_to_collision: f32 seconds, at most `MAX_TTC_S`.
      distance_to_road_edge: f32 metres, most off-road corner, positive off the road (`FAR` and offroad False
        where the scene has no road geometry).
      offroad: bool distance above 0.
      edge_inexact: bool where the road-edge candidate search could not prove its answer exact.
      red_light: optional bool, where the agent runs a red light (`gpd_jax.metrics.traffic_lights`); None for
        scenes without traffic-signal states.
    """

    valid: jax.Array
    speed_valid: jax.Array
    accel_valid: jax.Array
    linear_speed: jax.Array
    linear_acceleration: jax.Array
    angular_speed: jax.Array
    angular_acceleration: jax.Array
    distance_to_nearest_object: jax.Array
    collision: jax.Array
    time_to_collision: jax.Array
    distance_to_road_edge: jax.Array
    offroad: jax.Array
    edge_inexact: jax.Array
    red_light: jax.Array | None = None


def _central_diff(x):
    """[T, ...] -> [T, ...]: (x[t+1] - x[t-1]) / 2, NaN at both ends."""
    nan = jnp.full_like(x[:1], jnp.nan)
    return jnp.concatenate([nan, (x[2:] - x[:-2]) / 2, nan], axis=0)


def _central_and(v):
    false = jnp.zeros_like(v[:1])
    return jnp.concatenate([false, v[2:] & v[:-2], false], axis=0)


def kinematics(xy: jax.Array, heading: jax.Array, valid: jax.Array, dt: float):
    """Linear / angular speed and acceleration of `xy f32[T, A, 2]`, `heading f32[T, A]` by central differences.

    Returns (speed, accel, angular_speed, angular_accel, speed_valid, accel_valid), each `[T, A]`.
    """
    speed = jnp.linalg.norm(_central_diff(xy), axis=-1) / dt
    accel = _central_diff(speed) / dt
    dh_step = wrap_angle(_central_diff(heading) * 2) / 2
    d2h_step = wrap_angle(_central_diff(dh_step) * 2) / 2
    speed_valid = _central_and(valid)
    return speed, accel, dh_step / dt, d2h_step / dt ** 2, speed_valid, _central_and(speed_valid)


def box_signed_distance(xy_a, h_a, half_a, xy_b, h_b, half_b):
    """Signed distance between oriented rectangles A and B (broadcasting leading dims; negative = overlap).

    `xy f32[..., 2]`, `h f32[...]`, `half f32[..., 2]` (half length, half width). Separated boxes: the Euclidean
    distance, reached between a corner of one box and the other box. Overlapping boxes: minus the penetration
    depth, the largest gap over the four separating axes (the distance from the origin to the boundary of the
    Minkowski difference, as the official definition computes it). Written on scalar components so the pairwise
    computation fuses into one loop.
    """
    ca, sa, cb, sb = jnp.cos(h_a), jnp.sin(h_a), jnp.cos(h_b), jnp.sin(h_b)
    la, wa, lb, wb = half_a[..., 0], half_a[..., 1], half_b[..., 0], half_b[..., 1]
    dx, dy = xy_b[..., 0] - xy_a[..., 0], xy_b[..., 1] - xy_a[..., 1]
    c, s = cb * ca + sb * sa, sb * ca - cb * sa  # cos, sin of h_b - h_a
    ac, as_ = jnp.abs(c), jnp.abs(s)
    px, py = dx * ca + dy * sa, -dx * sa + dy * ca  # B's centre in A's frame
    qx, qy = -(dx * cb + dy * sb), dx * sb - dy * cb  # A's centre in B's frame
    sat = jnp.maximum(
        jnp.maximum(jnp.abs(px) - la - (lb * ac + wb * as_), jnp.abs(py) - wa - (lb * as_ + wb * ac)),
        jnp.maximum(jnp.abs(qx) - lb - (la * ac + wa * as_), jnp.abs(qy) - wb - (la * as_ + wa * ac)))

    def corner_sq(cx, cy, ex, ey, fx, fy, hx, hy):  # min squared distance of the 4 corners c +- e +- f to box h
        best = None
        for se in (1.0, -1.0):
            for sf in (1.0, -1.0):
                gx = jnp.maximum(jnp.abs(cx + se * ex + sf * fx) - hx, 0.0)
                gy = jnp.maximum(jnp.abs(cy + se * ey + sf * fy) - hy, 0.0)
                d2 = gx * gx + gy * gy
                best = d2 if best is None else jnp.minimum(best, d2)
        return best

    # B's half axes in A's frame: lb (c, s), wb (-s, c); A's in B's frame: la (c, -s), wa (s, c)
    sep2 = jnp.minimum(corner_sq(px, py, lb * c, lb * s, -wb * s, wb * c, la, wa),
                       corner_sq(qx, qy, la * c, -la * s, wa * s, wa * c, lb, wb))
    return jnp.where(sat < 0, sat, jnp.sqrt(sep2))


def nearest_object_distance(xy, heading, valid, size, rounding: float = CORNER_ROUNDING_FACTOR):
    """f32[..., A]: each agent's signed distance to the nearest other valid agent (rounded boxes; `FAR` if none).

    `xy f32[..., A, 2]`, `heading f32[..., A]`, `valid bool[..., A]`, `size f32[..., A, 2]` (length, width).
    """
    shrink = jnp.min(size, axis=-1) * rounding / 2  # [..., A]
    half = size / 2 - shrink[..., None]
    d = box_signed_distance(xy[..., :, None, :], heading[..., :, None], half[..., :, None, :],
                            xy[..., None, :, :], heading[..., None, :], half[..., None, :, :])
    d = d - shrink[..., :, None] - shrink[..., None, :]
    a = xy.shape[-2]
    ok = valid[..., :, None] & valid[..., None, :] & ~jnp.eye(a, dtype=bool)
    return jnp.min(jnp.where(ok, d, FAR), axis=-1)


def time_to_collision(xy, heading, speed, valid, size):
    """f32[..., A]: seconds until each agent reaches the object it follows at constant speeds (cap `MAX_TTC_S`).

    The followed object: valid, ahead of the agent's front, overlapping the agent's straight trail laterally,
    heading within 75 deg (10 deg where the lateral overlap is under 0.5 m); the nearest such one. The heading
    difference is not wrapped, as in the official code.
    """
    hi, hj = heading[..., :, None], heading[..., None, :]
    yaw_diff = jnp.abs(hj - hi)  # [..., i, j]
    cos_d, sin_d = jnp.abs(jnp.cos(yaw_diff)), jnp.abs(jnp.sin(yaw_diff))
    lj, wj = size[..., None, :, 0] / 2, size[..., None, :, 1] / 2
    dx = xy[..., None, :, 0] - xy[..., :, None, 0]
    dy = xy[..., None, :, 1] - xy[..., :, None, 1]
    c, s = jnp.cos(hi), jnp.sin(hi)
    long_dist = dx * c + dy * s - size[..., :, None, 0] / 2 - (lj * cos_d + wj * sin_d)
    lat_overlap = jnp.abs(-dx * s + dy * c) - size[..., :, None, 1] / 2 - (lj * sin_d + wj * cos_d)
    following = ((long_dist > 0) & (yaw_diff <= TTC_MAX_HEADING_DIFF) & (lat_overlap < 0)
                 & ((lat_overlap < -TTC_SMALL_OVERLAP_M) | (yaw_diff <= TTC_MAX_HEADING_DIFF_SMALL_OVERLAP))
                 & valid[..., None, :])  # the official code masks by the other's validity only
    masked = jnp.where(following, long_dist, FAR)
    dist = jnp.min(masked, axis=-1)
    # the speed of the nearest followed object (first index among ties, as argmin)
    a = xy.shape[-2]
    first = jnp.min(jnp.where(masked == dist[..., None], jnp.arange(a), a), axis=-1)
    ahead_speed = jnp.sum(jnp.where(jnp.arange(a) == first[..., None], speed[..., None, :], 0.0), axis=-1)
    rel_speed = speed - ahead_speed
    closing = rel_speed > 0  # False for NaN speeds (the last frame's central difference)
    return jnp.where(closing, jnp.minimum(dist / jnp.where(closing, rel_speed, 1.0), MAX_TTC_S), MAX_TTC_S)


# ------------------------------------------------------------------------------------------------ road edges
@flax.struct.dataclass(frozen=True)
class OrientedEdges:
    """Road-edge segments with the road on their left (what the official signed distance needs).

    Attributes:
      a, b: f32[S, 2] segment starts and ends (scene frame); ok: bool[S] which exist.
      prior, next: i32[S] the neighbouring segment in the polyline (itself at an open end, wrapping when closed).
      convex_before, convex_after: bool[S] whether the polyline turns left at the segment's start / end.
      dropped: i32[] existing segments left out by `max_segments` (then distances may be wrong: reported inexact).
    """

    a: jax.Array
    b: jax.Array
    ok: jax.Array
    prior: jax.Array
    next: jax.Array
    convex_before: jax.Array
    convex_after: jax.Array
    dropped: jax.Array


def _cross(u, v):
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def orient_edges(road: RoadGeometry, max_segments: int | None = None, probe_m: float = 0.05,
                 min_length_m: float = 1.0, official: bool = False) -> OrientedEdges:
    """The unbatched `road`'s edge polylines as segments with the drivable area on their left.

    Each polyline is reversed where most of its segments have the drivable area (`on_road`) on their right
    (probes `probe_m` either side of each segment's midpoint); segments with the drivable area on both sides or on
    neither are left out (not edges of the road; they still serve as a vertex's neighbour in the sign rule), and
    so are polylines shorter than `min_length_m` in all.
    Valid points of a polyline must be a prefix.
    `max_segments` (static): keep only that many segment slots, the existing ones first (stores pad their edge
    arrays heavily; `edge_segment_budget` picks a count that keeps them all) -- the distance search costs in
    proportion to it.
    A road with map edges (`RoadGeometry.map_edges`, stores of format 2) gives them as they are: oriented by the
    store, drivable side on their left (`gpd_jax.data.roadgeom`); nothing is probed or left out.
    `official`: the neighbours at the ends of the polylines as the official code has them (`_official_neighbours`:
    what it makes of `edge_polylines`), which decide the sign of a point nearest to such an end.
    """
    oriented = road.map_edges is not None
    pts = (road.map_edges if oriented else road.edges).astype(jnp.float32)
    pv = road.map_edge_valid if oriented else road.edge_valid
    e, p = pv.shape
    a, b = pts[:, :-1], pts[:, 1:]
    ok = pv[:, :-1] & pv[:, 1:]
    t = b - a
    length = jnp.linalg.norm(t, axis=-1)
    ok = ok & (length > 1e-6)
    if oriented:
        flip = jnp.zeros((e,), bool)
    else:
        n_left = jnp.stack([-t[..., 1], t[..., 0]], -1) / jnp.maximum(length, 1e-6)[..., None]
        mid = (a + b) / 2
        left = on_road(road, mid + probe_m * n_left)
        right = on_road(road, mid - probe_m * n_left)
        # a segment with the drivable area on both sides (or neither) bounds nothing: stores' edges include such
        # interior lines on real-road tiles, and a distance to them is no distance to the road's edge
        ok = ok & (left != right)
        # so are slivers: polylines shorter than `min_length_m` (artifacts of the areas' union), whose open ends
        # would lend their side to points far along their line
        ok = ok & (jnp.sum(jnp.where(ok, length, 0.0), -1, keepdims=True) >= min_length_m)
        vote = jnp.sum(jnp.where(ok, left.astype(jnp.int32) - right.astype(jnp.int32), 0), -1)
        flip = vote < 0  # [E]
    # reversing a polyline: segment k becomes the reverse of segment S-1-k
    a_r, b_r, ok_r = b[:, ::-1], a[:, ::-1], ok[:, ::-1]
    a = jnp.where(flip[:, None, None], a_r, a)
    b = jnp.where(flip[:, None, None], b_r, b)
    ok = jnp.where(flip[:, None], ok_r, ok)
    s = p - 1
    idx = jnp.arange(s)
    has = jnp.any(ok, -1)
    first = jnp.argmax(ok, -1)
    last = s - 1 - jnp.argmax(ok[:, ::-1], -1)
    start = jnp.take_along_axis(a, first[:, None, None], 1)[:, 0]
    end = jnp.take_along_axis(b, last[:, None, None], 1)[:, 0]
    # Neighbours across polyline ends: a polyline closes on itself when its ends are within 1 m (the official
    # rule), and continues into another polyline that starts where it ends (stores cut long edges into pieces);
    # the sign rule at a vertex needs the segment on the other side of it.
    gid = jnp.arange(e)[:, None] * s + idx[None]  # [E, S] index into the flattened segments
    first_g, last_g = jnp.arange(e) * s + first, jnp.arange(e) * s + last
    d2 = jnp.sum((end[:, None] - start[None]) ** 2, -1)  # [i, j]: end of i to start of j
    tol = jnp.where(jnp.eye(e, dtype=bool), 1.0, 1e-4)
    d2 = jnp.where(has[:, None] & has[None] & (d2 < tol), d2, jnp.inf)
    succ, pred = jnp.argmin(d2, 1), jnp.argmin(d2, 0)
    next_end = jnp.where(jnp.isfinite(jnp.min(d2, 1)), first_g[succ], last_g)  # after the last segment
    prior_start = jnp.where(jnp.isfinite(jnp.min(d2, 0)), last_g[pred], first_g)  # before the first
    prior = jnp.where(idx[None] > first[:, None], gid - 1, prior_start[:, None]).reshape(-1)
    nxt = jnp.where(idx[None] < last[:, None], gid + 1, next_end[:, None]).reshape(-1)
    if official:
        prior, nxt = _official_neighbours(a, b, ok)
    t = (b - a).reshape(-1, 2)
    edges = OrientedEdges(a=a.reshape(-1, 2), b=b.reshape(-1, 2), ok=ok.reshape(-1), prior=prior, next=nxt,
                          convex_before=_cross(t[prior], t) > 0, convex_after=_cross(t, t[nxt]) > 0,
                          dropped=jnp.int32(0))
    return edges if max_segments is None else _compact(edges, max_segments)


def _official_neighbours(a, b, ok):
    """Segment neighbours `(prior i32[E * S], next i32[E * S])` as the official code sees the oriented edges it is
    handed (`edge_polylines`: each run of consecutive kept segments of a row a polyline of its own): a run's ends
    are open (the segment is its own neighbour), except a closed run (ends within 1 m) that has as many points
    as the longest run of the scene: the official code pads its polylines to the longest one and wraps a closed
    polyline to its last slot, which is a real segment for the longest ones only. No run continues another."""
    e, s = ok.shape
    idx = jnp.arange(s)[None]
    pad = jnp.pad(ok, ((0, 0), (1, 1)))
    prev_ok, next_ok = pad[:, :-2], pad[:, 2:]
    run_first = jax.lax.cummax(jnp.where(ok & ~prev_ok, idx, -1), axis=1)
    run_last = jax.lax.cummin(jnp.where(ok & ~next_ok, idx, s), axis=1, reverse=True)
    rf, rl = jnp.clip(run_first, 0, s - 1), jnp.clip(run_last, 0, s - 1)
    points = jnp.where(ok, rl - rf + 2, 0)
    start = jnp.take_along_axis(a, rf[..., None], 1)
    end = jnp.take_along_axis(b, rl[..., None], 1)
    wrap = ok & (jnp.sum((start - end) ** 2, -1) < 1.0) & (points == jnp.max(points))
    row = jnp.arange(e)[:, None] * s
    gid = row + idx
    prior = jnp.where(prev_ok, gid - 1, jnp.where(wrap & (idx == rf), row + rl, gid))
    nxt = jnp.where(next_ok, gid + 1, jnp.where(wrap & (idx == rl), row + rf, gid))
    return prior.reshape(-1), nxt.reshape(-1)


def _compact(edges: OrientedEdges, max_segments: int) -> OrientedEdges:
    """The existing segments first, `max_segments` kept (neighbour indices remapped; `dropped` counts the rest)."""
    n = edges.ok.shape[0]
    keep = min(max_segments, n)
    order = jnp.argsort(~edges.ok, stable=True)[:keep]
    new_index = jnp.zeros(n, jnp.int32).at[order].set(jnp.arange(keep, dtype=jnp.int32))
    remap = lambda i: new_index[i[order]]  # a dropped neighbour maps to 0 (counted)
    return OrientedEdges(a=edges.a[order], b=edges.b[order], ok=edges.ok[order], prior=remap(edges.prior),
                         next=remap(edges.next), convex_before=edges.convex_before[order],
                         convex_after=edges.convex_after[order],
                         dropped=jnp.sum(edges.ok, dtype=jnp.int32) - jnp.sum(edges.ok[order], dtype=jnp.int32))


def edge_polylines(road: RoadGeometry) -> list[np.ndarray]:
    """The unbatched `road`'s road edges as `orient_edges` keeps and orients them, as polylines `f64[n, 2]` (host
    side): each run of consecutive kept segments of an edge row, the road on its left. What the official code is
    handed (a `road_edge` map feature each) to score the same edges: it closes a polyline whose ends are within
    1 m as `orient_edges` does, but does not continue one row into the next (`orient_edges` does where a row
    starts where another ends), which can change a sign only at such a junction's vertex."""
    e = jax.device_get(orient_edges(road))
    rows, s = np.shape(road.edge_valid)[0], np.shape(road.edge_valid)[1] - 1
    a, b, ok = (np.asarray(x).reshape((rows, s) + np.shape(x)[1:]) for x in (e.a, e.b, e.ok))
    out = []
    for r in range(rows):
        k = np.flatnonzero(ok[r])
        for run in np.split(k, np.flatnonzero(np.diff(k) > 1) + 1) if k.size else []:
            out.append(np.concatenate([a[r, run[:1]], b[r, run]]).astype(np.float64))
    return out


def edge_segment_budget(edge_valid) -> int:
    """A static segment count for `orient_edges(..., max_segments=)` that keeps every road-edge segment of a batch
    of scenes (`edge_valid bool[..., E, P]`, on the host, or the batch's `RoadGeometry`: its map edges where it has
    them, as `orient_edges` reads): the largest count rounded up to a power of two, at least 64 (few distinct
    values: few compiles when batches differ)."""
    if isinstance(edge_valid, RoadGeometry):
        edge_valid = edge_valid.edge_valid if edge_valid.map_edges is None else edge_valid.map_edge_valid
    v = np.asarray(edge_valid)
    counts = np.sum(v[..., :-1] & v[..., 1:], axis=(-2, -1))
    return max(64, 1 << max(0, int(np.max(counts, initial=0)) - 1).bit_length())


def _signed_edge_distance(p, edges: OrientedEdges, seg):
    """Signed distance (positive off the road) of points `p f32[B, P, 2]` to their nearest candidate segment among
    `seg i32[B, C]` (the official rule, on the nearest segment). Returns (signed f32[B, P], unsigned f32[B, P])."""
    ax, ay = edges.a[seg, 0][:, None], edges.a[seg, 1][:, None]  # [B, 1, C]
    abx, aby = edges.b[seg, 0][:, None] - ax, edges.b[seg, 1][:, None] - ay
    ok = edges.ok[seg][:, None]
    apx, apy = p[..., 0, None] - ax, p[..., 1, None] - ay  # [B, P, C]
    den = abx * abx + aby * aby
    rel_t = (apx * abx + apy * aby) / jnp.where(den > 0, den, 1.0)
    tc = jnp.clip(rel_t, 0.0, 1.0)
    ex, ey = apx - tc * abx, apy - tc * aby
    dist2 = jnp.where(ok, ex * ex + ey * ey, jnp.inf)
    # the nearest candidate (the first among ties), by reductions that fuse (argmin + gathers do not on a CPU)
    d2 = jnp.min(dist2, axis=-1)  # [B, P]
    c = seg.shape[-1]
    k = jnp.minimum(jnp.min(jnp.where(dist2 == d2[..., None], jnp.arange(c), c), axis=-1), c - 1)
    s = jnp.take_along_axis(seg, k, axis=-1)  # [B, P]
    sa, sb = edges.a[s], edges.b[s]
    ab_s = sb - sa
    t = jnp.sum((p - sa) * ab_s, -1) / jnp.maximum(jnp.sum(ab_s * ab_s, -1), 1e-12)
    d = jnp.sqrt(d2)

    def side(i):  # +1 where the point is on segment i's starboard (off-road) side, -1 port
        return jnp.sign(_cross(p - edges.a[i], edges.b[i] - edges.a[i]))

    n, n_prior, n_next = side(s), side(edges.prior[s]), side(edges.next[s])
    before = jnp.where(edges.convex_before[s], jnp.maximum(n, n_prior), jnp.minimum(n, n_prior))
    after = jnp.where(edges.convex_after[s], jnp.maximum(n, n_next), jnp.minimum(n, n_next))
    sign = jnp.where(t < 0, before, jnp.where(t < 1, n, after))
    return jnp.where(jnp.isfinite(d), sign * d, FAR), d


def _box_segment_bound(lo, hi, edges: OrientedEdges):
    """f32[B, S]: a lower bound of the distance from any point of the axis-aligned boxes [lo, hi] f32[B, 2] to
    each segment: the larger of the gap between the box and the segment's bounding box and the distance from the
    box's centre to the segment less its half diagonal."""
    ax, ay, bx, by = (edges.a[None, :, 0], edges.a[None, :, 1], edges.b[None, :, 0], edges.b[None, :, 1])
    lx, ly, hx, hy = lo[:, 0, None], lo[:, 1, None], hi[:, 0, None], hi[:, 1, None]
    gx = jnp.maximum(jnp.maximum(jnp.minimum(ax, bx) - hx, lx - jnp.maximum(ax, bx)), 0.0)
    gy = jnp.maximum(jnp.maximum(jnp.minimum(ay, by) - hy, ly - jnp.maximum(ay, by)), 0.0)
    cx, cy = (lx + hx) / 2, (ly + hy) / 2
    abx, aby = bx - ax, by - ay
    den = abx * abx + aby * aby
    t = jnp.clip(((cx - ax) * abx + (cy - ay) * aby) / jnp.where(den > 0, den, 1.0), 0.0, 1.0)
    qx, qy = cx - ax - t * abx, cy - ay - t * aby
    half_diag = jnp.sqrt((hx - lx) ** 2 + (hy - ly) ** 2) / 2
    centre = jnp.sqrt(qx * qx + qy * qy) - half_diag
    return jnp.where(edges.ok[None], jnp.maximum(jnp.sqrt(gx * gx + gy * gy), centre), jnp.inf)


def road_edge_distance(edges: OrientedEdges, corners, valid, num_candidates: int = EDGE_CANDIDATES,
                       chunk: int = EDGE_CHUNK_FRAMES):
    """Most off-road corner's signed distance for box corners `f32[F, A, 4, 2]` (positive off the road).

    Candidate search: for every agent and chunk of `chunk` frames, the `num_candidates` segments with the smallest
    lower bound of their distance to the bounding box of the agent's corners in those frames
    (`_box_segment_bound`); a corner's nearest candidate is provably its nearest segment when it is no farther
    than the next segment's bound. (A per-scene grid of candidates measured slower and less often exact.)
    Returns (distance f32[F, A], inexact bool[F, A]: where that proof fails or segments were dropped).
    """
    f, a = corners.shape[:2]
    num_seg = edges.a.shape[0]
    pad = (-f) % chunk
    cp = jnp.pad(corners, ((0, pad), (0, 0), (0, 0), (0, 0)), mode="edge")
    vp = jnp.pad(valid, ((0, pad), (0, 0)))
    nc = (f + pad) // chunk
    cp = cp.reshape(nc, chunk, a, 4, 2).transpose(0, 2, 1, 3, 4).reshape(nc * a, chunk * 4, 2)
    vpts = jnp.repeat(vp.reshape(nc, chunk, a).transpose(0, 2, 1).reshape(nc * a, chunk), 4, axis=-1)
    lo = jnp.min(jnp.where(vpts[..., None], cp, jnp.inf), axis=1)
    hi = jnp.max(jnp.where(vpts[..., None], cp, -jnp.inf), axis=1)
    empty = ~jnp.any(vpts, -1)[:, None]  # a chunk with nothing valid: any box will do
    lo, hi = jnp.where(empty, cp[:, 0], lo), jnp.where(empty, cp[:, 0], hi)
    # the barriers keep XLA from fusing each reduction into its consumer (which recomputes it per element: 10x)
    lo, hi = jax.lax.optimization_barrier((lo, hi))
    m = min(num_candidates, num_seg)
    bound = _box_segment_bound(lo, hi, edges)  # [B, S]
    neg, seg = jax.lax.optimization_barrier(jax.lax.top_k(-bound, min(m + 1, num_seg)))
    next_bound = -neg[:, m] if num_seg > m else jnp.full(neg.shape[:1], jnp.inf)
    sd, d = _signed_edge_distance(cp, edges, seg[:, :m])  # [B, chunk * 4]
    inexact = ((d > next_bound[:, None]) | (edges.dropped > 0)).reshape(nc * a, chunk, 4).any(-1)
    out = jnp.max(sd.reshape(nc * a, chunk, 4), axis=-1)
    unchunk = lambda x: x.reshape(nc, a, chunk).transpose(0, 2, 1).reshape(nc * chunk, a)[:f]
    return unchunk(out), unchunk(inexact) & valid


def realism_features(xy: jax.Array, heading: jax.Array, valid: jax.Array, size: jax.Array, num_history: int,
                     dt: float = 0.1, edges: OrientedEdges | None = None,
                     signals: SignalGeometry | OfficialSignalGeometry | None = None,
                     rules: str = "corrected") -> RealismFeatures:
    """The realism features of one trajectory set's future frames.

    Args:
      xy: f32[T, A, 2] box centres (history and future, 10 Hz for the challenge's ranges); heading: f32[T, A];
        valid: bool[T, A]; size: f32[A, 2] (length, width).
      num_history: H, frames up to and including the current one; features cover frames H .. T-1.
      dt: seconds between frames.
      edges: `orient_edges(scene.road)` (computed once per scene, shared by the log and every rollout), or None
        for a scene without road geometry (then distance_to_road_edge is `FAR`, offroad False).
      signals: `signal_geometry` of the scene's signals (computed once per scene, states on these frames;
        `official_signal_geometry` under the official rules), or None (no traffic-light feature).
      rules: "corrected": a speed (acceleration) is valid where its neighbours one (two) frames away are, history
        included; "official": the same computed on the future frames alone (the first and last future frame
        never valid for speeds, the first two and last two for accelerations).
    """
    speed, accel, w, dw, sv, av = kinematics(xy, heading, valid, dt)
    fut = slice(num_history, None)
    xy_f, h_f, v_f, speed_f = xy[fut], heading[fut], valid[fut], speed[fut]
    if rules == "official":  # the validity of the differences from the future frames alone
        sv = _central_and(v_f)
        av = _central_and(sv)
    else:
        sv, av = sv[fut], av[fut]
    size_t = jnp.broadcast_to(size, xy_f.shape)
    dist = nearest_object_distance(xy_f, h_f, v_f, size_t)
    ttc = time_to_collision(xy_f, h_f, speed_f, v_f, size_t)  # NaN speed (last frame): no closing, MAX_TTC_S
    if edges is None:
        edge = jnp.full(v_f.shape, FAR, jnp.float32)
        inexact = jnp.zeros(v_f.shape, bool)
    else:
        edge, inexact = road_edge_distance(edges, box_corners(xy_f, h_f, size_t), v_f)
    return RealismFeatures(
        valid=v_f, speed_valid=sv, accel_valid=av, linear_speed=speed_f, linear_acceleration=accel[fut],
        angular_speed=w[fut], angular_acceleration=dw[fut], distance_to_nearest_object=dist,
        collision=(dist < 0) & v_f, time_to_collision=ttc, distance_to_road_edge=edge,
        offroad=(edge > 0) & v_f & (edge < FAR / 2), edge_inexact=inexact,
        red_light=None if signals is None else (  # from the current frame: crossings into H..
            official_red_light_violation if isinstance(signals, OfficialSignalGeometry) else red_light_violation)(
            xy[num_history - 1:], valid[num_history - 1:],
            signals.replace(state=signals.state[num_history - 1:]))[0][1:])


# ------------------------------------------------------------------------------------------------ likelihoods
def histogram_log_likelihood(log_values, sim_values, sim_valid, cfg: FeatureConfig, count_nan: bool = False):
    """Log-probability of each logged value under the histogram of the simulated ones.

    Args:
      log_values: f32[N, L] (N independent populations); sim_values: f32[N, S]; sim_valid: bool[N, S] which
        simulated values count.
      cfg: range, bins and pseudocount; values are clipped into [min_val, max_val] (infinities into the end bins).
      count_nan: False: only finite simulated values count; True: every one where `sim_valid`, NaN in the top
        bin (what the official code's `tfp.stats.histogram` does with it). A NaN logged value is scored as the
        top bin either way.

    Returns f32[N, L]: log((count of the logged value's bin + pseudocount) / (counted + bins * pseudocount)).
    """
    if cfg.estimator == "bernoulli":
        lo, hi, bins = -0.5, 1.5, 2
    else:
        lo, hi, bins = cfg.min_val, cfg.max_val, cfg.num_bins
    edges = jnp.linspace(lo, hi, bins + 1, dtype=jnp.float32)

    def bin_of(v):
        v = v.astype(jnp.float32)
        b = jnp.clip(jnp.searchsorted(edges, jnp.clip(v, lo, hi), side="right") - 1, 0, bins - 1)
        return jnp.where(jnp.isnan(v), bins - 1, b)

    ok = sim_valid if count_nan else sim_valid & jnp.isfinite(sim_values)
    counts = jnp.sum(jax.nn.one_hot(bin_of(sim_values), bins) * ok[..., None], axis=-2)
    probs = (counts + cfg.pseudocount) / jnp.sum(counts + cfg.pseudocount, axis=-1, keepdims=True)
    log_p = jnp.log(probs)  # [N, bins]
    return jnp.take_along_axis(log_p, bin_of(log_values), axis=-1)


def _masked_mean(x, m):
    m = m.astype(jnp.float32)
    return jnp.sum(jnp.where(m > 0, x, 0.0)) / jnp.sum(m)


def realism_metrics(sim: RealismFeatures, log: RealismFeatures, sim_xy, log_xy, evaluated, config: str = "2025",
                    has_road: bool = True, rules: str = "corrected", is_vehicle=None,
                    history_steps=None) -> dict[str, jax.Array]:
    """WOSAC likelihoods, meta-metric, minADE for one scenario from its features.

    Args:
      sim: `RealismFeatures` of the K rollouts (leading dim K); log: of the log (no leading dim).
      sim_xy: f32[K, F, A, 2] rollout positions of the future frames; log_xy: f32[F, A, 2].
      evaluated: bool[A] the agents scored (their rollouts are the model's; others only interact).
      config: "2024" or "2025"; has_road: whether the scene has road geometry (else the map terms are left out).
        The traffic-light term is scored where the features carry it (`realism_features(..., signals=)`).
      rules: "corrected": a simulated kinematic value counts where the rollout has both neighbours and it is
        finite; "official": every simulated value counts, the NaN padding of the central differences in the top
        bin (the features' validity says which frames the rollout has: all future frames under these rules).
      is_vehicle: bool[A], the agents whose time to collision and traffic-light violation are scored (the
        official rule: vehicles only); None: all.
      history_steps: f32[A], the log's valid history frames: the official ADE divides each agent's summed
        error by its valid frames history included (the history's error is zero); None: future frames only.

    Returns f32[] per key: "<feature>_likelihood" for each scored feature, "metametric", the bucket scores
    "kinematic", "interactive", "map_based", "min_ade", "ade", "collision_rate", "offroad_rate",
    "road_edge_inexact_share"; NaN where no evaluated agent has the feature.
    """
    if rules not in RULES:
        raise ValueError(f"realism rules {rules!r}: expected one of {RULES}")
    official = rules == "official"
    cfg = realism_config(config)
    weights = realism_weights(config, has_road=has_road, has_signals=log.red_light is not None)
    k = sim.valid.shape[0]
    ev = evaluated[None, :]  # [1, A] against [F, A]
    vehicle = jnp.ones_like(evaluated) if is_vehicle is None else is_vehicle
    out = {}
    # feature -> (field, the log's mask, the rollouts' mask)
    kin_sim = "valid" if official else None
    series = {
        "linear_speed": ("linear_speed", "speed_valid", kin_sim or "speed_valid"),
        "linear_acceleration": ("linear_acceleration", "accel_valid", kin_sim or "accel_valid"),
        "angular_speed": ("angular_speed", "speed_valid", kin_sim or "speed_valid"),
        "angular_acceleration": ("angular_acceleration", "accel_valid", kin_sim or "accel_valid"),
        "distance_to_nearest_object": ("distance_to_nearest_object", "valid", "valid"),
        "time_to_collision": ("time_to_collision", "valid", "valid"),
        "distance_to_road_edge": ("distance_to_road_edge", "valid", "valid"),
    }
    for name, (field, log_mask, sim_mask) in series.items():
        if name not in weights:
            continue
        c = cfg[name]
        sim_v = getattr(sim, field)  # [K, F, A]
        sim_m = getattr(sim, sim_mask)
        f, a = sim_v.shape[1:]
        # populations = agents; simulated samples pooled over rollouts and frames (independent_timesteps)
        pooled = jnp.transpose(sim_v, (2, 0, 1)).reshape(a, k * f)
        pooled_m = jnp.transpose(sim_m, (2, 0, 1)).reshape(a, k * f)
        ll = histogram_log_likelihood(getattr(log, field).T, pooled, pooled_m, c, count_nan=official)  # [A, F]
        scored = getattr(log, log_mask) & ev
        if name == "time_to_collision":
            scored = scored & vehicle[None]
        out[f"{name}_likelihood"] = jnp.exp(_masked_mean(ll.T, scored))
    for name, field in (("collision_indication", "collision"), ("offroad_indication", "offroad"),
                        ("traffic_light_violation", "red_light")):
        if name not in weights:
            continue
        mask = log.valid & vehicle[None] if name == "traffic_light_violation" else log.valid  # official: vehicles
        sim_any = jnp.any(getattr(sim, field) & mask[None], axis=1)  # [K, A]
        log_any = jnp.any(getattr(log, field) & mask, axis=0)  # [A]
        ll = histogram_log_likelihood(log_any[:, None].astype(jnp.float32), sim_any.T.astype(jnp.float32),
                                      jnp.ones((sim_any.shape[1], k), bool), cfg[name])[:, 0]
        out[f"{name}_likelihood"] = jnp.exp(_masked_mean(ll, evaluated))
        any_agent = jnp.any(getattr(sim, field) & log.valid[None], axis=1)  # the rate: every evaluated agent
        out[f"{field}_rate"] = _masked_mean(any_agent.astype(jnp.float32), jnp.broadcast_to(evaluated, sim_any.shape))
    out["metametric"] = sum(w * out[f"{n}_likelihood"] for n, w in weights.items())
    for bucket in ("kinematic", "interactive", "map_based"):
        names = [n for n in weights if FEATURES[n] == bucket]
        if names:
            total = sum(weights[n] for n in names)
            out[bucket] = sum(weights[n] * out[f"{n}_likelihood"] for n in names) / total
    # displacement: per rollout, the mean over evaluated agents of each agent's mean error over the log's frames
    # (the official rules: the history's frames counted too, at zero error)
    err = jnp.linalg.norm(sim_xy - log_xy[None], axis=-1)  # [K, F, A]
    m = log.valid[None] & ev[None]
    frames = jnp.sum(m, 1) + (0.0 if history_steps is None else history_steps[None])
    per_agent = jnp.sum(jnp.where(m, err, 0.0), 1) / jnp.maximum(frames, 1)  # [K, A]
    has = jnp.any(frames > 0, 0) & evaluated
    per_rollout = jnp.sum(jnp.where(has[None], per_agent, 0.0), -1) / jnp.sum(has)
    out["min_ade"] = jnp.min(per_rollout)
    out["ade"] = jnp.mean(per_rollout)
    inexact = jnp.concatenate([sim.edge_inexact.reshape(-1), log.edge_inexact.reshape(-1)])
    out["road_edge_inexact_share"] = jnp.mean(inexact.astype(jnp.float32))
    return out


def continue_missing(xy, heading, valid, num_history: int):
    """Rollouts with every agent at every future frame: where an agent is missing at a future frame, it goes on
    from its last valid frame at that frame's velocity (the backward difference to the valid frame before it,
    `gpd_jax.scene.backward_difference`; zero without one) and heading. What the official mode scores where a
    rollout, a baseline or the log has no state (the official format has none missing).

    `xy f32[..., T, A, 2]`, `heading f32[..., T, A]`, `valid bool[..., T, A]` -> (xy, heading) with the future
    frames (from `num_history`) filled; agents never valid up to a frame stay as they are there.
    """
    t = valid.shape[-2]
    index = jnp.arange(t)[:, None]
    last = jax.lax.cummax(jnp.where(valid, index, -1), axis=valid.ndim - 2)  # last valid frame <= t
    step, frames, known = backward_difference(xy, valid)
    vel = jnp.where(known[..., None], step / frames[..., None], 0.0)
    at = lambda x: jnp.take_along_axis(x, jnp.maximum(last, 0)[..., None], axis=-3)  # noqa: E731
    fill_xy = at(xy) + at(vel) * (index - last)[..., None]
    fill_h = at(heading[..., None])[..., 0]
    fill = ~valid & (last >= 0) & (index >= num_history)
    return jnp.where(fill[..., None], fill_xy, xy), jnp.where(fill, fill_h, heading)


def official_signal_arrays(signals: TrafficSignals, lanes=None, lane_valid=None) -> dict[str, np.ndarray]:
    """What the official code is handed of a batch of scenes' traffic signals and lanes (host arrays, leading
    dim B; `gpd_jax.metrics.traffic_lights.official_lanes`): "official_lanes" f32[B, R, W, 2],
    "official_lane_valid" bool[B, R, W] (rows of fewer than 2 points are not handed over), "signal_row" i32[B, S]
    (each signal's lane row), "signal_present" bool[B, S]; with the store's "signal_state" and "signal_stop"
    (`tests/conformance/run_official.py` reads them)."""
    signals = jax.tree.map(jnp.asarray, signals)
    pts, valid, row, present = jax.vmap(official_lanes)(signals) if lanes is None else \
        jax.vmap(official_lanes)(signals, jnp.asarray(lanes), jnp.asarray(lane_valid))
    return {"official_lanes": np.asarray(pts), "official_lane_valid": np.asarray(valid),
            "signal_row": np.asarray(row), "signal_present": np.asarray(present)}


def scenario_realism(sim_xy, sim_heading, sim_valid, log_xy, log_heading, log_valid, size, num_history: int,
                     road: RoadGeometry | None = None, evaluated=None, dt: float = 0.1,
                     config: str = "2025", max_edge_segments: int | None = None,
                     signals: TrafficSignals | None = None, lanes=None, lane_valid=None, rules: str = "corrected",
                     agent_type=None) -> dict[str, jax.Array]:
    """The realism metrics of K rollouts of one scenario (pure; `jax.vmap` over scenarios, `jit` it whole).

    Args:
      sim_xy: f32[K, T, A, 2], sim_heading: f32[K, T, A], sim_valid: bool[K, T, A] the rollouts, history
        included (frames before `num_history` are normally the log's).
      log_xy: f32[T, A, 2], log_heading: f32[T, A], log_valid: bool[T, A] the log; size: f32[A, 2].
      num_history: H; the future frames H .. T-1 are scored.
      road: the scene's `RoadGeometry` (unbatched), or None (map-based terms left out).
      evaluated: bool[A] agents to score; default: those valid in the log at the current frame (H - 1).
      dt: seconds between frames (0.1: the challenge's 10 Hz; see `upsample_frames` for model rates).
      config: "2024" or "2025".
      max_edge_segments: static road-edge segment slots kept (`edge_segment_budget` of the batch); None keeps the
        store's padded arrays (same results, slower).
      signals: the scene's `TrafficSignals` (unbatched, states on these frames) and its lane centrelines `lanes`,
        `lane_valid` (`Scene.polylines`, `polyline_valid`): the 2025 traffic-light term is scored; None leaves it
        out.
      rules: "corrected" or "official" (module docstring). Under "official" the simulated agents are those
        valid in the log at the current frame (the others are in neither the rollouts nor the log), every one
        of them present at every future frame of every rollout (`continue_missing` where a rollout lacks it),
        the history the log's; evaluated agents are among them.
      agent_type: i32[A] (`gpd_jax.scene.AGENT_TYPES`): under the official rules time to collision and the
        traffic-light violation are scored for vehicles only (all but "other"); None, or the corrected rules: for
        every agent.
    """
    if rules not in RULES:
        raise ValueError(f"realism rules {rules!r}: expected one of {RULES}")
    edges = None if road is None else orient_edges(road, max_edge_segments, official=rules == "official")
    if evaluated is None:
        evaluated = log_valid[num_history - 1]
    history_steps = None
    if rules == "official":
        present = log_valid[num_history - 1]
        evaluated = evaluated & present
        hist = (jnp.arange(log_valid.shape[0]) < num_history)[:, None]
        sim_xy = jnp.where(hist[..., None], log_xy, sim_xy)
        sim_heading = jnp.where(hist, log_heading, sim_heading)
        sim_valid = jnp.where(hist, log_valid, sim_valid)
        sim_xy, sim_heading = continue_missing(sim_xy, sim_heading, sim_valid, num_history)
        sim_valid = jnp.broadcast_to(jnp.where(hist, log_valid, present[None]), sim_valid.shape)
        log_valid = log_valid & present[None]
        first = max(0, num_history - OFFICIAL_HISTORY_FRAMES)
        history_steps = jnp.sum(log_valid[first:num_history], axis=0).astype(jnp.float32)
    is_vehicle = None if agent_type is None or rules != "official" else agent_type != TYPE_ID["other"]
    geo = None if signals is None else (official_signal_geometry if rules == "official" else signal_geometry)(
        signals, lanes, lane_valid)
    feats = lambda x, h, v: realism_features(x, h, v, size, num_history, dt, edges, geo, rules)  # noqa: E731
    log = feats(log_xy, log_heading, log_valid)
    sim = jax.vmap(feats)(sim_xy, sim_heading, sim_valid)
    return realism_metrics(sim, log, sim_xy[:, num_history:], log_xy[num_history:], evaluated, config,
                           has_road=road is not None, rules=rules, is_vehicle=is_vehicle,
                           history_steps=history_steps)


def rescore(per_scenario: Mapping[str, np.ndarray], config: str, has_road: bool,
            has_signals: bool) -> dict[str, np.ndarray]:
    """Per-scenario figures with the meta-metric and bucket scores made again from the likelihoods over the terms
    `realism_weights(config, has_road, has_signals)` keeps (the likelihoods of terms left out are dropped): how a
    term is left out after scoring (the map terms of a store whose road edges the log itself does not keep to)."""
    weights = realism_weights(config, has_road=has_road, has_signals=has_signals)
    out = {k: v for k, v in per_scenario.items()
           if not (k.endswith("_likelihood") and k[:-len("_likelihood")] not in weights)}
    lik = {n: np.asarray(per_scenario[f"{n}_likelihood"], np.float64) for n in weights}
    out["metametric"] = sum(w * lik[n] for n, w in weights.items())
    for bucket in ("kinematic", "interactive", "map_based"):
        names = [n for n in weights if FEATURES[n] == bucket]
        out.pop(bucket, None)
        if names:
            out[bucket] = sum(weights[n] * lik[n] for n in names) / sum(weights[n] for n in names)
    return out


def reduce_realism(per_scenario: Mapping[str, np.ndarray], config: str = "2025",
                   has_road: bool = True, has_signals: bool = False, road_reason: str = "no road geometry",
                   rules: str = "corrected") -> dict:
    """Dataset figures from per-scenario metrics (arrays with a leading scenario dim): the mean over scenarios
    with a finite value (the official aggregation), plus "scenarios", "scenarios_left_out" (no evaluated agent),
    "config", "rules" (the counting rules the figures were computed under), "weights" (renormalised) and
    "left_out" (terms not scored and why)."""
    if rules not in RULES:
        raise ValueError(f"realism rules {rules!r}: expected one of {RULES}")
    out: dict = {}
    meta = np.asarray(per_scenario["metametric"], np.float64)
    keep = np.isfinite(meta)
    for key, v in per_scenario.items():
        v = np.asarray(v, np.float64)[keep]
        v = v[np.isfinite(v)]
        out[key] = float(v.mean()) if v.size else float("nan")
    out["scenarios"] = int(keep.sum())
    out["scenarios_left_out"] = int((~keep).sum())
    out["config"] = config
    out["rules"] = rules
    out["weights"] = realism_weights(config, has_road=has_road, has_signals=has_signals)
    reasons = {"traffic_light_violation": "no traffic-signal states in the data",
               "distance_to_road_edge": road_reason, "offroad_indication": road_reason}
    out["left_out"] = {k: reasons[k] for k in left_out_terms(config, has_road=has_road, has_signals=has_signals)}
    return out


# ------------------------------------------------------------------------------------------------ frame rates
def upsample_frames(xy, heading, valid, stride: int):
    """Model-rate frames to the stored rate: `stride` - 1 frames inserted between consecutive frames.

    Cubic Hermite interpolation of positions and unwrapped headings with finite-difference tangents
    (Catmull-Rom; one-sided at the ends); an inserted frame is valid where both model frames around it are.
    `xy f32[..., T, A, 2]`, `heading f32[..., T, A]`, `valid bool[..., T, A]` -> `(T - 1) * stride + 1` frames.
    """
    if stride == 1:
        return xy, heading, valid
    lead = valid.ndim - 2
    x = jnp.moveaxis(xy, lead, 0)  # [T, ..., A, 2]
    h = jnp.unwrap(jnp.moveaxis(heading, lead, 0), axis=0)[..., None]
    v = jnp.moveaxis(valid, lead, 0)
    n = v.shape[0]
    s = jnp.arange(stride, dtype=jnp.float32) / stride

    def interp(p):  # [T, ...] -> [(T - 1) * stride + 1, ...]
        tangent = jnp.concatenate([p[1:2] - p[:1], (p[2:] - p[:-2]) / 2, p[-1:] - p[-2:-1]], axis=0)
        p0, p1, m0, m1 = p[:-1], p[1:], tangent[:-1], tangent[1:]
        ss = s.reshape((1, stride) + (1,) * (p.ndim - 1))
        e = lambda q: q[:, None]
        seg = ((2 * ss ** 3 - 3 * ss ** 2 + 1) * e(p0) + (ss ** 3 - 2 * ss ** 2 + ss) * e(m0)
               + (-2 * ss ** 3 + 3 * ss ** 2) * e(p1) + (ss ** 3 - ss ** 2) * e(m1))
        return jnp.concatenate([seg.reshape(((n - 1) * stride,) + p.shape[1:]), p[-1:]], axis=0)

    both = v[:-1] & v[1:]
    vs = jnp.concatenate([v[:-1, None], jnp.repeat(both[:, None], stride - 1, axis=1)], axis=1)
    v_u = jnp.concatenate([vs.reshape(((n - 1) * stride,) + v.shape[1:]), v[-1:]], axis=0)
    back = lambda q: jnp.moveaxis(q, 0, lead)
    return back(interp(x)), back(wrap_angle(interp(h)[..., 0])), back(v_u)
