"""The command line that examples/map_use.py and examples/stationary_drift.py share: a GPD and the first scenes of
a store's split."""

from __future__ import annotations

import argparse

import gpd_jax
from gpd_jax.data.loader import SplitSource


def store_parser(description: str, data_help: str = "a data store") -> argparse.ArgumentParser:
    """--checkpoint, --data, --split, --scenarios, --json."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--checkpoint", default=None, help="an exported GPD (default: checkpoints/gpd_sumo)")
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
