"""A tiny GPD for tests and quick CPU experiments: 11 frames (5 + 6), 5 agents, 16 map tokens (4x4),
d 32, 2 layers, 4 heads. Derived from the paper config so the two cannot drift apart in structure."""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import gpd_paper  # noqa: E402


def get_config():
    c = gpd_paper.get_config()
    m = c.model
    m.num_frames = 11
    m.num_history = 5
    m.num_agents = 5
    m.num_map_tokens = 16
    m.codebook_size = 32
    m.d_model = 32
    m.num_layers = 2
    m.num_heads = 4
    m.ffn_dim = 64
    m.head_hidden = 32
    m.xy_code_dim = 8
    m.heading_code_dim = 8
    m.attn_chunk_frames = 2
    c.train.batch_size = 4
    c.train.steps = 200
    c.train.warmup_steps = 10
    return c
