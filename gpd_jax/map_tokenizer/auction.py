"""A pure-JAX assignment solver (Bertsekas' auction algorithm, Jacobi bidding with epsilon scaling).

An alternative to `gpd_jax.metrics.matching.hungarian` (scipy on the host through a callback) that stays on the
device and needs no host round trip. It is epsilon-optimal: the total cost of its assignment is within
`n * eps_final` of the optimum (exactly optimal when costs are integers and `eps_final < 1/n`), so ties and
near-ties can be broken differently from scipy. `python -m gpd_jax.map_tokenizer bench` measures both; the
training code uses the scipy solver (exact, and faster on CPU for 50 x 50 problems — see the bench).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _auction_one(cost: jax.Array, eps_final: float, num_phases: int, scale: float, max_iters: int) -> jax.Array:
    n = cost.shape[-1]
    benefit = -cost
    ar = jnp.arange(n)

    def phase(prices, eps):
        def cond(s):
            _, assigned, _, it = s
            return jnp.any(assigned < 0) & (it < max_iters)

        def body(s):
            owner, assigned, prices, it = s
            v = benefit - prices[None, :]  # [persons (queries), objects (GT)]
            j1 = jnp.argmax(v, axis=1)
            v1 = jnp.max(v, axis=1)
            v2 = jnp.max(jnp.where(ar[None, :] == j1[:, None], -jnp.inf, v), axis=1)
            bid = prices[j1] + v1 - v2 + eps
            active = assigned < 0
            bids = jnp.where(active[:, None] & (ar[None, :] == j1[:, None]), bid[:, None], -jnp.inf)
            best = jnp.max(bids, axis=0)
            winner = jnp.argmax(bids, axis=0)
            has = best > -jnp.inf
            assigned = assigned.at[jnp.where(has & (owner >= 0), owner, n)].set(-1, mode="drop")
            assigned = assigned.at[jnp.where(has, winner, n)].set(ar, mode="drop")
            owner = jnp.where(has, winner, owner)
            prices = jnp.where(has, best, prices)
            return owner, assigned, prices, it + 1

        init = (jnp.full((n,), -1, jnp.int32), jnp.full((n,), -1, jnp.int32), prices, jnp.zeros((), jnp.int32))
        owner, _, prices, _ = jax.lax.while_loop(cond, body, init)
        return prices, owner

    eps = eps_final * scale ** jnp.arange(num_phases - 1, -1, -1, dtype=jnp.float32)
    _, owners = jax.lax.scan(phase, jnp.zeros((n,), cost.dtype), eps)
    return owners[-1].astype(jnp.int32)


def auction(cost: jax.Array, eps_final: float = 1e-3, num_phases: int = 6, scale: float = 5.0,
            max_iters: int = 20_000) -> jax.Array:
    """Minimum-cost assignment of a square cost matrix, same output convention as `hungarian`.

    Args:
      cost: f32[..., N, N], rows = queries, columns = GT slots.
      eps_final: final epsilon (the result is within N * eps_final of the optimal total cost).
      num_phases: epsilon-scaling phases; epsilon starts at `eps_final * scale ** (num_phases - 1)`.
      scale: epsilon reduction factor between phases.
      max_iters: bidding rounds per phase at most (a guard; not reached for finite costs).

    Returns:
      i32[..., N] for each GT slot the index of its query.
    """
    if cost.shape[-1] != cost.shape[-2]:
        raise ValueError(f"auction needs a square cost matrix, got {cost.shape[-2:]}")
    flat = cost.reshape((-1,) + cost.shape[-2:]).astype(jnp.float32)
    out = jax.vmap(lambda c: _auction_one(c, eps_final, num_phases, scale, max_iters))(flat)
    return out.reshape(cost.shape[:-1])
