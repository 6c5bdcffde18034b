"""Many futures: the sampling agent head (`model.agent_bins`), its likelihood and sampling (temperature, top-k,
top-p), the rollout's sample axis (`RolloutOptions.samples`), head-only training, and the shipped sampling model."""

import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from gpd_jax.config import load_config
from gpd_jax.decoding import rollout_prepared, rollout_tasks, sample_agents, sample_categorical
from gpd_jax.model import GPD, Modes
from gpd_jax.options import RolloutOptions, Sampling
from gpd_jax.synthetic import synthetic_scenes
from gpd_jax.tasks import make_tasks

HEAD = ["--config.model.agent_bins=0.5", "--config.model.agent_bin_extent=(1.0, 0.5)",
        "--config.model.predict_delta=True"]


@pytest.fixture(scope="module")
def setup():
    cfg = load_config("configs/gpd_tiny.py:test", HEAD + ["--config.train.trainable=sampling_head"])
    m = cfg.model
    scenes = synthetic_scenes(0, 2, m.num_frames, m.num_history, m.num_agents, m.num_map_tokens, m.codebook_size)
    tasks = make_tasks(["traffic_simulation", "scene_generation"], m.num_map_tokens, m.num_agents)
    return cfg, GPD(m, nnx.Rngs(0)), jax.tree.map(jnp.asarray, scenes), jax.tree.map(jnp.asarray, tasks)


def _random_modes(rng, a=4, c=3, velocity=True):
    dims = 5 if velocity else 3
    return Modes(logits=jnp.asarray(rng.normal(size=(a, c)), jnp.float32),
                 xy=jnp.asarray(rng.normal(size=(a, c, 2)) * 3, jnp.float32),
                 heading=jnp.asarray(rng.uniform(-3, 3, size=(a, c)), jnp.float32),
                 velocity=jnp.asarray(rng.normal(size=(a, c, 2)) * 5, jnp.float32) if velocity else None,
                 scale=jnp.asarray(rng.uniform(0.2, 2.0, size=(a, c, dims)), jnp.float32),
                 axes=jnp.asarray(rng.uniform(-3, 3, size=(a,)), jnp.float32))


def test_log_prob_is_a_mixture_of_laplace_products_in_each_agents_axes():
    """Against a direct loop: rotate the error into the agent's axes, wrap the heading, sum the Laplace terms,
    mix with the softmax weights; velocity dims count only where known."""
    rng = np.random.default_rng(0)
    modes = _random_modes(rng)
    xy, heading = rng.normal(size=(4, 2)) * 3, rng.uniform(-3, 3, size=4)
    vel, known = rng.normal(size=(4, 2)) * 5, np.array([True, False, True, True])
    got = np.asarray(modes.log_prob(jnp.asarray(xy, jnp.float32), jnp.asarray(heading, jnp.float32),
                                    jnp.asarray(vel, jnp.float32), jnp.asarray(known)))
    m = jax.tree.map(lambda x: np.asarray(x, np.float64), modes)
    for i in range(4):
        c, s = math.cos(-m.axes[i]), math.sin(-m.axes[i])
        terms = []
        for j in range(3):
            def along(v):
                return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])
            dh = (heading[i] - m.heading[i, j] + math.pi) % (2 * math.pi) - math.pi
            err = list(along(xy[i] - m.xy[i, j])) + [dh]
            if known[i]:
                err += list(along(vel[i] - m.velocity[i, j]))
            b = m.scale[i, j, :len(err)]
            log_w = m.logits[i, j] - np.log(np.exp(m.logits[i]).sum())
            terms.append(log_w + np.sum(-np.log(2 * b) - np.abs(err) / b))
        want = np.log(np.sum(np.exp(terms)))
        np.testing.assert_allclose(got[i], want, rtol=1e-4, atol=1e-4 * abs(want))


