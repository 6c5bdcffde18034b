"""Learning curves of a train.py run: `python -m gpd_jax.training.curves WORKDIR OUT.png`.

Reads `WORKDIR/metrics.jsonl` and draws the training losses (per part) and, from the periodic validation, the
validation loss and the `traffic_simulation` rollout agent ADE relative to constant velocity at each horizon.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from gpd_jax.fsutil import atomic_file


def read_metrics(workdir: str) -> list[dict]:
    path = os.path.join(workdir, "metrics.jsonl")
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no metrics (is {workdir} a train.py workdir?)")
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def plot_curves(records: list[dict], out_png: str, title: str = "") -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    train = [r for r in records if r.get("split") == "train"]
    val = [r for r in records if r.get("split") not in ("train", None)]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for key in ("loss", "position", "heading", "valid", "map", "velocity"):
        pts = [(r["step"], r[key]) for r in train if r.get(key) is not None]
        if pts:
            axes[0].plot(*zip(*pts), label=key, lw=1)
    axes[0].set_yscale("log")
    axes[0].set_title("training loss (weighted total and parts)")
    axes[0].set_xlabel("step")
    axes[0].legend(fontsize=8)
    for key in ("loss", "position", "map", "velocity"):
        pts = [(r["step"], r[key]) for r in val if r.get(key) is not None]
        if pts:
            axes[1].plot(*zip(*pts), "o-", label=f"val {key}", lw=1)
    axes[1].set_yscale("log")
    axes[1].set_title("validation loss")
    axes[1].set_xlabel("step")
    axes[1].legend(fontsize=8)
    for key in sorted({k for r in val for k in r if k.startswith("rollout_agent_ade_") and k.endswith("_vs_cv")}):
        pts = [(r["step"], r[key]) for r in val if r.get(key) is not None]
        axes[2].plot(*zip(*pts), "o-", label=key.replace("rollout_agent_ade_", "").replace("_vs_cv", ""), lw=1)
    axes[2].axhline(1.0, color="grey", lw=0.8, ls="--")
    axes[2].set_title("val traffic_simulation agent ADE / const. velocity")
    axes[2].set_xlabel("step")
    axes[2].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    with atomic_file(out_png, "wb") as f:
        fig.savefig(f, dpi=90, format="png")
    plt.close(fig)
    return out_png


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m gpd_jax.training.curves", description=__doc__.split("\n\n")[0])
    p.add_argument("workdir")
    p.add_argument("out", help="PNG path")
    p.add_argument("--title", default="")
    args = p.parse_args(argv)
    try:
        print(plot_curves(read_metrics(args.workdir), args.out, args.title))
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
