"""The recipe of gpd_traffic, the default model: a 1 Hz GPD whose agents step along the lanes, trained on SUMO
traffic and fine-tuned on recorded drone traffic (INTERACTION).

Stages run in order (`configs/gpd_traffic.py:STAGE`); each starts from the previous one's export and changes only
what its entry in `STAGES` says. Four times the recipe averages models in weight space (`python -m
gpd_jax.checkpoint average`: a fine-tune towards one distribution averaged back with where it started, as
WiSE-FT and model soups do). What each stage bought, and the alternatives tried, is in docs/results.md; the
retired intermediate models are in docs/model-lineage.md.

Data (`python -m gpd_jax.data ...`; where each source comes from and its terms: docs/data.md):

    python -m gpd_jax.data build --source sumo --traffic legacy --out data/sumo6k --scenarios 6000 --seed 11 --per-job 25
    python -m gpd_jax.data realnets --cache data/realnets
    python -m gpd_jax.data build --source sumo --net data/realnets/train/{drt_nw,drt_se,drt_sw,fin_se_east,fin_se_west,helsinki_south}.net.xml.gz \
        --net-layout real --split train --scenarios 600 --per-job 10 --seed 71 --out data/mix_real_train
    python -m gpd_jax.data build --source sumo --net data/realnets/train/{cologne1,cologne3,cologne8,ingolstadt_ne,ingolstadt_nw,ingolstadt_se,ingolstadt_sw}.net.xml.gz \
        --net-layout real --split train --scenarios 560 --per-job 10 --seed 81 --out data/real2_train
    python -m gpd_jax.data build --source sumo --net data/realnets/dev/*.net.xml.gz --net-layout real --split val \
        --scenarios 150 --per-job 10 --seed 73 --out data/mix_real_dev
    python -m gpd_jax.data build --source sumo --split train --scenarios 3000 --per-job 25 --seed 61 --out data/mix_gen_train
    python -m gpd_jax.data build --source sumo --split train --scenarios 1500 --per-job 25 --seed 61 --curved-share 0.5 \
        --out data/gen_curved_train
    python -m gpd_jax.data build --source sumo --traffic legacy --split train --scenarios 1500 --per-job 25 --seed 11 \
        --out data/legacy_train
    (dev stores of generated networks, for the stages that validate on three stores: data/gen_dev_curved and
     data/gen_dev_legacy, built like the two above with --split val and other seeds)
    (for the last stage: recorded drone traffic, INTERACTION, and a smaller legacy store; INTERACTION_ROOT holds
     recorded_trackfiles/ and maps/; its non-commercial terms and the split by site: docs/data.md)
    python -m gpd_jax.data build --source interaction --db INTERACTION_ROOT --split train --max-per-log 20 --workers 2 \
        --out data/interaction_train_small
    python -m gpd_jax.data build --source interaction --db INTERACTION_ROOT --split val --out data/interaction_dev
    python -m gpd_jax.data build --source sumo --traffic legacy --split train --scenarios 480 --per-job 20 --seed 11 \
        --out data/legacy_small
    for d in data/*/; do python -m gpd_jax.map_tokenizer encode --checkpoint map_tokenizer --data $d --frame-stride 10; done

Training (2-core CPU times from the original runs; every stage resumes where it stopped):

    python train.py --config configs/gpd_traffic.py:sumo --workdir runs/sumo                        # ~1.5 h
    python train.py --config configs/gpd_traffic.py:sumo_rollouts --workdir runs/sumo_rollouts
    python train.py --config configs/gpd_traffic.py:sumo_map_feedback --workdir runs/sumo_map_feedback
    python train.py --config configs/gpd_traffic.py:real --workdir runs/real                        # 42 min
    python train.py --config configs/gpd_traffic.py:curved --workdir runs/curved
    python train.py --config configs/gpd_traffic.py:euclid --workdir runs/euclid
    python train.py --config configs/gpd_traffic.py:euclid_narrow --workdir runs/euclid_narrow
    python train.py --config configs/gpd_traffic.py:lane_residual --workdir runs/lane_residual
    python train.py --config configs/gpd_traffic.py:mix --workdir runs/mix
    python train.py --config configs/gpd_traffic.py:mix_legacy --workdir runs/mix_legacy
    python train.py --config configs/gpd_traffic.py:mix_real2 --workdir runs/mix_real2             # 37 min
    python -m gpd_jax.checkpoint average runs/mix_real2/export runs/lane_residual/export runs/mix_legacy/export \
        --weights 0.3333333333 0.3333333333 0.3333333334 --config-from 2 --out runs/soup
    python train.py --config configs/gpd_traffic.py:soup_legacy --workdir runs/soup_legacy         # 30 min
    python -m gpd_jax.checkpoint average runs/soup_legacy/export runs/soup --weights 0.5 0.5 --config-from 1 \
        --out runs/soup_legacy_avg
    python train.py --config configs/gpd_traffic.py:soup_legacy2 --workdir runs/soup_legacy2       # 34 min
    python -m gpd_jax.checkpoint average runs/soup_legacy2/export runs/soup_legacy_avg --weights 0.5 0.5 \
        --config-from 1 --tokenizer-ref map_tokenizer --out runs/soup_legacy2_avg
    python train.py --config configs/gpd_traffic.py:interaction --workdir runs/interaction  # best at step 50: 3 min
    python -m gpd_jax.checkpoint average runs/interaction/best runs/soup_legacy2_avg --weights 0.5 0.5 \
        --config-from 0 --tokenizer-ref map_tokenizer --out gpd_traffic

runs/soup_legacy2_avg was the default until 2026-11-29 (`git show ab4875a:checkpoints/gpd_traffic/params.npz`; its
config.json is the `soup_legacy2` stage's). The last stage validates on 96 windows of INTERACTION's development site
every 50 steps and keeps the best; on a 2-core CPU a step takes about 3 s, and the run may be stopped once step 50's
validation has written runs/interaction/best (the best of the shipped run; `--stop-after 50` does it). Retrained
from this recipe, the average equals the shipped params bit for bit.

(The shipped model's first three stages took a longer route, through an earlier tokenizer's tokens; the commit
that shipped each stage is in docs/model-lineage.md.)
"""

