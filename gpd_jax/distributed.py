"""JAX's multi-controller runtime for the command lines that span processes and hosts (`train`, `eval`, `plan
evaluate`, `bench rollout`): one argument group, one validation, one initialization, and the gather of per-process
results to process 0.

    p = ArgumentParser(...)
    distributed.add_arguments(p)                  # --coordinator HOST:PORT --num-processes N --process-id I ...
    args = p.parse_args(argv)
    cluster = distributed.from_args(args)         # validated: UsageError naming the flag, before JAX starts
    distributed.initialize(cluster)               # before the first computation; a time-out is one clear line

Every process runs the same command with its own `--process-id` (0 is the coordinator, at `--coordinator`);
`--distributed` instead leaves the coordinator, the process count and the id to JAX's cluster detection (SLURM,
Open MPI, `JAX_COORDINATOR_ADDRESS` ...). On CPU hosts the processes talk through JAX's CPU collectives (gloo).
After `initialize`, `jax.devices()` spans every process's devices and `jax.process_index()` /
`jax.process_count()` say where this process stands. `gather_to_lead` sends every process's results (nested dicts
of arrays) to process 0 through the coordination service's key-value store (no pickle). docs/distributed.md has the
commands.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import ipaddress
import sys

import numpy as np

from gpd_jax.cliargs import UsageError

DEFAULT_TIMEOUT_S = 300
GATHER_TIMEOUT_MS = 7 * 24 * 3600 * 1000  # a worker still working is waited for (a dead one fails its heartbeat)
GATHER_CHUNK = 1 << 20  # bytes per key-value entry of a gather


class DistributedError(UsageError):
    """The runtime could not start: wrong coordinator, wrong process count, time-out (one line, exit 2)."""


@dataclasses.dataclass(frozen=True)
class Cluster:
    """How this process joins the others.

    coordinator: "HOST:PORT" of process 0 (None: JAX's cluster detection when `detect`).
    num_processes, process_id: this run's count and this process's id (None with `detect`).
    detect: `jax.distributed.initialize()` with the coordinator from the environment (SLURM, Open MPI, ...).
    timeout_s: how long to wait for every process to join before giving up with an error.
    """

    coordinator: str | None = None
    num_processes: int | None = None
    process_id: int | None = None
    detect: bool = False
    timeout_s: int = DEFAULT_TIMEOUT_S

    @property
    def enabled(self) -> bool:
        return self.detect or self.coordinator is not None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The multi-process flags of every command that can span processes and hosts."""
    g = parser.add_argument_group("several processes or hosts (JAX's multi-controller runtime; docs/distributed.md)")
    g.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="address of process 0, which listens there; every process gives the same")
    g.add_argument("--num-processes", default=None, metavar="N", help="how many processes take part")
    g.add_argument("--process-id", default=None, metavar="I", help="this process's id, 0 ... N-1 (0: the coordinator)")
    g.add_argument("--distributed", action="store_true",
                   help="take the coordinator, count and id from the environment (SLURM, Open MPI, "
                        "JAX_COORDINATOR_ADDRESS ...; jax.distributed.initialize())")
    g.add_argument("--init-timeout", default=str(DEFAULT_TIMEOUT_S), metavar="SECONDS",
                   help=f"give up when not every process has joined after this long (default {DEFAULT_TIMEOUT_S})")


def _int_flag(flag: str, text, low: int) -> int:
    try:
        v = int(text)
    except (TypeError, ValueError):
        raise UsageError(f"{flag} {text!r}: not an integer") from None
    if v < low:
        raise UsageError(f"{flag} {v}: must be >= {low}")
    return v


def parse_coordinator(text: str) -> tuple[str, int]:
    """"HOST:PORT" ("[::1]:PORT" for IPv6) -> (host, port), or UsageError naming --coordinator."""
    host, sep, port = str(text).rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise UsageError(f"--coordinator {text!r}: expected HOST:PORT (a port in 1..65535), e.g. 10.0.0.1:1234")
    return host, int(port)


