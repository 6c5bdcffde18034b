"""Every check an evaluation can make before loading a model: variant, tasks, horizons, the split, the number of
scenarios, model / data / tokenizer shapes. Each failure is an `EvalError` naming what is wrong and where."""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

from gpd_jax.data.errors import DataError
from gpd_jax.data.loader import SplitSource
from gpd_jax.data.pack import check_packed
from gpd_jax.data.store import list_splits
from gpd_jax.metrics import VARIANTS
from gpd_jax.scene import Scene
from gpd_jax.spec import HORIZONS_S, EvalError, ModelSpec, spec_from_config
from gpd_jax.tasks import map_task_names, resolve_task_names


def check_compatible(spec: ModelSpec, config, sample: dict[str, np.ndarray], where: str, tok=None) -> None:
    """Raises EvalError naming every mismatch between the model's shapes (and its map tokenizer's, if given)
    and a stored sample's."""
    t, a = sample["xy"].shape[0], sample["xy"].shape[1]
    m = sample["map_tokens"].shape[-1]
    problems = []
    if spec.stored_frames_needed > t:
        problems.append(f"the model needs {spec.stored_frames_needed} stored frames ({spec.num_frames} frames at "
                        f"stride {spec.frame_stride}) but the samples have {t}")
    if spec.num_agents > a:
        problems.append(f"the model has {spec.num_agents} agent slots but the samples have {a}")
    if spec.num_map_tokens != m:
        problems.append(f"the model has {spec.num_map_tokens} map tokens per frame but the store's frames have {m}")
    if tok is not None:
        if tok.num_tokens != spec.num_map_tokens:
            problems.append(f"the map tokenizer makes {tok.num_tokens} tokens per frame, the model takes "
                            f"{spec.num_map_tokens}")
        k_tok, k_model = int(tok.config.model.num_codes), int(config.model.codebook_size)
        if k_tok != k_model:
            problems.append(f"the map tokenizer has {k_tok} codes, the model's codebook_size is {k_model}")
    if problems:
        raise EvalError(f"model and data do not match ({where}): " + "; ".join(problems))


class SceneRecords:
    """Random access to the scenarios of in-memory stored-rate scenes `Scene [n, ...]` as store records (what
    `SplitSource` gives for a store), so an evaluation runs on scenes a user holds as on a split."""

    def __init__(self, scenes: Scene):
        if scenes.xy.ndim != 4:
            raise EvalError(f"scenes must have one leading batch dim (Scene [n, T, A, ...]), got xy of shape "
                            f"{tuple(np.shape(scenes.xy))}")
        if scenes.polylines is None:
            raise EvalError("the scenes carry no lane polylines (Scene.polylines), which the ground truth of map "
                            "metrics and map tokens made on the fly need; load them with gpd_jax.load_scenes")
        self.scenes = jax.tree.map(np.asarray, scenes)
        n = self.scenes.xy.shape[0]
        self.counts = np.asarray([n], np.int64)
        self.offsets = np.asarray([0, n], np.int64)

    def __len__(self) -> int:
        return int(self.counts[0])

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        s = self.scenes
        return {"xy": s.xy[i], "heading": s.heading[i], "valid": s.valid[i], "size": s.size[i],
                "agent_type": s.agent_type[i], "map_tokens": s.map_tokens[i], "map_valid": s.map_valid[i],
                "ego_pose": s.ego_pose[i], "polylines": s.polylines[i], "polyline_valid": s.polyline_valid[i]}


def scenario_ids(src) -> list[str]:
    """The scenario id of every sample of a split (from each shard's meta.json; '' where unknown)."""
    return _per_sample(src, "scenario_ids")


def scenario_locations(src) -> list[str]:
    """The location (road network) of every sample of a split (from each shard's meta.json; '' where unknown)."""
    return _per_sample(src, "locations")


