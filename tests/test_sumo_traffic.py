"""Real-traffic options of the SUMO build: parked and stopping vehicles, heterogeneous drivers, stationary egos,
left-hand networks and the gridlock gate that tells parked vehicles from jams."""

import dataclasses
import json
import os
import re
from collections import Counter

import numpy as np
import pytest

from gpd_jax.data import jobs, preprocess, store
from gpd_jax.data.__main__ import main, traffic_options
from gpd_jax.data.errors import DataError
from gpd_jax.data.raw import RawLog
from gpd_jax.data.sources import sumo, sumo_networks, sumo_traffic
from gpd_jax.geometry import AREA_KIND_ID
from gpd_jax.scene import TYPE_ID

TINY_SIM = sumo_traffic.SimConfig(warmup_s=60.0, record_s=12.0)


@pytest.fixture(scope="module")
def lefthand_store(tmp_path_factory):
    """A one-network build (2 samples) with the default traffic options on a left-hand generated network."""
    out = str(tmp_path_factory.mktemp("traffic") / "lh")
    man = sumo.build_sumo(out, 2, seed=6, workers=1, per_job=2, split="train", sim_cfg=TINY_SIM,
                          lefthand_share=1.0)
    return out, man


def test_lefthand_build_with_parked_vehicles(lefthand_store):
    out, man = lefthand_store
    assert man["num_samples"] == 2, man["build"]["rejections"]
    (loc, net), = man["build"]["networks"].items()
    assert net["lefthand"] is True
    # netconvert's output is marked left-hand, and the recorded spec says so
    idx = json.load(open(os.path.join(out, "_networks", "index.json")))
    path = os.path.join(out, idx[loc]["net"])
    assert sumo_networks.is_lefthand(path) and idx[loc]["spec"]["lefthand"] is True
    lefthand, edges = sumo_networks.read_network_edges(path)
    assert lefthand and edges
    tr = man["build"]["traffic"]
    assert tr["ego_rule"] == "mixed" and tr["drivers"] == "heterogeneous" and tr["parking_edge_share"] > 0
    assert man["build"]["sample_config"]["min_ego_travel"] == 0.0  # the mixed rule has no travel minimum
    assert man["build"]["stats"]["sim_parked_vehicles"] > 0
    sh = store.Shard(store.list_shards(out, "train")[0])
    assert sh.meta["lefthand"] is True and sh.meta["traffic"] == tr
    a = {k: np.asarray(v) for k, v in sh.arrays.items()}
    valid, xy = a["valid"], a["xy"].astype(np.float64)
    whole = valid.all(1)  # [B, A] agents present in every frame
    spread = np.linalg.norm(xy - xy[:, :1], axis=-1).max(1)  # [B, A] furthest from the first frame
    parked = whole & (spread < 0.05)
    parked[:, 0] = False
    assert parked.sum() >= 2, "no recorded agent stands still across the window"
    # parked vehicles stand on the parking strips (drivable kind "other") left of their lane: left-hand traffic
    import jax
    import jax.numpy as jnp

    from gpd_jax import geometry as geo
    from gpd_jax.data import loader
    scene, _ = loader.load_split(out, "train", with_polylines=True)
    on_strip = 0
    for b, j in zip(*np.nonzero(parked)):  # never moving: parked, or waiting at a light the whole window
        road = jax.tree.map(lambda x: jnp.asarray(x[b]), scene.road)
        kinds = np.asarray(geo.area_kinds(road, jnp.asarray(xy[b, 20, j], jnp.float32)))
        if not kinds[AREA_KIND_ID["other"]]:
            continue
        on_strip += 1
        # the nearest lane point: the parked box lies to its left (counter-clockwise of the heading)
        lanes = np.asarray(scene.polylines)[b][np.asarray(scene.polyline_valid)[b]]
        k = np.argmin(np.linalg.norm(lanes - xy[b, 20, j], axis=-1))
        h = float(a["heading"][b, 20, j])
        d = xy[b, 20, j] - lanes[k]
        assert np.cos(h) * d[1] - np.sin(h) * d[0] > 0.5
    assert on_strip >= 2
    # an old-style call of the loader still works on this store, and inspect reports the new figures
    from gpd_jax.data import inspection
    s = inspection.inspect(out, with_lanes=False)
    assert 0.0 < s["agents_never_moving_fraction"] <= 1.0 and s["agent_stationary_fraction"] > 0.0
    assert 0.0 <= s["stationary_agents_that_go_fraction"] < 1.0
    assert s["agents_stationary_on_other_area_fraction"] > 0.0 and s["agents_stationary_in_lanes_fraction"] >= 0.0
    assert s["ego_stationary_at_current_fraction"] is not None and s["traffic"] == tr


