"""ScenarioNet importer: scenarios the tests write themselves (tests/scenarionet_fixtures.py) -> RawLog -> store.

Covers types and sizes, the ego choice, coordinate and heading conventions in built samples, a 20 Hz log, bad
files (missing sdc, missing keys, truncated, foreign classes - and that a hostile pickle never runs), the
build (layouts, splits by map, resume, summary counts, CLI exit status) and evaluation on the built store.
"""

import json
import os
import pickle
import sys
from collections import Counter

import numpy as np
import pytest

import scenarionet_fixtures as fx
from gpd_jax.data import inspection, preprocess, safe_pickle, store
from gpd_jax.data.sources import scenarionet
from gpd_jax.data.__main__ import main as data_main
from gpd_jax.data.errors import DataError
from gpd_jax.scene import TYPE_ID

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _raw(sc=None, stats=None, name="x.pkl"):
    return scenarionet.scenario_to_rawlog(fx.make_scenario() if sc is None else sc, name, stats=stats)


# ------------------------------------------------------------------------------------------ reading
def test_types_kept_dropped_and_counted():
    stats = Counter()
    raw = _raw(stats=stats)
    assert set(raw.agent_ids) == {fx.SDC, "ahead", "left", "bus", "late"}
    assert stats["tracks_dropped_pedestrian"] == 1 and stats["tracks_dropped_cyclist"] == 1
    assert stats["tracks_dropped_traffic_cone"] == 1 and stats["tracks_vehicle"] == 4
    t = dict(zip(raw.agent_ids, raw.agent_type))
    assert t[fx.SDC] == TYPE_ID["ego"] and t["ahead"] == TYPE_ID["car"] and t["late"] == TYPE_ID["car"]
    assert t["left"] == TYPE_ID["truck"] and t["bus"] == TYPE_ID["bus"]


def test_sizes_from_valid_frames_and_column_arrays():
    sc = fx.make_scenario()
    st = sc["tracks"]["ahead"]["state"]
    st["length"], st["width"] = st["length"][:, None], st["width"][:, None]  # (T, 1), as MetaDrive exports
    raw = _raw(sc)
    size = dict(zip(raw.agent_ids, raw.agent_size.tolist()))
    assert size["bus"] == pytest.approx([12.0, 2.55])  # the 99 m of invalid frames is ignored
    assert size["ahead"] == pytest.approx([4.5, 1.9]) and size[fx.SDC] == pytest.approx([4.8, 2.0])


def test_missing_size_gets_default_and_is_counted():
    sc = fx.make_scenario()
    del sc["tracks"]["ahead"]["state"]["length"]
    stats = Counter()
    raw = _raw(sc, stats)
    assert raw.agent_size[raw.agent_ids.index("ahead")] == pytest.approx(scenarionet.DEFAULT_SIZE)
    assert stats["agent_size_defaulted"] == 1


def test_ego_is_the_sdc_track_whatever_its_position_in_the_dict():
    sc = fx.make_scenario()
    tracks = sc["tracks"]
    sc["tracks"] = {k: tracks[k] for k in ["ahead", "left", fx.SDC, "bus", "late", "ped1"]}
    raw = _raw(sc)
    assert raw.ego_index == 0 and raw.agent_ids[0] == fx.SDC
    want = fx.road_to_world(10.0 * np.arange(121) / 10.0, 0.0)
    np.testing.assert_allclose(raw.agent_xy[:, 0], want, atol=1e-3)
    # another sdc: that track becomes the ego (and is not double-counted)
    sc["metadata"]["sdc_id"] = "ahead"
    raw2 = _raw(sc)
    assert raw2.agent_ids[0] == "ahead" and raw2.agent_ids.count("ahead") == 1 and fx.SDC in raw2.agent_ids
    assert raw2.agent_type[0] == TYPE_ID["ego"]


def test_validity_nan_and_timestamps():
    raw = _raw()
    j = raw.agent_ids.index("late")
    assert not raw.agent_valid[:50, j].any() and raw.agent_valid[50:, j].all()
    assert np.isnan(raw.agent_xy[:50, j]).all() and np.isfinite(raw.agent_xy[50:, j]).all()
    np.testing.assert_allclose(raw.timestamps, np.arange(121) * 0.1, atol=1e-5)  # from the first ts (3.0 s)


