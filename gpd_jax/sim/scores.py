"""nuPlan's planning scores (`reference/sledge_nuplan.md` §6) on closed-loop runs, per scenario, in JAX.

**OLS** (open loop): the policy's plan at the current frame (poses at the next F model frames, 1 Hz for the shipped
model) against the logged ego at horizons 3 / 5 / 8 s: average and final displacement errors (threshold 8 m,
weights 1, 1), average and final heading errors (0.8 rad, weights 2, 2), each averaged over the horizons and
scored max(0, 1 - err / threshold); multiplied by the miss-rate multiplier (a miss: the largest displacement within
a horizon above 6 / 8 / 16 m; with one sampled frame per scenario a miss at any horizon gives 0).

**CLS** (closed loop), over the stored frames from the current one to the end (8 s at 10 Hz: our scenes are 10 s
long, nuPlan's 15 s), score = product of the multipliers x weighted mean of the terms:

* ``no_ego_at_fault_collisions``: a collision with a track counts once, classified at its first frame as nuPlan's
  devkit does: ego stopped (speed <= 0.05 m/s: not at fault); track stopped (<= 0.005 m/s: at fault); track behind
  (its centre more than 150 deg off the ego's heading seen from the ego's rear axle: not at fault); the ego's
  front bumper (the front edge of its box) touching the track (at fault); else lateral (at fault when the ego is
  in multiple lanes or off the drivable area). Every track is a vehicle: score max(0, 1 - n) over at-fault ones.
* ``drivable_area_compliance``: 0 if a corner of the ego's box is >= 0.3 m outside the drivable area at any frame.
* ``driving_direction_compliance``: the ego's progress along the direction of the nearest lane centreline
  (within 2 m), summed over 1 s windows; the largest wrong-way sum < 2 m gives 1, < 6 m 0.5, else 0.
* ``ego_is_making_progress``: 1 if the progress ratio (below) >= 0.2.
* weighted ``ego_progress_along_expert_route`` (5): min(1, max(ego, 2) / max(expert, 2)), 0 if the ego went more
  than 2 m backwards; progress = arc length along the logged ego's path between the projections of the first and
  last positions.
* weighted ``time_to_collision_within_bound`` (5): at each frame where the ego moves (> 0.005 m/s) the ego and
  the tracks ahead of it (within 20 deg; also those not behind when the ego is in multiple lanes, off the road or
  in a junction), not yet collided, are moved at constant speed along their headings in 0.1 s steps up to 3 s;
  the first overlap is the TTC (0 at frames of an at-fault collision); 1 if the smallest TTC > 0.95 s.
* weighted ``speed_limit_compliance`` (4): max(0, 1 - sum(overspeed dt) / (2.23 m/s x duration)) where lanes carry
  speed limits; our stores carry none, so the term is left out (None) and the weights renormalise over the others.
* weighted ``ego_is_comfortable`` (2): 1 if at every frame the longitudinal acceleration is in [-4.05, 2.40] m/s^2,
  |lateral acceleration| <= 4.89 m/s^2, |jerk| <= 8.37 m/s^3, |longitudinal jerk| <= 4.13 m/s^3, |yaw acceleration|
  <= 1.93 rad/s^2 and |yaw rate| <= 0.95 rad/s; derivatives by nuPlan's Savitzky-Golay filter (window 5, order 2).

"In multiple lanes": the ego's centre more than (3.2 m - its width) / 2 from the nearest centreline (a wheel over
the lane line of a 3.2 m lane, SUMO's default width; our lanes carry no ids), or off the road. Positions are box
centres; the rear axle is taken 0.28 box lengths behind the centre (nuPlan's Pacifica: 1.46 m of 5.18 m).
"""

from __future__ import annotations

import functools

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
from scipy.signal import savgol_filter

from gpd_jax.geometry import AREA_KIND_ID, area_kinds, lane_direction, project_on_path, signed_distance_to_edge
from gpd_jax.metrics.agents import box_corners, box_overlap_pairwise
from gpd_jax.scene import wrap_angle

