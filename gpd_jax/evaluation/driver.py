"""The evaluation driver: batches of a split through the one compiled rollout, scored in the same run against
the baselines (the metrics.json layout is in `gpd_jax.evaluation`)."""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from gpd_jax import distributed
from gpd_jax.checkpoint import Model
from gpd_jax.data.errors import DataError
from gpd_jax.data.loader import to_scene
from gpd_jax.data.store import foreign_map_token_shards, sample_layouts
from gpd_jax.decoding import RolloutOutput, check_options, rollout_model
from gpd_jax.evaluation.bootstrap import scene_sums_from_batches
from gpd_jax.evaluation.keys import RATIO_TARGETS, SCORED_AGENTS
from gpd_jax.evaluation.maps import gt_future_lanes, persistence_future_lanes
from gpd_jax.options import RolloutOptions
from gpd_jax.evaluation.preflight import preflight
from gpd_jax.evaluation.realism import (OFFICIAL_FUTURE_FRAMES, RESULT_KEYS, group_names, official_rollouts,
                                       realism_batch, reduce_groups, write_official_scenes)
from gpd_jax.evaluation.reduce import other_variant, reduce_results
from gpd_jax.evaluation.scoring import add_sums, score_batch
from gpd_jax.metrics.realism import CONFIGS as REALISM_CONFIGS
from gpd_jax.metrics.realism import (OFFICIAL_HISTORY_FRAMES, edge_polylines, edge_segment_budget,
                                     official_signal_arrays)
from gpd_jax.geometry import edge_source_names
from gpd_jax.scene import Scene
from gpd_jax.spec import HORIZONS_S, EvalError
from gpd_jax.tasks import generated, make_tasks, map_task_names


@dataclasses.dataclass
class RenderItem:
    """What `gpd_jax.render` needs for one scenario (model-rate arrays, every task)."""

    index: int
    scenario_id: str
    pred: dict[str, np.ndarray]  # xy [K, T, A, 2], heading [K, T, A], valid [K, T, A], map_tokens [K, T, M]
    log: dict[str, np.ndarray]  # xy [T, A, 2], heading, valid, size [A, 2], agent_type, map_tokens [T, M], ego_pose


