"""The recipe of gpd_sampling: the default model, gpd_traffic, with a sampling agent head (`model.agent_bins`) that
a rollout samples at temperature > 0 (`gpd_jax.RolloutOptions(temperature=0.5, samples=32)`: 32 futures of each
scene in one compiled rollout; 0.5 is the temperature chosen on the development store).

Only the head trains (`train.trainable = "sampling_head"`): every other parameter is gpd_traffic's, so at
temperature 0 the model rolls out exactly as gpd_traffic. The head is a categorical over 0.5 m cells of each agent's
next 1 Hz position's offset from the regressed one (+-8 m along its heading, +-3 m across: 33 x 13 = 429 cells, not
tuned), each cell a Laplace kernel of its spread, with the regressed heading and velocity under one learned scale
each, fitted by the negative log-likelihood of the logged next state on the logged history (teacher forcing). The
checkpoint kept is the best validation likelihood (`train.best_metric = "modes"`: step 800 of 800); the rollout
temperature was chosen on the development store's realism (docs/results.md, "Many futures"). It replaced a mixture
of six learned Laplace components (`model.agent_modes`, same recipe otherwise; `git show 3201a87:configs/
gpd_sampling.py`), which it beats on the development store's realism (0.681 against 0.641, both on the SUMO-only
gpd_traffic of the time). Retrained by this recipe on the current gpd_traffic (fine-tuned on recorded traffic) it
reads 0.673 there.

Data (`python -m gpd_jax.data ...`; where each source comes from and its terms: docs/data.md; `legacy_small` and
`mix_real_small` are smaller builds than configs/gpd_traffic.py's `legacy_train` and `mix_real_train`):

    python -m gpd_jax.data build --source sumo --traffic legacy --split train --scenarios 480 --per-job 20 --seed 11 \
        --out data/legacy_small
    python -m gpd_jax.data realnets --cache data/realnets
    python -m gpd_jax.data build --source sumo --net data/realnets/train/{drt_nw,drt_se,drt_sw,fin_se_east,fin_se_west,helsinki_south}.net.xml.gz \
        --net-layout real --split train --scenarios 240 --per-job 10 --seed 71 --out data/mix_real_small
    python -m gpd_jax.data build --source sumo --net data/realnets/dev/*.net.xml.gz --net-layout real --split val \
        --scenarios 150 --per-job 10 --seed 73 --out data/mix_real_dev
    for d in legacy_small mix_real_small mix_real_dev; do
        python -m gpd_jax.map_tokenizer encode --checkpoint map_tokenizer --data data/$d --frame-stride 10; done

Training (5 min on 2 CPU cores; resumes where it stopped); the best validation is exported to
runs/sampling/best (its config.json and params.npz are the shipped folder):

    python train.py --config configs/gpd_sampling.py --workdir runs/sampling
"""

from gpd_jax.config import gpd_config


def get_config():
    c = gpd_config()
    c.data.dir = "data/legacy_small:0.65,data/mix_real_small:0.35"
    c.data.val_dir, c.data.frame_stride = "data/mix_real_dev", 10
    m = c.model  # gpd_traffic's architecture (checkpoints/gpd_traffic/config.json), plus the sampling head
    m.num_frames, m.num_history, m.num_agents = 11, 3, 17
    m.num_layers, m.num_heads, m.ffn_dim, m.head_hidden, m.attn_chunk_frames = 4, 4, 512, 128, 4
    m.predict_delta = m.velocity_residual = m.velocity_inputs = m.agent_lane_residual = True
    m.map_tokenizer = "map_tokenizer"
    m.agent_bins, m.agent_bin_extent = 0.5, (8.0, 3.0)
    c.loss.agent_norm, c.loss.agent_norm_delta = "euclidean", 0.01
    t = c.train
    t.init_from, t.trainable = "gpd_traffic", "sampling_head"
    t.lane_context_drop = 0.25
    t.batch_size, t.steps, t.learning_rate, t.warmup_steps, t.min_learning_rate = 8, 800, 1e-3, 50, 1e-5
    t.grad_clip, t.log_every, t.eval_every, t.eval_batches, t.checkpoint_every = 1.0, 50, 200, 8, 200
    t.eval_rollout_scenarios, t.best_metric, t.loader_threads = 0, "modes", 2
    return c
