"""The WOSAC-form realism metric (`gpd_jax.metrics.realism`): features on hand-built cases, the likelihoods
against an independent NumPy estimator, the meta-metric's behaviour, one compile for a batch of scenarios."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import shapely
from scipy.spatial import ConvexHull

from gpd_jax.geometry import RoadGeometry
from gpd_jax.metrics import realism as R

H = 3  # history frames (current included) of the hand-built scenes
DT = 0.1


# ------------------------------------------------------------------------------------------ likelihoods
def _numpy_histogram_ll(log_values, sim_values, sim_valid, lo, hi, bins, pseudocount):
    """Independent estimator: np.histogram with clipping, additive smoothing, log of the logged value's bin."""
    out = np.zeros(log_values.shape)
    for n in range(log_values.shape[0]):
        sims = np.clip(sim_values[n][sim_valid[n]], lo, hi)
        counts, edges = np.histogram(sims, bins=bins, range=(lo, hi))
        p = (counts + pseudocount) / (counts + pseudocount).sum()
        for l_, v in enumerate(np.clip(log_values[n], lo, hi)):
            # np.histogram's bins are half-open [e_i, e_i+1) except the last, closed
            b = min(np.searchsorted(edges, v, side="right") - 1, bins - 1)
            out[n, l_] = np.log(p[b])
    return out


def test_histogram_likelihood_matches_an_independent_numpy_estimator():
    rng = np.random.default_rng(0)
    cfg = R.CONFIGS["2025"]["linear_acceleration"]  # [-12, 12], 11 bins, pseudocount 0.1
    log = rng.normal(0, 8, (5, 7)).astype(np.float32)
    log[0, 0], log[1, 1] = 40.0, -40.0  # clipped into the end bins
    sim = rng.normal(1, 6, (5, 64)).astype(np.float32)
    valid = rng.random((5, 64)) > 0.3
    got = np.asarray(R.histogram_log_likelihood(jnp.asarray(log), jnp.asarray(sim), jnp.asarray(valid), cfg))
    want = _numpy_histogram_ll(log, sim, valid, cfg.min_val, cfg.max_val, cfg.num_bins, cfg.pseudocount)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    # a Bernoulli is a 2-bin histogram on {0, 1} with pseudocount 0.001
    b = R.CONFIGS["2025"]["collision_indication"]
    sim_b = (rng.random((4, 32)) > 0.8).astype(np.float32)
    log_b = np.array([[0.0], [1.0], [1.0], [0.0]], np.float32)
    got_b = np.asarray(R.histogram_log_likelihood(jnp.asarray(log_b), jnp.asarray(sim_b), jnp.ones((4, 32), bool), b))
    p1 = (sim_b.sum(1) + 0.001) / (32 + 0.002)
    want_b = np.log(np.where(log_b[:, 0] > 0, p1, 1 - p1))
    np.testing.assert_allclose(got_b[:, 0], want_b, rtol=1e-5)


def test_official_counting_puts_nan_in_the_top_bin_and_corrected_counting_drops_it():
    cfg = R.CONFIGS["2025"]["linear_speed"]  # [0, 25] m/s, 10 bins, pseudocount 0.1
    sim = jnp.array([[1.0, 1.0, jnp.nan, jnp.nan]])
    log = jnp.array([[1.0, 24.0, jnp.nan]])
    ok = jnp.ones((1, 4), bool)
    official = np.exp(np.asarray(R.histogram_log_likelihood(log, sim, ok, cfg, count_nan=True)))[0]
    corrected = np.exp(np.asarray(R.histogram_log_likelihood(log, sim, ok, cfg)))[0]
    np.testing.assert_allclose(official, [2.1 / 5.0, 2.1 / 5.0, 2.1 / 5.0], rtol=1e-6)  # NaN: the top bin
    np.testing.assert_allclose(corrected, [2.1 / 3.0, 0.1 / 3.0, 0.1 / 3.0], rtol=1e-6)


