"""configs/gpd_sumo_real.py with `model.agent_map_context` (not in the paper): every agent token also reads the
3 x 3 map cells around it (`gpd_jax.model.transformer.GPD.local_map_context`). Same data, schedule, seed and
starting point (checkpoints/gpd_sumo; the new layers start at zero, so step 0 is that model), so it compares with
checkpoints/gpd_sumo_real run for run.

    python train.py --config configs/gpd_sumo_real_context.py --workdir runs/gpd_sumo_real_context
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_sumo_real  # noqa: E402


def get_config():
    c = gpd_sumo_real.get_config()
    c.model.agent_map_context = True
    c.model.map_extent_m = 64.0  # the map tokenizer's window: 256 px x 0.25 m
    return c
