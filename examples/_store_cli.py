"""What the examples share: a GPD and the first scenes of a store's split (examples/map_use.py,
examples/stationary_drift.py), and scenes to play with when no store is named (examples/quickstart.py,
examples/functional.py): the README's main-job store if it is there, else four scenes simulated once into
data/examples (the same settings for every example, so they never clash)."""

from __future__ import annotations

import argparse
import os

import jax

import gpd_jax
from gpd_jax.data.loader import SplitSource

MAIN_JOB_STORE = "data/test"  # what the README's set-up builds
EXAMPLE_STORE = "data/examples"


def example_scenes(data: str | None, split: str, count: int) -> gpd_jax.Scene:
    """The first `count` scenes of `data`'s `split`; without `data`, of the main job's store, or of four SUMO
    scenes simulated into data/examples (about 20 s, once)."""
    if data is None and os.path.isdir(os.path.join(MAIN_JOB_STORE, "test")):
        data, split = MAIN_JOB_STORE, "test"
    if data is None:
        return jax.tree.map(lambda x: x[:count], gpd_jax.build_scenes(EXAMPLE_STORE, num_scenarios=4, seed=7))
    return gpd_jax.load_scenes(data, split, indices=range(count))


def store_parser(description: str, data_help: str = "a data store") -> argparse.ArgumentParser:
    """--checkpoint, --data, --split, --scenarios, --json."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--checkpoint", default=None,
                    help="a shipped model's name or an exported GPD (default: the default model)")
    ap.add_argument("--data", required=True, help=data_help)
    ap.add_argument("--split", default="val")
    ap.add_argument("--scenarios", type=int, default=150)
    ap.add_argument("--json", default=None, help="write the figures here")
    return ap


def load_model_and_scenes(args: argparse.Namespace):
    """(model, the first min(--scenarios, split size) stored scenes of --data's --split, how many that is)."""
    model = gpd_jax.load_model(args.checkpoint)
    n = min(args.scenarios, len(SplitSource(args.data, args.split)))
    return model, gpd_jax.load_scenes(args.data, args.split, indices=range(n)), n
