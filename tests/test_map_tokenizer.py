"""Map tokenizer: straight-through VQ, k-means, dead codes, loss, training, encode/decode, checkpoints."""

import json
import os
import shutil

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpd_jax.config import load_config
from gpd_jax.map_tokenizer import core
from gpd_jax.map_tokenizer.model import quantize, sine_position_2d
from gpd_jax.map_tokenizer.synthetic import synthetic_lanes
from gpd_jax.map_tokenizer.tokenizer import export_tokenizer, load_tokenizer

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def small_config(*extra):
    return load_config(os.path.join(ROOT, "configs/map_tokenizer.py:test"), list(extra))


# The training tests' one config: the steps of test_training_steps_lower_the_loss and the stopped and resumed runs
# of test_train_checkpoint_resume_and_encode_decode are one compiled train step (`compiled_steps`: built once per
# process, and this file runs in one process). Only the step count enters the step's program (the schedule); the
# other settings are the loop's.
TRAIN_ARGS = ("--config.train.num_steps=30", "--config.train.checkpoint_every=1", "--config.train.eval_every=2",
              "--config.train.restart_every=1")


def test_quantize_straight_through():
    cb = jnp.array([[0.0, 0.0], [1.0, 1.0], [-1.0, 2.0]])
    z = jnp.array([[0.9, 1.2], [-0.1, 0.1], [-0.8, 1.7]])
    zq, idx, loss = quantize(cb, z)
    np.testing.assert_array_equal(idx, [1, 0, 2])
    np.testing.assert_allclose(zq, cb[idx], atol=1e-6)
    c = jnp.arange(6.0).reshape(3, 2)
    g = jax.grad(lambda z: jnp.sum(quantize(cb, z)[0] * c))(z)
    np.testing.assert_allclose(g, c)  # identity gradient to the encoder output
    gcb = jax.grad(lambda cb: quantize(cb, z)[2])(cb)
    assert jnp.all(jnp.isfinite(gcb)) and jnp.abs(gcb).sum() > 0  # codebook loss moves the codes


@pytest.fixture(scope="module")
def small_grad():
    """(graphdef, params, grad): the test size's loss gradient on a synthetic batch, jitted once with
    `quantized` a traced flag, so the tests of both paths share one compile."""
    from gpd_jax.training.map_tokenizer import build_model, loss_fn
    cfg = small_config()
    graphdef, params = build_model(cfg)
    batch = synthetic_lanes(0, 2)
    grad = jax.jit(jax.grad(lambda p, quantized: loss_fn(graphdef, cfg, p, batch, quantized)[0]))
    return graphdef, params, grad


def test_gradient_reaches_encoder(small_grad):
    _, params, grad = small_grad
    grads = grad(params, jnp.bool_(True))
    enc = jax.tree.leaves(grads["encoder"])
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in enc)
    # the first conv sits before the quantizer: only the straight-through path can give it a gradient
    assert float(jnp.abs(grads["encoder"]["stem"]["conv"]["kernel"]).sum()) > 0


def test_kmeans_recovers_clusters():
    centres = jnp.array([[5.0, 0.0], [-5.0, 0.0], [0.0, 5.0], [0.0, -5.0]])
    x = jnp.repeat(centres, 50, axis=0) + 0.1 * jax.random.normal(jax.random.key(0), (200, 2))
    found = core.kmeans(jax.random.key(1), x, 4, iters=10)
    d = jnp.linalg.norm(found[:, None] - centres[None], axis=-1)
    assert float(d.min(0).max()) < 0.1  # every true centre has a found centre near it


def test_dead_codes_are_reseeded():
    cb = jnp.zeros((8, 3))
    usage = jnp.array([0.5, 0.5, 0, 0, 0, 0, 0, 0.0])
    z = jnp.ones((10, 3)) * 7.0
    new, u, n = core.restart_dead_codes(jax.random.key(0), cb, usage, z, 0.1)
    assert int(n) == 6
    np.testing.assert_array_equal(new[:2], 0.0)
    np.testing.assert_allclose(new[2:], 7.0, atol=0.1)
    np.testing.assert_allclose(u[2:], 1 / 8)


