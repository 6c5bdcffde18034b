"""Map road edges and traffic-light states in the stores (format 2), and the traffic-light violation feature.

Road edges are read from each source's fixture (ScenarioNet `ROAD_EDGE_*`, nuPlan's drivable area, Lanelet2
curbstones, a SUMO network's outline) and oriented with the drivable side on their left; a red light run is
flagged and a green one not; stores of format 1 (no map edges, no signals) still load and score as before.
"""

import os
import re
from collections import Counter

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nuplan_fixtures as nfx
import scenarionet_fixtures as sfx
from gpd_jax.data import loader, preprocess, store
from gpd_jax.data.augment import mirror_arrays
from gpd_jax.data.roadgeom import MAP_EDGE_KEYS, RoadIndex
from gpd_jax.data.signals import SIGNAL_KEYS, RawSignals, lane_piece
from gpd_jax.data.sources import interaction, nuplan, scenarionet, sumo_networks, sumo_traffic
from gpd_jax.geometry import (EDGE_SOURCE_ID, SIGNAL_STATE_ID, TrafficSignals, edge_source_names, on_road,
                              road_from_arrays)
from gpd_jax.metrics import realism
from gpd_jax.metrics.traffic_lights import (official_lanes, official_red_light_violation, official_segment_distance,
                                            official_signal_geometry, red_light_violation, signal_geometry)

CFG = preprocess.SampleConfig()


def _road(sample):
    return road_from_arrays({k: jnp.asarray(v) for k, v in sample.items()}, jnp.asarray(sample["polylines"]),
                            jnp.asarray(sample["polyline_valid"]))


_on_road = jax.jit(on_road)


def drivable_left_share(sample, probe=0.5):
    """Share of the map-edge segments (by length) whose left side is drivable and right side is not."""
    pts, ok = sample["road_map_edges"], sample["road_map_edge_valid"]
    a, b = pts[:, :-1].reshape(-1, 2), pts[:, 1:].reshape(-1, 2)
    seg_ok = (ok[:, :-1] & ok[:, 1:]).reshape(-1)
    a, b = a[seg_ok], b[seg_ok]
    t = b - a
    n = np.linalg.norm(t, axis=-1)
    left = np.stack([-t[:, 1], t[:, 0]], -1) / n[:, None]
    mid = (a + b) / 2
    road = _road(sample)
    lon = np.asarray(_on_road(road, jnp.asarray(mid + probe * left)))
    ron = np.asarray(_on_road(road, jnp.asarray(mid - probe * left)))
    return float(np.sum(n * (lon & ~ron)) / np.sum(n))


@jax.jit
def _offroad(road, xy, hd, v, size):
    feats = realism.realism_features(xy, hd, v, size, CFG.num_history, 0.1, realism.orient_edges(road))
    return jnp.any(feats.offroad, 0)


def log_offroad_share(sample):
    """The share of agents valid at the current frame whose box is off the map edges in some future frame."""
    off = np.asarray(_offroad(_road(sample), *(jnp.asarray(sample[k]) for k in ("xy", "heading", "valid", "size"))))
    return float(off[sample["valid"][CFG.current]].mean())


# ------------------------------------------------------------------------------------------------ road edges
def test_scenarionet_road_edge_lines_oriented():
    raw = scenarionet.scenario_to_rawlog(sfx.make_scenario(), "s0.pkl")
    assert len(raw.road_edges) == 2  # the two ROAD_EDGE_BOUNDARY lines
    (_, s), *_ = list(preprocess.iter_samples(raw, CFG))
    assert int(s["road_edge_source"]) == EDGE_SOURCE_ID["map_lines"]
    assert s["road_map_edge_valid"].sum() >= 4
    assert drivable_left_share(s) > 0.9  # the driveway beside the left edge is drivable on both sides there
    assert log_offroad_share(s) == 0.0
    # without ROAD_EDGE lines (nuScenes conversions) the lane union's outline, tagged so
    sc = sfx.make_scenario()
    sc["map_features"] = {k: f for k, f in sc["map_features"].items() if not f["type"].startswith("ROAD_EDGE")}
    (_, s2), *_ = list(preprocess.iter_samples(scenarionet.scenario_to_rawlog(sc, "s0.pkl"), CFG))
    assert int(s2["road_edge_source"]) == EDGE_SOURCE_ID["lane_union"] and drivable_left_share(s2) > 0.99