def test_lanes_are_vehicle_lane_centrelines_only():
    stats = Counter()
    raw = _raw(fx.make_scenario(extra_lanes=4), stats)
    assert len(raw.lanes) == 3 + 4  # 2 street + 1 freeway + 4 extra; not the bike lane, edges, lines, crosswalk
    assert all(p.shape[1] == 2 for p in raw.lanes)  # z dropped
    assert stats["map_lane_other"] == 1 and stats["map_road_edge"] == 2 and stats["map_road_line"] == 1
    assert stats["map_crosswalk"] == 1 and stats["map_lane_with_polygon"] == 3
    lats = sorted(round(float((p[0] - fx.ORIGIN) @ fx.rot(fx.THETA)[:, 1]), 3) for p in raw.lanes[:3])
    assert lats == [-3.5, 0.0, 3.5]


def test_location_keys():
    assert scenarionet.scenario_location({"map": "singapore-onenorth", "dataset": "nuscenes"}, "f") == \
        "singapore-onenorth"
    assert scenarionet.scenario_location({"dataset": "waymo", "scenario_id": "abc"}, "f") == "waymo:abc"
    assert scenarionet.scenario_location({}, "stem") == "scenarionet:stem"
    assert _raw(fx.make_scenario(map_name=None, dataset="waymo", scenario_id="q1")).location == "waymo:q1"


# -------------------------------------------------------------------------------------- conventions
@pytest.mark.parametrize("theta", [fx.THETA, -0.7])
def test_built_sample_ego_frame_and_agent_positions(theta):
    raw = _raw(fx.make_scenario(theta=theta))
    cfg = preprocess.SampleConfig()
    (sid, s), *_ = list(preprocess.iter_samples(raw, cfg))
    c = cfg.current
    assert sid == "x/0/" + fx.SDC
    np.testing.assert_allclose(s["xy"][c, 0], [0.0, 0.0], atol=1e-4)
    assert s["heading"][c, 0] == pytest.approx(0.0, abs=1e-5)
    np.testing.assert_allclose(s["ego_pose"][c], [0.0, 0.0, 0.0], atol=1e-4)
    # the ego drives along +x at 10 m/s: 1 m per frame
    np.testing.assert_allclose(s["xy"][:, 0, 0], np.arange(cfg.num_frames) - c, atol=1e-3)
    np.testing.assert_allclose(s["xy"][:, 0, 1], 0.0, atol=1e-3)
    slot = {(round(float(x), 2), round(float(y), 2)): i for i, (x, y) in enumerate(s["xy"][c]) if s["valid"][c, i]}
    ahead, left, bus = slot[(12.0, 0.0)], slot[(2.0, 3.5)], slot[(25.0, -3.5)]  # left is +y
    assert s["agent_type"][ahead] == TYPE_ID["car"] and s["agent_type"][left] == TYPE_ID["truck"]
    assert s["agent_type"][bus] == TYPE_ID["bus"] and s["agent_type"][0] == TYPE_ID["ego"]
    assert list(s["size"][left]) == pytest.approx([8.0, 2.5])
    np.testing.assert_allclose(s["heading"][:, [ahead, left]], 0.0, atol=1e-5)
    assert s["valid"][:, 1:].any(0).sum() == 3  # "late" is not valid at the current frame
    # lanes: the ego's lane runs along the x axis of the scene frame
    pts = s["polylines"][s["polyline_valid"]]
    assert np.min(np.abs(pts[:, 1])) < 1e-3 and np.min(np.abs(pts[:, 1] - 3.5)) < 1e-3


def test_windows_every_stride_where_the_ego_is_present():
    sc = fx.make_scenario(num_frames=161)
    v = sc["tracks"][fx.SDC]["state"]["valid"]
    v[135:] = False  # the ego leaves: windows reaching frame 135 are skipped
    raw = _raw(sc)
    stats = Counter()
    ids = [sid for sid, _ in preprocess.iter_samples(raw, preprocess.SampleConfig(), stats=stats)]
    assert ids == [f"x/{s}/{fx.SDC}" for s in (0, 10, 20, 30)]
    assert stats["skip_ego_not_present"] == 3  # starts 40, 50, 60
    # the build's window choice makes the same samples as preprocess.iter_samples ...
    every = scenarionet._scenario_samples(raw, preprocess.SampleConfig(), None, 0, Counter())
    assert [sid for sid, _ in every] == ids
    for (_, a), (_, b) in zip(every, preprocess.iter_samples(raw, preprocess.SampleConfig())):
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])
    # ... and --max-per-log draws among the windows that have the ego (never fewer than there are)
    for n in (1, 2, 4, 9):
        stats = Counter()
        pairs = scenarionet._scenario_samples(raw, preprocess.SampleConfig(), n, 0, stats)
        assert len(pairs) == min(n, 4) and stats["samples"] == min(n, 4)
        assert {sid for sid, _ in pairs} <= set(ids)


