"""The training command line of both stages (`train.py`, `gpd-jax train`).

    python train.py --config configs/map_tokenizer.py:tiny --workdir DIR [--config.a.b=value ...]   # stage 1
    python train.py --config configs/gpd_tiny.py --workdir DIR [--config.a.b=value ...]             # stage 2
    python train.py --config configs/gpd_planner.py --workdir DIR [...]          # the planning head

The config's `stage` field picks the stage: "map_tokenizer" trains the map VQ-VAE
(`gpd_jax.training.map_tokenizer`), "gpd" the scene transformer (`gpd_jax.training.loop`), or, when the config
has a `plan_head` section, its planning head (`gpd_jax.training.planning`). Runs resume from the latest checkpoint in
DIR when one is there.
"""

from __future__ import annotations

import argparse
import os

from gpd_jax import distributed
from gpd_jax.cliargs import ArgumentParser, UsageError, run_command
from gpd_jax.config import split_config_args

PROG = "train.py"
# the source checkout's configs/ folder (listed by --help; any config file can be passed by path)
CONFIGS_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "configs")


class Parser(ArgumentParser):
    def error(self, message):  # one line, pointing at --help
        raise UsageError(f"{message} (python {PROG} --help lists the options)")


def epilog() -> str:
    """The overrides' syntax and the config files next to this script, each with its docstring's first line."""
    from gpd_jax.training.common import config_summaries

    text = ["Any field of the config can be overridden: --config.a.b=value (e.g. --config.train.batch_size=8); the "
            "value is parsed with the field's type, and an unknown field or a wrong type is an error.", ""]
    configs = config_summaries(CONFIGS_DIR)
    if configs is None:
        text.append(f"config files: {CONFIGS_DIR} does not exist (pass --config PATH to any configs/*.py file)")
    else:
        text.append(f"config files in {CONFIGS_DIR}:" if configs else f"config files: none in {CONFIGS_DIR}")
        width = max((len(n) for n, _ in configs), default=0)
        text += [f"  {name.ljust(width)}  {first}" for name, first in configs]
    return "\n".join(text)


def parser(prog: str = PROG) -> argparse.ArgumentParser:
    p = Parser(prog=prog, description=__doc__.split("\n\n")[0], epilog=epilog(),
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", required=True, help="a configs/*.py file (FILE.py:ARG calls its get_config(ARG))")
    p.add_argument("--workdir", required=True, help="checkpoints, metrics and logs go here")
    p.add_argument("--stop-after", type=int, default=None,
                   help="stop (with a checkpoint) after this many steps of this invocation; run again to resume")
    distributed.add_arguments(p)  # --coordinator HOST:PORT --num-processes N --process-id I | --distributed
    return p


def main(argv: list[str], prog: str = PROG) -> int:
    """Runs the training command line: exit 0, or 2 with one line naming the problem."""
    overrides, rest = split_config_args(list(argv))
    return run_command(prog, lambda: run(parser(prog).parse_args(rest), overrides))


def run(args: argparse.Namespace, overrides: list[str]) -> int:
    from gpd_jax.training.common import ConfigLoadError, error_message, load_training_config

    distributed.initialize(distributed.from_args(args))
    try:
        config = load_training_config(args.config, overrides)
    except ConfigLoadError as e:
        raise UsageError(str(e)) from None
    stage = config.stage
    if stage == "map_tokenizer":
        from gpd_jax.training.map_tokenizer import train_and_evaluate

        def train():
            train_and_evaluate(config, args.workdir, stop_after=args.stop_after)
    elif stage == "gpd":
        if "plan_head" in config:  # a GPD with the planning head (configs/gpd_planner.py)
            from gpd_jax.training.planning import train_and_evaluate as train_gpd
        else:
            from gpd_jax.training.loop import train_and_evaluate as train_gpd

        def train():
            train_gpd(config, args.workdir, stop_after=args.stop_after)
    else:
        raise UsageError(f"{args.config} has stage={stage!r}; expected 'map_tokenizer' or 'gpd'")
    try:  # bad data, a missing or damaged model to start from, ... (DataError is a ValueError)
        train()
    except (ValueError, FileNotFoundError) as e:
        raise UsageError(" ".join(error_message(e).split())) from None
    return 0

