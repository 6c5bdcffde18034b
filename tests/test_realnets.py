"""Real-road training / development tiles: disjoint from the test networks and from each other, cached."""

import json
import os

import numpy as np
import pytest

from gpd_jax.data.__main__ import main as data_main
from gpd_jax.data.sources import realnets, sumo_networks
from gpd_jax.data.errors import DataError


def _boxes_intersect(a, b):
    return not (a[2] < b[0] or b[2] < a[0] or a[3] < b[1] or b[3] < a[1])


def test_catalogue_splits_and_boxes():
    cat = realnets.catalogue()
    names = [t["name"] for t in cat["tiles"]]
    assert len(names) == len(set(names))
    assert {t["split"] for t in cat["tiles"]} == {"train", "dev"}
    test_refs = set(realnets.TEST_ONLY)
    for t in cat["tiles"]:
        src = cat["sources"][t["source"]]
        assert src["ref"] not in test_refs  # no test network is a source of tiles
        assert src["licence"] and "OpenStreetMap" in src["attribution"]
    for i, a in enumerate(realnets.TILES):  # tiles of one source: disjoint boxes, so no shared edge
        for b in realnets.TILES[i + 1:]:
            if a.source == b.source:
                assert not _boxes_intersect(a.box, b.box), (a.name, b.name)
    # every split has tiles, and dev tiles are not train tiles
    assert {t.name for t in realnets.TILES if t.split == "dev"}.isdisjoint(
        {t.name for t in realnets.TILES if t.split == "train"})


def test_edges_inside_boxes_are_disjoint():
    net = os.path.join(sumo_networks.sumo_home(), "tools", "game", "DRT", "osm.net.xml")
    a = realnets.edges_inside(net, (400.0, -10.0, 1330.0, 700.0))
    b = realnets.edges_inside(net, (1430.0, -10.0, 2400.0, 700.0))
    wide = realnets.edges_inside(net, (400.0, -10.0, 2400.0, 700.0))
    assert a and b and set(a).isdisjoint(b) and set(a) | set(b) <= set(wide)


def test_prepare_tile_cached_inside_its_box_and_clear_of_test_networks(tmp_path):
    out = realnets.prepare_real_networks(str(tmp_path), splits=("dev",), names=["drt_ne"])
    assert list(out) == ["dev"] and len(out["dev"]) == 1
    path = out["dev"][0]
    tile = next(t for t in realnets.TILES if t.name == "drt_ne")
    pts = np.concatenate(sumo_networks.read_network_lanes(path, merge_chains=False))
    x0, y0, x1, y1 = tile.box
    tol = 5.0  # netconvert rebuilds junction shapes and connectors (a few cm past the box here); boxes are 100 m apart
    assert np.all((pts[:, 0] >= x0 - tol) & (pts[:, 0] <= x1 + tol) & (pts[:, 1] >= y0 - tol)
                  & (pts[:, 1] <= y1 + tol))
    man = json.load(open(tmp_path / "manifest.json"))
    rec = man["tiles"]["drt_ne"]
    assert rec["split"] == "dev" and rec["licence"] == "ODbL-1.0" and rec["lane_km"] > 5.0
    assert len(rec["source_sha256"]) == 64
    mtime = os.path.getmtime(path)
    again = realnets.prepare_real_networks(str(tmp_path), splits=("dev",), names=["drt_ne"])
    assert again == out and os.path.getmtime(path) == mtime  # reused, not rebuilt
    with open(path + ".key", "w") as f:  # made from something else (e.g. an older box): rebuilt
        f.write("other\n")
    realnets.prepare_real_networks(str(tmp_path), splits=("dev",), names=["drt_ne"])
    assert open(path + ".key").read().strip() != "other"
    realnets.check_disjoint([path], realnets.test_networks())  # no exception


def test_overlap_with_a_test_network_is_caught():
    # SUMO's bs3d (Braunschweig centre) contains the test network fokr_bs_demo: the check must say so
    game = os.path.join(sumo_networks.sumo_home(), "tools", "game")
    with pytest.raises(DataError, match="overlaps"):
        realnets.check_disjoint([os.path.join(game, "bs3d", "bs.net.xml")],
                                [os.path.join(game, "fokr_bs_demo", "fokr_bs.net.xml.gz")])


def test_bad_requests(tmp_path):
    with pytest.raises(DataError, match="TEST_ONLY"):
        realnets.prepare_real_networks(str(tmp_path), splits=("test",))
    with pytest.raises(DataError, match="unknown tile"):
        realnets.prepare_real_networks(str(tmp_path), names=["A10KW"])
    assert data_main(["realnets", "--cache", str(tmp_path), "--splits", "test"]) == 2


def test_chain_statistics_matches_the_data_layer_and_turnarounds_cut():
    net = os.path.join(sumo_networks.sumo_home(), "tools", "game", "fkk_in", "ingolstadt.net.xml.gz")
    s = realnets.chain_statistics(net)
    assert s["chains"] == len(sumo_networks.read_network_lanes(net))
    t = realnets.chain_statistics(net, ignore_turnarounds=True)
    assert t["chains"] == len(sumo_networks.read_network_lanes(net, ignore_turnarounds=True))
    assert s["turnaround_connections"] > 0 and t["chains"] < s["chains"]
    assert t["chain_length_m"]["p10"] > s["chain_length_m"]["p10"]


def test_resco_tiles_from_the_sumo_rl_wheel_stay_clear_of_ingolstadt_test_network(tmp_path):
    # ingolstadt21 (sumo-rl's RESCO networks) reaches the test network fkk_in: the tile nearest it must stay
    # 300 m clear of it (the boxes stop 330 m west of it), and a whole-network Cologne crop is kept whole.
    out = realnets.prepare_real_networks(str(tmp_path), splits=("train",), names=["ingolstadt_ne", "cologne1"])
    paths = dict(zip(["ingolstadt_ne", "cologne1"], sorted(out["train"], key=lambda p: "cologne" in p)))
    assert "ingolstadt_ne" in paths["ingolstadt_ne"] and "cologne1" in paths["cologne1"]
    fkk = next(p for p in realnets.test_networks() if "fkk_in" in p)
    realnets.check_disjoint(list(paths.values()), [fkk], margin_m=300.0)  # no exception
    full, sha = realnets.source_network(realnets.SOURCES["resco_cologne1"], str(tmp_path))
    kept, whole = realnets._lane_km(paths["cologne1"]), realnets._lane_km(full)
    assert 0.9 * whole <= kept <= 1.01 * whole and len(sha) == 64
    man = json.load(open(tmp_path / "manifest.json"))["tiles"]
    assert man["cologne1"]["shipped_by"].startswith("sumo-rl") and "ODbL" in man["cologne1"]["licence"]
    # the whole ingolstadt21 network is not clear of fkk_in: the check that guards the tiles would catch it
    big, _ = realnets.source_network(realnets.SOURCES["resco_ingolstadt21"], str(tmp_path))
    with pytest.raises(DataError, match="overlaps"):
        realnets.check_disjoint([big], [fkk])
