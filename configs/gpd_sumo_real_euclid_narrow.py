"""Second stage of checkpoints/gpd_sumo_real_euclid: configs/gpd_sumo_real_euclid.py's run (the Euclidean agent
loss, 400 steps from checkpoints/gpd_sumo_real_curved) trained 400 more steps with the same recipe and the loss's
quadratic zone narrowed from 0.05 to 0.01 (m, m/s). Below that width the pseudo-Huber is quadratic and still
pulls a prediction towards the mean; after the first stage, stopped cars still crept a median 1.5 cm in the first
second (examples/stationary_drift.py), within the 5 cm zone.

    python train.py --config configs/gpd_sumo_real_euclid.py --workdir runs/euclid
    python train.py --config configs/gpd_sumo_real_euclid_narrow.py --workdir runs/s2_d001
    python -m gpd_jax.checkpoint export runs/s2_d001 checkpoints/gpd_sumo_real_euclid --tokenizer-ref ../map_tokenizer

Its control is the same second stage with the width kept at 0.05 (`--config.loss.agent_norm_delta=0.05`).
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo_real_euclid  # noqa: E402


def get_config():
    c = gpd_sumo_real_euclid.get_config()
    c.loss.agent_norm_delta = 0.01
    c.train.init_from = "runs/euclid/export"
    return c
