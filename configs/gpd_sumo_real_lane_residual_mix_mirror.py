"""checkpoints/gpd_sumo_real_lane_residual_mix fine-tuned 400 more steps with its stage 2 recipe, half of the real
tiles' share given to their mirror images (`python -m gpd_jax.data mirror`: the same six networks reflected, with
left-hand traffic). At GPU scale the real training tiles were memorized (their own ratio 0.25 x constant velocity
against 0.87 on the dev tiles); mirroring doubles the road geometry the six networks give.

    python -m gpd_jax.data mirror data/mix_real_train --out data/mix_real_train_mirror
    python -m gpd_jax.map_tokenizer encode --checkpoint checkpoints/map_tokenizer --data data/mix_real_train_mirror \\
        --frame-stride 10
    python train.py --config configs/gpd_sumo_real_lane_residual_mix_mirror.py --workdir runs/mix_mirror

It validates on the three dev stores every 100 steps (150 scenes each, the corrected metric variant) and exports
the best of those validations to WORKDIR/best (`train.best_metric`).

Dev rule, fixed before the run: the candidates are the run's final export and WORKDIR/best; each is scored by
`rollout.py --split val --tasks traffic_simulation` on data/mix_real_dev, data/gen_dev_curved and
data/gen_dev_legacy, and the mean of the nine agent ADE / constant-velocity ratios at 3 / 5 / 8 s decides; the
lower ships only if it is below checkpoints/gpd_sumo_real_lane_residual_mix's (0.6866, re-scored this session).
The test stores are read after that choice, once.

Outcome (2026-11-26, CPU): step 400 was the run's best validation, 0.6887 by the rule against 0.6866: level, not
shipped (checkpoints/gpd_sumo_real_lane_residual_mix/README.md, "Mirrored real tiles").
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo_real_lane_residual_mix_legacy  # noqa: E402


def get_config():
    c = gpd_sumo_real_lane_residual_mix_legacy.get_config()
    c.data.dir = ("data/gen_curved_train:0.2,data/legacy_train:0.4,data/mix_real_train:0.2,"
                  "data/mix_real_train_mirror:0.2")
    c.data.val_dir = "data/mix_real_dev,data/gen_dev_curved,data/gen_dev_legacy"
    c.train.init_from = "checkpoints/gpd_sumo_real_lane_residual_mix"
    t = c.train
    t.eval_every = 100
    t.eval_rollout_scenarios = 150
    t.best_metric = "rollout_agent_ade_vs_cv_mean"
    return c