def test_heterogeneous_drivers_short_stops_and_parking_files(tmp_path):
    spec = dataclasses.replace(sumo_networks.random_net_spec(3, "grid"), size=3, size2=3, lanes=1)
    net = sumo_networks.generate_network(spec, str(tmp_path / "g.net.xml"))
    wd = tmp_path / "wd"
    wd.mkdir()
    info = {}
    cfg = dataclasses.replace(TINY_SIM, record_s=2.0, short_stop_share=0.5, min_vehicles=1)
    raw = sumo_traffic.simulate(net, "x", "loc", 7, cfg, workdir=str(wd), info=info)
    drivers = (wd / "drivers.add.xml").read_text()
    assert len(re.findall(r"<vTypeDistribution ", drivers)) == len(sumo_traffic.VEHICLE_MIX)
    variants = re.findall(r'<vType id="g_car\.\d+"[^>]*>', drivers)
    assert len(variants) == cfg.driver_variants
    assert len(set(re.findall(r'carFollowModel="(\w+)"', drivers))) >= 2
    for attr in ("sigma", "tau", "lcAssertive", "lcSpeedGain"):
        assert len(set(re.findall(rf'{attr}="([\d.]+)"', drivers))) >= 4, attr
    routes = (wd / "routes.xml").read_text()
    # the vehicles name the size classes, which are the distributions: SUMO draws each vehicle's driver
    assert set(re.findall(r'<vehicle id="\d+" type="(\w+)"', routes)) <= {m[0] for m in sumo_traffic.VEHICLE_MIX}
    assert info["short_stops"] > 0 and routes.count("<stop lane=") == info["short_stops"]
    assert info["parked_vehicles"] > 0 and "parkingArea" in (wd / "parking.add.xml").read_text()
    assert info["planned_stop_frames"] > 0
    assert any(a.kind == AREA_KIND_ID["other"] for a in raw.areas)
    # uniform drivers: one IDM type per class (the stores built before), no distribution file
    wd2 = tmp_path / "wd2"
    wd2.mkdir()
    sumo_traffic.simulate(net, "x", "loc", 7, dataclasses.replace(cfg, **sumo_traffic.LEGACY_TRAFFIC), workdir=str(wd2))
    assert not (wd2 / "drivers.add.xml").exists() and not (wd2 / "parked.rou.xml").exists()
    assert "<stop" not in (wd2 / "routes.xml").read_text()


def _stop_and_go_log() -> RawLog:
    """12 vehicles in a row on a straight road, 10 m apart: track 0 stands until frame 60 then drives off at
    5 m/s; track 1 is parked (never moves); the others drive at 8 m/s."""
    F, N = 140, 12
    t = np.arange(F) * 0.1
    x = np.zeros((F, N))
    x[:, 0] = np.where(t < 6.0, 0.0, 5.0 * (t - 6.0))
    x[:, 1] = 30.0
    for j in range(2, N):
        x[:, j] = 10.0 * j + 20.0 + 8.0 * t
    y = np.zeros((F, N))
    y[:, 1] = 3.5  # beside the lane
    xy = np.stack([x, y], -1)
    s = np.linspace(-50, 400, 451)
    return RawLog("stopgo", "loc", t, tuple(str(i) for i in range(N)), xy, np.zeros((F, N)), np.ones((F, N), bool),
                  np.tile(np.array([[4.6, 1.85]], np.float32), (N, 1)), np.full((N,), TYPE_ID["car"], np.int32),
                  (np.stack([s, np.zeros_like(s)], -1),))


def test_stationary_ego_rule():
    raw = _stop_and_go_log()
    cfg = preprocess.SampleConfig(min_neighbours=3, min_ego_travel=30.0)
    still = sumo.EgoChoice("mixed", 1.0)
    wins = sumo.sumo_windows(raw, cfg, 10, np.random.default_rng(0), still)
    assert wins, "no window with a stationary ego"
    c = cfg.current
    for s, e in wins:
        speed = np.linalg.norm(raw.agent_xy[s + c, e] - raw.agent_xy[s + c - 1, e]) / 0.1
        assert speed < 0.5 and e == 0  # track 0 waits and then goes; the parked track 1 is never an ego
    # the samples themselves: ego stopped at the current frame, then moving
    stats = Counter()
    samples = list(sumo.iter_sumo_samples(raw, cfg, 3, 0, stats, still))
    assert len(samples) == 3 and stats["ego_stationary_at_current"] == 3
    xy0 = samples[0][1]["xy"][:, 0]
    assert np.linalg.norm(xy0[c] - xy0[c - 1]) < 0.05 and np.linalg.norm(xy0[-1] - xy0[c]) > 2.0
    # the default mix: about a quarter stationary; the legacy travel rule: never this waiting ego
    mixed = sumo.sumo_windows(raw, cfg, 8, np.random.default_rng(1), sumo.EgoChoice())
    n_still = sum(np.linalg.norm(raw.agent_xy[s + c, e] - raw.agent_xy[s + c - 1, e]) < 0.05 for s, e in mixed)
    assert len(mixed) == 8 and n_still == 2
    legacy = sumo.sumo_windows(raw, cfg, 20, np.random.default_rng(0), sumo.LEGACY_EGO)
    assert legacy and all(np.linalg.norm(raw.agent_xy[s + c, e] - raw.agent_xy[s + c - 1, e]) > 0.05
                          for s, e in legacy)
    with pytest.raises(DataError, match="ego rule"):
        sumo.EgoChoice("random")


