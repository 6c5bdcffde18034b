"""Map tokenizer runs at accelerator scale (issue 23): three questions about real roads, one data mixture.

The shipped tokenizer (checkpoints/map_tokenizer) was trained on the 2-core CPU: a tiny encoder, 128 codes, a
6-layer d=128 lane decoder. On real road networks it never saw its paper F1 is 0.128 (cut-free 0.740). Which part
holds it back? Three runs from it, each `VARIANT` on the same data (the shipped decoder's mixture,
configs/map_tokenizer_decoder_netframes.py: generated and real map-only frames plus four traffic stores), batch 64,
loader processes so the accelerator is fed (`data.processes`):

  decoder512  the tokens kept (encoder and codebook frozen), a fresh paper-size decoder (d_model 512, 8 heads,
              6 layers, FFN 2048): is the decoder's capacity the limit? Every GPD keeps working with it.
  full        encoder, codebook and decoder fine-tuned together (the tokens change): what do tokens fitted to
              the wider set give?
  probe       `full` with `train.quantize = False`: the decoder reads the encoder's continuous outputs. Not a
              tokenizer; against `full` it measures what the 128-code bottleneck costs.
  directional `full` again, from its result (checkpoints/map_tokenizer_refit), with SLEDGE's line channels
              (`raster.direction`: occupancy, cos and sin of the lane heading; the two new channels start at zero
              weight, so it starts from exactly the refit tokens). A binary raster cannot show which way a lane
              runs: 18 % of the real test networks' found line length is decoded the wrong way round (refit:
              cut-free F1 0.749, directed 0.611). Run on the 2-core CPU on 2026-11-26 (no accelerator lent):
              --config.train.batch_size=32 --config.train.num_steps=6000 --config.data.processes=1.

    python train.py --config configs/map_tokenizer_gpu.py:decoder512 --workdir runs/tok_gpu_dec512
    python -m gpd_jax.map_tokenizer export --workdir runs/tok_gpu_dec512 --out runs/tok_gpu_dec512/export
    python -m gpd_jax.map_tokenizer evaluate --checkpoint runs/tok_gpu_dec512/export --data data/mix_real_dev \\
        --split val --json ...

Rule, written before the run: `decoder512` replaces the shipped decoder if the mean paper F1 of its three dev
stores (gen_dev_legacy, gen_dev_curved, mix_real_dev; split val; every 10th frame; corrected ground truth) beats
the shipped decoder's 0.421. `full` and `probe` are diagnostics (`full` would need a GPD retrained on its tokens to
ship). The test stores are read once, after that choice.

Outcome (2026-11-26, one H200, ~6 min a run; checkpoints/map_tokenizer/README.md, "At accelerator scale"): dev
mean 0.452 (decoder512), 0.493 (full), 0.585 (probe). The rule picked decoder512, but it is not committed: its
params are 49 MB, over the repository's 20 MiB a file (a constraint the rule did not name). `full` ships as
checkpoints/map_tokenizer_refit with a GPD on its tokens (configs/gpd_sumo_refit.py). `init_from` is the shipped
tokenizer, unchanged by this.
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import map_tokenizer_decoder_netframes  # noqa: E402

VARIANTS = ("decoder512", "full", "probe", "directional")


def get_config(variant: str = "decoder512"):
    if variant not in VARIANTS:
        raise ValueError(f"configs/map_tokenizer_gpu.py: variant {variant!r} is not one of {VARIANTS}")
    c = map_tokenizer_decoder_netframes.get_config()
    c.data.eval_dir = "data/mix_real_dev"
    c.data.processes = 4
    t = c.train
    t.init_from = "checkpoints/map_tokenizer"
    t.batch_size = 64
    # the steps the H200 run fitted into its lease (its probe of the step rates sized them; 2026-11-26)
    t.num_steps = 4400 if variant == "decoder512" else 4000
    t.eval_every = t.num_steps
    t.eval_batches = 20
    t.checkpoint_every = t.num_steps // 4
    t.keep_checkpoints = 2
    t.log_every = 100
    if variant == "decoder512":
        t.decoder_only = True
        t.init_decoder = False
        d = c.model.decoder
        d.d_model = 512
        d.num_heads = 8
        d.num_layers = 6
        d.ffn_dim = 2048
        t.lr = 3e-4
        t.warmup_steps = 300
    else:
        t.decoder_only = False
        t.lr = 3e-4
        t.codebook_lr = 3e-4
        t.warmup_steps = 100
        t.quantize = variant != "probe"
    if variant == "directional":
        # `full` again from its own result, with SLEDGE's line channels (occupancy, cos, sin of the lane heading):
        # `init_from` adds the two channels with zero weights, so training starts from exactly the refit tokens
        c.raster.direction = True
        t.init_from = "checkpoints/map_tokenizer_refit"
    return c
