"""What both training stages share: the orbax checkpoint manager of a workdir, restoring a train state into its
template's structure, the JSON-lines metrics log, and a clean stop on SIGTERM."""

from __future__ import annotations

import json
import math
import os
import signal
import time
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp

from gpd_jax.fsutil import orbax_manager


def graft_params(template, source, fresh) -> tuple[Any, list[str]]:
    """`template` (a params tree) with every leaf taken from `source` (a params tree of another model) at the same
    path and shape, except where `fresh(path)` (a jax key path) says the leaf stays as initialised. Returns (tree, the key
    strings of the other leaves `source` lacks)."""
    flat = {jax.tree_util.keystr(p): x for p, x in jax.tree_util.tree_leaves_with_path(source)}
    missing = []

    def take(p, x):
        if fresh(p):
            return x
        k = jax.tree_util.keystr(p)
        if k not in flat or flat[k].shape != x.shape:
            missing.append(k)
            return x
        return jax.numpy.asarray(flat[k], x.dtype)

    return jax.tree_util.tree_map_with_path(take, template), missing


def checkpoint_manager(workdir: str, keep: int = 2) -> ocp.CheckpointManager:
    """The workdir's CheckpointManager (`WORKDIR/checkpoints`, the `keep` latest steps kept)."""
    return orbax_manager(workdir, keep=keep)


def save_state(mgr: ocp.CheckpointManager, step: int, tree: dict, force: bool = False) -> None:
    """Saves a train state (a dict tree) as step `step` (`force`: even off the manager's save interval)."""
    mgr.save(step, args=ocp.args.StandardSave(tree), force=force)


def restore_state(mgr: ocp.CheckpointManager, template: dict, step: int | None = None) -> dict:
    """The checkpoint at `step` (latest by default) in the structure of `template` (a dict tree of the train
    state; optax states are namedtuples there and plain dicts in the checkpoint)."""
    step = mgr.latest_step() if step is None else step
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, template)
    tree = mgr.restore(step, args=ocp.args.StandardRestore(abstract))
    return jax.tree.unflatten(jax.tree.structure(template), jax.tree.leaves(tree))


class MetricsLog:
    """Appends JSON records to WORKDIR/metrics.jsonl (NaN written as null) and, when tensorboardX is installed
    and `tensorboard` is set, scalars to WORKDIR/tensorboard."""

    def __init__(self, workdir: str, enabled: bool = True, tensorboard: bool = True):
        self.path = os.path.join(workdir, "metrics.jsonl")
        self.enabled = enabled
        self.tb = None
        if enabled and tensorboard:
            try:
                from tensorboardX import SummaryWriter

                self.tb = SummaryWriter(os.path.join(workdir, "tensorboard"))
            except ImportError:
                pass

    def record(self, rec: dict[str, Any]) -> dict[str, Any]:
        """Appends one record as it is (numbers as floats, non-finite as null); returns what was written."""
        out = {}
        for k, v in rec.items():
            if isinstance(v, (np.floating, np.integer, jax.Array)):
                v = float(v)
            out[k] = None if isinstance(v, float) and not math.isfinite(v) else v
        if self.enabled:
            with open(self.path, "a") as f:
                f.write(json.dumps(out) + "\n")
        return out

    def write(self, step: int, split: str, values: dict[str, Any]) -> None:
        """A record of `values` at `step` for `split` (with the wall time), also sent to TensorBoard."""
        vals = {k: float(v) if isinstance(v, (int, float, np.number, jax.Array)) else v for k, v in values.items()}
        rec = self.record({"step": int(step), "split": split, "time": time.time(), **vals})
        if self.enabled and self.tb is not None:
            for k, v in rec.items():
                if isinstance(v, float):
                    self.tb.add_scalar(f"{split}/{k}", v, step)
            self.tb.flush()


class StopOnSigterm:
    """Turns SIGTERM into a clean stop (checkpoint, then exit) like Ctrl-C: `requested` becomes True."""

    def __init__(self):
        self.requested = False
        self._old = None

    def __enter__(self):
        try:
            self._old = signal.signal(signal.SIGTERM, self._handler)
        except ValueError:  # not the main thread
            self._old = None
        return self

    def _handler(self, signum, frame):
        self.requested = True

    def __exit__(self, *exc):
        if self._old is not None:
            signal.signal(signal.SIGTERM, self._old)
        return False
