"""The public front door (re-exported by `gpd_jax/__init__.py`): load a model and scenes, roll out, evaluate,
draw, and the pure rollout function under it all.

    import gpd_jax, jax
    model = gpd_jax.load_model()                                      # the default model (gpd_jax.list_models())
    scenes = gpd_jax.load_scenes("data/test", indices=range(4))       # Scene [4, 101, 33, ...] at 10 Hz
    out = gpd_jax.rollout(model, scenes, ["traffic_simulation", "scene_generation"], jax.random.key(0))
    out.xy.shape                                                      # [4, 2, T, A, 2] at the model's rate
    results = gpd_jax.evaluate(model, scenes, tasks="traffic_simulation")

    fn = gpd_jax.make_rollout_fn(model)                               # fn(params, view, tasks, key): pure
    view = model.prepare(scenes)                                      # the model's view, map tokens filled
    out = jax.jit(fn)(model.params, view, gpd_jax.make_tasks(model, "closed_loop"), key)

Scenes come in at the stored rate (`load_scenes`); `rollout` and `evaluate` take the model's view inside
(`Model.prepare`: its frame stride, history and future, agent slots, map tokens encoded where the store has none).
How a rollout runs is a `RolloutOptions` (temperature, the log's map as tokens or re-encoded lanes, generated-map
mode, cached or recompute), checked once and handed to the one compiled rollout (`gpd_jax.decoding.rollout_model`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from gpd_jax.checkpoint import Model
from gpd_jax.data.loader import SplitSource, to_scene
from gpd_jax.data.sources.sumo import build_sumo
from gpd_jax.decoding import RolloutOutput, check_options, rollout_model, rollout_prepared
from gpd_jax.evaluation.driver import RenderItem, run_evaluation
from gpd_jax.evaluation.render import render_items
from gpd_jax.options import RolloutOptions
from gpd_jax.prompts import Prompt, prompt_from_task, stack_prompts
from gpd_jax.prompts import make_prompt as _make_prompt
from gpd_jax.scene import Scene
from gpd_jax.spec import HORIZONS_S, EvalError
from gpd_jax.tasks import Task, resolve_task_names
from gpd_jax.tasks import make_tasks as _make_tasks

__all__ = ["build_scenes", "evaluate", "load_scenes", "make_prompt", "make_rollout_fn", "make_tasks", "render",
           "rollout", "stack_prompts", "task_prompt"]


def load_scenes(data_dir: str, split: str = "test", indices: Sequence[int] | None = None) -> Scene:
    """Scenes of a data store at the stored rate, with their lane polylines: Scene [n, T, A, ...] (numpy leaves;
    T = 101 frames at 10 Hz, A = 33 slots as stored). `indices`: which samples (default: the whole split)."""
    if not os.path.isdir(os.path.join(data_dir, split)):
        raise EvalError(f"split {split!r} not found in {data_dir}")
    src = SplitSource(data_dir, split, with_polylines=True)
    idx = range(len(src)) if indices is None else [int(i) for i in indices]
    if not len(idx):
        raise EvalError("no scenes asked for (indices is empty)")
    bad = [i for i in idx if not 0 <= i < len(src)]
    if bad:
        raise EvalError(f"scene index {bad[0]} is out of range: {data_dir}/{split} holds {len(src)} scenes")
    recs = [src[i] for i in idx]
    return to_scene({k: np.stack([r[k] for r in recs]) for k in recs[0]})


def build_scenes(out_dir: str, num_scenarios: int = 8, seed: int = 7, split: str = "test", *,
                 workers: int = 1) -> Scene:
    """Simulates `num_scenarios` SUMO scenes on networks generated from `seed` into a store at `out_dir`
    (resumed if it is already there with these settings) and returns them (`load_scenes`). About a second per
    scene on a CPU core."""
    build_sumo(out_dir, num_scenarios=num_scenarios, seed=seed, workers=workers, split=split,
               per_job=min(50, num_scenarios))
    return load_scenes(out_dir, split)


def make_tasks(model: Model, tasks: str | Sequence[str]) -> Task:
    """Named tasks (a name, a comma list, a list, or "all") as stacked `Task` arrays [K, ...] for `model`."""
    return jax.tree.map(jnp.asarray, _make_tasks(resolve_task_names(tasks), model.spec.num_map_tokens,
                                                 model.spec.num_agents))


def task_prompt(model: Model, task: str) -> Prompt:
    """The prompt of a named task for `model` (it rolls out exactly as the task)."""
    return jax.tree.map(jnp.asarray, prompt_from_task(task, model.spec.num_frames, model.spec.num_map_tokens,
                                                      model.spec.num_agents))


def make_prompt(model: Model, scene: Scene, **choices) -> Prompt:
    """A prompt for one scene (`gpd_jax.prompts.make_prompt`: base task, given `paths`, `log_until`,
    `initial_slots`, `max_agents`, `hidden`, `lanes` / `lanes_pose`, `map_tokens`). `scene`: one Scene at the
    stored rate (its model view is taken) or already in the model's view; coordinates are the scene frame.
    A prompt with lanes needs the model's map tokenizer."""
    if np.ndim(scene.xy) != 3:
        raise EvalError(f"make_prompt takes one scene [T, A, ...], got xy of shape {np.shape(scene.xy)}")
    model.require_tokenizer(prompt_lanes=choices.get("lanes") is not None)
    view = scene
    if (scene.num_frames, scene.num_agents) != (model.spec.num_frames, model.spec.num_agents):
        view = jax.tree.map(lambda x: x[0], model.prepare(jax.tree.map(lambda x: np.asarray(x)[None], scene)))
    choices.setdefault("frame_period_s", model.spec.frame_period_s)
    return _make_prompt(jax.tree.map(np.asarray, view), model.spec.num_history, **choices)


