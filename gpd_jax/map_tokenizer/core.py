"""Pure functions of a params pytree around `MapVQVAE`: forward pass, losses, k-means, dead-code restarts.

`params` is the pure nested dict of the model's `nnx.Param` arrays (`nnx.to_pure_dict(nnx.state(model,
nnx.Param))`) and `graphdef` comes from `nnx.split(model, nnx.Param)`; `nnx.merge(graphdef, params)` rebuilds
the module inside a trace.
Everything here is jit-able; the Hungarian matching runs on the host through `gpd_jax.metrics.matching`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import nnx

from gpd_jax.map_tokenizer.model import MapVQVAE, nearest_code
from gpd_jax.metrics.matching import match_lines


def codebook_of(params) -> jax.Array:
    """The learned codebook f32[K, D] inside a VQ tokenizer's params pytree (FSQ has none: `code_table`)."""
    return params["codebook"]["embedding"]


def with_codebook(params, codebook: jax.Array):
    """A copy of `params` whose codebook is replaced by `codebook: f32[K, D]`."""
    return {**params, "codebook": {**params["codebook"], "embedding": codebook}}


def forward(graphdef, params, raster: jax.Array, quantized: bool | jax.Array = True):
    """`MapVQVAE.__call__` as a pure function: raster f32[B, 256, 256] -> dict (see the model)."""
    model: MapVQVAE = nnx.merge(graphdef, params)
    return model(raster, quantized)


def code_table(graphdef, params) -> jax.Array:
    """f32[K, D]: the decoder input of each token id (the VQ codebook, or FSQ's implied one)."""
    model: MapVQVAE = nnx.merge(graphdef, params)
    return model.code_table()


def tokens_of(graphdef, params, z: jax.Array) -> jax.Array:
    """Token ids i32[...] of continuous latents f32[..., D] (the nearest code, or FSQ's rounded levels)."""
    model: MapVQVAE = nnx.merge(graphdef, params)
    return model.tokens(z)


def encode_latents(graphdef, params, raster: jax.Array) -> jax.Array:
    """Continuous encoder outputs f32[B, M, D] of rasters f32[B, 256, 256]."""
    model: MapVQVAE = nnx.merge(graphdef, params)
    return model.encode_latents(raster)


def _line_terms(points, logits, gt_points, gt_valid, w_l1: float, w_bce: float):
    """Per-sample (l1 f32[N], bce f32[N], match i32[N, G]) for flat batches (shapes as in `line_loss`, N = B):
    l1 is the sum over GT slots of the matched, labelled mean-point L1 divided by G; bce the mean over queries."""
    m_pts, _, match = match_lines(points, logits, gt_points, gt_valid, w_bce, w_l1)
    label = gt_valid.astype(jnp.float32)
    g = gt_valid.shape[-1]
    l1 = jnp.mean(jnp.sum(jnp.abs(m_pts - gt_points), -1), -1)  # [N, G]
    l1 = jnp.sum(l1 * label * (match >= 0), -1) / g
    q = logits.shape[-1]
    # Per-query label: the label of the GT slot the query was matched to, 0 if unmatched.
    onehot = jax.nn.one_hot(match, q, dtype=jnp.float32)  # [N, G, Q] (match -1 gives zeros)
    q_label = jnp.einsum("bgq,bg->bq", onehot, label)
    bce = jnp.mean(jax.nn.softplus(logits) - logits * q_label, -1)
    return l1, bce, match


