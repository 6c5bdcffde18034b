"""A short teacher-forced training run on a small synthetic batch: the loss falls by at least half."""


import chex
import jax
import numpy as np
import pytest
from flax import nnx

from gpd_jax.config import load_config
from gpd_jax.model import GPD
from gpd_jax.synthetic import synthetic_scenes
from gpd_jax.training.step import make_trainer

from conftest import ROOT


def test_loss_falls_by_half_and_step_compiles_once():
    cfg = load_config(f"{ROOT}/configs/gpd_tiny.py:test",
                      ["--config.train.learning_rate=3e-3", "--config.model.predict_delta=true"])
    m = cfg.model
    trainer, state = make_trainer(GPD(m, nnx.Rngs(0)), cfg)
    weights = cfg.loss.to_dict()
    cfg.loss.map = 0.0  # changed after the trainer was made: its steps (traced later) keep the weights they were made with
    step = jax.jit(chex.assert_max_traces(lambda st, sc: trainer.step_fn(st, sc), n=1), donate_argnums=(0,))
    scenes = synthetic_scenes(0, 8, m.num_frames, m.num_history, m.num_agents, m.num_map_tokens, m.codebook_size)
    losses = []
    for _ in range(120):
        state, metrics = step(state, scenes)
        losses.append(float(metrics["loss"]))
    total = sum(weights[k] * float(metrics[k]) for k in ("position", "heading", "valid", "map"))
    np.testing.assert_allclose(losses[-1], total, rtol=1e-5)
    assert np.isfinite(losses).all()
    assert losses[-1] < 0.5 * losses[0], (losses[0], losses[-1])
    assert int(state.step) == 120
    # the heads learned something real: map tokens are predicted better than chance (1/32)
    ev = trainer.eval_step(state.params, scenes)
    assert float(ev["map_accuracy"]) > 0.3


def test_codebook_embedding_is_frozen_and_used():
    cfg = load_config(f"{ROOT}/configs/gpd_tiny.py:test")
    m = cfg.model
    from gpd_jax.checkpoint import build_model

    codebook = np.random.default_rng(0).normal(size=(m.codebook_size, 12)).astype(np.float32)
    model = build_model(cfg, codebook=codebook)
    trainer, state = make_trainer(model, cfg)
    # the codebook is not a trainable parameter
    leaves = jax.tree_util.tree_leaves_with_path(state.params)
    assert not any("codebook" in jax.tree_util.keystr(p) for p, _ in leaves)
    scenes = synthetic_scenes(1, 2, m.num_frames, m.num_history, m.num_agents, m.num_map_tokens, m.codebook_size)
    tok = model.embed(scenes.xy[0], scenes.heading[0], scenes.valid[0], scenes.map_tokens[0],
                      np.arange(m.num_frames))
    other = model.embed(scenes.xy[0], scenes.heading[0], scenes.valid[0], (scenes.map_tokens[0] + 1) % 32,
                        np.arange(m.num_frames))
    assert tok.shape == (m.num_frames, m.num_map_tokens + m.num_agents, m.d_model)
    assert not np.allclose(tok[:, : m.num_map_tokens], other[:, : m.num_map_tokens])
    np.testing.assert_allclose(tok[:, m.num_map_tokens:], other[:, m.num_map_tokens:])


def test_velocity_inputs_add_a_velocity_loss_that_trains_its_head():
    cfg = load_config(f"{ROOT}/configs/gpd_tiny.py:test", ["--config.model.predict_delta=true",
                                                      "--config.model.velocity_residual=true",
                                                      "--config.model.velocity_inputs=true"])
    m = cfg.model
    model = GPD(m, nnx.Rngs(0), frame_period_s=0.5)
    trainer, state = make_trainer(model, cfg, donate=False)
    scenes = synthetic_scenes(2, 4, m.num_frames, m.num_history, m.num_agents, m.num_map_tokens, m.codebook_size)
    ev = trainer.eval_step(state.params, scenes.with_velocity(0.5))
    assert float(ev["velocity"]) > 0
    np.testing.assert_allclose(float(ev["loss"]), sum(float(cfg.loss[k]) * float(ev[k]) for k in
                                                      ("position", "heading", "valid", "map", "velocity")), rtol=1e-5)
    new = state
    for _ in range(2):  # the warm-up's first learning rate is 0
        new, _ = trainer.train_step(new, scenes.with_velocity(0.5))
    moved = jax.tree.map(lambda a, b: float(np.abs(np.asarray(a) - np.asarray(b)).max()),
                         new.params["velocity_head"], state.params["velocity_head"])
    assert max(jax.tree.leaves(moved)) > 0


