"""One command line over the library: `gpd-jax COMMAND ...` (installed with the package).

    gpd-jax models                              the shipped models: name, kind, purpose, where found
    gpd-jax data build|inspect|realnets|...     data stores (python -m gpd_jax.data)
    gpd-jax tokenizer evaluate|encode|...       the map tokenizer (python -m gpd_jax.map_tokenizer)
    gpd-jax train --config FILE --workdir DIR   training, both stages (train.py)
    gpd-jax eval --data DIR --out DIR           rollouts of every task, metrics, baselines (rollout.py)
    gpd-jax compare RUN_A RUN_B ...             scene-bootstrap intervals of evaluation runs
    gpd-jax plan evaluate|bench                 closed-loop planning scores (python -m gpd_jax.plan)
    gpd-jax bench rollout|realism ...           rollout and realism-metric speed (python -m gpd_jax.bench)
    gpd-jax checkpoint export|average           export a workdir, average models (python -m gpd_jax.checkpoint)

Every command exits 0, or 2 with one line naming what is wrong.
"""

from __future__ import annotations

import importlib
import sys

# command -> (module whose `main(argv)` runs it, its own program name, one line of help)
COMMANDS = {
    "models": ("gpd_jax.cli", None, "the shipped models: name, kind, purpose, where found"),
    "data": ("gpd_jax.data.__main__", None, "data stores: build, inspect, realnets, pack, ..."),
    "tokenizer": ("gpd_jax.map_tokenizer.__main__", None, "the map tokenizer: evaluate, encode, export, ..."),
    "train": ("gpd_jax.training.command", "gpd-jax train", "training, both stages (as train.py)"),
    "eval": ("gpd_jax.evaluation.command", "gpd-jax eval", "rollouts of every task, metrics, tables (as rollout.py)"),
    "compare": ("gpd_jax.evaluation.__main__", None, "scene-bootstrap intervals of evaluation runs"),
    "plan": ("gpd_jax.plan.__main__", None, "closed-loop planning scores and the simulator's speed"),
    "bench": ("gpd_jax.bench", None, "rollout speed (cached against recompute, attention paths); realism metric speed"),
    "checkpoint": ("gpd_jax.checkpoint", None, "export a training workdir, average models"),
}


def models(argv: list[str]) -> int:
    """`gpd-jax models`: the shipped models (the default first) and where each was found."""
    from gpd_jax import zoo

    if argv:
        print(f"gpd-jax models: takes no arguments, got {' '.join(argv)}", file=sys.stderr)
        return 2
    for card in zoo.list_models():
        default = " (default)" if card.name == zoo.DEFAULT_MODEL else ""
        print(f"{card.name}{default} [{card.kind}]: {card.purpose}")
        if card.tokenizer:
            print(f"    tokenizer: {card.tokenizer}")
        print(f"    figures: {card.figures}")
        print(f"    folder: {card.path or 'not found in ' + zoo.where_searched()}")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__.split("\n\n")[0] + "\n")
        for name, (_, _, text) in COMMANDS.items():
            print(f"  {name:<11} {text}")
        print("\n`gpd-jax COMMAND --help` for a command's options.")
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"gpd-jax: unknown command {name!r}; commands: {', '.join(COMMANDS)}", file=sys.stderr)
        return 2
    if name == "models":
        return models(rest)
    module, prog, _ = COMMANDS[name]
    from gpd_jax.cliargs import set_program

    # usage lines and errors name the program typed (`gpd-jax plan evaluate`), not `python -m gpd_jax.plan`
    set_program("gpd-jax" if name == "compare" else f"gpd-jax {name}")
    run = importlib.import_module(module).main
    if name == "compare":
        rest = ["compare"] + rest
    try:
        return int((run(rest, prog) if prog else run(rest)) or 0)
    except SystemExit as e:  # --help of a command
        return e.code if isinstance(e.code, int) else 0
    finally:
        set_program(None)


if __name__ == "__main__":
    sys.exit(main())
