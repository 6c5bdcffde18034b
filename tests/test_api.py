"""The public API (`import gpd_jax`): the shipped model on a small store, shapes, one compile, agreement with the
store-driven evaluation, a gradient through the pure rollout function, and the examples as users run them."""

import os
import sys

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpd_jax
from data_fixtures import write_small_store

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TASKS = ["traffic_simulation", "scene_generation"]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("api_store"))
    write_small_store(path, n_shards=2, per_shard=2, split="test")
    return path


@pytest.fixture(scope="module")
def model():
    return gpd_jax.load_model()


@pytest.fixture(scope="module")
def scenes(store):
    return gpd_jax.load_scenes(store, "test")


def test_public_names_are_curated():
    assert set(gpd_jax.__all__) >= {"load_model", "list_models", "load_scenes", "build_scenes", "rollout",
                                    "make_rollout_fn", "evaluate", "metrics", "render", "Model", "Scene", "Task",
                                    "RolloutOptions", "sim"}
    for name in gpd_jax.__all__:
        assert hasattr(gpd_jax, name), name


def test_a_dozen_lines_roll_out_and_score_four_scenes(model, scenes):
    assert scenes.xy.shape[0] == 4 and scenes.polylines is not None
    out = gpd_jax.rollout(model, scenes, TASKS, jax.random.key(0))
    s = model.spec
    chex.assert_shape(out.xy, (4, 2, s.num_frames, s.num_agents, 2))
    chex.assert_shape(out.map_tokens, (4, 2, s.num_frames, s.num_map_tokens))
    results = gpd_jax.evaluate(model, scenes, tasks=TASKS)
    ade = results["tasks"]["traffic_simulation"]["3s"]["agent_ade"]
    assert np.isfinite(ade) and ade >= 0
    assert results["scenarios"] == 4 and set(results["tasks"]) == set(TASKS)


def test_samples_add_a_realism_table_beside_unchanged_metrics(model, scenes):
    """evaluate(samples=K): the WOSAC-form realism of every task that moves agents and of the baselines; the
    paper's metrics stay as they are; the log scored against itself has no displacement and no collision."""
    plain = gpd_jax.evaluate(model, scenes, tasks=TASKS)
    res = gpd_jax.evaluate(model, scenes, tasks=TASKS, samples=3, realism_config="2024")
    assert res["tasks"] == plain["tasks"] and res["baselines"] == plain["baselines"]
    real = res["realism"]
    assert real["samples"] == 3 and real["config"] == "2024" and set(real["tasks"]) == set(TASKS)
    assert set(real["baselines"]) == {"constant_velocity", "constant_velocity_lanes", "log"}
    for d in list(real["tasks"].values()) + list(real["baselines"].values()):
        assert 0 < d["metametric"] <= 1 and d["scenarios"] == 4, d
    log = real["baselines"]["log"]
    assert log["min_ade"] == 0 and log["collision_rate"] == 0 and log["collision_indication_likelihood"] > 0.99
    assert real["baselines"]["constant_velocity"]["min_ade"] > 0
    assert abs(sum(real["weights"].values()) - 1) < 1e-9
    # the official code's counting rules beside the corrected ones, on the same rollouts
    off = res["realism_official"]
    assert real["rules"] == "corrected" and off["rules"] == "official" and off["samples"] == 3
    assert set(off["tasks"]) == set(TASKS) and set(off["baselines"]) == set(real["baselines"])
    assert off["baselines"]["log"]["min_ade"] == 0 and 0 < off["tasks"][TASKS[0]]["metametric"] <= 1
    assert off["tasks"] != real["tasks"]  # the kinematic terms count differently
    tables = gpd_jax.evaluation.format_tables(res)
    assert "Realism, corrected rules (3 rollouts per scenario" in tables and "Realism, official rules" in tables


def test_export_official_refuses_what_the_official_format_cannot_hold(model, scenes, tmp_path):
    """--export-official needs K rollouts and the official 11 + 80 frames at 10 Hz; it says so before rolling
    anything out and writes nothing."""
    from gpd_jax.evaluation.driver import run_evaluation
    from gpd_jax.spec import EvalError

    out = tmp_path / "official"
    with pytest.raises(EvalError, match="samples"):
        run_evaluation(model, scenes, task_names=TASKS, export_official=str(out), progress=False)
    spec = model.spec
    if spec.full_history < 11 or spec.stored_frames_needed - spec.full_history < 80:  # the tiny test model
        with pytest.raises(EvalError, match="11 history and 80 future frames"):
            run_evaluation(model, scenes, task_names=TASKS, samples=2, export_official=str(out), progress=False)
    assert not out.exists()


def test_in_memory_scenes_score_as_the_store_does(model, scenes, store):
    from_scenes = gpd_jax.evaluate(model, scenes, tasks=TASKS)
    from_store = gpd_jax.evaluate(model, store, tasks=TASKS)
    assert from_scenes["tasks"] == from_store["tasks"]
    assert from_scenes["baselines"] == from_store["baselines"]


