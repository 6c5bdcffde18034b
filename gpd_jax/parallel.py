"""Data parallelism over local devices with `jax.sharding` (CPU cores, GPUs, or several hosts).

On a CPU, XLA runs each fusion of one computation on one thread, so a memory-bound batched rollout uses a
single core. Exposing the cores as separate XLA host devices (`--xla_force_host_platform_device_count`)
and sharding the batch over a 1-D `data` mesh runs one slice of the batch per core. Several hosts:
start JAX's multi-controller runtime first (`gpd_jax.distributed.initialize`); `data_mesh` then spans every
process's devices (training: one global batch), `data_mesh(local=True)` this process's (evaluation: each process
rolls out its own share of the scenes).
"""

from __future__ import annotations

import os

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

_FLAG = "--xla_force_host_platform_device_count"


def use_host_cores(count: int | None = None) -> bool:
    """Asks XLA to expose `count` (default: all cores) CPU devices. Must run before the first JAX
    computation; does nothing (and returns False) if XLA_FLAGS already sets a count or JAX is running."""
    flags = os.environ.get("XLA_FLAGS", "")
    if _FLAG in flags:
        return False
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        return False
    count = count or os.cpu_count() or 1
    os.environ["XLA_FLAGS"] = f"{flags} {_FLAG}={count}".strip()
    return True


def data_mesh(num_devices: int | None = None, local: bool = False) -> Mesh:
    """A 1-D mesh named `data` over the first `num_devices` devices (default: all, every process's; `local`:
    this process's own, for work that each process does alone, such as its share of an evaluation)."""
    devices = jax.local_devices() if local else jax.devices()
    if num_devices is not None:
        if num_devices > len(devices):
            raise ValueError(f"asked for {num_devices} devices, only {len(devices)} available")
        devices = devices[:num_devices]
    return Mesh(np.array(devices), ("data",))


def shard_batch(tree, mesh: Mesh):
    """Places every leaf with its leading (batch) dim split over the mesh's `data` axis."""
    n = mesh.devices.size

    def put(x):
        x = np.asarray(x) if not isinstance(x, jax.Array) else x
        if x.ndim == 0 or x.shape[0] % n:
            raise ValueError(f"batch dim of shape {x.shape} is not divisible by {n} devices")
        return jax.device_put(x, NamedSharding(mesh, PartitionSpec("data")))

    return jax.tree.map(put, tree)


def replicate(tree, mesh: Mesh):
    """Places every leaf whole on every device of the mesh (parameters, a train state), from this process's copy
    (each process of a multi-process mesh holds the same values): the leaves go through host memory, so arrays
    already on one local device (a restored checkpoint) need no cross-host transfer."""
    return jax.device_put(jax.device_get(tree), NamedSharding(mesh, PartitionSpec()))


def data_parallel(fn, mesh: Mesh, num_replicated: int = 1):
    """`fn(*replicated, *batched)` run on every device with its own slice of the batch (`shard_map`).

    The first `num_replicated` arguments (parameters) are whole on every device; the rest and every output
    are split along their leading dim. Each device runs the plain single-device program on its slice, so
    batch-indexed loops inside `fn` (such as the attention kernel's per-scenario rule) stay local instead
    of making the partitioner gather whole arrays.
    """

    def wrapped(*args):
        specs = tuple(PartitionSpec() if i < num_replicated else PartitionSpec("data") for i in range(len(args)))
        return jax.shard_map(fn, mesh=mesh, in_specs=specs, out_specs=PartitionSpec("data"), check_vma=False)(*args)

    return wrapped


def devices_for_batch(batch: int, available: int) -> int:
    """The largest device count <= available that divides the batch."""
    return max(d for d in range(1, available + 1) if batch % d == 0)
