"""Training, both stages, over shared utilities.

* `map_tokenizer`: stage 1, the map VQ-VAE and lane decoder (`python train.py --config configs/map_tokenizer_*.py`).
* `loop`: stage 2, the GPD on a store with map tokens (`python train.py --config configs/gpd_*.py`); `step` holds
  its losses, optimizer and jitted step, `validation` its validation loss and rollouts.
* `common`: checkpoint manager and train-state restore, the metrics log, a clean stop on SIGTERM.
* `curves`: learning curves of a workdir (`python -m gpd_jax.training.curves WORKDIR OUT.png`).
"""
