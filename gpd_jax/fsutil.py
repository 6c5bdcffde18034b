"""Files on disk: atomic writes, umask modes, directory swaps, and parameter (de)serialisation.

Every writer in gpd_jax (data stores, model and tokenizer exports, evaluation outputs, benchmark JSON, pictures,
the native kernel's cache) writes to a temporary beside its target and renames it into place, so a reader sees
the old file or the new one, never a half-written one, and an interrupted run loses nothing already written:

    with atomic_path("out/metrics.json") as tmp: write(tmp)      # any writer that takes a path
    with atomic_file("out/tables.txt") as f: f.write(text)       # a file object
    atomic_write_json("out/metrics.json", obj)

Parameters are stored as `.npz` archives keyed by their pytree path (`flatten_params` / `unflatten_params`),
and training workdirs as orbax checkpoints whose parameters `restore_params` reads back without needing the
optimizer that wrote them.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from typing import Any

import numpy as np


def umask_mode(path: str, directory: bool = False) -> None:
    """Gives a temporary from `tempfile.mkstemp`/`mkdtemp` (private: 0600/0700) the mode a plain open/makedirs
    would have, before it is renamed into place, so that what gpd_jax writes can be read by the other users the
    umask allows."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, (0o777 if directory else 0o666) & ~umask)


@contextlib.contextmanager
def atomic_directory(out_dir: str) -> Iterator[str]:
    """Yields a fresh temporary directory beside `out_dir` to write an export into; on success it becomes
    `out_dir` (`swap_in_directory`: files of an existing `out_dir` the export does not write are kept), on an
    exception it is removed and `out_dir` is untouched."""
    out_dir = os.path.abspath(out_dir)
    parent = os.path.dirname(out_dir)
    os.makedirs(parent, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=".export-", dir=parent)
    umask_mode(tmp, directory=True)  # mkdtemp makes it private; an export is meant to be shared
    try:
        yield tmp
        swap_in_directory(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def swap_in_directory(tmp: str, out_dir: str) -> None:
    """Moves the freshly written directory `tmp` to `out_dir` in one rename, so readers see either the old
    export or the new one, never a mixture of their files.

    Entries of an existing `out_dir` that `tmp` does not contain (a README, evaluation files, pictures written
    beside an export) are copied into `tmp` first and so survive; the ones `tmp` writes are replaced.
    `tmp` must be on the same file system as `out_dir` (make it in the same parent directory).
    """
    if not os.path.exists(out_dir):
        os.replace(tmp, out_dir)
        return
    for name in os.listdir(out_dir):
        src, dst = os.path.join(out_dir, name), os.path.join(tmp, name)
        if os.path.lexists(dst):
            continue
        if os.path.isdir(src) and not os.path.islink(src):
            shutil.copytree(src, dst, symlinks=True)
        else:
            shutil.copy2(src, dst, follow_symlinks=False)
    old = out_dir + ".old"
    shutil.rmtree(old, ignore_errors=True)
    os.replace(out_dir, old)
    os.replace(tmp, out_dir)
    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_path(path: str, suffix: str = "") -> Iterator[str]:
    """Yields a temporary path beside `path` to write to; on success it gets the umask's mode and is renamed to
    `path`, on an exception it is removed and `path` is untouched. Parent directories are created."""
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=d, prefix=".tmp-", suffix=suffix or "-" + os.path.basename(path))
    os.close(fd)
    try:
        yield tmp
        umask_mode(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


@contextlib.contextmanager
def atomic_file(path: str, mode: str = "w") -> Iterator[Any]:
    """`atomic_path` as an open file object (`mode` "w" or "wb")."""
    with atomic_path(path) as tmp, open(tmp, mode) as f:
        yield f


def atomic_write_text(path: str, text: str) -> None:
    with atomic_file(path) as f:
        f.write(text)


def atomic_write_json(path: str, obj: Any, indent: int | None = 1, **kw) -> None:
    with atomic_file(path) as f:
        json.dump(obj, f, indent=indent, **kw)


# ----------------------------------------------------------------------------------------------- parameters
def _path_key(path) -> str:
    return "/".join(str(getattr(p, "key", getattr(p, "name", getattr(p, "idx", p)))) for p in path)


def flatten_params(params) -> dict[str, np.ndarray]:
    """{path: array} of a params pytree (the keys of `params.npz`, for GPD and map-tokenizer exports)."""
    import jax  # here, not at the top: the command lines import this module before they check their arguments

    return {_path_key(p): np.asarray(x) for p, x in jax.tree_util.tree_leaves_with_path(params)}


def unflatten_params(template, flat: dict[str, np.ndarray], where: str = "params"):
    """Fills `template` (a params pytree; leaves may be abstract) from `flatten_params` output, checking names
    and shapes and casting to the template's dtypes (float16 exports come back as float32)."""
    import jax

    missing, bad = [], []

    def fill(path, x):
        k = _path_key(path)
        if k not in flat:
            missing.append(k)
            return x
        v = np.asarray(flat[k])
        if v.shape != x.shape:
            bad.append(f"{k}: stored {v.shape}, model {x.shape}")
            return x
        return jax.numpy.asarray(v, x.dtype)

    out = jax.tree_util.tree_map_with_path(fill, template)
    extra = sorted(set(flat) - {_path_key(p) for p, _ in jax.tree_util.tree_leaves_with_path(template)})
    if missing or bad or extra:
        parts = [f"{name} {len(keys)} ({', '.join(keys[:5])}{', ...' if len(keys) > 5 else ''})"
                 for name, keys in (("missing", missing), ("wrong shapes", bad), ("unexpected", extra)) if keys]
        raise ValueError(f"{where} does not match the model of its config: {'; '.join(parts)}")
    return out


def read_params_npz(path: str) -> dict[str, np.ndarray]:
    """{key: array} of a `params.npz`, read without executing anything in it (no pickles).

    Raises FileNotFoundError when `path` does not exist and ValueError naming `path` and the reason when it is not
    a readable archive of numeric arrays (an empty or truncated download, a `.npy` file, object arrays, ...)."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: file not found")

    def unreadable(reason: str) -> ValueError:
        return ValueError(f"{path}: not a readable parameter archive ({reason}); re-export or re-download it")

    if os.path.isfile(path) and os.path.getsize(path) == 0:
        raise unreadable("the file is empty")
    try:
        z = np.load(path, allow_pickle=False)
    except Exception as e:  # noqa: BLE001 - whatever numpy/zipfile/zlib/the OS raise on a damaged file
        raise unreadable(str(e) or type(e).__name__) from e
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise unreadable("a single array, not an .npz archive of named arrays")
    try:
        with z:
            flat = {k: z[k] for k in z.files}
    except Exception as e:  # noqa: BLE001
        raise unreadable(str(e) or type(e).__name__) from e
    odd = sorted(k for k, v in flat.items() if v.dtype.kind not in "biuf")
    if odd:
        raise unreadable(f"{len(odd)} arrays are not numeric, e.g. {odd[0]} of dtype {flat[odd[0]].dtype}")
    return flat


def load_params_npz(path: str, template):
    """The params of an exported `params.npz` in `template`'s structure and dtypes (see `unflatten_params`).
    Raises FileNotFoundError / ValueError naming `path` (see `read_params_npz`)."""
    return unflatten_params(template, read_params_npz(path), where=os.fspath(path))


def save_params_npz(path: str, params, cast=lambda key, a: a, compressed: bool = False) -> None:
    """Writes `flatten_params(params)` to `path` atomically; `cast(key, array)` may change each array's dtype."""
    flat = {k: cast(k, v) for k, v in flatten_params(params).items()}
    with atomic_file(path, "wb") as f:
        (np.savez_compressed if compressed else np.savez)(f, **flat)


def orbax_manager(workdir: str, keep: int = 2, create: bool = True):
    """The orbax CheckpointManager of a training workdir (`WORKDIR/checkpoints`), both training stages. Several
    processes (`gpd_jax.distributed`) each call it on the same (shared) folder: orbax writes each array once, from
    the process holding its first replica, and process 0 commits the step."""
    import orbax.checkpoint as ocp

    return ocp.CheckpointManager(os.path.abspath(os.path.join(workdir, "checkpoints")),
                                 item_handlers=ocp.StandardCheckpointHandler(),
                                 options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=create))


