"""The generated map moved with the ego (`MapTokenizer.warper`, the rollout's `map_warp`, `--gen-map warp`)."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def tok():
    from gpd_jax.map_tokenizer import load_tokenizer

    return load_tokenizer(os.path.join(ROOT, "checkpoints", "map_tokenizer"))


def _road(length=200.0, y=0.0, n=201):
    """Two parallel straight lanes along x (scene frame), 1 m point spacing: f32[2, n, 2], bool[2, n]."""
    x = np.linspace(-length / 2, length / 2, n, dtype=np.float32)
    lines = np.stack([np.stack([x, np.full_like(x, y + dy)], -1) for dy in (-1.75, 1.75)])
    return jnp.asarray(lines), jnp.ones(lines.shape[:2], bool)


def test_new_cells_are_those_the_previous_window_missed(tok):
    warp = jax.jit(tok.warper(tok.params))
    tokens = jnp.zeros(64, jnp.int32)
    at = lambda x, y, h: jnp.array([x, y, h], jnp.float32)
    _, new = warp(tokens, at(5.0, 3.0, 0.4), at(5.0, 3.0, 0.4))
    assert not np.asarray(new).any()  # standing still: everything was seen
    _, new = warp(tokens, at(0.0, 0.0, 0.0), at(10.0, 0.0, 0.0))  # 10 m ahead: the two front rows (8 m cells)
    np.testing.assert_array_equal(np.asarray(new).reshape(8, 8), np.repeat([[1], [1], [0], [0], [0], [0], [0], [0]],
                                                                          8, axis=1).astype(bool))
    # heading north, 10 m north: the same cells (the test is in each ego's frame)
    _, new2 = warp(tokens, at(3.0, 4.0, np.pi / 2), at(3.0, 14.0, np.pi / 2))
    np.testing.assert_array_equal(np.asarray(new2), np.asarray(new))
    _, new = warp(tokens, at(0.0, 0.0, 0.0), at(0.0, -10.0, 0.0))  # 10 m to the right: the two right columns
    assert np.asarray(new).reshape(8, 8)[:, 6:].all() and not np.asarray(new).reshape(8, 8)[:, :6].any()


def test_warped_map_is_the_previous_map_moved(tok):
    """The warp re-encodes the previous frame's decoded lanes (logit > 0), moved from the previous ego's frame
    into the scene frame (rotation by the previous heading, then its position), around the new ego: the same
    tokens as doing those steps by hand; and not the tokens of the unmoved map."""
    lines, valid = _road()
    p0, p1 = np.array([10.0, -3.0, 1.0], np.float32), np.array([14.0, 0.0, 1.3], np.float32)
    tokens = tok.encode_lanes(tok.params, lines, valid, jnp.asarray(p0))
    warped, new = jax.jit(tok.warper(tok.params))(tokens, jnp.asarray(p0), jnp.asarray(p1))

    pts, logits = (np.asarray(a) for a in tok.decode(tok.params, tokens))
    c, s = np.cos(p0[2]), np.sin(p0[2])
    scene = np.stack([c * pts[..., 0] - s * pts[..., 1] + p0[0], s * pts[..., 0] + c * pts[..., 1] + p0[1]], -1)
    keep = np.broadcast_to((logits > 0)[:, None], pts.shape[:-1])
    assert keep.any()
    by_hand = np.asarray(tok.encode_lanes(tok.params, jnp.asarray(scene), jnp.asarray(keep), jnp.asarray(p1)))
    assert (np.asarray(warped) == by_hand).mean() >= 62 / 64  # up to pixel-border rounding
    unmoved = np.asarray(tok.encode_lanes(tok.params, jnp.asarray(pts), jnp.asarray(keep), jnp.zeros(3)))
    assert (np.asarray(warped) != unmoved).mean() > 0.25
    assert np.asarray(new).any() and not np.asarray(new).all()