def _write_fcd(path, speeds):
    """An FCD CSV of vehicles on a line: `speeds f[F, N]` (a stopped vehicle stays where it is)."""
    F, N = speeds.shape
    x = np.cumsum(speeds * 0.1, axis=0) + 20.0 * np.arange(N)
    rows = ["timestep_time;vehicle_id;vehicle_x;vehicle_y;vehicle_angle;vehicle_speed"]
    for f in range(F):
        for n in range(N):
            rows.append(f"{120 + 0.1 * f:.2f};{n};{x[f, n]:.3f};0.0;90.0;{speeds[f, n]:.3f}")
    path.write_text("\n".join(rows) + "\n")


def test_gridlock_gate_tells_parked_from_jammed(tmp_path):
    F, N = 50, 10
    sp = np.full((F, N), 8.0)
    sp[:, :7] = 0.0  # 7 of 10 vehicles stand for the whole recording
    f = tmp_path / "fcd.csv"
    _write_fcd(f, sp)
    cfg = sumo_traffic.SimConfig()
    with pytest.raises(sumo_networks.SumoRunRejected, match="gridlock"):  # a jam: nothing planned
        sumo_traffic._fcd_to_rawlog(str(f), {}, "x", "loc", cfg)
    planned = {n: [(0.0, np.inf)] for n in range(7)}  # parked (their stops never end)
    info = {}
    raw = sumo_traffic._fcd_to_rawlog(str(f), {}, "x", "loc", cfg, planned_stops=planned, info=info)
    assert raw.num_agents == N and info["jam_stopped_fraction"] == 0.0 and info["stopped_fraction"] == 0.7
    # parked vehicles do not hide a jam among the others
    sp[:, 7:9] = 0.0
    _write_fcd(f, sp)
    with pytest.raises(sumo_networks.SumoRunRejected, match="gridlock"):
        sumo_traffic._fcd_to_rawlog(str(f), {}, "x", "loc", cfg, planned_stops={n: [(0.0, np.inf)] for n in range(5)})
    # stop output as SUMO writes it (CSV, unfinished stops end at -1)
    so = tmp_path / "stops.csv"
    so.write_text("stopinfo_id;stopinfo_type;stopinfo_started;stopinfo_ended\n3;g_car.1;10.0;-1\n4;g_car;5;25.5\n")
    assert sumo_traffic._read_planned_stops(str(so)) == {3: [(10.0, np.inf)], 4: [(5.0, 25.5)]}


def test_parking_jumps_are_smoothed():
    F = 60
    xy = np.zeros((F, 1, 2))
    xy[:, 0, 0] = 10.0
    xy[30:, 0, 1] = 3.2  # the step from the space onto the lane in one frame
    n = sumo_traffic.smooth_parking_jumps(xy, np.ones((F, 1), bool), np.zeros((F, 1)))
    steps = np.linalg.norm(np.diff(xy[:, 0], axis=0), axis=-1)
    assert n == 1 and steps.max() < 0.25 and abs(xy[0, 0, 1]) < 1e-9 and abs(xy[-1, 0, 1] - 3.2) < 1e-9
    assert np.all(xy[30:, 0, 1] == 3.2)  # parking: only the frames on the lane (before the jump) move
    # leaving: stationary in the space (y = 0), then on the lane (y = 3.2) and moving: only the lane side moves
    xy = np.zeros((F, 1, 2))
    xy[30:, 0, 1] = 3.2
    xy[31:, 0, 0] = np.cumsum(np.full(F - 31, 0.2))
    speed = np.zeros((F, 1))
    speed[30:] = 2.0
    assert sumo_traffic.smooth_parking_jumps(xy, np.ones((F, 1), bool), speed) == 1
    assert np.all(xy[:30, 0, 1] == 0.0) and np.diff(xy[29:, 0, 1]).max() < 0.6 and abs(xy[-1, 0, 1] - 3.2) < 1e-9


