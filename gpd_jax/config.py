"""Configuration files: `configs/*.py` modules exposing `get_config() -> ml_collections.ConfigDict`.

Any field can be overridden from a command line with `--config.a.b=value` (the flax-examples convention);
values are parsed with the type of the existing field, so typos and type errors fail loudly.
"""

from __future__ import annotations

import ast
import importlib.util
import json
import os
from collections.abc import Sequence

import ml_collections


def load_config(path: str | os.PathLike, overrides: Sequence[str] = ()) -> ml_collections.ConfigDict:
    """Loads `get_config()` from a python file and applies `--config.key=value` style overrides. `FILE.py:ARG`
    calls `get_config(ARG)` (a config file with variants, as ml_collections' config flags do)."""
    path = os.fspath(path)
    arg = None
    if not os.path.isfile(path) and ":" in path:
        path, arg = path.rsplit(":", 1)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"config file not found: {path}")
    spec = importlib.util.spec_from_file_location(f"_gpd_config_{abs(hash(path))}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    if not hasattr(module, "get_config"):
        raise ValueError(f"config file {path} defines no get_config()")
    cfg = module.get_config() if arg is None else module.get_config(arg)
    apply_overrides(cfg, overrides, source=path)
    return cfg


def apply_overrides(cfg: ml_collections.ConfigDict, overrides: Sequence[str], source: str = "config") -> None:
    """Applies overrides of the form `--config.a.b=v`, `config.a.b=v` or `a.b=v` in place."""
    for item in overrides:
        text = item[2:] if item.startswith("--") else item
        if text.startswith("config."):
            text = text[len("config."):]
        if "=" not in text:
            raise ValueError(f"override {item!r} is not of the form --config.key=value")
        key, raw = text.split("=", 1)
        parent = cfg
        parts = key.split(".")
        for p in parts[:-1]:
            if p not in parent:
                raise KeyError(f"override {item!r}: {source} has no field {key!r}")
            parent = parent[p]
        leaf = parts[-1]
        if leaf not in parent:
            raise KeyError(f"override {item!r}: {source} has no field {key!r}")
        old = parent[leaf]
        parent[leaf] = _parse_like(raw, old, item)


def _parse_like(raw: str, old, item: str):
    if isinstance(old, bool):
        low = raw.lower()
        if low in ("1", "true", "yes"):
            return True
        if low in ("0", "false", "no"):
            return False
        raise ValueError(f"override {item!r}: expected a boolean")
    if isinstance(old, str) or old is None:
        if old is None:
            try:
                return ast.literal_eval(raw)
            except (ValueError, SyntaxError):
                return raw
        return raw
    try:
        value = ast.literal_eval(raw)
    except (ValueError, SyntaxError) as e:
        raise ValueError(f"override {item!r}: cannot parse {raw!r}") from e
    if isinstance(old, float) and isinstance(value, int):
        value = float(value)
    if isinstance(old, tuple) and isinstance(value, list):
        value = tuple(value)
    if type(value) is not type(old) and not (isinstance(old, (list, tuple)) and isinstance(value, (list, tuple))):
        raise ValueError(f"override {item!r}: expected {type(old).__name__}, got {type(value).__name__}")
    return value


def split_config_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """Splits argv into (`--config.*` overrides, the rest) so argparse can parse the rest."""
    overrides = [a for a in argv if a.startswith("--config.")]
    rest = [a for a in argv if not a.startswith("--config.")]
    return overrides, rest


def config_differences(mine: ml_collections.ConfigDict, theirs: ml_collections.ConfigDict,
                       ignore: Sequence[str] = ()) -> str:
    """The top-level fields in which two config sections differ, as "k (theirs there, mine here), ..." ('' when
    they agree); fields in `ignore` are left out. Used to refuse starting a run from another model."""
    a, b = json.loads(mine.to_json()), json.loads(theirs.to_json())
    diff = sorted(k for k in set(a) | set(b) if k not in ignore and a.get(k) != b.get(k))
    return ", ".join(f"{k} ({b.get(k)!r} there, {a.get(k)!r} here)" for k in diff)


def config_from_json(path: str) -> ml_collections.ConfigDict:
    """A config written with `config.to_json()` (exports, workdirs); JSON lists come back as tuples. Raises
    ValueError naming the file when it cannot be read."""
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