def test_20hz_log_is_resampled_to_10hz():
    stats = Counter()
    raw20 = _raw(fx.make_scenario(num_frames=241, hz=20.0), stats)
    raw10 = _raw()
    assert stats["scenarios_resampled_to_10hz"] == 1
    assert raw20.num_frames == 121 and raw20.agent_ids == raw10.agent_ids
    np.testing.assert_allclose(raw20.timestamps, raw10.timestamps, atol=1e-5)
    np.testing.assert_allclose(raw20.agent_xy, raw10.agent_xy, atol=1e-3)
    np.testing.assert_array_equal(raw20.agent_valid, raw10.agent_valid)


@pytest.mark.parametrize("hz", [2.0, 15.0, 12.5])
def test_other_rates_are_refused_naming_file_and_rate(hz):
    with pytest.raises(DataError, match=rf"x\.pkl: frame period .*\({hz:.2f} Hz\)"):
        _raw(fx.make_scenario(num_frames=60, hz=hz))


def test_irregular_timestamps_are_refused():
    sc = fx.make_scenario()
    sc["metadata"]["ts"][60:] += 0.1  # a dropped frame
    with pytest.raises(DataError, match="irregular timestamps.*frames 59 and 60"):
        _raw(sc)


def test_mirrored_heading_is_refused():
    sc = fx.make_scenario()
    st = sc["tracks"][fx.SDC]["state"]
    st["heading"] = (-st["heading"]).astype(np.float32)  # y mirrored for the heading only
    with pytest.raises(DataError, match="heading disagrees with its direction of motion"):
        _raw(sc)


# ------------------------------------------------------------------------------------------ bad files
@pytest.mark.parametrize("edit, match", [
    (lambda sc: sc["metadata"].pop("sdc_id"), r"missing key scenario\['metadata'\]\['sdc_id'\]"),
    (lambda sc: sc["metadata"].__setitem__("sdc_id", "999"), r"sdc_id'\] = '999' names no track.*no ego"),
    (lambda sc: sc["tracks"][fx.SDC]["state"]["valid"].fill(False), "ego track '172'.*never valid"),
    (lambda sc: sc.pop("tracks"), r"missing key scenario\['tracks'\]"),
    (lambda sc: sc.pop("map_features"), r"missing key scenario\['map_features'\]"),
    (lambda sc: sc["metadata"].pop("ts"), r"missing key scenario\['metadata'\]\['ts'\]"),
    (lambda sc: sc["tracks"]["ahead"]["state"].pop("heading"),
     r"missing key scenario\['tracks'\]\['ahead'\]\['state'\]\['heading'\]"),
    (lambda sc: sc["tracks"]["ahead"].pop("type"), r"missing key scenario\['tracks'\]\['ahead'\]\['type'\]"),
    (lambda sc: sc["map_features"]["101"].pop("polyline"), r"missing key .*\['101'\]\['polyline'\]"),
    (lambda sc: sc["tracks"]["bus"]["state"].__setitem__("position", np.zeros((50, 3))),
     r"\['bus'\]\['state'\]\['position'\] has shape \(50, 3\), expected \(121, 2\) or \(121, 3\)"),
    (lambda sc: sc.__setitem__("length", 90), r"scenario\['length'\] = 90 but metadata\['ts'\] has 121"),
])
def test_bad_scenarios_raise_dataerror_naming_file_and_key(tmp_path, edit, match):
    sc = fx.make_scenario()
    edit(sc)
    path = fx.write_scenario(str(tmp_path / "sd_bad.pkl"), sc)
    with pytest.raises(DataError, match=match) as ei:
        scenarionet.read_scenario(path)
    assert ei.value.path == path


def test_not_a_dict(tmp_path):
    path = fx.write_scenario(str(tmp_path / "sd_list.pkl"), [1, 2, 3])
    with pytest.raises(DataError, match="holds a list, expected a dict"):
        scenarionet.read_scenario(path)