def test_code_stats():
    counts, used, ppl = core.code_stats(jnp.array([0, 0, 1, 1]), 4)
    np.testing.assert_allclose(counts, [2, 2, 0, 0])
    assert float(used) == 0.5 and abs(float(ppl) - 2.0) < 1e-5


def test_line_loss_zero_for_perfect_prediction():
    b = synthetic_lanes(3, 2)
    logits = jnp.where(b["lanes_valid"], 20.0, -20.0)
    loss, aux = core.line_loss(jnp.asarray(b["lanes"]), logits, b["lanes"], b["lanes_valid"])
    assert float(aux["l1"]) < 1e-5 and float(aux["bce"]) < 1e-6
    # shuffled queries are matched back
    perm = np.random.default_rng(0).permutation(50)
    loss2, aux2 = core.line_loss(jnp.asarray(b["lanes"])[:, perm], logits[:, perm], b["lanes"], b["lanes_valid"])
    assert float(aux2["l1"]) < 1e-5


def test_continuous_warmup_bypasses_the_quantizer(small_grad):
    from flax import nnx
    graphdef, params, grad = small_grad
    raster = jnp.asarray(np.random.default_rng(0).random((2, 256, 256)) < 0.05, jnp.float32)
    model = nnx.merge(graphdef, params)
    z = model.encode_latents(raster)
    cont = core.forward(graphdef, params, raster, quantized=jnp.bool_(False))
    quant = core.forward(graphdef, params, raster, quantized=jnp.bool_(True))
    np.testing.assert_allclose(cont["points"], model.decoder(z)[0], atol=1e-5)
    np.testing.assert_allclose(quant["points"], core.forward(graphdef, params, raster)["points"], atol=1e-5)
    assert float(jnp.abs(cont["points"] - quant["points"]).max()) > 1e-4
    assert float(cont["vq_loss"]) == 0.0 and float(quant["vq_loss"]) > 0.0
    g = grad(params, jnp.bool_(False))
    assert float(jnp.abs(g["codebook"]["embedding"]).max()) == 0.0  # the codebook is untouched while bypassed


def test_sine_position_code():
    pe = sine_position_2d(8, 8, 32)
    chex.assert_shape(pe, (64, 32))
    assert len(np.unique(np.round(np.asarray(pe), 5), axis=0)) == 64  # every cell has its own code


def test_training_steps_lower_the_loss():
    import optax
    from gpd_jax.training.map_tokenizer import TrainState, build_model, compiled_steps, make_optimizer
    cfg = small_config(*TRAIN_ARGS)
    graphdef, params = build_model(cfg)
    tx = make_optimizer(cfg.train, params)
    k = cfg.model.num_codes
    # usage float32 as the step returns it (a weakly typed one compiled the step twice: for the first call and the rest)
    state = TrainState(jnp.zeros((), jnp.int32), params, tx.init(params), jnp.full((k,), 1 / k, jnp.float32),
                       jnp.ones((), bool))
    step, _ = compiled_steps(graphdef, cfg, tx)  # the train step train_and_evaluate runs (donates the state)
    batch = synthetic_lanes(7, 4)
    losses = []
    for _ in range(12):
        state, m, z = step(state, batch)
        losses.append(float(m["loss"]))
    assert np.isfinite(losses).all()
    assert min(losses[-3:]) < 0.8 * losses[0], losses
    chex.assert_shape(z, (4 * 64, cfg.model.encoder.code_dim))
    assert isinstance(optax.tree.norm(state.params), jax.Array)


