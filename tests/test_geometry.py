"""Drivable-area queries (gpd_jax.geometry) on hand-built geometry."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpd_jax import geometry as geo
from gpd_jax.scene import empty_scene

# jitted once per module (eager dispatch of the many small ops is slow on a loaded machine)
on_road = jax.jit(geo.on_road)
area_kinds = jax.jit(geo.area_kinds)
signed_distance_to_edge = jax.jit(geo.signed_distance_to_edge)
lane_direction = jax.jit(geo.lane_direction)


def _pad(rows, width):
    """List of point lists -> (f32[len, width, 2], bool[len, width]) with prefix validity."""
    arr = np.zeros((len(rows), width, 2), np.float32)
    valid = np.zeros((len(rows), width), bool)
    for i, r in enumerate(rows):
        arr[i, : len(r)] = r
        valid[i, : len(r)] = True
    return arr, valid


def crossroad() -> geo.RoadGeometry:
    """Two 3.5 m lanes along x in [0, 50] (eastbound y in [-3.5, 0], westbound y in [0, 3.5]), a 20 x 20 m
    junction at x in [50, 70], y in [-10, 10], and a road going north out of the junction with a 2 x 2 m
    traffic island (a hole) in the middle of the road at x in [59, 61], y in [20, 22]."""
    lane_road = [(0, -3.5), (50, -3.5), (50, 3.5), (0, 3.5)]
    north_road = [(55, 10), (65, 10), (65, 40), (55, 40)]
    island = [(59, 20), (61, 20), (61, 22), (59, 22)]
    junction = [(50, -10), (70, -10), (70, 10), (50, 10)]
    polys, pvalid = _pad([lane_road, north_road, island, junction], 6)
    kind = np.array([0, 0, 0, 1], np.int32)
    # boundary of the union (clipped region: x in [0, 70], y in [-10, 40]; the clip box's sides are not edges)
    edges, evalid = _pad([
        [(0, -3.5), (50, -3.5), (50, -10), (70, -10)],
        [(0, 3.5), (50, 3.5), (50, 10), (55, 10), (55, 40)],
        [(70, 10), (65, 10), (65, 40)],
        [(59, 20), (61, 20), (61, 22), (59, 22), (59, 20)],
    ], 6)
    lanes, lvalid = _pad([
        [(0, -1.75), (25, -1.75), (50, -1.75)],  # eastbound
        [(50, 1.75), (25, 1.75), (0, 1.75)],  # westbound
        [(57.5, 10), (57.5, 40)],  # northbound
    ], 4)
    return geo.RoadGeometry(polygons=jnp.asarray(polys), polygon_valid=jnp.asarray(pvalid),
                            polygon_kind=jnp.asarray(kind), edges=jnp.asarray(edges), edge_valid=jnp.asarray(evalid),
                            lanes=jnp.asarray(lanes), lane_valid=jnp.asarray(lvalid)).validate()


POINTS = {
    "on_eastbound": (10.0, -1.0),
    "between_lanes": (20.0, 0.0),
    "in_junction": (60.0, 0.0),
    "off_road_south": (20.0, -6.0),
    "off_road_corner": (40.0, 8.0),
    "on_island": (60.0, 21.0),
    "beside_island": (58.0, 21.0),
    "far_away": (500.0, 500.0),
}


def test_on_road_and_kinds():
    road = crossroad()
    xy = jnp.asarray(list(POINTS.values()), jnp.float32)
    got = dict(zip(POINTS, np.asarray(on_road(road, xy))))
    assert got == {"on_eastbound": True, "between_lanes": True, "in_junction": True, "off_road_south": False,
                   "off_road_corner": False, "on_island": False, "beside_island": True, "far_away": False}
    kinds = np.asarray(area_kinds(road, xy))
    assert kinds.shape == (len(POINTS), len(geo.AREA_KINDS))
    k = dict(zip(POINTS, kinds))
    assert k["in_junction"].tolist() == [False, True, False]
    assert k["on_eastbound"].tolist() == [True, False, False]
    assert not k["on_island"].any()


def test_signed_distance():
    road = crossroad()
    xy = jnp.asarray(list(POINTS.values()), jnp.float32)
    d = dict(zip(POINTS, np.asarray(signed_distance_to_edge(road, xy))))
    want = {"on_eastbound": 2.5, "between_lanes": 3.5, "in_junction": 10.0, "off_road_south": -2.5,
            "off_road_corner": -4.5, "on_island": -1.0, "beside_island": 1.0}
    for name, w in want.items():
        assert d[name] == pytest.approx(w, rel=1e-5, abs=1e-5), name
    assert d["far_away"] < -400


def test_lane_direction():
    road = crossroad()
    xy = jnp.asarray([(10.0, -1.0), (10.0, 2.5), (57.0, 30.0), (20.0, -6.0)], jnp.float32)
    heading, dist = lane_direction(road, xy)
    np.testing.assert_allclose(np.asarray(dist), [0.75, 0.75, 0.5, 4.25], rtol=1e-5)
    np.testing.assert_allclose(np.cos(np.asarray(heading) - np.array([0, np.pi, np.pi / 2, 0])), 1.0, atol=1e-6)
    assert np.all(np.asarray(heading) >= -np.pi) and np.all(np.asarray(heading) < np.pi)


def test_empty_geometry_and_blocking_and_leading_dims():
    empty = geo.empty_road()
    xy = jnp.zeros((3, 2), jnp.float32)
    assert not np.asarray(on_road(empty, xy)).any()
    assert np.all(np.isneginf(np.asarray(signed_distance_to_edge(empty, xy))))
    h, d = lane_direction(empty, xy)
    assert np.all(np.isinf(np.asarray(d))) and np.all(np.asarray(h) == 0)
    # more points than one block (lax.map path), with leading dims, agree with the per-point answers
    road = crossroad()
    rng = np.random.default_rng(0)
    pts = rng.uniform([-5, -15], [75, 45], size=(3, 100, 2)).astype(np.float32)
    big = np.asarray(signed_distance_to_edge(road, jnp.asarray(pts)))
    assert big.shape == (3, 100)
    small = np.stack([np.asarray(signed_distance_to_edge(road, jnp.asarray(p))) for p in pts])
    np.testing.assert_allclose(big, small, rtol=1e-6)
    hb, db = lane_direction(road, jnp.asarray(pts))
    assert hb.shape == db.shape == (3, 100)


def test_jit_vmap_single_compile():
    road = crossroad()
    batch = jax.tree.map(lambda a: jnp.stack([a, a]), road)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def queries(r, xy):
        one = lambda rr, p: (geo.on_road(rr, p), geo.signed_distance_to_edge(rr, p), *geo.lane_direction(rr, p))
        return jax.vmap(one)(r, xy)

    for seed in range(3):
        xy = jax.random.uniform(jax.random.key(seed), (2, 7, 2), minval=-5, maxval=70)
        out = queries(batch, xy)
        chex.assert_shape(out, [(2, 7)] * 4)
    ref = on_road(road, xy[1])
    np.testing.assert_array_equal(np.asarray(out[0][1]), np.asarray(ref))


def test_validate_and_scene_field():
    road = crossroad()
    with pytest.raises(ValueError, match="edges"):
        road.replace(edges=road.edges[..., :1]).validate()
    with pytest.raises(ValueError, match="polygon_kind"):
        road.replace(polygon_kind=road.polygon_kind.astype(jnp.float32)).validate()
    scene = empty_scene(5, 3, 64)
    scene.replace(road=road).validate()
    batched = empty_scene(5, 3, 64, batch_shape=(2,))
    with pytest.raises(ValueError, match="Scene.road"):
        batched.replace(road=road).validate()  # road unbatched, scene batched
    two = jax.tree.map(lambda a: jnp.stack([a, a]), road)
    sub = batched.replace(road=two).validate().subsample(stride=2, num_frames=3, num_agents=2)
    assert sub.road is two
    assert batched.replace(road=two).slice_frames(1, 3).road is two


def test_route_ahead_in_the_poses_frame():
    """Points every 5 m along an L-shaped path ahead of a pose beside it, in the pose's frame; they stop at the
    path's end."""
    from gpd_jax.geometry import route_ahead

    xy = jnp.array([[0.0, 0.0], [20.0, 0.0], [20.0, 20.0]])
    s = jnp.array([0.0, 20.0, 40.0])
    pts = np.asarray(route_ahead(xy, s, jnp.array([10.0, 1.0, 0.0]), 7, 5.0))       # 1 m left of the path
    np.testing.assert_allclose(pts, [[5, -1], [10, -1], [10, 4], [10, 9], [10, 14], [10, 19], [10, 19]], atol=1e-5)
    turned = np.asarray(route_ahead(xy, s, jnp.array([10.0, 0.0, np.pi / 2]), 2, 5.0))  # facing +y: x ahead is right
    np.testing.assert_allclose(turned, [[0, -5], [0, -10]], atol=1e-5)
