"""The paper's fine-tuned planner (Table 2) on the shipped GPD: one decoder layer on the ego token
(`gpd_jax.model.PlanningHead`) trained on the logged ego's next 8 s, the backbone starting from
checkpoints/gpd_sumo and fine-tuned at a tenth of the head's learning rate. The no-pre-training ablation is
configs/gpd_sumo_plan_head_scratch.py (same head, data and budget; the backbone from a random initialisation).

    python -m gpd_jax.data build --source sumo --traffic legacy --out /work/data/plan_train --scenarios 400 --seed 31 --per-job 25 --split train
    python -m gpd_jax.data build --source sumo --traffic legacy --out /work/data/plan_dev --scenarios 150 --seed 37 --per-job 25 --split val --against /work/data/plan_train
    python -m gpd_jax.map_tokenizer encode --checkpoint checkpoints/map_tokenizer --data /work/data/plan_train --frame-stride 10
    python -m gpd_jax.map_tokenizer encode --checkpoint checkpoints/map_tokenizer --data /work/data/plan_dev --frame-stride 10
    python train.py --config configs/gpd_sumo_plan_head.py --workdir runs/plan_head \
        --config.data.dir=/work/data/plan_train --config.data.val_dir=/work/data/plan_dev

Options: `train.backbone_lr_scale` = 0 freezes the backbone (the head alone trains; the model's agent
predictions stay exactly the shipped model's); `train.gpd_loss_weight` > 0 adds the GPD's own teacher-forced
loss (a second backbone pass per step) so that a moving backbone keeps predicting agents and maps.
checkpoints/gpd_sumo_plan_head/README.md has what was run and measured.
"""

import os
import sys

import ml_collections

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo  # noqa: E402


def get_config():
    c = gpd_sumo.get_config()
    c.data.dir = "data/plan_train"
    ph = c.plan_head = ml_collections.ConfigDict()
    ph.num_future = 8              # poses planned: 8 model frames = 8 s at 1 Hz
    ph.num_heads = 4
    ph.ffn_dim = 512
    ph.position_scale = 10.0       # metres per unit of the displacement output
    ph.first_frame = -1            # plans trained from this frame on (-1: the current frame) to T - 2
    ph.position_weight = 1.0
    ph.heading_weight = 5.73 / 5.0  # the GPD's heading : position loss ratio
    t = c.train
    t.init_from = "checkpoints/gpd_sumo"
    t.backbone_lr_scale = 0.1
    t.gpd_loss_weight = 0.0
    t.cache_features = False       # True (frozen backbone only): run the backbone once per scene, train the head alone
    t.batch_size = 8
    t.steps = 300
    t.learning_rate = 1e-3
    t.warmup_steps = 50
    t.min_learning_rate = 1e-5
    t.log_every = 25
    t.eval_every = 150
    t.eval_batches = 4
    t.checkpoint_every = 100
    t.loader_threads = 2
    return c