def test_continue_missing_goes_on_at_the_last_velocity_and_leaves_the_rest():
    """Future frames where an agent is missing continue it from its last valid frame at that frame's velocity and
    heading; history frames, valid frames and agents never seen stay as they are."""
    t = np.arange(8, dtype=np.float32)
    xy = np.stack([np.stack([2.0 * t, 0.5 * t], -1), np.full((8, 2), np.nan)], 1)  # [T, A=2, 2]
    heading = np.stack([np.full(8, 0.3), np.zeros(8)], 1).astype(np.float32)
    valid = np.stack([t < 5, np.zeros(8, bool)], 1)
    valid[1, 0] = False  # a history gap: the velocity comes from the last two valid frames (3, 4)
    xy[5:, 0] = np.nan
    heading[5:, 0] = np.nan
    out_xy, out_h = (np.asarray(x) for x in R.continue_missing(jnp.asarray(xy), jnp.asarray(heading),
                                                               jnp.asarray(valid), num_history=3))
    np.testing.assert_allclose(out_xy[:, 0], np.stack([2.0 * t, 0.5 * t], -1), rtol=1e-6)
    np.testing.assert_allclose(out_h[:, 0], 0.3)
    assert np.isnan(out_xy[:, 1]).all()  # never valid: nothing to continue from
    gap = R.continue_missing(jnp.asarray(np.where(valid[..., None], xy, 9.0)), jnp.asarray(heading),
                             jnp.asarray(valid), num_history=3)[0]
    assert np.asarray(gap)[1, 0, 0] == 9.0  # a history frame is left as it is


# ------------------------------------------------------------------------------------------ features
def test_box_distance_equals_an_independent_minkowski_and_polygon_computation():
    rng = np.random.default_rng(1)
    n = 200
    xy_a, xy_b = rng.uniform(-4, 4, (n, 2)), rng.uniform(-4, 4, (n, 2))
    h_a, h_b = rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi, np.pi, n)
    half_a, half_b = rng.uniform(0.3, 2.5, (n, 2)), rng.uniform(0.3, 2.5, (n, 2))
    got = np.asarray(R.box_signed_distance(*(jnp.asarray(x, jnp.float32) for x in (xy_a, h_a, half_a, xy_b, h_b,
                                                                                   half_b))))

    def corners(xy, h, half):
        c, s = np.cos(h), np.sin(h)
        loc = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * half
        return xy + loc @ np.array([[c, s], [-s, c]])

    want = []
    for i in range(n):
        ca, cb = corners(xy_a[i], h_a[i], half_a[i]), corners(xy_b[i], h_b[i], half_b[i])
        pa, pb = shapely.Polygon(ca), shapely.Polygon(cb)
        if not pa.intersects(pb):
            want.append(pa.distance(pb))
            continue
        # overlap: minus the distance from the origin to the boundary of the Minkowski difference A - B
        diff = (ca[:, None, :] - cb[None, :, :]).reshape(-1, 2)
        hull = shapely.Polygon(diff[ConvexHull(diff).vertices])
        want.append(-hull.exterior.distance(shapely.Point(0, 0)))
    np.testing.assert_allclose(got, np.array(want), atol=2e-4)
    assert (got < 0).sum() > 20 and (got > 0).sum() > 20  # both cases were exercised


def _road_square(side=20.0, reverse=False, interior=False):
    """A square drivable area [0, side]^2 with its boundary as one closed road edge; the second edge slot is
    padding, or with `interior` a line through the middle (drivable on both sides: not an edge of the road) and a
    5 cm sliver."""
    ring = np.array([[0, 0], [side, 0], [side, side], [0, side]], np.float32)
    polys = np.zeros((2, 6, 2), np.float32)
    polys[0, :4] = ring
    pvalid = np.zeros((2, 6), bool)
    pvalid[0, :4] = True
    edge = np.concatenate([ring, ring[:1]])
    if reverse:
        edge = edge[::-1]
    edges = np.zeros((2, 8, 2), np.float32)
    edges[0, :5] = edge
    evalid = np.zeros((2, 8), bool)
    evalid[0, :5] = True
    if interior:
        edges = np.concatenate([edges, np.zeros((1, 8, 2), np.float32)])
        evalid = np.concatenate([evalid, np.zeros((1, 8), bool)])
        edges[1, :2] = [[5, side / 2], [15, side / 2]]
        edges[2, :2] = [[side, 3], [side, 3.05]]
        evalid[1:, :2] = True
    lanes = np.zeros((1, 2, 2), np.float32)
    return RoadGeometry(polygons=jnp.asarray(polys), polygon_valid=jnp.asarray(pvalid),
                        polygon_kind=jnp.zeros(2, jnp.int32), edges=jnp.asarray(edges),
                        edge_valid=jnp.asarray(evalid), lanes=jnp.asarray(lanes),
                        lane_valid=jnp.zeros((1, 2), bool))


