"""gpd_jax: GPD-1 (Generative Pre-training for Driving) in JAX/Flax.

    import gpd_jax, jax
    model = gpd_jax.load_model()                                     # the shipped model
    scenes = gpd_jax.build_scenes("data/quick", num_scenarios=4)     # or gpd_jax.load_scenes(store_dir)
    out = gpd_jax.rollout(model, scenes, ["traffic_simulation", "scene_generation"], jax.random.key(0))
    results = gpd_jax.evaluate(model, scenes, tasks="traffic_simulation")
    fn = gpd_jax.make_rollout_fn(model)                              # pure: fn(params, scenes, tasks, key)
    head_model = gpd_jax.load_model("checkpoints/gpd_sumo_plan_head")  # GPD + the fine-tuned planning head
    plan = gpd_jax.plan_trajectory(head_model.module, hidden)        # one frame's tokens -> ego's next 8 s
    sim_scenes = gpd_jax.sim.make_sim_scenes(model, scenes)          # closed loop: your planner, GPD agents
    out = gpd_jax.sim.run(model, sim_scenes, gpd_jax.sim.make_policy("cv", model), jax.random.key(0), agents="gpd")

The layers, bottom to top (nothing imports upward; `tests/test_layers.py` enforces it): `scene`, `tasks`,
`spec`, `config`, `fsutil`, `parallel`, `data/`, `metrics/` | `model/`, `map_tokenizer/` | `checkpoint` |
`decoding` | `evaluation/`, `sim/` | `training/`, `api` | command lines (`bench`,
`python -m gpd_jax.{data,map_tokenizer,plan}`, `train.py`, `rollout.py`).
"""

from gpd_jax import metrics, sim
from gpd_jax.api import (Model, build_scenes, evaluate, load_model, load_scenes, make_prompt, make_rollout_fn,
                         make_tasks, prepare, render, rollout, stack_prompts, task_prompt)
from gpd_jax.decoding import RolloutOutput
from gpd_jax.model import PlanningHead, plan_trajectory
from gpd_jax.geometry import RoadGeometry, lane_direction, on_road, signed_distance_to_edge
from gpd_jax.prompts import Prompt, PromptError
from gpd_jax.scene import AGENT_TYPES, TYPE_ID, Scene, empty_scene, wrap_angle
from gpd_jax.spec import EvalError, ModelSpec
from gpd_jax.tasks import TASK_NAMES, Task

__all__ = [
    "AGENT_TYPES",
    "TASK_NAMES",
    "TYPE_ID",
    "EvalError",
    "Model",
    "ModelSpec",
    "PlanningHead",
    "Prompt",
    "PromptError",
    "RoadGeometry",
    "RolloutOutput",
    "Scene",
    "Task",
    "build_scenes",
    "empty_scene",
    "evaluate",
    "lane_direction",
    "load_model",
    "load_scenes",
    "make_prompt",
    "make_rollout_fn",
    "make_tasks",
    "metrics",
    "on_road",
    "plan_trajectory",
    "prepare",
    "render",
    "rollout",
    "signed_distance_to_edge",
    "sim",
    "stack_prompts",
    "task_prompt",
    "wrap_angle",
]
__version__ = "0.1.0"