def test_categorical_sampling_follows_the_tempered_probabilities_and_the_cuts():
    logits = jnp.log(jnp.array([0.5, 0.3, 0.15, 0.05]))
    keys = jax.random.split(jax.random.key(1), 20_000)
    draw = lambda s: np.bincount(np.asarray(jax.vmap(lambda k: sample_categorical(k, logits, s))(keys)),  # noqa: E731
                                 minlength=4) / len(keys)
    np.testing.assert_allclose(draw(Sampling(1.0)), [0.5, 0.3, 0.15, 0.05], atol=0.015)
    hot = np.exp(np.log([0.5, 0.3, 0.15, 0.05]) / 2.0)
    np.testing.assert_allclose(draw(Sampling(2.0)), hot / hot.sum(), atol=0.015)
    np.testing.assert_allclose(draw(Sampling(1.0, top_k=2)), [0.625, 0.375, 0, 0], atol=0.015)
    # top_p 0.7: {0.5, 0.3} is the smallest set that reaches it; 0.5 alone does not
    np.testing.assert_allclose(draw(Sampling(1.0, top_p=0.7)), [0.625, 0.375, 0, 0], atol=0.015)
    assert draw(Sampling(1.0, top_p=0.4))[0] == 1.0


def test_agent_samples_pick_a_component_and_its_noise_scaled_by_the_temperature():
    rng = np.random.default_rng(2)
    modes = _random_modes(rng)
    best = np.argmax(np.asarray(modes.logits), -1)
    xy, heading, vel = sample_agents(modes, jax.random.key(0), Sampling(1e-6, top_k=1))
    a = np.arange(4)
    np.testing.assert_allclose(xy, np.asarray(modes.xy)[a, best], atol=1e-4)
    np.testing.assert_allclose(heading, np.asarray(modes.heading)[a, best], atol=1e-4)
    np.testing.assert_allclose(vel, np.asarray(modes.velocity)[a, best], atol=1e-4)
    # one component: the noise along / across the agent's heading has mean |x| = temperature x scale
    one = jax.tree.map(lambda x: x[:, :1] if x.ndim > 1 else x, modes)
    keys = jax.random.split(jax.random.key(3), 4000)
    xy, _, _ = jax.vmap(lambda k: sample_agents(one, k, Sampling(0.5)))(keys)
    err = np.asarray(xy) - np.asarray(one.xy)[None, :, 0]
    th = -np.asarray(one.axes)
    along = np.stack([np.cos(th) * err[..., 0] - np.sin(th) * err[..., 1],
                      np.sin(th) * err[..., 0] + np.cos(th) * err[..., 1]], -1)
    np.testing.assert_allclose(np.abs(along).mean(0), 0.5 * np.asarray(one.scale)[:, 0, :2], rtol=0.1)


def test_temperature_zero_rolls_out_the_regression_heads_and_samples_differ_by_key(setup):
    """The sampling head adds parameters after every other one: a model without it (same seed) is the same model
    and rolls out identically at temperature 0; at temperature 1 the rollout's sample axis gives N futures of
    every (scene, task), different from each other only after the history, in one compile."""
    cfg, model, scenes, tasks = setup
    h = cfg.model.num_history
    plain_cfg = load_config("configs/gpd_tiny.py:test", ["--config.model.predict_delta=True"])
    plain = GPD(plain_cfg.model, nnx.Rngs(0))
    key = jax.random.key(0)
    chex.assert_trees_all_equal(rollout_tasks(model, scenes, tasks, key, h), rollout_tasks(plain, scenes, tasks, key, h))

    graphdef, state = nnx.split(model)
    opts = RolloutOptions(temperature=1.0, samples=4)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def fn(state, key):
        return rollout_prepared(nnx.merge(graphdef, state), scenes, tasks, key, h, opts)

    out = fn(state, key)
    fn(state, jax.random.key(1))
    chex.assert_shape(out.xy, (2, 2, 4, cfg.model.num_frames, cfg.model.num_agents, 2))
    np.testing.assert_array_equal(out.xy[:, :, :, :h], jnp.broadcast_to(out.xy[:, :, :1, :h], out.xy[:, :, :, :h].shape))
    gen = np.asarray(out.xy[:, :, :, h:])
    assert np.abs(gen[:, :, 1:] - gen[:, :, :1]).max(axis=(2, 3, 4, 5)).min() > 1e-3  # every pair's samples differ