@pytest.mark.parametrize("frac", [0.0, 0.01, 0.5, 0.999])
def test_truncated_file(tmp_path, frac):
    path = fx.write_scenario(str(tmp_path / "sd_t.pkl"), fx.make_scenario())
    data = open(path, "rb").read()
    with open(path, "wb") as f:
        f.write(data[: int(len(data) * frac)])
    with pytest.raises(DataError, match="truncated") as ei:
        scenarionet.read_scenario(path)
    assert ei.value.path == path


@pytest.mark.parametrize("protocol", [0, 2, 3, 4, 5])
def test_all_pickle_protocols_read(tmp_path, protocol):
    path = fx.write_scenario(str(tmp_path / "sd_p.pkl"), fx.make_scenario(), protocol=protocol)
    raw = scenarionet.read_scenario(path)
    np.testing.assert_allclose(raw.agent_xy[~np.isnan(raw.agent_xy)], _raw().agent_xy[~np.isnan(_raw().agent_xy)],
                               atol=1e-4)


def test_scenario_description_subclass_is_read_as_dict(monkeypatch):
    """Older files were pickled as metadrive's ScenarioDescription (a dict subclass): it is read as a plain dict,
    without importing metadrive."""
    import types

    names = ("metadrive", "metadrive.scenario", "metadrive.scenario.scenario_description")
    for name in names:  # a stand-in for metadrive, only to write the pickle
        monkeypatch.setitem(sys.modules, name, types.ModuleType(name))
    mod = sys.modules[names[-1]]
    mod.ScenarioDescription = type("ScenarioDescription", (dict,), {"__module__": mod.__name__})
    sc = fx.make_scenario()
    data = pickle.dumps(mod.ScenarioDescription(sc), protocol=4)
    for name in names:
        monkeypatch.delitem(sys.modules, name)
    assert b"ScenarioDescription" in data
    obj = safe_pickle.loads(data, "sd.pkl")
    assert type(obj) is dict and set(obj) == set(sc)
    assert scenarionet.scenario_to_rawlog(obj, "sd.pkl").agent_ids == _raw().agent_ids


HOSTILE = [fx.TouchOnLoad, fx.MkdirOnLoad, fx.ExecOnLoad]


@pytest.mark.parametrize("payload", HOSTILE)
def test_hostile_pickle_does_run_under_plain_pickle(tmp_path, payload, monkeypatch):
    """Control: the payloads are live (plain pickle.load runs them), so the refusal test below can fail."""
    monkeypatch.delenv(fx.MARKER_ENV, raising=False)
    marker = str(tmp_path / "ran")
    sc = fx.make_scenario()
    sc["metadata"]["evil"] = payload(marker)
    data = pickle.dumps(sc)
    pickle.loads(data)  # noqa: S301 - our own payload, to prove it is live
    assert os.path.exists(marker)


@pytest.mark.parametrize("payload", HOSTILE)
@pytest.mark.parametrize("where", ["scenario", "summary", "mapping"])
def test_hostile_pickle_is_refused_and_never_runs(tmp_path, payload, where, monkeypatch):
    monkeypatch.delenv(fx.MARKER_ENV, raising=False)
    marker = str(tmp_path / "ran")
    db = str(tmp_path / "db")
    paths = fx.write_dataset(db, [fx.make_scenario()], layout="nested")
    evil = payload(marker)
    if where == "scenario":
        sc = fx.make_scenario()
        sc["tracks"]["ahead"]["metadata"]["x"] = [1, {"deep": evil}]
        target = fx.write_scenario(paths[0], sc)
    else:
        target = os.path.join(db, f"dataset_{where}.pkl")
        obj = safe_pickle.load(target)
        obj[next(iter(obj))] = evil if where == "mapping" else {"x": evil}
        fx.write_scenario(target, obj)
    with pytest.raises(DataError, match=r"refused to unpickle: the pickle names the global '(scenarionet_fixtures\."
                                        r"touch_marker|posix\.mkdir|builtins\.exec)'") as ei:
        scenarionet.build_scenarionet(str(tmp_path / "out"), db, split="test")
    assert ei.value.path == target
    assert not os.path.exists(marker) and fx.MARKER_ENV not in os.environ