OLS_THRESHOLDS = {"avg_displacement": 8.0, "final_displacement": 8.0, "avg_heading": 0.8, "final_heading": 0.8}
OLS_WEIGHTS = {"avg_displacement": 1.0, "avg_heading": 2.0, "final_displacement": 1.0, "final_heading": 2.0}
MISS_THRESHOLDS_M = {3.0: 6.0, 5.0: 8.0, 8.0: 16.0}
CLS_WEIGHTS = {"ego_progress_along_expert_route": 5.0, "time_to_collision_within_bound": 5.0,
               "speed_limit_compliance": 4.0, "ego_is_comfortable": 2.0}
CLS_MULTIPLIERS = ("no_ego_at_fault_collisions", "drivable_area_compliance", "driving_direction_compliance",
                   "ego_is_making_progress")
COMFORT = {"min_lon_accel": -4.05, "max_lon_accel": 2.40, "max_abs_lat_accel": 4.89, "max_abs_jerk": 8.37,
           "max_abs_lon_jerk": 4.13, "max_abs_yaw_accel": 1.93, "max_abs_yaw_rate": 0.95}
EGO_STOPPED, TRACK_STOPPED, TTC_STOPPED = 5e-2, 5e-3, 5e-3
LANE_WIDTH = 3.2
REAR_AXLE = 0.28


# ------------------------------------------------------------------------------------------------ OLS
def ols_scores(plan: jax.Array, expert: jax.Array, horizons: tuple[int, ...], frame_period_s: float) -> dict:
    """plan, expert f32[F, 3] (x, y, heading at the next F model frames) -> OLS and its terms (f32[] each)."""
    err = jnp.linalg.norm(plan[:, :2] - expert[:, :2], axis=-1)
    herr = jnp.abs(wrap_angle(plan[:, 2] - expert[:, 2]))
    ade, fde, ahe, fhe, miss = [], [], [], [], []
    for h in horizons:
        ade.append(jnp.mean(err[:h]))
        fde.append(err[h - 1])
        ahe.append(jnp.mean(herr[:h]))
        fhe.append(herr[h - 1])
        sec = round(h * frame_period_s, 6)
        thr = MISS_THRESHOLDS_M.get(sec, MISS_THRESHOLDS_M[min(MISS_THRESHOLDS_M, key=lambda k: abs(k - sec))])
        miss.append(jnp.max(err[:h]) > thr)
    errs = {"avg_displacement": jnp.mean(jnp.stack(ade)), "final_displacement": jnp.mean(jnp.stack(fde)),
            "avg_heading": jnp.mean(jnp.stack(ahe)), "final_heading": jnp.mean(jnp.stack(fhe))}
    terms = {f"planner_expert_{k}_error_within_bound": jnp.maximum(0.0, 1.0 - v / OLS_THRESHOLDS[k])
             for k, v in errs.items()}
    mult = jnp.where(jnp.any(jnp.stack(miss)), 0.0, 1.0)
    wsum = sum(OLS_WEIGHTS.values())
    weighted = sum(OLS_WEIGHTS[k] * terms[f"planner_expert_{k}_error_within_bound"] for k in errs) / wsum
    out = dict(terms)
    out["planner_miss_rate_within_bound"] = mult
    out["OLS"] = mult * weighted
    return out


# ------------------------------------------------------------------------------------------------ CLS helpers
@functools.lru_cache(maxsize=8)
def _savgol_matrix(n: int, deriv: int, dt: float) -> np.ndarray:
    """The linear map of scipy's savgol_filter (window 5, order 2, mode 'interp') on n samples: f32[n, n]."""
    return savgol_filter(np.eye(n), 5, 2, deriv=deriv, delta=dt, axis=0).astype(np.float32)


