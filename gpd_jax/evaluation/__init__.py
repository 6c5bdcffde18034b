"""Multi-task evaluation of a GPD model on a data split: rollouts, metrics at 3 / 5 / 8 s, baselines, tables.

Modules, by job: `driver` (the batched loop: `run_evaluation`, under `gpd_jax.evaluate`), `preflight` (every check before a model loads),
`scoring` (metric sums of a batch, jitted), `reduce` (sums -> metrics), `report` (tables, strict JSON), `maps`
(the lanes generated maps are scored against), `baselines` (constant velocity, log replay), `render` (pictures),
`keys` (the names of what is reported), `bootstrap` (each scenario's sums: scene-bootstrap intervals and paired
comparisons of runs on the same scenes; `python -m gpd_jax.evaluation compare`), `realism` (the WOSAC-form realism
of K rollouts per scenario, `samples=K`).

What `run_evaluation` does (the command line is `rollout.py` at the repository root):

1. Reads the first N scenarios of a split in store order (10 Hz, 101 frames, 33 slots) and gives the model
   `ModelSpec.view(scene)` (`gpd_jax.spec`) (`scene.subsample(frame_stride, num_frames, num_agents)`, plus stored-rate velocities
   for a `velocity_inputs` model): the model's frame period is
   `frame_stride * frame_period_s` (1 s for the shipped models, 0.1 s for the paper), and the horizons
   3, 5 and 8 s become that many model frames (6 / 10 / 16 at 2 Hz, 30 / 50 / 80 at 10 Hz), labelled "3s" ...
2. Map tokens come from the store where it has them (`map_valid`); otherwise the model's map tokenizer encodes
   the needed frames on the fly (rasterized polylines at each frame's `ego_pose`, as
   `python -m gpd_jax.map_tokenizer encode` does), so a freshly built split needs no encode step.
3. Every task runs in one compiled `rollout_tasks` call per batch of scenarios (the last batch is padded with
   copies of its last scenario, weighted out of every sum, so the shapes and the compile stay the same).
   `log_map="lanes"` re-encodes the logged map around the generated ego in tasks that take the map from the
   log but generate the ego (traffic simulation, motion planning) inside that compiled rollout; the default,
   "tokens", feeds the logged tokens (encoded around the logged ego), as the paper does. `gen_map="warp"` moves
   the last given map with the ego where the map is generated (the model's tokens only in cells it did not see;
   `gpd_jax.decoding`); the default, "model", keeps every generated token the model's, as the paper does.
4. Metrics per task (`score_batch`, jitted): ego ADE / FDE / collision rate where the task generates the ego,
   agent ADE / FDE / collision rate where it generates the agents, map F1 / precision / recall / lateral /
   Chamfer where it generates the map. Map metrics decode the predicted tokens of the future frames with the
   tokenizer's decoder and compare them, frame by frame in that frame's ego frame, with the ground-truth SLEDGE
   vector lanes of those frames (`gpd_jax.data.lanes`).
5. Baselines in the same run, on the same slots: constant velocity and log replay, computed on the full-rate
   (10 Hz) scene and then subsampled to the model's frames (so constant velocity takes its velocity from the
   last two 10 Hz history frames: more recent motion than a model at a lower frame rate ever sees), and
   `constant_velocity_model_rate`, whose velocity is the difference of the last two *model* frames (the same
   information the model gets; identical to the former at stride 1). Log replay has zero ADE / FDE; its
   collision rate is the log's own, the floor a generator should not exceed. Where the scenes carry their lane
   polylines, `constant_velocity_lanes` too (not in the paper): constant velocity's speed along the lane each
   agent is on, its offset from the lane kept (`baselines.follow_lanes`): what the map alone gives.
   Two map baselines where a task generates the map: `map_tokenizer_reconstruction` (the logged tokens
   decoded: the ceiling of any generated map) and `map_persistence` (the current frame's ground-truth lanes
   carried into each future frame with the logged ego pose: the map seen now, kept, never extended; the map
   analogue of constant velocity; its F1 counts points exactly on the ground truth as hits, which the paper's
   F1 does not). The paper's F1 aligns points by index along each matched line, so a lane cut by an earlier
   window edge scores low even where it lies on the right road.

**Scored agents**: those valid at the current frame (the last history frame), for the model and the baselines
alike. Slots not valid at the current frame are neither scored nor obstacles (they are removed from the
ground-truth validity before scoring). Slots a task takes from the log are not scored but stay obstacles for
the collision test of the generated ones.

**Variants** (`gpd_jax.metrics`): "paper" reproduces the official code's definitions (quirks included), "corrected"
normalises properly. Both are computed in every run; the chosen one fills the main keys (`ego_ade`,
`map_chamfer`, ...) and the other one is written beside it with its name as a suffix (`ego_ade_corrected` when
the main variant is "paper", `ego_ade_paper` when it is "corrected"). For the map only the Chamfer distance has
two definitions (paper: index-aligned squared distances, m^2; corrected: set-based, metres); F1, precision,
recall and lateral distance have the paper's single definition.

Aggregation is exact: every batch yields sums and counts (`agent_metric_sums`, `map_metric_sums`) which are
added in float64 on the host, and ratios are formed once at the end (`reduce_results`). Map metrics are formed
per future step and averaged over the steps up to the horizon, as the official code does.

metrics.json (written by rollout.py; NaN written as null)::

    {"checkpoint", "data", "split", "scenarios": n, "variant": "paper", "other_variant_suffix": "_corrected",
     "frame_period_s": 0.5, "frame_stride", "stored_frame_period_s", "num_history", "num_future", "num_agents",
     "horizons": {"3s": 6, "5s": 10, "8s": 16},                  # label -> model frames
     "scored_agents": "valid at the current frame", "num_scored_agents": ...,
     "task_generates": {task: ["ego", "agent", "map"]}, "map_tokens": {"from_store": n1, "encoded": n2},
     "log_map": "tokens" | "lanes", "gen_map": "model" | "warp",
     "temperature", "top_k", "top_p" (only where set), "seed",
     "tasks": {task: {"3s": {"ego_ade", "ego_fde", "ego_collision", "ego_collision_frames",  # if it makes the ego
                             "agent_ade", "agent_fde", "agent_collision", "agent_collision_frames",  # the agents
                             "<same>_corrected",                           # the other variant
                             "map_f1", "map_precision", "map_recall", "map_lateral",
                             "map_chamfer", "map_chamfer_corrected", "map_chamfer_corrected_skipped"}}},
     "baselines": {"constant_velocity": {"3s": {ego_* and agent_* as above}},
                   "constant_velocity_model_rate": {...}, "log_replay": {...},
                   "constant_velocity_lanes": {...},         # where the scenes have lane polylines
                   "map_tokenizer_reconstruction": {"3s": {map_* as above}},  # logged tokens decoded
                   "map_persistence": {"3s": {map_* as above}}},  # current lanes carried forward
     "ratios": {"traffic_simulation_agent_ade_over_constant_velocity": {"3s": r, "5s": r, "8s": r},
                "traffic_simulation_agent_ade_over_constant_velocity_model_rate": {...},
                "traffic_simulation_agent_ade_over_constant_velocity_lanes": {...}},  # with that baseline
     "ratio_targets": {...: {"3s": 0.8, "5s": 0.75, "8s": 0.7}},
     "motion_split": {"stationary_below_mps": 0.5, "speed": "...", "classes": ["stationary", "moving",
                                                                          "speed_unknown"],
                      "tasks": {task: {"3s": {"agent_ade_stationary", "agent_fde_stationary", "agent_n_stationary",
                                              "agent_ade_stationary_corrected", ..., "ego_ade_moving", ...}}},
                      "baselines": {"constant_velocity": {...}, "constant_velocity_model_rate": ..., "log_replay": ...},
                      "ratios": {"traffic_simulation_over_constant_velocity": {"agent_stationary": {"3s": r}, ...},
                                 "traffic_simulation_over_constant_velocity_model_rate": {...},
                                 "traffic_simulation_over_constant_velocity_lanes": {...}}},
     "by_layout": {layout: {"scenarios": n, "tasks": ..., "baselines": ..., "ratios": ...,
                            "motion_split": ...}},  # 2+ layouts only
     "realism": {"config", "rules", "samples", "weights", "left_out", "evaluated", "frame_rate",  # samples=K
                 "tasks": {task: {"metametric", "kinematic", "interactive", "map_based", "<feature>_likelihood",
                                  "min_ade", "ade", "collision_rate", "offroad_rate", "scenarios", ...}},
                 "baselines": {"constant_velocity" | "constant_velocity_lanes" | "log": {...}}},
     "realism_official": {...},      # the same under the official code's counting rules ("rules": "official")
     "timing_s": {...}, "render": {...}}                           # render: only with --render

**Motion split** ("motion_split"): ego and agent ADE / FDE of every task and baseline again, separately for slots
*stationary* (speed < 0.5 m/s at the current frame), *moving* and of unknown speed (not valid at the stored frame
before the current one: first seen now), with `*_n_<class>` the number of such slots with a valid log frame within
the horizon. The speed is the stored-rate backward difference at the current frame (the velocity a
`velocity_inputs` model is given, and the one constant velocity extrapolates). Each class's sums are the unsplit
sums restricted to it (the paper variant's N_exist too), so the three classes add up to the unsplit figures.

ADE / FDE in metres, collision rates in percent (`*_collision`: the paper's share of agents with at least one
collision within the horizon; `*_collision_frames`: the per-frame rate of the official code), map lateral distance in metres, map Chamfer in m^2 (paper) or
metres (corrected).
"""

