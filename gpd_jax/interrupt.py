"""Ctrl-C in a long command: stop within seconds, say in one line what was kept and how to resume, exit 130.

Every command line runs under `watch` (through `gpd_jax.cliargs.run_command`), one mechanism for all of them:

* the first SIGINT raises KeyboardInterrupt in the main thread as usual, so `finally` blocks and atomic writers
  (`gpd_jax.fsutil`) clean up and nothing half-written is left under a final name; the command line prints its
  one line and exits 130;
* the main thread may be inside a long native call (an XLA compilation, a blocking wait) where Python cannot
  raise: a watchdog thread, woken by the signal itself (`signal.set_wakeup_fd`), prints the line, stops the
  worker processes and ends the process after `grace_s` seconds (at once on a second Ctrl-C);
* worker processes (`quiet_worker` as their initializer) leave quietly: no traceback per worker, and a running
  job's subprocesses are killed with it (an exception unwinds `subprocess.run`).

A long command says what an interruption keeps with `keep("the shards of finished jobs")` as it learns it.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator

EXIT_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports for a process ended by Ctrl-C

_state = {"interrupted": False, "kept": None, "announced": False}
_lock = threading.Lock()


def interrupted() -> bool:
    """Whether a SIGINT arrived during the watched command."""
    return bool(_state["interrupted"])


def keep(text: str) -> None:
    """Says what an interruption from now on keeps (e.g. "the checkpoint of step 120"), for the one line."""
    _state["kept"] = text


def kept(default: str) -> str:
    return _state["kept"] or default


def announce_once(line: str) -> bool:
    """Prints `line` to stderr unless the line of this interruption was already printed; True if printed."""
    with _lock:
        if _state["announced"]:
            return False
        _state["announced"] = True
    if "tqdm" in sys.modules:  # end the progress bars, so that the line starts a line of its own
        for bar in list(getattr(sys.modules["tqdm"].tqdm, "_instances", ())):
            with contextlib.suppress(Exception):
                bar.close()
    print(line, file=sys.stderr, flush=True)
    return True


def stop_children(timeout_s: float = 2.0) -> None:
    """Stops this process's worker processes (multiprocessing / concurrent.futures): SIGINT first (they unwind
    quietly, killing their own subprocesses; see `quiet_worker`), then SIGKILL for any still alive after
    `timeout_s`."""
    children = multiprocessing.active_children()
    for p in children:
        with contextlib.suppress(OSError, ValueError, AttributeError):
            os.kill(p.pid, signal.SIGINT)
    deadline = time.monotonic() + timeout_s
    for p in children:
        p.join(max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            with contextlib.suppress(OSError, ValueError, AttributeError):
                p.kill()


def _raise_interrupt(signum, frame):
    _state["interrupted"] = True
    raise KeyboardInterrupt


_worker_ready = False


def _leave_quietly(signum, frame):
    if not _worker_ready:  # still in its initializer: no job to unwind, and an exception there is logged loudly
        os._exit(EXIT_INTERRUPTED)
    raise SystemExit(EXIT_INTERRUPTED)


def quiet_worker() -> None:
    """Initializer of worker processes: a SIGINT (Ctrl-C reaches the whole process group) ends the worker without
    a traceback. Inside a job the exception unwinds it (`subprocess.run` kills its child) and goes back to the
    parent, which is stopping anyway; an idle worker exits. `worker_pool` starts its workers with SIGINT blocked
    (a Ctrl-C while a worker's interpreter starts would print a traceback from its `site` import); it is
    unblocked here, once the quiet handler is in place (a Ctrl-C that came meanwhile ends the worker now)."""
    global _worker_ready
    signal.signal(signal.SIGINT, _leave_quietly)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    _worker_ready = True


@contextlib.contextmanager
def _sigint_blocked() -> Iterator[None]:
    """SIGINT blocked in this thread for the body: processes started meanwhile inherit the mask (across exec);
    this process's Ctrl-C stays pending and arrives when the body ends."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


@contextlib.contextmanager
def worker_pool(workers: int, initializer: Callable[[], None] = quiet_worker):
    """A `concurrent.futures.ProcessPoolExecutor` of `workers` spawned processes started with `initializer` (which
    should call `quiet_worker`: the workers start with SIGINT blocked, and it unblocks it); when the body raises
    (Ctrl-C), the workers are stopped at once instead of being waited for."""
    import concurrent.futures as cf

    # a pool stopped by Ctrl-C leaves its queues' semaphores to multiprocessing's resource tracker, which cleans
    # them up but warns in two lines; the tracker is a process of its own, started with this environment
    quiet = "ignore::UserWarning:multiprocessing.resource_tracker"
    if quiet not in os.environ.get("PYTHONWARNINGS", ""):
        os.environ["PYTHONWARNINGS"] = ",".join(w for w in (os.environ.get("PYTHONWARNINGS"), quiet) if w)
    class Pool(cf.ProcessPoolExecutor):
        def submit(self, *args, **kwargs):  # spawned workers start here (and `map` submits): SIGINT blocked
            with _sigint_blocked():
                return super().submit(*args, **kwargs)

    ex = Pool(workers, mp_context=multiprocessing.get_context("spawn"), initializer=initializer)
    try:
        yield ex
    except BaseException:
        ex.shutdown(wait=False, cancel_futures=True)
        stop_children()
        raise
    finally:
        ex.shutdown(wait=True)


@contextlib.contextmanager
def watch(line: Callable[[], str], grace_s: float = 5.0) -> Iterator[None]:
    """Runs the body with Ctrl-C watched (see the module docstring); `line()` is the one line an interruption
    prints. Outside the main thread, or where SIGINT is ignored, the body runs unwatched."""
    _state.update(interrupted=False, kept=None, announced=False)
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) in (signal.SIG_IGN, None):
        yield
        return
    old_handler = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, _raise_interrupt)
    r, w = socket.socketpair()
    r.setblocking(True)
    w.setblocking(False)
    try:
        old_fd = signal.set_wakeup_fd(w.fileno(), warn_on_full_buffer=False)
    except ValueError:
        r.close(), w.close()
        yield
        return

    def watchdog():
        deadline = None  # set by the first Ctrl-C
        while True:
            r.settimeout(None if deadline is None else max(0.0, deadline - time.monotonic()))
            try:
                data = r.recv(64)
            except TimeoutError:
                data = None
            except OSError:
                return
            if data == b"":  # the body finished: the write end was closed
                return
            if data and signal.SIGINT not in data:
                continue
            if data and deadline is None:  # the first Ctrl-C: the main thread gets grace_s to unwind
                _state["interrupted"] = True
                deadline = time.monotonic() + grace_s
                continue
            # a second Ctrl-C, or the main thread is stuck in native code past the grace period
            announce_once(line())
            stop_children(timeout_s=1.0)
            os._exit(EXIT_INTERRUPTED)

    t = threading.Thread(target=watchdog, name="gpd_jax-interrupt-watchdog", daemon=True)
    t.start()
    try:
        yield
    finally:
        signal.set_wakeup_fd(old_fd)
        signal.signal(signal.SIGINT, old_handler)
        if _state["interrupted"]:
            stop_children()
        w.close()
        t.join(timeout=1.0)
        r.close()


def typed_command(argv: list[str] | None = None) -> str:
    """The command line as the user typed it (to rerun it): `gpd-jax data build ...`, `python train.py ...`,
    `python -m gpd_jax.data build ...`."""
    import shlex

    argv = list(sys.argv if argv is None else argv)
    if not argv:
        return ""
    head, rest = argv[0], argv[1:]
    base = os.path.basename(head)
    if base == "__main__.py":
        pkg = os.path.dirname(os.path.abspath(head))
        parts = []
        while os.path.isfile(os.path.join(pkg, "__init__.py")):
            parts.insert(0, os.path.basename(pkg))
            pkg = os.path.dirname(pkg)
        words = ["python", "-m", ".".join(parts)]
    elif base.endswith(".py"):
        words = ["python", head]
    else:
        words = [base]
    return shlex.join(words + rest)
