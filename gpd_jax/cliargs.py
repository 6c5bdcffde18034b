"""What every command line of the package shares: one-line usage errors (exit status 2, no traceback, nothing
written) and argparse types for counts and shares.

    p = ArgumentParser(prog="gpd-jax data")        # parse errors raise UsageError instead of printing the usage
    p.add_argument("--batch", type=count)          # an integer >= 1, else "argument --batch: must be ..."
    sys.exit(run_command("gpd-jax data", lambda: work(p.parse_args(argv))))
"""

from __future__ import annotations

import argparse
import sys
from typing import Callable


class UsageError(Exception):
    """Bad command-line input; the message (one line) names the flag, file or value."""


class ArgumentParser(argparse.ArgumentParser):
    """An ArgumentParser whose errors raise `UsageError` (one line, without the usage block); its sub-parsers
    are of the same class. `--help` still prints and exits 0."""

    def error(self, message):
        raise UsageError(message)


def run_command(prog: str, work: Callable[[], int | None], errors: tuple = ()) -> int:
    """Runs `work()`: its exit status (None: 0), or 2 with `prog: error: <one line>` on stderr for a UsageError or
    any of `errors` (the library's own bad-input exceptions)."""
    try:
        return int(work() or 0)
    except (UsageError, *errors) as e:
        msg = e.args[0] if isinstance(e, KeyError) and len(e.args) == 1 else str(e)
        print(f"{prog}: error: {' '.join(str(msg).split())}", file=sys.stderr)
        return 2
    except SystemExit as e:  # --help
        return e.code if isinstance(e.code, int) else 0


def _integer(text: str, low: int) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if v < low:
        raise argparse.ArgumentTypeError(f"must be an integer >= {low}, got {v}")
    return v


def count(text: str) -> int:
    """argparse type of counts (scenarios, batch sizes, workers, repeats): an integer >= 1."""
    return _integer(text, 1)


def count0(text: str) -> int:
    """argparse type of counts that may be zero (scenes to render): an integer >= 0."""
    return _integer(text, 0)


def share(text: str) -> float:
    """argparse type of shares: a number in [0, 1]."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"must be a share in [0, 1], got {v}")
    return v
