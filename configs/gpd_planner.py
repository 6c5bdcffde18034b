"""The recipe of gpd_planner: the paper's planning head (one decoder layer on the ego token,
`gpd_jax.model.PlanningHead`) trained on the logged ego's next 8 s over a pre-trained 1 Hz GPD.

Variants (`configs/gpd_planner.py:VARIANT`), all with the same head, data and targets:

* `closed_loop` (shipped): `frozen`'s head continued on real-road SUMO tiles with the route as an input and two
  closed-loop (DAgger) rounds: at steps 200 and 400 the head drives the simulator on 120 training scenes and the
  states it reaches, labelled with the log's future, join the 240 training scenes; 600 steps of 32 (about 25 min on
  2 busy CPU cores).
* `frozen`: the backbone frozen and its output tokens computed once per scene (`train.cache_features`), so only
  the head's ~0.3 M parameters train: 2,000 steps of 32 scenes, 27 min on 2 CPU cores; the model's own agent and
  map predictions stay exactly its backbone's.
* `idm_choice`: a head that chooses its plan among IDM's plans along the route at seven target speeds
  (`plan_head.candidates = "idm"`, `idm_speeds` 1 to 13.89 m/s; PDM's idea, the choice learned by imitation)
  instead of drawing it: a fresh head on the frozen backbone, the route as an input, the same real-road tiles and
  two closed-loop rounds as `closed_loop`, 600 steps of 32 at 1e-3 (about 4 min on 2 CPU cores);
  `idm_choice_scratch` is the same on a frozen random backbone (the no-pre-training ablation at the same budget).
* `finetune`: the paper's setting, the backbone fine-tuned too at a tenth of the head's learning rate (a backbone
  pass per step).
* `scratch`, `frozen_scratch`: the no-pre-training ablations at the same budget (a random backbone trained on the
  planning loss, or frozen).

The backbone is the retired first GPD, gpd_sumo (docs/model-lineage.md: `git show 42b82c9:checkpoints/gpd_sumo/...`
into runs/gpd_sumo).

    python -m gpd_jax.data build --source sumo --traffic legacy --out data/plan_train2 --scenarios 1600 --seed 31 \
        --per-job 25 --split train
    python -m gpd_jax.data build --source sumo --traffic legacy --out data/plan_dev --scenarios 150 --seed 37 \
        --per-job 25 --split val --against data/plan_train2
    for d in plan_train2 plan_dev; do python -m gpd_jax.map_tokenizer encode --checkpoint map_tokenizer --data data/$d \
        --frame-stride 10; done
    python train.py --config configs/gpd_planner.py:frozen --workdir runs/planner

`closed_loop` starts from `frozen`'s export (runs/planner/export; the one shipped before it:
`git show 454eff3:checkpoints/gpd_planner/{config.json,params.npz}` into runs/gpd_planner_logged) and reads
real-road SUMO tiles (the training and development tiles of `gpd_jax.data realnets`, docs/data.md):

    python -m gpd_jax.data build --source sumo --net data/realnets/train/{drt_nw,drt_se,drt_sw,fin_se_east,fin_se_west,helsinki_south}.net.xml.gz \
        --net-layout real --split train --scenarios 240 --per-job 10 --seed 71 --out data/mix_real_train
    python -m gpd_jax.data build --source sumo --net data/realnets/dev/*.net.xml.gz --net-layout real --split val \
        --scenarios 150 --per-job 10 --seed 73 --out data/mix_real_dev
    for d in mix_real_train mix_real_dev; do python -m gpd_jax.map_tokenizer encode --checkpoint map_tokenizer \
        --data data/$d --frame-stride 10; done
    python train.py --config configs/gpd_planner.py:closed_loop --workdir runs/planner_closed_loop
    python -m gpd_jax.checkpoint export runs/planner_closed_loop gpd_planner --tokenizer-ref map_tokenizer
"""

from gpd_jax.config import gpd_config

VARIANTS = ("idm_choice", "idm_choice_scratch", "closed_loop", "frozen", "finetune", "scratch", "frozen_scratch")


def get_config(variant: str = "closed_loop"):
    if variant not in VARIANTS:
        raise ValueError(f"configs/gpd_planner.py: variant {variant!r} is not one of {VARIANTS}")
    c = gpd_config(plan_head=True)
    c.data.dir, c.data.val_dir, c.data.frame_stride = "data/plan_train2", "data/plan_dev", 10
    m = c.model  # the backbone: gpd_sumo's architecture
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
    if variant.startswith(("frozen", "idm_choice")) or variant == "closed_loop":
        t.backbone_lr_scale, t.cache_features = 0.0, True
        t.batch_size, t.steps, t.warmup_steps = 32, 2_000, 200
        t.log_every, t.eval_every, t.checkpoint_every = 100, 500, 500
    if variant == "closed_loop":
        c.data.dir, c.data.val_dir = "data/mix_real_train", "data/mix_real_dev"
        t.init_from = "runs/gpd_planner_logged"
        t.steps, t.learning_rate, t.warmup_steps = 600, 3e-4, 50
        t.log_every, t.eval_every, t.checkpoint_every = 50, 200, 200
        ph = c.plan_head
        ph.route_points, ph.route_spacing_m = 16, 5.0
        ph.closed_loop_rounds, ph.closed_loop_scenes = 2, 120
    if variant.startswith("idm_choice"):
        c.data.dir, c.data.val_dir = "data/mix_real_train", "data/mix_real_dev"
        t.steps, t.learning_rate, t.warmup_steps = 600, 1e-3, 50
        t.log_every, t.eval_every, t.checkpoint_every = 50, 200, 200
        ph = c.plan_head
        ph.route_points, ph.route_spacing_m = 16, 5.0
        ph.candidates, ph.idm_speeds = "idm", (1.0, 3.0, 5.0, 7.0, 9.0, 11.0, 13.89)
        ph.closed_loop_rounds, ph.closed_loop_scenes = 2, 120
    if variant.endswith("scratch"):
        t.init_from = ""
        if variant == "scratch":
            t.backbone_lr_scale = 1.0
    return c
