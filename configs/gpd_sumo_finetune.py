"""Second stage of the shipped checkpoints/gpd_sumo: fine-tune configs/gpd_sumo.py's model on its own rollouts.

Starts from the teacher-forced model (`train.init_from`, the first stage's export) and trains 1,000 more steps
whose future-frame agent inputs are the model's own predictions (`train.rollout_passes` = 8, the number of future
frames: the inputs are then exactly the free-running rollout, with validity and map kept from the log) while the
targets stay the log's. A step costs ~2.5x a teacher-forced one (8 forward passes without gradient + 1 with).

    python train.py --config configs/gpd_sumo.py --workdir runs/gpd_sumo
    python train.py --config configs/gpd_sumo_finetune.py --workdir runs/gpd_sumo_ft

Measured (held-out networks, agent ADE / 10 Hz constant velocity at 3 / 5 / 8 s, 600 test scenes of sumo6k):
0.715 / 0.746 / 0.813 before, 0.692 / 0.680 / 0.685 after; 1,000 more teacher-forced steps with the same
schedule instead (`--config.train.rollout_passes=0`): 0.685 / 0.714 / 0.781. (On an earlier tokenizer's map
tokens; the shipped model's stage 4 did the same, 500 steps, on the shipped tokenizer's: 0.60 / 0.60 / 0.62.
Its stage 5, configs/gpd_sumo_map_feedback.py, then also feeds back the model's own map tokens.)
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo  # noqa: E402


def get_config():
    c = gpd_sumo.get_config()
    t = c.train
    t.init_from = "runs/gpd_sumo/export"
    t.rollout_passes = 8
    t.steps = 1_000
    t.learning_rate = 3e-4
    t.warmup_steps = 50
    t.eval_every = 250
    return c
