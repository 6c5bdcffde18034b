"""Map tokenizer (stage 1), paper / official deployment size: ResNet-50 (bottleneck 3-4-6-3), 128x128 codebook,
DETR decoder d_model 512, 8 heads, 6 layers, FFN 2048, 50 line queries x 20 points. For accelerators.

    python train.py --config configs/map_tokenizer_paper.py --workdir /tmp/map_tok_paper
"""

import importlib.util
import os

import ml_collections


def _tiny():
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "map_tokenizer_tiny.py")
    spec = importlib.util.spec_from_file_location("_map_tokenizer_tiny", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.get_config()


def get_config() -> ml_collections.ConfigDict:
    c = _tiny()
    c.data.dir = "/work/data/sumo1k"
    e = c.model.encoder
    e.block = "bottleneck"
    e.stage_sizes = (3, 4, 6, 3)
    e.stage_strides = (1, 2, 2, 2)
    e.width = 64
    e.stem_patch = 1  # the ResNet stem: 7x7/2 conv + 3x3/2 max-pool, total stride 32
    e.stem_kernel = 7
    e.stem_stride = 2
    e.stem_pool = True
    e.norm_groups = 32
    e.head_channels = 256
    d = c.model.decoder
    d.d_model = 512
    d.num_heads = 8
    d.num_layers = 6
    d.ffn_dim = 2048
    t = c.train
    t.batch_size = 64
    t.num_steps = 200_000
    t.warmup_steps = 5_000
    t.lr = 1e-4  # official: 1e-4 for the network, 5e-3 for the quantizer, cosine to 1e-5
    t.codebook_lr = 5e-3
    t.end_lr_factor = 0.1
    t.kmeans_rasters = 512
    t.kmeans_at_step = 2_000
    t.restart_every = 1_000
    t.eval_every = 5_000
    t.eval_batches = 50
    t.checkpoint_every = 2_000
    return c