def _velocity_model():
    cfg = load_config(f"{ROOT}/configs/gpd_tiny.py:test", ["--config.model.predict_delta=true",
                                                      "--config.model.velocity_residual=true",
                                                      "--config.model.velocity_inputs=true"])
    m = cfg.model
    scenes = synthetic_scenes(3, 2, m.num_frames, m.num_history, m.num_agents, m.num_map_tokens, m.codebook_size)
    return cfg, GPD(m, nnx.Rngs(0), frame_period_s=0.1), scenes.with_velocity(0.1)


def test_free_running_inputs_are_the_models_own_rollout():
    from gpd_jax.training.step import free_running_inputs, teacher_forced

    cfg, model, scenes = _velocity_model()
    h, t = cfg.model.num_history, cfg.model.num_frames
    scene = jax.tree.map(lambda x: x[0], scenes)
    logged_maps = np.asarray(scene.map_tokens[:-1])
    assert np.asarray(scene.map_valid).all()
    teacher = nnx.jit(teacher_forced)  # one compile for every frame of the reference, not op by op
    for feed_map in (False, True):
        # Reference: a frame-by-frame rollout (validity, and the map unless fed back, from the log), one frame
        # replaced per pass.
        xy, heading, vel = (np.array(a[:-1]) for a in (scene.xy, scene.heading, scene.velocity))
        maps = logged_maps.copy()
        valid = np.asarray(scene.valid[:-1])
        tracked = valid & np.concatenate([np.zeros_like(valid[:1]), valid[:-1]], 0)
        for f in range(h, t - 1):
            pred = teacher(model, xy, heading, valid, maps, vel)
            own = tracked[f]
            xy[f][own], heading[f][own], vel[f][own] = (np.asarray(p)[f - 1][own]
                                                        for p in (pred.xy, pred.heading, pred.velocity))
            if feed_map:
                maps[f] = np.argmax(np.asarray(pred.map_logits)[f - 1], -1)
        assert tracked[h:].sum() > 0 and np.abs(xy - np.asarray(scene.xy[:-1])).max() > 0.1
        assert (maps[h:] != logged_maps[h:]).mean() > (0.5 if feed_map else -1)  # an untrained model's own map
        for passes in (2, t - 1 - h):
            fx, fh, fv, fm = (np.asarray(a) for a in free_running_inputs(model, scene, h, passes, feed_map))
            exact = slice(0, h + passes)  # the first `passes` future frames are exact after `passes` passes
            np.testing.assert_allclose(fx[exact], xy[exact], atol=1e-4)
            np.testing.assert_allclose(fh[exact], heading[exact], atol=1e-5)
            np.testing.assert_allclose(fv[exact], vel[exact], atol=1e-4)
            np.testing.assert_array_equal(fm[exact], maps[exact])
        # history frames and agents not tracked into a frame keep the log's values
        np.testing.assert_array_equal(fx[:h], np.asarray(scene.xy[:h]))
        np.testing.assert_array_equal(fm[:h], logged_maps[:h])
        np.testing.assert_array_equal(fx[~tracked], np.asarray(scene.xy[:-1])[~tracked])


