"""gpd_traffic fine-tuned on recorded INTERACTION traffic (issue 51, step 4; a first, small version).

One stage from the default model `gpd_traffic` (its model fields, copied from checkpoints/gpd_traffic/config.json),
on a mixture of recorded drone traffic (INTERACTION's train sites) and the SUMO legacy-traffic store, with whole
rollouts as gpd_traffic's last stages; it validates on the INTERACTION dev site and exports the best validation
(traffic-simulation agent ADE over constant velocity) to WORKDIR/best. Where INTERACTION comes from, its
non-commercial terms, the importer's conventions and the split by site: docs/data.md, section INTERACTION.

Data (DB: the INTERACTION dataset root, recorded_trackfiles/ and maps/; every track file of the train sites gives
at most 20 windows, drawn at random: 2,550 windows instead of the 10,021 that a window every 3 s gives):

    python -m gpd_jax.data build --source interaction --db DB --split train --max-per-log 20 --workers 2 \
        --out data/interaction_train_small
    python -m gpd_jax.data build --source interaction --db DB --split val --out data/interaction_dev
    (data/legacy_train: the commands in configs/gpd_traffic.py)
    for d in data/interaction_train_small data/interaction_dev; do
        python -m gpd_jax.map_tokenizer encode --checkpoint map_tokenizer --data $d --frame-stride 10; done

Training and evaluation (dev only; the test store is not looked at). The run was made on one H200 (16 ms a step
after a minute of compiling; the stores travelled gzipped in two calls): on the shared 2-core CPU a step takes
30-40 s, but the best validation came at step 50, and WORKDIR/best is written at each validation, so a run
stopped (Ctrl-C) after step 50's validation holds the same best:

    python train.py --config configs/gpd_interaction.py --workdir runs/int_ft          # best: step 50 of 1,000
    python -m gpd_jax.checkpoint average runs/int_ft/best gpd_traffic --weights 0.5 0.5 --config-from 1 \
        --tokenizer-ref map_tokenizer --out runs/int_ft_avg
    python rollout.py --checkpoint runs/int_ft/best --data data/interaction_dev --split val \
        --tasks traffic_simulation --out runs/int_ft_eval
    python rollout.py --checkpoint runs/int_ft/best --data data/mix_real_dev --split val \
        --tasks traffic_simulation --out runs/int_ft_eval_real

Dev figures (traffic-simulation agent ADE / 10 Hz constant velocity at 3 / 5 / 8 s; agent collision % at 3 / 5 / 8 s):

    model                        interaction_dev (765 scenes)            mix_real_dev (150 scenes)
    gpd_traffic                  1.002 / 0.903 / 0.857; 2.6 / 7.5 / 14.6  0.780 / 0.747 / 0.740; 0.7 / 2.9 / 6.3
    this fine-tune (step 50)     0.940 / 0.846 / 0.805; 2.7 / 8.7 / 16.7  0.784 / 0.755 / 0.750; 1.0 / 3.6 / 7.6
    0.5 fine-tune + 0.5 gpd_traffic  0.954 / 0.857 / 0.814; 2.6 / 7.9 / 15.0  0.769 / 0.743 / 0.737; 1.0 / 2.9 / 6.5

The best was chosen on the first 96 dev scenes; on the other 669 the fine-tune's ratios are 0.941 / 0.845 / 0.805
(gpd_traffic 1.005 / 0.905 / 0.859). Longer or faster fine-tuning got worse on dev (docs/results.md, 2026-11-28).
"""

from gpd_jax.config import gpd_config, set_fields

# gpd_traffic's model (checkpoints/gpd_traffic/config.json); train.init_from needs the same model config.
MODEL = {
    "model.num_frames": 11, "model.num_history": 3, "model.num_agents": 17, "model.num_map_tokens": 64,
    "model.codebook_size": 128, "model.d_model": 128, "model.num_layers": 4, "model.num_heads": 4,
    "model.ffn_dim": 512, "model.head_hidden": 128, "model.xy_range": 300.0, "model.xy_levels": [1.0, 0.01],
    "model.xy_code_dim": 48, "model.heading_levels_deg": [20.0, 1.0], "model.heading_code_dim": 32,
    "model.attn_chunk_frames": 4, "model.predict_delta": True, "model.velocity_residual": True,
    "model.velocity_inputs": True, "model.velocity_range": 50.0, "model.velocity_levels": [1.0, 0.05],
    "model.velocity_code_dim": 32, "model.agent_lane_residual": True, "model.lane_context_stride": 4,
    "model.map_tokenizer": "map_tokenizer",
}

# gpd_traffic's loss and its last stages' training terms, then what this fine-tune changes.
TRAIN = {
    "data.dir": "data/interaction_train_small:0.7,data/legacy_train:0.3",
    "data.val_dir": "data/interaction_dev", "data.train_split": "train", "data.val_split": "val",
    "data.frame_stride": 10, "data.frame_period_s": 0.1,
    "loss.agent_norm": "euclidean", "loss.agent_norm_delta": 0.01,
    "train.init_from": "gpd_traffic",
    "train.batch_size": 8, "train.steps": 1_000, "train.learning_rate": 1e-4, "train.warmup_steps": 30,
    "train.min_learning_rate": 1e-5, "train.grad_clip": 1.0,
    "train.rollout_passes": 8, "train.map_feedback": 1.0, "train.lane_context_drop": 0.25,
    # Validation on the first 96 dev scenes every 50 steps; WORKDIR/best keeps the best of them.
    "train.log_every": 25, "train.eval_every": 50, "train.eval_rollout_scenarios": 96,
    "train.best_metric": "rollout_agent_ade_vs_cv_mean", "train.eval_at_start": True,
    "train.checkpoint_every": 1_000, "train.keep_checkpoints": 4, "train.loader_threads": 8,
}


def get_config():
    return set_fields(gpd_config(), {**MODEL, **TRAIN})