def test_options_cli_and_old_settings(tmp_path):
    class A:
        traffic, parking_edge_share, parking_occupancy, parked_leave_share = "legacy", None, None, None
        short_stop_share, drivers, ego_rule, ego_stationary_share = None, None, None, None
        lefthand_share, static_tls_share, curved_share = None, None, None

    o = traffic_options(A)
    assert o["ego"] == sumo.LEGACY_EGO and o["lefthand_share"] == 0.0 and o["static_tls_share"] == 0.0
    assert o["traffic"] == sumo_traffic.LEGACY_TRAFFIC
    A.traffic, A.parking_occupancy = "realistic", 0.9
    o = traffic_options(A)
    assert o["traffic"] == {"parking_occupancy": 0.9} and o["ego"] == sumo.EgoChoice()
    for bad in (["--parking-occupancy", "1.5"], ["--source", "nuplan", "--drivers", "uniform"]):
        assert main(["build", "--out", str(tmp_path / "o"), *bad]) == 2
    assert main(["build", "--out", str(tmp_path / "o"), "--scenarios", "1", "--ego-stationary-share", "0.5",
                 "--ego-rule", "mixed", "--drivers", "uniform", "--net", str(tmp_path / "missing.net.xml")]) == 2
    with pytest.raises(DataError, match="driver"):
        sumo_traffic.check_sim_config(dataclasses.replace(sumo_traffic.SimConfig(), drivers="crazy"))
    # a store built before the traffic options: the error says how to resume it
    out = tmp_path / "old"
    (out / "_jobs").mkdir(parents=True)
    (out / "_jobs" / "settings.json").write_text(json.dumps({"source": "sumo", "seed": 0}))
    (out / "_jobs" / "job_00000.json").write_text("{}")
    assert sumo._built_before_traffic_options(str(out))
    with pytest.raises(DataError, match="--traffic legacy"):
        jobs.check_settings(str(out), {"source": "sumo", "seed": 0, "traffic": {}})
    # specs without the options are those drawn before them; the shares draw from their own stream
    assert sumo_networks.random_net_spec(9) == dataclasses.replace(sumo_networks.random_net_spec(9, None, 1.0, 1.0),
                                                                   lefthand=False, tls_type="actuated")
    assert sum(sumo_networks.random_net_spec(s, None, 0.25).lefthand for s in range(200)) in range(30, 71)
    assert sumo_networks.random_net_spec(9, None, 1.0, 1.0) == dataclasses.replace(
        sumo_networks.random_net_spec(9, None, 1.0, 1.0, 1.0), bend=0.0)
    bends = [sumo_networks.random_net_spec(s, None, 0.0, 0.0, 0.5).bend for s in range(200)]
    assert sum(b > 0 for b in bends) in range(70, 131)
    assert all(b == 0 or sumo_networks.BEND_RANGE[0] <= b <= sumo_networks.BEND_RANGE[1] for b in bends)
    # bending is for generated networks: with given ones the flag is refused, not ignored
    assert main(["build", "--out", str(tmp_path / "o"), "--scenarios", "1", "--curved-share", "0.5",
                 "--net", str(tmp_path / "missing.net.xml")]) == 2


def test_curved_streets_share_one_centreline_per_road():
    nod = ('<nodes><node id="a" x="0.00" y="0.00" type="priority"/><node id="b" x="200.00" y="0.00"/>'
           '<node id="c" x="200.00" y="20.00"/></nodes>')
    edg = ('<edges><edge id="ab" from="a" to="b" numLanes="1"/><edge id="ba" from="b" to="a" numLanes="1"/>'
           '<edge id="bc" from="b" to="c" numLanes="1"/></edges>')
    spec = dataclasses.replace(sumo_networks.random_net_spec(4, "grid"), bend=0.2)
    out = sumo_networks._bend_edges(edg, nod, spec)
    assert out == sumo_networks._bend_edges(edg, nod, spec)  # deterministic in the seed

    def shape(eid):
        m = re.search(rf'<edge id="{eid}"[^>]*?shape="([^"]+)"', out)
        return None if m is None else np.array([[float(v) for v in p.split(",")] for p in m.group(1).split()])

    ab, ba = shape("ab"), shape("ba")
    assert shape("bc") is None  # 20 m: too short to bend
    if ab is None:  # this seed drew a straight street: both directions stay straight
        assert ba is None
        return
    np.testing.assert_allclose(ab, ba[::-1])  # one road, two directions: the same centreline
    np.testing.assert_allclose(ab[[0, -1]], [[0, 0], [200, 0]])
    assert 0.95 * 0.5 * 0.2 * 200 * 0.6 <= np.abs(ab[:, 1]).max() <= 0.2 * 200 + 1e-6
    assert np.all(np.diff(ab[:, 0]) > 0) and np.diff(ab[:, 0]).max() <= 4.0 + 1e-6


