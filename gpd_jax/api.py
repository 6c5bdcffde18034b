"""The public front door (re-exported by `gpd_jax/__init__.py`): load a model and scenes, roll out, evaluate,
draw, and the pure rollout function under it all.

    import gpd_jax, jax
    model = gpd_jax.load_model()                                      # the shipped model
    scenes = gpd_jax.load_scenes("data/heldout", indices=range(4))    # Scene [4, 101, 33, ...] at 10 Hz
    out = gpd_jax.rollout(model, scenes, ["traffic_simulation", "scene_generation"], jax.random.key(0))
    out.xy.shape                                                      # [4, 2, T, A, 2] at the model's rate
    metrics = gpd_jax.evaluate(model, scenes, tasks="traffic_simulation")

    fn = gpd_jax.make_rollout_fn(model)                               # fn(params, scenes, tasks, key): pure
    model_scenes = gpd_jax.prepare(model, scenes)                     # the model's view, map tokens filled
    out = jax.jit(fn)(model.params, model_scenes, gpd_jax.make_tasks(model, "closed_loop"), key)

Scenes come in at the stored rate (`load_scenes`); `rollout` and `evaluate` take the model's view inside
(`model.spec.view`: its frame stride, history and future, agent slots) and encode map tokens on the fly where the
store has none. `make_rollout_fn` works on scenes already in the model's view (`prepare`), so that nothing but
array code stands between the parameters and the output.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from gpd_jax.checkpoint import Model, load_model
from gpd_jax.data.build import build_sumo
from gpd_jax.data.loader import SplitSource, to_scene
from gpd_jax.decoding import LogLanes, RolloutOutput, drop_unread_lanes, rollout_jit, rollout_recompute, rollout_tasks
from gpd_jax.evaluation.driver import RenderItem
from gpd_jax.evaluation.driver import evaluate as _evaluate
from gpd_jax.evaluation.maps import encode_map_frames
from gpd_jax.evaluation.render import render_items
from gpd_jax.prompts import Prompt, as_prompt, prompt_from_task, stack_prompts
from gpd_jax.prompts import make_prompt as _make_prompt
from gpd_jax.scene import Scene
from gpd_jax.spec import EvalError
from gpd_jax.tasks import Task, resolve_task_names
from gpd_jax.tasks import make_tasks as _make_tasks

__all__ = ["Model", "Prompt", "build_scenes", "evaluate", "load_model", "load_scenes", "make_prompt",
           "make_rollout_fn", "make_tasks", "prepare", "render", "rollout", "stack_prompts", "task_prompt"]


def load_scenes(data_dir: str, split: str = "test", indices: Sequence[int] | None = None) -> Scene:
    """Scenes of a data store at the stored rate, with their lane polylines: Scene [n, T, A, ...] (numpy leaves;
    T = 101 frames at 10 Hz, A = 33 slots as stored). `indices`: which samples (default: the whole split)."""
    if not os.path.isdir(os.path.join(data_dir, split)):
        raise EvalError(f"split {split!r} not found in {data_dir}")
    src = SplitSource(data_dir, split, with_polylines=True)
    idx = range(len(src)) if indices is None else [int(i) for i in indices]
    if not len(idx):
        raise EvalError("no scenes asked for (indices is empty)")
    recs = [src[i] for i in idx]
    return to_scene({k: np.stack([r[k] for r in recs]) for k in recs[0]})


def build_scenes(out_dir: str, num_scenarios: int = 8, seed: int = 7, split: str = "test", *,
                 workers: int = 1) -> Scene:
    """Simulates `num_scenarios` SUMO scenes on networks generated from `seed` into a store at `out_dir`
    (resumed if it is already there) and returns them (`load_scenes`). About a second per scene on a CPU core."""
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
    if choices.get("lanes") is not None and model.tokenizer is None:
        raise EvalError("a vector-map prompt (lanes) needs the model's map tokenizer, and the model has none")
    view = scene
    if (scene.num_frames, scene.num_agents) != (model.spec.num_frames, model.spec.num_agents):
        view = jax.tree.map(lambda x: x[0], prepare(model, jax.tree.map(lambda x: np.asarray(x)[None], scene)))
    choices.setdefault("frame_period_s", model.spec.frame_period_s)
    return _make_prompt(jax.tree.map(np.asarray, view), model.spec.num_history, **choices)


def prepare(model: Model, scenes: Scene) -> Scene:
    """The model's view of stored-rate scenes (`model.spec.view`: frames, slots, velocities), with map tokens
    encoded on the fly by its tokenizer where the scenes have none: Scene [..., T, A, ...] at the model's rate.
    The lane polylines are kept (for `log_map="lanes"`)."""
    view = model.spec.view(scenes)
    missing = ~np.asarray(view.map_valid).all(axis=-1)
    if missing.any():
        if model.tokenizer is None or view.polylines is None:
            raise EvalError("the scenes have no map tokens at the model's frames, and "
                            + ("the model has no map tokenizer" if model.tokenizer is None
                               else "no lane polylines to encode them from"))
        lead = view.map_tokens.shape[:-2]
        flat = lambda x: np.reshape(np.asarray(x), (-1,) + np.shape(x)[len(lead):])
        enc = np.asarray(encode_map_frames(model.tokenizer, model.tokenizer.params, flat(view.polylines),
                                           flat(view.polyline_valid), flat(view.ego_pose))).reshape(view.map_tokens.shape)
        tokens = np.where(missing[..., None, None], enc, np.asarray(view.map_tokens)).astype(np.int32)
        view = view.replace(map_tokens=tokens, map_valid=np.ones_like(np.asarray(view.map_valid)))
    return view


def _check_gen_map(model: Model, gen_map: str) -> bool:
    """Whether `gen_map` asks for the warp ("warp"; needs the model's tokenizer) or not ("model")."""
    if gen_map not in ("model", "warp"):
        raise ValueError(f"gen_map must be 'model' or 'warp', got {gen_map!r}")
    if gen_map == "warp" and model.tokenizer is None:
        raise EvalError("gen_map='warp' moves generated maps through the model's map tokenizer, and the model has none")
    return gen_map == "warp"


def make_rollout_fn(model: Model, *, temperature: float | None = None, method: str = "cached",
                    log_map: str = "tokens", gen_map: str = "model") -> Callable[..., RolloutOutput]:
    """The rollout as a pure function of the parameters: `fn(params, scenes, tasks, key) -> RolloutOutput`.

    scenes: Scene [S, T, A, ...] in the model's view (`prepare`); tasks: Task [K, ...] (`make_tasks`) or Prompt
    [K, ...] / [S, K, ...] (`make_prompt`, `stack_prompts`); key: a
    PRNG key (used at temperature > 0); params: a pytree shaped like `model.params` (swap or perturb it freely).
    Returns RolloutOutput [S, K, T, ...]. Nothing is compiled until you `jax.jit` it; it also `vmap`s.

    method: "cached" (the KV-cached rollout: fast; its attention loops over a traced number of cache chunks, so
    it is not reverse-differentiable) or "recompute" (the full-prefix forward at every frame, the official
    method: slower, and `jax.grad` goes through it). log_map "lanes": tasks that take the map from the log but
    generate the ego get the log's lanes (`scenes.polylines`) encoded around the generated ego each frame.
    gen_map "warp": where the map is generated, the last given map moves with the ego and the model's tokens
    fill only the cells it did not see (`gpd_jax.decoding`).
    """
    if method not in ("cached", "recompute"):
        raise ValueError(f"method must be 'cached' or 'recompute', got {method!r}")
    if log_map not in ("tokens", "lanes"):
        raise ValueError(f"log_map must be 'tokens' or 'lanes', got {log_map!r}")
    if log_map == "lanes" and model.tokenizer is None:
        raise EvalError("log_map='lanes' needs the model's map tokenizer, and the model has none")
    warp_on = _check_gen_map(model, gen_map)
    graphdef, rest, h = model.graphdef, model.rest, model.spec.num_history
    temp = float(model.config.rollout.temperature if temperature is None else temperature)
    tok = model.tokenizer

    def fn(params, scenes: Scene, tasks: Task, key) -> RolloutOutput:
        module = nnx.merge(graphdef, params, rest)
        lanes = encoder = None
        if log_map == "lanes":
            if scenes.polylines is None:
                raise EvalError("log_map='lanes' needs the scenes' lane polylines (Scene.polylines)")
            lanes, encoder = LogLanes(scenes.polylines, scenes.polyline_valid), tok.pose_encoder(tok.params)
        scenes = drop_unread_lanes(model.config.model, scenes)
        if isinstance(tasks, Prompt) and tasks.lanes is not None:  # a prompt's own vector map
            if tok is None:
                raise EvalError("a vector-map prompt (lanes) needs the model's map tokenizer, and the model has none")
            encoder = tok.pose_encoder(tok.params)
        warp = tok.warper(tok.params) if warp_on else None
        if method == "cached":
            return rollout_tasks(module, scenes, tasks, key, h, temp, lanes, encoder, warp)
        tasks = as_prompt(tasks, scenes.xy.shape[-3])
        per_scene = tasks.from_log.ndim == 4
        s, k = scenes.xy.shape[0], tasks.from_log.shape[1 if per_scene else 0]
        rep = lambda x: jnp.repeat(x, k, axis=0)
        flat_s, flat_l = jax.tree.map(rep, (scenes, lanes))
        flat_t = (jax.tree.map(lambda x: x.reshape((s * k,) + x.shape[2:]), tasks) if per_scene else
                  jax.tree.map(lambda x: jnp.tile(x, (s,) + (1,) * (x.ndim - 1)), tasks))
        one = lambda sc, ta, ke, ln: rollout_recompute(module, sc, ta, ke, h, temp, ln, encoder, warp)
        out = jax.vmap(one)(flat_s, flat_t, jax.random.split(key, s * k), flat_l)
        return jax.tree.map(lambda x: x.reshape((s, k) + x.shape[1:]), out)

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
            key: jax.Array | None = None, *, temperature: float | None = None, log_map: str = "tokens",
            gen_map: str = "model") -> RolloutOutput:
    """Rolls out stored-rate scenes under tasks or prompts with the KV-cached rollout, compiled once per shape.

    scenes: one Scene [T, A, ...] or a batch [B, T, A, ...] at the stored rate (`load_scenes`); the model's view
    is taken inside, map tokens encoded on the fly where missing. tasks: a task name, names, "all", Task arrays,
    a Prompt (`make_prompt`, `task_prompt`), a list of prompts (stacked: K prompts, every scene under each), or
    a Prompt [B, K, ...] (scene b under prompts[b, k]). key: PRNG key for sampling (temperature > 0; default 0).
    log_map / gen_map: as `make_rollout_fn`.
    Returns RolloutOutput at the model's rate: [B, K, T, A, ...], without the B axis for one scene and without
    the K axis for one task (a single name or an unstacked Task).
    """
    single_scene = np.ndim(scenes.xy) == 3
    if single_scene:
        scenes = jax.tree.map(lambda x: x[None], scenes)
    view = prepare(model, scenes)
    task_arrays, single_task = _as_tasks(model, tasks)
    key = jax.random.key(0) if key is None else key
    temp = float(model.config.rollout.temperature if temperature is None else temperature)
    extra: dict[str, Any] = {}
    if isinstance(task_arrays, Prompt) and task_arrays.lanes is not None:
        if model.tokenizer is None:
            raise EvalError("a vector-map prompt (lanes) needs the model's map tokenizer, and the model has none")
        extra = dict(tok=model.tokenizer, tok_params=model.tokenizer.params)
    if log_map == "lanes":
        if model.tokenizer is None or view.polylines is None:
            raise EvalError("log_map='lanes' needs the model's map tokenizer and the scenes' lane polylines")
        extra = dict(extra, tok=model.tokenizer, tok_params=model.tokenizer.params,
                     lanes=LogLanes(jnp.asarray(view.polylines), jnp.asarray(view.polyline_valid)))
    elif log_map != "tokens":
        raise ValueError(f"log_map must be 'tokens' or 'lanes', got {log_map!r}")
    if _check_gen_map(model, gen_map):
        extra = dict(extra, tok=model.tokenizer, tok_params=model.tokenizer.params, map_warp=True)
    view = jax.tree.map(jnp.asarray, drop_unread_lanes(model.config.model, view))
    out = rollout_jit(model.graphdef, model.params, model.rest, view, task_arrays, key, model.spec.num_history,
                      temp, **extra)
    if single_task:
        out = jax.tree.map(lambda x: x[:, 0], out)
    if single_scene:
        out = jax.tree.map(lambda x: x[0], out)
    return out