def line_loss(points, logits, gt_points, gt_valid, w_l1: float = 2.0, w_bce: float = 5.0):
    """SLEDGE / GPD-1 line loss after Hungarian matching.

    Args:
      points: f32[B, Q, P, 2]; logits: f32[B, Q]; gt_points: f32[B, G, P, 2]; gt_valid: bool[B, G].

    Returns:
      (loss, dict(l1, bce, match i32[B, G])): `w_l1 * L1 + w_bce * BCE`, where L1 is mean_k sum_xy |p - g| of
      matched pairs masked by the GT label and BCE covers every query (queries matched to padding or to
      nothing learn label 0); both are averaged over B x G (SLEDGE's normalisation).
    """
    l1, bce, match = _line_terms(points, logits, gt_points, gt_valid, w_l1, w_bce)
    l1, bce = jnp.mean(l1), jnp.mean(bce)
    return w_l1 * l1 + w_bce * bce, dict(l1=l1, bce=bce, match=match)


def code_stats(idx: jax.Array, num_codes: int):
    """(counts f32[K], usage fraction of codes used, perplexity exp(H(p))) of token ids `idx: i32[...]`."""
    counts = jnp.zeros((num_codes,), jnp.float32).at[idx.reshape(-1)].add(1.0)
    p = counts / jnp.maximum(counts.sum(), 1.0)
    perplexity = jnp.exp(-jnp.sum(jnp.where(p > 0, p * jnp.log(jnp.where(p > 0, p, 1.0)), 0.0)))
    return counts, jnp.mean(counts > 0), perplexity


def kmeans(key: jax.Array, x: jax.Array, k: int, iters: int = 20) -> jax.Array:
    """k-means on `x: f32[N, D]` (N >= k) -> centres f32[k, D].

    k-means++ seeding (each new centre drawn with probability proportional to the squared distance to the
    nearest chosen one), then `iters` Lloyd steps; a cluster that empties is re-seeded with a random point.
    """
    n = x.shape[0]
    if n < k:
        raise ValueError(f"k-means needs at least k={k} points, got {n}")
    k_first, k_seed, k_lloyd = jax.random.split(key, 3)
    centres = jnp.zeros((k, x.shape[1]), x.dtype).at[0].set(x[jax.random.randint(k_first, (), 0, n)])
    d2 = jnp.sum((x - centres[0]) ** 2, -1)

    def seed(i, carry):
        c, d2 = carry
        j = jax.random.categorical(jax.random.fold_in(k_seed, i), jnp.log(jnp.maximum(d2, 1e-30)))
        c = c.at[i].set(x[j])
        return c, jnp.minimum(d2, jnp.sum((x - x[j]) ** 2, -1))

    centres, _ = jax.lax.fori_loop(1, k, seed, (centres, d2))

    def step(c, key):
        a = nearest_code(c, x)
        onehot = jax.nn.one_hot(a, k, dtype=x.dtype)  # [N, k]
        cnt = onehot.sum(0)
        mean = (onehot.T @ x) / jnp.maximum(cnt, 1.0)[:, None]
        fresh = x[jax.random.randint(key, (k,), 0, n)]
        return jnp.where((cnt > 0)[:, None], mean, fresh), None

    centres, _ = jax.lax.scan(step, centres, jax.random.split(k_lloyd, iters))
    return centres


def restart_dead_codes(key: jax.Array, codebook: jax.Array, usage: jax.Array, z: jax.Array, threshold: float):
    """Re-seeds rarely used codes with recent encoder outputs (the dead-code remedy).

    Args:
      key: PRNG key.
      codebook: f32[K, D].
      usage: f32[K] running (EMA) fraction of tokens assigned to each code; sums to about 1.
      z: f32[N, D] recent encoder outputs.
      threshold: a code is dead when its usage is below `threshold / K`.

    Returns:
      (codebook f32[K, D], usage f32[K] with re-seeded codes set to 1/K, number of codes re-seeded).
    """
    k = codebook.shape[0]
    dead = usage < threshold / k
    pick = jax.random.randint(key, (k,), 0, z.shape[0])
    new = z[pick] + 1e-3 * jax.random.normal(jax.random.fold_in(key, 1), codebook.shape) * jnp.std(z)
    codebook = jnp.where(dead[:, None], new, codebook)
    usage = jnp.where(dead, 1.0 / k, usage)
    return codebook, usage, jnp.sum(dead)