def test_rollout_passes_train_on_own_predictions_against_the_log():
    cfg, model, scenes = _velocity_model()
    tf, _ = make_trainer(model, cfg, donate=False)
    cfg.train.rollout_passes = 3
    fr, state = make_trainer(model, cfg, donate=False)
    a, b = tf.eval_step(state.params, scenes), fr.eval_step(state.params, scenes)
    # same targets; the future frames' inputs are an untrained model's own predictions, far from the log
    assert float(b["position"]) > 1.3 * float(a["position"]), (a["position"], b["position"])
    new, parts = fr.train_step(state, scenes)
    assert np.isfinite(float(parts["loss"])) and np.isfinite(float(parts["grad_norm"]))
    np.testing.assert_allclose(float(parts["loss"]), float(b["loss"]), rtol=1e-5)
    # map feedback: own future map tokens for the first round(f * B) scenes only (B = 2 here: one fed)
    cfg.train.map_feedback = 0.5
    half, _ = make_trainer(model, cfg, donate=False)
    cfg.train.map_feedback = 1.0
    full, _ = make_trainer(model, cfg, donate=False)
    assert scenes.xy.shape[0] == 2
    # scene i's own accuracy: a batch of scene i twice (the batch's shape: no compile for a batch of one)
    acc = lambda tr, i: float(tr.eval_step(state.params, jax.tree.map(lambda x: x[np.array([i, i])], scenes))[
        "map_accuracy"])
    assert acc(full, 0) != acc(fr, 0)  # an untrained model's own map tokens as inputs change its predictions
    c = half.eval_step(state.params, scenes)
    np.testing.assert_allclose(float(c["map_accuracy"]) * 2, acc(full, 0) + acc(fr, 1), rtol=1e-5)
    cfg.train.map_feedback = 1.5
    with pytest.raises(ValueError, match="map_feedback must be a fraction"):
        make_trainer(model, cfg, donate=False)
    cfg.train.map_feedback, cfg.train.rollout_passes = 0.5, 0
    with pytest.raises(ValueError, match="set train.rollout_passes > 0"):
        make_trainer(model, cfg, donate=False)


def test_euclidean_agent_loss_takes_the_median_where_smooth_l1_creeps():
    """A car stopped at a light stays (80 %) or moves 2 m on (20 %): the expected smooth-L1 (beta 1) is least at
    a 0.25 m creep, the expected Euclidean pseudo-Huber at the median, staying put. Both norms as defined."""
    from gpd_jax.training.step import vector_loss

    e = np.array([[3.0, 4.0], [0.3, -0.4], [0.0, 0.0]], np.float32)
    np.testing.assert_allclose(vector_loss(e, "smooth_l1"), [2.5 + 3.5, 0.045 + 0.08, 0.0], rtol=1e-6)
    np.testing.assert_allclose(vector_loss(e, "euclidean", 0.05),
                               np.sqrt(np.array([25.0, 0.25, 0.0]) + 0.0025) - 0.05, rtol=1e-6, atol=1e-7)
    futures = np.array([[0.0, 0.0]] * 8 + [[2.0, 0.0]] * 2, np.float32)
    grid = np.linspace(0.0, 1.0, 201, dtype=np.float32)

    def best(norm):
        cost = [float(np.mean(vector_loss(np.array([[x, 0.0]], np.float32) - futures, norm))) for x in grid]
        return grid[int(np.argmin(cost))]

    assert abs(best("smooth_l1") - 0.25) <= 0.005
    assert best("euclidean") <= 0.015


def test_euclidean_agent_loss_trains_and_an_unknown_norm_is_refused():
    cfg, model, scenes = _velocity_model()
    with pytest.raises(ValueError, match="loss.agent_norm"):
        make_trainer(model, load_config(f"{ROOT}/configs/gpd_tiny.py:test", ["--config.loss.agent_norm=l2"]))
    cfg.loss.agent_norm = "euclidean"
    trainer, state = make_trainer(model, cfg, donate=False)
    ev = trainer.eval_step(state.params, scenes)
    assert np.isfinite(float(ev["loss"])) and float(ev["position"]) > 0 and float(ev["velocity"]) > 0
    cfg.loss.agent_norm = "smooth_l1"
    smooth = make_trainer(model, cfg, donate=False)[0].eval_step(state.params, scenes)
    assert abs(float(ev["position"]) - float(smooth["position"])) > 1e-3 * float(smooth["position"])
    new = state
    for _ in range(3):
        new, metrics = trainer.train_step(new, scenes)
    assert np.isfinite(float(metrics["grad_norm"])) and float(metrics["grad_norm"]) > 0