def test_scenarionet_signals_and_a_logged_red_light_run():
    sc = sfx.make_scenario()
    T = sc["length"]
    stop = np.zeros(3, np.float32)
    stop[:2] = sfx.road_to_world(np.array([30.5]), np.array([0.0]))[0]  # on the ego's lane, 30.5 m ahead
    sc["dynamic_map_states"]["tl1"].update(stop_point=stop, state={"object_state": ["LANE_STATE_STOP"] * T})
    sc["dynamic_map_states"]["tl2"] = {"type": "TRAFFIC_LIGHT", "lane": "100", "stop_point": stop,
                                       "state": {"object_state": ["TRAFFIC_LIGHT_GREEN"] * (T - 1) + [None]}}
    sc["dynamic_map_states"]["tl3"] = {"type": "TRAFFIC_LIGHT", "lane": "999", "stop_point": stop,
                                       "state": {"object_state": ["LANE_STATE_STOP"] * T}}  # no such lane
    stats = Counter()
    raw = scenarionet.scenario_to_rawlog(sc, "s0.pkl", stats=stats)
    assert raw.signals.state.shape == (raw.num_frames, 2) and stats["signals_without_lane_or_stop"] == 1
    assert set(raw.signals.state[:, 0]) == {SIGNAL_STATE_ID["stop"]}
    assert raw.signals.state[-1, 1] == 0 and raw.signals.state[0, 1] == SIGNAL_STATE_ID["go"]
    (_, s), *_ = list(preprocess.iter_samples(raw, CFG))
    state = s["signal_state"]
    assert (s["signal_lane_valid"].sum(-1) >= 2).sum() == 2 and (state[:, :2] != 0).all()
    sig = TrafficSignals(state=jnp.asarray(state, jnp.int32), stop=jnp.asarray(s["signal_stop"]),
                         lane=jnp.asarray(s["signal_lane"]), lane_valid=jnp.asarray(s["signal_lane_valid"]))
    geo = signal_geometry(sig, jnp.asarray(s["polylines"]), jnp.asarray(s["polyline_valid"]))
    red, _ = jax.jit(red_light_violation)(jnp.asarray(s["xy"]), jnp.asarray(s["valid"]), geo)
    red = np.asarray(red)
    # the ego (10 m/s from 0) passes the stop 30.5 m ahead after 3 s, on its own lane: flagged once (a position
    # exactly on the stop point is neither behind nor ahead of it, as in the official rule); so is the car 12 m
    # ahead of it in the lane; the cars in the other lanes cross the same line but are on other lanes (the right
    # lane's light is green, the left lane has none): not flagged
    assert red[:, 0].sum() == 1
    t, a = np.nonzero(red)
    assert len(a) == 2 and (np.abs(s["xy"][t, a, 1]) < 0.5).all()
    other_lanes = s["valid"] & (np.abs(s["xy"][..., 1]) > 2.0)
    assert other_lanes.any() and not (red & other_lanes).any()


def test_nuplan_drivable_area_outline(tmp_path):
    root = tmp_path / "maps"
    nfx.write_maps_root(root)
    (tmp_path / "logs").mkdir()
    db = nfx.write_log_db(tmp_path / "logs" / "2021.05.12.22.00.38_veh-35_01008_01518.db")
    raw = nuplan.read_log(db, root)
    assert raw.areas_outline == "drivable_area" and not raw.road_edges
    cfg = preprocess.SampleConfig(num_history=5, num_future=10)
    s = preprocess.make_sample(raw, 0, 0, cfg)
    assert int(s["road_edge_source"]) == EDGE_SOURCE_ID["drivable_area"]
    assert s["road_map_edge_valid"].any() and drivable_left_share(s) > 0.99