def from_args(args: argparse.Namespace) -> Cluster:
    """The validated `Cluster` of the parsed flags (`add_arguments`); UsageError naming the flag."""
    timeout = _int_flag("--init-timeout", args.init_timeout, 1)
    explicit = [f for f, v in (("--coordinator", args.coordinator), ("--num-processes", args.num_processes),
                               ("--process-id", args.process_id)) if v is not None]
    if args.distributed and explicit:
        raise UsageError(f"--distributed takes everything from the environment; it cannot be combined with "
                         f"{', '.join(explicit)}")
    if args.distributed:
        return Cluster(detect=True, timeout_s=timeout)
    if not explicit:
        return Cluster(timeout_s=timeout)
    missing = [f for f in ("--coordinator", "--num-processes", "--process-id") if f not in explicit]
    if missing:
        raise UsageError(f"{', '.join(explicit)} given without {', '.join(missing)}: several processes need all "
                         "three (or --distributed for the environment's)")
    parse_coordinator(args.coordinator)
    n = _int_flag("--num-processes", args.num_processes, 1)
    i = _int_flag("--process-id", args.process_id, 0)
    if i >= n:
        raise UsageError(f"--process-id {i}: must be < --num-processes {n}")
    return Cluster(coordinator=str(args.coordinator), num_processes=n, process_id=i, timeout_s=timeout)


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def initialize(cluster: Cluster) -> None:
    """Starts JAX's multi-controller runtime for `cluster` (nothing for a single process without flags). Must run
    before the first JAX computation. Sets JAX's CPU collectives to gloo (cross-process all-reduce on CPU hosts).
    A coordinator that cannot be reached, a process count that is never reached or a port that cannot be bound
    raises `DistributedError` (one line) after at most `cluster.timeout_s` seconds."""
    if not cluster.enabled:
        return
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    kw = {}
    if cluster.coordinator is not None:
        host, port = parse_coordinator(cluster.coordinator)
        kw = dict(coordinator_address=cluster.coordinator, num_processes=cluster.num_processes,
                  process_id=cluster.process_id)
        if _is_loopback(host):  # a loopback coordinator listens on loopback only (one machine, tests)
            kw["coordinator_bind_address"] = cluster.coordinator
    where = (f"coordinator {cluster.coordinator}, {cluster.num_processes} processes, this one "
             f"{cluster.process_id}" if cluster.coordinator else "coordinator from the environment")
    global _STARTING
    _STARTING = True
    try:
        with _reporting_client():
            jax.distributed.initialize(**kw, initialization_timeout=int(cluster.timeout_s),
                                       heartbeat_timeout_seconds=max(10, min(100, int(cluster.timeout_s))),
                                       shutdown_timeout_seconds=max(5, min(60, int(cluster.timeout_s))))
    except Exception as e:  # noqa: BLE001 - XlaRuntimeError (DEADLINE_EXCEEDED, UNAVAILABLE ...), ValueError, ...
        _release()  # now, so that its last log lines come before the error line
        msg = " ".join(str(e).split())
        # jaxlib reports a connect time-out through the error callback, whose status it cannot hand to Python
        cause = "" if "bad_cast" in msg else f" ({type(e).__name__}: {msg[:300]}{'...' if len(msg) > 300 else ''})"
        raise DistributedError(
            f"JAX's multi-process runtime did not start ({where}) within --init-timeout {cluster.timeout_s} s: "
            f"check that every process got the same --coordinator and --num-processes, and that process 0 runs "
            f"and can be reached there{cause}") from None
    finally:
        _STARTING = False


_STARTING = False


def _release() -> None:
    """Shuts down what a failed `jax.distributed.initialize` started (its client, and the coordination service on
    process 0), each part on its own."""
    from jax._src import distributed as jd

    for part in ("preemption_sync_manager", "client", "service"):
        obj = getattr(jd.global_state, part, None)
        if obj is not None:
            try:
                obj.shutdown()
            except Exception:  # noqa: BLE001 - half started: nothing more to release
                pass
            setattr(jd.global_state, part, None)


def _on_runtime_error(status) -> None:
    """JAX's coordination client reports a fatal error (a peer stopped sending heartbeats, the coordinator went
    away). While starting, `initialize` turns the failed connect into a `DistributedError` (its default callback
    would abort the process with a stack trace); later the run cannot go on (its collectives would wait forever):
    one line on stderr and exit status 1. (jaxlib 0.10 cannot convert the status for Python; the call then fails
    in C++ and the process ends as with JAX's default, which is still no hang.)"""
    if _STARTING:
        return
    import os

    print(f"gpd_jax: error: the multi-process run lost a process or its coordinator ({' '.join(str(status).split())});"
          " a training run resumes from its last checkpoint when started again", file=sys.stderr, flush=True)
    os._exit(1)


