"""Closed-loop fine-tuning (gpd_jax/training/closed_loop.py): the closest-of-K choice, the rollout it trains on, the
compiled step (one trace) and an exact resume."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from gpd_jax.config import load_config
from gpd_jax.decoding import Frame
from gpd_jax.model import GPD, Modes
from gpd_jax.synthetic import synthetic_scenes
from gpd_jax.training.closed_loop import closed_loop_inputs, closest_frame, closest_of_k, top_k_candidates
from gpd_jax.training.step import free_running_inputs, make_trainer
from test_train_loop import _config, _params, _store

HEAD = ["--config.model.agent_bins=0.5", "--config.model.agent_bin_extent=(1.0, 0.5)",
        "--config.model.predict_delta=True", "--config.model.velocity_inputs=True"]


def _modes(rng, a=3, c=6):
    return Modes(logits=jnp.asarray(rng.normal(size=(a, c)), jnp.float32),
                 xy=jnp.asarray(rng.normal(size=(a, c, 2)) * 3, jnp.float32),
                 heading=jnp.asarray(rng.uniform(-3, 3, size=(a, c)), jnp.float32),
                 velocity=jnp.asarray(rng.normal(size=(a, c, 2)) * 5, jnp.float32),
                 scale=jnp.ones((a, c, 5), jnp.float32), axes=jnp.zeros((a,), jnp.float32))


def test_closest_of_k_keeps_the_log_nearest_of_the_top_k_cells():
    rng = np.random.default_rng(0)
    modes = _modes(rng)
    a, k = 3, 3
    t = 1
    log_xy = jnp.asarray(rng.normal(size=(2, a, 2)) * 3, jnp.float32)
    log = Frame(xy=log_xy, heading=jnp.zeros((2, a)), valid=jnp.ones((2, a), bool), valid_logit=jnp.zeros((2, a)),
                map_tokens=jnp.zeros((2, 4), jnp.int32), velocity=jnp.zeros((2, a, 2)))
    own = jnp.asarray([True, True, False])
    frame = closest_frame(modes, log, t, own, k)
    top = np.argsort(-np.asarray(modes.logits), axis=-1)[:, :k]
    for i in range(a):
        if not own[i]:  # not valid at t - 1: the log's state
            np.testing.assert_array_equal(frame.xy[i], log_xy[t, i])
            continue
        d = [np.linalg.norm(np.asarray(modes.xy[i, c]) - np.asarray(log_xy[t, i])) for c in top[i]]
        best = top[i][int(np.argmin(d))]
        np.testing.assert_array_equal(frame.xy[i], modes.xy[i, best])
        np.testing.assert_array_equal(frame.heading[i], modes.heading[i, best])
        np.testing.assert_array_equal(frame.velocity[i], modes.velocity[i, best])
    # the candidates are the k most likely cells, and the choice is the nearest of them
    xy, _, _ = top_k_candidates(modes, k)
    np.testing.assert_array_equal(np.sort(np.asarray(xy), axis=1), np.sort(np.asarray(modes.xy)[np.arange(a)[:, None],
                                                                                             top], axis=1))
    assert list(closest_of_k(jnp.asarray([[[0.0, 0.0], [2.0, 0.0], [1.1, 0.0]]]), jnp.asarray([[1.0, 0.0]]))) == [2]


@pytest.fixture(scope="module")
def tiny():
    cfg = load_config("configs/gpd_tiny.py:test", HEAD + ["--config.train.closed_loop_top_k=4"])
    m = cfg.model
    scenes = synthetic_scenes(0, 2, m.num_frames, m.num_history, m.num_agents, m.num_map_tokens, m.codebook_size)
    scenes = jax.tree.map(jnp.asarray, scenes)
    return cfg, GPD(m, nnx.Rngs(0)), jax.vmap(lambda s: s.with_velocity(0.1))(scenes)


def test_the_rollout_keeps_history_and_stays_nearer_the_log_than_the_top_cell(tiny):
    cfg, model, scenes = tiny
    h = cfg.model.num_history
    scene = jax.tree.map(lambda a: a[0], scenes)
    xy, heading, vel, maps = closed_loop_inputs(model, scene, h, 4)
    one, _, _, _ = closed_loop_inputs(model, scene, h, 1)
    np.testing.assert_array_equal(xy[:h], scene.xy[:h])
    np.testing.assert_array_equal(maps, scene.map_tokens[:-1])
    assert xy.shape == scene.xy[:-1].shape and vel.shape == scene.xy[:-1].shape
    own = np.asarray(scene.valid[h] & scene.valid[h - 1])
    assert own.any()
    err = lambda a: np.linalg.norm(np.asarray(a[h] - scene.xy[h]), axis=-1)[own]  # noqa: E731
    # the first reached frame: the closest of the top 4 is never farther than the top 1 (which is among them)
    assert np.all(err(xy) <= err(one) + 1e-6) and np.any(err(xy) < err(one) - 1e-6)
    # the reached states are the model's: not the log's, and not a teacher-forced pass's regression
    tf, _, _, _ = free_running_inputs(model, scene, h, 1)
    assert not np.allclose(np.asarray(xy[h])[own], np.asarray(tf[h])[own])


def test_closed_loop_train_step_compiles_once_and_learns(tiny):
    cfg, model, scenes = tiny
    trainer, state = make_trainer(model, cfg, donate=False)
    step = jax.jit(chex.assert_max_traces(trainer.step_fn, n=1))
    losses = []
    for _ in range(3):
        state, parts = step(state, scenes)
        losses.append(float(parts["loss"]))
    assert all(np.isfinite(losses)) and losses[-1] < losses[0]
    assert float(parts["grad_norm"]) > 0


def test_closed_loop_needs_a_sampling_head_and_no_rollout_passes():
    cfg = load_config("configs/gpd_tiny.py:test", ["--config.train.closed_loop_top_k=4"])
    with pytest.raises(ValueError, match="agent_bins"):
        make_trainer(GPD(cfg.model, nnx.Rngs(0)), cfg)
    cfg = load_config("configs/gpd_tiny.py:test", HEAD + ["--config.train.closed_loop_top_k=4",
                                                          "--config.train.rollout_passes=1"])
    with pytest.raises(ValueError, match="closed_loop_top_k"):
        make_trainer(GPD(cfg.model, nnx.Rngs(0)), cfg)


def _closed_loop_config(store):
    c = _config(store, closed_loop_top_k=3)
    c.model.agent_bins, c.model.agent_bin_extent = 0.5, (1.0, 0.5)
    return c


def _pair(gap):
    """Two 4 x 2 m cars side by side `gap` metres apart (centre to centre across), 3 frames, history 1."""
    xy = np.zeros((3, 2, 2), np.float32)
    xy[:, 1, 1] = gap
    xy[:, :, 0] = np.arange(3)[:, None] * 2.0  # both drive 2 m a frame
    return jnp.asarray(xy), jnp.zeros((3, 2)), jnp.ones((3, 2), bool), jnp.asarray([[4.0, 2.0], [4.0, 2.0]])


def test_a_colliding_pair_is_rewarded_less_than_a_pair_apart():
    from gpd_jax.geometry import empty_road
    from gpd_jax.training.closed_loop import agent_rewards

    apart, hit = _pair(3.0), _pair(1.0)
    r_apart = agent_rewards(*apart, 1, apart[0], apart[2])
    r_hit = agent_rewards(*hit, 1, hit[0], hit[2])
    np.testing.assert_array_equal(r_hit.collided, [1.0, 1.0])
    np.testing.assert_array_equal(r_apart.collided, [0.0, 0.0])
    assert np.all(np.asarray(r_hit.total) < np.asarray(r_apart.total))
    # progress: the logged path driven is worth 1, standing still 0; off the (empty) road costs
    still = agent_rewards(jnp.broadcast_to(apart[0][:1], apart[0].shape), *apart[1:], 1, apart[0], apart[2])
    np.testing.assert_allclose(r_apart.progress, [1.0, 1.0])
    np.testing.assert_allclose(still.progress, [0.0, 0.0])
    off = agent_rewards(*apart, 1, apart[0], apart[2], road=empty_road())
    np.testing.assert_allclose(off.offroad, [1.0, 1.0])
    assert np.all(np.asarray(off.total) < np.asarray(r_apart.total))


def test_group_advantages_are_relative_within_each_agents_group():
    from gpd_jax.training.closed_loop import group_advantages

    r = jnp.asarray([[0.0, 5.0, 1.0], [1.0, 5.0, 1.0], [2.0, 5.0, 1.0]])
    adv = np.asarray(group_advantages(r, jnp.asarray([True, True, False])))
    assert adv[0, 0] < 0 < adv[2, 0] and abs(adv[1, 0]) < 1e-6
    np.testing.assert_array_equal(adv[:, 1:], 0.0)  # no difference in the group / an agent left out


def test_a_closed_loop_and_reward_fine_tune_resumes_exactly(tmp_path_factory):
    """Both fine-tunes in one config (one compile): the closest-of-K inputs, the sampled rollouts' rewards (their
    key folded with the step), stopped after 2 of 4 steps and resumed: the same parameters, bit for bit."""
    from gpd_jax.training.loop import train_and_evaluate

    def config(store):
        c = _closed_loop_config(store)
        c.train.reward_samples, c.train.steps = 2, 4
        return c

    store = _store(str(tmp_path_factory.mktemp("clstore")))
    full, part = str(tmp_path_factory.mktemp("cl") / "full"), str(tmp_path_factory.mktemp("cl") / "part")
    assert train_and_evaluate(config(store), full, quiet=True)["step"] == 4
    assert train_and_evaluate(config(store), part, stop_after=2, quiet=True)["step"] == 2
    assert train_and_evaluate(config(store), part, quiet=True)["step"] == 4
    for x, y in zip(jax.tree.leaves(_params(full)), jax.tree.leaves(_params(part))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
