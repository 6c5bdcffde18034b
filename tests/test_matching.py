import itertools

import chex
import jax
import jax.numpy as jnp
import numpy as np

from gpd_jax.metrics import gather_matched, hungarian, line_match_cost, match_lines


def _brute_force(cost):
    """Minimum total cost over all permutations (Q == G)."""
    q, g = cost.shape
    best = min(itertools.permutations(range(q), g), key=lambda p: sum(cost[p[j], j] for j in range(g)))
    return sum(cost[best[j], j] for j in range(g))


def test_cost_matches_hand_formula():
    pred = jnp.array([[[0.0, 0.0], [1.0, 0.0]], [[0.0, 1.0], [1.0, 1.0]]])  # Q=2, P=2
    logits = jnp.array([2.0, -1.0])
    gt = jnp.array([[[0.0, 0.5], [1.0, 0.0]], [[9.0, 9.0], [9.0, 9.0]]])
    valid = jnp.array([True, False])
    c = np.asarray(line_match_cost(pred, logits, gt, valid))
    sp = lambda x: np.log1p(np.exp(x))
    # q0-g0: BCE(2, 1) = softplus(-2); L1 = mean(0.5, 0) = 0.25
    np.testing.assert_allclose(c[0, 0], 5 * sp(-2.0) + 2 * 0.25, rtol=1e-6)
    # q1-g0: BCE(-1, 1) = softplus(1); L1 = mean(0.5, 1.0) = 0.75
    np.testing.assert_allclose(c[1, 0], 5 * sp(1.0) + 2 * 0.75, rtol=1e-6)
    # padded GT slot: BCE only, the far-away padding points do not count
    np.testing.assert_allclose(c[0, 1], 5 * sp(2.0), rtol=1e-6)
    np.testing.assert_allclose(c[1, 1], 5 * sp(-1.0), rtol=1e-6)


def test_hungarian_equals_brute_force_batched_under_jit():
    rng = np.random.default_rng(0)
    b, q, p = 6, 5, 3
    pred = rng.normal(size=(2, b // 2, q, p, 2)).astype(np.float32)
    logits = rng.normal(size=(2, b // 2, q)).astype(np.float32)
    gt = rng.normal(size=(2, b // 2, q, p, 2)).astype(np.float32)
    valid = rng.random((2, b // 2, q)) < 0.6

    @jax.jit
    def f(pred, logits, gt, valid):
        cost = line_match_cost(pred, logits, gt, valid)
        return cost, hungarian(cost)

    cost, match = f(pred, logits, gt, valid)
    chex.assert_shape(match, (2, b // 2, q))
    cost, match = np.asarray(cost), np.asarray(match)
    for i in range(2):
        for j in range(b // 2):
            assert sorted(match[i, j].tolist()) == list(range(q))  # a permutation
            total = cost[i, j][match[i, j], np.arange(q)].sum()
            np.testing.assert_allclose(total, _brute_force(cost[i, j]), rtol=1e-5)


def test_hungarian_under_vmap_and_rectangular():
    rng = np.random.default_rng(1)
    cost = rng.random((3, 4, 4)).astype(np.float32)
    m_vmap = jax.jit(jax.vmap(hungarian))(cost)
    np.testing.assert_array_equal(m_vmap, hungarian(cost))
    # fewer queries than GT slots: one GT slot is left unmatched (-1)
    m = np.asarray(hungarian(jnp.asarray(rng.random((2, 3)))))
    assert (m == -1).sum() == 1 and sorted(m[m >= 0].tolist()) == [0, 1]


def test_match_lines_recovers_a_permutation():
    rng = np.random.default_rng(2)
    gt = rng.normal(size=(4, 20, 2)).astype(np.float32) * 10
    perm = np.array([2, 0, 3, 1])
    pred = gt[perm] + 0.01
    logits = jnp.full((4,), 3.0)
    pts, lg, match = match_lines(pred, logits, gt, jnp.ones(4, bool))
    # GT slot g is matched to the query holding it: perm[match[g]] == g
    np.testing.assert_array_equal(perm[np.asarray(match)], np.arange(4))
    np.testing.assert_allclose(pts, gt + 0.01, atol=1e-5)
    chex.assert_shape(gather_matched(jnp.arange(4.0), match), (4,))


def test_matching_inside_a_differentiated_loss():
    rng = np.random.default_rng(3)
    gt = jnp.asarray(rng.normal(size=(2, 3, 4, 2)), jnp.float32)
    valid = jnp.array([[True, False, True], [True, True, False]])

    def loss(pred):
        pts, _, _ = match_lines(pred, jnp.zeros(pred.shape[:-2]), gt, valid)
        return jnp.sum(jnp.abs(pts - gt) * valid[..., None, None])

    g = jax.jit(jax.grad(loss))(gt + 0.1)
    assert g.shape == gt.shape and np.all(np.isfinite(g))
    assert float(jnp.sum(jnp.abs(g))) > 0  # gradients flow through the gathers
