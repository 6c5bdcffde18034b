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

from gpd_jax import metrics, sim
from gpd_jax.api import (build_scenes, evaluate, load_scenes, make_prompt, make_rollout_fn, make_tasks, render,
                         rollout, stack_prompts, task_prompt)
from gpd_jax.checkpoint import Model, load_model
from gpd_jax.decoding import RolloutOutput
from gpd_jax.geometry import RoadGeometry, lane_direction, on_road, signed_distance_to_edge
from gpd_jax.model import PlanningHead, plan_trajectory
from gpd_jax.options import RolloutOptions
from gpd_jax.prompts import Prompt, PromptError
from gpd_jax.scene import AGENT_TYPES, TYPE_ID, Scene, empty_scene, wrap_angle
from gpd_jax.spec import EvalError, ModelSpec
from gpd_jax.tasks import TASK_NAMES, Task
from gpd_jax.zoo import DEFAULT_MODEL, ModelCard, list_models

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
