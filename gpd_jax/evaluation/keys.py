"""Names of what `gpd_jax.evaluate` reports: baselines, metric groups, ratio keys and their targets (the keys of
`metrics.json`)."""

LOG_MAP_SOURCES = ("tokens", "lanes")  # what a task that takes the map from the log feeds (see `evaluate`)
# Where a generated map comes from: every token the model's (the paper's), or the last given map moved with the
# ego and the model's tokens only in cells it did not see (`gpd_jax.decoding`'s map_warp).
GEN_MAP_SOURCES = ("model", "warp")
BASELINE_NAMES = ("constant_velocity", "constant_velocity_model_rate", "log_replay")
# Constant velocity's speed along the lanes (`gpd_jax.evaluation.baselines.follow_lanes`; not in the paper): scored
# where the scenes carry their lane polylines, after the other baselines.
LANE_BASELINE = "constant_velocity_lanes"
OPTIONAL_BASELINES = (LANE_BASELINE,)
# The logged map tokens decoded and scored like a map task: the ceiling any generated map can reach.
TOKENIZER_CEILING = "map_tokenizer_reconstruction"
# The current frame's ground-truth lanes carried into each future frame with the logged ego pose, nothing added:
# the map analogue of constant velocity (what a generator gets by keeping the map it sees and predicting nothing).
MAP_PERSISTENCE = "map_persistence"
MAP_BASELINES = (TOKENIZER_CEILING, MAP_PERSISTENCE)
SCORED_AGENTS = "valid at the current frame"
# collision: share of entities with at least one collision within the horizon (the paper's definition);
# collision_frames: per-frame rate (the official code's) -- see gpd_jax.metrics.agents.
AGENT_METRICS = ("ade", "fde", "collision", "collision_frames")
MAP_METRICS = ("map_f1", "map_precision", "map_recall", "map_lateral")
# Cut-invariant map score (gpd_jax.metrics.map.reduce_cutfree), beside the paper's F1 when the sums carry it.
MAP_CUTFREE_METRICS = ("map_f1_cutfree", "map_precision_cutfree", "map_recall_cutfree", "map_chamfer_cutfree",
                       "map_f1_cutfree_directed")
# The paper-table targets of the traffic-simulation agent ADE relative to constant velocity.
RATIO_TARGETS = {"3s": 0.8, "5s": 0.75, "8s": 0.7}
RATIO_KEY = "traffic_simulation_agent_ade_over_constant_velocity"
RATIO_KEY_MODEL_RATE = "traffic_simulation_agent_ade_over_constant_velocity_model_rate"
RATIO_KEY_LANES = "traffic_simulation_agent_ade_over_constant_velocity_lanes"
# ADE / FDE split by motion at the current frame (`metrics.json`'s "motion_split"; `gpd_jax.metrics.agents`).
MOTION_SPLIT = "motion_split"
MOTION_SPEED = ("stored-rate backward difference at the current frame: |xy[c] - xy[c-1]| / stored frame period "
                "(the velocity input of a velocity_inputs model and constant velocity's velocity); unknown where "
                "the slot is not valid at both frames")
# The model / baseline ratios of the motion split: (key, task, baseline).
MOTION_RATIOS = (("traffic_simulation_over_constant_velocity", "traffic_simulation", "constant_velocity"),
                 ("traffic_simulation_over_constant_velocity_model_rate", "traffic_simulation",
                  "constant_velocity_model_rate"),
                 ("traffic_simulation_over_constant_velocity_lanes", "traffic_simulation", LANE_BASELINE))