def test_foreign_class_is_refused_naming_the_class(tmp_path):
    sc = fx.make_scenario()
    sc["metadata"]["obj"] = fx.Foreign()
    path = fx.write_scenario(str(tmp_path / "sd_f.pkl"), sc)
    with pytest.raises(DataError, match=r"sd_f\.pkl: refused to unpickle.*'scenarionet_fixtures\.Foreign'"):
        scenarionet.read_scenario(path)


@pytest.mark.parametrize("glob", [b"cos\nsystem\n", b"cbuiltins\ngetattr\n", b"cnumpy\nload\n",
                                  b"c_codecs\nlookup\n", b"ccopyreg\n_reconstructor\n"])
def test_unlisted_globals_are_refused(glob):
    with pytest.raises(DataError, match="refused to unpickle"):
        safe_pickle.loads(glob + b"(S'x'\ntR.", "h.pkl")


def test_codecs_encode_is_latin1_only():
    assert safe_pickle.loads(pickle.dumps(b"\x00\xffab", protocol=2)) == b"\x00\xffab"
    with pytest.raises(DataError, match="refused"):
        safe_pickle.loads(b"c_codecs\nencode\n(S'x'\nS'zlib'\ntR.", "h.pkl")


# ------------------------------------------------------------------------------------------ building
def _dataset(tmp_path, layout="nested", maps=("m_a", "m_b", "m_c"), per_map=2, frames=121, name="db"):
    scs = [fx.make_scenario(frames, map_name=m, scenario_id=f"{m}_{i}", seed=i)
           for m in maps for i in range(per_map)]
    db = str(tmp_path / name)
    fx.write_dataset(db, scs, layout=layout)
    return db


@pytest.mark.parametrize("layout", ["flat", "nested", "plain"])
def test_find_scenarios_layouts(tmp_path, layout):
    db = _dataset(tmp_path, layout)
    files = scenarionet.find_scenarios(db)
    assert len(files) == 6 and all(os.path.isfile(f.path) for f in files)
    assert all((f.metadata is None) == (layout == "plain") for f in files)
    if layout == "nested":
        assert {os.path.basename(os.path.dirname(f.path)) for f in files} == {"part_0", "part_1"}
    assert scenarionet.find_scenarios(files[0].path)[0].path == files[0].path


def test_find_scenarios_errors(tmp_path):
    with pytest.raises(DataError, match="no such file"):
        scenarionet.find_scenarios(str(tmp_path / "nope"))
    os.makedirs(tmp_path / "empty")
    with pytest.raises(DataError, match="no scenario .pkl files"):
        scenarionet.find_scenarios(str(tmp_path / "empty"))
    db = _dataset(tmp_path)
    os.remove(scenarionet.find_scenarios(db)[0].path)
    with pytest.raises(DataError, match="listed in .*dataset_summary.pkl but missing"):
        scenarionet.find_scenarios(db)


@pytest.mark.parametrize("layout", ["nested", "plain"])
def test_build_splits_by_map_and_summary_counts(tmp_path, layout):
    db = _dataset(tmp_path, layout)
    out = str(tmp_path / "out")
    man = scenarionet.build_scenarionet(out, db, seed=0, max_per_log=2, per_job=1)
    assert man["num_samples"] == 6 * 2
    split_of = {}
    for sp, v in man["splits"].items():
        for sh in v["shards"]:
            for loc in sh["locations"]:
                assert split_of.setdefault(loc, sp) == sp  # a map in one split only
    assert set(split_of) == {"m_a", "m_b", "m_c"} and set(split_of.values()) == {"train", "val", "test"}
    st = man["build"]["stats"]
    assert st["tracks_dropped_pedestrian"] == 6 and st["tracks_dropped_cyclist"] == 6
    assert st["scenarios_read"] == 6 and st["samples"] == 12 and st["map_lane"] == 18
    sh = store.Shard(store.list_shards(out, split_of["m_a"])[0])
    assert sh.meta["source"] == "scenarionet" and sh.meta["dataset"] == "testset"
    assert sh.meta["scenario_ids"][0].startswith("sd_testset_v1_m_a_")
    if layout == "plain":  # the per-file index was read once and cached
        assert os.path.isfile(os.path.join(out, "_jobs", "scenario_index.json"))


