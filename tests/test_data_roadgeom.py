"""Drivable-area geometry built into samples: SUMO networks, the hand-built road log, clipping, old stores."""

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from data_fixtures import straight_road_log, write_small_store
from gpd_jax import geometry as geo
from gpd_jax.data import loader, preprocess, roadgeom, store
from gpd_jax.data.sources import sumo_networks

on_road = jax.jit(geo.on_road)
area_kinds = jax.jit(geo.area_kinds)
signed_distance = jax.jit(geo.signed_distance_to_edge)
lane_direction = jax.jit(geo.lane_direction)


def sample_road(s) -> geo.RoadGeometry:
    return geo.road_from_arrays(s, s["polylines"], s["polyline_valid"]).validate()


def check_points(road, cases):
    """cases: name -> (xy, on_road, kinds or None, signed distance or None)."""
    xy = jnp.asarray([c[0] for c in cases.values()], jnp.float32)
    on, kinds, sd = map(np.asarray, (on_road(road, xy), area_kinds(road, xy), signed_distance(road, xy)))
    for i, (name, (_, want_on, want_kinds, want_sd)) in enumerate(cases.items()):
        assert on[i] == want_on, name
        if want_kinds is not None:
            assert kinds[i].tolist() == want_kinds, name
        if want_sd is not None:
            assert sd[i] == pytest.approx(want_sd, rel=1e-3, abs=0.02), (name, sd[i])


# ------------------------------------------------------------------------------------ hand-built road log
def test_straight_road_sample_geometry():
    """Scene frame of window 0: the ego's current position is along 20 m of the road, so scene x = along - 20,
    y = lateral. Lanes at y = -3.5, 0, 3.5 (3.5 m wide), the junction at x 10 .. 30, |y| <= 10, the crossing
    road (7 m wide) at x 16.5 .. 23.5."""
    log = straight_road_log()
    st = {}
    from collections import Counter
    st = Counter()
    s = preprocess.make_sample(log, 0, 0, stats=st)
    road = sample_road(s)
    check_points(road, {
        "on a lane": ((0.0, 0.0), True, [True, False, False], 5.25),
        "between two lanes": ((0.0, 1.75), True, [True, False, False], 3.5),
        "in the junction": ((12.0, 8.0), True, [False, True, False], 2.0),
        "off the road": ((0.0, 8.0), False, [False, False, False], -2.75),
        "on the crossing road": ((20.0, 30.0), True, [True, False, False], 3.5),
    })
    heading, dist = lane_direction(road, jnp.asarray([[0.0, 1.0], [20.0, 30.0]], jnp.float32))
    np.testing.assert_allclose(np.asarray(dist), [1.0, 0.0], atol=1e-3)
    assert abs(np.cos(float(heading[0]))) == pytest.approx(1.0, abs=1e-5)  # along the road
    assert abs(np.sin(float(heading[1]))) == pytest.approx(1.0, abs=1e-5)  # the crossing road
    # every recorded agent drives on the road
    assert np.asarray(on_road(road, jnp.asarray(s["xy"][s["valid"]]))).all()
    assert st["road_rings_dropped"] == 0 and st["road_edges_dropped"] == 0


def test_log_without_areas_gives_empty_geometry_and_is_counted():
    import dataclasses
    from collections import Counter
    st = Counter()
    s = preprocess.make_sample(dataclasses.replace(straight_road_log(), areas=()), 0, 0, stats=st)
    assert not s["road_polygon_valid"].any() and not s["road_edge_valid"].any()
    assert st["samples_without_road_geometry"] == 1


def test_clip_splits_big_rings_and_keeps_the_clip_box_out_of_the_edges():
    # a wavy 10 m wide road: many vertices in one ring, split into pieces of <= V vertices
    x = np.linspace(-200, 200, 801)
    centre = np.stack([x, 3 * np.sin(x / 7)], -1)
    idx = roadgeom.RoadIndex([roadgeom.lane_area(centre, 10.0)], tolerance=0.01)
    ego = np.zeros((11, 3))
    out = roadgeom.clip_road(idx, np.zeros(3), ego, reach=40.0, G=64, V=16, E=64, P=32)
    road = geo.road_from_arrays(out, np.zeros((1, 2, 2), np.float32), np.zeros((1, 2), bool))
    assert out["road_polygon_valid"].sum(-1).max() <= 16 and out["road_polygon_valid"].any(-1).sum() > 2
    xs = np.linspace(-35, 35, 15)
    on = np.asarray(on_road(road, jnp.asarray(np.stack([xs, 3 * np.sin(xs / 7)], -1), jnp.float32)))
    off = np.asarray(on_road(road, jnp.asarray(np.stack([xs, 3 * np.sin(xs / 7) + 6], -1), jnp.float32)))
    assert on.all() and not off.any()
    # edges: only the two road sides, never the clip box's sides at x = +-40
    pts = out["road_edges"][out["road_edge_valid"]]
    from shapely.geometry import LineString, Point
    mid = LineString(centre)
    np.testing.assert_allclose([mid.distance(Point(p)) for p in pts], 5.0, atol=0.05)


