"""The paper's no-pre-training ablation of the planning head (Table 2, "without pre-training"): the same head,
data, steps and schedule as configs/gpd_sumo_plan_head.py, the backbone randomly initialised and trained on the
planning loss only, at the head's learning rate (there is nothing pre-trained to protect).

    python train.py --config configs/gpd_sumo_plan_head_scratch.py --workdir runs/plan_head_scratch \
        --config.data.dir=/work/data/plan_train --config.data.val_dir=/work/data/plan_dev
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo_plan_head  # noqa: E402


def get_config():
    c = gpd_sumo_plan_head.get_config()
    c.train.init_from = ""
    c.train.backbone_lr_scale = 1.0
    c.train.gpd_loss_weight = 0.0
    return c