@pytest.mark.parametrize("reverse,interior", [(False, False), (True, True)])
def test_road_edge_distance_is_signed_off_the_road_whatever_the_edge_direction(reverse, interior):
    """Edges in either direction; lines with the road on both sides and slivers are no edges of the road."""
    road = _road_square(reverse=reverse, interior=interior)
    rng = np.random.default_rng(2)
    pts = rng.uniform(-8, 28, (30, 1, 4, 2)).astype(np.float32)  # 30 "frames" x 1 agent x 4 corners
    valid = jnp.ones((30, 1), bool)
    square = shapely.Polygon([(0, 0), (20, 0), (20, 20), (0, 20)])
    want = []
    for f in range(30):
        d = [square.exterior.distance(shapely.Point(p)) * (-1 if square.contains(shapely.Point(p)) else 1)
             for p in pts[f, 0]]
        want.append(max(d))
    orient = jax.jit(R.orient_edges, static_argnums=1)
    distance = jax.jit(R.road_edge_distance, static_argnames=("num_candidates", "chunk"))
    got, inexact = distance(orient(road, None), jnp.asarray(pts), valid, chunk=4)
    np.testing.assert_allclose(np.asarray(got)[:, 0], want, atol=1e-4)
    assert not np.asarray(inexact).any()
    # two candidates per frame over a compacted road: an answer is either right or said to be unproven
    got, inexact = distance(orient(road, 64), jnp.asarray(pts), valid, num_candidates=2, chunk=1)
    right = np.abs(np.asarray(got)[:, 0] - want) < 1e-4
    assert np.all(right | np.asarray(inexact)[:, 0]) and right.sum() >= 10


def _straight(speed, n=12, y=0.0, x0=0.0, heading=0.0):
    t = np.arange(n) * DT
    xy = np.stack([x0 + speed * t * np.cos(heading), y + speed * t * np.sin(heading)], -1)
    return xy.astype(np.float32), np.full(n, heading, np.float32)


def test_kinematics_time_to_collision_and_nearest_object_on_hand_built_motion():
    # agent 0 follows agent 1 on a line, 10 m between boxes, closing at 5 m/s -> TTC 2 s;
    # agent 2 turns on a circle of radius 10 m at 5 m/s -> angular speed 0.5 rad/s, 25 m off to the side
    n = 12
    xy0, h0 = _straight(10.0, n)
    xy1, h1 = _straight(5.0, n, x0=14.0)
    t = np.arange(n) * DT
    ang = 0.5 * t
    xy2 = np.stack([10 * np.sin(ang), 25 + 10 - 10 * np.cos(ang)], -1).astype(np.float32)
    h2 = ang.astype(np.float32)
    xy = jnp.asarray(np.stack([xy0, xy1, xy2], 1))
    heading = jnp.asarray(np.stack([h0, h1, h2], 1))
    valid = jnp.ones((n, 3), bool)
    size = jnp.asarray([[4.0, 2.0]] * 3, jnp.float32)
    f = R.realism_features(xy, heading, valid, size, H, DT)
    speed = np.asarray(f.linear_speed)
    np.testing.assert_allclose(speed[:-1, :2], np.array([[10.0, 5.0]] * (n - H - 1)), rtol=1e-4)
    np.testing.assert_allclose(speed[:-1, 2], 2 * 10 * np.sin(0.5 * DT) / (2 * DT), rtol=1e-4)  # chord / 2 dt
    np.testing.assert_allclose(np.asarray(f.linear_acceleration)[:-2, :2], 0.0, atol=1e-3)
    np.testing.assert_allclose(np.asarray(f.angular_speed)[:-1, 2], 0.5, rtol=1e-3)
    assert not np.asarray(f.speed_valid)[-1].any() and not np.asarray(f.accel_valid)[-2:].any()
    gap = np.asarray(xy1[H:, 0] - xy0[H:, 0]) - 4.0  # front of 0 to rear of 1
    ttc = np.asarray(f.time_to_collision)
    np.testing.assert_allclose(ttc[:-1, 0], np.minimum(gap[:-1] / 5.0, 5.0), rtol=1e-4)
    assert np.all(ttc[:, 1] == R.MAX_TTC_S) and np.all(ttc[:, 2] == R.MAX_TTC_S)  # nothing ahead of them
    # nearest object: rounded boxes (shrink 0.7 x 1 m = 0.7 m each): gap + 2 x 0.7 - 2 x 0.7 along the axis
    np.testing.assert_allclose(np.asarray(f.distance_to_nearest_object)[:, 0], gap, rtol=1e-4)
    assert not np.asarray(f.collision).any()