def test_nuplan_traffic_light_status(tmp_path):
    root = tmp_path / "maps"
    nfx.write_maps_root(root)
    (tmp_path / "logs").mkdir()
    db = nfx.write_log_db(tmp_path / "logs" / "2021.05.12.22.00.38_veh-35_01008_01518.db",
                          lights={3: lambda i: "red" if i < 30 else ("green" if i < 50 else None)})
    raw = nuplan.read_log(db, root)
    sig = raw.signals
    assert sig is not None and sig.state.shape == (raw.num_frames, 1)
    stop, go = SIGNAL_STATE_ID["stop"], SIGNAL_STATE_ID["go"]
    # the connector turns left off lane 1 (fixture); its light: red, then green, then no record (unknown)
    assert sig.state[:15, 0].tolist() == [stop] * 15 and sig.state[15:25, 0].tolist() == [go] * 10
    assert (sig.state[25:, 0] == 0).all()  # no row: unknown
    assert np.allclose(sig.stop[0], sig.lane[0][0]) and len(sig.lane[0]) >= 2
    # no table rows: no signals
    db2 = nfx.write_log_db(tmp_path / "logs" / "2021.05.12.22.00.38_veh-35_01008_01519.db")
    assert nuplan.read_log(db2, root).signals is None


def test_lanelet2_curbstones_are_the_road_edges(tmp_path):
    from test_interaction import SITE, write_csv, write_osm

    root = tmp_path / "interaction"
    os.makedirs(root / "recorded_trackfiles" / SITE)
    os.makedirs(root / "maps")
    write_csv(root / "recorded_trackfiles" / SITE / "vehicle_tracks_000.csv")
    osm = root / "maps" / f"{SITE}.osm"
    write_osm(osm)
    text = osm.read_text()
    for wid in (10, 12):  # the road's outer bounds become curbstones (one written against traffic)
        text = re.sub(rf'(<way id="{wid}" [^>]*>.*?)<tag k="type" v="line_thin" />', r'\1<tag k="type" v="curbstone" />',
                      text)
    osm.write_text(text)
    lanes, areas, borders = interaction.map_features(str(osm))
    assert len(borders) == 2
    raw = interaction.read_log(interaction.find_track_files(str(root))[0], str(root))
    pairs = interaction.log_samples(raw, CFG, seed=0)
    assert pairs
    for _, s in pairs:
        assert int(s["road_edge_source"]) == EDGE_SOURCE_ID["map_lines"]
        assert drivable_left_share(s) > 0.99 and log_offroad_share(s) == 0.0


SUMO_NET = """<net version="1.9">
  <edge id=":J1_0" function="internal"><lane id=":J1_0_0" index="0" speed="13" length="10" shape="100,-1.6 110,-1.6"/></edge>
  <edge id="E0" from="J0" to="J1"><lane id="E0_0" index="0" speed="13" length="100" width="3.2" shape="0,-1.6 100,-1.6"/></edge>
  <edge id="E1" from="J1" to="J2"><lane id="E1_0" index="0" speed="13" length="100" width="3.2" shape="110,-1.6 210,-1.6"/></edge>
  <junction id="J1" type="traffic_light" x="105" y="0" shape="100,0 110,0 110,-3.2 100,-3.2"/>
  <connection from="E0" to="E1" fromLane="0" toLane="0" via=":J1_0_0" tl="J1" linkIndex="0" dir="s" state="O"/>
  <connection from=":J1_0" to="E1" fromLane="0" toLane="0" dir="s" state="M"/>
</net>
"""


def test_sumo_outline_and_signals(tmp_path):
    net = tmp_path / "n.net.xml"
    net.write_text(SUMO_NET)
    idx = RoadIndex(sumo_networks.read_network_areas(str(net)), edge_source="drivable_area")
    assert idx.edge_source == EDGE_SOURCE_ID["drivable_area"]
    # the outline of a one-way road along +x, drivable side on the left: counter-clockwise
    line = np.asarray(idx.map_edges.coords if idx.map_edges.geom_type == "LineString" else idx.map_edges.geoms[0].coords)
    area2 = np.sum(line[:-1, 0] * line[1:, 1] - line[1:, 0] * line[:-1, 1])
    assert area2 > 0
    links = sumo_networks.read_network_signals(str(net))
    assert len(links) == 1 and links[0].tl == "J1" and np.allclose(links[0].stop, [100, -1.6])
    assert np.allclose(links[0].lane[-1], [110, -1.6])  # the incoming lane, then the junction lane
    csv = tmp_path / "tls.csv"
    csv.write_text("tlsState_time;tlsState_id;tlsState_programID;tlsState_phase;tlsState_state\n"
                   "0.00;J1;0;0;G\n60.20;J1;0;1;y\n60.50;J1;0;2;r\n")
    ts = 60.0 + 0.1 * np.arange(10)
    sig = sumo_traffic.read_signal_states(str(csv), links, ts)
    go, caution, stop = (SIGNAL_STATE_ID[k] for k in ("go", "caution", "stop"))
    assert sig.state[:, 0].tolist() == [go, go, caution, caution, caution, stop, stop, stop, stop, stop]
    assert sumo_traffic.read_signal_states(str(csv), (), ts) is None


