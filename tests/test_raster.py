"""The lane rasterizer: pixel convention, gap-free lines, pose transform, jit/vmap, one compile."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpd_jax.map_tokenizer.raster import pixel_index, rasterize


def _line(a, b, n):
    t = np.linspace(0.0, 1.0, n)[:, None]
    return (np.asarray(a) + t * (np.asarray(b) - np.asarray(a))).astype(np.float32)


def test_horizontal_line_marks_exactly_its_pixels():
    pts = _line((-10.0, 5.1), (10.0, 5.1), 21)  # 1 m spacing, y = 5.1 m (left of the ego)
    r = np.asarray(rasterize(pts[None], np.ones((1, 21), bool), np.zeros(3, np.float32)))
    assert r.shape == (256, 256)
    col = int(np.floor((32 - 5.1) / 0.25))  # 107
    rows = np.arange(int(np.floor((32 - 10) / 0.25)), int(np.floor((32 + 10) / 0.25)) + 1)  # front (row 88) to back
    expected = np.zeros((256, 256), bool)
    expected[rows, col] = True
    np.testing.assert_array_equal(r > 0, expected)
    assert set(np.unique(r)) <= {0.0, 1.0}


def test_row0_is_front_and_col0_is_left():
    pts = np.array([[[31.9, 31.9], [-31.9, -31.9]]], np.float32)  # front-left and back-right corners
    r = np.asarray(rasterize(pts, np.array([[True, False]]), np.zeros(3, np.float32)))
    assert r[0, 0] == 1 and r.sum() == 1
    r = np.asarray(rasterize(pts, np.array([[False, True]]), np.zeros(3, np.float32)))
    assert r[255, 255] == 1 and r.sum() == 1


def test_diagonal_line_is_connected_and_close():
    a, b = np.array([-20.0, -13.0]), np.array([18.0, 25.0])
    pts = _line(a, b, 40)  # ~1.4 m spacing
    r = np.asarray(rasterize(pts[None], np.ones((1, 40), bool), np.zeros(3, np.float32)))
    rows, cols = np.nonzero(r)
    # every marked pixel centre lies within one pixel diagonal of the segment
    cx, cy = 32 - (rows + 0.5) * 0.25, 32 - (cols + 0.5) * 0.25
    d = b - a
    n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
    dist = np.abs((cx - a[0]) * n[0] + (cy - a[1]) * n[1])
    assert dist.max() <= 0.25 * np.sqrt(2) / 2 + 1e-5
    # 8-connected: consecutive samples along the line never skip a pixel
    fine = _line(a, b, 5000)
    fr, fc, inside = (np.asarray(x) for x in pixel_index(jnp.asarray(fine)))
    assert inside.all() and r[fr, fc].all()
    order = np.argsort(rows * 1000 + cols)
    steps = np.abs(np.diff(np.stack([rows[order], cols[order]]), axis=1))
    assert steps.max() <= 1


def test_invalid_points_and_far_points_draw_nothing():
    pts = _line((-5.0, 0.0), (5.0, 0.0), 11)
    valid = np.zeros((1, 11), bool)
    valid[0, 5] = True  # a single valid point draws one pixel
    r = np.asarray(rasterize(pts[None], valid, np.zeros(3, np.float32)))
    assert r.sum() == 1 and r[128, 128] == 1
    far = _line((100.0, 100.0), (120.0, 100.0), 21)
    r = np.asarray(rasterize(far[None], np.ones((1, 21), bool), np.zeros(3, np.float32)))
    assert r.sum() == 0


def test_pose_transform():
    # A line 10 m ahead of an ego at (50, -20) heading +90 deg (north): it runs east-west at y = -10.
    pose = np.array([50.0, -20.0, np.pi / 2], np.float32)
    pts = _line((40.0, -10.0), (60.0, -10.0), 21)
    r = np.asarray(rasterize(pts[None], np.ones((1, 21), bool), pose))
    ref = np.asarray(rasterize(_line((10.0, 10.0), (10.0, -10.0), 21)[None], np.ones((1, 21), bool),
                               np.zeros(3, np.float32)))
    assert ref.sum() > 0
    # Equal up to float rounding on pixel borders.
    assert np.sum((r > 0) != (ref > 0)) <= 4 and abs(int(r.sum()) - int(ref.sum())) <= 2
    assert r[int((32 - 10) / 0.25)].sum() >= 70  # the row 10 m ahead holds the line


def test_jit_vmap_and_batch_dims_agree():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-40, 40, (2, 3, 4, 12, 2)).astype(np.float32)
    valid = rng.uniform(size=(2, 3, 4, 12)) < 0.8
    pose = rng.uniform(-5, 5, (2, 3, 3)).astype(np.float32)
    f = chex.assert_max_traces(rasterize, n=1)
    batched = jax.jit(f)(pts, valid, pose)
    chex.assert_shape(batched, (2, 3, 256, 256))
    vm = jax.vmap(jax.vmap(rasterize))(pts, valid, pose)
    one = rasterize(pts[1, 2], valid[1, 2], pose[1, 2])
    np.testing.assert_array_equal(batched, vm)
    np.testing.assert_array_equal(batched[1, 2], one)


def test_from_ego_frame_inverts_to_ego_frame():
    from gpd_jax.map_tokenizer.raster import from_ego_frame, to_ego_frame

    rng = np.random.default_rng(0)
    pts = rng.normal(0, 30, (5, 7, 2)).astype(np.float32)
    pose = np.array([12.0, -40.0, 2.3], np.float32)
    back = np.asarray(from_ego_frame(to_ego_frame(pts, pose), pose))
    np.testing.assert_allclose(back, pts, rtol=1e-5, atol=1e-4 * np.abs(pts).max())
    # a point 10 m ahead of an ego heading north is 10 m north of it
    np.testing.assert_allclose(np.asarray(from_ego_frame(np.array([[10.0, 0.0]], np.float32),
                                                         np.array([1.0, 2.0, np.pi / 2], np.float32))),
                               [[1.0, 12.0]], atol=1e-5)


def test_directional_raster_holds_the_lane_heading():
    """Channel 0 is the binary raster; channels 1-2 are cos / sin of the heading in the ego frame where a line
    passes (zero elsewhere): a line driving +x ahead, one driving -x behind, and the heading turns with the ego."""
    ahead = _line((5.0, 3.0), (15.0, 3.0), 11)
    behind = _line((-5.0, -3.0), (-15.0, -3.0), 11)
    lines, valid = np.stack([ahead, behind]), np.ones((2, 11), bool)
    r = np.asarray(rasterize(lines, valid, np.zeros(3, np.float32), direction=True))
    binary = np.asarray(rasterize(lines, valid, np.zeros(3, np.float32)))
    assert r.shape == (256, 256, 3)
    np.testing.assert_array_equal(r[..., 0], binary)
    on = binary > 0
    np.testing.assert_array_equal(r[~on, 1:], 0.0)
    rows = np.nonzero(on)[0]
    front, back = on & (np.arange(256)[:, None] < 128), on & (np.arange(256)[:, None] > 128)
    assert front.sum() > 30 and back.sum() > 30 and len(rows) == on.sum()
    np.testing.assert_allclose(r[front, 1], 1.0, atol=1e-5)   # cos = +1: along +x
    np.testing.assert_allclose(r[back, 1], -1.0, atol=1e-5)   # cos = -1: along -x
    np.testing.assert_allclose(r[on, 2], 0.0, atol=1e-5)
    # the same lines seen by an ego turned +90 degrees: +x in the scene is -y (to the right) for it, sin = -1
    turned = np.asarray(rasterize(lines, valid, np.array([0.0, 0.0, np.pi / 2], np.float32), direction=True))
    on_t = turned[..., 0] > 0
    np.testing.assert_allclose(np.abs(turned[on_t, 2]), 1.0, atol=1e-5)
    assert (turned[on_t, 2] < 0).sum() == pytest.approx(front.sum(), abs=4)
