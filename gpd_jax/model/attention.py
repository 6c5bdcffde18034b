"""Block-causal ("scene-level") attention over frame-structured sequences, chunked over keys.

A token of frame t attends to every token of frames <= t (GPD-1's scene-level mask). Sequences are laid out
frame by frame, `tokens_per_frame` tokens each, so the frame of key position p is p // tokens_per_frame and
the mask is computed from positions; no (T*N)^2 matrix is ever materialized.

Keys and values are processed in chunks of whole frames with an online softmax (the flash-attention
recurrence). Two drivers share the chunk step:

* `attend_static`: a `lax.scan` over a static number of chunks with a flash-attention custom VJP, so memory
  is linear in sequence length in the forward and the backward pass (only the output and the per-query
  log-sum-exp are saved). Used for teacher-forced training and the recompute baseline.
* `attend_dynamic`: a `lax.fori_loop` over the chunks that are filled so far (a traced trip count), used by
  the KV-cached rollout so a step never touches empty cache slots beyond the last partial chunk.

Under `vmap` (a batch of scenarios) the XLA path has two batching rules: `"xla"` runs the scenarios one after
another (each score block stays in a CPU's caches), `"xla_batched"` runs every scenario's chunk at once (one
bigger matmul per chunk: what a GPU needs; one scenario at a time leaves it idle). On a CPU the KV-cached rollout
can instead call a fused native kernel (`gpd_jax.model.native`, an XLA FFI custom call with the same semantics)
that keeps score tiles in cache and uses every core: `kernel="native"`. `"auto"` (the default) chooses among
these by measurement, once per machine and shape: `gpd_jax.model.autotune` (`GPD_JAX_DECODE_ATTENTION` forces its
choice, `autotune.auto_choices()` says what was chosen and why). This module hands it the paths to choose from
(`decode_kernel`); the choosing lives there.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from gpd_jax.model import autotune, native

_NEG = -1e30


def _chunk(k, v, start, chunk_len):
    """Keys and values [start, start + chunk_len) of k, v f32[H, S, Dh]."""
    return (jax.lax.dynamic_slice_in_dim(k, start, chunk_len, axis=1),
            jax.lax.dynamic_slice_in_dim(v, start, chunk_len, axis=1))


def _chunk_update(q, q_frame, kc, vc, start, tokens_per_frame, carry):
    """One online-softmax update with a chunk kc, vc f32[H, C, Dh] whose first key is at `start`.

    q: f32[H, Sq, Dh] (pre-scaled), q_frame: i32[Sq], carry: (m f32[H, Sq], l f32[H, Sq], acc f32[H, Sq, Dh]).
    Head-major so both products are plain batched matmuls.
    """
    m, l, acc = carry
    k_frame = (start + jnp.arange(kc.shape[1])) // tokens_per_frame
    bias = jnp.where(k_frame[None, :] <= q_frame[:, None], 0.0, _NEG)  # [Sq, C], shared by heads
    f32 = jnp.float32  # bf16 inputs (a bf16 cache) accumulate in fp32; the carry is fp32 either way
    s = jnp.einsum("hqd,hkd->hqk", q.astype(kc.dtype), kc, preferred_element_type=f32) + bias[None]
    m_new = jnp.maximum(m, jnp.max(s, axis=-1))
    # Every query sees frame 0, which is in the first chunk, so m_new is a real score from the first chunk
    # on and masked entries underflow to exactly 0.
    p = jnp.exp(s - m_new[..., None])
    corr = jnp.exp(m - m_new)
    l = l * corr + jnp.sum(p, axis=-1)
    acc = acc * corr[..., None] + jnp.einsum("hqk,hkd->hqd", p.astype(vc.dtype), vc, preferred_element_type=f32)
    return m_new, l, acc


def _init_carry(q):
    h, sq, dh = q.shape
    f32 = jnp.float32
    return (jnp.full((h, sq), _NEG, f32), jnp.zeros((h, sq), f32), jnp.zeros((h, sq, dh), f32))


def _finish(carry):
    _, l, acc = carry
    return acc / jnp.maximum(l, 1e-30)[..., None]  # [H, Sq, Dh]


def attend_static(q, k, v, tokens_per_frame: int, chunk_len: int):
    """Block-causal attention of a whole sequence starting at frame 0; memory-linear, forward and backward.

    The query of position p has frame p // tokens_per_frame. A custom VJP (the flash-attention backward)
    saves only the output and the per-query log-sum-exp, and recomputes each chunk's probabilities in the
    backward scan, so neither pass stores more than one [H, Sq, chunk] block.

    Args:
      q: f32[H, Sq, Dh] queries. k, v: f32[H, S, Dh] keys/values, S a multiple of `chunk_len`, S >= Sq.
    Returns:
      f32[H, Sq, Dh].
    """
    if k.shape[1] % chunk_len:
        raise ValueError(f"key length {k.shape[1]} is not a multiple of the chunk length {chunk_len}")
    return _flash(q * (q.shape[-1] ** -0.5), k, v, tokens_per_frame, chunk_len)


def _flash_fwd_impl(q, k, v, n, c):
    q_frame = jnp.arange(q.shape[1]) // n

    def body(carry, start):
        kc, vc = _chunk(k, v, start, c)
        return _chunk_update(q, q_frame, kc, vc, start, n, carry), None

    carry, _ = jax.lax.scan(body, _init_carry(q), jnp.arange(0, k.shape[1], c))
    m, l, _ = carry
    return _finish(carry), m + jnp.log(jnp.maximum(l, 1e-30))


@functools.partial(jax.custom_vjp, nondiff_argnums=(3, 4))
def _flash(q, k, v, n, c):
    return _flash_fwd_impl(q, k, v, n, c)[0]


def _flash_fwd(q, k, v, n, c):
    out, lse = _flash_fwd_impl(q, k, v, n, c)
    return out, (q, k, v, out, lse)


def _flash_bwd(n, c, res, dout):
    q, k, v, out, lse = res
    q_frame = jnp.arange(q.shape[1]) // n
    delta = jnp.sum(dout * out, axis=-1)  # [H, Sq]

    def body(dq, start):
        kc, vc = _chunk(k, v, start, c)
        mask = ((start + jnp.arange(c)) // n)[None, :] <= q_frame[:, None]
        s = jnp.einsum("hqd,hkd->hqk", q, kc)
        p = jnp.where(mask[None], jnp.exp(s - lse[..., None]), 0.0)
        dv = jnp.einsum("hqk,hqd->hkd", p, dout)
        dp = jnp.einsum("hqd,hkd->hqk", dout, vc)
        ds = p * (dp - delta[..., None])
        dq = dq + jnp.einsum("hqk,hkd->hqd", ds, kc)
        dk = jnp.einsum("hqk,hqd->hkd", ds, q)
        return dq, (dk, dv)

    dq, (dk, dv) = jax.lax.scan(body, jnp.zeros_like(q), jnp.arange(0, k.shape[1], c))
    # scan stacks chunks on a new leading axis: [n_chunks, H, C, Dh] -> [H, S, Dh]
    unchunk = lambda x: jnp.transpose(x, (1, 0, 2, 3)).reshape(k.shape)
    return dq, unchunk(dk), unchunk(dv)


_flash.defvjp(_flash_fwd, _flash_bwd)


KERNELS = ("auto",) + autotune.PATHS  # attend_dynamic's `kernel`: "auto" or one of the paths


def use_native(kernel: str) -> bool:
    """Whether `attend_dynamic(..., kernel=kernel)` may call the native kernel: always for "native" (an error
    where it cannot), never for "xla" and "xla_batched"; for "auto", whether it is a candidate here (a CPU
    backend, the kernel built, not forced to an XLA path); which path "auto" takes at a given shape is measured
    (`autotune.auto_choices()`)."""
    if kernel not in KERNELS:
        raise ValueError(f"attention kernel {kernel!r}: expected one of {KERNELS}")
    if kernel in ("xla", "xla_batched", "cudnn"):
        return False
    if kernel == "native":
        if jax.default_backend() != "cpu":
            raise ValueError(f"the native attention kernel runs on CPU only (backend: {jax.default_backend()})")
        if not native.available():
            raise RuntimeError("the native attention kernel could not be built (see the warning above)")
        return True
    forced = autotune.forced()
    if forced is not None:
        return forced == "native" and use_native("native")
    return jax.default_backend() == "cpu" and native.available()


def attend_dynamic(q, k, v, q_frame, num_chunks, tokens_per_frame: int, chunk_len: int, kernel: str = "auto"):
    """Block-causal attention over the first `num_chunks` (traced) key chunks only.

    Same arguments as `attend_static` (q f32[H, Sq, Dh], k, v f32[H, S, Dh]) plus `q_frame: i32[Sq]` and
    `num_chunks: i32[]`, how many chunks of the cache are filled (at least partly). Not
    reverse-differentiable (a loop with a traced trip count); used for inference.

    Under `jax.vmap` the "xla" batching rule processes the batch one scenario after another, slicing each
    key chunk straight out of the batched cache: the score block of one scenario ([H, Sq, chunk], about a
    megabyte at paper size) stays in the CPU caches, where the memory-bound softmax runs several times
    faster per element than on a [B, H, Sq, chunk] block. The linear layers around it still see the batch.
    The "xla_batched" rule runs every scenario's chunk in one step (the loop over chunks goes to the largest
    filled count; later chunks are masked, so the result is the same): on a GPU the per-scenario loop
    serializes the batch.

    `kernel`: "xla", "xla_batched" (the above; the same without `vmap`), "cudnn" (one frame of queries per
    scenario, a decode step, through cuDNN's fused bf16 attention on a GPU, the batch in one call), "native" (the
    fused CPU kernel of `gpd_jax.model.native`, float32 arithmetic on a float32 or bfloat16 cache; same results
    within float rounding) or "auto" (the fastest of `autotune.candidates()` at this shape and batch, measured once
    per machine and shape; see `gpd_jax.model.autotune`). The choice is made while tracing, never inside the
    compiled computation.
    """
    q = q * (q.shape[-1] ** -0.5)
    f32 = all(x.dtype == jnp.float32 for x in (q, k, v))
    if kernel == "cudnn" and (jax.default_backend() != "gpu" or k.dtype != jnp.bfloat16):
        raise ValueError(f"the cudnn attention path runs bfloat16 (model.decode_dtype) on a GPU; got k {k.dtype} "
                         f"on backend {jax.default_backend()}")
    if kernel == "auto":
        if autotune.forced() is None:
            return autotune.dispatch(q, k, v, q_frame, num_chunks, tokens_per_frame, chunk_len, f32,
                                     kernel_for=decode_kernel)
        h, sq, dh = q.shape[-3:]  # forced: logged for auto_choices()
        kernel = autotune.choose(1, h, sq, k.shape[-2], dh, tokens_per_frame, chunk_len,
                                 kernel_for=decode_kernel)["choice"]
    if use_native(kernel):
        return native.block_causal_attention(q, k, v, q_frame, num_chunks, tokens_per_frame, chunk_len)
    return decode_kernel(kernel, tokens_per_frame, chunk_len)(q, k, v, q_frame, num_chunks)


def decode_kernel(kind: str, n: int, c: int):
    """Path `kind` ("native", "xla", "xla_batched" or "cudnn") of the decode attention of one scenario with `n`
    tokens per frame and chunks of `c`: `f(q, k, v, q_frame, num_chunks)` with q pre-scaled, vmappable. What
    `gpd_jax.model.autotune` measures and runs for "auto"."""
    if kind == "native":
        return lambda q, k, v, f, m: native.block_causal_attention(q, k, v, f, m, n, c)
    if kind in ("xla", "xla_batched"):
        return _dynamic_kernel(n, c, kind == "xla_batched")
    if kind == "cudnn":
        return _cudnn_kernel(n, c)
    raise ValueError(f"decode attention path {kind!r}: expected one of {autotune.PATHS}")


def _cudnn_attention(q, k, v, q_frame, n: int):
    """cuDNN's fused (flash) attention of a batch whose queries q bf16[B, H, n, Dh] (pre-scaled) are one frame each
    (q_frame i32[B, n], the same frame f within a row) against k, v bf16[B, H, S, Dh] (head-major, as the cache is
    held: no transpose): every key of frames <= f, i.e. the first (f + 1) * n, is visible (a padding mask of that
    length per scenario). Returns f32[B, H, n, Dh]."""
    from jax._src.cudnn.fused_attention_stablehlo import MaskType, dot_product_attention

    b, _, sq, _ = q.shape
    kv_len = ((q_frame[:, 0] + 1) * n).astype(jnp.int32)
    out = dot_product_attention(q.astype(k.dtype), k, v, None, None, jnp.full((b,), sq, jnp.int32), kv_len,
                                scale=1.0, mask_type=MaskType.PADDING, qkv_layout="BNTH")
    return out.astype(jnp.float32)


@functools.lru_cache(maxsize=None)
def _cudnn_kernel(n: int, c: int):
    """The "cudnn" decode path of one scenario (bf16 on a GPU): one frame of queries (n of them, a decode step) goes
    to cuDNN's flash attention in one call for the whole batch (its `vmap` rule); a block of several frames (a
    prefill outside `vmap`) takes the "xla_batched" path, since its mask is block-causal rather than a length."""
    masked = _dynamic_kernel(n, c, True)

    def one(q, k, v, q_frame, num_chunks):
        if q.shape[-2] != n:
            return masked(q, k, v, q_frame, num_chunks)
        return _cudnn_attention(q[None], k[None], v[None], q_frame[None], n)[0]

    kernel = jax.custom_batching.custom_vmap(one)

    @kernel.def_vmap
    def _all_scenarios(axis_size, in_batched, q, k, v, q_frame, num_chunks):
        if q.shape[-2] != n:
            axes = tuple(0 if b else None for b in in_batched)
            return jax.vmap(masked, in_axes=axes, axis_size=axis_size)(q, k, v, q_frame, num_chunks), True
        bcast = lambda x, b: x if b else jnp.broadcast_to(x, (axis_size,) + x.shape)
        q, k, v, q_frame = (bcast(x, b) for x, b in zip((q, k, v, q_frame), in_batched))
        return _cudnn_attention(q, k, v, q_frame, n), True

    return kernel


def _attend_one(q, q_frame, num_chunks, n, c, kv_slice):
    """Online softmax over `num_chunks` chunks; `kv_slice(start)` returns that chunk's (k, v)."""

    def body(i, carry):
        kc, vc = kv_slice(i * c)
        return _chunk_update(q, q_frame, kc, vc, i * c, n, carry)

    return _finish(jax.lax.fori_loop(0, num_chunks, body, _init_carry(q)))