def test_train_checkpoint_resume_and_encode_decode(tmp_path):
    from gpd_jax.training.map_tokenizer import train_and_evaluate
    wd = str(tmp_path / "wd")
    # one config for the stopped run and its resumption (and test_training_steps_lower_the_loss): one compiled train
    # step serves them all
    cfg = small_config(*TRAIN_ARGS)
    metrics = train_and_evaluate(cfg, wd, stop_after=2)
    for key in ("f1", "lateral", "chamfer", "chamfer_corrected", "codebook_usage", "perplexity"):
        assert key in metrics
    # the recall by GT line ends inside the window: every GT line in exactly one group
    from gpd_jax.metrics.map import END_LABELS
    assert list(metrics["recall_by_gt_ends"]) == list(END_LABELS)
    assert sum(metrics["gt_lines_by_ends"].values()) == sum(metrics["gt_lines_by_length"].values()) > 0
    tok = load_tokenizer(wd)
    train_and_evaluate(cfg, wd, stop_after=1)  # resumes at step 2, runs one step
    lines = open(os.path.join(wd, "metrics.jsonl")).read().splitlines()
    assert any('"step": 3' in ln for ln in lines)
    tok3 = load_tokenizer(wd)
    assert not np.allclose(tok.params["decoder"]["points_head"]["kernel"],
                           tok3.params["decoder"]["points_head"]["kernel"])

    chex.assert_shape(tok.codebook, (16, 16))
    rasters = jnp.zeros((2, 3, 256, 256)).at[..., 100:110, 128].set(1.0)
    tokens = jax.jit(tok.encode)(tok.params, rasters)
    chex.assert_shape(tokens, (2, 3, 64))
    assert tokens.dtype == jnp.int32 and int(tokens.max()) < 16
    pts, logits = jax.jit(tok.decode)(tok.params, tokens)
    chex.assert_shape(pts, (2, 3, 50, 20, 2))
    chex.assert_shape(logits, (2, 3, 50))
    assert float(jnp.abs(pts).max()) <= 32.0

    out = str(tmp_path / "export")
    export_tokenizer(tok.params, tok.config, out)
    with open(os.path.join(out, "README.md"), "w") as f:  # exporting again replaces the model, keeps the rest
        f.write("notes")
    export_tokenizer(tok.params, tok.config, out)
    assert sorted(os.listdir(out)) == ["README.md", "config.json", "params.npz"]
    assert open(os.path.join(out, "README.md")).read() == "notes"
    tok2 = load_tokenizer(out)
    np.testing.assert_array_equal(jax.jit(tok2.encode)(tok2.params, rasters), tokens)  # one compile, not op by op
    p2, l2 = jax.jit(tok2.decode)(tok2.params, tokens)
    np.testing.assert_allclose(p2, pts, atol=0.1)  # float16 export
    # the export makes the same tokens, so it has the workdir's fingerprint; other parameters do not
    assert tok2.fingerprint() == tok.fingerprint() != tok3.fingerprint()
    _check_encode_cli(tmp_path, out, tok2)

    # decoder-only fine-tuning from the export: same tokens (fingerprint), a different decoder
    ft = str(tmp_path / "ft")
    train_and_evaluate(small_config("--config.train.num_steps=2", "--config.train.eval_every=100",
                                    f"--config.train.init_from={out}", "--config.train.decoder_only=True",
                                    "--config.train.restart_every=1"), ft)
    tok4 = load_tokenizer(ft)
    assert tok4.fingerprint() == tok2.fingerprint()
    # a config written before `raster.direction` existed (binary raster, the key absent) makes the same tokens
    old = str(tmp_path / "old_export")
    shutil.copytree(out, old)
    with open(os.path.join(old, "config.json")) as f:
        cfg = json.load(f)
    assert cfg["raster"].pop("direction") is False
    with open(os.path.join(old, "config.json"), "w") as f:
        json.dump(cfg, f)
    assert load_tokenizer(old).fingerprint() == tok2.fingerprint()
    assert not np.allclose(tok4.params["decoder"]["points_head"]["kernel"],
                           np.asarray(tok2.params["decoder"]["points_head"]["kernel"], np.float32))
    assert '"event": "kmeans_init"' not in open(os.path.join(ft, "metrics.jsonl")).read()
    with pytest.raises(ValueError, match="model config differs in num_codes"):
        train_and_evaluate(small_config("--config.model.num_codes=8", f"--config.train.init_from={out}"),
                           str(tmp_path / "bad"))
    with pytest.raises(ValueError, match="set train.init_from"):
        train_and_evaluate(small_config("--config.train.decoder_only=True"), str(tmp_path / "bad2"))


