"""Map tokenizer (stage 1), tiny: a basic-block ResNet (space-to-depth stem) and a 3-layer d=128 decoder, trainable on a 2-core CPU.

    python train.py --config configs/map_tokenizer_tiny.py --workdir /tmp/map_tok

The shipped checkpoint (checkpoints/map_tokenizer/) was trained with exactly this config on /work/data/sumo6k
(`--config.data.dir=/work/data/sumo6k`; see its README).
"""

import ml_collections


def get_config() -> ml_collections.ConfigDict:
    c = ml_collections.ConfigDict()
    c.stage = "map_tokenizer"
    c.seed = 0

    c.data = ml_collections.ConfigDict()
    c.data.dir = "/work/data/sumo1k"
    c.data.train_split = "train"
    c.data.eval_split = "val"
    c.data.eval_dir = ""  # where validation reads eval_split ("" : the first store of data.dir, which may be a
    #                       weighted mixture "DIR:0.7,DIR:0.3" for training)
    c.data.num_workers = 1  # loader prefetch threads
    c.data.processes = 0  # training-stream loader processes (0: one thread); an accelerator needs several
    # the decoder's targets: "" the stored cut of the lanes into lines (the paper's setting), or a
    # `gpd_jax.data.lanes.RECUT_MODES` mode, e.g. "join_ends" (lines joined where one-to-one)
    c.data.gt_recut = ""

    c.raster = ml_collections.ConfigDict()
    c.raster.size = 256
    c.raster.pixel_size = 0.25
    c.raster.max_segment_length = 1.0  # the data store resamples lanes every 1 m: 4 samples per segment, gap-free
    # True: 3-channel rasters (occupancy, cos, sin of the lane heading; SLEDGE's line channels): the decoder can see
    # which way a lane runs. False: binary (the paper's, and the shipped tokenizer's)
    c.raster.direction = False

    c.model = ml_collections.ConfigDict()
    c.model.grid = 8
    c.model.num_codes = 128
    c.model.commitment = 0.25
    e = c.model.encoder = ml_collections.ConfigDict()
    e.block = "basic"
    # Space-to-depth 8x8 (lossless) then a 3x3 conv: 32x32x32, then basic stages at 32, 16 and 8 cells.
    e.stage_sizes = (1, 1, 1)
    e.stage_strides = (1, 2, 2)
    e.width = 32
    e.stem_patch = 8
    e.stem_kernel = 3
    e.stem_stride = 1
    e.stem_pool = False
    e.norm_groups = 8
    e.head_channels = 128
    e.code_dim = 128
    d = c.model.decoder = ml_collections.ConfigDict()
    d.d_model = 128
    d.num_heads = 4
    d.num_layers = 3
    d.ffn_dim = 512
    d.num_queries = 50
    d.num_points = 20
    d.max_coord = 32.0

    c.loss = ml_collections.ConfigDict()
    c.loss.w_l1 = 2.0
    c.loss.w_bce = 5.0
    c.loss.vq_weight = 1.0
    # Also train every decoder layer's output (DETR's auxiliary losses). Off: at this size it learned slower
    # (validation F1 after 1,500 steps 0.06 against 0.16, both without the continuous warm-up).
    c.loss.every_layer = False

    t = c.train = ml_collections.ConfigDict()
    t.batch_size = 32
    t.num_steps = 4000
    t.warmup_steps = 200
    t.lr = 1e-3
    t.codebook_lr = 1e-3
    t.end_lr_factor = 0.01
    t.weight_decay = 0.0
    t.grad_clip = 1.0
    t.kmeans_rasters = 256  # rasters whose encoder outputs initialise the codebook (64 cells each)
    t.kmeans_iters = 20
    t.kmeans_at_step = 1000  # k-means once the encoder has warmed up (0: at initialisation)
    # The decoder reads the continuous latents until k-means, then the quantized ones. Training through the
    # quantizer from the start learns far slower: validation F1 after 1,500 steps 0.16, against 0.58 with
    # k-means and the switch at step 600 (sumo1k, otherwise this config).
    t.continuous_warmup = True
    # False: a probe, not a tokenizer: the decoder always reads the encoder's continuous outputs (no codebook
    # bottleneck); compared with the same run quantized it measures what the 128 codes cost
    t.quantize = True
    t.init_from = ""  # start from this tokenizer (an export or a workdir), keeping its codebook
    t.decoder_only = False  # with init_from: train only the decoder (the tokens stay those of init_from)
    # False: take only the encoder and codebook from init_from and start a fresh decoder, of any size (with
    # decoder_only: the same tokens, a new decoder)
    t.init_decoder = True
    t.usage_decay = 0.99
    t.restart_every = 100  # dead-code restart period in steps (0: never)
    t.restart_threshold = 0.03  # a code is dead below threshold / K of the recent tokens
    t.restart_until = 0.8  # fraction of training after which codes are no longer re-seeded
    t.log_every = 50
    t.eval_every = 500
    t.eval_batches = 8
    t.checkpoint_every = 250
    t.keep_checkpoints = 2
    return c
