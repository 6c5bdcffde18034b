"""The cut-invariant map score beside the paper's F1, the raster-level reconstruction and the GT re-cut probe."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpd_jax.data.lanes import vector_lanes
from gpd_jax.map_tokenizer.evaluation import (decoded_raster, raster_sums, recut_polylines, reduce_raster)
from gpd_jax.map_tokenizer.raster import rasterize
from gpd_jax.metrics.map import (cutfree_frame_sums, map_metric_sums, map_metrics, point_to_segments_distance,
                                 reduce_cutfree)

Q, P = 50, 20


def _arc(s0, s1, n=P, radius=40.0, offset=0.0):
    """Points of a circular road (radius m) from arc length s0 to s1, moved `offset` m to the left."""
    s = np.linspace(s0, s1, n) / radius
    r = radius - offset
    return np.stack([r * np.sin(s), radius - r * np.cos(s)], -1).astype(np.float32)


def _frame(lines):
    pts = np.zeros((Q, P, 2), np.float32)
    ok = np.zeros((Q,), bool)
    for i, ln in enumerate(lines):
        pts[i], ok[i] = ln, True
    return pts, ok, np.where(ok, 5.0, -5.0).astype(np.float32)


def test_same_road_cut_differently_scores_one_and_paper_f1_does_not():
    gt, gv, _ = _frame([_arc(0, 25), _arc(25, 60)])  # the road as two lines
    pred, _, logits = _frame([_arc(0, 60)])  # the same road as one line
    r = map_metrics(pred, logits, gt, gv)
    assert r["map_f1_cutfree"] == pytest.approx(1.0, abs=1e-4)
    assert r["map_precision_cutfree"] == pytest.approx(1.0, abs=1e-4)
    assert r["map_chamfer_cutfree"] < 0.05  # chord error of 20 points on a 40 m radius only
    assert r["map_f1"] < 0.1  # the paper's F1 compares points by index: the cut alone ruins it
    # the line reversed: the same road again
    rev, _, _ = _frame([_arc(0, 60)[::-1]])
    r = map_metrics(rev, logits, gt, gv)
    assert r["map_f1_cutfree"] == pytest.approx(1.0, abs=1e-4)
    # ... unless the direction counts: the reversed road is found but runs the wrong way
    assert r["map_f1_cutfree_directed"] == 0.0 and r["map_f1"] == 0.0
    assert map_metrics(pred, logits, gt, gv)["map_f1_cutfree_directed"] == pytest.approx(1.0, abs=1e-4)


def test_directed_cutfree_counts_only_the_length_running_the_same_way():
    # two lanes 3.5 m apart: the decoded right lane is right, the left one reversed (a binary raster's guess)
    right, left = _arc(0, 60), _arc(0, 60, offset=3.5)
    gt, gv, _ = _frame([right, left])
    pred, _, logits = _frame([right, left[::-1]])
    r = map_metrics(pred, logits, gt, gv)
    assert r["map_f1_cutfree"] == pytest.approx(1.0, abs=1e-4)
    share = 40.0 / (40.0 + 36.5)  # the right lane's share of the length (the left one is the inner arc)
    assert r["map_precision_cutfree_directed"] == pytest.approx(share, abs=0.01)
    assert r["map_recall_cutfree_directed"] == pytest.approx(share, abs=0.01)
    # a reversed line right beside a same-way one still finds it: the nearest same-way segment within 1.5 m counts
    gt1, gv1, _ = _frame([right])
    pred2, _, logits2 = _frame([right[::-1], _arc(0, 60, offset=1.0)])
    r = map_metrics(pred2, logits2, gt1, gv1)
    assert r["map_recall_cutfree_directed"] == pytest.approx(1.0, abs=1e-4)
    assert r["map_precision_cutfree_directed"] == pytest.approx(0.5, abs=0.02)


def test_shifted_and_partial_roads_drop():
    gt, gv, _ = _frame([_arc(0, 60)])
    far, _, logits = _frame([_arc(0, 60, offset=3.0)])  # 3 m beside the road
    r = map_metrics(far, logits, gt, gv)
    assert r["map_f1_cutfree"] == 0.0 and r["map_chamfer_cutfree"] == pytest.approx(3.0, rel=0.02)
    near, _, _ = _frame([_arc(0, 60, offset=1.0)])  # 1 m beside: within the 1.5 m threshold
    r = map_metrics(near, logits, gt, gv)
    assert r["map_f1_cutfree"] == pytest.approx(1.0, abs=1e-4)
    assert r["map_chamfer_within_cutfree"] == pytest.approx(1.0, rel=0.02)
    half, _, _ = _frame([_arc(0, 30)])  # half of the road, exactly on it
    r = map_metrics(half, logits, gt, gv)
    assert r["map_precision_cutfree"] == pytest.approx(1.0, abs=1e-4)
    assert r["map_recall_cutfree"] == pytest.approx(0.5, abs=0.03)
    assert r["map_f1_cutfree"] == pytest.approx(2 * 0.5 / 1.5, abs=0.03)


def test_paper_keys_unchanged_and_batches_add_up():
    rng = np.random.default_rng(3)
    b = 5
    gt = rng.normal(size=(b, Q, P, 2)).astype(np.float32) * 10
    gv = rng.random((b, Q)) < 0.4
    pred = gt + rng.normal(size=gt.shape).astype(np.float32)
    logits = rng.normal(size=(b, Q)).astype(np.float32) * 3
    fn = jax.jit(map_metric_sums, static_argnames=("cutfree",))
    with_cf = jax.device_get(fn(pred, logits, gt, gv))
    without = jax.device_get(fn(pred, logits, gt, gv, cutfree=False))
    assert set(without) < set(with_cf) and not any(k.startswith("cf_") for k in without)
    for k in without:
        np.testing.assert_array_equal(with_cf[k], without[k], err_msg=k)
    parts = [jax.device_get(fn(pred[i:i + 1], logits[i:i + 1], gt[i:i + 1], gv[i:i + 1]))
             for i in range(b)]
    summed = {k: sum(p[k] for p in parts) for k in parts[0]}
    for k, v in reduce_cutfree(with_cf).items():
        assert reduce_cutfree(summed)[k] == pytest.approx(v, rel=1e-4), k


def test_cutfree_compiles_once_and_empty_frames():
    fn = jax.jit(chex.assert_max_traces(lambda *a: cutfree_frame_sums(*a), n=1))
    gt, gv, _ = _frame([_arc(0, 60)])
    pred, pv, _ = _frame([_arc(0, 60, offset=0.5)])
    s = fn(jnp.asarray(pred), jnp.asarray(pv), jnp.asarray(gt), jnp.asarray(gv))
    assert float(s["cf_pred_len"]) == pytest.approx(60.0 * 39.5 / 40.0, rel=0.005)  # the inner arc
    s = fn(jnp.asarray(pred), jnp.zeros(Q, bool), jnp.asarray(gt), jnp.asarray(gv))  # nothing predicted
    r = reduce_cutfree({k: np.asarray(v)[None] for k, v in s.items()})
    assert r["map_recall_cutfree"] == 0.0 and r["map_f1_cutfree"] == 0.0 and np.isnan(r["map_chamfer_cutfree"])


def test_point_to_segments_distance():
    a = jnp.array([[0.0, 0.0], [10.0, 0.0]])
    b = jnp.array([[10.0, 0.0], [10.0, 10.0]])
    p = jnp.array([[5.0, 2.0], [-3.0, 4.0], [12.0, 5.0]])
    d = point_to_segments_distance(p, a, b, jnp.array([True, True]))
    np.testing.assert_allclose(np.asarray(d), [2.0, 5.0, 2.0], rtol=1e-6)
    d = point_to_segments_distance(p, a, b, jnp.array([False, True]))
    np.testing.assert_allclose(np.asarray(d), [5.0, 13.0, 2.0], rtol=1e-6)


def _sample_road():
    """Scene-frame polylines at 1 m spacing: a straight road and a curve branching off it."""
    lines = np.zeros((4, 128, 2), np.float32)
    ok = np.zeros((4, 128), bool)
    x = np.arange(-40.0, 60.0, 1.0)
    lines[0, :len(x)] = np.stack([x, np.full_like(x, -1.6)], -1)
    ok[0, :len(x)] = True
    lines[1, :len(x)] = np.stack([x[::-1], np.full_like(x, 1.6)], -1)
    ok[1, :len(x)] = True
    c = _arc(0, 50, n=51, radius=30.0) + np.array([5.0, -1.6], np.float32)
    lines[2, :51] = c
    ok[2, :51] = True
    return lines, ok


def test_recut_keeps_geometry_and_changes_the_cut():
    lines, ok = _sample_road()
    pose = np.array([3.0, 0.5, 0.2], np.float32)
    gt, gv = vector_lanes(lines, ok, pose)
    for mode in ("split_mid", "join_ends"):
        rl, rok = recut_polylines(lines, ok, mode)
        lz, lok = vector_lanes(rl, rok, pose)
        r = map_metrics(lz, np.where(lok, 10.0, -10.0).astype(np.float32), gt, gv, count_exact_hits=True)
        assert r["map_f1_cutfree"] == pytest.approx(1.0, abs=1e-3), mode
        if mode == "split_mid":
            assert lok.sum() > gv.sum() and r["map_f1"] < 0.9  # more, shorter lines: the paper's F1 drops
    # join_ends: two lines meeting one-to-one become one
    a = np.zeros((2, 128, 2), np.float32)
    v = np.zeros((2, 128), bool)
    a[0, :10] = np.stack([np.arange(10.0), np.zeros(10)], -1)
    a[1, :10] = np.stack([np.arange(9.0, 19.0), np.zeros(10)], -1)
    v[:, :10] = True
    j, jv = recut_polylines(a, v, "join_ends")
    assert jv.sum(-1).tolist() == [19]
    with pytest.raises(ValueError, match="recut mode"):
        recut_polylines(a, v, "nope")
    # no_turnarounds: a U-turn arc leaving the end of the first line is dropped, then the lines join
    b = np.zeros((3, 128, 2), np.float32)
    w = np.zeros((3, 128), bool)
    b[:2], w[:2] = a, v
    t = np.linspace(0.0, np.pi, 8)
    b[2, :8] = np.stack([9.0 + 1.6 * np.sin(t), 1.6 - 1.6 * np.cos(t)], -1)  # starts at (9, 0), ends heading back
    w[2, :8] = True
    j, jv = recut_polylines(b, w, "join_ends")
    assert sorted(jv.sum(-1).tolist()) == [8, 10, 10]  # three lines meet at (9, 0): nothing is one-to-one
    j, jv = recut_polylines(b, w, "no_turnarounds")
    assert jv.sum(-1).tolist() == [19]


def test_raster_reconstruction_frames_agree():
    """The GT vector lanes (ego frame) drawn by `decoded_raster` fall on the input raster of the same road."""
    class R:
        size, pixel_size, max_segment_length = 256, 0.25, 2.0

    class C:
        raster = R

    lines, ok = _sample_road()
    pose = np.array([3.0, 0.5, 0.2], np.float32)
    target = rasterize(lines[None], ok[None], pose[None])
    gt, gv = vector_lanes(lines, ok, pose)
    dec = decoded_raster(C, jnp.asarray(gt)[None], jnp.where(jnp.asarray(gv), 5.0, -5.0)[None])
    r = reduce_raster(jax.device_get(raster_sums(dec, target)))
    assert r["raster_f1"] > 0.97 and r["raster_iou"] > 0.5
    moved = decoded_raster(C, jnp.asarray(gt + np.array([0.0, 3.0], np.float32))[None],
                           jnp.where(jnp.asarray(gv), 5.0, -5.0)[None])
    r2 = reduce_raster(jax.device_get(raster_sums(moved, target)))
    assert r2["raster_iou"] < 0.2 and r2["raster_f1"] < r["raster_f1"]


@pytest.mark.parametrize("n_pred, n_gt", [(23, 17), (50, 50), (5, 0), (0, 9)])
def test_tiled_nearest_segment_search_equals_the_full_one(n_pred, n_gt):
    """The cut-free score and the set Chamfer visit only the tiles of valid lines (`_tiled_nearest`): on every
    point of a valid line they give the distances of the search over every pair (to float32 rounding: the
    compiler may arrange a tile's arithmetic differently), valid lines in any slots."""
    from gpd_jax.metrics.map import _nearest_by_line, _point_to_segments

    rng = np.random.default_rng(n_pred + 100 * n_gt)
    lp, ls, n, m = 50, 50, 6, 3
    p = rng.normal(size=(lp, n, 2)).astype(np.float32) * 20
    pdir = rng.normal(size=(lp, n, 2)).astype(np.float32)
    a = rng.normal(size=(ls, m, 2)).astype(np.float32) * 20
    b = a + rng.normal(size=(ls, m, 2)).astype(np.float32) * 3
    b[0, 0] = a[0, 0]  # a zero-length segment
    pv = np.zeros(lp, bool)
    pv[rng.permutation(lp)[:n_pred]] = True
    sv = np.zeros(ls, bool)
    sv[rng.permutation(ls)[:n_gt]] = True
    d, dd = jax.jit(_nearest_by_line)(p, pdir, pv, a, b, sv)
    ref = jax.jit(_point_to_segments)(p.reshape(-1, 2), a.reshape(-1, 2), b.reshape(-1, 2), np.repeat(sv, m),
                                      pdir.reshape(-1, 2))
    rd, rdd = (np.asarray(x).reshape(lp, n) for x in ref)
    np.testing.assert_allclose(np.asarray(d)[pv], rd[pv], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(np.asarray(dd)[pv], rdd[pv], rtol=1e-6, atol=1e-6)
    assert (np.asarray(d)[~pv] == 0).all() and (np.asarray(dd)[~pv] == 0).all()
    # the set Chamfer between the points of valid lines, the same way
    from gpd_jax.metrics.map import _set_chamfer_by_line, set_chamfer

    c, ok = jax.jit(_set_chamfer_by_line)(p, pv, a, sv)
    rc, rok = jax.jit(set_chamfer)(p.reshape(-1, 2), np.repeat(pv, n), a.reshape(-1, 2), np.repeat(sv, m))
    assert bool(ok) == bool(rok) == (n_pred > 0 and n_gt > 0)
    np.testing.assert_allclose(float(c), float(rc), rtol=1e-6)
