"""checkpoints/gpd_sumo_real_euclid fine-tuned with `model.agent_lane_residual` (not in the paper): the position,
heading and velocity heads regress the residual over an agent that keeps its lane (constant velocity's step walked
along the lane it is on, its offset from the lane kept: `gpd_jax.geometry.lane_follow`) instead of over its
straight line, in the frames whose map is given. The option adds no parameters: step 0 is the shipped model's
heads over the new base, which alone took the real-tile dev ratios from 0.839 / 0.818 / 0.809 to 0.794 / 0.759 /
0.751 x constant velocity (checkpoints/gpd_sumo_real_euclid/README.md, "Residuals over the lane").

Same data, loss and schedule as configs/gpd_sumo_real_euclid_narrow.py, from the shipped model; a quarter of each
batch's scenes have no lanes in their future frames (`train.lane_context_drop`), as in the tasks that generate the
map, where the base stays constant velocity's.

    python train.py --config configs/gpd_sumo_real_lane_residual.py --workdir runs/lane_residual
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo_real_euclid_narrow  # noqa: E402


def get_config():
    c = gpd_sumo_real_euclid_narrow.get_config()
    c.model.agent_lane_residual = True
    c.model.lane_context_stride = 4  # every 4th stored 1 m lane point: 4 m segments
    c.train.lane_context_drop = 0.25
    c.train.init_from = "checkpoints/gpd_sumo_real_euclid"
    return c
