"""The GPD-1 transformer and its parts: agent tokenizer, block-causal attention, the native CPU kernel.

Public names (pure functions of an NNX module; `gpd_jax.checkpoint.build_model` builds one from a config):

* `GPD`: the NNX module (parameters, embeddings, heads).
* `forward(model, tokens)`: teacher-forced pass over whole frames, memory-linear attention.
* `forward_cached(model, tokens, cache, start_frame)`: a block of frames appended to a KV cache.
* `reads_lanes(model_config)`: whether such a model reads vector lanes (its scenes then carry polylines);
  `samples_agents(model_config)`: whether it has a sampling agent head (`agent_bins`).
* `Prediction`, `Modes`, `KVCache`: what the heads return (`Modes`: the sampling head's distribution over the agents'
  next states) and what the cache holds.
* `PlanningHead`, `plan_trajectory(head, hidden[, ego_pose])`: the paper's fine-tuned planner, one decoder layer
  on a frame's ego token -> the ego's next F poses (gpd_jax/model/planning_head.py).
"""

from gpd_jax.model.planning_head import PlanningHead, plan_trajectory, to_ego_frame, to_scene_frame
from gpd_jax.model.transformer import (GPD, MODE_HEAD, KVCache, LaneContext, Modes, Prediction, count_params,
                                      forward, forward_cached, reads_lanes, samples_agents)

__all__ = ["GPD", "MODE_HEAD", "KVCache", "LaneContext", "Modes", "PlanningHead", "Prediction", "count_params",
           "forward", "forward_cached", "plan_trajectory", "reads_lanes", "samples_agents", "to_ego_frame",
           "to_scene_frame"]
