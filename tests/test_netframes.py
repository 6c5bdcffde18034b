"""Map-only tokenizer frames (`gpd_jax.map_tokenizer.netframes`): built from generated networks, resumed, drawn
with the ego on a lane, mixed with stores, and refused with a clear error when broken."""

import json
import os

import numpy as np
import pytest

from gpd_jax.data.errors import DataError
from gpd_jax.map_tokenizer import netframes
from gpd_jax.map_tokenizer.store import frame_batches


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    d = str(tmp_path_factory.mktemp("nf") / "nets")
    man = netframes.build_netframes(d, num_generated=2, seed=5, log=lambda *a: None)
    return d, man


def test_build_writes_a_manifest_and_resumes(built):
    d, man = built
    assert man["num_networks"] == 2 and netframes.is_netframes(d)
    for r in man["networks"]:
        assert r["source"] == "generated" and r["layout"] in ("grid", "spider", "random") and r["lane_km"] > 1.0
        with np.load(os.path.join(d, r["file"]), allow_pickle=False) as z:
            assert z["xy"].shape == (r["points"], 2) and z["line"].shape == (r["points"],)
    stamps = {f: os.path.getmtime(os.path.join(d, f)) for f in os.listdir(d)}
    again = netframes.build_netframes(d, num_generated=2, seed=5, log=lambda *a: None)
    assert again["networks"] == man["networks"]
    assert all(os.path.getmtime(os.path.join(d, f)) == t for f, t in stamps.items() if f.endswith(".npz"))
    with pytest.raises(DataError, match="other settings"):
        netframes.build_netframes(d, num_generated=3, seed=5, log=lambda *a: None)


def test_items_put_the_ego_on_a_lane_heading_along_it(built):
    d, _ = built
    nf = netframes.NetFrames(d)
    rng = np.random.default_rng(0)
    for _ in range(20):
        it = nf.item(rng, heading_sd=0.0, lateral_sd=0.0)
        assert it["polylines"].shape == (96, 128, 2) and it["lanes"].shape == (50, 20, 2)
        np.testing.assert_array_equal(it["pose"], 0.0)
        lanes, ok = it["lanes"][it["lanes_valid"]], it["polyline_valid"]
        assert len(lanes) >= 1 and ok.any()
        pts = it["polylines"][ok]
        assert np.linalg.norm(pts, axis=-1).min() < 0.6  # on a lane point (1 m spacing: at most 0.5 m off one)
        along = []  # lines through the ego (junctions cross several): one of them runs along +x there
        for line, v in zip(it["polylines"], ok):
            line = line[v]
            if len(line) < 2 or np.linalg.norm(line, axis=-1).min() >= 0.6:
                continue
            j = int(np.argmin(np.linalg.norm(line, axis=-1)))
            step = line[min(j + 1, len(line) - 1)] - line[max(j - 1, 0)]
            along.append(step[0] > 0.95 * np.linalg.norm(step))
        assert any(along)
        assert np.abs(pts).max() <= 32.0 + 1.5 + 1.0  # clipped to the window (+ margin, + one spacing)


def test_netframes_mix_with_stores_deterministically(built, tmp_path):
    from data_fixtures import write_small_store

    d, _ = built
    s = str(tmp_path / "store")
    write_small_store(s, n_shards=1, per_shard=3, offset=500.0)  # the store's poses lie 500 m along x
    mix = f"{d}:1,{s}:1"
    first = list(frame_batches(mix, "train", 8, seed=2, max_batches=10))
    from_store = np.concatenate([b["pose"][:, 0] > 250.0 for b in first])
    assert 0.3 <= from_store.mean() <= 0.7
    again = list(frame_batches(mix, "train", 8, seed=2, max_batches=10))
    for x, y in zip(first, again):
        np.testing.assert_array_equal(x["lanes"], y["lanes"])
    alone = next(frame_batches(d, "train", 4, seed=0))  # a netframes directory alone is a training source
    assert alone["lanes"].shape == (4, 50, 20, 2)
    with pytest.raises(ValueError, match="evaluate one store"):
        next(frame_batches(mix, "val", 4, shuffle=False, repeat=False, max_batches=1))
    with pytest.raises(ValueError, match="give max_batches"):
        next(frame_batches(d, "val", 4, shuffle=False, repeat=False))
    evals = [list(frame_batches(d, "val", 4, shuffle=False, repeat=False, max_batches=3)) for _ in range(2)]
    assert len(evals[0]) == 3  # a netframes directory of held-out maps evaluates on the same drawn frames
    for x, y in zip(*evals):
        np.testing.assert_array_equal(x["lanes"], y["lanes"])