def make_rollout_fn(model: Model, options: RolloutOptions | None = None) -> Callable[..., RolloutOutput]:
    """The rollout as a pure function of the parameters: `fn(params, view, tasks, key) -> RolloutOutput`.

    view: Scene [S, T, A, ...] prepared for the model (`model.prepare`); tasks: Task [K, ...] (`make_tasks`) or
    Prompt [K, ...] / [S, K, ...] (`make_prompt`, `stack_prompts`); key: a PRNG key (used at temperature > 0);
    params: a pytree shaped like `model.params` (swap or perturb it freely). Returns RolloutOutput [S, K, T, ...]
    ([S, K, N, T, ...] with `RolloutOptions(samples=N)`: N futures of every pair). Nothing is compiled until you `jax.jit` it; it also `vmap`s. `options` (`RolloutOptions`) as in `rollout`;
    `RolloutOptions(method="recompute")` is the official full-prefix rollout, which `jax.grad` goes through.
    """
    options = RolloutOptions() if options is None else options
    check_options(model, options)
    graphdef, rest, h, tok = model.graphdef, model.rest, model.spec.num_history, model.tokenizer

    def fn(params, view: Scene, tasks: Task | Prompt, key) -> RolloutOutput:
        use = check_options(model, options, tasks) or options.needs_tokenizer
        return rollout_prepared(nnx.merge(graphdef, params, rest), view, tasks, key, h, options,
                                tok if use else None, tok.params if use else None)

    return fn


def _as_tasks(model: Model, tasks) -> tuple[Task | Prompt, bool]:
    """(Task or Prompt [K, ...] (a Prompt also [B, K, ...]), whether a single task or prompt was given)."""
    if isinstance(tasks, (list, tuple)) and tasks and all(isinstance(p, Prompt) for p in tasks):
        return jax.tree.map(jnp.asarray, stack_prompts(tasks)), False
    if isinstance(tasks, Prompt):
        single = np.ndim(tasks.from_log) == 2
        t = jax.tree.map(lambda x: jnp.asarray(x)[None] if single else jnp.asarray(x), tasks)
        return t, single
    if isinstance(tasks, Task):
        single = np.ndim(tasks.from_log) == 1
        t = jax.tree.map(lambda x: jnp.asarray(x)[None] if single else jnp.asarray(x), tasks)
        return t, single
    single = isinstance(tasks, str) and "," not in tasks and tasks != "all"
    return make_tasks(model, tasks), single