def _per_sample(src, key: str) -> list[str]:
    out: list[str] = []
    for p, c in zip(getattr(src, "paths", ()), src.counts):
        try:
            with open(os.path.join(p, "meta.json")) as f:
                got = [str(x) for x in json.load(f).get(key, [])]
        except (OSError, ValueError):
            got = []
        out += (got + [""] * int(c))[: int(c)]
    return out


@dataclasses.dataclass
class Prepared:
    """What `preflight` checked and opened."""

    spec: ModelSpec
    task_names: tuple[str, ...]
    source: Any  # gpd_jax.data.loader.SplitSource (with polylines) or SceneRecords
    num_scenarios: int
    skipped_horizons: tuple[float, ...]
    store_has_tokens: bool
    where: str  # the split directory, or "the given scenes"
    scenario_ids: list[str]
    locations: list[str]  # each scenario's road network ('' where unknown)


def preflight(config, data: str | Scene, split: str = "test", *, task_names: Sequence[str] = ("all",),
              num_scenarios: int | None = None, variant: str = "paper", horizons_s: Sequence[float] = HORIZONS_S,
              has_tokenizer: bool = True, tokenizer=None) -> Prepared:
    """Every check that needs only the config and the data (no model): raises EvalError naming the problem.

    `data` is a store directory (its split `split` is opened) or stored-rate scenes `Scene [n, ...]`.

    Checks the variant, the task names, the horizons, that the split exists and is readable, that it has at
    least `num_scenarios` scenarios, that the model's frames / slots / map tokens fit the stored samples, and that
    a map tokenizer is available where one is needed (map tasks; stores without map tokens).
    """
    if variant not in VARIANTS:
        raise EvalError(f"variant must be one of {', '.join(VARIANTS)}, got {variant!r}")
    try:
        names = resolve_task_names(list(task_names) if not isinstance(task_names, str) else task_names)
    except KeyError as e:
        raise EvalError(str(e.args[0])) from None
    if not names:
        raise EvalError("no task given")
    spec, skipped = spec_from_config(config, horizons_s)
    if isinstance(data, str):
        data_dir, where = data, os.path.join(data, split)
        if not os.path.isdir(data_dir):
            raise EvalError(f"data directory not found: {data_dir}")
        if not os.path.isdir(where):
            raise EvalError(f"split {split!r} not found in {data_dir} "
                            f"(splits: {', '.join(list_splits(data_dir)) or 'none'})")
        try:
            check_packed(data_dir, spec.frame_stride, spec.num_agents)
            src = SplitSource(data_dir, split, with_polylines=True)
            first = src[0]
        except DataError as e:
            raise EvalError(f"cannot read split {split!r}: {e}") from None
    else:
        where, src = "the given scenes", SceneRecords(data)
        first = src[0]
    available = len(src)
    n = available if num_scenarios is None else int(num_scenarios)
    if n < 1:
        raise EvalError(f"the number of scenarios must be >= 1, got {n}")
    if n > available:
        raise EvalError(f"{n} scenarios asked for, but {where} has only {available}")
    check_compatible(spec, config, first, where, tokenizer)
    has_tokenizer = has_tokenizer or tokenizer is not None
    store_has_tokens = bool(first["map_valid"][spec.model_frames()].all())
    maps = map_task_names(names)
    if maps and not has_tokenizer:
        raise EvalError(f"tasks {', '.join(maps)} generate the map, but the model has no map tokenizer to decode "
                        "it (config.model.map_tokenizer is empty); leave them out of the tasks")
    if not store_has_tokens and not has_tokenizer:
        raise EvalError(f"{where} has no map tokens and the model has no map tokenizer to encode them "
                        "(config.model.map_tokenizer is empty); run `python -m gpd_jax.map_tokenizer encode` first")
    return Prepared(spec=spec, task_names=names, source=src, num_scenarios=n, skipped_horizons=skipped,
                    store_has_tokens=store_has_tokens, where=where, scenario_ids=scenario_ids(src),
                    locations=scenario_locations(src))
