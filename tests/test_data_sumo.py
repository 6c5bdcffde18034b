"""Tiny end-to-end SUMO builds (generated and real networks), resume, splits by network, nuPlan wiring."""

import dataclasses
import json
import os

import numpy as np
import pytest

from gpd_jax.data import loader, preprocess, store
from gpd_jax.data.sources import nuplan, sumo, sumo_networks, sumo_traffic
from gpd_jax.data.__main__ import main

SMALL_SIM = sumo_traffic.SimConfig(warmup_s=60.0, record_s=30.0)


def test_net_spec_varies_and_splits_by_network():
    specs = {(s.layout, s.lanes, s.junction) for s in map(sumo_networks.random_net_spec, range(30))}
    assert {l for l, _, _ in specs} == {"random", "grid", "spider"} and {n for _, n, _ in specs} == {1, 2, 3}
    jobs = sumo.plan_sumo_jobs(1000, 0, None)
    assert len(jobs) == 20 and sum(j.num_samples for j in jobs) == 1000
    by_split = {}
    for j in jobs:
        by_split.setdefault(j.split, set()).add(j.location)
        assert j.location.endswith("_" + j.layout)
    # layouts take turns (7 + 7 + 6 networks); splits are stratified by layout: one val and one test network each
    assert {k: len(v) for k, v in by_split.items()} == {"train": 14, "val": 3, "test": 3}
    for sp in ("val", "test"):
        assert sorted(j.layout for j in jobs if j.split == sp and j.num_samples) == ["grid", "random", "spider"]
    assert all(j.split == "val" for j in sumo.plan_sumo_jobs(100, 0, None, split="val"))


def test_tiny_build_resume_and_load(tmp_path):
    out = str(tmp_path / "ds")
    man = sumo.build_sumo(out, 4, seed=3, workers=1, per_job=2, sim_cfg=SMALL_SIM)
    assert man["num_samples"] == 4 and man["build"]["build_wall_s"] > 0
    gate = man["build"]["overlap_gate"]
    assert gate["enabled"] and gate["windows_checked"] == 4 + gate["windows_removed"]
    layouts = {sh["locations"][0]: sh["layout"] for v in man["splits"].values() for sh in v["shards"]}
    assert all(loc.endswith("_" + lay) and lay in sumo_networks.LAYOUTS for loc, lay in layouts.items())
    assert sum(e["locations"] for e in man["build"]["layouts"].values()) == 2
    locs = {s: {l for sh in v["shards"] for l in sh["locations"]} for s, v in man["splits"].items()}
    assert sum(len(v) for v in locs.values()) == 2  # two networks, each in exactly one split
    scene = loader.load_split(out, next(iter(man["splits"])))
    scene.validate()
    assert scene.valid[:, :, 0].all() and np.abs(scene.xy[:, 20, 0]).max() < 1e-4
    assert (scene.size[:, 0, 0] >= 4.0).all()
    # drivable area: every sample has it, and SUMO's vehicles drive on it, along their lanes
    import jax
    import jax.numpy as jnp

    from gpd_jax import geometry as geo
    withroad, _ = loader.load_split(out, next(iter(man["splits"])), with_polylines=True)
    road = jax.tree.map(jnp.asarray, withroad.road)
    assert road.polygon_valid.any(-1).any(-1).all() and road.edge_valid.any(-1).any(-1).all()
    on = np.asarray(jax.jit(jax.vmap(geo.on_road))(road, jnp.asarray(withroad.xy)))
    valid = np.asarray(withroad.valid)
    assert on[:, :, 0].all() and on[valid].mean() > 0.98
    heading, dist = jax.jit(jax.vmap(geo.lane_direction))(road, jnp.asarray(withroad.xy[:, :, 0]))
    err = np.abs(np.angle(np.exp(1j * (np.asarray(heading) - np.asarray(withroad.heading[:, :, 0])))))
    assert np.median(err) < 0.05 and np.median(np.asarray(dist)) < 0.5
    # resume: a killed job (no marker, a stale temporary) is redone, finished jobs are not
    marker = os.path.join(out, "_jobs", "job_00001.json")
    old0 = json.load(open(os.path.join(out, "_jobs", "job_00000.json")))
    os.remove(marker)
    os.makedirs(os.path.join(out, "train", ".tmp-shard_00001-dead"))
    man2 = sumo.build_sumo(out, 4, seed=3, workers=1, per_job=2, sim_cfg=SMALL_SIM)
    assert man2["num_samples"] == 4 and os.path.isfile(marker)
    assert json.load(open(os.path.join(out, "_jobs", "job_00000.json"))) == old0
    assert not any(n.startswith(".tmp-") for n in os.listdir(os.path.join(out, "train")))
    with pytest.raises(ValueError, match="other settings"):
        sumo.build_sumo(out, 6, seed=3, workers=1, per_job=2, sim_cfg=SMALL_SIM)