def _check_encode_cli(tmp_path, checkpoint, tok):
    """`python -m gpd_jax.map_tokenizer encode` writes every frame's tokens and skips what it already did."""
    from data_fixtures import write_small_store
    from gpd_jax.data import store
    from gpd_jax.map_tokenizer.__main__ import main
    from gpd_jax.map_tokenizer.raster import rasterize
    d = str(tmp_path / "ds")
    write_small_store(d, n_shards=2, per_shard=1)
    path = os.path.join(store.shard_dir(d, "train", 1), store.MAP_TOKENS)
    main(["encode", "--checkpoint", checkpoint, "--data", d])
    sh = store.Shard(store.shard_dir(d, "train", 0))
    a = sh.read(0)
    r = tok.config.raster
    want = jax.jit(lambda pl, v, pose: tok.encode(tok.params, rasterize(  # one compile, not op by op
        pl, v, pose, size=r.size, pixel_size=r.pixel_size, max_segment_length=r.max_segment_length)))(
        a["polylines"], a["polyline_valid"], a["ego_pose"])
    np.testing.assert_array_equal(sh.map_tokens[0], want)
    assert store.map_tokens_source(d, "train", 1) == tok.fingerprint()
    stamp = os.stat(path).st_ino  # a rewrite is a new file (temporary + rename)
    main(["encode", "--checkpoint", checkpoint, "--data", d])  # nothing to do: both shards are skipped
    assert os.stat(path).st_ino == stamp
    store.save_map_tokens(d, "train", 1, np.asarray(sh.map_tokens))  # tokens of unknown origin ...
    assert store.map_tokens_source(d, "train", 1) is None
    main(["encode", "--checkpoint", checkpoint, "--data", d])  # ... are re-encoded
    assert store.map_tokens_source(d, "train", 1) == tok.fingerprint()
    stamp = os.stat(path).st_ino
    main(["encode", "--checkpoint", checkpoint, "--data", d, "--force"])
    assert os.stat(path).st_ino != stamp
    # --frame-stride S: the same tokens at frames 0, S, 2S, ...; the others stored as not encoded
    full = np.array(store.Shard(store.shard_dir(d, "train", 0)).map_tokens)
    main(["encode", "--checkpoint", checkpoint, "--data", d, "--frame-stride", "5", "--force"])
    part = np.array(store.Shard(store.shard_dir(d, "train", 0)).map_tokens)
    np.testing.assert_array_equal(part[:, ::5], full[:, ::5])
    assert (np.delete(part, np.s_[::5], axis=1) == store.MISSING_MAP_TOKEN).all()
    assert store.map_tokens_record(d, "train", 1)["frame_stride"] == 5
    stamp = os.stat(path).st_ino
    main(["encode", "--checkpoint", checkpoint, "--data", d, "--frame-stride", "10"])  # covered: skipped
    assert os.stat(path).st_ino == stamp
    main(["encode", "--checkpoint", checkpoint, "--data", d])  # every frame: not covered, re-encoded
    assert os.stat(path).st_ino != stamp and store.map_tokens_record(d, "train", 1)["frame_stride"] == 1


def test_auction_matches_scipy_total_cost():
    from scipy.optimize import linear_sum_assignment
    from gpd_jax.map_tokenizer.auction import auction
    cost = np.random.default_rng(0).uniform(0, 10, (3, 7, 7)).astype(np.float32)
    m = np.asarray(auction(jnp.asarray(cost)))
    for b in range(3):
        r, c = linear_sum_assignment(cost[b])
        assert sorted(m[b]) == list(range(7))  # a permutation
        assert cost[b][m[b], np.arange(7)].sum() <= cost[b][r, c].sum() + 7 * 1e-3 + 1e-4