def comfort_signals(xy: jax.Array, heading: jax.Array, dt: float) -> dict:
    """Ego kinematics f32[F] each from xy f32[F, 2], heading f32[F] (Savitzky-Golay derivatives)."""
    n = xy.shape[0]
    d1, d2 = jnp.asarray(_savgol_matrix(n, 1, dt)), jnp.asarray(_savgol_matrix(n, 2, dt))
    u = jnp.stack([jnp.cos(heading), jnp.sin(heading)], -1)
    nrm = jnp.stack([-u[:, 1], u[:, 0]], -1)
    acc = d2 @ xy
    lon, lat = jnp.sum(acc * u, -1), jnp.sum(acc * nrm, -1)
    unwrapped = heading[0] + jnp.concatenate([jnp.zeros(1), jnp.cumsum(wrap_angle(jnp.diff(heading)))])
    return {"lon_accel": lon, "lat_accel": lat, "jerk": d1 @ jnp.linalg.norm(acc, axis=-1), "lon_jerk": d1 @ lon,
            "yaw_rate": d1 @ unwrapped, "yaw_accel": d2 @ unwrapped, "speed": jnp.linalg.norm(d1 @ xy, axis=-1)}


def comfortable(sig: dict) -> jax.Array:
    c = COMFORT
    ok = ((sig["lon_accel"] >= c["min_lon_accel"]) & (sig["lon_accel"] <= c["max_lon_accel"])
          & (jnp.abs(sig["lat_accel"]) <= c["max_abs_lat_accel"]) & (jnp.abs(sig["jerk"]) <= c["max_abs_jerk"])
          & (jnp.abs(sig["lon_jerk"]) <= c["max_abs_lon_jerk"]) & (jnp.abs(sig["yaw_accel"]) <= c["max_abs_yaw_accel"])
          & (jnp.abs(sig["yaw_rate"]) <= c["max_abs_yaw_rate"]))
    return jnp.all(ok)


def _relative_angle(origin, heading, points):
    """Angle (rad, [0, pi]) between the heading at `origin` f32[2] and the directions to `points` f32[..., 2]."""
    d = points - origin
    u = jnp.stack([jnp.cos(heading), jnp.sin(heading)])
    cosang = jnp.sum(d * u, -1) / jnp.maximum(jnp.linalg.norm(d, axis=-1), 1e-9)
    return jnp.arccos(jnp.clip(cosang, -1.0, 1.0))


def _overlap_one(xy0, h0, size0, xy, h, size, valid):
    """Box 0 against boxes f32[A, ...] -> bool[A] (pair by pair: A tests, not the (A + 1)^2 of all pairs)."""
    pair = lambda x, hh, sz: box_overlap_pairwise(jnp.stack([xy0, x]), jnp.stack([h0, hh]), jnp.stack([size0, sz]))
    return jax.vmap(pair)(xy, h, size)[:, 0, 1] & valid


@flax.struct.dataclass
class RoadQueries:
    """Per-frame road facts of the ego: corner signed distance min f32[F] (negative off road), lane heading f32[F]
    and distance f32[F] at the centre, in a junction bool[F]."""

    corner_sd: jax.Array
    lane_heading: jax.Array
    lane_distance: jax.Array
    in_junction: jax.Array


def road_queries(road, xy, heading, size) -> RoadQueries:
    corners = box_corners(xy, heading, jnp.broadcast_to(size, xy.shape))             # [F, 4, 2]
    sd = jnp.min(signed_distance_to_edge(road, corners), axis=-1)
    lh, ld = lane_direction(road, xy)
    rear = xy - REAR_AXLE * size[0] * jnp.stack([jnp.cos(heading), jnp.sin(heading)], -1)
    junction = area_kinds(road, rear)[..., AREA_KIND_ID["junction"]]
    return RoadQueries(corner_sd=sd, lane_heading=lh, lane_distance=ld, in_junction=junction)


