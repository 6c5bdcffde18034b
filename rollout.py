"""Multi-task evaluation of a trained GPD model: rollouts of every task, metrics, baselines, pictures.

    python rollout.py --data data/heldout --out runs/eval                     # checkpoints/gpd_sumo, test split
    python rollout.py --checkpoint DIR --data DIR [--split test] [--tasks all|a,b] --out DIR [--scenarios N]
                      [--batch B] [--render K] [--seed S] [--variant paper|corrected] [--horizons 3,5,8]
                      [--log-map tokens|lanes] [--config.rollout.temperature=0.5]
    python rollout.py --data DIR --out DIR --prompt examples/prompt_inpaint.json[,more.json] [--render K]

Runs every task (gpd_jax/tasks.py) on the first N scenarios of the split in one compiled rollout per batch, scores
them at 3 / 5 / 8 s next to the constant-velocity, log-replay and map baselines, prints tables shaped like the
paper's Tables 1 and 2 and writes OUT/metrics.json, OUT/tables.txt, OUT/scene_sums.npz (each scenario's sums:
`python -m gpd_jax.evaluation compare` turns them into scene-bootstrap intervals) and, with --render K, pictures
of the first K scenarios under OUT/render/ (definitions and layout: gpd_jax/evaluation/__init__.py). Bad input
exits with status 2 and a message naming the problem, before anything is written.
"""

from __future__ import annotations

import argparse
import os
import sys

REPO_ROOT = os.path.dirname(os.path.abspath(__file__))
PROG = "rollout.py"


def _parser() -> argparse.ArgumentParser:
    from gpd_jax.evaluation.command import Parser

    p = Parser(prog=PROG, description=__doc__.split("\n\n")[0],
                                epilog="Any --config.rollout.X=value overrides that field of the model's config.")
    p.add_argument("--checkpoint", default=os.path.join(REPO_ROOT, "checkpoints", "gpd_sumo"),
                   help="exported model directory or train.py workdir (default: checkpoints/gpd_sumo)")
    p.add_argument("--data", required=True, help="data store directory (python -m gpd_jax.data build)")
    p.add_argument("--split", default="test")
    p.add_argument("--tasks", default="all", help="'all' or a comma list of task keys")
    p.add_argument("--out", required=True, help="output directory (metrics.json, tables.txt, render/)")
    p.add_argument("--scenarios", type=int, default=None, help="first N scenarios of the split (default: all)")
    p.add_argument("--batch", type=int, default=8, help="scenarios per compiled rollout call (every task each)")
    p.add_argument("--render", type=int, default=0, metavar="K", help="GIF + PNG of every task for the first K")
    p.add_argument("--render-size", type=int, default=320, help="pixels per rendered frame")
    p.add_argument("--seed", type=int, default=0, help="rollout PRNG seed (used at temperature > 0)")
    p.add_argument("--variant", default="paper", choices=("paper", "corrected"),
                   help="metric variant of the main keys; the other is written with its name as a suffix")
    p.add_argument("--horizons", default="3,5,8", help="horizons in seconds (comma list)")
    p.add_argument("--log-map", default="tokens", choices=("tokens", "lanes"),
                   help="tasks that take the map from the log but generate the ego get the logged map tokens "
                        "(the paper's choice) or the log's lanes re-encoded around the generated ego every frame")
    p.add_argument("--gen-map", default="model", choices=("model", "warp"),
                   help="where the map is generated: every token the model's (the paper's choice) or the previous "
                        "frame's map moved with the ego, the model's tokens only in cells newly in view")
    p.add_argument("--prompt", default=None, metavar="FILE[,FILE]",
                   help="JSON prompt file(s) (examples/prompt_*.json): roll out every scenario under each prompt "
                        "and score how the conditions are respected (OUT/conditions.json) instead of the tasks")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv=None) -> int:
    from gpd_jax.evaluation.command import UsageError, check_arguments, run

    try:
        args, overrides = check_arguments(_parser(), list(sys.argv[1:] if argv is None else argv))
        return run(args, overrides)
    except UsageError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    except SystemExit as e:  # --help
        return int(e.code or 0)


if __name__ == "__main__":
    sys.exit(main())
