"""checkpoints/gpd_sumo_real_lane_residual_mix fine-tuned at GPU scale (issue 24: "the paper-config model trained at
GPU scale if a GPU is available"; the lent GPU is one H200 for 15 minutes of one session, so the scale is in the
batch and the steps, not the model size). Everything else is its second stage's recipe
(configs/gpd_sumo_real_lane_residual_mix_legacy.py: mixture 0.2 curved generated / 0.4 legacy generated / 0.4 real
tiles, Euclidean agent loss of width 0.01, 8 rollout passes with map feedback, a quarter of the scenes without
lanes in their future frames, lr 3e-4 cosine to 1e-5), with 4x its batch (32 scenes) and the steps that fit the
lease (`--config.train.steps`, recorded with the run). No validation rollouts during the run: the checkpoints
are exported every `checkpoint_every` steps and chosen on the dev stores afterwards, on the CPU.

Dev rule, fixed before the run: the candidates are the run's exported checkpoints (every quarter of its steps);
each is scored by the mean of the nine traffic-simulation agent ADE / constant-velocity ratios at 3 / 5 / 8 s on
data/mix_real_dev, data/gen_dev_curved and data/gen_dev_legacy (150 scenes each, `rollout.py --split val --tasks
traffic_simulation`); the lowest mean is chosen, and it ships only if it is below the mean of
checkpoints/gpd_sumo_real_lane_residual_mix scored the same way in the same session. The test stores are read
after that choice, once.

Outcome (2026-11-26, one H200): 4,496 of 5,400 steps in the lease; no checkpoint beat the model it started from
on dev, and the real training tiles were memorized (checkpoints/gpd_sumo_real_lane_residual_mix/README.md, "At GPU
scale"). A next run should choose its step on dev while it trains:

    --config.data.val_dir=data/mix_real_dev,data/gen_dev_curved,data/gen_dev_legacy --config.train.eval_every=250 \
    --config.train.eval_rollout_scenarios=150 --config.train.best_metric=rollout_agent_ade_vs_cv_mean \
    --config.train.eval_at_start=True

(the rule's nine ratios, in the corrected metric variant, with the best step exported to WORKDIR/best).

    python train.py --config configs/gpd_sumo_real_lane_residual_mix_gpu.py --workdir runs/mix_gpu \\
        --config.train.steps=N --config.train.checkpoint_every=N/4
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo_real_lane_residual_mix_legacy  # noqa: E402


def get_config():
    c = gpd_sumo_real_lane_residual_mix_legacy.get_config()
    c.train.init_from = "checkpoints/gpd_sumo_real_lane_residual_mix"
    t = c.train
    t.batch_size = 32
    t.steps = 3000
    t.warmup_steps = 100
    t.eval_every = 0            # chosen on dev afterwards, from the exported checkpoints
    t.checkpoint_every = 750
    t.keep_checkpoints = 8
    t.loader_threads = 12
    t.log_every = 50
    return c
