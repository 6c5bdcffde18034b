"""Store round trip, corrupt shards, map tokens, loader determinism / resume / sharding, inspect keys."""

import json
import os

import numpy as np
import pytest

from data_fixtures import straight_road_log, write_small_store
from gpd_jax.data import inspection, loader, preprocess, store
from gpd_jax.data.errors import DataError


@pytest.fixture()
def small_store(tmp_path):
    d = str(tmp_path / "ds")
    ids = write_small_store(d, n_shards=3, per_shard=4)
    return d, ids


def test_round_trip_and_manifest(small_store):
    d, ids = small_store
    man = json.load(open(os.path.join(d, "dataset.json")))
    assert man["num_samples"] == 12 and man["splits"]["train"]["num_shards"] == 3
    assert man["keys"]["polylines"]["dtype"] == "float32"
    sh = store.Shard(store.shard_dir(d, "train", 1))
    assert sh.meta["scenario_ids"] == ids[4:8]
    rec = sh.read(2)
    log = straight_road_log()
    ref = preprocess.make_sample(log, 6 % 25, 0)
    np.testing.assert_allclose(rec["polylines"], ref["polylines"])
    np.testing.assert_array_equal(rec["valid"], ref["valid"])
    assert rec["agent_type"].dtype == np.int8


def test_store_files_follow_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        d = str(tmp_path / "ds")
        write_small_store(d, n_shards=1, per_shard=2)
        store.save_map_tokens(d, "train", 0, np.zeros((2, 101, 64), np.uint8), tokenizer="t")
    finally:
        os.umask(old)
    sh = store.shard_dir(d, "train", 0)
    for p, mode in [(sh, 0o755), (os.path.join(d, "dataset.json"), 0o644), (os.path.join(sh, "meta.json"), 0o644),
                    (os.path.join(sh, store.MAP_TOKENS), 0o644), (os.path.join(sh, store.MAP_TOKENS_SOURCE), 0o644)]:
        assert os.stat(p).st_mode & 0o777 == mode, p


def test_temporaries_are_not_shards(small_store):
    d, _ = small_store
    os.makedirs(os.path.join(d, "train", ".tmp-shard_00009-x"))
    assert len(store.list_shards(d, "train")) == 3
    assert store.clean_temporaries(d) == 1