def test_lanelet2_maps_and_their_mirrored_copies(tmp_path):
    """A real map in another format (Lanelet2 here) becomes a network of the directory, around its own centre;
    its left-hand copy is the map mirrored, each lane still in its direction of travel."""
    from test_interaction import LANE_W, X0, X1, write_osm

    from gpd_jax.data.sources import maps

    osm = str(tmp_path / "road.osm")
    write_osm(osm)
    lanes = maps.read_map_lanes(osm)
    assert maps.map_format(osm) == "lanelet2" and len(lanes) == 2
    east = next(lane for lane in lanes if lane[-1, 0] > lane[0, 0])
    west = next(lane for lane in lanes if lane[-1, 0] < lane[0, 0])
    assert east[-1, 0] - east[0, 0] == pytest.approx(X1 - X0, rel=1e-3)
    assert abs(east[:, 0].mean()) < 0.1 * (X1 - X0)  # around the map's centre, not INTERACTION's origin
    assert east[:, 1].mean() - west[:, 1].mean() == pytest.approx(LANE_W, rel=1e-2)
    d = str(tmp_path / "nf")
    man = netframes.build_netframes(d, real_nets=[osm], real_lefthand=True, log=lambda *a: None)
    recs = {r["name"]: r for r in man["networks"]}
    assert set(recs) == {"real_road", "real_road_lh"}
    assert [recs[k]["lefthand"] for k in ("real_road", "real_road_lh")] == [False, True]
    assert recs["real_road"]["layout"] == "lanelet2"
    assert recs["real_road"]["lane_km"] == pytest.approx(2 * (X1 - X0) / 1000, rel=1e-3)
    nf = netframes.NetFrames(d)
    k = nf.names.index("real_road_lh")
    np.testing.assert_allclose(nf.lanes[k].xy[:, 1], -nf.lanes[nf.names.index("real_road")].xy[:, 1], atol=1e-4)
    with pytest.raises(DataError, match="unknown map format"):
        maps.read_map_lanes(str(tmp_path / "road.shp"))


def test_broken_netframes_are_refused_by_name(built, tmp_path):
    d, man = built
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / netframes.MANIFEST).write_text(json.dumps(man))
    r0 = man["networks"][0]
    (bad / r0["file"]).write_bytes(b"not an npz")
    with pytest.raises(DataError, match=r0["file"]):
        netframes.NetFrames(str(bad))
    with pytest.raises(DataError, match="not a netframes directory"):
        netframes.NetFrames(str(tmp_path))


def test_gt_recut_changes_the_targets_not_the_input(built, tmp_path):
    """`gt_recut` (config `data.gt_recut`): the decoder's targets are the lanes re-cut, the raster's polylines are
    as stored, for stores and netframes alike; the same frames are drawn either way."""
    from data_fixtures import write_small_store

    from gpd_jax.metrics.map import map_metrics

    d, _ = built
    s = str(tmp_path / "store")
    write_small_store(s, n_shards=2, per_shard=4)
    with pytest.raises(ValueError, match="fewer than a batch of 9"):
        next(frame_batches(s, "train", 9))  # 8 samples: it never yields a full batch, so it says so
    for src in (s, d, f"{d}:1,{s}:1"):
        plain = list(frame_batches(src, "train", 8, seed=4, max_batches=4))
        split = list(frame_batches(src, "train", 8, seed=4, max_batches=4, gt_recut="split_mid"))
        for p, j in zip(plain, split):
            np.testing.assert_array_equal(p["polylines"], j["polylines"])
            np.testing.assert_array_equal(p["pose"], j["pose"])
            assert (j["lanes_valid"].sum(-1) > p["lanes_valid"].sum(-1)).any()
            for i in range(len(p["pose"])):  # the same road: cut-free F1 ~1 between the two cuts (a half of
                if p["lanes_valid"][i].any():  # under 3 points inside the window is dropped, as any short run)
                    r = map_metrics(j["lanes"][i], np.where(j["lanes_valid"][i], 10.0, -10.0).astype(np.float32),
                                    p["lanes"][i], p["lanes_valid"][i])
                    assert r["map_f1_cutfree"] == pytest.approx(1.0, abs=0.05)
    with pytest.raises(ValueError, match="gt_recut"):
        next(frame_batches(d, "train", 4, gt_recut="nope"))


def test_pack_netframes_round_trip(built, tmp_path, capsys):
    """`pack-netframes`: an archive that `tar xf` turns into a netframes directory whose networks are the
    original's within 5 mm (centimetre rounding), a subset on request, a kept archive on a second call, and a
    clear error for what is not a netframes directory."""
    import tarfile

    from gpd_jax.map_tokenizer.__main__ import main as tok_main

    d, man = built
    out = tmp_path / "packs"
    assert tok_main(["pack-netframes", d, "--out", str(out), "--networks", "1"]) == 0
    archive = out / (os.path.basename(d) + ".tar.xz")
    stamp = os.path.getmtime(archive)
    assert netframes.pack_netframes(d, str(out)) == str(archive) and os.path.getmtime(archive) == stamp
    with tarfile.open(archive) as tf:
        names = tf.getnames()
        assert all(n.startswith(os.path.basename(d) + "/") for n in names)
        tf.extractall(tmp_path / "x", **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))
    back = str(tmp_path / "x" / os.path.basename(d))
    assert netframes.is_netframes(back)
    got, want = netframes.NetFrames(back), netframes.NetFrames(d)
    assert len(got.lanes) == 1 and got.names == want.names[:1]
    np.testing.assert_array_equal(got.lanes[0].line, want.lanes[0].line)
    assert np.abs(got.lanes[0].xy - want.lanes[0].xy).max() <= 0.0051
    assert json.load(open(os.path.join(back, "netframes.json")))["packed"]["source"] == os.path.abspath(d)
    # all networks packed: the same items as the original, within the rounding
    whole = netframes.pack_netframes(d, str(tmp_path / "packs2"))
    with tarfile.open(whole) as tf:
        tf.extractall(tmp_path / "y", **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))
    full = netframes.NetFrames(str(tmp_path / "y" / os.path.basename(d)))
    for a, b in zip(full.walk(3), want.walk(3)):
        np.testing.assert_array_equal(a["lanes_valid"], b["lanes_valid"])
        np.testing.assert_allclose(a["lanes"], b["lanes"], atol=0.02)
        np.testing.assert_array_equal(a["sample"], b["sample"])
        break
    capsys.readouterr()
    assert tok_main(["pack-netframes", str(tmp_path), "--out", str(out)]) == 2
    assert "not a netframes directory" in capsys.readouterr().err