def test_sumo_build_has_outline_and_signals(tmp_path):
    """Determinism of a SUMO build with the traffic-light output (same seed -> identical store)."""
    from gpd_jax.data.sources import sumo

    sim = sumo_traffic.SimConfig(warmup_s=60.0, record_s=30.0)
    outs = []
    for k in range(2):
        out = str(tmp_path / f"ds{k}")
        sumo.build_sumo(out, 2, seed=7, workers=1, per_job=2, sim_cfg=sim)
        outs.append(out)
    a, b = (store.Shard(store.list_shards(o, s)[0]) for o in outs for s in store.list_splits(o)[:1])
    assert a.has_map_edges and a.has_signals
    for k in a.arrays:
        np.testing.assert_array_equal(np.asarray(a.arrays[k]), np.asarray(b.arrays[k]), err_msg=k)
    assert (np.asarray(a.arrays["road_edge_source"]) == EDGE_SOURCE_ID["drivable_area"]).all()
    # inspect --road-edges: where the edges come from and the log's own offroad rate on them (SUMO keeps to its road)
    from gpd_jax.data import inspection

    summary = inspection.road_edge_summary(outs[0])
    for split, r in summary.items():
        assert r["edge_sources"] == {"drivable_area": r["scenes"]} and r["agents"] > 0
        assert r["log_offroad_rate"] <= 0.05


def test_mirror_keeps_the_drivable_side_left():
    raw = scenarionet.scenario_to_rawlog(sfx.make_scenario(), "s0.pkl")
    (_, s), *_ = list(preprocess.iter_samples(raw, CFG))
    m = mirror_arrays(s)
    assert drivable_left_share(m) == pytest.approx(drivable_left_share(s), abs=1e-6)


# ------------------------------------------------------------------------------------------------ old stores
def test_format1_store_loads_and_scores_as_before(tmp_path):
    raw = scenarionet.scenario_to_rawlog(sfx.make_scenario(), "s0.pkl")
    samples = [s for _, s in preprocess.iter_samples(raw, CFG)][:2]
    arrays = store.stack_samples(samples)
    old = {k: v for k, v in arrays.items() if k not in MAP_EDGE_KEYS + SIGNAL_KEYS}
    d = str(tmp_path / "old")
    store.write_shard(d, "test", 0, old, ["a", "b"], ["x", "x"])
    sh = store.Shard(store.list_shards(d, "test")[0])
    assert sh.has_road and not sh.has_map_edges and not sh.has_signals
    scene, _ = loader.load_split(d, "test", with_polylines=True)
    assert scene.road.map_edges is None and scene.signals is None
    assert list(edge_source_names(scene.road)) == ["area_boundary_unoriented"] * 2
    # a shard with only part of a group is refused
    d2 = str(tmp_path / "half")
    store.write_shard(d2, "test", 0, {**old, "road_map_edges": arrays["road_map_edges"]}, ["a", "b"], ["x", "x"])
    with pytest.raises(Exception, match="keys incomplete"):
        store.Shard(store.list_shards(d2, "test")[0])


# ------------------------------------------------------------------------------------------------ red lights
def _signal_scene(state_name, t_n=12):
    """One lane along +x (y = 0) with a stop point at x = 0, a parallel lane at y = 3.5 without a signal; agent 0
    drives along y = 0 from x = -5.5 at 1 m per frame (crosses x = 0 between frames 5 and 6), agent 1 the same on
    y = 3.5, agent 2 stops before the line."""
    x = -5.5 + np.arange(t_n, dtype=np.float32)
    xy = np.zeros((t_n, 3, 2), np.float32)
    xy[:, 0, 0] = x
    xy[:, 1, 0], xy[:, 1, 1] = x, 3.5
    xy[:, 2, 0] = np.minimum(x, -1.0)
    valid = np.ones((t_n, 3), bool)
    s_n, q = 4, 16
    lane = np.zeros((s_n, q, 2), np.float32)
    lane_valid = np.zeros((s_n, q), bool)
    lane[0, :, 0] = np.arange(q) - 8.0
    lane_valid[0] = True
    state = np.zeros((t_n, s_n), np.int32)
    state[:, 0] = SIGNAL_STATE_ID[state_name]
    stop = np.zeros((s_n, 2), np.float32)
    sig = TrafficSignals(state=jnp.asarray(state), stop=jnp.asarray(stop), lane=jnp.asarray(lane),
                         lane_valid=jnp.asarray(lane_valid))
    lanes = np.zeros((2, 40, 2), np.float32)
    lanes[:, :, 0] = np.arange(40) - 20.0
    lanes[1, :, 1] = 3.5
    return jnp.asarray(xy), jnp.asarray(valid), sig, jnp.asarray(lanes), jnp.ones((2, 40), bool)