def test_per_layout_figures_are_each_layout_scored_alone(model, scenes):
    """by_layout holds each layout's figures: the same as evaluating its scenarios alone; the overall figures
    do not change with grouping (up to float summation order)."""
    both = gpd_jax.evaluate(model, scenes, tasks=TASKS, batch_size=4, layouts=["grid", "real", "grid", "real"])
    plain = gpd_jax.evaluate(model, scenes, tasks=TASKS, batch_size=4)
    assert set(both["by_layout"]) == {"grid", "real"} and "by_layout" not in plain
    close = lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)

    def compare(a, b):
        for name in ("tasks", "baselines"):
            for key in a[name]:
                for lb in a[name][key]:
                    for k, v in a[name][key][lb].items():
                        close(np.float64(np.nan if v is None else v), np.float64(np.nan if b[name][key][lb][k] is None
                                                                                 else b[name][key][lb][k]))

    compare(both, plain)
    for layout, idx in (("grid", [0, 2]), ("real", [1, 3])):
        alone = gpd_jax.evaluate(model, jax.tree.map(lambda x: x[np.array(idx)], scenes), tasks=TASKS)
        assert both["by_layout"][layout]["scenarios"] == 2
        compare(both["by_layout"][layout], alone)
    assert "Per road-network layout" in gpd_jax.evaluation.format_tables(both)


def test_one_scene_one_task_drop_their_axes_and_match_the_batch(model, scenes):
    batch = gpd_jax.rollout(model, scenes, TASKS, jax.random.key(0))
    one = gpd_jax.rollout(model, jax.tree.map(lambda x: x[2], scenes), "scene_generation", jax.random.key(0))
    chex.assert_shape(one.xy, batch.xy.shape[2:])
    np.testing.assert_allclose(one.xy, batch.xy[2, 1], rtol=1e-4, atol=1e-4 * float(jnp.abs(batch.xy).max()))
    np.testing.assert_array_equal(one.map_tokens, batch.map_tokens[2, 1])


def test_rollout_compiles_once_per_shape(model, scenes):
    from gpd_jax.decoding import rollout_jit

    gpd_jax.rollout(model, scenes, TASKS, jax.random.key(1))
    before = rollout_jit._cache_size()
    gpd_jax.rollout(model, scenes, TASKS[::-1], jax.random.key(2))  # other tasks, same shapes
    other = model.replace(params=jax.tree.map(lambda p: p * 1.01, model.params))  # other parameters
    gpd_jax.rollout(other, scenes, TASKS, jax.random.key(3))
    assert rollout_jit._cache_size() == before


def test_make_rollout_fn_is_pure_jittable_and_traced_once(model, scenes):
    view = model.prepare(scenes)
    tasks = gpd_jax.make_tasks(model, TASKS)
    fn = jax.jit(chex.assert_max_traces(gpd_jax.make_rollout_fn(model), n=1))
    a = fn(model.params, view, tasks, jax.random.key(0))
    b = fn(jax.tree.map(lambda p: p + 0.0, model.params), view, tasks, jax.random.key(5))
    ref = gpd_jax.rollout(model, scenes, TASKS, jax.random.key(0))
    np.testing.assert_array_equal(a.map_tokens, b.map_tokens)  # greedy: the key does not matter
    np.testing.assert_allclose(a.xy, ref.xy, rtol=1e-4, atol=1e-4 * float(jnp.abs(ref.xy).max()))


def test_rollout_options_are_checked_once_naming_the_field():
    with pytest.raises(ValueError, match="RolloutOptions.method"):
        gpd_jax.RolloutOptions(method="fast")
    with pytest.raises(ValueError, match="RolloutOptions.temperature"):
        gpd_jax.RolloutOptions(temperature=-1.0)
    with pytest.raises(ValueError, match="RolloutOptions.log_map"):
        gpd_jax.RolloutOptions(log_map="lane")
    assert gpd_jax.RolloutOptions(temperature=1) == gpd_jax.RolloutOptions(temperature=1.0)  # hashable, static


