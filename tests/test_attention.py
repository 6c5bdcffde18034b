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


KERNELS = pytest.mark.parametrize("kernel", ["xla", "xla_batched", "native"])


@KERNELS
def test_chunked_equals_dense(kernel):
    kernel = _kernel(kernel)
    n, frames, chunk = 5, 6, 10  # chunk of two frames
    s = n * frames
    q, k, v = _qkv(s)
    frame = jnp.arange(s) // n
    ref = dense_block_causal(q, k, v, frame, frame)
    _close(attend_static(q, k, v, n, chunk), ref)
    _close(attend_dynamic(q, k, v, frame, 3, n, chunk, kernel), ref)
    # the last frame's queries against a cache filled up to that frame only (garbage beyond)
    k_garbage = k.at[:, s - n:].set(1e3)
    last = slice(s - 2 * n, s - n)
    got = attend_dynamic(q[:, last], k_garbage, v, frame[last], 3, n, chunk, kernel)
    _close(got, ref[:, last])


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
        _close(nat, xla)
        _close(nat[0], dense_block_causal(q[0, :, rows], k[0], v[0], qf, frame))


def test_native_kernel_falls_back_when_it_cannot_build(monkeypatch):
    """A failed build warns and leaves "auto" on the XLA path (same results); "native" is then an error, as
    is an unknown kernel name; GPD_JAX_NATIVE=0 disables the kernel."""
    def broken_build(*args, **kwargs):
        raise RuntimeError("no C++ compiler found")

    monkeypatch.delenv("GPD_JAX_DECODE_ATTENTION", raising=False)  # tests/conftest.py pins it
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
    """The batching rules (xla: one scenario at a time; xla_batched: all scenarios per chunk, to the largest
    chunk count; native: batch dims passed to the kernel) match unbatched calls, also for a batched chunk count
    and unbatched keys."""
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
        _close(got[i][:, rows], ref[:, rows])
    shared = jax.vmap(lambda q: attend_dynamic(q, k[0], v[0], frame, 3, n, chunk, kernel))(q)
    _close(shared[1], dense_block_causal(q[1], k[0], v[0], frame, frame))


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