from gpd_jax.config import gpd_config, recipe_stages, set_fields

_REAL = "data/mix_real_train"
_DEV3 = "data/mix_real_dev,data/gen_dev_curved,data/gen_dev_legacy"

# stage -> (the stage it starts from, the fields it changes). Values hold until a later stage changes them.
STAGES = {
    # Teacher forcing on generated networks with legacy traffic. 1 Hz: every 10th stored frame (3 history + 8 future),
    # 11 x 81 tokens a scene; agents regress the residual over constant velocity from their 10 Hz velocity.
    "sumo": (None, {
        "data.dir": "data/sumo6k", "data.frame_stride": 10,
        "model.num_frames": 11, "model.num_history": 3, "model.num_agents": 17, "model.num_layers": 4,
        "model.num_heads": 4, "model.ffn_dim": 512, "model.head_hidden": 128, "model.attn_chunk_frames": 4,
        "model.predict_delta": True, "model.velocity_residual": True, "model.velocity_inputs": True,
        "model.map_tokenizer": "map_tokenizer",
        "train.batch_size": 8, "train.steps": 4_000, "train.warmup_steps": 200, "train.min_learning_rate": 1e-5,
        "train.grad_clip": 1.0, "train.log_every": 25, "train.eval_every": 500, "train.checkpoint_every": 100}),
    # On its own rollouts: 8 passes without gradient make the future frames' agent inputs its own predictions.
    "sumo_rollouts": ("sumo", {
        "train.rollout_passes": 8, "train.steps": 1_000, "train.learning_rate": 3e-4, "train.warmup_steps": 50,
        "train.eval_every": 250}),
    # Its own map tokens fed back too.
    "sumo_map_feedback": ("sumo_rollouts", {
        "train.rollout_passes": 2, "train.map_feedback": 1.0, "train.steps": 450, "train.eval_every": 225}),
    # Real traffic (parked and queued cars, heterogeneous drivers) on generated networks and real OSM road tiles.
    "real": ("sumo_map_feedback", {
        "data.dir": f"data/mix_gen_train:0.6,{_REAL}:0.4", "data.val_dir": "data/mix_real_dev",
        "train.steps": 1_200, "train.eval_every": 300, "train.eval_rollout_scenarios": 64,
        "train.keep_checkpoints": 13}),
    # Curved generated streets, whole rollouts.
    "curved": ("real", {
        "data.dir": f"data/gen_curved_train:0.6,{_REAL}:0.4", "train.rollout_passes": 8, "train.steps": 400,
        "train.eval_every": 200, "train.keep_checkpoints": 5}),
    # The agents' loss on the error's length (stopped cars stay put), then a narrower pseudo-Huber width.
    "euclid": ("curved", {"loss.agent_norm": "euclidean"}),
    "euclid_narrow": ("euclid", {"loss.agent_norm_delta": 0.01}),
    # The heads' base walks along the lane each agent is on; a quarter of the scenes see no lanes in the future.
    "lane_residual": ("euclid_narrow", {"model.agent_lane_residual": True, "train.lane_context_drop": 0.25}),
    # Legacy-traffic generated networks back in the mixture, in two steps.
    "mix": ("lane_residual", {"data.dir": f"data/gen_curved_train:0.3,data/legacy_train:0.3,{_REAL}:0.4"}),
    "mix_legacy": ("mix", {"data.dir": f"data/gen_curved_train:0.2,data/legacy_train:0.4,{_REAL}:0.4"}),
    # Seven more real tiles (Cologne, Ingolstadt); validates on three dev stores, exports its best validation.
    "mix_real2": ("mix_legacy", {
        "data.dir": f"data/gen_curved_train:0.2,data/legacy_train:0.4,{_REAL}:0.2,data/real2_train:0.2",
        "data.val_dir": _DEV3, "train.best_metric": "rollout_agent_ade_vs_cv_mean",
        "train.eval_rollout_scenarios": 150}),
    # From the soup (the average of mix_real2, lane_residual and mix_legacy), towards legacy traffic; averaged back.
    "soup_legacy": ("mix_real2", {
        "data.dir": f"data/gen_curved_train:0.15,data/legacy_train:0.55,{_REAL}:0.15,data/real2_train:0.15",
        "train.init_from": "runs/soup"}),
    # Once more, from that average; averaged back again: gpd_traffic.
    "soup_legacy2": ("soup_legacy", {
        "data.dir": f"data/gen_curved_train:0.10,data/legacy_train:0.65,{_REAL}:0.125,data/real2_train:0.125",
        "train.init_from": "runs/soup_legacy_avg"}),
    # From that average (runs/soup_legacy2_avg, the default until 2026-11-29) onto recorded drone traffic: INTERACTION's
    # five train sites with legacy SUMO traffic; validates on the development site every 50 steps and exports the
    # best (step 50 of 300) to runs/interaction/best, averaged 0.5 / 0.5 with where it started: gpd_traffic.
    "interaction": ("soup_legacy2", {
        "data.dir": "data/interaction_train_small:0.7,data/legacy_small:0.3", "data.val_dir": "data/interaction_dev",
        "train.init_from": "runs/soup_legacy2_avg", "train.steps": 300, "train.learning_rate": 1e-4,
        "train.warmup_steps": 30, "train.map_feedback": 0.0, "train.eval_every": 50, "train.eval_at_start": True,
        "train.eval_rollout_scenarios": 96, "train.checkpoint_every": 1_000, "train.keep_checkpoints": 4,
        "train.loader_threads": 2}),
}


def get_config(stage: str = "interaction"):
    c = gpd_config()
    for _, parent, changes in recipe_stages(STAGES, stage, "configs/gpd_traffic.py"):
        c.train.init_from = "" if parent is None else f"runs/{parent}/export"
        set_fields(c, changes)
    return c
