"""gpd_jax: GPD-1 (Generative Pre-training for Driving) in JAX/Flax.

    import gpd_jax, jax
    gpd_jax.list_models()                                            # the shipped models, the default first
    model = gpd_jax.load_model()                                     # the default (or a name, or a path)
    scenes = gpd_jax.load_scenes("data/test", indices=range(4))      # or gpd_jax.build_scenes(dir, 4)
    out = gpd_jax.rollout(model, scenes, ["traffic_simulation", "scene_generation"], jax.random.key(0))
    results = gpd_jax.evaluate(model, scenes, tasks="traffic_simulation")
    fn = gpd_jax.make_rollout_fn(model)                              # pure: fn(params, model.prepare(scenes), ...)
    sim_scenes = gpd_jax.sim.make_sim_scenes(model, scenes)          # closed loop: your planner, GPD agents

The layers, bottom to top (nothing imports upward; `tests/test_layers.py` enforces it): `scene`, `tasks`,
`config`, `zoo`, `fsutil`, `parallel`, `metrics/` | `prompts` | `data/`, `spec`, `options` | `model/`,
`map_tokenizer/` | `checkpoint` | `decoding` | `evaluation/`, `sim/` | `training/`, `api` | command lines.
"""

from gpd_jax.lazy import lazy_names

# imported on first use, so that `import gpd_jax.cliargs` (every command line starts there) does not import JAX
# and a bad flag is refused at once
__getattr__, __dir__ = lazy_names(__name__, {
    "gpd_jax.api": ("build_scenes", "evaluate", "load_scenes", "make_prompt", "make_rollout_fn", "make_tasks",
                    "render", "rollout", "stack_prompts", "task_prompt"),
    "gpd_jax.checkpoint": ("Model", "load_model"),
    "gpd_jax.decoding": ("RolloutOutput",),
    "gpd_jax.geometry": ("RoadGeometry", "lane_direction", "on_road", "signed_distance_to_edge"),
    "gpd_jax.model": ("PlanningHead", "plan_trajectory"),
    "gpd_jax.options": ("RolloutOptions",),
    "gpd_jax.prompts": ("Prompt", "PromptError"),
    "gpd_jax.scene": ("AGENT_TYPES", "TYPE_ID", "Scene", "empty_scene", "wrap_angle"),
    "gpd_jax.spec": ("EvalError", "ModelSpec"),
    "gpd_jax.tasks": ("TASK_NAMES", "Task"),
    "gpd_jax.zoo": ("DEFAULT_MODEL", "ModelCard", "list_models"),
}, submodules=("metrics", "sim"))


__all__ = [
    "AGENT_TYPES",
    "DEFAULT_MODEL",
    "TASK_NAMES",
    "TYPE_ID",
    "EvalError",
    "Model",
    "ModelCard",
    "ModelSpec",
    "PlanningHead",
    "Prompt",
    "PromptError",
    "RoadGeometry",
    "RolloutOptions",
    "RolloutOutput",
    "Scene",
    "Task",
    "build_scenes",
    "empty_scene",
    "evaluate",
    "lane_direction",
    "list_models",
    "load_model",
    "load_scenes",
    "make_prompt",
    "make_rollout_fn",
    "make_tasks",
    "metrics",
    "on_road",
    "plan_trajectory",
    "render",
    "rollout",
    "signed_distance_to_edge",
    "sim",
    "stack_prompts",
    "task_prompt",
    "wrap_angle",
]
__version__ = "0.1.0"