def test_truncated_shard_raises(small_store):
    d, _ = small_store
    f = os.path.join(store.shard_dir(d, "train", 2), "xy.npy")
    with open(f, "r+b") as fh:
        fh.truncate(os.path.getsize(f) // 2)
    with pytest.raises(DataError, match="xy.npy.*truncated"):
        store.Shard(store.shard_dir(d, "train", 2))
    src = loader.SplitSource(d, "train")
    with pytest.raises(DataError, match="shard_00002"):
        src[len(src) - 1]


def test_corrupt_meta_and_nan(small_store):
    d, _ = small_store
    with open(os.path.join(store.shard_dir(d, "train", 0), "meta.json"), "w") as f:
        f.write("{not json")
    with pytest.raises(DataError, match="meta.json"):
        store.Shard(store.shard_dir(d, "train", 0))
    # NaN inside a valid agent entry: a DataError naming the file and sample
    p = os.path.join(store.shard_dir(d, "train", 1), "xy.npy")
    a = np.load(p, mmap_mode="r+")
    a[3, 20, 0, 0] = np.nan
    a.flush()
    del a
    with pytest.raises(DataError, match="xy.npy: sample 3: non-finite"):
        store.Shard(store.shard_dir(d, "train", 1)).read(3)


def test_map_tokens(small_store):
    d, _ = small_store
    s = loader.load_split(d, "train")
    assert not s.map_valid.any() and (s.map_tokens == 0).all()
    tok = np.random.default_rng(0).integers(0, 128, (4, 101, 64))
    store.save_map_tokens(d, "train", 1, tok)
    with pytest.raises(ValueError):
        store.save_map_tokens(d, "train", 0, tok[:, :5])
    s = loader.load_split(d, "train")
    assert s.map_valid[4:8].all() and not s.map_valid[:4].any()
    np.testing.assert_array_equal(s.map_tokens[4:8], tok)
    s.validate()
    # frames that were not encoded (encode --frame-stride) load as map_valid False with token 0
    part = tok.copy()
    part[:, 1::10] = store.MISSING_MAP_TOKEN
    store.save_map_tokens(d, "train", 2, part, tokenizer="t", frame_stride=10)
    assert store.map_tokens_record(d, "train", 2)["frame_stride"] == 10
    s = loader.load_split(d, "train")
    want = np.ones(101, bool)
    want[1::10] = False
    np.testing.assert_array_equal(s.map_valid[8:12], np.broadcast_to(want, (4, 101)))
    np.testing.assert_array_equal(s.map_tokens[8:12], np.where(want[:, None], tok, 0))
    part[0, 1, 0] = 7  # a frame only partly marked missing
    with pytest.raises(ValueError, match="only some tokens"):
        store.save_map_tokens(d, "train", 2, part)
    with pytest.raises(ValueError, match=r"\[0, 254\]"):
        store.save_map_tokens(d, "train", 2, tok + 200)


def _ids(batch):
    return [round(float(x), 4) for x in batch.xy[:, 0, 0, 0]]


def test_loader_determinism_resume_and_sharding(small_store):
    d, _ = small_store
    first = [_ids(next_b) for next_b in _take(loader.make_loader(d, "train", 4, seed=7), 6)]
    again = [_ids(b) for b in _take(loader.make_loader(d, "train", 4, seed=7), 6)]
    assert first == again
    # each epoch (3 batches) is a permutation of all 12 samples, different between epochs
    assert sorted(sum(first[:3], [])) == sorted(sum(first[3:6], [])) and len(set(sum(first[:3], []))) == 12
    assert first[:3] != first[3:6]
    resumed = [_ids(b) for b in _take(loader.make_loader(d, "train", 4, seed=7, start_step=4), 2)]
    assert resumed == first[4:6]
    other = [_ids(b) for b in _take(loader.make_loader(d, "train", 4, seed=8), 3)]
    assert other != first[:3]
    # two processes read disjoint halves of every global batch: together, in process order, exactly the batches
    # of one process (the same rows in the same order), also from a resumed step
    for start in (0, 4):
        p0, p1 = ([_ids(b) for b in _take(loader.make_loader(d, "train", 2, seed=7, process_index=i, process_count=2,
                                                              start_step=start), 6 - start)] for i in (0, 1))
        assert [a + b for a, b in zip(p0, p1)] == first[start:6]


def test_loader_mixture_of_stores_follows_the_weights_and_resumes(small_store, tmp_path):
    a, _ = small_store  # 12 samples
    b = str(tmp_path / "b")
    write_small_store(b, n_shards=1, per_shard=4, offset=5.0)  # 4 samples, told apart from a's by the offset
    in_a, in_b = set(_ids(loader.load_split(a, "train"))), set(_ids(loader.load_split(b, "train")))
    assert len(in_a) == 12 and len(in_b) == 4 and not in_a & in_b
    mix = f"{a}:3,{b}:1"
    batches = [_ids(x) for x in _take(loader.make_loader(mix, "train", 4, seed=7), 40)]
    flat = sum(batches, [])
    assert set(flat) == in_a | in_b  # both stores read whole (b repeated more often)
    assert 0.2 <= sum(x in in_b for x in flat) / len(flat) <= 0.3  # weight 1 of 4, though b holds 4 of 16 scenes
    assert batches == [_ids(x) for x in _take(loader.make_loader(mix, "train", 4, seed=7), 40)]
    assert [_ids(x) for x in _take(loader.make_loader(mix, "train", 4, seed=7, start_step=30), 5)] == batches[30:35]
    assert [_ids(x) for x in _take(loader.make_loader(mix, "train", 4, seed=8), 5)] != batches[:5]
    # the other weights change the share
    flat9 = sum([_ids(x) for x in _take(loader.make_loader(f"{a}:1,{b}:9", "train", 4, seed=7), 20)], [])
    assert sum(x in in_b for x in flat9) / len(flat9) >= 0.85
    with pytest.raises(ValueError, match="endless"):
        loader.make_dataset(mix, "train", 4, num_epochs=1)
    with pytest.raises(DataError, match="no complete shards"):
        next(loader.make_loader(f"{a}:1,{tmp_path / 'missing'}:1", "train", 4))


def test_parse_mixture():
    assert loader.parse_mixture("/d") == (("/d", 1.0),)
    assert loader.parse_mixture("/a:3, /b:1") == (("/a", 0.75), ("/b", 0.25))
    assert loader.parse_mixture("/a,/b:3") == (("/a", 0.25), ("/b", 0.75))
    assert loader.parse_mixture("/x/run:v2") == (("/x/run:v2", 1.0),)  # a colon in a name, no weight
    for bad, why in [("/a:0", "positive"), ("/a:-1", "positive"), ("/a:nan", "positive"), ("/a:inf", "positive"),
                     (":2", "no directory"), ("/a:1,/a/:2", "twice"), ("", "no data directory"), ("/a,,/b", "no directory")]:
        with pytest.raises(DataError, match=why):
            loader.parse_mixture(bad)


def test_loader_lanes_and_polylines(small_store):
    d, _ = small_store
    scene, poly = next(loader.make_loader(d, "train", 2, seed=0, with_lanes=True, with_polylines=True))
    scene.validate()
    assert scene.lanes.shape == (2, 101, 50, 20, 2) and scene.lanes_valid[:, :].any(-1).all()
    assert poly["polylines"].shape[0] == 2 and poly["polyline_valid"].dtype == bool


def test_inspect_keys(small_store, tmp_path):
    d, _ = small_store
    s = inspection.inspect(d)
    for k in ("scenarios", "scenarios_per_split", "agents_per_frame_mean", "agents_per_frame_max",
              "lanes_per_frame_mean", "lanes_per_frame_min", "stationary_fraction", "speed_mps_p5",
              "speed_mps_p50", "speed_mps_p95", "accel_mps2_p1", "accel_mps2_p99", "log_collisions",
              "build_wall_s", "frame_rate_floor"):
        assert k in s, k
    assert set(s["frame_rate_floor"]) == {"1hz", "2hz", "5hz"} and s["frame_rate_floor"]["1hz"]["all"]["n"] > 0
    assert s["scenarios"] == 12 and s["log_collisions"] == 0 and s["lanes_per_frame_min"] >= 3
    assert abs(s["speed_mps_p50"] - 10.0) < 0.1
    from gpd_jax.data.__main__ import main
    out = tmp_path / "s.json"
    assert main(["inspect", d, "--json", str(out), "--no-lanes"]) == 0
    assert json.load(open(out))["scenarios"] == 12


def test_box_overlap():
    from gpd_jax.data.boxes import boxes_overlap
    size = np.array([4.0, 2.0])
    assert boxes_overlap([0, 0], 0.0, size, [3.9, 0], 0.0, size)
    assert not boxes_overlap([0, 0], 0.0, size, [4.1, 0], 0.0, size)
    # rotated 45 deg: corner-to-side separation that axis-aligned boxes would miss
    assert not boxes_overlap([0, 0], 0.0, size, [3.8, 2.2], np.pi / 4, size)  # bounding boxes do overlap
    assert boxes_overlap([0, 0], 0.0, size, [3.3, 1.9], np.pi / 4, size)
    assert boxes_overlap([0, 0], 0.0, size, [2.5, 1.2], np.pi / 4, size)


def _take(it, n):
    return [next(it) for _ in range(n)]


def test_frame_rate_floor_is_the_sagitta_of_a_turn_and_zero_on_a_straight_line():
    from gpd_jax.data.inspection import frame_rate_floor_errors

    T, v, R = 41, 8.0, 20.0  # 10 Hz; slot 0 drives straight at 8 m/s, slot 1 circles at 8 m/s on radius 20 m
    t = np.arange(T) * 0.1
    xy = np.zeros((1, T, 3, 2))
    heading = np.zeros((1, T, 3))
    xy[0, :, 0, 0] = v * t
    ang = v * t / R
    xy[0, :, 1] = np.stack([R * np.sin(ang), R * (1 - np.cos(ang))], -1)
    heading[0, :, 1] = ang
    valid = np.ones((1, T, 3), bool)
    valid[0, :, 2] = False  # slot 2 is padding: never scored
    e, man = frame_rate_floor_errors(xy, heading, valid, current=0, stride=10)
    assert len(e) == 2 * 4 * 9  # two valid slots, four 1 s intervals, nine frames between their ends
    straight, turn = e[0::2], e[1::2]
    np.testing.assert_allclose(straight, 0.0, atol=1e-9)
    w = np.tile(np.arange(1, 10) / 10, 4)
    th = v * 1.0 / R  # the angle turned in one model frame
    chord = np.abs(R * np.exp(1j * w * th) - ((1 - w) * R + w * R * np.exp(1j * th)))
    np.testing.assert_allclose(turn, chord, rtol=1e-6)
    assert turn.max() > 0.3  # a 0.4 rad/s turn is 0.39 m off a straight line in the middle of a 1 s step
    # yaw rate 0.4 rad/s > 0.2: the turning slot's frames are maneuvers, the straight slot's are not
    assert man[1::2].all() and not man[0::2].any()
    e2, _ = frame_rate_floor_errors(xy, heading, valid, current=0, stride=5)
    assert e2.max() < turn.max() / 3  # half the step, a quarter of the sagitta