def cls_scores(ego_xy, ego_heading, ego_size, ag_xy, ag_heading, ag_valid, ag_size, route_xy, route_s,
               expert_progress, dt: float, road: RoadQueries, speed_limit=None) -> dict:
    """CLS and its terms for one scenario (see the module docstring).

    ego_xy f32[F, 2], ego_heading f32[F], ego_size f32[2]; ag_xy f32[F, A, 2], ag_heading f32[F, A], ag_valid
    bool[F, A], ag_size f32[A, 2] (the other tracks); route_xy f32[R, 2], route_s f32[R] the expert's path;
    expert_progress f32[] its progress; dt the frame period; road: `RoadQueries` of the ego's frames;
    speed_limit: optional f32[F] (m/s) at the ego's lane. Frames F from the current one on.
    """
    f = ego_xy.shape[0]
    sig = comfort_signals(ego_xy, ego_heading, dt)
    ego_speed = sig["speed"]
    ag_vel = jnp.concatenate([jnp.zeros_like(ag_xy[:1]), (ag_xy[1:] - ag_xy[:-1]) / dt], 0)
    ag_vel = jnp.where((ag_valid & jnp.concatenate([ag_valid[:1] & False, ag_valid[:-1]], 0))[..., None], ag_vel, 0.0)
    ag_vel = ag_vel.at[0].set(ag_vel[1])
    ag_speed = jnp.linalg.norm(ag_vel, axis=-1)
    u = jnp.stack([jnp.cos(ego_heading), jnp.sin(ego_heading)], -1)
    rear = ego_xy - REAR_AXLE * ego_size[0] * u

    # multiple lanes / off road
    off_road = road.corner_sd < 0.0
    multi = (road.lane_distance > 0.5 * (LANE_WIDTH - ego_size[1])) | off_road

    # collisions (first frame per track)
    overlap = jax.vmap(lambda x, h, axy, ah, av: _overlap_one(x, h, ego_size, axy, ah, ag_size, av))(
        ego_xy, ego_heading, ag_xy, ag_heading, ag_valid)                                     # [F, A]
    seen_before = jnp.cumsum(overlap, axis=0) - overlap > 0
    new = overlap & ~seen_before
    front_c = ego_xy + 0.5 * ego_size[0] * u
    bumper_size = jnp.stack([jnp.asarray(1e-3, ego_size.dtype), ego_size[1]])
    bumper = jax.vmap(lambda x, h, axy, ah, av: _overlap_one(x, h, bumper_size, axy, ah, ag_size, av))(
        front_c, ego_heading, ag_xy, ag_heading, ag_valid)
    behind = jax.vmap(lambda r, h, p: _relative_angle(r, h, p))(rear, ego_heading, ag_xy) > jnp.deg2rad(150.0)
    ego_stopped = (ego_speed <= EGO_STOPPED)[:, None]
    track_stopped = ag_speed <= TRACK_STOPPED
    ctype = jnp.where(ego_stopped, 0, jnp.where(track_stopped, 1, jnp.where(behind, 2, jnp.where(bumper, 3, 4))))
    at_fault = new & ((ctype == 1) | (ctype == 3) | ((ctype == 4) & multi[:, None]))
    n_at_fault = jnp.sum(at_fault)
    no_collisions = jnp.maximum(0.0, 1.0 - n_at_fault.astype(jnp.float32))

    # drivable area
    drivable = jnp.where(jnp.any(road.corner_sd <= -0.3), 0.0, 1.0)

    # driving direction
    delta = jnp.concatenate([jnp.zeros((1, 2)), ego_xy[1:] - ego_xy[:-1]], 0)
    lane_u = jnp.stack([jnp.cos(road.lane_heading), jnp.sin(road.lane_heading)], -1)
    prog = jnp.where(road.lane_distance < 2.0, jnp.sum(delta * lane_u, -1), 0.0)
    win = max(int(round(1.0 / dt)), 1)
    csum = jnp.concatenate([jnp.zeros(1), jnp.cumsum(prog)])
    idx = jnp.arange(1, f + 1)
    window = csum[idx] - csum[jnp.maximum(idx - win, 0)]
    wrong = jnp.max(jnp.maximum(-window, 0.0))
    direction = jnp.where(wrong < 2.0, 1.0, jnp.where(wrong < 6.0, 0.5, 0.0))

    # progress
    arcs, _, _ = project_on_path(route_xy, route_s, ego_xy[jnp.array([0, f - 1])])
    ego_prog = arcs[1] - arcs[0]
    ratio = jnp.minimum(1.0, jnp.maximum(ego_prog, 2.0) / jnp.maximum(expert_progress, 2.0))
    progress = jnp.where(ego_prog < -2.0, 0.0, ratio)
    making_progress = jnp.where(progress >= 0.2, 1.0, 0.0)

    # time to collision
    collided_upto = jnp.cumsum(overlap, axis=0) > 0                                           # collided at or before
    angle = jax.vmap(lambda r, h, p: _relative_angle(r, h, p))(rear, ego_heading, ag_xy)
    ahead = angle < jnp.deg2rad(20.0)
    lateral_ok = (multi | road.in_junction)[:, None] & (angle <= jnp.deg2rad(150.0))
    relevant = ag_valid & ~collided_upto & (ahead | lateral_ok)
    steps = jnp.arange(1, 30, dtype=jnp.float32) * 0.1                                        # 0.1 .. 2.9 s
    ag_u = jnp.stack([jnp.cos(ag_heading), jnp.sin(ag_heading)], -1)

    def ttc_frame(exy, eh, es, axy, ah, au, asp, rel):
        def at(tau):
            o = _overlap_one(exy + es * tau * jnp.stack([jnp.cos(eh), jnp.sin(eh)]), eh, ego_size,
                             axy + (asp * tau)[:, None] * au, ah, ag_size, rel)
            return jnp.any(o)
        hits = jax.vmap(at)(steps)
        return jnp.where(jnp.any(hits), steps[jnp.argmax(hits)], jnp.inf)

    ttc = jax.vmap(ttc_frame)(ego_xy, ego_heading, ego_speed, ag_xy, ag_heading, ag_u, ag_speed, relevant)
    ttc = jnp.where(ego_speed <= TTC_STOPPED, jnp.inf, ttc)
    ttc = jnp.where(jnp.any(at_fault, axis=1), 0.0, ttc)
    min_ttc = jnp.min(ttc)
    ttc_ok = jnp.where(min_ttc > 0.95, 1.0, 0.0)

    comfort = jnp.where(comfortable(sig), 1.0, 0.0)
    terms = {"ego_progress_along_expert_route": progress, "time_to_collision_within_bound": ttc_ok,
             "ego_is_comfortable": comfort}
    if speed_limit is not None:
        over = jnp.maximum(ego_speed - speed_limit, 0.0)
        terms["speed_limit_compliance"] = jnp.maximum(0.0, 1.0 - jnp.sum(over * dt) / (2.23 * f * dt))
    mults = {"no_ego_at_fault_collisions": no_collisions, "drivable_area_compliance": drivable,
             "driving_direction_compliance": direction, "ego_is_making_progress": making_progress}
    wsum = sum(CLS_WEIGHTS[k] for k in terms)
    weighted = sum(CLS_WEIGHTS[k] * v for k, v in terms.items()) / wsum
    prod = mults["no_ego_at_fault_collisions"] * mults["drivable_area_compliance"] \
        * mults["driving_direction_compliance"] * mults["ego_is_making_progress"]
    out = {**mults, **terms, "CLS": prod * weighted, "num_at_fault_collisions": n_at_fault.astype(jnp.float32),
           "num_collisions": jnp.sum(new).astype(jnp.float32), "min_ttc_capped_3s": jnp.minimum(min_ttc, 3.0), "ego_progress_m": ego_prog,
           "expert_progress_m": expert_progress, "max_wrong_way_m": wrong}
    return out
