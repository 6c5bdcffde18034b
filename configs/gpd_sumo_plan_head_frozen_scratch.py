"""The no-pre-training ablation of configs/gpd_sumo_plan_head_frozen.py at exactly its budget: the same head,
data, steps, batches and schedule on a frozen, randomly initialised backbone (its cached outputs are those of an
untrained GPD), so the gap between the two is what pre-training puts into the ego token and its context.
(configs/gpd_sumo_plan_head_scratch.py is the paper's form of the ablation, the backbone trained from scratch on
the planning loss, which costs a backbone pass per step.)

    python train.py --config configs/gpd_sumo_plan_head_frozen_scratch.py --workdir runs/plan_head_frozen_scratch \
        --config.data.dir=/work/data/plan_train2 --config.data.val_dir=/work/data/plan_dev
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo_plan_head_frozen  # noqa: E402


def get_config():
    c = gpd_sumo_plan_head_frozen.get_config()
    c.train.init_from = ""
    return c
