import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from gpd_jax.attention import attend_dynamic, attend_static, dense_block_causal
from gpd_jax.model import GPD
from gpd_jax.train_lib import batch_loss


def _qkv(s, h=3, dh=4, seed=0):
    k1, k2, k3 = jax.random.split(jax.random.key(seed), 3)
    return (jax.random.normal(k1, (h, s, dh)), jax.random.normal(k2, (h, s, dh)),
            jax.random.normal(k3, (h, s, dh)))


def test_chunked_equals_dense():
    n, frames, chunk = 5, 6, 10  # chunk of two frames
    s = n * frames
    q, k, v = _qkv(s)
    frame = jnp.arange(s) // n
    ref = dense_block_causal(q, k, v, frame, frame)
    np.testing.assert_allclose(attend_static(q, k, v, n, chunk), ref, atol=1e-5)
    np.testing.assert_allclose(attend_dynamic(q, k, v, frame, 3, n, chunk), ref, atol=1e-5)
    # the last frame's queries against a cache filled up to that frame only (garbage beyond)
    k_garbage = k.at[:, s - n:].set(1e3)
    last = slice(s - 2 * n, s - n)
    got = attend_dynamic(q[:, last], k_garbage, v, frame[last], 3, n, chunk)
    np.testing.assert_allclose(got, ref[:, last], atol=1e-5)


def test_gradients_match_dense():
    n, frames, chunk = 4, 4, 8
    s = n * frames
    q, k, v = _qkv(s, seed=1)
    frame = jnp.arange(s) // n
    g1 = jax.grad(lambda q, k, v: jnp.sum(jnp.sin(attend_static(q, k, v, n, chunk))), (0, 1, 2))(q, k, v)
    g2 = jax.grad(lambda q, k, v: jnp.sum(jnp.sin(dense_block_causal(q, k, v, frame, frame))), (0, 1, 2))(q, k, v)
    for a, b in zip(g1, g2):
        np.testing.assert_allclose(a, b, atol=1e-4)


def _max_intermediate(jaxpr) -> int:
    biggest = 0
    for eqn in jaxpr.eqns:
        for var in eqn.outvars:
            shape = getattr(var.aval, "shape", ())
            biggest = max(biggest, int(np.prod(shape)) if shape else 1)
        for p in eqn.params.values():
            for sub in (p if isinstance(p, (list, tuple)) else [p]):
                inner = getattr(sub, "jaxpr", None)
                if inner is not None:
                    biggest = max(biggest, _max_intermediate(getattr(inner, "jaxpr", inner)))
    return biggest


def test_training_gradient_is_memory_linear(tiny_config):
    """No intermediate of the training gradient holds a (T*N)^2 attention matrix."""
    cfg = tiny_config
    m = cfg.model.copy_and_resolve_references()
    m.num_frames, m.attn_chunk_frames = 40, 2
    model = GPD(m, nnx.Rngs(0))
    from gpd_jax.synthetic import synthetic_scenes

    scenes = synthetic_scenes(0, 1, 40, 5, m.num_agents, m.num_map_tokens, m.codebook_size)
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    loss = lambda p: batch_loss(nnx.merge(graphdef, p, rest), scenes, cfg.loss)[0]
    jaxpr = jax.make_jaxpr(jax.grad(loss))(params)
    s = 39 * (m.num_agents + m.num_map_tokens)  # tokens of the 39 input frames
    biggest = _max_intermediate(jaxpr.jaxpr)
    # the largest intermediate is one [H, S, chunk] score block (plus [S, ffn]-sized activations)
    assert biggest <= max(m.num_heads * s * model.chunk_len, 40 * 21 * m.ffn_dim), (biggest, s * s)
    assert biggest * 4 < s * s


def test_vmapped_dynamic_attention_equals_per_scenario():
    """The custom batching rule (one scenario at a time) matches unbatched calls, also for a batched
    chunk count and unbatched keys."""
    n, frames, chunk, b = 5, 6, 10, 3
    s = n * frames
    qs, ks, vs = zip(*[_qkv(s, seed=i) for i in range(b)])
    q, k, v = jnp.stack(qs), jnp.stack(ks), jnp.stack(vs)
    frame = jnp.arange(s) // n
    counts = jnp.array([1, 3, 2])
    got = jax.jit(jax.vmap(lambda q, k, v, c: attend_dynamic(q, k, v, frame, c, n, chunk)))(q, k, v, counts)
    for i in range(b):
        ref = dense_block_causal(q[i], k[i], v[i], frame, frame)
        # rows whose visible keys all lie inside the processed chunks are exact
        rows = frame < (int(counts[i]) * chunk) // n
        np.testing.assert_allclose(got[i][:, rows], ref[:, rows], atol=1e-5)
    shared = jax.vmap(lambda q: attend_dynamic(q, k[0], v[0], frame, 3, n, chunk))(q)
    np.testing.assert_allclose(shared[1], dense_block_causal(q[1], k[0], v[0], frame, frame), atol=1e-5)


def test_model_dense_training_attention_equals_flash(tiny_model, tiny_scenes):
    """`model.train_attention = "dense"` is the same function as the chunked flash path."""
    import jax.numpy as jnp

    from gpd_jax.model import forward

    s = jax.tree.map(lambda x: jnp.asarray(x[0]), tiny_scenes)
    tok = tiny_model.embed(s.xy, s.heading, s.valid, s.map_tokens, jnp.arange(s.num_frames))
    flash = forward(tiny_model, tok)
    tiny_model.dense_attention = True
    try:
        dense = forward(tiny_model, tok)
    finally:
        tiny_model.dense_attention = False
    np.testing.assert_allclose(np.asarray(dense), np.asarray(flash), atol=1e-4, rtol=1e-4)
