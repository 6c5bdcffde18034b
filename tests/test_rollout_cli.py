"""rollout.py end to end on a tiny store with a tiny exported model: metrics.json layout, pictures, bad input."""

import json
import os
import sys

import numpy as np
import pytest
from PIL import Image

from data_fixtures import write_small_store

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import rollout  # noqa: E402
from gpd_jax.evaluation.keys import AGENT_METRICS  # noqa: E402
from gpd_jax.tasks import TASK_NAMES  # noqa: E402

AGENT_KEYS = {f"{g}_{n}{s}" for g in ("ego", "agent") for n in AGENT_METRICS for s in ("", "_corrected")}


def tiny_config():
    """configs/gpd_tiny.py: the shipped models' view (1 Hz, 3 history + 8 future frames, 17 slots, the shipped map
    tokenizer's 64 tokens) with velocity inputs and the velocity residual, at a tiny size."""
    from gpd_jax.config import load_config

    return load_config(os.path.join(ROOT, "configs", "gpd_tiny.py"))


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    from flax import nnx

    from gpd_jax.checkpoint import build_model, export_model
    from gpd_jax.data import store
    from gpd_jax.map_tokenizer import load_tokenizer

    d = tmp_path_factory.mktemp("cli")
    data = str(d / "store")
    write_small_store(data, n_shards=2, per_shard=2, split="test")
    # shard 0 gets map tokens (what `python -m gpd_jax.map_tokenizer encode` writes); shard 1 has none
    tok = load_tokenizer("map_tokenizer")
    sh = store.Shard(store.shard_dir(data, "test", 0))
    a = sh.arrays
    tokens = np.asarray(tok.encode_frames(np.asarray(a["polylines"]), np.asarray(a["polyline_valid"]),
                                          np.asarray(a["ego_pose"])))
    store.save_map_tokens(data, "test", 0, tokens)
    config = tiny_config()
    _, params, _ = nnx.split(build_model(config), nnx.Param, ...)
    model = export_model(params, config, str(d / "model"))
    return d, data, model


@pytest.fixture(scope="module")
def run_ok(setup):
    d, data, model = setup
    out = str(d / "out")
    rc = rollout.main(["--checkpoint", model, "--data", data, "--out", out, "--scenarios", "3", "--batch", "2",
                       "--render", "1", "--render-size", "96", "--no-progress"])
    return rc, out


def _strict_json(path):
    def no_nan(c):
        raise ValueError(f"non-JSON constant {c}")
    with open(path) as f:
        return json.load(f, parse_constant=no_nan)


def test_metrics_json_layout(run_ok, setup):
    rc, out = run_ok
    assert rc == 0
    m = _strict_json(os.path.join(out, "metrics.json"))
    assert m["variant"] == "paper" and m["scenarios"] == 3 and m["split"] == "test"
    assert m["checkpoint"] == setup[2] and m["data"] == setup[1]
    assert m["frame_period_s"] == pytest.approx(1.0) and m["horizons"] == {"3s": 3, "5s": 5, "8s": 8}
    assert m["scored_agents"] == "valid at the current frame"
    assert m["map_tokens"] == {"from_store": 2, "encoded": 1}  # shard 0 has tokens, shard 1 is encoded
    assert set(m["tasks"]) == set(TASK_NAMES)
    assert set(m["baselines"]) == {"constant_velocity", "constant_velocity_model_rate", "log_replay",
                                   "constant_velocity_lanes", "map_tokenizer_reconstruction", "map_persistence"}
    assert set(m["ratios"]["traffic_simulation_agent_ade_over_constant_velocity_lanes"]) == {"3s", "5s", "8s"}
    for name in ("map_tokenizer_reconstruction", "map_persistence"):
        base = m["baselines"][name]
        assert set(base) == {"3s", "5s", "8s"} and 0.0 <= base["3s"]["map_f1"] <= 1.0, name
        assert not any(k.startswith(("ego_", "agent_")) for k in base["3s"]), name
    for name, per in m["tasks"].items():
        assert set(per) == {"3s", "5s", "8s"}
        keys = set(per["8s"])
        gen = m["task_generates"][name]
        for g in ("ego", "agent"):
            has = {k for k in keys if k.startswith(g + "_")}
            assert bool(has) == (g in gen), (name, g)
            if g in gen:
                assert has == {k for k in AGENT_KEYS if k.startswith(g + "_")}
        maps = {k for k in keys if k.startswith("map_")}
        assert bool(maps) == ("map" in gen), name
        if "map" in gen:
            assert {"map_f1", "map_lateral", "map_chamfer", "map_chamfer_corrected"} <= maps
            assert 0.0 <= per["3s"]["map_f1"] <= 1.0
    assert m["task_generates"]["closed_loop"] == ["agent"] and m["task_generates"]["motion_planning"] == ["ego"]
    for lb in ("3s", "5s", "8s"):
        lr = m["baselines"]["log_replay"][lb]
        assert lr["agent_ade"] == 0.0 and lr["ego_ade"] == 0.0 and lr["agent_fde_corrected"] == 0.0
        assert m["baselines"]["constant_velocity"][lb].keys() == lr.keys() == AGENT_KEYS
    for key in ("traffic_simulation_agent_ade_over_constant_velocity",
                "traffic_simulation_agent_ade_over_constant_velocity_model_rate"):
        assert set(m["ratios"][key]) == {"3s", "5s", "8s"}
    assert os.path.isfile(os.path.join(out, "tables.txt"))
    assert not [f for f in os.listdir(out) if f.startswith(".")]  # no temporaries left