def test_head_only_training_moves_the_sampling_head_alone_and_lowers_its_loss(setup):
    from gpd_jax.training.step import make_trainer

    _, _, scenes, _ = setup
    cfg = load_config("configs/gpd_tiny.py:test", HEAD + ["--config.train.trainable=sampling_head",
                                                          "--config.train.warmup_steps=1"])
    trainer, state = make_trainer(GPD(cfg.model, nnx.Rngs(0)), cfg)
    before = jax.tree.map(np.array, state.params)
    first = None
    for _ in range(30):
        state, parts = trainer.train_step(state, scenes)
        first = float(parts["modes"]) if first is None else first
    assert float(parts["modes"]) < first - 0.1
    moved = {jax.tree_util.keystr(p): bool(np.any(np.asarray(a) != b))
             for (p, a), b in zip(jax.tree_util.tree_flatten_with_path(state.params)[0], jax.tree.leaves(before))}
    assert all(m == ("mode_head" in p) for p, m in moved.items()), moved
    with pytest.raises(ValueError, match="agent_bins"):
        make_trainer(GPD(cfg.model, nnx.Rngs(0)), load_config("configs/gpd_tiny.py:test",
                                                               ["--config.train.trainable=sampling_head"]))


def test_fine_tuning_adds_the_head_to_a_model_without_one(setup, monkeypatch):
    """init_from a model without a sampling head: its parameters, plus this run's fresh head."""
    import types

    from gpd_jax.training import loop

    cfg, model, _, _ = setup
    plain_cfg = load_config("configs/gpd_tiny.py:test", ["--config.model.predict_delta=True"])
    src = nnx.state(GPD(plain_cfg.model, nnx.Rngs(5)), nnx.Param)
    monkeypatch.setattr(loop, "load_model", lambda path: types.SimpleNamespace(config=plain_cfg, params=src))
    fresh = nnx.state(model, nnx.Param)
    got = loop.initial_params("somewhere", cfg, fresh)
    head, rest = nnx.split_state(got, nnx.PathContains("mode_head"), ...)
    chex.assert_trees_all_equal(rest, src)
    chex.assert_trees_all_equal(head, nnx.split_state(fresh, nnx.PathContains("mode_head"), ...)[0])
    other = load_config("configs/gpd_tiny.py:test", HEAD + ["--config.model.num_layers=1"])
    with pytest.raises(ValueError, match="num_layers"):
        loop.initial_params("somewhere", other, fresh)


def test_sampling_head_is_a_mixture_fixed_to_the_grid_cells(setup):
    """`agent_bins` = w: one component per w-metre cell of the offset (along, across the agent's heading) from the
    regressed position, each a Laplace kernel of the cell's spread; heading and velocity are the regressed ones with
    one learned scale each. Near temperature 0 with top-k 1 a draw is the regressed position moved by the most
    likely cell, turned into the agent's axes."""
    from gpd_jax.model.transformer import bin_grid

    grid = bin_grid(0.5, (1.0, 0.5))
    np.testing.assert_allclose(grid[:3], [[-1.0, -0.5], [-1.0, 0.0], [-1.0, 0.5]])
    assert grid.shape == (15, 2) and np.all(np.abs(grid).max(0) == [1.0, 0.5])
    cfg, model, _, _ = setup  # agent_bins 0.5 m over +-1 m along, +-0.5 m across
    rng = np.random.default_rng(4)
    f, a, d = 2, 3, cfg.model.d_model
    ha = jnp.asarray(rng.normal(size=(f, a, d)), jnp.float32)
    xy, heading = jnp.asarray(rng.normal(size=(f, a, 2)), jnp.float32), jnp.asarray(rng.uniform(-3, 3, (f, a)))
    axes = jnp.asarray(rng.uniform(-3, 3, (f, a)), jnp.float32)
    modes = model.modes(ha, xy, heading, None, axes)
    chex.assert_shape((modes.logits, modes.xy, modes.heading, modes.scale), [(f, a, 15), (f, a, 15, 2), (f, a, 15),
                                                                              (f, a, 15, 3)])
    th = np.asarray(axes)[..., None]
    want = np.asarray(xy)[..., None, :] + np.stack([np.cos(th) * grid[:, 0] - np.sin(th) * grid[:, 1],
                                                    np.sin(th) * grid[:, 0] + np.cos(th) * grid[:, 1]], -1)
    np.testing.assert_allclose(modes.xy, want, atol=1e-5)
    np.testing.assert_allclose(modes.heading, np.broadcast_to(np.asarray(heading)[..., None], (f, a, 15)))
    np.testing.assert_allclose(modes.scale[..., :2], 0.5 / math.sqrt(24.0), rtol=1e-6)
    assert np.ptp(np.asarray(modes.scale[..., 2]), axis=-1).max() == 0  # one heading scale per agent
    one = jax.tree.map(lambda x: x[0], modes)
    got, _, _ = sample_agents(one, jax.random.key(0), Sampling(1e-6, top_k=1))
    best = np.argmax(np.asarray(one.logits), -1)
    np.testing.assert_allclose(got, np.asarray(one.xy)[np.arange(a), best], atol=1e-4)
    with pytest.raises(ValueError, match="agent_bins"):
        GPD(load_config("configs/gpd_tiny.py:test", ["--config.model.agent_bins=-1.0"]).model, nnx.Rngs(0))


