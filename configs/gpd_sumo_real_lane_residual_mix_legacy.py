"""Second stage of checkpoints/gpd_sumo_real_lane_residual_mix: the first stage's export
(configs/gpd_sumo_real_lane_residual_mix.py) trained 400 more steps with the same recipe and a larger share of
legacy-traffic generated scenes (0.4, the curved real-traffic networks 0.2, the real tiles 0.4). After the first
stage, moving agents on legacy traffic still lost to checkpoints/gpd_sumo on their pace (along-track error 0.653
against 0.595 x constant velocity's at 3 s on the legacy dev store) while they already beat it on their path.

    python train.py --config configs/gpd_sumo_real_lane_residual_mix.py --workdir runs/lane_residual_mix
    python train.py --config configs/gpd_sumo_real_lane_residual_mix_legacy.py --workdir runs/lane_residual_mix_legacy
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo_real_lane_residual_mix  # noqa: E402


def get_config():
    c = gpd_sumo_real_lane_residual_mix.get_config()
    c.data.dir = "data/gen_curved_train:0.2,data/legacy_train:0.4,data/mix_real_train:0.4"
    c.train.init_from = "runs/lane_residual_mix/export"
    return c