def test_build_resumes_and_refuses_other_settings_or_files(tmp_path, monkeypatch):
    db = _dataset(tmp_path, maps=("m_a",), per_map=4)
    out = str(tmp_path / "out")
    man = scenarionet.build_scenarionet(out, db, split="train", max_per_log=1, per_job=2)
    assert man["num_samples"] == 4 and man["build"]["jobs"] == 2
    calls = []
    real = scenarionet.run_scenarionet_job
    monkeypatch.setattr(scenarionet, "run_scenarionet_job", lambda *a, **k: calls.append(1) or real(*a, **k))
    os.remove(os.path.join(out, "_jobs", "job_00001.json"))  # as if stopped during the second job
    man2 = scenarionet.build_scenarionet(out, db, split="train", max_per_log=1, per_job=2)
    assert len(calls) == 1 and man2["num_samples"] == 4
    with pytest.raises(ValueError, match="other settings"):
        scenarionet.build_scenarionet(out, db, split="train", max_per_log=2, per_job=2)
    fx.write_scenario(os.path.join(db, "part_0", "sd_extra.pkl"), fx.make_scenario())
    summary = safe_pickle.load(os.path.join(db, "dataset_summary.pkl"))
    summary["sd_extra.pkl"] = {"map": "m_a"}
    mapping = safe_pickle.load(os.path.join(db, "dataset_mapping.pkl"))
    mapping["sd_extra.pkl"] = "part_0"
    fx.write_scenario(os.path.join(db, "dataset_summary.pkl"), summary)
    fx.write_scenario(os.path.join(db, "dataset_mapping.pkl"), mapping)
    with pytest.raises(ValueError, match="other settings"):
        scenarionet.build_scenarionet(out, db, split="train", max_per_log=1, per_job=2)


def test_bad_file_stops_build_or_is_skipped(tmp_path):
    db = _dataset(tmp_path, maps=("m_a",), per_map=3)
    bad = scenarionet.find_scenarios(db)[1].path
    sc = fx.make_scenario()
    del sc["metadata"]["sdc_id"]
    fx.write_scenario(bad, sc)
    with pytest.raises(DataError, match="sdc_id") as ei:
        scenarionet.build_scenarionet(str(tmp_path / "o1"), db, split="train")
    assert ei.value.path == bad
    man = scenarionet.build_scenarionet(str(tmp_path / "o2"), db, split="train", skip_bad=True, max_per_log=1)
    assert man["num_samples"] == 2 and man["build"]["stats"]["scenarios_skipped_bad"] == 1
    assert any(bad in r for r in man["build"]["rejections"])


def test_short_scenarios_are_counted(tmp_path, caplog):
    db = _dataset(tmp_path, maps=("m_a",), per_map=2, frames=91)  # Waymo length
    man = scenarionet.build_scenarionet(str(tmp_path / "o"), db, split="train")
    assert man["num_samples"] == 0 and man["build"]["stats"]["skip_log_too_short"] == 2
    assert "shorter than the 101 frames" in caplog.text


