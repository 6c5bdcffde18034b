"""Training command line for both stages.

    python train.py --config configs/map_tokenizer_tiny.py --workdir DIR [--config.a.b=value ...]   # stage 1
    python train.py --config configs/gpd_tiny.py --workdir DIR [--config.a.b=value ...]             # stage 2
    python train.py --config configs/gpd_sumo_plan_head.py --workdir DIR [...]   # the planning head (fine-tuning)

The config's `stage` field picks the stage: "map_tokenizer" trains the map VQ-VAE
(`gpd_jax.training.map_tokenizer`), "gpd" the scene transformer (`gpd_jax.training.loop`), or, when the config
has a `plan_head` section, its planning head (`gpd_jax.training.planning`). Runs resume from the latest checkpoint in
DIR when one is there.
"""

from __future__ import annotations

import argparse
import sys

from gpd_jax.config import load_config, split_config_args


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    overrides, rest = split_config_args(argv)
    p = argparse.ArgumentParser(prog="train.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--config", required=True, help="a configs/*.py file")
    p.add_argument("--workdir", required=True, help="checkpoints, metrics and logs go here")
    p.add_argument("--stop-after", type=int, default=None,
                   help="stage 2: stop (with a checkpoint) after this many steps of this invocation")
    p.add_argument("--distributed", action="store_true",
                   help="call jax.distributed.initialize() first (several hosts; coordinator from the environment)")
    args = p.parse_args(rest)
    if args.distributed:
        import jax

        jax.distributed.initialize()
    config = load_config(args.config, overrides)
    stage = config.get("stage")
    if stage == "map_tokenizer":
        from gpd_jax.training.map_tokenizer import train_and_evaluate

        train_and_evaluate(config, args.workdir)
        return 0
    if stage == "gpd":
        from gpd_jax.data.errors import DataError
        if config.get("plan_head"):  # a GPD with the planning head (configs/gpd_sumo_plan_head*.py)
            from gpd_jax.training.planning import train_and_evaluate as train_gpd
        else:
            from gpd_jax.training.loop import train_and_evaluate as train_gpd

        try:
            train_gpd(config, args.workdir, stop_after=args.stop_after)
        except (DataError, ValueError, FileNotFoundError) as e:
            print(f"train.py: {e}", file=sys.stderr)
            return 2
        return 0
    print(f"train.py: {args.config} has stage={stage!r}; expected 'map_tokenizer' or 'gpd'", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
