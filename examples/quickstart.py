"""Quickstart: load the shipped model, make (or load) a few scenes, roll out three tasks, print metrics, draw.

    python examples/quickstart.py                               # data/test of the README's set-up, else 4 new scenes
    python examples/quickstart.py --data data/test --scenes 8   # scenes of a store you built
"""

import argparse
import os
import sys

import jax

import gpd_jax

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _store_cli import example_scenes  # noqa: E402

p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
p.add_argument("--data", default=None, help="a data store (default: the README's data/test, else 4 simulated scenes)")
p.add_argument("--split", default="test")
p.add_argument("--scenes", type=int, default=4)
p.add_argument("--out", default="runs/quickstart", help="pictures go here")
args = p.parse_args()

model = gpd_jax.load_model()  # the default model (gpd_jax.list_models()) and its map tokenizer
scenes = example_scenes(args.data, args.split, args.scenes)
tasks = ["traffic_simulation", "scene_generation", "motion_planning"]

out = gpd_jax.rollout(model, scenes, tasks, jax.random.key(0))  # xy [scenes, tasks, frames, agents, 2]
print("rollout:", out.xy.shape, f"({model.spec.frame_period_s:g} s per frame)")

results = gpd_jax.evaluate(model, scenes, tasks=tasks)
cv = results["baselines"]["constant_velocity"]
for task in tasks:
    for h, m in results["tasks"][task].items():
        who = "agent" if "agent_ade" in m else "ego"
        print(f"{task:>20} {h}: {who} ADE {m[who + '_ade']:6.2f} m (constant velocity {cv[h][who + '_ade']:.2f} m)"
              f", map F1 {m.get('map_f1', float('nan')):.2f}")

first = jax.tree.map(lambda x: x[:1], (scenes, out))
paths = gpd_jax.render(model, *first, tasks, args.out)
print("pictures:", *paths[:2], "...")