def rollout(model: Model, scenes: Scene, tasks: str | Sequence[str] | Task | Prompt | Sequence[Prompt] = "all",
            key: jax.Array | None = None, options: RolloutOptions | None = None) -> RolloutOutput:
    """Rolls out stored-rate scenes under tasks or prompts with the KV-cached rollout, compiled once per shape.

    scenes: one Scene [T, A, ...] or a batch [B, T, A, ...] at the stored rate (`load_scenes`); the model's view
    is taken inside (`model.prepare`). tasks: a task name, names, "all", Task arrays, a Prompt (`make_prompt`,
    `task_prompt`), a list of prompts (stacked: K prompts, every scene under each), or a Prompt [B, K, ...]
    (scene b under prompts[b, k]). key: PRNG key for sampling (temperature > 0; default key 0). options: a
    `RolloutOptions` (default: the paper's rollout; `RolloutOptions(temperature=1.0, samples=32)` with a
    sampling model, `load_model("gpd_sampling")`: 32 futures of each scene and task in one compiled call).
    Returns RolloutOutput at the model's rate: [B, K, T, A, ...] ([B, K, N, T, A, ...] with N samples), without
    the B axis for one scene and without the K axis for one task (a single name or an unstacked Task).
    """
    options = RolloutOptions() if options is None else options
    single_scene = np.ndim(scenes.xy) == 3
    if single_scene:
        scenes = jax.tree.map(lambda x: x[None], scenes)
    view = model.prepare(scenes, options)
    task_arrays, single_task = _as_tasks(model, tasks)
    if options.log_map == "lanes" and view.polylines is None:
        raise EvalError("log_map='lanes' needs the scenes' lane polylines (load them with gpd_jax.load_scenes)")
    out = rollout_model(model, view, task_arrays, jax.random.key(0) if key is None else key, options)
    if single_task:
        out = jax.tree.map(lambda x: x[:, 0], out)
    if single_scene:
        out = jax.tree.map(lambda x: x[0], out)
    return out


def evaluate(model: Model, scenes_or_dir: Scene | str, tasks: str | Sequence[str] = "all", *,
             options: RolloutOptions | None = None, split: str = "test", num_scenarios: int | None = None,
             batch_size: int = 8, seed: int = 0, variant: str = "paper", horizons_s: Sequence[float] = HORIZONS_S,
             layouts: Sequence[str] | None = None, scene_sums: bool = False, samples: int = 0,
             realism_config: str = "2025") -> dict[str, Any]:
    """Scores every task (and the constant-velocity, log-replay and map baselines, on the same agents) at 3 / 5 /
    8 s on stored-rate scenes Scene [n, ...] or the split of a store directory: the content of `rollout.py`'s
    metrics.json (`results["tasks"][task]["3s"]["agent_ade"]`, `results["ratios"]`, ...; the layout is in
    `gpd_jax.evaluation`). options: how the rollouts run (`RolloutOptions`). variant: which metric variant fills
    the main keys ("paper" or "corrected"). layouts: a label per scene for figures per group. scene_sums=True adds
    `results["scene_sums"]` (each scenario's sums, for `gpd_jax.evaluation.bootstrap.compare_runs`). samples=K adds
    `results["realism"]`: the WOSAC-form realism (`gpd_jax.metrics.realism`, configuration `realism_config`) of K
    rollouts of every task and of the baselines (`gpd_jax.evaluation.realism`)."""
    results, _ = run_evaluation(model, scenes_or_dir, split, task_names=tasks, num_scenarios=num_scenarios,
                                batch_size=batch_size, seed=seed, variant=variant, horizons_s=horizons_s,
                                options=RolloutOptions() if options is None else options, progress=False,
                                log=lambda _msg: None, layouts=layouts, scene_sums=scene_sums, samples=samples,
                                realism_config=realism_config)
    return results


def render(model: Model, scenes: Scene, out: RolloutOutput, tasks: str | Sequence[str], out_dir: str, *,
           size_px: int = 320) -> list[str]:
    """Draws rollouts (`rollout` of the same stored-rate scenes and named tasks) as `<i>_<task>.gif` / `.png`
    under `out_dir`: agents as boxes (the ego, the model's agents and the log's), map lanes decoded by the model's
    tokenizer, a legend and a scale. Returns the paths."""
    names = resolve_task_names(tasks)
    view = model.prepare(scenes if np.ndim(scenes.xy) == 4 else jax.tree.map(lambda x: x[None], scenes))
    pred = jax.tree.map(np.asarray, out)
    if np.ndim(pred.xy) == 3:  # one scene, one task
        pred = jax.tree.map(lambda x: x[None, None], pred)
    elif np.ndim(pred.xy) == 4:  # one scene with K tasks, or B scenes with one task
        pred = jax.tree.map(lambda x: x[None] if view.xy.shape[0] == 1 and len(names) == x.shape[0] else x[:, None],
                            pred)
    items = []
    for i in range(view.xy.shape[0]):
        items.append(RenderItem(
            index=i, scenario_id="",
            pred={k: getattr(pred, k)[i] for k in ("xy", "heading", "valid", "map_tokens")},
            log={k: np.asarray(getattr(view, k)[i]) for k in ("xy", "heading", "valid", "size", "agent_type",
                                                             "map_tokens", "ego_pose")}))
    os.makedirs(out_dir, exist_ok=True)
    return render_items(items, names, out_dir, num_history=model.spec.num_history,
                        frame_period_s=model.spec.frame_period_s, tokenizer=model.tokenizer, size_px=size_px)