def test_red_light_run_flagged_green_not():
    fn = jax.jit(chex.assert_max_traces(
        lambda xy, v, sig, lanes, lv: red_light_violation(xy, v, signal_geometry(sig, lanes, lv)), n=1))
    xy, valid, sig, lanes, lv = _signal_scene("stop")
    red, beyond = fn(xy, valid, sig, lanes, lv)
    red = np.asarray(red)
    assert red[:, 0].tolist() == [False] * 6 + [True] + [False] * 5  # the crossing frame only
    assert not red[:, 1].any() and not red[:, 2].any() and int(beyond) == 0
    for name in ("go", "caution", "flashing_stop", "unknown"):
        assert not np.asarray(fn(*_signal_scene(name))[0]).any(), name
    assert np.asarray(fn(*_signal_scene("arrow_stop"))[0])[:, 0].any()
    # a crossing where the agent is invalid on either side does not count
    xy, valid, sig, lanes, lv = _signal_scene("stop")
    assert not np.asarray(fn(xy, valid.at[5, 0].set(False), sig, lanes, lv)[0]).any()


def test_official_red_light_run_flagged_green_not():
    """The official rules on the same scene (the signal's piece lies on the first centreline: that centreline is
    the signal's lane, `official_lanes`): the run on red flagged at its crossing frame, the same run on green,
    caution, flashing or unknown not, nor the agent on the next lane or the one that stops."""
    fn = jax.jit(chex.assert_max_traces(lambda xy, v, sig, lanes, lv: official_red_light_violation(
        xy, v, official_signal_geometry(sig, lanes, lv)), n=1))
    xy, valid, sig, lanes, lv = _signal_scene("stop")
    _, _, row, present = official_lanes(sig, lanes, lv)
    assert int(row[0]) == 0 and bool(present[0]) and not np.asarray(present[1:]).any()
    red, inexact = fn(xy, valid, sig, lanes, lv)
    red = np.asarray(red)
    assert red[:, 0].tolist() == [False] * 6 + [True] + [False] * 5
    assert not red[:, 1:].any() and int(inexact) == 0
    for name in ("go", "caution", "flashing_stop", "unknown"):
        assert not np.asarray(fn(*_signal_scene(name))[0]).any(), name
    assert np.asarray(fn(*_signal_scene("arrow_stop"))[0])[:, 0].any()
    # the official rule asks validity at the crossing frame only
    assert np.asarray(fn(xy, valid.at[5, 0].set(False), sig, lanes, lv)[0])[6, 0]
    assert not np.asarray(fn(xy, valid.at[6, 0].set(False), sig, lanes, lv)[0]).any()


def test_official_lane_test_is_the_official_codes_nearest_segment():
    """The official nearest-segment distance adds the projection where the true one subtracts it: a point 0.05 m
    off a lane, 0.9 of the way along a 1 m segment, is 1.8 m from that segment and 0.1 m from the next one."""
    p = jnp.array([0.9, 0.05])
    a, b = jnp.array([[0.0, 0.0], [1.0, 0.0]]), jnp.array([[1.0, 0.0], [2.0, 0.0]])
    d = official_segment_distance(p, a, b, jnp.ones(2, bool))
    np.testing.assert_allclose(np.asarray(d), [np.hypot(1.8, 0.05), np.hypot(0.1, 0.05)], rtol=1e-6)


