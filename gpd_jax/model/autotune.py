"""Choosing the decode attention path by measurement: what `attend_dynamic(..., kernel="auto")` runs.

The decode attention of the KV-cached rollout (`gpd_jax.model.attention.attend_dynamic`) has several paths with
the same results: `"native"` (the fused CPU kernel of `gpd_jax.model.native`), `"xla"` (under
`vmap`, the scenarios one after another), `"xla_batched"` (every scenario's chunk at once) and `"cudnn"` (cuDNN's
fused attention, bfloat16 on a GPU). Which is fastest
depends on the machine, the backend, the shape and the batch, so "auto" measures: the first time a shape is
traced, a few calls of each candidate (`candidates()`: the native kernel on a CPU where it builds, the two XLA
rules where the batch is above 1) at that shape (batch, heads, queries, cache length, head size, devices running
it side by side) are timed outside the traced computation (in a separate thread, so no enclosing trace stages
them) and the fastest is used. The choice is kept per process and on disk (`native.cache_dir()/decode-attention/`,
keyed by CPU, backend, JAX version, kernel build, shapes, batch bucket and candidates; written atomically), so a
machine measures each shape once. `GPD_JAX_DECODE_ATTENTION=native|xla|xla_batched` (`FORCE_ENV`) forces the
choice; `GPD_JAX_NATIVE=0` (or no C++ compiler) leaves only the XLA paths; `auto_choices()` says what was chosen
and why.

This module computes no attention itself: the caller passes `kernel_for(kind, tokens_per_frame, chunk_len)`, which
returns path `kind`'s attention of one scenario, `f(q, k, v, q_frame, num_chunks)` (vmappable; q pre-scaled), and
`dispatch` / `choose` measure and run those. So `attention` imports this module, never the reverse.

Public names: `FORCE_ENV`, `forced()`, `candidates(batch, f32)`, `choose(...)`, `choice_path(key)`,
`auto_choices()`, `dispatch(...)`, `batch_size(x)`.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import tempfile
import threading
import time
from typing import Callable

import jax
import numpy as np

from gpd_jax.model import native

FORCE_ENV = "GPD_JAX_DECODE_ATTENTION"
PATHS = ("native", "xla", "xla_batched", "cudnn")  # what "auto" may choose

# kernel_for(kind, tokens_per_frame, chunk_len) -> f(q, k, v, q_frame, num_chunks): one scenario's attention
KernelFor = Callable[[str, int, int], Callable]

_choice_lock = threading.Lock()
_choices: dict = {}      # key digest -> record (measured or read from disk at most once per process)
_choice_log: list = []   # every lookup of this process, in order (what auto_choices() reports)


def forced() -> str | None:
    """The path `FORCE_ENV` forces "auto" to (None where unset or "auto"); a ValueError for an unknown one."""
    value = os.environ.get(FORCE_ENV, "").strip().lower()
    if value in ("", "auto"):
        return None
    if value not in PATHS:
        raise ValueError(f"{FORCE_ENV}={value!r}: expected one of {', '.join(PATHS)} or auto")
    return value


def candidates(batch: int, f32: bool = True) -> list[str]:
    """The decode attention paths "auto" chooses among at this batch (`f32`: a float32 cache, else bfloat16):
    "native" on a CPU where the kernel builds, "xla", "xla_batched" where a batch makes its batching rule differ
    from "xla"'s, and "cudnn" on a GPU for bfloat16 (a candidate that fails to compile there is dropped when
    measured)."""
    out = ["native"] if jax.default_backend() == "cpu" and native.available() else []
    out += ["xla", "xla_batched"] if batch > 1 else ["xla"]
    return out + (["cudnn"] if not f32 and jax.default_backend() == "gpu" else [])


# ----------------------------------------------------------------------------------------------------------
# the choice: key, on-disk cache, lookup


def _bucket(batch: int) -> int:
    """Batch bucket of a choice: the next power of two."""
    return 1 << max(0, int(batch) - 1).bit_length()


def _concurrent_devices() -> int:
    """How many devices run this computation side by side (the manual axes of an enclosing shard_map)."""
    try:
        mesh = jax.sharding.get_abstract_mesh()
    except Exception:  # noqa: BLE001
        return 1
    if mesh is None or getattr(mesh, "empty", True):
        return 1
    manual = set(getattr(mesh, "manual_axes", ()) or ())
    sizes = dict(zip(mesh.axis_names, mesh.axis_sizes))
    n = 1
    for name in manual:
        n *= int(sizes.get(name, 1))
    return n


def _choice_key(batch, h, sq, s, dh, n, c, ndev, kinds, f32=True) -> dict:
    build = native.build_info() or {}
    return {"cpu": hashlib.sha256(native._cpu_id().encode()).hexdigest()[:12], "jax": jax.__version__,
            "backend": jax.default_backend(), "device": jax.devices()[0].device_kind,
            "dtype": "float32" if f32 else "bfloat16", "kernel_build": build.get("key"), "march": build.get("target"),
            "batch_bucket": _bucket(batch), "heads": h, "queries": sq, "cache_len": s, "head_dim": dh,
            "tokens_per_frame": n, "chunk_len": c, "devices": ndev, "candidates": list(kinds)}


def choice_path(key: dict):
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:20]
    return native.cache_dir() / "decode-attention" / f"{digest}.json"


def _write_atomic(path, record: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".json", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(record, f, indent=1, sort_keys=True)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def _read(path, key) -> dict | None:
    try:
        with open(path) as f:
            rec = json.load(f)
    except (OSError, ValueError):
        return None
    if rec.get("key") != key or rec.get("choice") not in key["candidates"]:
        return None
    return rec


def choose(batch: int, h: int, sq: int, s: int, dh: int, n: int, c: int, ndev: int = 1, f32: bool = True, *,
           kernel_for: KernelFor) -> dict:
    """The "auto" choice for one shape: {"choice": one of `candidates()`, "why", "source", "times_ms", ...}.

    Looked up in this process, then on disk; otherwise every candidate (`kernel_for(kind, n, c)`) is timed (in a
    separate thread, so that no enclosing trace stages the measurement) and the result is written atomically
    (temp file + rename)."""
    forced_kind = forced()
    if forced_kind is not None:
        rec = {"choice": forced_kind, "source": "forced", "why": f"{FORCE_ENV}={forced_kind}"}
        _choice_log.append(rec)
        return rec
    kinds = candidates(batch, f32)
    if len(kinds) == 1:
        why = ("GPD_JAX_NATIVE=0" if native.disabled() else
               "the backend is not a CPU" if jax.default_backend() != "cpu" else "the native kernel did not build")
        rec = {"choice": kinds[0], "source": "only candidate", "why": why}
        _choice_log.append(rec)
        return rec
    key = _choice_key(batch, h, sq, s, dh, n, c, ndev, kinds, f32)
    digest = json.dumps(key, sort_keys=True)
    with _choice_lock:
        rec = _choices.get(digest)
        if rec is None:
            path = choice_path(key)
            rec = _read(path, key)
            if rec is None:
                times = _measure_in_thread(batch, h, sq, s, dh, n, c, ndev, tuple(kinds), f32,
                                           kernel_for=kernel_for)
                best = min(times, key=times.get)
                others = ", ".join(f"{k} {t * 1e3:.2f} ms ({t / times[best]:.2f}x)" for k, t in
                                   sorted(times.items(), key=lambda kv: kv[1]) if k != best)
                rec = {"key": key, "choice": best, "times_ms": {k: round(t * 1e3, 3) for k, t in times.items()},
                       "measured_batch": batch, "measured_at": time.strftime("%Y-%m-%dT%H:%M:%S"),
                       "why": f"{best} {times[best] * 1e3:.2f} ms vs {others} per call at batch {batch}"}
                try:
                    _write_atomic(path, rec)
                except OSError:
                    pass  # a read-only cache: the choice still holds for this process
                rec = dict(rec, source="measured", path=str(path))
            else:
                rec = dict(rec, source="cached", path=str(path))
            _choices[digest] = rec
    _choice_log.append(rec)
    return rec


def auto_choices() -> list[dict]:
    """The "auto" decisions of this process, one per distinct shape, in the order first made."""
    seen, out = set(), []
    for rec in _choice_log:
        tag = json.dumps({k: rec.get(k) for k in ("key", "choice", "source", "why")}, sort_keys=True, default=str)
        if tag not in seen:
            seen.add(tag)
            out.append(rec)
    return out


# ----------------------------------------------------------------------------------------------------------
# measurement


def _measure_in_thread(*args, **kwargs) -> dict:
    box = {}

    def work():
        try:
            box["times"] = _measure(*args, **kwargs)
        except BaseException as e:  # noqa: BLE001 - re-raised in the tracing thread
            box["error"] = e

    t = threading.Thread(target=work, name="gpd-attention-auto", daemon=True)
    t.start()
    t.join()
    if "error" in box:
        raise box["error"]
    return box["times"]


def _measure(batch, h, sq, s, dh, n, c, ndev, kinds=("native", "xla"), f32=True, *, kernel_for: KernelFor,
             budget_s: float = 0.25, max_repeats: int = 7) -> dict:
    """Seconds per call (the fastest of a few) of each path in `kinds` on random data of this shape (float32, or
    bfloat16 where not `f32`), with the cache filled to about 60 % and the queries in the frames just before the
    filled end (a mid-rollout step). A candidate after the first that fails to compile (a cuDNN without this
    shape) is left out."""
    devices = jax.devices()[:ndev]
    total = batch * len(devices)
    rng = np.random.default_rng(0)
    dtype = np.float32 if f32 else jax.numpy.bfloat16
    q = (rng.standard_normal((total, h, sq, dh), np.float32) * dh**-0.5).astype(dtype)
    kk = rng.standard_normal((total, h, s, dh), np.float32).astype(dtype)
    vv = rng.standard_normal((total, h, s, dh), np.float32).astype(dtype)
    chunks = max(1, round(0.6 * (s // c)))
    end_frame = max(1, (chunks * c) // n)  # frames [0, end_frame) are filled
    q_frame = np.maximum(0, end_frame - max(1, sq // n) + np.arange(sq) // n).astype(np.int32)
    nc = np.full((total,), chunks, np.int32)

    def make(kind):
        f = jax.vmap(kernel_for(kind, n, c), in_axes=(0, 0, 0, None, 0))
        if len(devices) > 1:
            from jax.sharding import Mesh, PartitionSpec as P

            mesh = Mesh(np.array(devices), ("data",))
            f = jax.shard_map(f, mesh=mesh, in_specs=(P("data"), P("data"), P("data"), P(), P("data")),
                              out_specs=P("data"), check_vma=False)
        return jax.jit(f)

    args = [jax.device_put(x) for x in (q, kk, vv, q_frame, nc)]
    if len(devices) > 1:
        from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

        mesh = Mesh(np.array(devices), ("data",))
        args = [jax.device_put(x, NamedSharding(mesh, P() if i == 3 else P("data"))) for i, x in enumerate(args)]
    fns = {}
    for i, kind in enumerate(kinds):
        try:
            fns[kind] = make(kind).lower(*args).compile()
        except Exception:  # noqa: BLE001 - an optional path this backend cannot compile at this shape
            if i == 0:
                raise
    if len(fns) == 1:
        t0 = time.perf_counter()
        jax.block_until_ready(next(iter(fns.values()))(*args))
        return {next(iter(fns)): time.perf_counter() - t0}
    best = {}
    spent, rounds = 0.0, 0
    # Rounds alternate the candidates, so a change of load hits them all. The first call of each is already a
    # timing (compiled ahead). Stop early once the budget is spent or the runner-up is clearly (2x) slower: a
    # prefill-sized call can take seconds, a decode step milliseconds.
    while True:
        for kind, f in fns.items():
            t0 = time.perf_counter()
            jax.block_until_ready(f(*args))
            dt = time.perf_counter() - t0
            spent += dt
            best[kind] = min(best.get(kind, dt), dt)
        rounds += 1
        ranked = sorted(best.values())
        clear = ranked[1] > 2 * ranked[0]  # the runner-up is 2x slower: the choice is made
        if (rounds >= max_repeats or (rounds >= 2 and (clear or spent > budget_s))
                or (clear and spent > 4 * budget_s)):
            return best


# ----------------------------------------------------------------------------------------------------------
# "auto" dispatch: decide while tracing, run the chosen path


def batch_size(x) -> int:
    """The product of the `vmap` batch sizes around a traced array (1 outside vmap). Reads JAX's batching
    tracers; if their layout ever changes this degrades to 1 (a choice measured at batch 1), never an error."""
    try:
        from jax._src.interpreters import batching

        size = 1
        while isinstance(x, batching.BatchTracer):
            if isinstance(x.batch_dim, int):  # not "not mapped"
                size *= int(x.val.shape[x.batch_dim])
            x = x.val
        return size
    except Exception:  # noqa: BLE001
        return 1


def dispatch(q, k, v, q_frame, num_chunks, n: int, c: int, f32: bool = True, *, kernel_for: KernelFor):
    """attend_dynamic's "auto" path (q pre-scaled): decides while tracing, where shapes and the vmap batch are
    known, and runs `kernel_for(choice, n, c)`.

    Directly under `vmap` the batch is read from the tracers. Inside a `lax.scan` body (the rollout's decode
    step) the body is traced unbatched and batched afterwards, so the batch is only known to a batching rule:
    there a `custom_vmap` decides again at the real batch (the unbatched trace also makes a batch-1 choice,
    which is what runs when nothing batches it)."""
    h, sq, dh = q.shape[-3:]
    batch = max(batch_size(q), batch_size(k))
    if batch > 1:
        choice = choose(batch, h, sq, k.shape[-2], dh, n, c, _concurrent_devices(), f32, kernel_for=kernel_for)
        return _run(kernel_for(choice["choice"], n, c), None, q, k, v, q_frame, num_chunks)
    return _auto_kernel(n, c, f32, kernel_for)(q, k, v, q_frame, num_chunks)


def _run(one, in_axes, q, k, v, q_frame, num_chunks):
    if in_axes is None:
        return one(q, k, v, q_frame, num_chunks)
    return jax.vmap(one, in_axes=in_axes)(q, k, v, q_frame, num_chunks)


@functools.lru_cache(maxsize=None)
def _auto_kernel(n: int, c: int, f32: bool, kernel_for: KernelFor):
    def decide(batch, q, k):
        h, sq, dh = q.shape[-3:]
        kind = choose(batch, h, sq, k.shape[-2], dh, n, c, _concurrent_devices(), f32, kernel_for=kernel_for)
        return kernel_for(kind["choice"], n, c)

    def one(q, k, v, q_frame, num_chunks):
        return _run(decide(1, q, k), None, q, k, v, q_frame, num_chunks)

    kernel = jax.custom_batching.custom_vmap(one)

    @kernel.def_vmap
    def _batched(axis_size, in_batched, q, k, v, q_frame, num_chunks):
        in_axes = tuple(0 if b else None for b in in_batched)
        return _run(decide(axis_size, q, k), in_axes, q, k, v, q_frame, num_chunks), True

    return kernel
