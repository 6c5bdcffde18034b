"""Finite scalar quantisation (`model.fsq_levels`): token ids, their values, the straight-through gradient, a
vector tokenizer encoding and decoding through FSQ, and fine-tuning a trained tokenizer onto FSQ."""

import itertools
import os

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpd_jax.config import load_config
from gpd_jax.map_tokenizer import core
from gpd_jax.map_tokenizer.model import fsq_index, fsq_round, fsq_values
from gpd_jax.map_tokenizer.synthetic import synthetic_lanes

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LEVELS = (8, 5, 3, 2)  # even and odd level counts, binary included


def fsq_config(*extra):
    return load_config(os.path.join(ROOT, "configs/map_tokenizer.py:vector_test"),
                       ["--config.model.fsq_levels=(4, 3)", "--config.model.num_codes=12", *extra])


def test_ids_cover_the_vocabulary_and_round_trip_to_values():
    digits = jnp.asarray(list(itertools.product(*[range(n) for n in LEVELS])), jnp.int32)  # [240, 4]
    ids = np.asarray(fsq_index(digits, LEVELS))
    np.testing.assert_array_equal(np.sort(ids), np.arange(int(np.prod(LEVELS))))  # a bijection onto [0, K)
    # random latents, wide enough to reach every level: ids in range, values equal to those of their ids
    h = 4.0 * jax.random.normal(jax.random.key(0), (4096, 4))
    values, d = fsq_round(h, LEVELS)
    idx = fsq_index(d, LEVELS)
    assert int(idx.min()) >= 0 and int(idx.max()) < int(np.prod(LEVELS))
    for i, n in enumerate(LEVELS):
        assert set(np.unique(np.asarray(d[:, i]))) == set(range(n))  # every level of every dim is used
    np.testing.assert_allclose(fsq_values(idx, LEVELS), values, atol=1e-6)
    assert float(jnp.abs(values).max()) <= 1.0
    # a value sits on its level: rounding the bounded latent moves it by at most half a level
    width = np.asarray([n // 2 for n in LEVELS], np.float32)
    np.testing.assert_allclose(np.asarray(values) * width, np.round(np.asarray(values) * width), atol=1e-5)


def test_straight_through_gradient():
    h = jnp.linspace(-2.0, 2.0, 40).reshape(10, 4)
    c = jnp.arange(40.0).reshape(10, 4) - 19.5
    g = jax.grad(lambda h: jnp.sum(fsq_round(h, LEVELS)[0] * c))(h)
    assert bool(jnp.all(jnp.isfinite(g)))
    assert bool(jnp.all(jnp.sign(g) == jnp.sign(c)))  # the bound is monotone: the gradient keeps the sign
    assert float(jnp.abs(g).min()) > 0


@pytest.fixture(scope="module")
def fsq_model():
    from gpd_jax.training.map_tokenizer import build_model
    cfg = fsq_config()
    graphdef, params = build_model(cfg)
    return cfg, graphdef, params


def test_model_tokens_table_and_gradient(fsq_model):
    from gpd_jax.training.map_tokenizer import loss_fn
    cfg, graphdef, params = fsq_model
    assert "fsq" in params and "codebook" not in params
    batch = synthetic_lanes(2, 2)
    from gpd_jax.map_tokenizer.evaluation import encoder_input
    out = core.forward(graphdef, params, encoder_input(cfg, batch))
    z, idx = out["z"], out["idx"]
    np.testing.assert_array_equal(core.tokens_of(graphdef, params, z), idx)
    table = core.code_table(graphdef, params)
    chex.assert_shape(table, (12, cfg.model.encoder.code_dim))
    # the decoder input of a token is the table's row: decoding ids equals decoding the quantised latents
    from flax import nnx
    zq = nnx.merge(graphdef, params).quantize(z)[0]
    np.testing.assert_allclose(jnp.take(table, idx, axis=0), zq, atol=1e-5 * float(jnp.abs(zq).max()))
    assert float(out["vq_loss"]) == 0.0
    grads = jax.grad(lambda p: loss_fn(graphdef, cfg, p, batch)[0])(params)
    for group in ("encoder", "fsq"):  # the encoder is reached only through the straight-through rounding
        leaves = jax.tree.leaves(grads[group])
        assert all(bool(jnp.all(jnp.isfinite(x))) for x in leaves)
        assert sum(float(jnp.abs(x).sum()) for x in leaves) > 0, group


def test_fsq_tokenizer_encodes_and_decodes(tmp_path, fsq_model):
    from gpd_jax.map_tokenizer.tokenizer import export_tokenizer, load_tokenizer
    cfg, graphdef, params = fsq_model
    d = synthetic_lanes(3, 2)
    poly, valid, pose = d["polylines"], d["polyline_valid"], d["pose"]
    export_tokenizer(params, cfg, str(tmp_path / "tok"))
    tok = load_tokenizer(str(tmp_path / "tok"))
    chex.assert_shape(tok.codebook, (12, cfg.model.encoder.code_dim))  # what the GPD embeds
    enc = jax.jit(chex.assert_max_traces(lambda p, a, b, c: tok.encode_lanes(p, a, b, c), n=1))
    poses = np.stack([pose, pose + np.float32([1.0, 0.0, 0.1])], 1)  # [B, T=2, 3]
    t = enc(tok.params, poly[:, None], valid[:, None], poses)
    enc(tok.params, poly[:, None], valid[:, None], poses + np.float32([0.5, 0.0, 0.0]))
    chex.assert_shape(t, (2, 2, 64))
    assert t.dtype == jnp.int32 and int(t.min()) >= 0 and int(t.max()) < 12
    np.testing.assert_array_equal(tok.encode_frames(poly, valid, poses), t)
    pts, logits = tok.decode_tokens(t)
    chex.assert_shape(pts, (2, 2, 50, 20, 2))
    # the decoded lines of the tokens are those of the quantised forward pass
    from gpd_jax.map_tokenizer.evaluation import encoder_input
    out = core.forward(tok.graphdef, tok.params, encoder_input(cfg, d))
    pts0, _ = tok.decode_tokens(out["idx"])
    np.testing.assert_allclose(pts0, out["points"], atol=1e-3 * cfg.model.decoder.max_coord)
    # the FSQ projections decide the tokens: they enter the fingerprint
    moved = jax.tree.map(lambda x: x, tok.params)
    moved["fsq"]["proj_in"]["bias"] = moved["fsq"]["proj_in"]["bias"] + 1.0
    assert type(tok)(tok.config, tok.graphdef, moved).fingerprint() != tok.fingerprint()


def test_levels_must_match_the_code_count():
    from flax import nnx
    from gpd_jax.map_tokenizer.model import MapVQVAE
    bad = fsq_config("--config.model.num_codes=16")
    with pytest.raises(ValueError, match="model.fsq_levels"):
        MapVQVAE(bad.model, nnx.Rngs(0))


def test_a_trained_tokenizer_takes_fsq_keeping_encoder_and_decoder(tmp_path):
    from gpd_jax.map_tokenizer.tokenizer import export_tokenizer
    from gpd_jax.training.map_tokenizer import build_model, initial_params
    vq = load_config(os.path.join(ROOT, "configs/map_tokenizer.py:vector_test"))
    _, src = build_model(vq, seed=3)
    export_tokenizer(src, vq, str(tmp_path / "src"), dtype=np.float32)
    cfg = fsq_config(f"--config.train.init_from={tmp_path / 'src'}")
    params = initial_params(cfg, str(tmp_path / "src"))
    assert "codebook" not in params and "fsq" in params
    for group in ("encoder", "decoder"):
        chex.assert_trees_all_close(params[group], src[group])
    with pytest.raises(ValueError, match="decoder_only"):
        initial_params(fsq_config("--config.train.decoder_only=True"), str(tmp_path / "src"))
    with pytest.raises(ValueError, match="quantiser only to FSQ"):  # a new VQ codebook would need its k-means
        initial_params(load_config(os.path.join(ROOT, "configs/map_tokenizer.py:vector_test"),
                                   ["--config.model.num_codes=32"]), str(tmp_path / "src"))
