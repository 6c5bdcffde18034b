"""configs/gpd_sumo_real_lanes.py with walks that leave a lane's end clipped at the sample's edge instead of
stalling on it (`model.lane_context_max_gap_m`: a 5 m step landing more than 2.5 m from every lane goes on straight),
and 800 steps instead of 400. The two lane runs of checkpoints/gpd_sumo_real_euclid/README.md ("Agents that read
the lanes") trained on stalling walks; this is their follow-up (not yet measured).

    python train.py --config configs/gpd_sumo_real_lanes_gap.py --workdir runs/lanes_gap
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo_real_lanes  # noqa: E402


def get_config():
    c = gpd_sumo_real_lanes.get_config()
    c.model.lane_context_max_gap_m = 2.5
    c.train.steps = 800
    return c
