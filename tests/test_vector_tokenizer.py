"""The vector map encoder (`gpd_jax.map_tokenizer.vector`): what it is invariant to and what not, empty frames,
one compilation, and a tiny tokenizer that learns to redraw a handful of frames through its codes."""

import os

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpd_jax.config import load_config
from gpd_jax.map_tokenizer import core
from gpd_jax.map_tokenizer.synthetic import synthetic_lanes
from gpd_jax.map_tokenizer.vector import cell_mask, lane_segments

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def vector_config(*extra):
    return load_config(os.path.join(ROOT, "configs/map_tokenizer.py:vector_test"), list(extra))


@pytest.fixture(scope="module")
def model():
    from gpd_jax.training.map_tokenizer import build_model
    cfg = vector_config()
    graphdef, params = build_model(cfg)
    enc = jax.jit(lambda p, lanes: core.encode_latents(graphdef, p, lanes))
    return cfg, graphdef, params, enc


@pytest.fixture(scope="module")
def frames():
    d = synthetic_lanes(3, 2)
    return d["polylines"], d["polyline_valid"], d["pose"]


def test_segments_are_the_lanes_seen_from_the_ego():
    """One straight lane along the ego's heading, points every metre: 2 m segments on the x axis, pointing forward."""
    pts = np.zeros((1, 2, 8, 2), np.float32)
    pts[0, 0, :, 0] = 10.0 + np.arange(8)  # scene frame: the ego stands at (10, 5) facing +x
    pts[0, 0, :, 1] = 5.0
    valid = np.zeros((1, 2, 8), bool)
    valid[0, 0, :7] = True  # 7 points: 3 segments of 2 m
    seg = lane_segments(pts, valid, np.array([[10.0, 5.0, 0.0]], np.float32), half=32.0, margin=2.0,
                        point_stride=2, max_segments=8)
    assert int(seg.valid.sum()) == 3
    starts = np.sort(np.asarray(seg.start[0, :, 0])[np.asarray(seg.valid[0])])
    np.testing.assert_allclose(starts, [0.0, 2.0, 4.0], atol=1e-5)
    np.testing.assert_allclose(np.asarray(seg.end - seg.start)[np.asarray(seg.valid)], [[2.0, 0.0]] * 3, atol=1e-5)
    assert not np.any(np.asarray(seg.start)[~np.asarray(seg.valid)])  # padding is zero


def test_invariant_to_lane_order_padding_rows_and_padding_positions(model, frames):
    cfg, _, params, enc = model
    poly, valid, pose = frames
    z = enc(params, (poly, valid, pose))
    rng = np.random.default_rng(0)
    perm = rng.permutation(poly.shape[1])
    z_perm = enc(params, (poly[:, perm], valid[:, perm], pose))
    # eight more empty rows, and every row's points moved three slots later in a longer row (padding in front)
    pad_p = np.zeros((poly.shape[0], poly.shape[1] + 8, poly.shape[2] + 3, 2), np.float32)
    pad_v = np.zeros(pad_p.shape[:-1], bool)
    pad_p[:, 8:, 3:], pad_v[:, 8:, 3:] = poly, valid
    pad_p[:, :8] = 1e3 * rng.normal(size=pad_p[:, :8].shape)  # garbage under invalid points
    z_pad = enc(params, (pad_p, pad_v, pose))
    scale = float(jnp.max(jnp.abs(z)))
    np.testing.assert_allclose(z_perm, z, atol=1e-4 * scale)
    np.testing.assert_allclose(z_pad, z, atol=1e-4 * scale)