def test_decoder_only_adds_identity_layers(tmp_path):
    """`train.decoder_only` may deepen the decoder: added layers start as identities (same lines, same tokens)
    and still get gradients; without decoder_only, or to remove layers, the source must match."""
    from gpd_jax.map_tokenizer.tokenizer import MapTokenizer
    from gpd_jax.training.map_tokenizer import build_model, initial_params, loss_fn
    cfg = small_config()
    _, params = build_model(cfg)
    out = str(tmp_path / "src")
    export_tokenizer(params, cfg, out, dtype=np.float32)
    src = load_tokenizer(out)
    deeper = small_config("--config.model.decoder.num_layers=3", f"--config.train.init_from={out}",
                          "--config.train.decoder_only=True")
    grown = initial_params(deeper, out)
    assert sorted(grown["decoder"]["layers"]) == [0, 1, 2]
    graphdef, _ = build_model(deeper)
    tok = MapTokenizer(deeper, graphdef, grown)
    assert tok.fingerprint() == src.fingerprint()
    tokens = (jnp.arange(64) * 5 % 16)[None]
    p0, l0 = jax.jit(src.decode)(src.params, tokens)  # one compile each, not op by op
    p1, l1 = jax.jit(tok.decode)(grown, tokens)
    np.testing.assert_allclose(p1, p0, atol=1e-5)
    np.testing.assert_allclose(l1, l0, atol=1e-5)
    grads = jax.jit(jax.grad(lambda p: loss_fn(graphdef, deeper, p, synthetic_lanes(0, 2))[0]))(grown)
    assert float(jnp.abs(grads["decoder"]["layers"][2]["ff2"]["kernel"]).sum()) > 0
    with pytest.raises(ValueError, match="only train.decoder_only may add layers"):
        initial_params(small_config("--config.model.decoder.num_layers=3"), out)
    with pytest.raises(ValueError, match="never remove"):
        initial_params(small_config("--config.model.decoder.num_layers=0", "--config.train.decoder_only=True"), out)
    with pytest.raises(ValueError, match="decoder: ffn_dim"):
        initial_params(small_config("--config.model.decoder.ffn_dim=32", "--config.train.decoder_only=True"), out)


def test_direction_channels_start_from_a_binary_tokenizer(tmp_path):
    """`raster.direction` started from a binary tokenizer: the same tokens and lines on the same lanes (the new
    channels' weights are zero), the heading channels get gradients, and the reverse is refused."""
    from gpd_jax.map_tokenizer.tokenizer import MapTokenizer
    from gpd_jax.training.map_tokenizer import build_model, initial_params, loss_fn
    cfg = small_config()
    _, params = build_model(cfg)
    out = str(tmp_path / "src")
    export_tokenizer(params, cfg, out, dtype=np.float32)
    src = load_tokenizer(out)
    directed = small_config("--config.raster.direction=True", f"--config.train.init_from={out}")
    grown = initial_params(directed, out)
    graphdef, _ = build_model(directed)
    tok = MapTokenizer(directed, graphdef, grown)
    assert tok.fingerprint() != src.fingerprint()  # other rasters: other tokens in general
    batch = synthetic_lanes(0, 3)
    poses = jnp.asarray(batch["pose"])
    t_src = jax.jit(src.encode_lanes)(src.params, batch["polylines"], batch["polyline_valid"], poses)
    t_dir = jax.jit(tok.encode_lanes)(grown, batch["polylines"], batch["polyline_valid"], poses)
    np.testing.assert_array_equal(t_dir, t_src)
    grads = jax.jit(jax.grad(lambda p: loss_fn(graphdef, directed, p, batch)[0]))(grown)
    stem = grads["encoder"]["stem"]["conv"]["kernel"].reshape(3, 3, -1, 3, grads["encoder"]["stem"]["conv"][
        "kernel"].shape[-1])
    assert float(jnp.abs(stem[:, :, :, 1:]).sum()) > 0
    with pytest.raises(ValueError, match="directional source cannot start a binary"):
        d_out = str(tmp_path / "dir")
        export_tokenizer(grown, directed, d_out, dtype=np.float32)
        initial_params(small_config(f"--config.train.init_from={d_out}"), d_out)


