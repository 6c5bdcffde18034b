"""What every command line of the package shares: one-line usage errors (exit status 2, no traceback, nothing
written), the program name the user typed, checks of output locations, argparse types for counts and shares, and a
clean stop on Ctrl-C (one line, exit 130; `gpd_jax.interrupt`).

    p = ArgumentParser(prog=program(PROG))         # parse errors raise UsageError instead of printing the usage
    p.add_argument("--batch", type=count)          # an integer >= 1, else "argument --batch: must be ..."
    p.add_argument("--out", type=output_dir)       # a directory that can be made and written, checked at once
    sys.exit(run_command(PROG, lambda: work(p.parse_args(argv)), kept="the shards already written"))

This module imports nothing heavy (no JAX): a command line parses and checks its arguments with it first and
imports the rest after, so a bad flag is refused at once.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Callable

from gpd_jax import interrupt

_PROGRAM: list[str] = []  # the program name the user typed, when a command runs under `gpd-jax` (set_program)


def set_program(name: str | None) -> None:
    """Names the program the user typed (`gpd-jax data`) for usage lines and errors of the command about to run;
    None restores the commands' own names."""
    _PROGRAM[:] = [name] if name else []


def program(default: str) -> str:
    """The program name of usage lines and errors: the one set by `set_program`, else `default`."""
    return _PROGRAM[0] if _PROGRAM else default


class UsageError(Exception):
    """Bad command-line input; the message (one line) names the flag, file or value."""


class ArgumentParser(argparse.ArgumentParser):
    """An ArgumentParser whose errors raise `UsageError` (one line, without the usage block); its sub-parsers
    are of the same class. `--help` still prints and exits 0."""

    def error(self, message):
        raise UsageError(message)


NOTHING_KEPT = "nothing half-written was kept"


def run_command(prog: str, work: Callable[[], int | None], errors: tuple = (), kept: str = NOTHING_KEPT,
                grace_s: float = 5.0) -> int:
    """Runs `work()`: its exit status (None: 0), or 2 with `prog: error: <one line>` on stderr for a UsageError or
    any of `errors` (the library's own bad-input exceptions: classes, or "module:Class" for those of modules that
    import JAX, which the command imports only after its arguments are checked).

    Ctrl-C stops it within `grace_s` seconds with one line on stderr saying what was kept (`kept`, or what the
    work said since with `gpd_jax.interrupt.keep`) and the command that resumes, and exit status 130."""
    prog = program(prog)

    def line() -> str:
        return (f"{prog}: interrupted; {interrupt.kept(kept)}; to go on, run the same command again: "
                f"{interrupt.typed_command()}")

    def stopped() -> int:
        import gc

        gc.collect()  # frees what the unwound work held (worker pools' semaphores) before the process ends
        interrupt.announce_once(line())
        return interrupt.EXIT_INTERRUPTED

    with interrupt.watch(line, grace_s=grace_s):
        rc = None
        try:
            rc = int(work() or 0)
        except KeyboardInterrupt:
            pass  # below, once the exception and the frames it holds are gone
        except (UsageError, *_classes(errors)) as e:
            if not interrupt.interrupted():  # else e.g. a worker pool broken by the interruption: below
                msg = e.args[0] if isinstance(e, KeyError) and len(e.args) == 1 else str(e)
                print(f"{prog}: error: {' '.join(str(msg).split())}", file=sys.stderr)
                return 2
        except SystemExit as e:  # --help
            return e.code if isinstance(e.code, int) else 0
        except BaseException:
            if not interrupt.interrupted():
                raise
        return stopped() if rc is None or interrupt.interrupted() else rc


def _classes(errors: tuple) -> tuple:
    """The exception classes of `errors`; a "module:Class" entry counts once its module is imported (before that
    nothing can have raised it)."""
    out = []
    for e in errors:
        if isinstance(e, str):
            module, name = e.split(":")
            if module in sys.modules:
                out.append(getattr(sys.modules[module], name))
        else:
            out.append(e)
    return tuple(out)


def _unwritable(path: str) -> str | None:
    """Why `path` (a directory to create or write into) cannot be written, else None."""
    path = os.path.abspath(path)
    if os.path.exists(path):
        if not os.path.isdir(path):
            return "exists and is not a directory"
        return None if os.access(path, os.W_OK | os.X_OK) else "is not writable"
    parent = path
    while not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent):
        return f"cannot be created: {parent} is a file"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"cannot be created: {parent} is not writable"
    return None


def check_output_dir(path: str, flag: str) -> str:
    """`path` as an absolute path when it is a directory that exists and can be written, or can be created;
    else UsageError naming `flag` and why. Creates nothing."""
    why = _unwritable(path)
    if why:
        raise UsageError(f"{flag} {path}: {why}")
    return os.path.abspath(path)


def check_output_file(path: str, flag: str) -> str:
    """`path` as an absolute path when a file can be written there (its folder exists or can be created, and it
    is not a directory); else UsageError naming `flag` and why. Creates nothing."""
    if os.path.isdir(path):
        raise UsageError(f"{flag} {path}: is a directory, not a file")
    if os.path.exists(path) and not os.access(path, os.W_OK):
        raise UsageError(f"{flag} {path}: is not writable")
    folder = os.path.dirname(os.path.abspath(path))
    why = _unwritable(folder)
    if why:
        raise UsageError(f"{flag} {path}: its folder {folder} {why}")
    return os.path.abspath(path)


def output_dir(text: str) -> str:
    """argparse type of output directories: one that can be written or created (checked, nothing created)."""
    why = _unwritable(text)
    if why:
        raise argparse.ArgumentTypeError(f"{text}: {why}")
    return text


def output_file(text: str) -> str:
    """argparse type of output files (--json): a path a file can be written to (checked, nothing created)."""
    try:
        check_output_file(text, "")
    except UsageError as e:
        raise argparse.ArgumentTypeError(str(e).strip()) from None
    return text


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


def number(text: str) -> float:
    """argparse type of finite numbers (metres, seconds, degrees, temperatures)."""
    import math

    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return v


def positive(text: str) -> float:
    """argparse type of quantities that must be > 0 (tolerances, sizes, rates per second)."""
    v = number(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return v


def nonnegative(text: str) -> float:
    """argparse type of quantities that may be 0 (sigmas, temperatures)."""
    v = number(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return v


def share(text: str) -> float:
    """argparse type of shares: a number in [0, 1]."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"must be a share in [0, 1], got {v}")
    return v
