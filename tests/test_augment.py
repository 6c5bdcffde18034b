"""gpd_jax.data.augment: mirror images of a store's scenes."""

import json
import os

import jax.numpy as jnp
import numpy as np
import pytest

from data_fixtures import write_small_store
from gpd_jax.data import augment, store
from gpd_jax.data.errors import DataError
from gpd_jax.data.loader import SplitSource


def _arrays(path, split="train"):
    return [store.Shard(store.shard_dir(path, split, j)) for j in store.shard_indices(path, split)]


def test_mirror_store_reflects_every_geometry_key_and_twice_is_the_original(tmp_path):
    src, dst, back = (str(tmp_path / n) for n in ("src", "mirror", "back"))
    write_small_store(src, n_shards=2, per_shard=3)
    man = augment.mirror_store(src, dst)
    assert man["num_samples"] == 6 and man["mirrored_from"] == os.path.abspath(src)
    for a, b in zip(_arrays(src), _arrays(dst)):
        assert b.has_road and a.has_road
        for k in ("xy", "polylines", "road_polygons", "road_edges"):
            np.testing.assert_array_equal(b.arrays[k][..., 0], a.arrays[k][..., 0])
            np.testing.assert_array_equal(b.arrays[k][..., 1], -a.arrays[k][..., 1])
            assert np.any(a.arrays[k][..., 1] != 0), k  # the check is not vacuous
        np.testing.assert_allclose(np.cos(b.arrays["heading"]), np.cos(a.arrays["heading"]), atol=1e-6)
        np.testing.assert_allclose(np.sin(b.arrays["heading"]), -np.sin(a.arrays["heading"]), atol=1e-6)
        np.testing.assert_allclose(np.sin(b.arrays["ego_pose"][..., 2]), -np.sin(a.arrays["ego_pose"][..., 2]),
                                   atol=1e-6)
        for k in ("valid", "size", "agent_type", "polyline_valid", "road_polygon_kind"):
            np.testing.assert_array_equal(b.arrays[k], a.arrays[k])
        assert b.meta["lefthand"] is (not a.meta.get("lefthand", False))
        assert all(s.endswith("/mirror") for s in b.meta["scenario_ids"])
        assert b.map_tokens is None  # the tokenizer is not mirror-equivariant: encode the new store
    augment.mirror_store(dst, back)
    angle_gap = lambda x, y: np.angle(np.exp(1j * (x - y)))  # headings are equal up to wrapping at +-pi
    for a, c in zip(_arrays(src), _arrays(back)):
        for k in a.arrays:
            if k == "heading":
                np.testing.assert_allclose(angle_gap(c.arrays[k], a.arrays[k]), 0, atol=1e-6)
            elif k == "ego_pose":
                np.testing.assert_array_equal(c.arrays[k][..., :2], a.arrays[k][..., :2])
                np.testing.assert_allclose(angle_gap(c.arrays[k][..., 2], a.arrays[k][..., 2]), 0, atol=1e-6)
            else:
                np.testing.assert_array_equal(c.arrays[k], a.arrays[k])
    assert len(SplitSource(dst, "train")) == 6


def test_mirrored_scene_rasterizes_to_the_flipped_map(tmp_path):
    """The map tokenizer's raster of a mirrored frame (its polylines and ego pose together) is the original's
    raster flipped left-right: the reflection keeps lanes, poses and frames consistent. The lanes are moved 3 m to
    the left first, so that the road is not its own mirror image."""
    from gpd_jax.map_tokenizer.raster import rasterize

    src = str(tmp_path / "src")
    write_small_store(src, n_shards=1, per_shard=2)
    sh = _arrays(src)[0]
    a = {k: np.asarray(sh.arrays[k][0]) for k in ("polylines", "polyline_valid", "ego_pose")}
    a["polylines"] = a["polylines"] + np.where(a["polyline_valid"][..., None], np.float32([0.0, 3.0]), 0.0)
    b = augment.mirror_arrays(a)
    near = lambda x: x | np.roll(x, 1, axis=-1) | np.roll(x, -1, axis=-1)  # one pixel: pixel centres move
    for t in (0, 20, 60):
        ra, rb = (np.asarray(rasterize(jnp.asarray(d["polylines"]), jnp.asarray(d["polyline_valid"]),
                                       jnp.asarray(d["ego_pose"][t]))) > 0 for d in (a, b))
        assert ra.sum() > 100
        flipped = ra[..., ::-1]
        assert (rb & near(flipped)).sum() / rb.sum() > 0.97
        assert (flipped & near(rb)).sum() / flipped.sum() > 0.97
        assert (rb & ~near(ra)).sum() > 0.2 * rb.sum()  # and it is not the unflipped raster