def test_real_network_build(tmp_path):
    net = os.path.join(sumo_networks.sumo_home(), "tools", "game", "fokr_bs_demo", "fokr_bs.net.xml.gz")
    if not os.path.isfile(net):
        pytest.skip("SUMO's fokr_bs_demo network is not installed")
    lanes = sumo_networks.read_network_lanes(net)
    assert len(lanes) > 20
    out = str(tmp_path / "real")
    cfg = dataclasses.replace(sumo_traffic.REAL_NETWORK_SIM, warmup_s=120.0, record_s=40.0)
    man = sumo.build_sumo(out, 2, seed=0, nets=[net], workers=1, per_job=2, split="test", sim_cfg=cfg)
    assert man["num_samples"] == 2, man["build"]["rejections"]
    assert man["splits"]["test"]["shards"][0]["locations"] == ["fokr_bs_demo_fokr_bs"]


def test_real_networks_listed_and_built_as_an_ungated_test_split(tmp_path):
    nets = sumo_networks.real_networks()
    if len(nets) < 6:
        pytest.skip("this SUMO install lacks some of the shipped real networks")
    assert {os.path.basename(os.path.dirname(n)) for n in nets} == {"A10KW", "DRT", "bs3d", "fkk_in", "fokr_bs_demo",
                                                                     "highway"}
    assert sumo_networks.real_networks(scan=True) == nets  # the scan of SUMO_HOME finds exactly these
    out = str(tmp_path / "real")
    assert main(["build", "--real-networks", "fokr_bs_demo", "--out", out, "--split", "test", "--scenarios", "3",
                 "--per-job", "3", "--workers", "1", "--keep-overlaps"]) == 0
    man = store.read_manifest(out)
    b = man["build"]
    assert b["layouts"] == {"real": {"locations": 1, "samples": {"test": man["num_samples"]}}}
    assert b["net_layout"] == "real" and b["sample_config"]["reject_overlaps"] is False
    gate = b["overlap_gate"]
    assert not gate["enabled"] and gate["windows_removed"] == 0 and gate["windows_checked"] == man["num_samples"]
    assert 0 <= gate["windows_with_overlaps"] <= gate["windows_checked"]
    assert store.sample_layouts(out, "test") == ["real"] * man["num_samples"]
    from gpd_jax.data import inspection

    s = inspection.inspect(out, with_lanes=False)
    assert s["samples_per_layout"] == {"real": {"test": man["num_samples"]}} and s["overlap_gate"] == gate


def test_teleported_tracks_are_dropped():
    from data_fixtures import straight_road_log
    raw = straight_road_log()
    xy = raw.agent_xy.copy()
    xy[70:, 5] += 50.0  # a 50 m jump between two frames
    raw = dataclasses.replace(raw, agent_xy=xy)
    out = sumo_traffic.drop_discontinuous_tracks(raw)
    assert not out.agent_valid[:, 5].any() and out.agent_valid[:, 4].all()
    assert out.agent_valid[:60, 1].all()  # track 1 just ends (leaves the network): kept


def test_nuplan_wiring(tmp_path):
    """`build --source nuplan` runs gpd_jax.data.sources.nuplan.iter_logs on the nuPlan fixture (short windows)."""
    nfx = pytest.importorskip("nuplan_fixtures")
    nfx.write_maps_root(tmp_path / "maps")
    (tmp_path / "logs").mkdir()
    nfx.write_log_db(tmp_path / "logs" / "2021.05.12.22.00.38_veh-35_01008_01518.db")
    cfg = preprocess.SampleConfig(num_history=5, num_future=10, window_stride=5)
    man = nuplan.build_nuplan(str(tmp_path / "out"), str(tmp_path / "logs"), str(tmp_path / "maps"), split="test",
                              sample_cfg=cfg)
    assert man["num_samples"] >= 2
    scene = loader.load_split(str(tmp_path / "out"), "test")
    scene.validate()
    assert scene.xy.shape[1:] == (15, 33, 2) and scene.valid[:, :, 0].all()
    np.testing.assert_allclose(scene.xy[:, 4, 0], 0.0, atol=1e-4)
    # too-short windows for the default config: no samples, counted
    man = nuplan.build_nuplan(str(tmp_path / "out2"), str(tmp_path / "logs"), str(tmp_path / "maps"))
    assert man["num_samples"] == 0 and man["build"]["stats"]["skip_log_too_short"] == 1