def _scene(num_agents=4, frames=H + 20, seed=0):
    """Agents driving along x in their own lanes (4 m apart), inside a long drivable strip."""
    rng = np.random.default_rng(seed)
    xy, heading = [], []
    for a in range(num_agents):
        p, h = _straight(float(rng.uniform(4, 12)), frames, y=4.0 * a, x0=float(rng.uniform(0, 10)))
        xy.append(p)
        heading.append(h)
    xy = np.stack(xy, 1)
    heading = np.stack(heading, 1)
    ring = np.array([[-50, -3], [400, -3], [400, 4.0 * num_agents], [-50, 4.0 * num_agents]], np.float32)
    polys = ring[None]
    edges = np.concatenate([ring, ring[:1]])[None]
    road = RoadGeometry(polygons=jnp.asarray(polys), polygon_valid=jnp.ones((1, 4), bool),
                        polygon_kind=jnp.zeros(1, jnp.int32), edges=jnp.asarray(edges),
                        edge_valid=jnp.ones((1, 5), bool), lanes=jnp.zeros((1, 2, 2)),
                        lane_valid=jnp.zeros((1, 2), bool))
    size = np.array([[4.5, 1.9]] * num_agents, np.float32)
    return (jnp.asarray(xy), jnp.asarray(heading), jnp.ones((frames, num_agents), bool), jnp.asarray(size), road)


def _rollouts(xy, heading, k, noise, key, drift=(0.0, 0.0)):
    """K rollouts: the log's future with a random walk of step `noise` and a constant drift per frame."""
    steps = jax.random.normal(key, (k,) + xy.shape) * noise + jnp.asarray(drift, jnp.float32)
    steps = steps.at[:, :H].set(0.0)
    return xy[None] + jnp.cumsum(steps, axis=1), jnp.broadcast_to(heading, (k,) + heading.shape)


SCORE = jax.jit(lambda sx, sh, sv, lx, lh, lv, size, road: R.scenario_realism(sx, sh, sv, lx, lh, lv, size, H, road))


def test_samples_near_the_log_score_higher_than_shifted_ones_and_collisions_cost_the_collision_term():
    xy, heading, valid, size, road = _scene()
    k = 16
    sv = jnp.broadcast_to(valid, (k,) + valid.shape)
    key = jax.random.key(0)
    near = SCORE(*_rollouts(xy, heading, k, 0.01, key), sv, xy, heading, valid, size, road)
    far = SCORE(*_rollouts(xy, heading, k, 0.01, key, drift=(0.6, 0.0)), sv, xy, heading, valid, size, road)
    assert near["metametric"] > 0.9 * sum(R.realism_weights("2025").values())  # near the maximum (1)
    assert far["metametric"] < near["metametric"] - 0.02
    assert far["min_ade"] > near["min_ade"] + 1.0
    assert near["linear_speed_likelihood"] > far["linear_speed_likelihood"]
    assert float(near["road_edge_inexact_share"]) == 0.0
    # the log is collision-free; rollouts that put agent 1 on top of agent 0 lose the collision term
    crash_xy, crash_h = _rollouts(xy, heading, k, 0.01, key)
    crash_xy = crash_xy.at[:, H + 5:, 1].set(crash_xy[:, H + 5:, 0] + jnp.asarray([1.0, 0.5]))
    crash = SCORE(crash_xy, crash_h, sv, xy, heading, valid, size, road)
    assert float(near["collision_indication_likelihood"]) > 0.999
    assert float(crash["collision_indication_likelihood"]) < 0.9
    assert float(crash["collision_rate"]) > 0 and float(near["collision_rate"]) == 0.0
    # off the road: pushing every rollout 20 m sideways costs the offroad term
    off = SCORE(crash_xy.at[:, H:].add(jnp.asarray([0.0, 40.0])), crash_h, sv, xy, heading, valid, size, road)
    assert float(off["offroad_indication_likelihood"]) < 0.01 and float(off["offroad_rate"]) == 1.0