def test_frame_batches_from_a_mixture_of_stores(tmp_path):
    """A training mixture draws frames from every store by weight, deterministically; evaluation refuses it."""
    from data_fixtures import write_small_store
    from gpd_jax.map_tokenizer.store import frame_batches

    a, b = str(tmp_path / "a"), str(tmp_path / "b")
    write_small_store(a, n_shards=2, per_shard=3)
    write_small_store(b, n_shards=1, per_shard=2, offset=500.0)  # b's ego poses lie 500 m further along x

    def from_b(batches):
        return np.concatenate([bt["pose"][:, 0] > 250.0 for bt in batches])

    mix = f"{a}:1,{b}:3"
    first = list(frame_batches(mix, "train", 8, seed=3, max_batches=25))
    share = from_b(first).mean()
    assert 0.65 <= share <= 0.85  # weight 3 of 4, though b holds 2 of 8 samples
    assert first[0]["lanes"].shape == (8, 50, 20, 2) and first[0]["lanes_valid"].any()
    again = list(frame_batches(mix, "train", 8, seed=3, max_batches=25))
    for x, y in zip(first, again):
        np.testing.assert_array_equal(x["pose"], y["pose"])
    other = list(frame_batches(mix, "train", 8, seed=4, max_batches=3))
    assert any(not np.array_equal(x["pose"], y["pose"]) for x, y in zip(first, other))
    with pytest.raises(ValueError, match="evaluate one store"):
        next(frame_batches(mix, "train", 8, shuffle=False, repeat=False))
    single = next(frame_batches(f"{a}:1", "train", 4, seed=0))  # a one-store "mixture" reads that store
    assert not (single["pose"][:, 0] > 250.0).any()


def test_loader_processes_give_a_deterministic_stream(tmp_path):
    """`data.processes`: the training stream from worker processes (each its own seed, taken in turn) is the same
    for the same seed and count, differs from the one-thread stream, has the batch layout, and a worker's failure
    reaches the consumer by name."""
    from data_fixtures import write_small_store
    from gpd_jax.map_tokenizer.data import frame_batches

    a = str(tmp_path / "a")
    write_small_store(a, n_shards=2, per_shard=3)
    cfg = small_config(f"--config.data.dir={a}", "--config.data.processes=2")
    first = list(frame_batches(cfg, "train", 4, seed=3, max_batches=4))
    again = list(frame_batches(cfg, "train", 4, seed=3, max_batches=4))
    for x, y in zip(first, again, strict=True):
        assert x.keys() == y.keys()
        for k in x:
            np.testing.assert_array_equal(x[k], y[k])
    assert first[0]["lanes"].shape == (4, 50, 20, 2) and first[0]["polylines"].dtype == np.float32
    one = list(frame_batches(small_config(f"--config.data.dir={a}"), "train", 4, seed=3, max_batches=4))
    assert any(not np.array_equal(x["frame"], y["frame"]) or not np.array_equal(x["sample"], y["sample"])
               for x, y in zip(first, one))
    # a finite pass (evaluation) keeps the one-process order
    ev = list(frame_batches(cfg, "train", 4, seed=0, shuffle=False, repeat=False))
    ev1 = list(frame_batches(small_config(f"--config.data.dir={a}"), "train", 4, seed=0, shuffle=False,
                             repeat=False))
    for x, y in zip(ev, ev1, strict=True):
        np.testing.assert_array_equal(x["pose"], y["pose"])
    bad = small_config(f"--config.data.dir={tmp_path / 'missing'}", "--config.data.processes=1")
    with pytest.raises(RuntimeError, match="loader process .* failed: FileNotFoundError"):
        next(frame_batches(bad, "train", 4, seed=0))


