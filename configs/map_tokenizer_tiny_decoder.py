"""Second stage of the map tokenizer: a deeper lane decoder trained on the first stage's frozen tokens.

Starts from a trained tiny tokenizer (`train.init_from`, the first stage's export) and trains only its decoder
(`train.decoder_only`): the encoder and codebook stay fixed, so every token, and any GPD trained on them, stays
valid (the tokenizer's fingerprint does not change). The decoder grows from 3 to 6 layers (the official
deployment depth); the 3 added layers start as exact identities, so training starts from the first stage's
reconstructions.

    python train.py --config configs/map_tokenizer_tiny.py --workdir runs/map_tok
    python -m gpd_jax.map_tokenizer export --workdir runs/map_tok --out runs/map_tok/export
    python train.py --config configs/map_tokenizer_tiny_decoder.py --workdir runs/map_tok_dec

The shipped checkpoints/map_tokenizer was made this way (its README has the exact commands and figures).
"""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import map_tokenizer_tiny  # noqa: E402


def get_config():
    c = map_tokenizer_tiny.get_config()
    c.data.dir = "/work/data/sumo6k"
    c.model.decoder.num_layers = 6
    t = c.train
    t.init_from = "runs/map_tok/export"
    t.decoder_only = True
    t.num_steps = 12_000
    t.warmup_steps = 100
    t.lr = 5e-4
    t.eval_every = 500
    return c
