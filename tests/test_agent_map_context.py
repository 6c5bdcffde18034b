"""`model.agent_map_context`: each agent token reads the 3 x 3 map cells around it (not in the paper)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from gpd_jax.config import load_config
from gpd_jax.model import GPD
from gpd_jax.model.transformer import CONTEXT_CELLS
from gpd_jax.synthetic import synthetic_scenes

from conftest import ROOT


def _cfg(context: bool):
    c = load_config(f"{ROOT}/configs/gpd_tiny.py", ["--config.model.num_map_tokens=64"])
    c.model.agent_map_context = context
    return c


def test_context_reads_the_cells_around_each_agent_in_the_egos_frame():
    cfg = _cfg(True)
    model = GPD(cfg.model, nnx.Rngs(0))
    d = cfg.model.d_model
    seen = []
    # record what the MLP reads: replace it by a probe that returns its input's cell part
    model.context_in = lambda feats: feats[..., : len(CONTEXT_CELLS) * d]
    model.context_ln = lambda x: x
    model.context_out = lambda x: seen.append(x) or jnp.zeros((*x.shape[:-1], d))
    maps = jnp.broadcast_to(jnp.arange(64, dtype=jnp.float32)[None, :, None], (1, 64, d)) + 1.0  # cell id + 1
    h = 0.7  # the ego's heading: agents are placed in its frame
    c, s = np.cos(h), np.sin(h)
    ego = np.array([10.0, -4.0])
    local = np.array([[0.0, 0.0], [20.0, 12.0], [-29.0, -29.0], [40.0, 0.0]])  # (x forward, y left)
    xy = ego + local @ np.array([[c, s], [-s, c]])
    heading = np.full((1, 4), h)
    valid = np.ones((1, 4), bool)
    out = model.local_map_context(jnp.asarray(xy[None], jnp.float32), jnp.asarray(heading, jnp.float32),
                                  jnp.asarray(valid), maps)
    cells = np.asarray(seen[0]).reshape(1, 4, 9, d)[0, :, :, 0] - 1  # cell id, -1 where outside the grid
    # row = floor((32 - x) / 8), col = floor((32 - y) / 8), row-major over 8 x 8
    expect_center = [4 * 8 + 4, 1 * 8 + 2, 7 * 8 + 7]
    for a, centre in enumerate(expect_center):
        assert cells[a, 4] == centre, (a, cells[a])
        r, col = divmod(centre, 8)
        for k, (dr, dc) in enumerate(CONTEXT_CELLS):
            inside = 0 <= r + dr < 8 and 0 <= col + dc < 8
            assert cells[a, k] == ((r + dr) * 8 + col + dc if inside else -1)
    assert np.all(np.asarray(out) == 0)


def test_a_new_context_starts_as_the_model_without_it_and_agents_outside_get_none():
    plain, ctx = _cfg(False), _cfg(True)
    m = plain.model
    a = GPD(plain.model, nnx.Rngs(0))
    b = GPD(ctx.model, nnx.Rngs(0))
    scenes = synthetic_scenes(3, 1, m.num_frames, m.num_history, m.num_agents, 64, m.codebook_size)
    args = (scenes.xy[0], scenes.heading[0], scenes.valid[0], scenes.map_tokens[0], np.arange(m.num_frames))
    np.testing.assert_array_equal(np.asarray(a.embed(*args)), np.asarray(b.embed(*args)))
    # with a trained (non-zero) last layer, the map under the agents changes their tokens, only theirs
    b.context_out.kernel[...] = 0.1 * jax.random.normal(jax.random.key(1), b.context_out.kernel[...].shape)
    other = (scenes.map_tokens[0] + 1) % m.codebook_size
    t1 = np.asarray(b.embed(*args))
    t2 = np.asarray(b.embed(*args[:3], other, args[4]))
    agents = slice(64, None)
    valid = np.asarray(scenes.valid[0])
    changed = ~np.all(np.isclose(t1[:, agents], t2[:, agents]), axis=-1)
    assert changed[valid].mean() > 0.5
    assert not changed[~valid].any()
    # NaN in invalid slots leaves every gradient finite
    xy = np.where(valid[..., None], np.asarray(scenes.xy[0]), np.nan).astype(np.float32)

    def f(model):
        return jnp.sum(model.embed(xy, *args[1:]) ** 2)

    g = nnx.grad(f)(b)
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(g))


def test_fine_tune_adds_the_context_to_a_model_without_it(tmp_path):
    from gpd_jax.checkpoint import build_model, export_model
    from gpd_jax.training.loop import initial_params

    plain = _cfg(False)
    src = str(tmp_path / "src")
    export_model(nnx.state(build_model(plain, seed=7), nnx.Param), plain, src)
    ctx = _cfg(True)
    template = nnx.state(build_model(ctx, seed=0), nnx.Param)
    params = initial_params(src, ctx, template)
    flat_src = {jax.tree_util.keystr(p): x for p, x in jax.tree_util.tree_leaves_with_path(
        initial_params(src, plain))}
    for p, x in jax.tree_util.tree_leaves_with_path(params):
        k = jax.tree_util.keystr(p)
        if "context_" in k:
            assert k not in flat_src
        else:
            np.testing.assert_array_equal(np.asarray(x), np.asarray(flat_src[k]))
    with pytest.raises(ValueError, match="template"):
        initial_params(src, ctx)
    ctx.model.num_layers = 1
    with pytest.raises(ValueError, match="num_layers"):
        initial_params(src, ctx, template)


def test_map_extent_must_match_the_tokenizer():
    from types import SimpleNamespace

    from gpd_jax.checkpoint import check_map_extent

    cfg = _cfg(True)
    tok = SimpleNamespace(config=load_config(f"{ROOT}/configs/map_tokenizer_tiny.py"))
    check_map_extent(cfg, tok)
    cfg.model.map_extent_m = 50.0
    with pytest.raises(ValueError, match="map_extent_m is 50.0 m .* cover 64.0 m"):
        check_map_extent(cfg, tok)
