"""Real-traffic fine-tune of the shipped checkpoints/gpd_sumo (issues 23/24): the same model and map tokenizer,
trained on a mixture of generated networks with the real-traffic SUMO defaults (parked and stopping vehicles,
fixed-cycle lights and queues, heterogeneous drivers, left-hand networks, egos that stand) and real OSM road
networks (`gpd_jax.data.realnets`), on its own rollouts with its own map tokens fed back (stage 5's schedule,
configs/gpd_sumo_map_feedback.py). Validation reads the real development tiles (`data.val_dir`).

    python -m gpd_jax.data.realnets --cache data/realnets
    python -m gpd_jax.data build --source sumo --net data/realnets/train/{drt_nw,drt_se,drt_sw,fin_se_east,fin_se_west,helsinki_south}.net.xml.gz --net-layout real \\
        --split train --scenarios 600 --per-job 10 --seed 71 --out data/mix_real_train
    python -m gpd_jax.data build --source sumo --net data/realnets/dev/*.net.xml.gz --net-layout real \\
        --split val --scenarios 150 --per-job 10 --seed 73 --out data/mix_real_dev --against data/mix_real_train
    python -m gpd_jax.data build --source sumo --split train --scenarios 3000 --per-job 25 --seed 61 \\
        --out data/mix_gen_train
    for d in mix_real_train mix_real_dev mix_gen_train; do
        python -m gpd_jax.map_tokenizer encode --checkpoint checkpoints/map_tokenizer --data data/$d --frame-stride 10
    done
    python train.py --config configs/gpd_sumo_real.py --workdir runs/gpd_sumo_real
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo_map_feedback  # noqa: E402


def get_config():
    c = gpd_sumo_map_feedback.get_config()
    c.data.dir = "data/mix_gen_train:0.6,data/mix_real_train:0.4"
    c.data.val_dir = "data/mix_real_dev"
    t = c.train
    t.init_from = "checkpoints/gpd_sumo"
    t.steps = 1_200
    t.eval_every = 300
    t.eval_rollout_scenarios = 64
    t.keep_checkpoints = 13  # every 100 steps: a validation step can be exported and compared on dev
    return c