def test_red_light_budget_counts_the_rest_as_violations():
    # agents 0 and 1 both cross the stop point's line (agent 1 on the next lane): two candidate crossings; with a
    # budget of one, agent 0's (first in frame-major order) is tested exactly, agent 1's is counted as a violation
    xy, valid, sig, lanes, lv = _signal_scene("stop")
    fn = jax.jit(lambda xy, v, sig, lanes, lv, max_events: red_light_violation(
        xy, v, signal_geometry(sig, lanes, lv), max_events), static_argnames="max_events")
    red, beyond = fn(xy, valid, sig, lanes, lv, max_events=1)
    assert int(beyond) == 1 and np.asarray(red)[:, :2].any(0).all() and not np.asarray(red)[:, 2].any()
    red, beyond = fn(xy, valid, sig, lanes, lv, max_events=2)
    assert int(beyond) == 0 and np.asarray(red).any(0).tolist() == [True, False, False]


def test_realism_2025_scores_traffic_lights_only_with_signals():
    xy, valid, sig, lanes, lv = _signal_scene("stop")
    t_n = xy.shape[0]
    hd = jnp.zeros(valid.shape)
    size = jnp.broadcast_to(jnp.array([4.5, 1.9]), (3, 2))
    sims = jnp.stack([xy, xy.at[:, 0, 0].set(jnp.minimum(xy[:, 0, 0], -1.0))])  # one run, one stop
    k = sims.shape[0]
    score = jax.jit(lambda *a, **kw: realism.scenario_realism(*a, num_history=3, **kw))
    common = (jnp.zeros((k, t_n, 3)), jnp.ones((k, t_n, 3), bool), xy, hd, valid, size)
    with_sig = score(sims, *common, signals=sig, lanes=lanes, lane_valid=lv)
    without = score(sims, *common)
    assert "traffic_light_violation_likelihood" in with_sig and "traffic_light_violation_likelihood" not in without
    # the log runs the light; one of the two rollouts does: likelihood (1 + p) / (2 + 2p) on agent 0, 1 elsewhere
    assert float(with_sig["red_light_rate"]) == pytest.approx(0.5 / 3, rel=1e-5)
    r = realism.reduce_realism({k: np.asarray(v)[None] for k, v in with_sig.items()}, "2025", has_road=False,
                               has_signals=True)
    assert "traffic_light_violation" in r["weights"] and "traffic_light_violation" not in r["left_out"]


def test_lane_union_gate_leaves_map_terms_out():
    from gpd_jax.evaluation.realism import reduce_groups

    rng = np.random.default_rng(0)
    names = list(realism.CONFIGS["2025"])
    per = {k: rng.uniform(0.2, 0.9, 4) for k in (f"{n}_likelihood" for n in names if n != "traffic_light_violation")}
    per.update(metametric=rng.uniform(0.2, 0.9, 4), offroad_rate=np.array([0.0, 0.5, 0.5, 0.0]),
               collision_rate=np.zeros(4), min_ade=np.ones(4))
    groups = {"log": dict(per), "constant_velocity": dict(per)}
    out = reduce_groups(groups, [], 4, "2025", True, False, ["lane_union"] * 4)
    assert set(out["left_out"]) == {"distance_to_road_edge", "offroad_indication", "traffic_light_violation"}
    assert out["road_edges"]["map_terms"] == "left out" and out["road_edges"]["log_offroad_rate_on_lane_union"] == 0.25
    w = realism.realism_weights("2025", has_road=False)
    want = np.mean(sum(wt * per[f"{n}_likelihood"] for n, wt in w.items()))
    assert out["baselines"]["log"]["metametric"] == pytest.approx(want, rel=1e-9)
    kept = reduce_groups(groups, [], 4, "2025", True, False, ["map_lines"] * 4)
    assert "offroad_indication" not in kept["left_out"] and kept["road_edges"]["scenes"] == {"map_lines": 4}


def test_lane_piece_around_the_stop_point():
    lane = np.array([[0.0, 0.0], [30.0, 0.0]])
    piece = lane_piece(lane, np.array([20.0, 0.4]))
    assert len(piece) == 16 and piece[0, 0] == pytest.approx(12.0) and piece[-1, 0] == pytest.approx(27.0)
    assert len(lane_piece(lane, np.array([2.0, 0.0]))) == 10  # clipped at the lane's start
    with pytest.raises(ValueError, match="disagree"):
        RawSignals(stop=np.zeros((2, 2)), lane=(lane,), state=np.zeros((5, 1), np.int8))
