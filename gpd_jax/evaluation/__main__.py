"""Command line: `python -m gpd_jax.evaluation compare RUN [RUN ...]`.

  compare RUN_A [RUN_B ...] [--names A,B,...] [--task traffic_simulation] [--baseline constant_velocity]
          [--metric agent_ade] [--variant paper] [--unit scene|location] [--resamples 2000] [--level 0.95]
          [--seed 0] [--json PATH]

RUN is a `rollout.py --out` directory (its scene_sums.npz) or the .npz itself. Prints each run's model / baseline
ratio at every horizon with a scene-bootstrap interval and, for runs after the first (which must be on the same
scenes), the paired difference to the first with its interval and the share of draws where it is lower
(`gpd_jax.evaluation.bootstrap`). `--unit location` draws whole road networks instead of scenes: the interval
for "on networks it never saw". `--metric` is any summed ADE / FDE key: agent_ade, agent_fde, ego_ade,
agent_ade_moving, agent_ade_stationary, agent_ade_along_moving, ... Bad input exits with status 2.
"""

from __future__ import annotations

import argparse
import os
import sys

from gpd_jax.cliargs import ArgumentParser, count, output_file, program, run_command, share


PROG = "python -m gpd_jax.evaluation"


def _parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog=program(PROG), description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("compare", help="scene-bootstrap intervals of runs' ratios, paired differences to the first")
    c.add_argument("runs", nargs="+", help="rollout.py output directories (or their scene_sums.npz)")
    c.add_argument("--names", default=None, help="comma list, one name per run (default: the directory names)")
    c.add_argument("--task", default="traffic_simulation")
    c.add_argument("--baseline", default="constant_velocity")
    c.add_argument("--metric", default="agent_ade")
    c.add_argument("--variant", default="paper", choices=("paper", "corrected"))
    c.add_argument("--unit", default="scene", choices=("scene", "location"),
                   help="what a bootstrap draw resamples: scenes, or whole road networks (the store's locations)")
    c.add_argument("--resamples", type=count, default=2000)
    c.add_argument("--level", type=share, default=0.95)
    c.add_argument("--seed", type=int, default=0, help="seed of the bootstrap draws")
    c.add_argument("--json", type=output_file, default=None, help="also write the result here (written to a temporary, renamed)")
    return p


def main(argv=None) -> int:
    return run_command(PROG, lambda: _compare(_parser().parse_args(argv)), ("gpd_jax.spec:EvalError",))


def _compare(args) -> int:
    from gpd_jax.evaluation.bootstrap import compare_runs, format_comparison, load_scene_sums
    from gpd_jax.evaluation.report import to_json_compatible
    from gpd_jax.fsutil import atomic_write_json
    from gpd_jax.spec import EvalError

    names = args.names.split(",") if args.names else [os.path.basename(os.path.normpath(r)) for r in args.runs]
    if len(names) != len(args.runs):
        raise EvalError(f"--names has {len(names)} names for {len(args.runs)} runs")
    runs = [load_scene_sums(r) for r in args.runs]
    res = compare_runs(runs, task=args.task, baseline=args.baseline, metric=args.metric, variant=args.variant,
                       resamples=args.resamples, level=args.level, seed=args.seed, unit=args.unit)
    res["names"], res["sources"] = names, [os.path.abspath(r) for r in args.runs]
    print(format_comparison(res, names))
    if args.json:
        atomic_write_json(args.json, to_json_compatible(res), indent=1, allow_nan=False)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