from gpd_jax.lazy import lazy_names

# imported on first use: the command lines import this package before they check their arguments (no JAX yet)
__getattr__, __dir__ = lazy_names(__name__, {
    "gpd_jax.evaluation.baselines": ("constant_velocity", "log_replay"),
    "gpd_jax.evaluation.bootstrap": ("SceneSums", "compare_runs", "load_scene_sums"),
    "gpd_jax.evaluation.driver": ("RenderItem", "run_evaluation"),
    "gpd_jax.evaluation.preflight": ("SceneRecords", "check_compatible", "preflight"),
    "gpd_jax.evaluation.reduce": ("reduce_results",),
    "gpd_jax.evaluation.render": ("render_items", "render_rollout"),
    "gpd_jax.evaluation.report": ("format_tables", "to_json_compatible"),
    "gpd_jax.evaluation.scoring": ("add_sums", "baseline_predictions", "score_batch"),
    "gpd_jax.spec": ("EvalError",),
})

__all__ = ["EvalError", "RenderItem", "SceneRecords", "SceneSums", "add_sums", "baseline_predictions",
           "check_compatible", "compare_runs", "constant_velocity", "format_tables", "load_scene_sums",
           "log_replay", "preflight", "reduce_results", "render_items", "render_rollout", "run_evaluation",
           "score_batch", "to_json_compatible"]
