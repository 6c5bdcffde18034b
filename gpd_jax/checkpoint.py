"""Trained GPD models on disk: exported (what ships) and training workdirs (orbax).

    config, model = load_model("checkpoints/gpd_sumo")          # exported: config.json + params.npz
    config, model = load_model("runs/gpd")                      # a train.py workdir: latest orbax step

An exported model is a directory with `config.json` (the full training config) and `params.npz` (the model's
`nnx.Param` leaves keyed by their path, float32 or float16). The map tokenizer whose frozen codebook embeds
map tokens is named by `config.model.map_tokenizer`; a relative path is looked up next to the checkpoint
first, then in the repository, then in the working directory (`resolve_tokenizer_path`), so an exported
model and its tokenizer can travel together (`export_model(..., tokenizer_dir=...)` copies it in).
"""

from __future__ import annotations

import json
import os
import shutil

import jax
import ml_collections
import numpy as np
from flax import nnx

from gpd_jax.fsutil import atomic_directory
from gpd_jax.model import GPD, build_model

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIG_FILE = "config.json"
PARAMS_FILE = "params.npz"


def _path_key(path) -> str:
    return "/".join(str(getattr(p, "key", getattr(p, "name", getattr(p, "idx", p)))) for p in path)


def flatten_params(params) -> dict[str, np.ndarray]:
    """{path: array} of a params pytree (the keys of `params.npz`, for GPD and map-tokenizer exports)."""
    return {_path_key(p): np.asarray(x) for p, x in jax.tree_util.tree_leaves_with_path(params)}


def unflatten_params(template, flat: dict[str, np.ndarray], where: str = "params"):
    """Fills `template` (a params pytree; leaves may be abstract) from `flatten_params` output, checking names
    and shapes and casting to the template's dtypes (float16 exports come back as float32)."""
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
        raise ValueError(f"{where} does not match the model of its config: missing {missing[:5]}, "
                         f"wrong shapes {bad[:5]}, unexpected {extra[:5]}")
    return out


def config_from_json(path: str) -> ml_collections.ConfigDict:
    try:
        with open(path) as f:
            d = json.load(f)
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: unreadable config ({e})") from e

    def lists_to_tuples(x):
        if isinstance(x, dict):
            return {k: lists_to_tuples(v) for k, v in x.items()}
        if isinstance(x, list):
            return tuple(lists_to_tuples(v) for v in x)
        return x

    return ml_collections.ConfigDict(lists_to_tuples(d))


def resolve_tokenizer_path(path: str, checkpoint_dir: str | None = None) -> str:
    """An absolute path to the map tokenizer `path` names (see the module docstring for the search order)."""
    if not path or os.path.isabs(path):
        return path
    bases = ([checkpoint_dir] if checkpoint_dir else []) + [REPO_ROOT, os.getcwd()]
    for base in bases:
        p = os.path.normpath(os.path.join(base, path))
        if os.path.exists(os.path.join(p, "config.json")):
            return p
    raise FileNotFoundError(f"map tokenizer {path!r} not found next to {checkpoint_dir}, in {REPO_ROOT} "
                            f"or in {os.getcwd()}")


def model_from_config(config: ml_collections.ConfigDict, checkpoint_dir: str | None = None, seed: int = 0) -> GPD:
    """A freshly initialised model of `config`, its tokenizer path resolved relative to `checkpoint_dir`."""
    config = ml_collections.ConfigDict(config.to_dict())
    if config.model.get("map_tokenizer"):
        config.model.map_tokenizer = resolve_tokenizer_path(config.model.map_tokenizer, checkpoint_dir)
    return build_model(config, seed=seed)


def is_exported(path: str) -> bool:
    return os.path.exists(os.path.join(path, PARAMS_FILE))


def export_model(params, config: ml_collections.ConfigDict, out_dir: str, dtype=np.float32,
                 tokenizer_dir: str | None = None) -> str:
    """Writes `config.json` + `params.npz` to `out_dir` atomically (a temporary directory renamed into place;
    other files already in `out_dir`, such as a README or evaluation files, are kept).

    With `tokenizer_dir`, the map tokenizer is copied to `out_dir/map_tokenizer` and the config points there.
    """
    out_dir = os.path.abspath(out_dir)
    with atomic_directory(out_dir) as tmp:
        config = ml_collections.ConfigDict(config.to_dict())
        if tokenizer_dir:
            shutil.copytree(tokenizer_dir, os.path.join(tmp, "map_tokenizer"),
                            ignore=shutil.ignore_patterns("checkpoints", "*.jsonl"))
            config.model.map_tokenizer = "map_tokenizer"
        flat = {k: v.astype(dtype) if np.issubdtype(v.dtype, np.floating) else v
                for k, v in flatten_params(params).items()}
        np.savez(os.path.join(tmp, PARAMS_FILE), **flat)
        with open(os.path.join(tmp, CONFIG_FILE), "w") as f:
            f.write(config.to_json(indent=2))
    return out_dir


def load_model(path: str, step: int | None = None) -> tuple[ml_collections.ConfigDict, GPD]:
    """(config, model) of an exported model directory or a train.py workdir (latest step, or `step`)."""
    path = os.path.abspath(path)
    cfg_path = os.path.join(path, CONFIG_FILE)
    if not os.path.exists(cfg_path):
        raise FileNotFoundError(f"{path}: no {CONFIG_FILE}; expected an exported GPD model or a train.py workdir")
    config = config_from_json(cfg_path)
    if config.get("stage") != "gpd":
        raise ValueError(f"{cfg_path}: stage is {config.get('stage')!r}, not a GPD model")
    model = model_from_config(config, path)
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    if is_exported(path):
        with np.load(os.path.join(path, PARAMS_FILE)) as z:
            params = unflatten_params(params, dict(z), where=os.path.join(path, PARAMS_FILE))
    else:
        from gpd_jax.train_loop import restore_params

        params = restore_params(path, model, config, step)
    return config, nnx.merge(graphdef, params, rest)


def main(argv=None) -> int:
    """`python -m gpd_jax.checkpoint export WORKDIR OUT [--step N] [--tokenizer-ref PATH] [--float16]`."""
    import argparse
    import sys

    p = argparse.ArgumentParser(prog="python -m gpd_jax.checkpoint", description="export a trained GPD model")
    sub = p.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("export", help="a train.py workdir's checkpoint -> config.json + params.npz")
    e.add_argument("workdir")
    e.add_argument("out")
    e.add_argument("--step", type=int, default=None, help="default: the latest checkpoint")
    e.add_argument("--tokenizer-ref", default=None,
                   help="write this map-tokenizer path into the exported config instead of copying the tokenizer "
                        "(relative paths are resolved next to the export first, e.g. ../map_tokenizer)")
    e.add_argument("--float16", action="store_true", help="store parameters as float16 (half the size)")
    args = p.parse_args(argv)
    try:
        config, model = load_model(args.workdir, args.step)
    except (FileNotFoundError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    params = nnx.state(model, nnx.Param)
    dtype = np.float16 if args.float16 else np.float32
    if args.tokenizer_ref is not None:
        config.model.map_tokenizer = args.tokenizer_ref
        out = export_model(params, config, args.out, dtype=dtype)
        resolve_tokenizer_path(args.tokenizer_ref, out)  # fails loudly if the reference does not resolve
    else:
        tok = config.model.get("map_tokenizer") or None
        out = export_model(params, config, args.out, dtype=dtype,
                           tokenizer_dir=resolve_tokenizer_path(tok, args.workdir) if tok else None)
    print(f"exported {args.workdir} -> {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