@functools.lru_cache(maxsize=None)
def _dynamic_kernel(n: int, c: int, batched: bool = False):
    """The XLA decode attention of one scenario; under `vmap` its batching rule runs the scenarios one after
    another (`batched` False: "xla") or all of them in each chunk step ("xla_batched")."""
    def one(q, k, v, q_frame, num_chunks):
        return _attend_one(q, q_frame, num_chunks, n, c, lambda start: _chunk(k, v, start, c))

    kernel = jax.custom_batching.custom_vmap(one)

    if batched:
        @kernel.def_vmap
        def _all_scenarios(axis_size, in_batched, q, k, v, q_frame, num_chunks):
            qb, kb, vb, fb, nb = in_batched
            if nb:  # chunks beyond a scenario's filled part hold later frames and are masked: the max is exact
                num_chunks = jnp.max(num_chunks)
            axes = tuple(0 if b else None for b in (qb, kb, vb, fb))
            each = lambda q, k, v, f: _attend_one(q, f, num_chunks, n, c, lambda start: _chunk(k, v, start, c))
            return jax.vmap(each, in_axes=axes, axis_size=axis_size)(q, k, v, q_frame), True

        return kernel

    @kernel.def_vmap
    def _scenario_by_scenario(axis_size, in_batched, q, k, v, q_frame, num_chunks):
        qb, kb, vb, fb, nb = in_batched
        if nb:  # chunks beyond a scenario's filled part hold later frames and are masked: the max is exact
            num_chunks = jnp.max(num_chunks)
        bcast = lambda x, b: x if b else jnp.broadcast_to(x, (axis_size,) + x.shape)
        q, k, v, q_frame = bcast(q, qb), bcast(k, kb), bcast(v, vb), bcast(q_frame, fb)
        h, _, dh = q.shape[1:]

        def scenario(b, out):
            def sl(start):
                idx = (b, 0, start, 0)
                return (jax.lax.dynamic_slice(k, idx, (1, h, c, dh))[0],
                        jax.lax.dynamic_slice(v, idx, (1, h, c, dh))[0])

            res = _attend_one(q[b], q_frame[b], num_chunks, n, c, sl)
            return jax.lax.dynamic_update_index_in_dim(out, res.astype(out.dtype), b, axis=0)

        out = jax.lax.fori_loop(0, axis_size, scenario, jnp.zeros(q.shape, jnp.float32))
        return out, True

    return kernel


def dense_block_causal(q, k, v, q_frame, k_frame):
    """Reference implementation materializing the full mask (tests only). Shapes as `attend_static`."""
    s = jnp.einsum("hqd,hkd->hqk", q, k) * (q.shape[-1] ** -0.5)
    mask = k_frame[None, :] <= q_frame[:, None]
    s = jnp.where(mask[None], s, _NEG)
    p = jax.nn.softmax(s, axis=-1)
    return jnp.einsum("hqk,hkd->hqd", p, v)