def _decode_case(b=2, h=2, dh=16, n=37, frames=12, chunk=74, seed=3):
    rng = np.random.default_rng(seed)
    s = n * frames
    q, k, v = (jnp.asarray(rng.normal(size=(b, h, size, dh)) * 2, jnp.float32) for size in (n, s, s))
    qf = jnp.full((n,), 7, jnp.int32)
    chunks = jnp.array([(8 * n) // chunk + 1] * b)
    return q, k, v, qf, chunks, n, chunk


def _close(got, want, rtol=1e-5):
    """Float comparison relative to the magnitude of the reference (portable across CPUs and builds)."""
    scale = max(1.0, float(jnp.abs(want).max()))
    np.testing.assert_allclose(got, want, rtol=rtol, atol=rtol * scale)


@pytest.fixture
def fresh_auto(monkeypatch, tmp_path):
    """An empty choice cache (on disk and in this process) and a counter of measurements."""
    from gpd_jax.model import autotune

    monkeypatch.setenv("GPD_JAX_CACHE", str(tmp_path))
    monkeypatch.delenv(autotune.FORCE_ENV, raising=False)
    monkeypatch.setattr(autotune, "_choices", {})
    monkeypatch.setattr(autotune, "_choice_log", [])
    calls = []
    real = autotune._measure

    def counted(*args, **kwargs):
        calls.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(autotune, "_measure", counted)
    return autotune, calls, tmp_path


def test_auto_measures_once_caches_on_disk_and_matches_xla(fresh_auto, monkeypatch):
    """"auto" times both paths once per shape and batch bucket at trace time (inside jit and vmap), writes
    the choice beside the kernel, reads it back in a new process (simulated by clearing the memo) without
    measuring, and gives the XLA path's results whichever it picked."""
    autotune, calls, cache = fresh_auto
    _kernel("native")
    q, k, v, qf, chunks, n, c = _decode_case()
    att = lambda kernel: jax.jit(jax.vmap(lambda q, k, v, m: attend_dynamic(q, k, v, qf, m, n, c, kernel)))(
        q, k, v, chunks)
    got = att("auto")
    _close(got, att("xla"))
    assert len(calls) == 1
    (rec,) = autotune.auto_choices()
    # whichever candidate measured fastest wins, the batched XLA path included
    assert rec["source"] == "measured" and rec["choice"] in ("native", "xla", "xla_batched")
    assert set(rec["times_ms"]) == {"native", "xla", "xla_batched"} == set(rec["key"]["candidates"])
    assert rec["choice"] == min(rec["times_ms"], key=rec["times_ms"].get)
    files = list((cache / "decode-attention").glob("*.json"))
    assert len(files) == 1 and not list((cache / "decode-attention").glob("*.tmp*"))
    key = rec["key"]
    assert key["batch_bucket"] == 2 and key["heads"] == 2 and key["queries"] == n and key["jax"] == jax.__version__
    # same shape again (retraced): no new measurement in this process
    jax.jit(jax.vmap(lambda q, k, v, m: attend_dynamic(q, k, v, qf, m, n, c, "auto")))(q, k, v, chunks)
    assert len(calls) == 1
    # a "new process": the choice comes from disk
    monkeypatch.setattr(autotune, "_choices", {})
    monkeypatch.setattr(autotune, "_choice_log", [])
    att("auto")
    assert len(calls) == 1 and autotune.auto_choices()[0]["source"] == "cached"
    # another batch bucket is measured on its own
    q4, k4, v4, _, chunks4, _, _ = _decode_case(b=4)
    jax.jit(jax.vmap(lambda q, k, v, m: attend_dynamic(q, k, v, qf, m, n, c, "auto")))(q4, k4, v4, chunks4)
    assert len(calls) == 2 and calls[-1][0] == 4


@pytest.mark.parametrize("forced", ["xla", "xla_batched", "native"])
def test_auto_forced_by_environment(fresh_auto, monkeypatch, forced):
    autotune, calls, _ = fresh_auto
    if forced == "native":
        _kernel("native")
    monkeypatch.setenv(autotune.FORCE_ENV, forced)
    q, k, v, qf, chunks, n, c = _decode_case()
    got = jax.jit(jax.vmap(lambda q, k, v, m: attend_dynamic(q, k, v, qf, m, n, c, "auto")))(q, k, v, chunks)
    ref = jax.jit(jax.vmap(lambda q, k, v, m: attend_dynamic(q, k, v, qf, m, n, c, "xla")))(q, k, v, chunks)
    _close(got, ref)
    assert not calls
    assert autotune.auto_choices()[-1]["choice"] == forced and autotune.auto_choices()[-1]["source"] == "forced"
    assert use_native("auto") == (forced == "native")
    monkeypatch.setenv(autotune.FORCE_ENV, "fastest")
    with pytest.raises(ValueError, match="expected one of native, xla, xla_batched, cudnn or auto"):
        use_native("auto")


def test_auto_without_compiler_uses_xla(tmp_path):
    """In a fresh process whose CXX names a missing compiler (and an empty kernel cache), "auto" warns, runs
    the XLA path without measuring and says why."""
    import os
    import subprocess
    import sys

    code = """
import warnings, json
import jax, jax.numpy as jnp
from gpd_jax.model import attention, autotune
q = jnp.ones((1, 2, 4, 16)); k = jnp.ones((1, 2, 8, 16))
with warnings.catch_warnings(record=True) as w:
    warnings.simplefilter("always")
    out = jax.vmap(lambda q, k: attention.attend_dynamic(q, k, k, jnp.zeros(4, jnp.int32), 1, 4, 8, "auto"))(q, k)
print(json.dumps({"choices": autotune.auto_choices(), "warned": any("unavailable" in str(x.message) for x in w),
                  "ok": bool(jnp.allclose(out, 1.0))}))
"""
    env = dict(os.environ, CXX=str(tmp_path / "no-such-compiler"), GPD_JAX_CACHE=str(tmp_path / "cache"))
    env.pop("GPD_JAX_DECODE_ATTENTION", None)
    env.pop("GPD_JAX_NATIVE", None)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    import json

    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["ok"] and out["warned"]
    assert [c["choice"] for c in out["choices"]] == ["xla"]
    assert out["choices"][0]["why"] == "the native kernel did not build"


def test_native_kernel_built_for_avx2_target_equals_xla():
    """The kernel compiled for -march=x86-64-v3 (AVX2, 8-float vectors), run beside the XLA path, for a
    prefill of several frames and a decode step, where the CPU can run AVX2 code. A CI job may force this
    target for every test with GPD_JAX_NATIVE_MARCH=x86-64-v3."""
    import platform

    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("x86-64 only")
    _kernel("native")
    if not native.runnable("x86-64-v3"):
        pytest.skip("this CPU cannot run AVX2 code")
    assert native.available("x86-64-v3")
    assert native.load("x86-64-v3")["vector_width"] == 8
    n, chunk, frames, h, dh = 37, 74, 12, 3, 16
    s = n * frames
    rng = np.random.default_rng(5)
    q, k, v = (jnp.asarray(rng.normal(size=(3, h, s, dh)) * 2, jnp.float32) for _ in range(3))
    frame = jnp.arange(s) // n
    for fill, count in [(0, 5), (9, 1)]:
        rows = slice(fill * n, (fill + count) * n)
        qf = frame[rows]
        chunks = jnp.array([(fill + count) * n // chunk + 1, 6, 7])
        scale = dh**-0.5
        avx2 = jax.jit(jax.vmap(lambda q, k, v, m: native.block_causal_attention(
            q * scale, k, v, qf, m, n, chunk, target="x86-64-v3")))(q[:, :, rows], k, v, chunks)
        xla = jax.jit(jax.vmap(lambda q, k, v, m: attend_dynamic(q, k, v, qf, m, n, chunk, "xla")))(
            q[:, :, rows], k, v, chunks)
        _close(avx2, xla)


def test_build_target_is_part_of_the_cache_key_and_unrunnable_targets_are_refused(monkeypatch):
    if not (shutil.which("c++") or shutil.which("g++")):
        pytest.skip("no C++ compiler")
    assert native.build_key("x86-64-v3") != native.build_key("x86-64")
    monkeypatch.setenv("GPD_JAX_NATIVE_MARCH", "x86-64-v3")
    assert native.march() == "x86-64-v3" and native.build_key() == native.build_key("x86-64-v3")
    assert native.runnable("x86-64")
    if "avx512f" not in native.cpu_flags():
        assert not native.runnable("x86-64-v4")
        monkeypatch.setattr(native, "_state", {})
        with pytest.warns(UserWarning, match="cannot run code built for -march=x86-64-v4"):
            assert not native.available("x86-64-v4")
    info = native.machine_info()
    assert info["isa"] in ("avx512", "avx2", "avx", "sse", "neon") or info["isa"] == info["machine"]
    assert info["jax"] == jax.__version__


def test_auto_inside_a_vmapped_scan_chooses_at_the_real_batch(fresh_auto):
    """The rollout's decode step runs in a `lax.scan` under `vmap`: its body is traced unbatched, so the
    choice at the real batch is made by the batching rule (a batch-1 choice is made for the unbatched trace)."""
    autotune, calls, _ = fresh_auto
    _kernel("native")
    q, k, v, qf, chunks, n, c = _decode_case(b=3)

    def steps(q, k, v, m):
        def body(acc, _):
            return acc + attend_dynamic(q, k, v, qf, m, n, c, "auto"), None
        return jax.lax.scan(body, jnp.zeros_like(q), None, length=2)[0]

    got = jax.jit(jax.vmap(steps))(q, k, v, chunks)
    ref = jax.jit(jax.vmap(lambda q, k, v, m: 2 * attend_dynamic(q, k, v, qf, m, n, c, "xla")))(q, k, v, chunks)
    _close(got, ref)
    assert 3 in [args[0] for args in calls]
    assert any(r["key"]["batch_bucket"] == 4 for r in autotune.auto_choices())


def test_auto_without_the_native_kernel_measures_the_two_xla_batching_rules(fresh_auto, monkeypatch):
    """Where the native kernel is no candidate (a GPU, GPD_JAX_NATIVE=0, no compiler), "auto" still measures at
    a batch above 1: the scenario-by-scenario rule ("xla") against the all-scenarios one ("xla_batched"), which
    a GPU needs (one scenario at a time leaves it idle). At batch 1 the two are the same path: no measurement."""
    autotune, calls, _ = fresh_auto
    monkeypatch.setattr(native, "available", lambda *a, **k: False)
    q, k, v, qf, chunks, n, c = _decode_case(b=3)
    got = jax.jit(jax.vmap(lambda q, k, v, m: attend_dynamic(q, k, v, qf, m, n, c, "auto")))(q, k, v, chunks)
    _close(got, jax.jit(jax.vmap(lambda q, k, v, m: attend_dynamic(q, k, v, qf, m, n, c, "xla")))(q, k, v, chunks))
    (rec,) = autotune.auto_choices()
    assert rec["source"] == "measured" and set(rec["times_ms"]) == {"xla", "xla_batched"}
    assert rec["choice"] == min(rec["times_ms"], key=rec["times_ms"].get) and len(calls) == 1
    assert calls[0][8] == ("xla", "xla_batched")  # the candidates measured
    one = attend_dynamic(q[0], k[0], v[0], qf, chunks[0], n, c, "auto")
    _close(one, got[0])
    assert autotune.auto_choices()[-1]["source"] == "only candidate" and len(calls) == 1
    assert autotune.candidates(1) == ["xla"] and autotune.candidates(2) == ["xla", "xla_batched"]


def test_cudnn_path_is_a_gpu_bfloat16_candidate_and_refused_elsewhere(monkeypatch):
    from gpd_jax.model import autotune
    from gpd_jax.model.attention import attend_dynamic

    q = jnp.zeros((2, 4, 8), jnp.bfloat16)
    kv = jnp.zeros((2, 16, 8), jnp.bfloat16)
    with pytest.raises(ValueError, match="cudnn attention path runs bfloat16 .* on a GPU"):
        attend_dynamic(q, kv, kv, jnp.zeros(4, jnp.int32), 1, 4, 8, kernel="cudnn")
    assert "cudnn" not in autotune.candidates(8, f32=False)  # this CPU
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert autotune.candidates(8, f32=False) == ["xla", "xla_batched", "cudnn"]
    assert "cudnn" not in autotune.candidates(8, f32=True)  # cuDNN's fused attention takes 16-bit inputs


@pytest.mark.parametrize("dh", [16, 12])  # the vectorized kernel and the generic one
def test_native_kernel_reads_a_bfloat16_cache(dh):
    """A bfloat16 cache: the native kernel widens keys and values to float32 and does float32 arithmetic, so it
    equals float32 attention over the widened cache (the XLA path, which multiplies in bf16, is near it)."""
    from gpd_jax.model import autotune

    if not native.available():
        pytest.skip("the native attention kernel is unavailable here")
    q, k, v, qf, chunks, n, c = _decode_case(b=3, dh=dh)
    k16, v16 = k.astype(jnp.bfloat16), v.astype(jnp.bfloat16)
    run = lambda kern, k, v: jax.jit(jax.vmap(lambda q, k, v, m: attend_dynamic(q, k, v, qf, m, n, c, kern)))(
        q, k, v, chunks)
    wide = run("xla", k16.astype(jnp.float32), v16.astype(jnp.float32))
    got = run("native", k16, v16)
    assert got.dtype == jnp.float32
    _close(got, wide)
    _close(run("xla", k16, v16), wide, rtol=2e-2)  # bf16 products: about 2^-8 relative
    assert "native" in autotune.candidates(4, f32=False)
