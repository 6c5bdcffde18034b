"""A short teacher-forced training run on a small synthetic batch: the loss falls by at least half."""

import chex
import jax
import numpy as np
from flax import nnx

from gpd_jax.config import load_config
from gpd_jax.model import GPD
from gpd_jax.synthetic import synthetic_scenes
from gpd_jax.train_lib import make_trainer

from conftest import ROOT


def test_loss_falls_by_half_and_step_compiles_once():
    cfg = load_config(f"{ROOT}/configs/gpd_tiny.py",
                      ["--config.train.learning_rate=3e-3", "--config.model.predict_delta=true"])
    m = cfg.model
    trainer, state = make_trainer(GPD(m, nnx.Rngs(0)), cfg)
    step = jax.jit(chex.assert_max_traces(trainer.train_step.__wrapped__, n=1), donate_argnums=(0,))
    scenes = synthetic_scenes(0, 8, m.num_frames, m.num_history, m.num_agents, m.num_map_tokens, m.codebook_size)
    losses = []
    for _ in range(120):
        state, metrics = step(state, scenes)
        losses.append(float(metrics["loss"]))
    assert np.isfinite(losses).all()
    assert losses[-1] < 0.5 * losses[0], (losses[0], losses[-1])
    assert int(state.step) == 120
    # the heads learned something real: map tokens are predicted better than chance (1/32)
    ev = trainer.eval_step(state.params, scenes)
    assert float(ev["map_accuracy"]) > 0.3