def test_config_file_variants():
    """`FILE.py:ARG` calls get_config(ARG); the tokenizers' recipe stages differ where they say."""
    tiny = load_config(os.path.join(ROOT, "configs/map_tokenizer.py:tiny"))
    dec = load_config(os.path.join(ROOT, "configs/map_tokenizer.py:decoder"))
    f = load_config(os.path.join(ROOT, "configs/map_tokenizer.py:refit"))
    r = load_config(os.path.join(ROOT, "configs/map_tokenizer.py:directional"))
    assert tiny.model.decoder.num_layers == 3 and dec.model.decoder.num_layers == 6 and dec.train.decoder_only
    assert tiny.model.encoder.to_dict() == dec.model.encoder.to_dict() == f.model.encoder.to_dict()
    assert not f.train.decoder_only and f.train.init_from == "map_tokenizer"
    assert r.raster.direction and not f.raster.direction and not r.train.decoder_only
    assert r.train.init_from == "runs/tok_refit/export" and r.data.dir == f.data.dir
    assert load_config(os.path.join(ROOT, "configs/map_tokenizer.py:paper")).model.decoder.d_model == 512
    with pytest.raises(ValueError, match="stage 'nope'"):
        load_config(os.path.join(ROOT, "configs/map_tokenizer.py:nope"))
    with pytest.raises(FileNotFoundError, match="config file not found"):
        load_config(os.path.join(ROOT, "configs/missing.py:x"))


def test_shipped_directional_tokenizer_sees_which_way_lanes_run():
    """The shipped map_tokenizer_directional reads SLEDGE's heading channels: the same road with every lane turned
    the other way gets other tokens; the binary map_tokenizer cannot tell them apart."""
    from gpd_jax import zoo

    x = np.linspace(-60.0, 60.0, 128, dtype=np.float32)
    road = np.stack([np.stack([x, np.full_like(x, 0.0)], -1), np.stack([x[::-1], np.full_like(x, 3.5)], -1)])
    valid, pose = np.ones(road.shape[:2], bool), np.zeros(3, np.float32)
    diff = {}
    for name in ("map_tokenizer_directional", "map_tokenizer"):
        tok = load_tokenizer(zoo.resolve(name))
        a, b = (np.asarray(tok.encode_lanes(tok.params, jnp.asarray(r), valid, pose)) for r in (road, road[:, ::-1]))
        diff[name] = int((a != b).sum())
    assert diff["map_tokenizer"] == 0 and diff["map_tokenizer_directional"] > 0
    directional = load_tokenizer(zoo.resolve("map_tokenizer_directional"))
    assert directional.config.raster.direction and directional.fingerprint() == "ab468f23bfb2789e"


def test_continuous_training_reads_the_latents_not_the_codes():
    """`train.continuous`: the train step's loss is that of the continuous latents (no quantiser), with a
    codebook in place (k-means done) that would change it."""
    from gpd_jax.map_tokenizer.evaluation import frame_arrays
    from gpd_jax.training.map_tokenizer import TrainState, build_model, loss_fn, make_optimizer, make_train_step
    cfg = small_config("--config.train.continuous=True")
    graphdef, params = build_model(cfg)
    batch = frame_arrays(synthetic_lanes(0, 2))
    tx = make_optimizer(cfg.train, params)
    k = cfg.model.num_codes
    state = TrainState(jnp.zeros((), jnp.int32), params, tx.init(params), jnp.full((k,), 1 / k, jnp.float32),
                       jnp.ones((), bool))
    want = float(loss_fn(graphdef, cfg, params, batch, False)[0])
    codes = float(loss_fn(graphdef, cfg, params, batch, True)[0])
    _, metrics, _ = jax.jit(make_train_step(graphdef, cfg, tx))(state, batch)
    assert float(metrics["loss"]) == pytest.approx(want, rel=1e-4)
    assert abs(codes - want) > 1e-3 * abs(want)
