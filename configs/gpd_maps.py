"""The recipe of gpd_maps: gpd_traffic's architecture moved onto direction-aware map tokens, for the best generated
maps.

Two stages from the default model of the time, before its INTERACTION fine-tune (runs/soup_legacy2_avg: the
recipe configs/gpd_traffic.py up to its `soup_legacy2` average, or `git show ab4875a:checkpoints/gpd_traffic/
params.npz` and its config.json), each on copies of gpd_traffic's SUMO training stores whose
map tokens were encoded by the stage's tokenizer (a store holds one tokenizer's tokens):

1. `refit`: onto the tokens of map_tokenizer_refit (configs/map_tokenizer.py:refit; the shipped tokenizer
   fine-tuned whole on the wider map data), batch 32 and 8 rollout passes with map feedback on an accelerator
   (one H200; its lease stopped the run at step 1,922 of 2,400), then averaged 0.5 / 0.5 with where it started (the
   average reads the refit tokens: --mixed-tokenizers).
2. `directional`: from that average onto the tokens of map_tokenizer_directional (configs/map_tokenizer.py:
   directional: the refit tokenizer with SLEDGE's lane-heading raster channels) at a 2-core CPU's scale: batch 8,
   2 rollout passes, 800 steps (53 min).

    for t in refit directional; do for s in gen_curved_train legacy_train mix_real_train; do
      mkdir -p data/$t/$s && cp -r data/$s/dataset.json data/$s/train data/$t/$s/
      python -m gpd_jax.map_tokenizer encode --checkpoint runs/tok_$t/export --data data/$t/$s --splits train \
          --frame-stride 10 --force
    done; done
    python train.py --config configs/gpd_maps.py:refit --workdir runs/maps_refit --stop-after 1922     # a GPU
    python -m gpd_jax.checkpoint export runs/maps_refit runs/maps_refit_1922 --step 1922
    python -m gpd_jax.checkpoint average runs/maps_refit_1922 runs/soup_legacy2_avg --weights 0.5 0.5 --config-from 0 \
        --mixed-tokenizers --out runs/maps_refit_avg
    python train.py --config configs/gpd_maps.py:directional --workdir runs/maps_directional
    python -m gpd_jax.checkpoint export runs/maps_directional gpd_maps --tokenizer-ref map_tokenizer_directional

(runs/tok_refit and runs/tok_directional: the tokenizer recipes in configs/map_tokenizer.py. The shipped
map_tokenizer_refit is retired; docs/model-lineage.md has the commit that holds it.)
"""

from gpd_jax.config import gpd_config

STAGES = ("refit", "directional")


def get_config(stage: str = "directional"):
    if stage not in STAGES:
        raise ValueError(f"configs/gpd_maps.py: stage {stage!r} is not one of {STAGES}")
    c = gpd_config()
    # gpd_traffic's architecture and loss (configs/gpd_traffic.py)
    c.data.frame_stride = 10
    c.data.val_dir = "data/mix_real_dev"
    m = c.model
    m.num_frames, m.num_history, m.num_agents = 11, 3, 17
    m.num_layers, m.num_heads, m.ffn_dim, m.head_hidden, m.attn_chunk_frames = 4, 4, 512, 128, 4
    m.predict_delta = m.velocity_residual = m.velocity_inputs = m.agent_lane_residual = True
    c.loss.agent_norm, c.loss.agent_norm_delta = "euclidean", 0.01
    t = c.train
    t.learning_rate, t.warmup_steps, t.min_learning_rate, t.grad_clip = 3e-4, 100, 1e-5, 1.0
    t.rollout_passes, t.map_feedback, t.lane_context_drop = 8, 1.0, 0.25
    t.batch_size, t.steps, t.checkpoint_every, t.keep_checkpoints = 32, 2_400, 600, 8
    t.eval_every, t.eval_rollout_scenarios, t.log_every, t.loader_threads = 0, 64, 50, 12
    tokens = "refit" if stage == "refit" else "directional"
    c.data.dir = ",".join(f"data/{tokens}/{s}:{w}" for s, w in
                          (("gen_curved_train", 0.2), ("legacy_train", 0.4), ("mix_real_train", 0.4)))
    m.map_tokenizer = f"runs/tok_{tokens}/export"
    t.init_from = "runs/soup_legacy2_avg"
    if stage == "directional":
        m.map_tokenizer = "map_tokenizer_directional"
        t.init_from = "runs/maps_refit_avg"
        t.batch_size, t.rollout_passes, t.steps, t.warmup_steps = 8, 2, 800, 50
        t.checkpoint_every, t.loader_threads, t.log_every = 400, 2, 25
    return c
