"""Euclidean-loss fine-tune of checkpoints/gpd_sumo_real_curved (issue 24): the same model, tokenizer, data
mixture and 8-pass rollout training, with the agents' position and velocity loss switched from the official
smooth-L1 (beta 1) to the pseudo-Huber of the error's length (`loss.agent_norm = "euclidean"`, training/step.py).

Why: on real-road test networks the stationary agents (two thirds of them) scored 2.0 / 1.6 / 1.4 x constant
velocity at 3 / 5 / 8 s. Below a metre smooth-L1 is quadratic, so for a stopped car whose next second is "stay"
mostly and "go" sometimes, the loss is least at the mean, a creep forward every frame, fed back as the next
frame's velocity; ADE averages error lengths, whose expectation is least at the median, staying put.

    python train.py --config configs/gpd_sumo_real_euclid.py --workdir runs/euclid

Its control is the same run with `--config.loss.agent_norm=smooth_l1`: the same start, steps, schedule and data.
(data/gen_curved_train, data/mix_real_train and data/mix_real_dev as in configs/gpd_sumo_real_curved.py.)
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo_real_curved  # noqa: E402


def get_config():
    c = gpd_sumo_real_curved.get_config()
    c.loss.agent_norm = "euclidean"
    c.train.init_from = "checkpoints/gpd_sumo_real_curved"  # 400 steps, 8 passes, its schedule, data and seed
    return c