def evaluate(model: Model, scenes_or_dir: Scene | str, tasks: str | Sequence[str] = "all", *, split: str = "test",
             num_scenarios: int | None = None, **kwargs) -> dict[str, Any]:
    """Scores every task (and the constant-velocity, log-replay and map baselines) at 3 / 5 / 8 s on stored-rate
    scenes Scene [n, ...] or the split of a store directory: the content of `rollout.py`'s metrics.json
    (`results["tasks"][task]["3s"]["agent_ade"]`, ...). Other keyword arguments as `gpd_jax.evaluation.evaluate`
    (batch_size, seed, variant, horizons_s, log_map, gen_map, temperature, progress, log; scene_sums=True adds
    `results["scene_sums"]`, each scenario's sums, for `gpd_jax.evaluation.bootstrap.compare_runs`)."""
    kwargs.setdefault("progress", False)
    kwargs.setdefault("log", lambda _msg: None)
    results, _ = _evaluate(model, scenes_or_dir, split, task_names=tasks, num_scenarios=num_scenarios, **kwargs)
    return results


def render(model: Model, scenes: Scene, out: RolloutOutput, tasks: str | Sequence[str], out_dir: str, *,
           size_px: int = 320) -> list[str]:
    """Draws rollouts (`rollout` of the same stored-rate scenes and named tasks) as `<i>_<task>.gif` / `.png`
    under `out_dir`: agents as boxes (given ones pale), map lanes decoded by the model's tokenizer. Returns the
    paths."""
    names = resolve_task_names(tasks)
    view = prepare(model, scenes if np.ndim(scenes.xy) == 4 else jax.tree.map(lambda x: x[None], scenes))
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

