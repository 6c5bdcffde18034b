"""Hungarian matching of predicted lines to ground-truth lines (map tokenizer training and map metrics).

The cost is the one SLEDGE's RVAE and the official GPD-1 map tokenizer use (`reference/sledge_nuplan.md` §1,
`reference/gpd_official.md` §4):

    C[q, g] = w_bce * BCEWithLogits(logit_q, label_g) + w_l1 * label_g * mean_k sum_xy |p_qk - g_gk|

with `label_g` the ground-truth existence of slot g. Every query is matched, padded GT slots included: a padded
slot (label 0) costs only the BCE term, which pulls queries that predict "no line" towards it.

The assignment itself runs on the host (`scipy.optimize.linear_sum_assignment`) through `jax.pure_callback`, so it
works under `jit` and `vmap` with any number of leading batch dimensions.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize


def line_match_cost(pred_points: jax.Array, pred_logits: jax.Array, gt_points: jax.Array, gt_valid: jax.Array,
                    w_bce: float = 5.0, w_l1: float = 2.0) -> jax.Array:
    """Pairwise matching cost between predicted and ground-truth lines.

    Args:
      pred_points: f32[..., Q, P, 2] predicted line points (metres).
      pred_logits: f32[..., Q] predicted existence logits.
      gt_points: f32[..., G, P, 2] ground-truth line points (metres; padding is ignored).
      gt_valid: bool[..., G] ground-truth existence labels.
      w_bce: weight of the existence BCE term (5 in SLEDGE / GPD-1).
      w_l1: weight of the point L1 term (2 in SLEDGE / GPD-1).

    Returns:
      f32[..., Q, G] cost; `w_bce * BCE(logit_q, valid_g) + w_l1 * valid_g * mean_P(|dx| + |dy|)`.
    """
    label = gt_valid.astype(pred_logits.dtype)[..., None, :]  # [..., 1, G]
    logit = pred_logits[..., :, None]  # [..., Q, 1]
    # BCEWithLogits(x, y) = softplus(x) - x*y, written in the numerically stable form.
    bce = jax.nn.softplus(logit) - logit * label  # [..., Q, G]
    diff = jnp.abs(pred_points[..., :, None, :, :] - gt_points[..., None, :, :, :])  # [..., Q, G, P, 2]
    l1 = jnp.mean(jnp.sum(diff, axis=-1), axis=-1)  # [..., Q, G]
    return w_bce * bce + w_l1 * label * l1


def _lsa_host(cost: np.ndarray) -> np.ndarray:
    """Host side of `hungarian`: cost[..., Q, G] -> i32[..., G] (-1 for an unmatched GT slot when Q < G)."""
    cost = np.asarray(cost, dtype=np.float64)
    *lead, q, g = cost.shape
    flat = cost.reshape((-1, q, g))
    # linear_sum_assignment rejects NaN / inf; a huge finite value keeps such pairs last in line.
    flat = np.nan_to_num(flat, nan=1e30, posinf=1e30, neginf=-1e30)
    out = np.full((flat.shape[0], g), -1, dtype=np.int32)
    for b in range(flat.shape[0]):
        rows, cols = scipy.optimize.linear_sum_assignment(flat[b])
        out[b, cols] = rows
    return out.reshape(tuple(lead) + (g,))


def hungarian(cost: jax.Array) -> jax.Array:
    """Minimum-cost one-to-one assignment of queries to ground-truth slots.

    Args:
      cost: f32[..., Q, G] cost of assigning query q to GT slot g.

    Returns:
      i32[..., G] for each GT slot the index of its matched query; -1 where no query is left (only when Q < G).
      Jit- and vmap-able (host callback to `scipy.optimize.linear_sum_assignment`, one call per batch); safe inside
      a differentiated loss (the cost is treated as a constant).
    """
    cost = jax.lax.stop_gradient(jnp.asarray(cost))  # the assignment is piecewise constant: no gradient
    out_shape = jax.ShapeDtypeStruct(cost.shape[:-2] + cost.shape[-1:], jnp.int32)
    # The host function handles any leading dims, so vmap can hand it the batched array in one call.
    return jax.pure_callback(_lsa_host, out_shape, cost, vmap_method="broadcast_all")


def gather_matched(x: jax.Array, match: jax.Array) -> jax.Array:
    """Reorders per-query arrays into GT-slot order.

    Args:
      x: [..., Q, *F] per-query values (points f32[..., Q, P, 2], logits f32[..., Q], ...).
      match: i32[..., G] output of `hungarian` (-1 entries gather query 0; mask them with `match >= 0`).

    Returns:
      [..., G, *F] with `out[..., g, ...] = x[..., match[g], ...]`.
    """
    lead = match.ndim - 1
    idx = jnp.maximum(match, 0)
    feat = x.shape[lead + 1:]
    idx = idx.reshape(idx.shape + (1,) * len(feat))
    return jnp.take_along_axis(x, idx, axis=lead)


def match_lines(pred_points: jax.Array, pred_logits: jax.Array, gt_points: jax.Array, gt_valid: jax.Array,
                w_bce: float = 5.0, w_l1: float = 2.0) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Hungarian-matches predicted lines to GT slots and returns the predictions in GT-slot order.

    Args:
      pred_points: f32[..., Q, P, 2]; pred_logits: f32[..., Q]; gt_points: f32[..., G, P, 2]; gt_valid: bool[..., G].

    Returns:
      (matched_points f32[..., G, P, 2], matched_logits f32[..., G], match i32[..., G]). The matching is
      treated as a constant (no gradient flows through the assignment; gradients flow through the gathers).
    """
    cost = line_match_cost(pred_points, pred_logits, gt_points, gt_valid, w_bce, w_l1)
    match = hungarian(jax.lax.stop_gradient(cost))
    return gather_matched(pred_points, match), gather_matched(pred_logits, match), match