def test_one_compile_for_a_batch_of_scenarios_and_the_reduction_says_what_was_left_out():
    scenes = [_scene(seed=s) for s in range(3)]
    xy, heading, valid, size = (jnp.stack([s[i] for s in scenes]) for i in range(4))
    road = jax.tree.map(lambda *x: jnp.stack(x), *[s[4] for s in scenes])
    k = 8
    keys = jax.random.split(jax.random.key(1), 3)
    sx, sh = jax.vmap(lambda x, h, kk: _rollouts(x, h, k, 0.05, kk))(xy, heading, keys)
    sv = jnp.broadcast_to(valid[:, None], sx.shape[:-1])
    evaluated = jnp.ones((3, 4), bool).at[2].set(False)  # the third scenario scores no agent: NaN, left out

    @jax.jit
    @chex.assert_max_traces(n=1)
    def batch(sx, sh, sv, xy, heading, valid, size, road, evaluated):
        return jax.vmap(lambda *a: R.scenario_realism(*a[:7], H, a[7], a[8], config="2024"))(
            sx, sh, sv, xy, heading, valid, size, road, evaluated)

    out = jax.device_get(batch(sx, sh, sv, xy, heading, valid, size, road, evaluated))
    batch(sx + 0.01, sh, sv, xy, heading, valid, size, road, evaluated)  # same shapes: no new trace
    assert np.isnan(out["metametric"][2]) and np.all(np.isfinite(out["metametric"][:2]))
    red = R.reduce_realism(out, config="2024")
    assert red["scenarios"] == 2 and red["scenarios_left_out"] == 1
    assert red["left_out"] == {} and abs(sum(red["weights"].values()) - 1) < 1e-9
    np.testing.assert_allclose(red["metametric"], np.mean(out["metametric"][:2]), rtol=1e-6)
    red25 = R.reduce_realism(out, config="2025", has_road=False)
    assert set(red25["left_out"]) == {"traffic_light_violation", "distance_to_road_edge", "offroad_indication"}
    w = R.realism_weights("2025", has_road=False)
    assert abs(sum(w.values()) - 1) < 1e-9 and abs(w["collision_indication"] - 0.25 / 0.65) < 1e-9


def test_upsampling_model_frames_keeps_them_and_is_exact_on_straight_constant_speed_motion():
    xy, heading = _straight(8.0, 5)
    xy = jnp.asarray(xy)[:, None]
    heading = jnp.asarray(heading)[:, None]
    valid = jnp.ones((5, 1), bool).at[3, 0].set(False)
    # a model at 1 frame per stride of 10 stored frames: its frames are 10 x DT apart
    up_xy, up_h, up_v = R.upsample_frames(xy, heading, valid, 10)
    assert up_xy.shape == (41, 1, 2) and up_v.shape == (41, 1) and np.allclose(np.asarray(up_h), 0.0)
    np.testing.assert_allclose(np.asarray(up_xy[::10]), np.asarray(xy), atol=1e-5)
    np.testing.assert_allclose(np.asarray(up_xy[:, 0, 0]), 8.0 * DT * np.arange(41) / 10, atol=1e-4)
    # frames between model frames 2 and 4 depend on the invalid frame 3: invalid; frame 3 itself stays invalid
    v = np.asarray(up_v[:, 0])
    assert v[:21].all() and not v[21:40].any() and v[40]
    # headings are interpolated on the circle (no spin through zero when crossing +-pi)
    h = jnp.asarray([[3.0], [-3.0]])
    _, h_up, _ = R.upsample_frames(jnp.zeros((2, 1, 2)), h, jnp.ones((2, 1), bool), 4)
    assert np.all(np.abs(np.asarray(h_up)) > 2.9)
