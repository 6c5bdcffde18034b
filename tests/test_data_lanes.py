"""SLEDGE vector-lane processing of hand-built polylines."""

import numpy as np

from gpd_jax.data import lanes


def _poly(lines, P=64):
    out = np.zeros((len(lines), P, 2), np.float32)
    ok = np.zeros((len(lines), P), bool)
    for i, l in enumerate(lines):
        out[i, :len(l)] = l
        ok[i, :len(l)] = True
    return out, ok


def test_crop_resample_and_order():
    x = np.linspace(-40, 40, 41)
    far = np.stack([x, np.full_like(x, 50.0)], -1)    # outside the window
    near = np.stack([x, np.full_like(x, 1.0)], -1)
    mid = np.stack([x, np.full_like(x, -10.0)], -1)
    p, v = _poly([far, mid, near])
    l, ok = lanes.vector_lanes(p, v, np.zeros(3))
    assert l.shape == (50, 20, 2) and ok.shape == (50,) and ok.sum() == 2
    # nearest first; cropped to +-32, 20 points evenly spaced with end points included
    np.testing.assert_allclose(l[0, :, 1], 1.0, atol=1e-5)
    np.testing.assert_allclose(l[0, :, 0], np.linspace(-32, 32, 20), atol=1e-4)
    np.testing.assert_allclose(l[1, :, 1], -10.0, atol=1e-5)
    assert (l[2:] == 0).all()


def test_pose_transform():
    x = np.linspace(-40, 40, 41)
    p, v = _poly([np.stack([x, np.zeros_like(x)], -1)])
    # ego at (10, 0) facing +y: the line (world y = 0) runs along the ego's lateral axis through it
    l, ok = lanes.vector_lanes(p, v, np.array([10.0, 0.0, np.pi / 2]))
    assert ok[0]
    np.testing.assert_allclose(l[0, :, 0], 0.0, atol=1e-5)
    np.testing.assert_allclose(l[0, [0, -1], 1], [32.0, -30.0], atol=1e-4)  # world x from -22 to 40


def test_split_runs_and_min_points():
    # a line that leaves and re-enters the window gives two runs; a 0.2 m stub (2 points at 0.25 m spacing) is dropped
    l1 = np.array([[-20.0, 0.0], [20.0, 0.0], [20.0, 40.0], [25.0, 40.0], [25.0, 0.0], [30.0, 0.0]])
    stub = np.array([[0.0, 5.0], [0.2, 5.0]])
    p, v = _poly([l1, stub])
    l, ok = lanes.vector_lanes(p, v, np.zeros(3))
    assert ok.sum() == 2
    ends = sorted([tuple(np.round(l[i, 0], 3)) for i in range(2)])
    assert ends[0][0] == -20.0  # the first run starts at the line's start


def test_keep_50_nearest_and_batch():
    lines = [np.array([[-5.0, y], [5.0, y]]) for y in np.linspace(-30, 30, 61)]
    p, v = _poly(lines, P=4)
    l, ok = lanes.vector_lanes(p, v, np.zeros(3))
    assert ok.sum() == 50
    assert np.abs(l[ok][:, 0, 1]).max() <= 25.0  # the 11 farthest (|y| > 25) are dropped
    poses = np.zeros((3, 3))
    poses[1, 0] = 100.0  # nothing visible
    L, OK = lanes.vector_lanes_frames(p, v, poses)
    assert L.shape == (3, 50, 20, 2) and OK[0].sum() == 50 and OK[1].sum() == 0
    np.testing.assert_array_equal(L[0], l)
    LB, OKB = lanes.vector_lanes_batch(p[None], v[None], poses[None])
    np.testing.assert_array_equal(LB[0], L)


def test_empty():
    p, v = _poly([np.zeros((0, 2))])
    l, ok = lanes.vector_lanes(p, v, np.zeros(3))
    assert not ok.any() and (l == 0).all()


def test_carried_lanes_persist_but_never_extend():
    x = np.linspace(-80, 80, 81)
    ahead = np.stack([x, np.full_like(x, 2.0)], -1)  # a long lane along the ego's path
    new = np.array([[40.0, -5.0], [60.0, -5.0]])  # only visible once the ego has moved 10 m or more
    p, v = _poly([ahead, new], P=96)
    poses = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [20.0, 0.0, 0.0]])
    l, ok = lanes.vector_lanes_carried(p, v, poses[0], poses)
    full, full_ok = lanes.vector_lanes_frames(p, v, poses)
    # at the source pose: the ordinary lanes
    assert ok[0].sum() == full_ok[0].sum() == 1
    np.testing.assert_allclose(l[0], full[0], atol=1e-4)
    # 10 m on: the lane seen at the start ends 22 m ahead (32 - 10) instead of 32; the new lane is absent
    assert full_ok[2].sum() == 2 and ok[2].sum() == 1
    np.testing.assert_allclose(l[1, 0, :, 1], 2.0, atol=1e-5)
    np.testing.assert_allclose(l[1, 0, [0, -1], 0], [-32.0, 22.0], atol=1e-4)
    np.testing.assert_allclose(l[2, 0, [0, -1], 0], [-32.0, 12.0], atol=1e-4)
    # nothing visible at the source pose: nothing carried
    l, ok = lanes.vector_lanes_carried(p, v, np.array([0.0, 500.0, 0.0]), poses)
    assert not ok.any() and (l == 0).all()


def test_store_chunks_of_one_run_are_one_line():
    """Rule 0: the data store splits a run longer than P points into chunks sharing their end points
    (`preprocess.clip_lanes`); they are one lane, not two (the cut shows in no raster). A full polyline that
    ends where two lines start (a fork) and a short line ending where another starts stay cut."""
    x = np.arange(-30.0, 31.0)  # 61 points at 1 m
    road = np.stack([x, np.full_like(x, 2.0)], -1)
    p, v = _poly([road[:33], road[32:]], P=33)  # chunk 1 full (33 points), chunk 2 starts at its last point
    l, ok = lanes.vector_lanes(p, v, np.zeros(3))
    assert ok.sum() == 1
    np.testing.assert_allclose(l[0, [0, -1], 0], [-30.0, 30.0], atol=1e-4)
    c, cv = lanes.vector_lanes_carried(p, v, np.zeros(3), np.zeros((1, 3)))
    assert cv[0].sum() == 1
    short = np.zeros((2, 40, 2), np.float32)  # the same two pieces in wider arrays: not chunks, kept apart
    sv = np.zeros((2, 40), bool)
    short[0, :33], short[1, :29] = road[:33], road[32:]
    sv[0, :33], sv[1, :29] = True, True
    assert lanes.vector_lanes(short, sv, np.zeros(3))[1].sum() == 2
    branch = np.stack([np.full(10, 2.0), 2.0 + np.arange(10.0)], -1)  # a fork at the chunk's end
    f = np.zeros((3, 33, 2), np.float32)
    fv = np.zeros((3, 33), bool)
    f[0], fv[0] = road[:33], True
    f[1, :29], fv[1, :29] = road[32:], True
    f[2, :10], fv[2, :10] = branch, True
    assert lanes.vector_lanes(f, fv, np.zeros(3))[1].sum() == 3
