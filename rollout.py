"""Multi-task evaluation of a GPD model: rollouts of every task, metrics, baselines, pictures.

    python rollout.py --data data/test --out runs/eval                         # the default model, test split
    python rollout.py --checkpoint NAME_OR_DIR --data DIR [--split test] [--tasks all|a,b] --out DIR
                      [--scenarios N] [--batch B] [--render K] [--seed S] [--variant paper|corrected]
                      [--horizons 3,5,8] [--temperature T] [--top-k K] [--top-p P] [--log-map tokens|lanes]
                      [--gen-map model|warp] [--samples K] [--realism-config 2024|2025]
    python rollout.py --data DIR --out DIR --prompt examples/prompt_inpaint.json[,more.json] [--render K]

Runs every task (gpd_jax/tasks.py) on the first N scenarios of the split in one compiled rollout per batch, scores
them at 3 / 5 / 8 s next to the constant-velocity, log-replay and map baselines, prints tables shaped like the
paper's Tables 1 and 2 and writes OUT/metrics.json, OUT/tables.txt, OUT/scene_sums.npz (each scenario's sums:
`gpd-jax compare` turns them into scene-bootstrap intervals) and, with --render K, pictures of the first K
scenarios under OUT/render/ (definitions and layout: gpd_jax/evaluation/__init__.py). Bad input exits with status
2 and a message naming the problem, before anything is written. The same command is `gpd-jax eval`.
"""

import sys

from gpd_jax.evaluation.command import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