def test_cli_build_ok_and_exit_status_2(tmp_path, capsys):
    db = _dataset(tmp_path, maps=("m_a", "m_b"), per_map=1)
    assert data_main(["build", "--source", "scenarionet", "--db", db, "--out", str(tmp_path / "o"),
                      "--max-per-log", "1", "--workers", "1"]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["num_samples"] == 2 and set(printed["splits"]) == {"train", "test"}
    path = fx.write_scenario(str(tmp_path / "sd_20hz_bad.pkl"), fx.make_scenario(num_frames=60, hz=4.0))
    assert data_main(["build", "--source", "scenarionet", "--db", path, "--out", str(tmp_path / "o2"),
                      "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert "sd_20hz_bad.pkl" in err and "4.00 Hz" in err
    assert data_main(["build", "--source", "scenarionet", "--out", str(tmp_path / "o3")]) == 2
    assert "needs --db" in capsys.readouterr().err


def test_build_with_two_workers(tmp_path):
    db = _dataset(tmp_path, maps=("m_a", "m_b", "m_c"), per_map=1)
    man = scenarionet.build_scenarionet(str(tmp_path / "o"), db, workers=2, per_job=1, max_per_log=1)
    assert man["num_samples"] == 3


def test_inspect_reports_per_source(tmp_path):
    db = _dataset(tmp_path, maps=("m_a",), per_map=2)
    out = str(tmp_path / "o")
    scenarionet.build_scenarionet(out, db, split="train", max_per_log=2)
    s = inspection.inspect(out, with_lanes=False)
    per = s["per_source"]["scenarionet/testset"]
    assert per["scenarios"] == 4 == s["scenarios"]
    assert per["agents_per_frame_mean"] == pytest.approx(s["agents_per_frame_mean"])
    assert per["speed_mps_p50"] == pytest.approx(10.0, abs=0.05)  # everyone drives at 10 m/s (extras 8 m/s)
    assert per["stationary_fraction"] == 0.0 and per["log_collisions"] == 0
    assert per["agent_types"]["bus"] >= 4
    assert "scenarionet/testset" in inspection.format_summary(s)


# ------------------------------------------------------------------------------------------ evaluation
def test_rollout_cli_on_a_scenarionet_store(tmp_path):
    """A store built from ScenarioNet scenarios evaluates with rollout.py (tiny model, traffic simulation)."""
    from flax import nnx

    sys.path.insert(0, ROOT)
    import rollout
    from gpd_jax.checkpoint import export_model, build_model
    from test_rollout_cli import tiny_config

    db = _dataset(tmp_path, maps=("m_a",), per_map=2)
    data = str(tmp_path / "store")
    scenarionet.build_scenarionet(data, db, split="test", max_per_log=1)
    config = tiny_config()
    _, params, _ = nnx.split(build_model(config), nnx.Param, ...)
    model = export_model(params, config, str(tmp_path / "model"))
    out = str(tmp_path / "eval")
    assert rollout.main(["--checkpoint", model, "--data", data, "--out", out, "--tasks", "traffic_simulation",
                         "--batch", "2", "--no-progress"]) == 0
    with open(os.path.join(out, "metrics.json")) as f:
        m = json.load(f)
    assert m["scenarios"] == 2 and set(m["tasks"]) == {"traffic_simulation"}
    per = m["tasks"]["traffic_simulation"]["3s"]
    assert np.isfinite(per["ego_ade"]) and np.isfinite(per["agent_ade"])
    assert m["baselines"]["log_replay"]["3s"]["agent_ade"] == 0.0


# -------------------------------------------------------------------------------------- drivable area
def test_sample_geometry_from_lane_widths_polygons_and_driveways():
    """Scene frame of the first window: x = road along - 20 m (the ego's position at the current frame), y =
    lateral. Lanes at y = -3.5 and 0 from `width`, the left lane from its `polygon`, a driveway at x 60 .. 70,
    y 5.25 .. 15."""
    import jax
    import jax.numpy as jnp

    from gpd_jax import geometry as geo

    stats = Counter()
    raw = _raw(fx.make_scenario(), stats)
    assert stats["lane_area_from_width"] == 2 and stats["lane_area_from_polygon"] == 1
    (_, s), *_ = list(preprocess.iter_samples(raw, preprocess.SampleConfig()))
    road = geo.road_from_arrays(s, s["polylines"], s["polyline_valid"]).validate()
    pts = {  # name: (xy, on road, kinds, signed distance)
        "on the ego's lane": ((10.0, 0.0), True, [True, False, False], 5.25),
        "between two lanes": ((10.0, 1.75), True, [True, False, False], 3.5),
        "on the polygon lane": ((10.0, 4.0), True, [True, False, False], 1.25),
        "in the driveway": ((65.0, 10.0), True, [False, False, True], 5.0),
        "off the road": ((10.0, 8.0), False, [False, False, False], -2.75),
    }
    xy = jnp.asarray([p[0] for p in pts.values()], jnp.float32)
    on = np.asarray(jax.jit(geo.on_road)(road, xy))
    kinds = np.asarray(jax.jit(geo.area_kinds)(road, xy))
    sd = np.asarray(jax.jit(geo.signed_distance_to_edge)(road, xy))
    for i, (name, (_, want_on, want_kinds, want_sd)) in enumerate(pts.items()):
        assert on[i] == want_on and kinds[i].tolist() == want_kinds, name
        assert sd[i] == pytest.approx(want_sd, abs=0.02), (name, sd[i])
    heading, dist = jax.jit(geo.lane_direction)(road, xy[:2])
    np.testing.assert_allclose(np.asarray(dist), [0.0, 1.75], atol=1e-3)
    np.testing.assert_allclose(np.asarray(heading), 0.0, atol=1e-4)
    assert np.asarray(jax.jit(geo.on_road)(road, jnp.asarray(s["xy"][s["valid"]]))).all()