def local_restore_target(metadata):
    """Abstract arrays (shape, dtype) of an orbax checkpoint's tree metadata, each placed whole on this process's
    first device: a checkpoint written by any number of processes (a multi-process run records its devices) reads
    back in one process, or in each of another number of processes."""
    import jax

    sharding = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])

    def target(m):
        return jax.ShapeDtypeStruct(m.shape, m.dtype, sharding=sharding) if hasattr(m, "shape") else m

    return jax.tree.map(target, metadata, is_leaf=lambda m: hasattr(m, "shape"))


def restore_params(workdir: str, template, step: int | None = None):
    """The params of a training workdir's orbax checkpoint (latest step by default) in `template`'s structure.

    Training checkpoints are trees `{"step", "params", "opt_state", ...}`; only `params` is read, so loading a
    model needs no optimizer."""
    import orbax.checkpoint as ocp

    if not os.path.isdir(os.path.join(workdir, "checkpoints")):
        raise FileNotFoundError(f"{workdir}: no orbax checkpoints (no checkpoints/ directory)")
    mgr = orbax_manager(workdir, create=False)
    step = mgr.latest_step() if step is None else step
    if step is None:
        raise FileNotFoundError(f"{workdir}: no orbax checkpoints")
    tree = mgr.restore(step, args=ocp.args.StandardRestore(local_restore_target(mgr.item_metadata(step))))
    return unflatten_params(template, flatten_params(tree["params"]), where=f"{workdir} step {step}")