def test_render_writes_gif_and_png_per_task(run_ok):
    rc, out = run_ok
    assert rc == 0
    files = sorted(os.listdir(os.path.join(out, "render")))
    assert files == sorted(f"0000_{t}.{e}" for t in TASK_NAMES for e in ("gif", "png"))
    with Image.open(os.path.join(out, "render", "0000_scene_generation.gif")) as im:
        assert im.n_frames == 11 and im.size == (96, 96)
    with Image.open(os.path.join(out, "render", "0000_map_prediction.png")) as im:
        assert im.size[1] == 96 and im.size[0] > 3 * 96


def test_tokens_of_another_tokenizer_are_encoded_again(run_ok, setup, tmp_path):
    import shutil

    from gpd_jax.data import store
    d, data, model = setup
    copy = str(tmp_path / "store")
    shutil.copytree(data, copy)
    tokens = np.asarray(store.Shard(store.shard_dir(copy, "test", 0)).map_tokens)
    store.save_map_tokens(copy, "test", 0, tokens, tokenizer="0" * 16)  # recorded as another tokenizer's
    assert store.foreign_map_token_shards(copy, "test", "0" * 16) == []
    out = str(tmp_path / "out")
    assert rollout.main(["--checkpoint", model, "--data", copy, "--out", out, "--scenarios", "3", "--batch", "2",
                         "--no-progress"]) == 0
    m = _strict_json(os.path.join(out, "metrics.json"))
    assert m["map_tokens"] == {"from_store": 0, "encoded": 3}
    # the tokens were this tokenizer's after all: same metrics as reading them from the store
    ref = _strict_json(os.path.join(run_ok[1], "metrics.json"))
    for lb, per in ref["tasks"]["traffic_simulation"].items():
        assert m["tasks"]["traffic_simulation"][lb] == pytest.approx(per), lb


def test_log_map_lanes_re_encodes_only_where_the_ego_is_generated_from_a_logged_map(run_ok, setup, tmp_path):
    d, data, model = setup
    out = str(tmp_path / "out")
    assert rollout.main(["--checkpoint", model, "--data", data, "--out", out, "--scenarios", "3", "--batch", "2",
                         "--no-progress", "--log-map", "lanes"]) == 0
    m, ref = _strict_json(os.path.join(out, "metrics.json")), _strict_json(os.path.join(run_ok[1], "metrics.json"))
    assert (m["log_map"], ref["log_map"]) == ("lanes", "tokens")
    for name in TASK_NAMES:
        if name in ("traffic_simulation", "motion_planning"):  # map from the log, ego generated: other inputs
            assert m["tasks"][name]["3s"]["ego_ade"] != pytest.approx(ref["tasks"][name]["3s"]["ego_ade"]), name
        else:  # the logged tokens (ego from the log) or no logged map: the same rollout
            assert m["tasks"][name] == ref["tasks"][name], name


def test_gen_map_warp_changes_only_generated_maps(run_ok, setup, tmp_path):
    d, data, model = setup
    out = str(tmp_path / "out")
    assert rollout.main(["--checkpoint", model, "--data", data, "--out", out, "--scenarios", "3", "--batch", "2",
                         "--no-progress", "--gen-map", "warp", "--tasks", "traffic_simulation,map_prediction"]) == 0
    m, ref = _strict_json(os.path.join(out, "metrics.json")), _strict_json(os.path.join(run_ok[1], "metrics.json"))
    assert (m["gen_map"], ref["gen_map"]) == ("warp", "model")
    ts, ts_ref = m["tasks"]["traffic_simulation"], ref["tasks"]["traffic_simulation"]  # its map is the log's
    for h in ts_ref:  # the same rollout (another task batch: float rounding only)
        assert {k: v for k, v in ts[h].items() if isinstance(v, float)} == pytest.approx(
            {k: v for k, v in ts_ref[h].items() if isinstance(v, float)}, rel=1e-5, abs=1e-6), h
    assert m["tasks"]["map_prediction"]["3s"]["map_f1_cutfree"] != pytest.approx(
        ref["tasks"]["map_prediction"]["3s"]["map_f1_cutfree"])