def run_evaluation(model: Model, data: str | Scene, split: str = "test", *,
                   task_names: Sequence[str] | str = ("all",), num_scenarios: int | None = None, batch_size: int = 8,
                   seed: int = 0, variant: str = "paper", horizons_s: Sequence[float] = HORIZONS_S,
                   render_count: int = 0, options: RolloutOptions = RolloutOptions(), progress: bool = True,
                   log: Callable[[str], None] = print, layouts: Sequence[str] | None = None,
                   scene_sums: bool = False, samples: int = 0, realism_config: str = "2025",
                   export_official: str | None = None) -> tuple[dict[str, Any], list[RenderItem]]:
    """Rolls out every task on the first `num_scenarios` scenarios of a split (or of given scenes) and scores
    them.

    Args:
      model: a loaded GPD (`gpd_jax.load_model`): its config, spec and map tokenizer are used.
      data: a data store directory (read `split` in store order, deterministic), or stored-rate scenes
        `Scene [n, ...]` (`gpd_jax.load_scenes`; with `polylines` for map tasks and on-the-fly map tokens).
      task_names: task keys of `gpd_jax.tasks`, a comma list, or ["all"].
      num_scenarios: how many scenarios (None: all).
      batch_size: scenarios per compiled rollout call (each runs every task).
      seed: PRNG seed of the rollout keys (used when the rollout temperature is > 0).
      variant: which metric variant fills the main keys ("paper" or "corrected").
      horizons_s: horizons in seconds (those longer than the model's future are skipped with a note).
      render_count: keep the arrays of the first this-many scenarios for `gpd_jax.render` (returned).
      options: how the rollouts run (`gpd_jax.RolloutOptions`: temperature, the log's map as tokens or lanes,
        generated-map mode).
      layouts: the road-network layout of every scenario (grid, spider, random, real, ...), for figures per
        layout beside the overall ones (`results["by_layout"]`, when there are two or more). Default: read from
        the store (`gpd_jax.data.store.sample_layouts`; SUMO builds record it), none for in-memory scenes.
      scene_sums: also keep every scenario's own metric sums, as `results["scene_sums"]` (a
        `gpd_jax.evaluation.bootstrap.SceneSums`, not JSON: `rollout.py` writes it to scene_sums.npz) for
        scene-bootstrap intervals and paired comparisons (`bootstrap.compare_runs`).
      samples: K > 0 adds `results["realism"]`: the WOSAC-form realism of K sampled rollouts of every task that
        generates agents or the ego, and of the baselines (`gpd_jax.evaluation.realism`; at temperature 0 the
        model is deterministic and its K rollouts are one rollout repeated). The main metrics are unchanged.
      realism_config: "2024" or "2025" (the challenge's weights).
      export_official: with samples, a directory to write every group's rollouts to as the official mode scores
        them (`<group>.npz`, `gpd_jax.evaluation.realism.write_official_scenes`), for the official code
        (`tests/conformance/run_official.py`); `results["realism_official"]` is what it should reproduce.

    Returns:
      (results dict as written to metrics.json, render items). Raises EvalError on bad input. With several
      processes (`gpd_jax.distributed`), every process calls it alike: each rolls out its share of the batches
      and process 0 returns the results of all of them (the same figures as one process); the others return
      (None, []).
    """
    config, tokenizer = model.config, model.tokenizer
    if samples < 0:
        raise EvalError(f"samples must be >= 0, got {samples}")
    if options.samples is not None:
        raise EvalError("options.samples: an evaluation scores one rollout per scene and task; ask for realism over "
                        "K sampled rollouts with samples=K (rollout.py --samples K)")
    if realism_config not in REALISM_CONFIGS:
        raise EvalError(f"realism_config {realism_config!r}: expected one of {sorted(REALISM_CONFIGS)}")
    if options.method != "cached":
        raise EvalError(f"evaluation runs the cached rollout; options.method is {options.method!r}")
    check_options(model, options)
    prep = preflight(config, data, split, task_names=task_names, num_scenarios=num_scenarios, variant=variant,
                     horizons_s=horizons_s, has_tokenizer=tokenizer is not None, tokenizer=tokenizer)
    spec, names, src, n = prep.spec, prep.task_names, prep.source, prep.num_scenarios
    if export_official is not None:
        if jax.process_count() > 1:
            raise EvalError("export_official runs in one process; leave out --coordinator / --distributed")
        if not samples:
            raise EvalError("export_official: the official format holds the K rollouts of samples=K; ask for samples")
        if (spec.stored_period_s != 0.1 or spec.full_history < OFFICIAL_HISTORY_FRAMES
                or spec.stored_frames_needed - spec.full_history < OFFICIAL_FUTURE_FRAMES):
            raise EvalError(f"export_official: the official format is {OFFICIAL_HISTORY_FRAMES} history and "
                            f"{OFFICIAL_FUTURE_FRAMES} future frames at 10 Hz; this model has "
                            f"{spec.full_history} and {spec.stored_frames_needed - spec.full_history} at "
                            f"{1 / spec.stored_period_s:g} Hz")
    if prep.skipped_horizons:
        log(f"note: horizons {', '.join(f'{s:g} s' for s in prep.skipped_horizons)} exceed the model's future "
            f"({spec.num_future * spec.frame_period_s:g} s) and are skipped")
    maps = map_task_names(names)
    # Stored tokens made by another tokenizer mean other codes: those scenarios are encoded on the fly instead.
    foreign = np.zeros(len(src.counts), bool)
    if tokenizer is not None and isinstance(data, str):
        foreign[foreign_map_token_shards(data, split, tokenizer.fingerprint())] = True
    bs = max(1, min(int(batch_size), n))
    num_batches = -(-n // bs)
    tasks = jax.tree.map(jnp.asarray, make_tasks(names, spec.num_map_tokens, spec.num_agents))
    key = jax.random.key(seed)
    sample_key = jax.random.split(key)[1]  # the extra sampled rollouts of `samples` (the main ones use `key`)

    if layouts is None and isinstance(data, str):
        layouts = sample_layouts(data, split)
    layouts = None if layouts is None else [str(x) for x in list(layouts)[:n]]
    if layouts is not None and len(layouts) < n:
        raise EvalError(f"layouts: {len(layouts)} labels for {n} scenarios")
    per_layout = layouts is not None and len(set(layouts)) > 1
    layout_acc: dict[str, Any] = {}
    per_scene: list[dict[str, Any]] = []

    acc = None
    realism_parts: list[dict[str, dict[str, dict[str, np.ndarray]]]] = []
    export_parts: list[dict[str, Any]] = []
    export_groups: list[str] = []
    has_road = has_signals = True
    edge_sources: list[str] = []
    render_items: list[RenderItem] = []
    n_store = n_encoded = 0
    t_roll = t_score = t_data = 0.0
    # Several processes (`gpd_jax.distributed`): each rolls out its share of the batches (round-robin) on its own
    # devices and keeps each scenario's sums; process 0 gathers them and folds every batch in batch order, exactly
    # as one process folds its own, so the figures are those of one process.
    several = jax.process_count() > 1
    keep_scenes = per_layout or scene_sums or several
    mine = distributed.my_share(num_batches)
    kept: dict[str, dict[str, Any]] = {}

    def batch_indices(b: int) -> tuple[list[int], int]:
        idx = list(range(b * bs, min((b + 1) * bs, n)))
        real = len(idx)
        return idx + [idx[-1]] * (bs - real), real  # pad: same shapes, same compile

    def fold(b: int, rec: dict[str, Any]) -> None:
        """Adds batch `b`'s record (its scenarios' sums or their total, realism, pictures, counts)."""
        nonlocal acc, has_road, has_signals, n_store, n_encoded
        idx, real = batch_indices(b)
        if keep_scenes:  # each scenario's sums: the batch's total, each layout's part, each scene's
            sums = rec["scenes"]
            if scene_sums:
                per_scene.append(sums)
            if per_layout:
                labels = np.array([layouts[i] for i in idx[:real]])
                for g in sorted(set(labels)):
                    layout_acc[g] = add_sums(layout_acc.get(g), jax.tree.map(lambda x: x[labels == g].sum(0), sums))
            total = jax.tree.map(lambda x: x.sum(0), sums)
        else:
            total = rec["total"]
        acc = add_sums(acc, total)
        if samples:
            realism_parts.append(rec["realism"])
            has_road = has_road and bool(rec["has_road"])
            has_signals = has_signals and bool(rec["has_signals"])
            edge_sources.extend(str(x) for x in rec["edge_sources"])
        n_store += int(rec["n_store"])
        n_encoded += int(rec["n_encoded"])
        render_items.extend(_render_item_from(r) for r in rec.get("render", {}).values())

    t0 = time.perf_counter()
    bar = tqdm(total=sum(batch_indices(b)[1] for b in mine), unit="scenario", dynamic_ncols=True,
               desc=f"compiling the rollout of {len(names)} tasks (the first batch)",
               disable=not progress or not distributed.is_lead())
    try:
        for b in mine:
            ta = time.perf_counter()
            idx, real = batch_indices(b)
            weight = np.arange(bs) < real
            try:
                recs = [src[i] for i in idx]
            except DataError as e:
                raise EvalError(f"cannot read split {split!r}: {e}") from None
            full = to_scene({k: np.stack([r[k] for r in recs]) for k in recs[0]})
            polylines, poly_valid = full.polylines, full.polyline_valid
            reencode = foreign[np.searchsorted(src.offsets, idx, side="right") - 1]
            stored = np.asarray(full.map_valid)[:, spec.model_frames()].all(axis=-1) & ~reencode
            if not stored[:real].all() and tokenizer is None:
                raise EvalError(f"{prep.where} has no map tokens for some scenarios and the model has no map "
                                "tokenizer to encode them")
            view = model.prepare(full, options, reencode=reencode)
            rec: dict[str, Any] = {"n_store": int(stored[:real].sum()), "n_encoded": int((~stored[:real]).sum())}
            gt_lanes = kept_lanes = None
            if maps:
                gt_lanes = gt_future_lanes(polylines, poly_valid, full.ego_pose, spec)
                kept_lanes = persistence_future_lanes(polylines, poly_valid, full.ego_pose, spec)
            tb = time.perf_counter()
            t_data += tb - ta
            out = jax.block_until_ready(rollout_model(model, view, tasks, jax.random.fold_in(key, b), options))
            scene = view.replace(polylines=None, polyline_valid=None)  # the ground truth the scores read
            tc = time.perf_counter()
            t_roll += tc - tb
            map_pred = None
            if maps:
                mi = np.array([names.index(m_) for m_ in maps])
                fut = slice(spec.num_history, spec.num_history + spec.max_horizon)
                tokens = jnp.concatenate([out.map_tokens[:, mi, fut],
                                          jnp.asarray(scene.map_tokens)[:, None, fut]], axis=1)
                map_pred = tokenizer.decode_tokens(tokens)
            sums = score_batch(out, scene, _agents_only(full), weight, spec, names, map_pred, gt_lanes, kept_lanes,
                               per_scenario=keep_scenes)
            sums = jax.tree.map(lambda x: np.asarray(x, np.float64), jax.device_get(sums))
            if keep_scenes:
                rec["scenes"] = jax.tree.map(lambda x: x[:real], sums)
            else:
                rec["total"] = sums
            if samples:
                part, road_ok, exported = _realism(model, view, full, tasks, names, out, samples,
                                                   jax.random.fold_in(sample_key, b), options, realism_config,
                                                   export_official is not None)
                rec["realism"] = jax.tree.map(lambda x: x[:real], part)
                rec["has_road"] = road_ok
                rec["has_signals"] = full.signals is not None
                rec["edge_sources"] = np.asarray(edge_source_names(full.road, full.xy.shape[:1])[:real], dtype=str)
                if exported is not None:  # one process only (checked above): not part of the gathered record
                    export_parts.append({k: v[:real] for k, v in exported.items()})
                    export_groups = group_names(names, full.polylines is not None)  # the order of their G axis
            t_score += time.perf_counter() - tc
            rec["render"] = {str(j): _render_record(idx[j], prep.scenario_ids, out, scene, j)
                             for j in range(real) if idx[j] < render_count}
            if several:
                kept[f"{b:09d}"] = rec
            else:
                fold(b, rec)
            if b == mine[0]:
                bar.set_description(f"rollout {len(names)} tasks", refresh=False)
            bar.update(real)
    finally:
        bar.close()
    if several:
        gathered = distributed.gather_to_lead(f"evaluation/{seed}/{n}", {
            "batches": kept, "seconds": {"data": t_data, "rollout": t_roll, "score": t_score}})
        if gathered is None:  # not process 0: it writes the results
            return None, []
        for b, rec in sorted((int(b), rec) for g in gathered for b, rec in g["batches"].items()):
            fold(b, rec)
        t_data, t_roll, t_score = (sum(float(g["seconds"][k]) for g in gathered) for k in ("data", "rollout", "score"))
    wall = time.perf_counter() - t0
    if foreign.any():
        log(f"map tokens: {foreign.sum()} of {foreign.size} shards hold tokens of another tokenizer; not used")
    if n_encoded and n_store:
        source = f"read from the store for {n_store} scenarios, encoded on the fly for {n_encoded}"
    elif n_encoded:
        source = f"encoded on the fly with the model's map tokenizer (the store has none) for {n_encoded} scenarios"
    else:
        source = f"read from the store for {n_store} scenarios"
    log(f"map tokens: {source}")

    res = reduce_results(acc, spec, names, variant)
    results = {
        "variant": variant,
        "other_variant_suffix": f"_{other_variant(variant)}",
        "scenarios": n,
        "split": split,
        "data": os.path.abspath(data) if isinstance(data, str) else "in-memory scenes",
        "frame_period_s": round(spec.frame_period_s, 9),
        "frame_stride": spec.frame_stride,
        "stored_frame_period_s": spec.stored_period_s,
        "num_history": spec.num_history,
        "num_future": spec.num_future,
        "num_agents": spec.num_agents,
        "horizons": {lb: h for lb, h in zip(spec.labels, spec.horizons)},
        "scored_agents": SCORED_AGENTS,
        "num_scored_agents": int(acc["counts"]["scored_agents"]),
        "task_generates": {t: list(generated(t)) for t in names},
        "map_tokens": {"from_store": n_store, "encoded": n_encoded},
        "log_map": options.log_map,
        "gen_map": options.gen_map,
        "temperature": options.temperature,
        **({"top_k": options.top_k} if options.top_k else {}),
        **({"top_p": options.top_p} if options.top_p < 1 else {}),
        "seed": seed,
        **res,
        "ratio_targets": {k: RATIO_TARGETS for k in res["ratios"]},
        **({"by_layout": {g: {"scenarios": int(a["counts"]["scenarios"]), **reduce_results(a, spec, names, variant)}
                          for g, a in sorted(layout_acc.items())}} if per_layout else {}),
        "timing_s": {"total": round(wall, 2), "rollout": round(t_roll, 2), "scoring": round(t_score, 2),
                     "data": round(t_data, 2), "batches": num_batches, "batch_size": bs,
                     "processes": jax.process_count()},
    }
    if samples:
        for rules, key in RESULT_KEYS.items():
            first = realism_parts[0][rules]
            by_group = {g: {m: np.concatenate([p[rules][g][m] for p in realism_parts]) for m in first[g]}
                        for g in first}
            results[key] = reduce_groups(by_group, names, samples, realism_config, has_road, has_signals,
                                         edge_sources, rules)
        if export_official is not None:
            ids = [prep.scenario_ids[i] if i < len(prep.scenario_ids) else str(i) for i in range(n)]
            paths = write_official_scenes(export_official, export_groups, ids, export_parts, spec.full_history)
            results["realism_official"]["exported"] = paths
    if scene_sums:
        pad = lambda x: list(x[:n]) + [""] * max(0, n - len(x))  # noqa: E731
        results["scene_sums"] = scene_sums_from_batches(per_scene, pad(prep.scenario_ids), pad(prep.locations))
    return results, render_items


SAMPLED_ROLLOUTS_PER_CALL = 512  # rollouts (scenes x tasks x samples) in one call of the sampled realism draws


def _realism(model: Model, view: Scene, full: Scene, tasks, names, out: RolloutOutput, samples: int, key,
             options: RolloutOptions, config: str, export: bool = False
             ) -> tuple[dict[str, dict[str, dict[str, np.ndarray]]], bool, dict[str, Any] | None]:
    """Each scenario's realism figures of one batch under each counting rule (`gpd_jax.evaluation.realism`:
    `{rules: {group: {metric: f64[b]}}}`) and whether the scenes had road
    geometry. The first of the K samples is the main rollout `out`; the others are drawn only where the rollout
    samples (temperature > 0), through the rollout's sample axis (`RolloutOptions.samples`), in calls of equal size
    (one compile) of at most `SAMPLED_ROLLOUTS_PER_CALL` rollouts."""
    fields = ("xy", "heading", "valid")
    draws = [tuple(getattr(out, f)[:, :, None] for f in fields)]
    if options.temperature > 0 and samples > 1:
        pairs = view.xy.shape[0] * len(names)
        per_call = max(1, min(samples - 1, SAMPLED_ROLLOUTS_PER_CALL // pairs))
        for c in range(-(-(samples - 1) // per_call)):
            more = rollout_model(model, view, tasks, jax.random.fold_in(key, c), options.replace(samples=per_call))
            draws.append(tuple(getattr(more, f) for f in fields))
    xy, heading, valid = (jnp.concatenate([d[i] for d in draws], axis=2)[:, :, :samples] for i in range(3))
    reps = samples // xy.shape[2]  # 1, or K copies of the one deterministic rollout
    xy, heading, valid = (jnp.swapaxes(jnp.repeat(a, reps, axis=2), 1, 2) for a in (xy, heading, valid))
    full = jax.tree.map(jnp.asarray, full.replace(map_tokens=full.map_tokens[..., :1], lanes=None, lanes_valid=None))
    budget = None if full.road is None else edge_segment_budget(full.road)
    with_lanes = full.polylines is not None
    part = realism_batch(xy, heading, valid, full, model.spec, tuple(names), config, budget, with_lanes)
    exported = None
    if export:
        if full.road is None:
            raise EvalError("export_official: the official code needs road edges; these scenes have no road geometry")
        sub_xy, sub_h, ev = jax.device_get(official_rollouts(xy, heading, valid, full, model.spec, tuple(names),
                                                             with_lanes))
        a, b = model.spec.num_agents, xy.shape[0]
        road = jax.device_get(full.road)
        exported = {"sub_xy": sub_xy, "sub_heading": sub_h, "evaluated": ev,
                    **{k: np.asarray(getattr(full, f))[:, :, :a] for k, f in
                       (("log_xy", "xy"), ("log_heading", "heading"), ("log_valid", "valid"))},
                    "size": np.asarray(full.size)[:, :a], "agent_type": np.asarray(full.agent_type)[:, :a],
                    "edges": np.empty(b, object)}
        for i in range(b):  # the road edges as the metric orients them, one list of polylines per scene
            exported["edges"][i] = edge_polylines(jax.tree.map(lambda x, i=i: x[i], road))
        if full.signals is not None:  # the signals and lanes as the official mode hands them over
            exported.update(official_signal_arrays(full.signals, full.polylines, full.polyline_valid),
                            signal_state=np.asarray(full.signals.state), signal_stop=np.asarray(full.signals.stop))
    return (jax.tree.map(lambda x: np.asarray(x, np.float64), jax.device_get(part)), full.road is not None,
            exported)


def _agents_only(full: Scene) -> Scene:
    """The full-rate scene without the fields the baselines do not use (smaller jit arguments; the polylines stay,
    for the lane-following baseline)."""
    return jax.tree.map(jnp.asarray, full.replace(map_tokens=full.map_tokens[..., :1], lanes=None, lanes_valid=None,
                                                  road=None))


def _render_record(i: int, ids: Sequence[str], out: RolloutOutput, scene: Scene, j: int) -> dict[str, Any]:
    """What `RenderItem` holds, as a nested dict of arrays (sent between processes as is)."""
    pred = {k: np.asarray(getattr(out, k)[j]) for k in ("xy", "heading", "valid", "map_tokens")}
    log = {k: np.asarray(getattr(scene, k)[j]) for k in ("xy", "heading", "valid", "size", "agent_type",
                                                         "map_tokens", "ego_pose")}
    return {"index": np.int64(i), "scenario_id": np.str_(ids[i] if i < len(ids) else ""), "pred": pred, "log": log}


def _render_item_from(rec: dict[str, Any]) -> RenderItem:
    return RenderItem(index=int(rec["index"]), scenario_id=str(rec["scenario_id"]), pred=dict(rec["pred"]),
                      log=dict(rec["log"]))
