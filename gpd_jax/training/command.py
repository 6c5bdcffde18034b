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
import math
import os
import shutil

from gpd_jax import distributed, interrupt
from gpd_jax.cliargs import ArgumentParser, UsageError, check_output_dir, count, program, run_command
from gpd_jax.config import split_config_args

PROG = "train.py"
# the source checkout's configs/ folder (listed by --help; any config file can be passed by path)
CONFIGS_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "configs")


class Parser(ArgumentParser):
    def error(self, message):  # one line, pointing at --help
        python = "python " if self.prog.endswith(".py") else ""
        raise UsageError(f"{message} ({python}{self.prog} --help lists the options)")


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
    p = Parser(prog=program(prog), description=__doc__.split("\n\n")[0], epilog=epilog(),
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", required=True, help="a configs/*.py file (FILE.py:ARG calls its get_config(ARG))")
    p.add_argument("--workdir", required=True, help="checkpoints, metrics and logs go here")
    p.add_argument("--stop-after", type=count, default=None,
                   help="stop (with a checkpoint) after this many steps of this invocation; run again to resume")
    distributed.add_arguments(p)  # --coordinator HOST:PORT --num-processes N --process-id I | --distributed
    return p


def main(argv: list[str], prog: str = PROG) -> int:
    """Runs the training command line: exit 0, or 2 with one line naming the problem."""
    overrides, rest = split_config_args(list(argv))
    return run_command(prog, lambda: run(parser(prog).parse_args(rest), overrides),
                       kept="the last checkpoint in the workdir is kept", grace_s=30.0)


def check_train_numbers(config, path: str, overrides: list[str]) -> None:
    """UsageError naming the first `train` field (and its override, if one set it) whose value cannot train:
    sizes, step counts and intervals (`batch_size`, `steps`, `num_steps`, `*_every`, `*_size`) must be >= 1
    (`eval_every` >= 0 outside the map tokenizer's stage: 0 turns validation off),
    other counts (`*_batches`, `*_threads`, `*_steps`) >= 0, every number finite and rates >= 0."""
    train = config.get("train", {})
    for key in sorted(train.keys()):
        v = train[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        low = None
        if isinstance(v, int) and key == "eval_every" and config.get("stage") != "map_tokenizer":
            low = 0  # 0: no validation (a GPD or planning-head run); the tokenizer's trainer always validates
        elif isinstance(v, int) and (key in ("batch_size", "steps", "num_steps") or key.endswith(("_every", "_size"))):
            low = 1
        elif isinstance(v, int) and key.endswith(("_batches", "_threads", "_steps")):
            low = 0
        elif isinstance(v, float) and key.endswith("rate"):
            low = 0.0
        bad = not math.isfinite(v) or (low is not None and v < low)
        if bad:
            given = [o for o in overrides if o.split("=", 1)[0] == f"--config.train.{key}"]
            where = given[-1] if given else f"{path}: train.{key}"
            need = "a finite number" if low is None else f"{'an integer' if isinstance(v, int) else 'a number'} >= {low}"
            raise UsageError(f"{where}: must be {need}, got {v}")


def run(args: argparse.Namespace, overrides: list[str]) -> int:
    check_output_dir(args.workdir, "--workdir")
    from gpd_jax.training.common import ConfigLoadError, error_message, load_training_config

    distributed.initialize(distributed.from_args(args))
    try:
        config = load_training_config(args.config, overrides)
    except ConfigLoadError as e:
        raise UsageError(str(e)) from None
    check_train_numbers(config, args.config, overrides)
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
    existed = os.path.exists(args.workdir)
    interrupt.keep(f"the last checkpoint in {args.workdir} is kept")
    try:  # bad data, a missing or damaged model to start from, ... (DataError is a ValueError)
        train()
    except (ValueError, FileNotFoundError) as e:
        if not existed and latest_step(args.workdir) is None:  # refused at the start: leave nothing a rerun trips over
            shutil.rmtree(args.workdir, ignore_errors=True)
        raise UsageError(" ".join(error_message(e).split())) from None
    say_where_it_stopped(config, args.workdir)
    return 0


def latest_step(workdir: str) -> int | None:
    """The step of the workdir's latest checkpoint (orbax's numbered folders), None without one."""
    d = os.path.join(workdir, "checkpoints")
    steps = [int(n) for n in os.listdir(d) if n.isdigit()] if os.path.isdir(d) else []
    return max(steps, default=None)


def say_where_it_stopped(config, workdir: str) -> None:
    """Training's last line: where an interrupted run can resume (kept for the one line of an interruption),
    where a stopped one stopped, where a finished one exported its model."""
    step, total = latest_step(workdir), config.train.get("steps", config.train.get("num_steps"))
    if interrupt.interrupted():
        interrupt.keep(f"the checkpoint of step {step} is kept in {workdir}" if step is not None else
                       "no checkpoint was saved yet")
    elif step is not None and total is not None and step < total:
        print(f"stopped at step {step} of {total}; rerun the same command to resume", flush=True)
    else:
        export = os.path.join(workdir, "export")
        print(f"finished at step {step}; " + (f"exported to {export}" if os.path.isdir(export) else
                                              f"checkpoints in {os.path.join(workdir, 'checkpoints')}"), flush=True)

