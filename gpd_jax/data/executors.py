"""Where a store build's jobs run (`gpd_jax.data.jobs.run_jobs`): processes of this machine (the default) or Ray
tasks over a cluster (`pip install -e '.[ray]'`; `python -m gpd_jax.data build ... --executor ray --address
HOST:PORT`).

An executor has one method, `map(fn, items)`: it calls the picklable `fn` on every item, somewhere, and yields
`(item, result)` pairs as they finish. A job writes its own shard and its marker (`jobs.job_marker`) into the
store folder, so a build is resumable whatever ran it: a machine that dies loses only the jobs it was running (Ray
runs them again elsewhere, `max_retries` times; a job that raises is retried as well), and the same command started
again skips every finished job. The jobs are pure functions of their settings and seeds, so the store does not
depend on the executor, the number of workers or the order in which jobs finish. With Ray the store folder must be
one that every node reads and writes at the same path (NFS or alike).

For the tests only: `GPD_JAX_TEST_FAIL_ONCE=INDEX:FOLDER` makes the job of index INDEX (`job.index`) raise once, the
first time it runs (the run leaves FOLDER/failed_<INDEX>); any executor honours it (Ray then runs it again).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import dataclasses
import os
from typing import Any, Callable, Iterable, Iterator, Sequence

from gpd_jax import interrupt
from gpd_jax.data.errors import DataError

FAIL_ONCE_ENV = "GPD_JAX_TEST_FAIL_ONCE"
EXECUTORS = ("local", "ray")


class InjectedFailure(RuntimeError):
    """The failure `GPD_JAX_TEST_FAIL_ONCE` asks for (tests of retries)."""


def _fail_once(index: int | None) -> None:
    spec = os.environ.get(FAIL_ONCE_ENV)
    if not spec or index is None:
        return
    which, _, folder = spec.partition(":")
    if int(which) != index:
        return
    os.makedirs(folder, exist_ok=True)
    try:  # exclusive creation: only the first run of the item fails
        with open(os.path.join(folder, f"failed_{index}"), "x"):
            pass
    except FileExistsError:
        return
    raise InjectedFailure(f"{FAIL_ONCE_ENV}: item {index} fails once (a test of retries)")


def call(fn: Callable[[Any], Any], item: Any) -> Any:
    """`fn(item)` as every executor runs it (`GPD_JAX_TEST_FAIL_ONCE` honoured first, for jobs)."""
    _fail_once(getattr(item, "index", None))
    return fn(item)


def worker_init() -> None:
    """Initializer of local worker processes: warnings only; Ctrl-C ends them quietly (the parent says what was
    kept; `gpd_jax.interrupt.quiet_worker`)."""
    import logging

    logging.basicConfig(level=logging.WARNING)
    interrupt.quiet_worker()


@dataclasses.dataclass(frozen=True)
class LocalExecutor:
    """`workers` processes of this machine (spawned; 1: in this process, in order)."""

    workers: int = 1

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[Any, Any]]:
        items = list(items)
        if self.workers <= 1 or len(items) <= 1:
            for item in items:
                yield item, call(fn, item)
            return
        with interrupt.worker_pool(min(self.workers, len(items)), initializer=worker_init) as ex:
            futs = {ex.submit(call, fn, item): item for item in items}
            for fut in cf.as_completed(futs):
                yield futs[fut], fut.result()


@dataclasses.dataclass(frozen=True)
class RayExecutor:
    """Ray tasks, one per item, on the cluster at `address` (None: a Ray instance started here with `num_cpus`).

    Each task asks for `cpus_per_task` CPUs (one SUMO run or one log per core) and is run again up to
    `max_retries` times when its node dies or it raises."""

    address: str | None = None
    num_cpus: int | None = None
    cpus_per_task: float = 1.0
    max_retries: int = 3

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[Any, Any]]:
        ray = _import_ray()
        items = list(items)
        if not items:
            return
        if not ray.is_initialized():
            env = {k: os.environ[k] for k in (FAIL_ONCE_ENV,) if k in os.environ}
            try:
                ray.init(address=self.address, num_cpus=None if self.address else self.num_cpus,
                         include_dashboard=False, log_to_driver=False, configure_logging=False,
                         runtime_env={"env_vars": env} if env else None)
            except (ConnectionError, ValueError, RuntimeError) as e:
                raise DataError(None, f"--address {self.address}: cannot join the Ray cluster there "
                                      f"({' '.join(str(e).split())[:300]})") from None
        task = ray.remote(num_cpus=self.cpus_per_task, max_retries=self.max_retries, retry_exceptions=True)(call)
        fn_ref = ray.put(fn)
        pending = {task.remote(fn_ref, item): item for item in items}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                item = pending.pop(done[0])
                yield item, ray.get(done[0])
        finally:
            for ref in pending:  # stopped (an error, Ctrl-C): the finished jobs stay, the rest are cancelled
                ray.cancel(ref)


def _import_ray():
    try:
        import ray
    except ImportError:
        raise DataError(None, "--executor ray needs Ray: pip install -e '.[ray]' (or pip install ray)") from None
    return ray


def make_executor(name: str = "local", workers: int = 1, address: str | None = None) -> LocalExecutor | RayExecutor:
    """The executor of the build command's `--executor NAME --workers W --address ADDR`."""
    if name == "local":
        if address:
            raise DataError(None, "--address is for --executor ray")
        return LocalExecutor(workers)
    if name == "ray":
        _import_ray()
        return RayExecutor(address=address or None, num_cpus=None if address else workers)
    raise DataError(None, f"--executor {name!r}: expected one of {', '.join(EXECUTORS)}")


def results(executor, fn: Callable[[Any], Any], items: Sequence[Any]):
    """`with results(executor, fn, items) as it: for item, result in it: ...`: `executor.map(fn, items)`, closed
    as soon as the body stops (an error, Ctrl-C), so that the executor's workers are stopped then, not when the
    abandoned generator is collected."""
    return contextlib.closing(executor.map(fn, items))


def run_all(executor, fn: Callable[[Any], Any], items: Iterable[Any]) -> list[Any]:
    """Every `fn(item)` in the order of `items` (the executor may finish them in any order)."""
    items = list(items)
    out: dict[int, Any] = {}
    pos = {id(x): i for i, x in enumerate(items)}
    with results(executor, fn, items) as it:
        for item, result in it:
            out[pos[id(item)]] = result
    return [out[i] for i in range(len(items))]