@pytest.mark.parametrize("example", ["quickstart.py", "functional.py", "stationary_drift.py"])
def test_examples_run(example, store, model, tmp_path, monkeypatch, capsys):
    """The examples as a user runs them: their command line, from another folder; in this process, with the
    module's model (what `gpd_jax.load_model()` gives, loaded once)."""
    import runpy

    path = os.path.join(ROOT, "examples", example)
    args = ["--data", store]
    if example == "quickstart.py":
        args += ["--scenes", "2", "--out", str(tmp_path / "pictures")]
    elif example == "stationary_drift.py":
        args += ["--split", "test", "--scenarios", "2", "--json", str(tmp_path / "drift.json")]
    else:
        args += ["--shifts=-1,1"]
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [path] + args)
    monkeypatch.setattr(gpd_jax, "load_model", lambda name_or_path=None, step=None: model)
    try:
        runpy.run_path(path, run_name="__main__")
    except SystemExit as e:  # a script's `raise SystemExit(main())`
        assert e.code in (0, None), e.code
    res = type("Run", (), {"stdout": capsys.readouterr().out})
    if example == "quickstart.py":
        assert "traffic_simulation 3s" in res.stdout.replace("  ", " ")
        assert any(f.endswith(".gif") for f in os.listdir(tmp_path / "pictures"))
    elif example == "stationary_drift.py":
        import json

        out = json.load(open(tmp_path / "drift.json"))
        assert out["scenarios"] == 2 and set(out["frames"]) <= {"1", "2", "3", "5", "8"} and out["frames"]
    else:  # the gradient of a rollout's final error with respect to every parameter, through the recompute rollout
        import re

        m = re.search(r"mean 8 s error (\S+) m; gradient norm (\S+)", res.stdout)
        assert m, res.stdout
        loss, norm = float(m.group(1)), float(m.group(2))
        assert np.isfinite(loss) and np.isfinite(norm) and norm > 0, (loss, norm)


def test_map_use_example_swaps_only_the_map(scenes, store):
    import dataclasses
    import importlib.util

    spec = importlib.util.spec_from_file_location("map_use", os.path.join(ROOT, "examples", "map_use.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    with pytest.raises(SystemExit, match="no stored map tokens"):
        mod.main(["--data", store, "--split", "test", "--scenarios", "2"])
    n = np.asarray(scenes.xy).shape[0]
    tok = np.arange(np.asarray(scenes.map_tokens).size).reshape(np.asarray(scenes.map_tokens).shape) % 7
    tok[..., :3] = 5  # the most frequent code
    sc = dataclasses.replace(scenes, map_tokens=tok, map_valid=np.ones_like(np.asarray(scenes.map_valid)))
    v = mod.map_variants(sc)
    assert set(v) == {"logged", "other_scene", "constant_code"}
    np.testing.assert_array_equal(v["other_scene"].map_tokens[1:], tok[:-1])
    np.testing.assert_array_equal(v["other_scene"].polylines[0], np.asarray(scenes.polylines)[n - 1])
    assert np.all(v["constant_code"].map_tokens == 5)
    for name in ("other_scene", "constant_code"):  # agents, frames and poses untouched
        for f in ("xy", "heading", "valid", "ego_pose"):
            np.testing.assert_array_equal(np.asarray(getattr(v[name], f)), np.asarray(getattr(scenes, f)))


def test_stationary_drift_example_measures_stopped_agents_only():
    import importlib.util
    from types import SimpleNamespace

    spec = importlib.util.spec_from_file_location("drift", os.path.join(ROOT, "examples", "stationary_drift.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    t, a = 6, 4
    xy = np.zeros((1, t, a, 2), np.float32)
    xy[0, :, 2, 0] = 5.0 * np.arange(t)  # slot 2 moves: not stationary
    xy[0, 4:, 3, 1] = 2.0  # slot 3 stood, then left 2 m sideways in the log
    vel = np.zeros((1, t, a, 2), np.float32)
    vel[0, :, 2, 0] = 5.0
    valid = np.ones((1, t, a), bool)
    out_xy = xy.copy()
    out_xy[0, 2:, 1, 0] = 0.3 * np.arange(1, t - 1)  # slot 1 creeps 0.3 m a frame in the rollout
    out_xy[0, 2:, 3] = 0.0  # slot 3 stays put in the rollout
    out_valid = valid.copy()
    out_valid[0, 5, 1] = False  # not scored where the rollout dropped it
    res = mod.stationary_drift(SimpleNamespace(xy=xy, valid=valid, velocity=vel), out_xy, out_valid, 2,
                               frames=(1, 3, 4, 9))
    assert set(res) == {"1", "3", "4"}  # frame 9 lies beyond the scene
    assert res["1"]["n"] == 2 and res["4"]["n"] == 1  # slots 1 and 3 (never the ego or the moving slot 2)
    np.testing.assert_allclose(res["3"]["generated_quantiles_m"][0], 0.45, rtol=1e-5)  # median of 0.9 and 0
    np.testing.assert_allclose(res["3"]["logged_quantiles_m"][0], 1.0, rtol=1e-5)  # median of 0 and 2
    assert res["3"]["logged_beyond_1m"] == 0.5 and res["1"]["generated_beyond_1m"] == 0.0
    np.testing.assert_allclose(res["3"]["error_m"], (0.9 + 2.0) / 2, rtol=1e-5)
    np.testing.assert_allclose(res["3"]["stay_put_error_m"], 1.0, rtol=1e-5)
    np.testing.assert_allclose(res["4"]["generated_quantiles_m"][0], 0.0, atol=1e-6)  # slot 3 alone