@contextlib.contextmanager
def _reporting_client():
    """Has `jax.distributed.initialize` create its coordination client with `_on_runtime_error` as the error
    callback (JAX's default aborts the process with a stack trace, even on a connect time-out)."""
    from jax._src import distributed as jd

    lib = jd._jax
    original = lib.get_distributed_runtime_client

    def make(*args, **kw):
        kw.setdefault("missed_heartbeat_callback", _on_runtime_error)
        return original(*args, **kw)

    lib.get_distributed_runtime_client = make
    try:
        yield
    finally:
        lib.get_distributed_runtime_client = original


def is_lead() -> bool:
    """Whether this is process 0 (the one that writes a run's shared outputs)."""
    import jax

    return jax.process_index() == 0


def my_share(items: int) -> list[int]:
    """Indices 0 .. items-1 this process takes: round-robin over the processes (all of them for one process)."""
    import jax

    return list(range(jax.process_index(), items, jax.process_count()))


# ------------------------------------------------------------------------------------------------ gather
def _flatten(tree, prefix: str, out: dict[str, np.ndarray]) -> None:
    if isinstance(tree, dict):
        if not tree:
            out[prefix + "{}"] = np.zeros(0)
        for k, v in tree.items():
            k = str(k)
            if "/" in k or k.endswith("{}"):
                raise ValueError(f"gather: key {k!r} cannot be sent (contains '/')")
            _flatten(v, f"{prefix}{k}/", out)
    else:
        out[prefix.rstrip("/")] = np.asarray(tree)


def _unflatten(flat: dict[str, np.ndarray]) -> dict:
    root: dict = {}
    for path, v in flat.items():
        parts = path.split("/")
        node = root
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        if parts[-1] != "{}":
            node[parts[-1]] = v
    return root


def encode_tree(tree: dict) -> bytes:
    """A nested dict of arrays (numbers, strings; no objects) as .npz bytes."""
    flat: dict[str, np.ndarray] = {}
    _flatten(tree, "", flat)
    buf = io.BytesIO()
    np.savez(buf, **flat)
    return buf.getvalue()


def decode_tree(data: bytes) -> dict:
    """`encode_tree`'s bytes back as nested dicts of numpy arrays (never unpickles)."""
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return _unflatten({k: z[k] for k in z.files})


def _client():
    from jax._src import distributed as jd

    client = jd.global_state.client
    if client is None:
        raise RuntimeError("gather: JAX's multi-process runtime is not initialized")
    return client


_GATHERS = 0


def gather_to_lead(tag: str, tree: dict) -> list[dict] | None:
    """Every process's `tree` (nested dicts of arrays), in process order, on process 0; None on the others.

    One process: `[tree]` without a round trip. Every process makes the same calls in the same order (`tag` names
    the call in the key-value store, beside a running count)."""
    import jax

    global _GATHERS
    if jax.process_count() == 1:
        return [tree]
    _GATHERS += 1
    client, me = _client(), jax.process_index()
    key = f"gpd_jax/gather/{_GATHERS}/{tag}"
    if me != 0:  # in chunks: the coordination service's messages are kept small
        data = encode_tree(tree)
        chunks = [data[i:i + GATHER_CHUNK] for i in range(0, len(data), GATHER_CHUNK)] or [b""]
        for i, c in enumerate(chunks):
            client.key_value_set_bytes(f"{key}/{me}/{i}", c)
        client.key_value_set(f"{key}/{me}/chunks", str(len(chunks)))
        return None
    out = [tree]
    for p in range(1, jax.process_count()):
        n = int(client.blocking_key_value_get(f"{key}/{p}/chunks", GATHER_TIMEOUT_MS))
        parts = [client.blocking_key_value_get_bytes(f"{key}/{p}/{i}", GATHER_TIMEOUT_MS) for i in range(n)]
        out.append(decode_tree(b"".join(parts)))
        for i in range(n):
            client.key_value_delete(f"{key}/{p}/{i}")
    return out


__all__ = ["Cluster", "DistributedError", "add_arguments", "from_args", "initialize", "is_lead", "my_share",
           "gather_to_lead", "encode_tree", "decode_tree", "parse_coordinator"]