def test_depends_on_lane_direction_and_only_on_nearby_lanes(model, frames):
    cfg, _, params, enc = model
    poly, valid, pose = frames
    z = np.asarray(enc(params, (poly, valid, pose)))
    # reversing every lane's points: the same drawing, the other way round -> other latents (direction is read)
    rev = np.zeros_like(poly)
    for b in range(poly.shape[0]):
        for i in range(poly.shape[1]):
            n = int(valid[b, i].sum())
            rev[b, i, :n] = poly[b, i, :n][::-1]
    z_rev = np.asarray(enc(params, (rev, valid, pose)))
    assert np.abs(z_rev - z).max() > 1e-3 * np.abs(z).max()
    # a cell only sees the segments near it: dropping the lanes that touch no cell of the front-left quadrant's
    # neighbourhood leaves those cells' latents as they were only when no token mixing reaches them (one layer of
    # cell self-attention mixes all cells), so check the mask itself
    seg = lane_segments(jnp.asarray(poly), jnp.asarray(valid), jnp.asarray(pose), 32.0, 2.0, 2, 256)
    m = np.asarray(cell_mask(seg, 8, 32.0, 2.0))  # [B, 64, N]
    mid = np.asarray(0.5 * (seg.start + seg.end))
    far = np.abs(mid[:, None, :, 0] - 28.0) > 6.0 + 1e-4  # more than half a cell + margin from row 0's centre x
    assert not np.any(m[:, :8][far[:, 0][:, None, :].repeat(8, 1)])
    assert m.sum() > 0


def test_empty_frame_encodes_to_valid_tokens(model):
    cfg, graphdef, params, enc = model
    poly = np.zeros((2, 4, 16, 2), np.float32)
    valid = np.zeros((2, 4, 16), bool)
    pose = np.zeros((2, 3), np.float32)
    z = enc(params, (poly, valid, pose))
    chex.assert_shape(z, (2, 64, cfg.model.encoder.code_dim))
    assert np.isfinite(np.asarray(z)).all()
    # all lanes outside the window: the same as none
    far = poly + 500.0
    np.testing.assert_allclose(enc(params, (far, np.ones_like(valid), pose)), z, atol=1e-5)


def test_tokenizer_api_compiles_once_and_decodes(tmp_path, model, frames):
    from gpd_jax.map_tokenizer.tokenizer import MapTokenizer, export_tokenizer, load_tokenizer
    cfg, graphdef, params, _ = model
    poly, valid, pose = frames
    out = str(tmp_path / "tok")
    export_tokenizer(params, cfg, out)
    tok = load_tokenizer(out)
    assert tok.reads_vectors and tok.num_tokens == 64
    with pytest.raises(ValueError, match="reads lane polylines"):
        tok.encode(tok.params, jnp.zeros((1, 256, 256)))
    enc = jax.jit(chex.assert_max_traces(lambda p, a, b, c: tok.encode_lanes(p, a, b, c), n=1))
    poses = np.stack([pose, pose + np.float32([1.0, 0.0, 0.1])], 1)  # [B, T=2, 3]
    t1 = enc(tok.params, poly[:, None], valid[:, None], poses)
    t2 = enc(tok.params, poly[:, None], valid[:, None], poses + np.float32([0.5, 0.0, 0.0]))
    chex.assert_shape(t1, (2, 2, 64))
    assert t1.dtype == jnp.int32 and int(t1.max()) < cfg.model.num_codes and int(t1.min()) >= 0
    assert t2.shape == t1.shape
    # encode_frames (what Model.prepare and `tokenizer encode` run) gives the same tokens
    np.testing.assert_array_equal(tok.encode_frames(poly, valid, poses), t1)
    pts, logits = tok.decode_tokens(t1)
    chex.assert_shape(pts, (2, 2, 50, 20, 2))
    assert isinstance(tok, MapTokenizer)


def test_evaluation_decodes_the_continuous_latents_when_asked(model):
    """`make_eval_step(quantized=False)` (`tokenizer evaluate --continuous`, the quantiser's cost) scores the lines
    decoded from the encoder's own latents, the default the lines of their nearest codes."""
    from gpd_jax.map_tokenizer.evaluation import encoder_input, frame_arrays, make_eval_step
    from gpd_jax.metrics.map import map_metric_sums
    cfg, graphdef, params, _ = model
    params = jax.tree.map(lambda x: x, params)  # a copy in which every decoded line exists (logit bias +5)
    params["decoder"]["logit_head"]["bias"] = params["decoder"]["logit_head"]["bias"] + 5.0
    batch = frame_arrays(synthetic_lanes(5, 2))
    cont, idx = jax.jit(make_eval_step(graphdef, cfg, diagnostics=False, quantized=False))(params, batch)
    codes, idx_codes = jax.jit(make_eval_step(graphdef, cfg, diagnostics=False))(params, batch)
    np.testing.assert_array_equal(idx, idx_codes)  # the tokens are the nearest codes either way
    out = core.forward(graphdef, params, encoder_input(cfg, batch), False)
    direct = map_metric_sums(out["points"], out["logits"], batch["lanes"], batch["lanes_valid"])
    for k in ("cf_pred_len", "cf_gt_len", "cf_pred_hit_len"):  # the decoded lines' length and their hits
        np.testing.assert_allclose(cont[k], direct[k], rtol=1e-4, atol=1e-4 * float(np.max(np.abs(direct[k]))))
    assert not np.allclose(cont["cf_pred_len"], codes["cf_pred_len"], rtol=1e-3)


