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
