"""checkpoints/gpd_sumo_real_euclid fine-tuned with `model.agent_lane_context` (not in the paper): every agent
token also reads the lane it is on, walked 5 x 5 m ahead in the vector lane centrelines of the scene
(`gpd_jax.model.transformer.GPD.lane_context_features`), in frames whose map is given. On real roads the map
tokens decode poorly and the shipped model's moving agents keep constant velocity's path (cross-track error
0.96 x constant velocity at 8 s on the real-road test networks); the lanes give them the road's curve.

Same data, loss and schedule as configs/gpd_sumo_real_euclid_narrow.py, from the shipped model (the new layers
start at zero, so step 0 is that model); a quarter of each batch's scenes read no lanes in their future frames
(`train.lane_context_drop`), as in the tasks that generate the map.

    python train.py --config configs/gpd_sumo_real_lanes.py --workdir runs/lanes
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo_real_euclid_narrow  # noqa: E402


def get_config():
    c = gpd_sumo_real_euclid_narrow.get_config()
    c.model.agent_lane_context = True
    c.model.lane_context_steps = 5
    c.model.lane_context_step_m = 5.0
    c.model.lane_context_stride = 4
    c.train.lane_context_drop = 0.25
    c.train.init_from = "checkpoints/gpd_sumo_real_euclid"
    return c