def test_mirror_refuses_its_source_and_resumes(tmp_path):
    src, dst = str(tmp_path / "src"), str(tmp_path / "mirror")
    write_small_store(src, n_shards=2, per_shard=2)
    with pytest.raises(DataError, match="new directory"):
        augment.mirror_store(src, src)
    with pytest.raises(DataError, match="no complete shards"):
        augment.mirror_store(src, dst, ["val"])
    augment.mirror_store(src, dst)
    first = store.shard_dir(dst, "train", store.shard_indices(dst, "train")[0])
    stamp = os.path.getmtime(os.path.join(first, "meta.json"))
    import shutil

    shutil.rmtree(store.shard_dir(dst, "train", store.shard_indices(dst, "train")[-1]))
    man = augment.mirror_store(src, dst)  # rewrites only the missing shard
    assert man["num_samples"] == 4 and os.path.getmtime(os.path.join(first, "meta.json")) == stamp
    assert json.load(open(os.path.join(dst, "dataset.json")))["splits"]["train"]["num_shards"] == 2


def test_sensor_view_drifts_ranges_and_loses_tracks_of_the_other_agents_only():
    """`sensor_arrays` on 8 scenes of 32 tracked agents: slot 0 (the ego) and the maps are the log's; others are
    unseen beyond the range and in gaps of `gap_frames`, and seen ones carry errors with the asked standard
    deviation and frame-to-frame correlation."""
    rng = np.random.default_rng(0)
    n, t, a = 8, 101, 33
    ego = np.zeros((n, t, 3), np.float32)
    ego[:, :, 0] = np.arange(t) * 1.0
    xy = (ego[:, :, None, :2] + rng.uniform(-80, 80, (n, 1, a, 2))).astype(np.float32)
    xy[:, :, 0] = ego[:, :, :2]
    heading = rng.uniform(-np.pi, np.pi, (n, t, a)).astype(np.float32)
    heading[:, :, 0] = 0.0
    arrays = {"xy": xy, "heading": heading, "valid": np.ones((n, t, a), bool), "ego_pose": ego,
              "polylines": rng.normal(size=(n, 4, 8, 2)).astype(np.float32)}
    view = augment.SensorView(position_sigma_m=0.5, heading_sigma_deg=3.0, correlation=0.9, range_m=50.0,
                              gap_rate=0.02, gap_frames=4)
    out = augment.sensor_arrays(arrays, view, np.random.default_rng(1))
    for k in ("ego_pose", "polylines"):
        np.testing.assert_array_equal(out[k], arrays[k])
    np.testing.assert_array_equal(out["xy"][:, :, 0], xy[:, :, 0])
    assert out["valid"][:, :, 0].all()
    dist = np.linalg.norm(xy - ego[:, :, None, :2], axis=-1)
    v = out["valid"][:, :, 1:]
    assert not (v & (dist[:, :, 1:] > 50.0)).any()
    inside = dist[:, :, 1:] <= 50.0
    lost = inside & ~v
    assert 0.04 < lost.sum() / inside.sum() < 0.12          # 1 - (1 - 0.02)^4 = 7.8 % of the frames in range
    runs = np.diff(np.concatenate([np.zeros((n, 1, a - 1), bool), lost, np.zeros((n, 1, a - 1), bool)], 1)
                   .astype(np.int8), axis=1)
    assert (np.argwhere(runs.transpose(0, 2, 1) == -1)[:, 2] - np.argwhere(runs.transpose(0, 2, 1) == 1)[:, 2]
            >= 4).mean() > 0.6                               # lost for gap_frames or longer (runs merge, edges cut)
    err = (out["xy"] - xy)[:, :, 1:][v]
    np.testing.assert_allclose(err.std(0), 0.5, rtol=0.1)
    dh = np.angle(np.exp(1j * (out["heading"] - heading)))[:, :, 1:]
    np.testing.assert_allclose(np.rad2deg(dh[v].std()), 3.0, rtol=0.1)
    e = (out["xy"] - xy)[..., 0][:, :, 1:]
    both = v[:, 1:] & v[:, :-1]
    corr = np.corrcoef(e[:, 1:][both], e[:, :-1][both])[0, 1]
    assert abs(corr - 0.9) < 0.05
    with pytest.raises(ValueError, match="correlation"):
        augment.SensorView(correlation=1.0)
    with pytest.raises(ValueError, match="range_m"):
        augment.SensorView(range_m=-1.0)