def test_options_check_the_sampling_fields():
    for bad, match in (({"top_k": -1}, "top_k"), ({"top_p": 0.0}, "top_p"), ({"top_p": 1.5}, "top_p"),
                       ({"samples": 0}, "samples"), ({"samples": 2.0}, "samples")):
        with pytest.raises(ValueError, match=match):
            RolloutOptions(**bad)
    assert RolloutOptions(temperature=1, top_k=5).sampling == Sampling(1.0, 5, 1.0)


@pytest.fixture(scope="module")
def shipped(tmp_path_factory):
    import gpd_jax
    from data_fixtures import write_small_store

    path = str(tmp_path_factory.mktemp("sampling_store"))
    write_small_store(path, n_shards=1, per_shard=3, split="test")
    return gpd_jax.load_model("gpd_sampling"), gpd_jax.load_scenes(path, "test"), path


def test_the_shipped_sampling_model_is_the_default_at_temperature_zero_and_samples_in_one_call(shipped):
    """gpd_sampling is gpd_traffic plus a sampling head: the same rollouts at temperature 0; with samples=N the
    public rollout gives N different futures of each scene, and evaluate(samples=K) scores them."""
    import gpd_jax

    model, scenes, _ = shipped
    key = jax.random.key(0)
    chex.assert_trees_all_equal(gpd_jax.rollout(model, scenes, "traffic_simulation", key),
                                gpd_jax.rollout(gpd_jax.load_model("gpd_traffic"), scenes, "traffic_simulation", key))
    opts = RolloutOptions(temperature=1.0, samples=3)
    out = gpd_jax.rollout(model, scenes, "traffic_simulation", key, options=opts)
    s, h = model.spec, model.spec.num_history
    chex.assert_shape(out.xy, (3, 3, s.num_frames, s.num_agents, 2))
    moved = np.abs(np.asarray(out.xy[:, 1:, h:] - out.xy[:, :1, h:])) * np.asarray(out.valid[:, :1, h:, :, None])
    assert moved.max(axis=(1, 2, 3, 4)).min() > 0.01  # every scene's samples differ
    res = gpd_jax.evaluate(model, scenes, tasks=["traffic_simulation"], samples=4, options=opts.replace(samples=None))
    real = res["realism"]["tasks"]["traffic_simulation"]
    assert 0 < real["metametric"] <= 1 and real["scenarios"] == 3 and res["temperature"] == 1.0
    with pytest.raises(gpd_jax.evaluation.EvalError, match="samples=K"):
        gpd_jax.evaluate(model, scenes, tasks=["traffic_simulation"], options=opts)


def test_bench_samples_reports_the_kv_cache_of_k_futures(shipped, tmp_path, capsys):
    """`python -m gpd_jax.bench samples`: K futures of S scenes in one compiled call; its KV cache is S x K rollouts'
    caches, each 2 x layers x padded tokens x d floats."""
    import json

    from gpd_jax import bench

    model, _, store = shipped
    out = tmp_path / "samples.json"
    assert bench.main(["samples", "--data", store, "--samples", "3", "--scenarios", "3", "--temperature", "1.0",
                       "--repeats", "1", "--json", str(out)]) == 0
    rec = json.loads(out.read_text())
    m = model.config.model
    per = 2 * m.num_layers * model.module.padded_len(m.num_frames) * m.d_model * 4
    assert rec["rollouts"] == 9 and rec["kv_cache_bytes_per_rollout"] == per
    assert rec["kv_cache_bytes_per_scenario"] == 3 * per and rec["sample_spread_m"] > 0
    assert rec["memory"]["peak_bytes_per_scenario"] >= 3 * per
    assert "KV cache" in capsys.readouterr().out
