"""The map tokenizers' recipes (stage 1): 256 x 256 bird's-eye lane rasters -> 8 x 8 tokens of a 128-code VQ-VAE,
decoded back into 50 lane lines of 20 points by a DETR decoder.

Variants (`configs/map_tokenizer.py:VARIANT`); the shipped ones were trained on a 2-core CPU except `refit`:

* `paper`: the official deployment size (ResNet-50 encoder, decoder d 512): `gpd_jax.config.map_tokenizer_config()`.
* `tiny`: a CPU-sized tokenizer (a space-to-depth stem and three basic stages, a 3-layer d 128 decoder), 4,000
  steps: the first stage of map_tokenizer.
* `decoder`: its decoder deepened to 6 layers and trained alone (`train.decoder_only`: the tokens stay the same).
* `netframes`: that decoder retrained on map-only frames of 1,500 more generated networks and the real training
  tiles (`python -m gpd_jax.map_tokenizer netframes`) beside traffic stores: the shipped map_tokenizer.
* `refit`: map_tokenizer's encoder, codebook and decoder fine-tuned together on that data (new tokens; one H200,
  4,000 steps of 64): map_tokenizer_refit (retired; the stepping stone of map_tokenizer_directional).
* `directional`: `refit` again from its result with SLEDGE's line channels (occupancy, cos and sin of the lane
  heading: `raster.direction`), 6,000 CPU steps of 32: the shipped map_tokenizer_directional.
* `vector_tiny`: the vector encoder (`model.encoder.kind` "vector": lane segments -> one token per 8 m cell,
  `gpd_jax.map_tokenizer.vector`) with the tiny decoder, from scratch on real and generated maps, dev on SR
  (docs/tokenizer.md, "The vector encoder"); `vector`: its accelerator size (the paper's decoder).
* `vector_tiny_continuous` / `vector_tiny_maps`: dev probes of the vector recipe (no codebook; more real training
  maps), docs/results.md.
* `test` / `vector_test`: the sizes the test suite trains on synthetic lanes.

    python train.py --config configs/map_tokenizer.py:tiny --workdir runs/tok_tiny
    python -m gpd_jax.map_tokenizer export --workdir runs/tok_tiny --out runs/tok_tiny/export
    python train.py --config configs/map_tokenizer.py:decoder --workdir runs/tok_decoder    # and export, likewise
    python -m gpd_jax.map_tokenizer netframes --out data/netframes_gen --generated 1500 --seed 909
    python -m gpd_jax.map_tokenizer netframes --out data/netframes_real --real data/realnets/train/*.net.xml.gz \
        --real-lefthand
    python train.py --config configs/map_tokenizer.py:netframes --workdir runs/tok_netframes     # 38 min
    python train.py --config configs/map_tokenizer.py:refit --workdir runs/tok_refit            # a GPU
    python train.py --config configs/map_tokenizer.py:directional --workdir runs/tok_directional # 58 min

(data/sumo6k and the traffic stores: configs/gpd_traffic.py; the dev stores the choices were made on:
docs/results.md.)
"""

from gpd_jax.config import map_tokenizer_config, recipe_stages, set_fields

# variant -> (the variant it starts from, the fields it changes); "paper" is the schema's defaults