def _bad_model(setup, name, edit):
    d, _, model = setup
    bad = d / name
    bad.mkdir(exist_ok=True)
    cfg = json.load(open(os.path.join(model, "config.json")))
    edit(cfg)
    json.dump(cfg, open(bad / "config.json", "w"))
    if not (bad / "params.npz").exists():  # several cases may share one bad model
        os.symlink(os.path.join(model, "params.npz"), bad / "params.npz")
    return str(bad)


def _no_tokenizer(cfg):
    cfg["model"]["map_tokenizer"] = ""


def _shape_mismatch(cfg):
    cfg["model"]["num_frames"] = 21  # 21 frames at stride 10 need 201 stored frames
    cfg["model"]["num_agents"] = 40  # the store has 33 slots


@pytest.mark.parametrize("case, args, message", [
    ("missing checkpoint", ["--checkpoint", "{d}/nope"], "nope' not found: not a folder"),
    ("missing data", ["--data", "{d}/nodata"], "data directory not found"),
    ("missing split", ["--split", "val"], "split 'val' not found"),
    ("unknown task", ["--tasks", "traffic_simulation,flying"], "unknown task 'flying'"),
    ("too many scenarios", ["--scenarios", "5"], "5 scenarios asked for, but"),
    ("shape mismatch", ["--checkpoint", "{bad}"], "model and data do not match"),
    ("bad temperature", ["--temperature", "-1"], "argument --temperature: must be >= 0"),
    ("unknown flag", ["--config.model.d_model=8"], "unrecognized arguments: --config.model.d_model=8"),
    ("bad variant", ["--variant", "best"], "invalid choice"),
    ("log map without tokenizer", ["--checkpoint", "{notok}", "--log-map", "lanes"], "has none"),
    ("gen map without tokenizer", ["--checkpoint", "{notok}", "--gen-map", "warp"], "has none"),
])
def test_bad_input_exits_2_and_writes_nothing(setup, capsys, case, args, message):
    d, data, model = setup
    bad = _bad_model(setup, "bad_shapes", _shape_mismatch) if case == "shape mismatch" else ""
    notok = _bad_model(setup, "no_tokenizer", _no_tokenizer) if "without tokenizer" in case else ""
    out = d / f"out_{case.replace(' ', '_')}"
    # later occurrences of an option win (argparse), so the case's arguments go after the good ones
    argv = ["--checkpoint", model, "--data", data, "--out", str(out), "--no-progress"]
    argv += [a.format(d=d, bad=bad, notok=notok) for a in args]
    assert rollout.main(argv) == 2
    err = capsys.readouterr().err
    assert message in err, err
    assert not out.exists()


def test_scene_sums_add_up_to_the_run_and_compare_reads_them(run_ok, capsys, tmp_path):
    """Every run keeps each scenario's sums (scene_sums.npz): with every scene drawn once they give back the
    run's ratios, and `python -m gpd_jax.evaluation compare` reads them (a run against itself differs by 0)."""
    from gpd_jax.evaluation import __main__ as cli
    from gpd_jax.evaluation.bootstrap import compare_runs, load_scene_sums
    from gpd_jax.spec import EvalError

    rc, out = run_ok
    m = _strict_json(os.path.join(out, "metrics.json"))
    ss = load_scene_sums(out)
    assert ss.num_scenarios == 3 and len(set(ss.scenario_ids)) == 3
    assert ss.sums["counts/scenarios"].tolist() == [1.0, 1.0, 1.0]
    assert ss.locations == ("road_a",) * 3  # the store's per-sample road networks
    with pytest.raises(EvalError, match="at least 5 locations, the scenes have 1 \\('road_a'\\)"):
        compare_runs([ss], resamples=200, unit="location")
    for base, key in (("constant_velocity", "traffic_simulation_agent_ade_over_constant_velocity"),
                      ("constant_velocity_lanes", "traffic_simulation_agent_ade_over_constant_velocity_lanes")):
        res = compare_runs([ss, ss], baseline=base, resamples=200)
        for lb in ("3s", "5s", "8s"):
            assert res["runs"][0][lb]["ratio"] == pytest.approx(m["ratios"][key][lb], rel=1e-6)
            lo, hi = res["runs"][0][lb]["interval"]
            assert lo <= hi and np.isfinite([lo, hi]).all()
            assert res["versus_first"][0][lb]["difference"] == 0.0
            assert res["versus_first"][0][lb]["interval"] == [0.0, 0.0]
    js = str(tmp_path / "cmp.json")
    assert cli.main(["compare", out, out, "--names", "a,b", "--resamples", "200", "--json", js]) == 0
    assert "a |" in capsys.readouterr().out and _strict_json(js)["names"] == ["a", "b"]
    assert cli.main(["compare", out, str(tmp_path)]) == 2  # no scene_sums.npz there
    assert "no per-scene sums" in capsys.readouterr().err