def test_tiny_vector_tokenizer_redraws_a_handful_of_frames():
    """A few hundred steps on four frames through the quantizer (the steps take well under a second here; the
    compiles are the cost): the cut-invariant F1 at 1.5 m rises from nothing to a fixed level (about 0.78 after
    300 steps when written), and the reconstruction figures are all reported."""
    from gpd_jax.map_tokenizer.evaluation import frame_arrays, tokenizer_metrics
    from gpd_jax.training.map_tokenizer import (TrainState, build_model, compiled_steps, kmeans_init,
                                                make_optimizer)
    steps = 400
    cfg = vector_config(f"--config.train.num_steps={steps}", "--config.model.num_codes=32",
                        "--config.train.kmeans_rasters=4", "--config.train.lr=3e-3", "--config.train.warmup_steps=10")
    graphdef, params = build_model(cfg)
    batch = frame_arrays(synthetic_lanes(11, 4, max_lines=6))
    before = tokenizer_metrics(graphdef, params, cfg, [batch])
    params = kmeans_init(graphdef, params, cfg, jax.random.key(1), iter([batch] * 2))
    tx = make_optimizer(cfg.train, params)
    k = cfg.model.num_codes
    state = TrainState(jnp.zeros((), jnp.int32), params, tx.init(params), jnp.full((k,), 1 / k, jnp.float32),
                       jnp.ones((), bool))
    step, eval_step = compiled_steps(graphdef, cfg, tx)
    for _ in range(steps):
        state, m, _ = step(state, batch)
    after = tokenizer_metrics(graphdef, state.params, cfg, [batch], eval_step)
    for key in ("f1@0.5m", "f1@1m", "f1@1.5m", "f1_cutfree@0.5m", "f1_cutfree@1m", "f1_cutfree@1.5m",
                "chamfer_corrected", "chamfer_cutfree", "connectivity", "successor_pairs"):
        assert key in after, key
    assert after["f1@1.5m"] == pytest.approx(after["f1"])
    assert after["f1_cutfree@1.5m"] == pytest.approx(after["f1_cutfree"])
    assert after["f1_cutfree@0.5m"] <= after["f1_cutfree@1m"] <= after["f1_cutfree@1.5m"]
    assert before["f1_cutfree"] < 0.3, before["f1_cutfree"]
    assert after["f1_cutfree"] > 0.7, after["f1_cutfree"]


def test_config_variants_pick_the_encoder():
    """The raster encoder stays the paper's and the tiny one; the vector variants change the encoder only."""
    get = lambda v: load_config(os.path.join(ROOT, f"configs/map_tokenizer.py:{v}"))  # noqa: E731
    paper, tiny, vt, vec = get("paper"), get("tiny"), get("vector_tiny"), get("vector")
    assert paper.model.encoder.kind == tiny.model.encoder.kind == "raster"
    assert vt.model.encoder.kind == vec.model.encoder.kind == vector_config().model.encoder.kind == "vector"
    assert vt.model.decoder.to_dict() == tiny.model.decoder.to_dict()
    assert vec.model.decoder.to_dict() == paper.model.decoder.to_dict()
    assert vt.model.num_codes == 128 and vt.model.grid == 8  # the GPD's interface: 64 tokens of 128 codes
    from gpd_jax.map_tokenizer.model import MapVQVAE
    from flax import nnx
    bad = vector_config()
    bad.model.encoder.kind = "pointcloud"
    with pytest.raises(ValueError, match="model.encoder.kind"):
        MapVQVAE(bad.model, nnx.Rngs(0))
