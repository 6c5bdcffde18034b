"""Does a GPD use the map? Traffic simulation on the same scenes, agents and frames with three maps:

* `logged`: the scenes' own map tokens (plain traffic simulation);
* `other_scene`: the map tokens (and lane polylines) of another scene of the split (each scene takes the previous
  one's), so the road no longer matches the agents;
* `constant_code`: every map token the split's most frequent code (no road at all).

If agent ADE / constant velocity barely changes between them, the model's agents do not read the map.

    python examples/map_use.py --checkpoint gpd_traffic --data data/mix_real_dev --split val \
        --scenarios 150 --json OUT.json

(The "does the model use the map?" figures of docs/results.md come from this script.)
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys

import numpy as np

import gpd_jax
from gpd_jax.fsutil import atomic_write_json

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _store_cli import load_model_and_scenes, store_parser  # noqa: E402


def map_variants(scenes: gpd_jax.Scene) -> dict[str, gpd_jax.Scene]:
    """The three maps of the module docstring for stored-rate scenes Scene [n, ...] (n >= 2)."""
    tokens, known = np.asarray(scenes.map_tokens), np.asarray(scenes.map_valid)
    if not known.any():
        raise SystemExit("these scenes have no stored map tokens: run `python -m gpd_jax.map_tokenizer encode` "
                         "on the store first (constant_code needs real codes)")
    roll = lambda x: None if x is None else np.roll(np.asarray(x), 1, axis=0)  # noqa: E731
    common = np.bincount(tokens[known].ravel()).argmax()
    return {
        "logged": scenes,
        "other_scene": dataclasses.replace(scenes, map_tokens=roll(tokens), map_valid=roll(known),
                                           polylines=roll(scenes.polylines),
                                           polyline_valid=roll(scenes.polyline_valid)),
        "constant_code": dataclasses.replace(scenes, map_tokens=np.full_like(tokens, common),
                                             map_valid=np.ones_like(known)),
    }


def main(argv=None) -> int:
    args = store_parser(__doc__.split("\n\n")[0], "a data store with map tokens").parse_args(argv)
    model, scenes, n = load_model_and_scenes(args)
    out = {}
    for name, s in map_variants(scenes).items():
        r = gpd_jax.evaluate(model, s, "traffic_simulation")
        split = r["motion_split"]["ratios"]["traffic_simulation_over_constant_velocity"]
        out[name] = {"agent_ade_over_cv": r["ratios"]["traffic_simulation_agent_ade_over_constant_velocity"],
                     "moving": split["agent_moving"], "stationary": split["agent_stationary"]}
        print(name, json.dumps({k: {h: round(v, 3) for h, v in d.items()} for k, d in out[name].items()}))
    if args.json:
        atomic_write_json(args.json, {"checkpoint": args.checkpoint, "data": args.data, "split": args.split,
                                      "scenarios": n, **out})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
