"""The planning head on the *frozen* shipped GPD: the backbone runs once per training scene (its teacher-forced
output tokens are cached in memory, `train.cache_features`) and only the head's ~0.3 M parameters train, so
many more steps fit a CPU budget than in configs/gpd_sumo_plan_head.py (which fine-tunes the backbone too), and
the model's agent and map predictions stay exactly the shipped model's (the simulator's GPD agents are
unchanged). Same head, loss and targets.

    python train.py --config configs/gpd_sumo_plan_head_frozen.py --workdir runs/plan_head_frozen \
        --config.data.dir=/work/data/plan_train2 --config.data.val_dir=/work/data/plan_dev

checkpoints/gpd_sumo_plan_head/README.md has what was run and measured.
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo_plan_head  # noqa: E402


def get_config():
    c = gpd_sumo_plan_head.get_config()
    t = c.train
    t.backbone_lr_scale = 0.0
    t.cache_features = True
    t.batch_size = 64            # scenes per step, each with its plans from every source frame
    t.steps = 6000
    t.learning_rate = 1e-3
    t.warmup_steps = 200
    t.min_learning_rate = 1e-5
    t.log_every = 100
    t.eval_every = 500           # every scene of the validation split (cached too)
    t.checkpoint_every = 500
    return c
