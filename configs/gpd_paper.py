"""GPD-1 at the paper's size: 101 frames at 10 Hz (21 history + 80 future), ego + 32 agents, 64 map tokens from a
128-code map tokenizer, d 128, 6 layers, 8 heads, FFN 2048 (the official code's values).

Every field and its default is declared once, in `gpd_jax.config.gpd_config()`, whose defaults are this size; a
recipe sets only what differs. Override any field on the command line: --config.model.num_layers=4.

    python train.py --config configs/gpd_paper.py --workdir runs/paper --config.data.dir=data/STORE \
        --config.model.map_tokenizer=map_tokenizer
    python -m gpd_jax.bench rollout --config configs/gpd_paper.py --batch 1 16
"""

from gpd_jax.config import gpd_config


def get_config():
    return gpd_config()
