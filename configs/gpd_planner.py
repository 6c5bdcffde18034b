"""The recipe of gpd_planner: a planning head (one decoder layer on the ego token, `gpd_jax.model.PlanningHead`) on
a frozen pre-trained 1 Hz GPD, and the paper's head with its no-pre-training ablations.

Variants (`configs/gpd_planner.py:VARIANT`):

* `idm_choice` (shipped): the head chooses its plan among IDM's plans along the route at seven target speeds
  (`plan_head.candidates = "idm"`, `idm_speeds` 1 to 13.89 m/s; PDM's candidates, the choice learned by imitation:
  the cross-entropy of the candidate closest to the log) instead of drawing it. A fresh head on the frozen default
  model (`gpd_traffic`), the route as an input (16 points every 5 m), 1,291 scenes of the 13 real-road training
  tiles and two closed-loop (DAgger) rounds: at steps 333 and 666 the head drives the simulator on 300 training
  scenes and the states it reaches, labelled with the log's future, join the training scenes; 1,000 steps of 32 at
  1e-3 (about 7 min on 2 CPU cores). `idm_choice_scratch` is the same on a frozen random backbone (the
  no-pre-training ablation at the same budget).
* `frozen`: the paper's head (it draws its 8 poses) on the frozen retired first GPD, gpd_sumo (docs/model-lineage.md:
  `git show 42b82c9:checkpoints/gpd_sumo/...` into runs/gpd_sumo, its config's `model.map_tokenizer` set to
  "map_tokenizer"), trained on logged histories of generated networks: 2,000 steps of 32 scenes, 27 min on 2 CPU
  cores. `finetune` is the paper's setting, the backbone fine-tuned too at a tenth of the head's learning rate (a
  backbone pass per step); `scratch`, `frozen_scratch` are the paper's no-pre-training ablations at the same budget
  (a random backbone trained on the planning loss, or frozen). The head shipped before `idm_choice` continued
  `frozen` with the route and closed-loop rounds (`git show 1d7b7c2:configs/gpd_planner.py`, variant
  `closed_loop`); docs/results.md has both.

`idm_choice` reads real-road SUMO tiles (the training and development tiles of `gpd_jax.data realnets`,
docs/data.md):

    python -m gpd_jax.data build --source sumo --net data/realnets/train/*.net.xml.gz --net-layout real \
        --split train --scenarios 1300 --per-job 10 --seed 81 --out data/plan_real_train
    python -m gpd_jax.data build --source sumo --net data/realnets/dev/*.net.xml.gz --net-layout real --split val \
        --scenarios 150 --per-job 10 --seed 73 --out data/mix_real_dev
    for d in plan_real_train mix_real_dev; do python -m gpd_jax.map_tokenizer encode --checkpoint map_tokenizer \
        --data data/$d --frame-stride 10; done
    python train.py --config configs/gpd_planner.py:idm_choice --workdir runs/planner
    python -m gpd_jax.checkpoint export runs/planner gpd_planner --tokenizer-ref map_tokenizer

`frozen` and its ablations read generated networks:

    python -m gpd_jax.data build --source sumo --traffic legacy --out data/plan_train2 --scenarios 1600 --seed 31 \
        --per-job 25 --split train
    python -m gpd_jax.data build --source sumo --traffic legacy --out data/plan_dev --scenarios 150 --seed 37 \
        --per-job 25 --split val --against data/plan_train2
    for d in plan_train2 plan_dev; do python -m gpd_jax.map_tokenizer encode --checkpoint map_tokenizer --data data/$d \
        --frame-stride 10; done
    python train.py --config configs/gpd_planner.py:frozen --workdir runs/planner_paper
"""

from gpd_jax.config import gpd_config

VARIANTS = ("idm_choice", "idm_choice_scratch", "frozen", "finetune", "scratch", "frozen_scratch")


def get_config(variant: str = "idm_choice"):
    if variant not in VARIANTS:
        raise ValueError(f"configs/gpd_planner.py: variant {variant!r} is not one of {VARIANTS}")
    c = gpd_config(plan_head=True)
    c.data.dir, c.data.val_dir, c.data.frame_stride = "data/plan_train2", "data/plan_dev", 10
    m = c.model  # the backbone: gpd_sumo's architecture (gpd_traffic's for idm_choice, below)
    m.num_frames, m.num_history, m.num_agents = 11, 3, 17
    m.num_layers, m.num_heads, m.ffn_dim, m.head_hidden, m.attn_chunk_frames = 4, 4, 512, 128, 4
    m.predict_delta = m.velocity_residual = m.velocity_inputs = True
    m.map_tokenizer = "map_tokenizer"
    t = c.train
    t.init_from = "runs/gpd_sumo"
    t.backbone_lr_scale, t.gpd_loss_weight, t.cache_features = 0.1, 0.0, False
    t.batch_size, t.steps, t.learning_rate, t.warmup_steps, t.min_learning_rate = 8, 300, 1e-3, 50, 1e-5
    t.grad_clip, t.log_every, t.eval_every, t.eval_batches, t.checkpoint_every = 1.0, 25, 150, 4, 100
    t.loader_threads = 2
    if variant.startswith(("frozen", "idm_choice")):
        t.backbone_lr_scale, t.cache_features = 0.0, True
        t.batch_size, t.steps, t.warmup_steps = 32, 2_000, 200
        t.log_every, t.eval_every, t.checkpoint_every = 100, 500, 500
    if variant.startswith("idm_choice"):
        c.data.dir, c.data.val_dir = "data/plan_real_train", "data/mix_real_dev"
        m.agent_lane_residual, m.lane_context_stride = True, 4  # gpd_traffic, whose agents step along the lanes
        t.init_from = "gpd_traffic"
        t.steps, t.learning_rate, t.warmup_steps = 1_000, 1e-3, 50
        t.log_every, t.eval_every, t.checkpoint_every = 50, 250, 250
        ph = c.plan_head
        ph.route_points, ph.route_spacing_m = 16, 5.0
        ph.candidates, ph.idm_speeds = "idm", (1.0, 3.0, 5.0, 7.0, 9.0, 11.0, 13.89)
        ph.closed_loop_rounds, ph.closed_loop_scenes = 2, 300
    if variant.endswith("scratch"):
        t.init_from = ""
        if variant == "scratch":
            t.backbone_lr_scale = 1.0
    return c
