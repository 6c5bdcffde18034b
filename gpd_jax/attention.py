"""Block-causal ("scene-level") attention over frame-structured sequences, chunked over keys.

A token of frame t attends to every token of frames <= t (GPD-1's scene-level mask). Sequences are laid out
frame by frame, `tokens_per_frame` tokens each, so the frame of key position p is p // tokens_per_frame and
the mask is computed from positions; no (T*N)^2 matrix is ever materialized.

Keys and values are processed in chunks of whole frames with an online softmax (the flash-attention
recurrence). Two drivers share the chunk step:

* `attend_static`: a `lax.scan` over a static number of chunks with a rematerialized body, so reverse-mode
  memory is linear in sequence length (only the running (max, sum, acc) carry is saved per chunk). Used for
  teacher-forced training and the recompute baseline.
* `attend_dynamic`: a `lax.fori_loop` over the chunks that are filled so far (a traced trip count), used by
  the KV-cached rollout so a step never touches empty cache slots beyond the last partial chunk.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

_NEG = -1e30


def _chunk_step(q, q_frame, k, v, start, chunk_len, tokens_per_frame, carry):
    """One online-softmax update with keys/values [start, start + chunk_len).

    q: f32[Sq, H, Dh] (pre-scaled), q_frame: i32[Sq], k, v: f32[S, H, Dh], carry: (m f32[H, Sq],
    l f32[H, Sq], acc f32[H, Sq, Dh]).
    """
    m, l, acc = carry
    kc = jax.lax.dynamic_slice_in_dim(k, start, chunk_len, axis=0)
    vc = jax.lax.dynamic_slice_in_dim(v, start, chunk_len, axis=0)
    k_frame = (start + jnp.arange(chunk_len)) // tokens_per_frame
    mask = k_frame[None, :] <= q_frame[:, None]  # [Sq, C]
    s = jnp.einsum("qhd,khd->hqk", q, kc)
    s = jnp.where(mask[None], s, _NEG)
    m_new = jnp.maximum(m, jnp.max(s, axis=-1))
    p = jnp.where(mask[None], jnp.exp(s - m_new[..., None]), 0.0)
    corr = jnp.exp(m - m_new)
    l = l * corr + jnp.sum(p, axis=-1)
    acc = acc * corr[..., None] + jnp.einsum("hqk,khd->hqd", p, vc)
    return m_new, l, acc


def _init_carry(q):
    sq, h, dh = q.shape
    return (jnp.full((h, sq), _NEG, q.dtype), jnp.zeros((h, sq), q.dtype), jnp.zeros((h, sq, dh), q.dtype))


def _finish(carry):
    _, l, acc = carry
    out = acc / jnp.maximum(l, 1e-30)[..., None]  # [H, Sq, Dh]
    return jnp.transpose(out, (1, 0, 2))


def attend_static(q, k, v, q_frame, tokens_per_frame: int, chunk_len: int):
    """Block-causal attention, all keys, static chunk count; memory-linear under reverse-mode autodiff.

    Args:
      q: f32[Sq, H, Dh] queries. k, v: f32[S, H, Dh] keys/values with S a multiple of `chunk_len`.
      q_frame: i32[Sq] frame index of each query.
    Returns:
      f32[Sq, H, Dh].
    """
    s_len = k.shape[0]
    if s_len % chunk_len:
        raise ValueError(f"key length {s_len} is not a multiple of the chunk length {chunk_len}")
    q = q * (q.shape[-1] ** -0.5)

    @jax.checkpoint
    def body(carry, start):
        return _chunk_step(q, q_frame, k, v, start, chunk_len, tokens_per_frame, carry), None

    carry, _ = jax.lax.scan(body, _init_carry(q), jnp.arange(0, s_len, chunk_len))
    return _finish(carry)


def attend_dynamic(q, k, v, q_frame, num_chunks, tokens_per_frame: int, chunk_len: int):
    """Block-causal attention over the first `num_chunks` (traced) key chunks only.

    Same arguments as `attend_static`, plus `num_chunks: i32[]`: how many chunks of the cache are filled
    (at least partly). Not reverse-differentiable (a loop with a traced trip count); used for inference.
    """
    q = q * (q.shape[-1] ** -0.5)

    def body(i, carry):
        return _chunk_step(q, q_frame, k, v, i * chunk_len, chunk_len, tokens_per_frame, carry)

    carry = jax.lax.fori_loop(0, num_chunks, body, _init_carry(q))
    return _finish(carry)


def dense_block_causal(q, k, v, q_frame, k_frame):
    """Reference implementation materializing the full mask (tests only). Shapes as `attend_static`."""
    s = jnp.einsum("qhd,khd->hqk", q, k) * (q.shape[-1] ** -0.5)
    mask = k_frame[None, :] <= q_frame[:, None]
    s = jnp.where(mask[None], s, _NEG)
    p = jax.nn.softmax(s, axis=-1)
    return jnp.einsum("hqk,khd->qhd", p, v)