STAGES = {
    "tiny": (None, {
        "data.dir": "data/sumo6k",
        "model.encoder.block": "basic", "model.encoder.stage_sizes": (1, 1, 1), "model.encoder.stage_strides": (1, 2, 2),
        "model.encoder.width": 32, "model.encoder.stem_patch": 8, "model.encoder.stem_kernel": 3,
        "model.encoder.stem_stride": 1, "model.encoder.stem_pool": False, "model.encoder.norm_groups": 8,
        "model.encoder.head_channels": 128,
        "model.decoder.d_model": 128, "model.decoder.num_heads": 4, "model.decoder.num_layers": 3,
        "model.decoder.ffn_dim": 512,
        "train.batch_size": 32, "train.num_steps": 4_000, "train.warmup_steps": 200, "train.lr": 1e-3,
        "train.codebook_lr": 1e-3, "train.end_lr_factor": 0.01, "train.kmeans_rasters": 256,
        "train.kmeans_at_step": 1_000, "train.restart_every": 100, "train.eval_every": 500, "train.eval_batches": 8,
        "train.checkpoint_every": 250}),
    "decoder": ("tiny", {
        "model.decoder.num_layers": 6, "train.init_from": "runs/tok_tiny/export", "train.decoder_only": True,
        "train.num_steps": 12_000, "train.warmup_steps": 100, "train.lr": 5e-4}),
    "netframes": ("decoder", {
        "data.dir": ("data/netframes_gen:0.4,data/netframes_real:0.2,data/legacy_train:0.15,"
                     "data/gen_curved_train:0.1,data/mix_real_train:0.075,data/real2_train:0.075"),
        "data.eval_dir": "data/gen_dev_legacy", "data.gt_recut": "join_ends",
        "train.init_from": "runs/tok_decoder/export", "train.num_steps": 5_000, "train.lr": 3e-4,
        "train.eval_every": 1_000}),
    "refit": ("netframes", {
        "data.eval_dir": "data/mix_real_dev", "data.processes": 4, "train.init_from": "map_tokenizer",
        "train.decoder_only": False, "train.batch_size": 64, "train.num_steps": 4_000, "train.codebook_lr": 3e-4,
        "train.eval_every": 4_000, "train.eval_batches": 20, "train.checkpoint_every": 1_000, "train.log_every": 100}),
    "directional": ("refit", {
        "raster.direction": True, "data.processes": 1, "train.init_from": "runs/tok_refit/export",
        "train.batch_size": 32, "train.num_steps": 6_000, "train.eval_every": 6_000, "train.checkpoint_every": 500}),
    "vector_tiny": ("tiny", {
        "model.encoder.kind": "vector", "model.vector.d_model": 128, "model.vector.num_heads": 4,
        "model.vector.num_layers": 2, "model.vector.ffn_dim": 256,
        "data.dir": ("data/i70_interaction_train_small:0.4,data/i70_netframes_interaction_train:0.2,"
                     "data/i70_netframes_gen:0.4"),
        "data.eval_dir": "data/interaction_dev", "data.eval_split": "val", "data.gt_recut": "join_ends",
        "train.num_steps": 3_000, "train.kmeans_at_step": 300, "train.eval_every": 1_000}),
    # dev probes of the results log's 2026-11-29 "where the vector tokenizer loses F1" (1,000 steps, as run):
    # the same recipe without the codebook (the decoder reads the continuous latents throughout; score it with
    # `tokenizer evaluate --continuous`), and with the CommonRoad train towns and SinD's train cities added
    "vector_tiny_continuous": ("vector_tiny", {"train.num_steps": 1_000, "train.kmeans_at_step": 1_000_000_000}),
    "vector_tiny_maps": ("vector_tiny", {
        "data.dir": ("data/i70_interaction_train_small:0.3,data/i70_netframes_interaction_train:0.15,"
                     "data/b70_netframes_osm_train:0.2,data/b70_netframes_sind_train:0.05,data/i70_netframes_gen:0.3"),
        "train.num_steps": 1_000}),
    "vector": ("vector_tiny", {
        "model.vector.d_model": 256, "model.vector.num_heads": 8, "model.vector.num_layers": 4,
        "model.vector.ffn_dim": 1024, "model.decoder.d_model": 512, "model.decoder.num_heads": 8,
        "model.decoder.num_layers": 6, "model.decoder.ffn_dim": 2048, "train.batch_size": 64,
        "train.num_steps": 40_000, "train.warmup_steps": 1_000, "train.lr": 3e-4, "train.codebook_lr": 3e-4,
        "train.kmeans_at_step": 1_000, "train.eval_every": 5_000, "train.checkpoint_every": 1_000,
        "data.processes": 4}),
    "test": ("tiny", {
        "data.dir": "synthetic", "model.encoder.width": 8, "model.encoder.head_channels": 32,
        "model.encoder.code_dim": 16, "model.num_codes": 16, "model.decoder.d_model": 32,
        "model.decoder.num_layers": 1, "model.decoder.ffn_dim": 64, "model.decoder.num_heads": 2,
        "train.batch_size": 4, "train.kmeans_rasters": 4, "train.kmeans_at_step": 0, "train.warmup_steps": 1,
        "train.log_every": 1, "train.eval_batches": 1, "train.lr": 3e-3}),
    "vector_test": ("test", {
        "model.encoder.kind": "vector", "model.vector.d_model": 32, "model.vector.num_heads": 2,
        "model.vector.num_layers": 1, "model.vector.ffn_dim": 64, "model.vector.max_segments": 256}),
}


def get_config(variant: str = "netframes"):
    c = map_tokenizer_config()
    if variant == "paper":
        return c
    for _, _, changes in recipe_stages(STAGES, variant, "configs/map_tokenizer.py"):
        set_fields(c, changes)
    return c
