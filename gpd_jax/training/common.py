"""What both training stages share: the orbax checkpoint manager of a workdir, restoring a train state into its
template's structure, the JSON-lines metrics log, a clean stop on SIGTERM, and what `train.py` needs to load a config
file or say in one line why it cannot (`load_training_config`) and to list the config files (`config_summaries`), and
compiled steps shared by runs of one model and config (`compiled_once`)."""

from __future__ import annotations

import ast
import collections
import json
import math
import os
import signal
import time
import traceback
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import ml_collections
import numpy as np

from gpd_jax.config import load_config
from gpd_jax.fsutil import orbax_manager

if TYPE_CHECKING:  # annotations only: orbax is imported where it is used
    import orbax.checkpoint as ocp


def graft_params(template, source, fresh) -> tuple[Any, list[str]]:
    """`template` (a params tree) with every leaf taken from `source` (a params tree of another model) at the same
    path and shape, except where `fresh(path)` (a jax key path) says the leaf stays as initialised. Returns (tree, the key
    strings of the other leaves `source` lacks)."""
    import jax  # JAX and orbax are imported where used: `train.py` loads and checks its config without them

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
    import orbax.checkpoint as ocp

    mgr.save(step, args=ocp.args.StandardSave(tree), force=force)


def restore_state(mgr: ocp.CheckpointManager, template: dict, step: int | None = None) -> dict:
    """The checkpoint at `step` (latest by default) in the structure of `template` (a dict tree of the train
    state; optax states are namedtuples there and plain dicts in the checkpoint)."""
    import jax
    import orbax.checkpoint as ocp

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
        import jax

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
        import jax

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


class ConfigLoadError(ValueError):
    """A config file that cannot be loaded, or an override that does not apply to it; the message is one line that
    names the file or the override and what is wrong."""


def error_message(e: BaseException) -> str:
    """`str(e)` without the quotes KeyError adds around its message."""
    if isinstance(e, KeyError) and len(e.args) == 1 and isinstance(e.args[0], str):
        return e.args[0]
    return str(e)


def load_training_config(path: str, overrides: Sequence[str] = ()):
    """`gpd_jax.config.load_config(path, overrides)`, every failure turned into a `ConfigLoadError` with a one-line
    message: a missing file, an unknown field or a value of the wrong type in an override, a syntax error in the
    file, a file without get_config(), or an exception raised by the file's own code (located at its line)."""
    try:
        return load_config(path, overrides)
    except Exception as e:  # noqa: BLE001 - whatever a config file's code raises; rephrased below
        raise ConfigLoadError(_config_error(e, path)) from e


def _config_error(e: Exception, path: str) -> str:
    msg = " ".join(error_message(e).split())  # one line
    if isinstance(e, SyntaxError):
        return f"{e.filename or path}:{e.lineno}: {type(e).__name__}: {e.msg}"
    config_file = os.path.abspath(path.rsplit(":", 1)[0] if not os.path.isfile(path) and ":" in path else path)
    frames = traceback.extract_tb(e.__traceback__)
    in_file = [f for f in frames if os.path.abspath(f.filename) == config_file]
    located = f"{in_file[-1].filename}:{in_file[-1].lineno}: {type(e).__name__}: {msg}" if in_file else ""
    if in_file and in_file[-1] is frames[-1]:  # raised by the config file's own code
        return located
    if isinstance(e, (KeyError, ValueError, FileNotFoundError)):  # the library's messages name file / override
        return msg
    if located:  # raised in something the config file calls
        return located
    if os.path.isfile(config_file) and not config_file.endswith(".py"):
        return f"{path}: not a python config file (expected a configs/*.py file that defines get_config())"
    return f"{path}: cannot load the config ({type(e).__name__}: {msg})"


def config_summaries(configs_dir: str) -> list[tuple[str, str]] | None:
    """(file name, first line of its docstring) of every `configs_dir/*.py`, by name; None when the folder does not
    exist. The files are parsed, not run."""
    if not os.path.isdir(configs_dir):
        return None
    out = []
    for name in sorted(os.listdir(configs_dir)):
        if not name.endswith(".py") or name.startswith(("_", ".")):
            continue
        try:
            with open(os.path.join(configs_dir, name), encoding="utf-8") as f:
                doc = ast.get_docstring(ast.parse(f.read(), name)) or ""
            first = doc.strip().splitlines()[0] if doc.strip() else "(no docstring)"
        except (OSError, SyntaxError, ValueError) as e:
            first = f"(unreadable: {type(e).__name__})"
        out.append((name, first))
    return out


# What a compiled train or eval step never reads: the run's bookkeeping and where its data are. Two runs whose
# configs differ only here (a resumed run, a second run in the same process) share their compiled steps.
RUN_FIELDS = {"data": ("dir", "val_dir", "eval_dir", "num_workers", "processes"),
              "train": ("log_every", "eval_every", "eval_batches", "eval_rollout_scenarios", "checkpoint_every",
                        "keep_checkpoints", "loader_threads", "init_from", "best_metric", "eval_at_start")}
_COMPILED: "collections.OrderedDict[tuple, Any]" = collections.OrderedDict()


def step_key(config: ml_collections.ConfigDict) -> str:
    """The config as sorted JSON without its `RUN_FIELDS`: what a compiled step may depend on."""
    d = json.loads(config.to_json())
    for section, fields in RUN_FIELDS.items():
        for f in fields:
            d.get(section, {}).pop(f, None)
    return json.dumps(d, sort_keys=True)


def compiled_once(key: tuple, build: Callable[[], Any], keep: int = 4) -> Any:
    """`build()` (compiled step functions) the first time `key` is asked for and the same object afterwards (the
    last `keep` keys are kept): the steps must close over nothing but what `key` names (pass arrays such as a
    frozen codebook as arguments)."""
    if key not in _COMPILED:
        _COMPILED[key] = build()
        while len(_COMPILED) > keep:
            _COMPILED.popitem(last=False)
    _COMPILED.move_to_end(key)
    return _COMPILED[key]
