"""Curved-road fine-tune of checkpoints/gpd_sumo_real (issues 23, 24, 26): the same model and map tokenizer, 400
more steps on whole rollouts (8 passes, map tokens fed back) over a mixture whose generated half has curved
streets (`--curved-share 0.5`: bulges and S-bends of up to 0.22 x a street's length, `sumo.NetSpec.bend`).

Why: the real-traffic model barely reads the map (another scene's map costs it 0.00-0.02 x constant velocity)
and drives straight through a hand-drawn bend. On generated networks of straight streets a car's next second is
almost always its last second continued, so nothing in training pays for reading the map; on curved streets it
does. This is the previous session's 8-pass fine-tune (the same start, steps, passes, schedule and real-tile
store) with the generated store swapped, so the two compare directly.

    python -m gpd_jax.data build --source sumo --split train --scenarios 1500 --per-job 25 --seed 61 \\
        --curved-share 0.5 --out data/gen_curved_train
    python -m gpd_jax.map_tokenizer encode --checkpoint checkpoints/map_tokenizer --data data/gen_curved_train \\
        --frame-stride 10
    python train.py --config configs/gpd_sumo_real_curved.py --workdir runs/gpd_sumo_real_curved

(data/mix_real_train and data/mix_real_dev as in configs/gpd_sumo_real.py.)
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo_real  # noqa: E402


def get_config():
    c = gpd_sumo_real.get_config()
    c.data.dir = "data/gen_curved_train:0.6,data/mix_real_train:0.4"
    t = c.train
    t.init_from = "checkpoints/gpd_sumo_real"
    t.rollout_passes = 8
    t.steps = 400
    t.eval_every = 200
    t.warmup_steps = 50
    t.keep_checkpoints = 5
    return c