def test_sensor_store_keeps_tokens_is_deterministic_and_resumes(tmp_path):
    src, dst, again = (str(tmp_path / x) for x in ("src", "sensor", "again"))
    write_small_store(src, n_shards=2, per_shard=2)
    for j in store.shard_indices(src, "train"):
        sh = store.Shard(store.shard_dir(src, "train", j))
        tokens = np.full((2, sh.arrays["xy"].shape[1], store.NUM_MAP_TOKENS), 7, np.uint8)
        store.save_map_tokens(src, "train", j, tokens, tokenizer="abc", frame_stride=10)
    view = augment.SensorView(range_m=20.0, gap_rate=0.05)
    with pytest.raises(DataError, match="new directory"):
        augment.sensor_store(src, src, view)
    man = augment.sensor_store(src, dst, view)
    assert man["num_samples"] == 4 and man["sensor_view"]["range_m"] == 20.0
    augment.sensor_store(src, again, view)
    changed = 0
    for a, b, c in zip(_arrays(src), _arrays(dst), _arrays(again)):
        for k in b.arrays:
            np.testing.assert_array_equal(b.arrays[k], c.arrays[k])
        np.testing.assert_array_equal(b.map_tokens, a.map_tokens)
        assert store.map_tokens_record(dst, "train", int(os.path.basename(b.path)[6:]))["tokenizer"] == "abc"
        assert all(s.endswith("/sensor") for s in b.meta["scenario_ids"])
        changed += int((b.arrays["valid"] != a.arrays["valid"]).sum())
        np.testing.assert_array_equal(b.arrays["xy"][:, :, 0], a.arrays["xy"][:, :, 0])
    assert changed > 0
    last = store.shard_dir(dst, "train", store.shard_indices(dst, "train")[-1])
    kept = {k: np.array(v) for k, v in store.Shard(last).arrays.items()}
    import shutil

    shutil.rmtree(last)
    augment.sensor_store(src, dst, view)  # rewrites the missing shard, the same as before
    for k, v in store.Shard(last).arrays.items():
        np.testing.assert_array_equal(v, kept[k])
    assert len(SplitSource(dst, "train")) == 4


def test_sensor_command_reports_a_bad_view(tmp_path, capsys):
    from gpd_jax.data.__main__ import main

    src = str(tmp_path / "src")
    write_small_store(src, n_shards=1, per_shard=2)
    assert main(["sensor", src, "--out", str(tmp_path / "out"), "--correlation", "1"]) == 2
    assert "SensorView.correlation" in capsys.readouterr().err
    assert not os.path.exists(tmp_path / "out")
    assert main(["sensor", src, "--out", str(tmp_path / "out")]) == 0
    assert '"num_samples": 2' in capsys.readouterr().out
