"""A tiny GPD that trains on a CPU in minutes: the shipped models' view (every 10th stored frame: 3 history + 8
future frames at 1 Hz, ego + 16 agents, the 64 tokens of the shipped map tokenizer) at d 32, 2 layers.

The tiny training run (30 minutes on a busy 2-core machine, the store build 17 of them; README "Train your
own"): 100 SUMO scenes on 20 generated networks, split by network into train (70), val and test (15 each); the
shipped map tokenizer's tokens at every 10th frame; 300 steps of 8 scenes; the test split scored against the
baselines.

    gpd-jax data build --source sumo --out data/tiny --scenarios 100 --per-job 5 --seed 3
    gpd-jax tokenizer encode --checkpoint map_tokenizer --data data/tiny --frame-stride 10
    python train.py --config configs/gpd_tiny.py --workdir runs/tiny
    python rollout.py --checkpoint runs/tiny/export --data data/tiny --split test --out runs/tiny/eval

`configs/gpd_tiny.py:test` is the size the test suite builds on synthetic scenes (11 frames at 10 Hz: 5 history
+ 6 future, ego + 4 agents, 16 map tokens of 32 codes, no map tokenizer).
"""

from gpd_jax.config import gpd_config, set_fields

# d 32, 2 layers, 4 heads: the size both variants share
TINY = {"model.num_frames": 11, "model.d_model": 32, "model.num_layers": 2, "model.num_heads": 4,
        "model.ffn_dim": 64, "model.head_hidden": 32, "model.xy_code_dim": 8, "model.heading_code_dim": 8,
        "model.attn_chunk_frames": 2}
VARIANTS = {
    # 1 Hz on real stores: 3 history + 8 future frames, 17 slots, the shipped map tokenizer's 64 tokens, velocity
    # inputs and the residual over constant velocity (as the shipped models)
    "train": {"data.dir": "data/tiny", "data.frame_stride": 10, "model.num_history": 3, "model.num_agents": 17,
              "model.predict_delta": True, "model.velocity_residual": True, "model.velocity_inputs": True,
              "model.map_tokenizer": "map_tokenizer",
              "train.batch_size": 8, "train.steps": 300, "train.warmup_steps": 30, "train.min_learning_rate": 1e-5,
              "train.grad_clip": 1.0, "train.log_every": 25, "train.eval_every": 150, "train.eval_batches": 1,
              "train.eval_rollout_scenarios": 10, "train.checkpoint_every": 100, "train.loader_threads": 2},
    # synthetic scenes at 10 Hz: 5 history + 6 future frames, 5 slots, 16 map tokens of 32 codes
    "test": {"model.num_history": 5, "model.num_agents": 5, "model.num_map_tokens": 16, "model.codebook_size": 32,
             "train.batch_size": 4, "train.steps": 200, "train.warmup_steps": 10},
}


def get_config(variant: str = "train"):
    if variant not in VARIANTS:
        raise ValueError(f"configs/gpd_tiny.py: variant {variant!r} is not one of {tuple(VARIANTS)}")
    return set_fields(set_fields(gpd_config(), TINY), VARIANTS[variant])
