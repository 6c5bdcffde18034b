"""GPD-1 at the paper's size (official code values): T 101 = 21 + 80, 33 agents, 64 map tokens, 128x128
codebook, d 128, 6 layers, 8 heads, FFN 2048. Override any field: --config.model.num_layers=4."""

import ml_collections


def get_config() -> ml_collections.ConfigDict:
    c = ml_collections.ConfigDict()
    c.stage = "gpd"
    c.seed = 0

    m = c.model = ml_collections.ConfigDict()
    m.num_frames = 101          # T
    m.num_history = 21          # 2 s of history + the current frame, 10 Hz
    m.num_agents = 33           # ego (slot 0) + 32 nearest vehicles
    m.num_map_tokens = 64       # 8 x 8 grid
    m.codebook_size = 128       # K
    m.d_model = 128
    m.num_layers = 6
    m.num_heads = 8
    m.ffn_dim = 2048
    m.head_hidden = 256
    m.xy_range = 300.0          # x, y representable in [-300, 300) m
    m.xy_levels = (1.0, 0.01)   # metres
    m.xy_code_dim = 48
    m.heading_levels_deg = (20.0, 1.0)
    m.heading_code_dim = 32
    m.attn_chunk_frames = 8     # key chunk (in frames) of the chunked attention (measured best on CPU)
    m.train_attention = "flash"  # "flash": chunked, memory-linear; "dense": one masked softmax (short sequences)
    m.decode_attention = "auto"  # KV-cached rollout: "native" (fused CPU kernel), "xla" / "xla_batched" (scenario by
                                 # scenario / all at once under vmap) or "auto" (the fastest, measured here)
    m.predict_delta = False     # regress absolute positions (official) or displacements from frame t
    m.velocity_residual = False  # with predict_delta: regress the residual over constant velocity instead
    m.velocity_inputs = False   # not in the paper: tokens also encode velocity; a head predicts the next one
    m.velocity_range = 50.0     # vx, vy representable in [-50, 50) m/s
    m.velocity_levels = (1.0, 0.05)  # m/s
    m.velocity_code_dim = 32
    m.map_tokenizer = ""        # checkpoint dir of the map tokenizer whose codebook embeds map tokens

    d = c.data = ml_collections.ConfigDict()
    d.dir = ""                  # a data store (python -m gpd_jax.data build) with map tokens encoded into it, or a
                                # weighted mixture of stores "DIR:0.7,DIR:0.3" (gpd_jax.data.loader.parse_mixture)
    d.val_dir = ""              # where validation reads val_split ("" : the first store of d.dir; "A,B": each)
    d.train_split = "train"
    d.val_split = "val"
    d.frame_stride = 1          # model frame k is stored frame k * stride (stored data is 10 Hz, 101 frames)
    d.frame_period_s = 0.1      # seconds between stored frames

    lw = c.loss = ml_collections.ConfigDict()
    lw.position = 5.0
    lw.heading = 5.73           # (180 / 3.14) * 0.1 as in the official code
    lw.valid = 1.0
    lw.map = 1.0
    lw.velocity = 2.0           # only with model.velocity_inputs (smooth-L1 in m/s)
    lw.agent_norm = "smooth_l1"  # position / velocity loss: "smooth_l1" (official) or "euclidean" (training/step.py)
    lw.agent_norm_delta = 0.05  # the euclidean loss's pseudo-Huber width (m, m/s)
    lw.moving_weight = 1.0      # agent-loss weight of agents moving at the input frame (training/step.py)

    t = c.train = ml_collections.ConfigDict()
    t.batch_size = 16
    t.steps = 100_000
    t.learning_rate = 1e-3
    t.warmup_steps = 2_000
    t.min_learning_rate = 1e-6
    t.weight_decay = 1e-4
    t.grad_clip = 5.0
    t.log_every = 50
    t.eval_every = 1_000        # validation loss + validation rollouts
    t.eval_batches = 8          # validation loss over this many batches
    t.eval_rollout_scenarios = 32  # traffic_simulation rollouts (ADE vs constant velocity) at each evaluation
    t.best_metric = ""          # a validation key, lower is better (e.g. "rollout_agent_ade_vs_cv_mean"): the best
                                # validation's parameters are exported to WORKDIR/best (with WORKDIR/best.json)
    t.eval_at_start = False     # also validate before the first step (step 0; with best_metric, where a fine-tune
                                # started can stay its best)
    t.checkpoint_every = 500
    t.keep_checkpoints = 2
    t.loader_threads = 4
    t.rollout_passes = 0        # >0: future frames' agent inputs are the model's own predictions (training/step.py)
    t.map_feedback = 0.0        # with rollout_passes: fraction of each batch whose future map tokens are own too
    t.init_from = ""            # exported model or workdir whose parameters start a new run (fine-tuning)

    r = c.rollout = ml_collections.ConfigDict()
    r.temperature = 0.0         # 0: greedy (argmax) map tokens
    return c
