import shutil
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from gpd_jax.model import native
from gpd_jax.model.attention import attend_dynamic, attend_static, dense_block_causal, use_native
from gpd_jax.model import GPD
from gpd_jax.training.step import batch_loss


def _qkv(s, h=3, dh=4, seed=0):
    k1, k2, k3 = jax.random.split(jax.random.key(seed), 3)
    return (jax.random.normal(k1, (h, s, dh)), jax.random.normal(k2, (h, s, dh)),
            jax.random.normal(k3, (h, s, dh)))


def _kernel(kernel: str) -> str:
    """The decode kernel to test; the native one must build wherever a C++ compiler is installed."""
    if kernel == "native" and not native.available():
        if shutil.which("c++") or shutil.which("g++"):
            pytest.fail("a C++ compiler is installed but the native attention kernel did not build")
        pytest.skip("no C++ compiler: the native attention kernel is unavailable")
    return kernel


KERNELS = pytest.mark.parametrize("kernel", ["xla", "native"])


@KERNELS
def test_chunked_equals_dense(kernel):
    kernel = _kernel(kernel)
    n, frames, chunk = 5, 6, 10  # chunk of two frames
    s = n * frames
    q, k, v = _qkv(s)
    frame = jnp.arange(s) // n
    ref = dense_block_causal(q, k, v, frame, frame)
    np.testing.assert_allclose(attend_static(q, k, v, n, chunk), ref, atol=1e-5)
    np.testing.assert_allclose(attend_dynamic(q, k, v, frame, 3, n, chunk, kernel), ref, atol=1e-5)
    # the last frame's queries against a cache filled up to that frame only (garbage beyond)
    k_garbage = k.at[:, s - n:].set(1e3)
    last = slice(s - 2 * n, s - n)
    got = attend_dynamic(q[:, last], k_garbage, v, frame[last], 3, n, chunk, kernel)
    np.testing.assert_allclose(got, ref[:, last], atol=1e-5)


@pytest.mark.parametrize("dh", [16, 32, 12])
def test_native_kernel_equals_xla_at_model_sizes(dh):
    """The fused kernel's vector path (head size a multiple of 16) and its generic path, for a prefill of
    several frames and for one-frame decode steps against a partly filled cache, batched under vmap with a
    different fill per scenario; key blocks of 128 end mid-frame and mid-chunk."""
    _kernel("native")
    n, chunk, frames, h = 37, 74, 12, 3
    s = n * frames
    rng = np.random.default_rng(dh)
    q, k, v = (jnp.asarray(rng.normal(size=(4, h, s, dh)) * 2, jnp.float32) for _ in range(3))
    frame = jnp.arange(s) // n
    for fill, count in [(0, 5), (4, 1), (9, 1)]:  # prefill 5 frames; decode frame 4; decode frame 9
        rows = slice(fill * n, (fill + count) * n)
        qf = frame[rows]
        chunks = jnp.array([(fill + count) * n // chunk + 1, 6, 7, 8])  # >= the filled part
        att = lambda kernel: jax.jit(jax.vmap(lambda q, k, v, c: attend_dynamic(q, k, v, qf, c, n, chunk, kernel)))(
            q[:, :, rows], k, v, chunks)
        nat, xla = att("native"), att("xla")
        np.testing.assert_allclose(nat, xla, atol=2e-5, rtol=1e-5)
        np.testing.assert_allclose(nat[0], dense_block_causal(q[0, :, rows], k[0], v[0], qf, frame), atol=2e-5)


def test_native_kernel_falls_back_when_it_cannot_build(monkeypatch):
    """A failed build warns and leaves "auto" on the XLA path (same results); "native" is then an error, as
    is an unknown kernel name; GPD_JAX_NATIVE=0 disables the kernel."""
    def broken_build(*args, **kwargs):
        raise RuntimeError("no C++ compiler found")

    monkeypatch.setattr(native, "build", broken_build)
    monkeypatch.setattr(native, "_state", {})
    with pytest.warns(UserWarning, match="native attention kernel unavailable.*no C\\+\\+ compiler"):
        assert not use_native("auto")
    assert not use_native("auto")  # decided once
    with pytest.raises(RuntimeError, match="could not be built"):
        use_native("native")
    with pytest.raises(ValueError, match="expected one of"):
        use_native("fast")
    monkeypatch.setattr(native, "_state", {})
    monkeypatch.setenv("GPD_JAX_NATIVE", "0")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not native.available()


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


@KERNELS
def test_vmapped_dynamic_attention_equals_per_scenario(kernel):
    """The batching rules (XLA: one scenario at a time; native: batch dims passed to the kernel) match
    unbatched calls, also for a batched chunk count and unbatched keys."""
    kernel = _kernel(kernel)
    n, frames, chunk, b = 5, 6, 10, 3
    s = n * frames
    qs, ks, vs = zip(*[_qkv(s, seed=i) for i in range(b)])
    q, k, v = jnp.stack(qs), jnp.stack(ks), jnp.stack(vs)
    frame = jnp.arange(s) // n
    counts = jnp.array([1, 3, 2])
    got = jax.jit(jax.vmap(lambda q, k, v, c: attend_dynamic(q, k, v, frame, c, n, chunk, kernel)))(q, k, v, counts)
    for i in range(b):
        ref = dense_block_causal(q[i], k[i], v[i], frame, frame)
        # rows whose visible keys all lie inside the processed chunks are exact
        rows = frame < (int(counts[i]) * chunk) // n
        np.testing.assert_allclose(got[i][:, rows], ref[:, rows], atol=1e-5)
    shared = jax.vmap(lambda q: attend_dynamic(q, k[0], v[0], frame, 3, n, chunk, kernel))(q)
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
