"""Closed-loop supervised fine-tuning (CAT-K) of gpd_sampling: every parameter trains at the states
the model's own rollouts reach (`train.closed_loop_top_k`; docs/training.md, "Closed-loop fine-tuning").

Each train step rolls the model out from each scene's logged history (traffic simulation: map from the log, ego and
agents generated; the cached rollout every evaluation runs, parameters frozen), keeps at each future frame the
closest to the log of its sampling head's top K = 8 cells, and takes the usual losses (regression, velocity, the
sampling head's likelihood, validity, map) at the reached frames against the log's next frames: from where the
rollout is, return toward the log. Rollout and loss are one compiled step; the run resumes exactly.

This is a candidate recipe, not a shipped model's: its first measurement is in docs/results.md (2026-11-29); no
checkpoint built by it ships yet.

Data (INTERACTION training sites, 2 windows per recording; the same scenes as an on-board tracker sees them; SUMO
generated networks with legacy traffic, where built), `python -m gpd_jax.data ...`:

    gpd-jax data build --source interaction --db ../interaction --split train --max-per-log 2 \
        --out data/i67_interaction_train
    gpd-jax tokenizer encode --checkpoint map_tokenizer --data data/i67_interaction_train --frame-stride 10
    gpd-jax data sensor data/i67_interaction_train --out data/i67_interaction_train_sensor
    gpd-jax data build --source sumo --traffic legacy --split train --scenarios 120 --per-job 20 --seed 67 \
        --out data/i67_sumo_legacy_small
    gpd-jax tokenizer encode --checkpoint map_tokenizer --data data/i67_sumo_legacy_small --frame-stride 10

Training (no validation during the run: choices are made on the development store afterwards, rollout.py):

    python train.py --config configs/gpd_closed_loop.py:catk --workdir runs/closed_loop

Stage `reward`: reward fine-tuning, 4 sampled rollouts of each scene at temperature 0.5, each agent
rewarded -1 for a collision, -1 x its share of frames off the drivable area, +0.5 x its progress (path length over
the log's, at most 1), group-relative advantages over the 4, the policy-gradient loss beside the supervised
teacher-forced loss on the log (the anchor). Meant to start from the `catk` stage's export; this session's first
measurement started it from gpd_sampling (`--config.train.init_from=...` picks the start):

    python train.py --config configs/gpd_closed_loop.py:reward --workdir runs/closed_loop_reward
"""

from gpd_jax.config import gpd_config


STAGES = ("catk", "reward")


def get_config(stage: str = "catk"):
    if stage not in STAGES:
        raise ValueError(f"configs/gpd_closed_loop.py: stage {stage!r} is not one of {STAGES}")
    c = gpd_config()
    c.data.dir = ("data/i67_interaction_train:0.4,data/i67_interaction_train_sensor:0.3,"
                  "data/i67_sumo_legacy_small:0.3")
    c.data.val_dir, c.data.frame_stride = "", 10
    m = c.model  # gpd_sampling's architecture (checkpoints/gpd_sampling/config.json)
    m.num_frames, m.num_history, m.num_agents = 11, 3, 17
    m.num_layers, m.num_heads, m.ffn_dim, m.head_hidden, m.attn_chunk_frames = 4, 4, 512, 128, 4
    m.predict_delta = m.velocity_residual = m.velocity_inputs = m.agent_lane_residual = True
    m.map_tokenizer = "map_tokenizer"
    m.agent_bins, m.agent_bin_extent = 0.5, (8.0, 3.0)
    c.loss.agent_norm, c.loss.agent_norm_delta = "euclidean", 0.01
    t = c.train
    t.init_from, t.trainable, t.closed_loop_top_k = "gpd_sampling", "all", 8
    t.lane_context_drop = 0.0  # traffic simulation: the map (and its lanes) is the log's at every frame
    t.batch_size, t.steps, t.learning_rate, t.warmup_steps, t.min_learning_rate = 8, 160, 1e-4, 10, 1e-5
    t.grad_clip, t.log_every, t.eval_every, t.eval_batches, t.checkpoint_every = 1.0, 10, 0, 0, 50
    t.eval_rollout_scenarios, t.loader_threads = 0, 2
    if stage == "reward":  # 4 sampled rollouts per scene; the teacher-forced loss on the log is the anchor
        c.data.dir = "data/i67_interaction_train:0.6,data/i67_interaction_train_sensor:0.4"  # stores with road geometry
        t.closed_loop_top_k, t.reward_samples, t.reward_temperature = 0, 4, 0.5
        t.reward_weights, t.reward_scale = (1.0, 1.0, 0.5), 1.0
        t.batch_size, t.steps, t.learning_rate, t.warmup_steps = 4, 40, 5e-5, 5
        t.log_every, t.checkpoint_every = 5, 10
    return c