# ------------------------------------------------------------------------------------------------ SUMO
NET = """<net version="1.20">
  <location netOffset="0.00,0.00" convBoundary="0,0,200,100" origBoundary="0,0,200,100" projParameter="!"/>
  <edge id=":J_0" function="internal"><lane id=":J_0_0" index="0" speed="10" length="10" shape="95,-1.6 105,-1.6"/></edge>
  <edge id="A" from="S" to="J" priority="1">
    <lane id="A_0" index="0" speed="13.9" length="95" width="3.5" shape="0,-5.25 95,-5.25"/>
    <lane id="A_1" index="1" speed="13.9" length="95" width="3.5" shape="0,-1.75 95,-1.75"/>
    <lane id="A_2" index="2" speed="13.9" length="95" allow="pedestrian" width="2.0" shape="0,-8 95,-8"/>
  </edge>
  <edge id="B" from="J" to="E" priority="1">
    <lane id="B_0" index="0" speed="13.9" length="95" shape="105,-1.6 200,-1.6"/>
  </edge>
  <junction id="J" type="priority" x="100" y="0" incLanes="A_0 A_1" intLanes=":J_0_0" shape="95,-10 105,-10 105,10 95,10"/>
  <junction id="S" type="dead_end" x="0" y="0" incLanes="" intLanes="" shape="0,0 0,-7"/>
  <connection from="A" to="B" fromLane="1" toLane="0" via=":J_0_0" dir="s" state="M"/>
</net>
"""


def test_sumo_network_areas(tmp_path):
    """Lane `width` (A: 3.5 m, B: SUMO's default 3.2 m), a sidewalk left out, the junction `shape`."""
    net = tmp_path / "t.net.xml"
    net.write_text(NET)
    areas = sumo_networks.read_network_areas(str(net))
    kinds = sorted(a.kind for a in areas)
    assert kinds == [0, 0, 0, 1]  # A_0, A_1, B_0 lanes; junction J (dead end S has a degenerate shape)
    lanes = sumo_networks.read_network_lanes(str(net))
    idx = roadgeom.RoadIndex(areas)
    ego = np.zeros((11, 3))
    ego[:, 0] = np.linspace(-40, 40, 11)
    pose = np.array([90.0, -1.75, 0.0])  # scene frame: origin on lane A_1 at x = 90, heading +x (y = world + 1.75)
    out = roadgeom.clip_road(idx, pose, ego, reach=50.0, G=64, V=32, E=64, P=32)
    lp = preprocess.lane_points(lanes)
    cfg = preprocess.SampleConfig(view_half=40.0)
    poly, pvalid = preprocess.clip_lanes(lp, pose, ego, cfg)
    road = geo.road_from_arrays(out, poly, pvalid).validate()
    check_points(road, {
        "on lane A_0": ((-20.0, -3.5), True, [True, False, False], 1.75 + 0.0),
        "between A_0 and A_1": ((-20.0, -1.75), True, [True, False, False], 3.5),
        "in the junction": ((10.0, 10.75), True, [False, True, False], 1.0),
        "on the sidewalk (not drivable)": ((-20.0, -6.25), False, None, -(6.25 - 5.25)),
        "off the road": ((-20.0, 5.0), False, None, -3.25),
        "on B (default width 3.2)": ((40.0, 0.15 + 1.5), True, None, None),
        "beside B": ((40.0, 0.15 + 1.7), False, None, None),
    })
    h, d = lane_direction(road, jnp.asarray([[-20.0, -0.5], [40.0, 0.0]], jnp.float32))
    np.testing.assert_allclose(np.asarray(d), [0.5, 0.15], atol=1e-3)
    np.testing.assert_allclose(np.cos(np.asarray(h)), 1.0, atol=1e-5)


# ------------------------------------------------------------------------------------------------ store
def test_store_round_trip_and_scene_road(tmp_path):
    d = str(tmp_path / "ds")
    write_small_store(d, n_shards=1, per_shard=2)
    man = json.load(open(os.path.join(d, "dataset.json")))
    assert man["keys"]["road_polygons"]["shape"][1:] == [64, 32, 2]
    src = loader.SplitSource(d, "train", with_polylines=True)
    assert src.has_road
    scene = loader.to_scene({k: np.stack([src[i][k] for i in range(2)]) for k in src[0]})
    scene.validate()
    assert scene.road.polygons.shape == (2, 64, 32, 2)
    assert scene.road.lanes is scene.polylines
    on = jax.vmap(geo.on_road)(jax.tree.map(jnp.asarray, scene.road), jnp.asarray(scene.xy[:, 20, :1]))
    assert np.asarray(on).all()
    # without polylines the scene has no road (its lane centrelines are the polylines)
    assert loader.to_scene(loader.SplitSource(d, "train")[0] | {}).road is None


def test_old_store_without_road_keys_is_readable_with_road_none(tmp_path):
    d = str(tmp_path / "old")
    log = straight_road_log()
    s = preprocess.make_sample(log, 0, 0)
    arrays = store.stack_samples([s])
    for k in roadgeom.ROAD_KEYS:
        del arrays[k]
    store.write_shard(d, "test", 0, arrays, ["a"], ["road_a"])
    sh = store.Shard(store.shard_dir(d, "test", 0))
    assert not sh.has_road
    src = loader.SplitSource(d, "test", with_polylines=True)
    assert not src.has_road
    scene = loader.to_scene({k: v[None] for k, v in src[0].items()})
    assert scene.road is None and scene.polylines is not None
    with pytest.raises(ValueError, match="rebuild it with `python -m gpd_jax.data build"):
        geo.require_road(scene.road, "offroad metric")
    # a shard with only some of the road keys is corrupt
    arrays2 = store.stack_samples([s])
    del arrays2["road_edges"]
    store.write_shard(d, "test", 1, arrays2, ["b"], ["road_a"])
    from gpd_jax.data.errors import DataError
    with pytest.raises(DataError, match="road geometry keys incomplete"):
        store.Shard(store.shard_dir(d, "test", 1))