def test_curved_network_lanes_turn_along_their_streets(tmp_path):
    base = dataclasses.replace(sumo_networks.random_net_spec(3, "grid"), size=3, size2=3)

    def max_turn(spec):  # the largest heading change along one lane chain between junctions
        net = sumo_networks.generate_network(spec, str(tmp_path / f"{spec.bend}.net.xml"))
        _, edges = sumo_networks.read_network_edges(net)
        turns = [0.0]
        for e in edges:
            d = np.diff(np.asarray(e.shape), axis=0)
            h = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
            turns.append(float(h.max() - h.min()))
        return max(turns)

    assert max_turn(base) < 0.05
    assert max_turn(dataclasses.replace(base, bend=0.2)) > 0.6


def test_static_lights_and_lefthand_in_the_network_file(tmp_path):
    spec = dataclasses.replace(sumo_networks.random_net_spec(2, "grid"), size=3, size2=3, junction="traffic_light",
                               tls_type="static", lefthand=True)
    text = sumo_networks._open_xml(sumo_networks.generate_network(spec, str(tmp_path / "s.net.xml"))).read().decode()
    types = set(re.findall(r'<tlLogic [^>]*type="(\w+)"', text))
    assert types == {"static"} and re.search(r'<net [^>]*lefthand="true"', text)
    with pytest.raises(ValueError, match="tls_type"):
        sumo_networks.generate_network(dataclasses.replace(spec, tls_type="smart"), str(tmp_path / "x.net.xml"))


def test_given_network_as_a_lefthand_copy(tmp_path):
    spec = dataclasses.replace(sumo_networks.random_net_spec(6, "grid"), size=3, size2=3)
    net = sumo_networks.generate_network(spec, str(tmp_path / "given" / "town.net.xml"))
    assert not sumo_networks.is_lefthand(net)
    jobs = sumo.plan_sumo_jobs(4, 0, [net], per_job=2, split="train", lefthand_share=1.0)
    assert all(j.lefthand_net and j.location == "given_town_lh" for j in jobs)
    assert not any(j.lefthand_net for j in sumo.plan_sumo_jobs(4, 0, [net], per_job=2, split="train"))
    out = str(tmp_path / "store")
    man = sumo.build_sumo(out, 2, seed=0, nets=[net], workers=1, per_job=2, split="train", sim_cfg=TINY_SIM,
                          lefthand_share=1.0)
    assert man["num_samples"] == 2, man["build"]["rejections"]
    idx = json.load(open(os.path.join(out, "_networks", "index.json")))
    rec = idx["given_town_lh"]
    assert rec["lefthand"] and rec["source_net"] == os.path.abspath(net)
    assert sumo_networks.is_lefthand(os.path.join(out, rec["net"])) and not sumo_networks.is_lefthand(net)
    sh = store.Shard(store.list_shards(out, "train")[0])
    assert sh.meta["lefthand"] is True and sh.meta["net"] == net and sh.meta["traffic"]["lefthand_share"] == 1.0


def test_point_in_kind_even_odd():
    from gpd_jax.data.inspection import point_in_kind

    sq = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], np.float32)
    hole = np.array([[4, 4], [6, 4], [6, 6], [4, 6]], np.float32)
    rings = np.zeros((3, 6, 2), np.float32)
    valid = np.zeros((3, 6), bool)
    rings[0, :4], valid[0, :4] = sq, True
    rings[1, :4], valid[1, :4] = hole, True
    rings[2, :4], valid[2, :4] = sq + 20, True  # another kind
    kind = np.array([AREA_KIND_ID["other"], AREA_KIND_ID["other"], AREA_KIND_ID["lane"]])
    pts = np.array([[1, 1], [5, 5], [11, 5], [25, 25], [9.5, 0.5]])
    assert point_in_kind(pts, rings, valid, kind, AREA_KIND_ID["other"]).tolist() == [True, False, False, False, True]
    assert point_in_kind(pts, rings, valid, kind, AREA_KIND_ID["lane"]).tolist() == [False, False, False, True, False]
    assert point_in_kind(np.zeros((0, 2)), rings, valid, kind, 0).shape == (0,)
