import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpd_jax.metrics import (accumulate, agent_metric_sums, agent_metrics, box_corners, box_overlap_pairwise,
                             lateral_distances, map_metric_sums, map_metrics, reduce_agent_metrics,
                             reduce_map_metrics, set_chamfer)
from gpd_jax.metrics.map import END_LABELS, LENGTH_EDGES_M, length_labels

SIZE = np.array([4.5, 1.9], np.float32)


# ------------------------------------------------------------------------------------------------ agents
def _offset_scene():
    """4 future frames, 4 slots far apart (no collisions), predictions offset by exactly 1 m in x.

    slot 0 ego valid 0..3; agent 1 valid 0..3; agent 2 valid 0..1; agent 3 valid 2..3 (appears later).
    """
    f, a = 4, 4
    gt = np.zeros((f, a, 2), np.float32)
    gt[:, :, 1] = np.arange(a) * 10.0
    gt[:, :, 0] = np.arange(f)[:, None] * 1.0
    valid = np.ones((f, a), bool)
    valid[2:, 2] = False
    valid[:2, 3] = False
    pred = gt + np.array([1.0, 0.0], np.float32)
    head = np.zeros((f, a), np.float32)
    size = np.broadcast_to(SIZE, (a, 2))
    return pred, head, gt, valid, size


def test_constant_offset_paper_and_corrected():
    pred, head, gt, valid, size = _offset_scene()
    kw = dict(horizons=(2, 4))
    p = agent_metrics(pred, head, gt, valid, size, variant="paper", **kw)
    c = agent_metrics(pred, head, gt, valid, size, variant="corrected", **kw)
    assert set(p) == {"0.2s", "0.4s"}
    assert set(p["0.2s"]) == {f"{g}_{n}" for g in ("ego", "agent")
                              for n in ("ade", "fde", "collision", "collision_frames")}
    # ego: always valid, error 1 everywhere
    for r in (p, c):
        for h in r:
            assert r[h]["ego_ade"] == pytest.approx(1.0) and r[h]["ego_fde"] == pytest.approx(1.0)
            assert r[h]["ego_collision"] == 0.0 and r[h]["agent_collision"] == 0.0
    # paper: N_exist = 3 agents (valid somewhere in the 4 future frames).
    # ADE@2: errors at t<2: agents 1, 2 -> 4 m; / (2 steps * 3) = 2/3. ADE@4: 4 + 2 + 2 = 8 m / (4 * 3) = 2/3.
    assert p["0.2s"]["agent_ade"] == pytest.approx(2 / 3)
    assert p["0.4s"]["agent_ade"] == pytest.approx(2 / 3)
    # FDE@2: agent 3 has no valid frame yet and adds 0 but counts in N_exist: (1 + 1 + 0) / 3.
    assert p["0.2s"]["agent_fde"] == pytest.approx(2 / 3)
    assert p["0.4s"]["agent_fde"] == pytest.approx(1.0)
    # corrected: mean over valid (agent, t) pairs and over agents with a valid frame -> exactly the offset
    for h in c:
        assert c[h]["agent_ade"] == pytest.approx(1.0) and c[h]["agent_fde"] == pytest.approx(1.0)


def test_growing_error_ade_fde():
    pred, head, gt, valid, size = _offset_scene()
    pred = gt.copy()
    pred[:, 0, 0] += np.arange(1, 5)  # ego error 1, 2, 3, 4
    r = agent_metrics(pred, head, gt, valid, size, horizons=(2, 4), variant="paper")
    assert r["0.4s"]["ego_ade"] == pytest.approx(2.5) and r["0.4s"]["ego_fde"] == pytest.approx(4.0)
    assert r["0.2s"]["ego_ade"] == pytest.approx(1.5) and r["0.2s"]["ego_fde"] == pytest.approx(2.0)
    assert r["0.4s"]["agent_ade"] == 0.0


def test_num_history_slicing_and_default_horizons():
    rng = np.random.default_rng(0)
    t, a = 101, 5
    gt = rng.normal(size=(t, a, 2)).astype(np.float32) * 20
    pred = gt + 0.5
    valid = np.ones((t, a), bool)
    head = np.zeros((t, a), np.float32)
    pred[:21] += 100.0  # history errors must be ignored
    r = agent_metrics(pred, head, gt, valid, np.broadcast_to(SIZE, (a, 2)), num_history=21, variant="corrected")
    assert set(r) == {"3s", "5s", "8s"}
    assert r["8s"]["agent_ade"] == pytest.approx(np.sqrt(0.5), rel=1e-5)


def test_box_overlap_rotated_cases():
    # Two thin parallel boxes at 45 deg, 1.41 m apart sideways: axis-aligned bounds overlap, the boxes do not.
    q = np.pi / 4
    xy = jnp.array([[0.0, 0.0], [1.0, -1.0]])
    ov = box_overlap_pairwise(xy, jnp.array([q, q]), jnp.array([[4.0, 0.5], [4.0, 0.5]]))
    assert not bool(ov[0, 1])
    c = np.asarray(box_corners(xy, jnp.array([q, q]), jnp.array([[4.0, 0.5], [4.0, 0.5]])))
    lo, hi = c.min(1), c.max(1)
    assert np.all(lo[0] < hi[1]) and np.all(lo[1] < hi[0])  # an AABB test would report a collision
    # A 2x2 box rotated 45 deg whose corner pokes into a 4x2 box: the unrotated boxes would not touch.
    size = jnp.array([[4.0, 2.0], [2.0, 2.0]])
    ov = box_overlap_pairwise(jnp.array([[0.0, 0.0], [3.3, 0.0]]), jnp.array([0.0, q]), size)
    assert bool(ov[0, 1]) and bool(ov[1, 0])
    assert not bool(box_overlap_pairwise(jnp.array([[0.0, 0.0], [3.3, 0.0]]), jnp.array([0.0, 0.0]), size)[0, 1])
    assert not bool(box_overlap_pairwise(jnp.array([[0.0, 0.0], [3.5, 0.0]]), jnp.array([0.0, q]), size)[0, 1])
    # plain overlap / separation, diagonal False, masking
    xy3 = jnp.array([[0.0, 0.0], [3.0, 0.5], [0.0, 5.0]])
    ov = np.asarray(box_overlap_pairwise(xy3, jnp.zeros(3), jnp.asarray(SIZE)))
    np.testing.assert_array_equal(ov, [[False, True, False], [True, False, False], [False, False, False]])
    ov = box_overlap_pairwise(xy3, jnp.zeros(3), jnp.asarray(SIZE), valid=jnp.array([True, False, True]))
    assert not np.any(np.asarray(ov))
    # corners: front-left of a heading-0 box
    np.testing.assert_allclose(box_corners(jnp.zeros(2), jnp.array(0.0), jnp.array([4.0, 2.0]))[0], [2.0, 1.0])


def test_collision_rates_paper_and_corrected():
    pred, head, gt, valid, size = _offset_scene()
    pred = gt.copy()
    # at future frame 1 agent 1 (valid) is put on top of the ego: both collide in that frame
    pred[1, 1] = pred[1, 0] + np.array([1.0, 0.0])
    r = agent_metrics(pred, head, gt, valid, size, horizons=(1, 2, 4), variant="paper")
    # the paper's rate: agents with >= 1 collision / N_exist (ego: 1 per scenario; agents: 3 valid in the future)
    assert r["0.1s"]["ego_collision"] == 0.0 and r["0.1s"]["agent_collision"] == 0.0
    for h in ("0.2s", "0.4s"):  # the share does not shrink as the horizon grows
        assert r[h]["ego_collision"] == pytest.approx(100.0)
        assert r[h]["agent_collision"] == pytest.approx(100 / 3)
    # the official per-frame rate: 1 colliding step / (2 steps * 1 scenario) = 50 %; agents: 1 / (2 * 3)
    assert r["0.2s"]["ego_collision_frames"] == pytest.approx(50.0)
    assert r["0.2s"]["agent_collision_frames"] == pytest.approx(100 / 6)
    assert r["0.4s"]["ego_collision_frames"] == pytest.approx(25.0)
    assert r["0.4s"]["agent_collision_frames"] == pytest.approx(100 / 12)
    c = agent_metrics(pred, head, gt, valid, size, horizons=(2, 4), variant="corrected")
    # corrected @2: agents present in the first 2 frames are 1 and 2 (agent 3 appears at frame 2): 1 of 2 collides
    assert c["0.2s"]["agent_collision"] == pytest.approx(50.0)
    # corrected @4: all three agents present; one collides. Per frame: 4 + 2 + 2 = 8 present pairs, one colliding
    assert c["0.4s"]["ego_collision"] == pytest.approx(100.0)
    assert c["0.4s"]["agent_collision"] == pytest.approx(100 / 3)
    assert c["0.4s"]["ego_collision_frames"] == pytest.approx(25.0)
    assert c["0.4s"]["agent_collision_frames"] == pytest.approx(100 / 8)
    # a second colliding frame of the same agent raises the per-frame rate, not the share of agents
    pred[2, 1] = pred[2, 0] + np.array([1.0, 0.0])
    r2 = agent_metrics(pred, head, gt, valid, size, horizons=(4,), variant="paper")
    assert r2["0.4s"]["agent_collision"] == pytest.approx(100 / 3)
    assert r2["0.4s"]["agent_collision_frames"] == pytest.approx(200 / 12)
    # an invalid agent is no obstacle in either variant
    valid2 = valid.copy()
    valid2[1:3, 1] = False
    for v in ("paper", "corrected"):
        for k in ("ego_collision", "ego_collision_frames"):
            assert agent_metrics(pred, head, gt, valid2, size, horizons=(4,), variant=v)["0.4s"][k] == 0


def test_paper_box_vs_own_box():
    # two agents 4.3 m apart nose to tail: fixed 4.084 m boxes do not touch, their own 5 m boxes do
    f, a = 1, 3
    gt = np.array([[[0.0, 50.0], [0.0, 0.0], [4.3, 0.0]]], np.float32)
    valid = np.ones((f, a), bool)
    size = np.array([[4.5, 1.9], [5.0, 2.0], [5.0, 2.0]], np.float32)
    head = np.zeros((f, a), np.float32)
    assert agent_metrics(gt, head, gt, valid, size, horizons=(1,), variant="paper")["0.1s"]["agent_collision"] == 0
    c = agent_metrics(gt, head, gt, valid, size, horizons=(1,), variant="corrected")
    assert c["0.1s"]["agent_collision"] == pytest.approx(100.0)


@pytest.mark.parametrize("variant", ["paper", "corrected"])
def test_agent_batch_aggregation_exact_and_jit(variant):
    rng = np.random.default_rng(3)
    b, t, a = 6, 12, 5
    gt = rng.normal(size=(b, t, a, 2)).astype(np.float32) * 4
    pred = gt + rng.normal(size=gt.shape).astype(np.float32)
    head = rng.uniform(-3, 3, size=(b, t, a)).astype(np.float32)
    valid = rng.random((b, t, a)) < 0.7
    size = np.broadcast_to(SIZE, (b, a, 2))
    chex.clear_trace_counter()

    @jax.jit
    @chex.assert_max_traces(n=1)
    def fn(*args):  # one compile serves both batch halves (same shapes)
        return agent_metric_sums(*args, num_history=2, horizons=(4, 10), variant=variant)

    whole = agent_metrics(pred, head, gt, valid, size, num_history=2, horizons=(4, 10), variant=variant)
    acc = None
    for s in (slice(0, 3), slice(3, 6)):
        acc = accumulate(acc, fn(pred[s], head[s], gt[s], valid[s], size[s]))
    split = reduce_agent_metrics(acc)
    for h in whole:
        for k in whole[h]:
            np.testing.assert_allclose(split[h][k], whole[h][k], rtol=1e-5, err_msg=f"{h} {k}")
    # vmap over scenarios then summing gives the same sums
    vm = jax.vmap(functools.partial(agent_metric_sums, num_history=2, horizons=(4, 10), variant=variant))
    summed = jax.tree.map(lambda x: jnp.sum(x), vm(pred, head, gt, valid, size))
    for h in whole:
        for k, v in reduce_agent_metrics(summed)[h].items():
            np.testing.assert_allclose(v, whole[h][k], rtol=1e-5)


# ------------------------------------------------------------------------------------------------ map
def _straight(y, x0=0.0, n=20):
    return np.stack([np.arange(n, dtype=np.float32) + x0, np.full(n, y, np.float32)], -1)


def _map_case():
    """50 GT slots, lines in slots 0 and 1; 50 queries, three predicted to exist."""
    gt = np.zeros((50, 20, 2), np.float32)
    gt_valid = np.zeros(50, bool)
    gt[0], gt[1] = _straight(0.0), _straight(10.0)
    gt_valid[:2] = True
    pred = np.zeros((50, 20, 2), np.float32)
    logits = np.full(50, -5.0, np.float32)
    return gt, gt_valid, pred, logits


def test_map_f1_identical_lines():
    gt, gv, pred, logits = _map_case()
    pred[7], pred[3] = gt[0], gt[1]  # query order differs from GT slots: the matching sorts it out
    logits[[7, 3]] = 5.0
    r = map_metrics(pred, logits, gt, gv, count_exact_hits=True)
    assert r["map_f1"] == pytest.approx(1.0)
    assert r["map_lateral"] == pytest.approx(0.0) and r["map_chamfer_corrected"] == pytest.approx(0.0)
    # the paper's 0 < d quirk: exact hits are not true positives
    assert map_metrics(pred, logits, gt, gv)["map_f1"] == 0.0
    # a tiny offset is a hit either way
    pred[[7, 3], :, 1] += 0.01
    assert map_metrics(pred, logits, gt, gv)["map_f1"] == pytest.approx(1.0)


def test_map_f1_shifted_lines_hand_computed():
    gt, gv, pred, logits = _map_case()
    pred[0] = gt[0] + np.array([0.5, 1.0])  # d = 1.118 <= 1.5: 20 TPs, lateral 1.0 (the x shift is along the line)
    pred[1] = gt[1] + np.array([0.0, 2.0])  # d = 2 > 1.5: no TP
    pred[2] = _straight(-20.0)  # an extra predicted line (matched to padding): 20 FPs
    logits[:3] = 5.0
    r = map_metrics(pred, logits, gt, gv)
    # TP = 20, FP = 3*20 - 20 = 40, FN = 2*20 - 20 = 20; P = 1/3, R = 1/2, F1 = 0.4
    assert r["map_precision"] == pytest.approx(1 / 3)
    assert r["map_recall"] == pytest.approx(0.5)
    assert r["map_f1"] == pytest.approx(0.4)
    assert r["map_lateral"] == pytest.approx(1.0, abs=1e-5)
    assert map_metrics(pred, logits, gt, gv, threshold=2.5)["map_f1"] == pytest.approx(2 * 40 / (80 + 20 + 0))


def test_map_recall_by_gt_length():
    gt, gv, pred, logits = _map_case()
    gt[1] = np.stack([np.linspace(0.0, 3.0, 20), np.full(20, 10.0)], -1)  # a 3 m line
    pred[0] = gt[0] + np.array([0.0, 0.5])  # every point a hit
    pred[1] = gt[1] + np.array([0.0, 2.0])  # every point a miss
    logits[:2] = 5.0
    long_len = float(np.linalg.norm(np.diff(gt[0], axis=0), axis=-1).sum())
    edges = (5.0, long_len - 1.0, long_len + 1.0)
    r = map_metrics(pred, logits, gt, gv, length_edges=edges)
    assert length_labels(edges)[0] == "<5 m" and len(length_labels(edges)) == 4
    assert r["map_recall_by_length"][0] == 0.0 and r["map_recall_by_length"][2] == 1.0
    assert np.isnan(r["map_recall_by_length"][1]) and np.isnan(r["map_recall_by_length"][3])  # no GT lines there
    assert r["map_gt_points_by_length"] == [20.0, 0.0, 20.0, 0.0]
    assert r["map_recall"] == pytest.approx(0.5)  # the groups split the overall recall


def test_map_recall_by_gt_ends():
    gt, gv, pred, logits = _map_case()
    gv[2] = True
    gt[0] = np.stack([np.linspace(-32.0, 32.0, 20), np.full(20, 3.0)], -1)  # clipped by the window at both ends
    gt[1] = np.stack([np.linspace(-31.8, 10.0, 20), np.full(20, -3.0)], -1)  # clipped at one end (within 0.5 m)
    gt[2] = np.stack([np.full(20, 5.0), np.linspace(-10.0, 10.0, 20)], -1)  # both ends inside (a junction)
    pred[:3] = gt[:3] + np.array([0.0, 0.5])
    pred[1, :, 1] += 2.0  # the one-end line missed
    logits[:3] = 5.0
    r = map_metrics(pred, logits, gt, gv, window_half=32.0)
    assert r["map_recall_by_ends"] == [1.0, 0.0, 1.0]
    assert r["map_gt_points_by_ends"] == [20.0, 20.0, 20.0]
    assert len(END_LABELS) == 3
    assert "map_recall_by_ends" not in map_metrics(pred, logits, gt, gv)  # only with window_half


def test_lateral_hand_computed():
    gt = jnp.array([[0.0, 0.0], [1.0, 0.0], [2.0, 1.0]])
    pred = jnp.array([[0.0, 1.0], [1.0, 0.5], [2.0, 2.0]])
    want = [1.0, 0.5 / np.sqrt(2), 1.0 / np.sqrt(2)]  # the last point uses the line through points 1, 2
    np.testing.assert_allclose(lateral_distances(pred, gt), want, rtol=1e-6)
    r = map_metrics(pred[None], jnp.array([5.0]), gt[None], jnp.array([True]))
    assert r["map_lateral"] == pytest.approx(np.mean(want), rel=1e-6)
    assert r["map_f1"] == pytest.approx(1.0)


def test_paper_chamfer_hand_computed():
    # two slots, two points; one GT line near the origin, the second slot is padding
    gt = np.array([[[1.0, 0.0], [2.0, 0.0]], [[0.0, 0.0], [0.0, 0.0]]], np.float32)
    gv = np.array([True, False])
    pred = np.array([[[1.0, 3.0], [2.0, 3.0]], [[50.0, 50.0], [50.0, 50.0]]], np.float32)
    logits = np.array([5.0, -5.0], np.float32)
    r = map_metrics(pred, logits, gt, gv)
    # pred->gt: 9 + 9 (squared, index-aligned). gt->pred: the padded prediction is zeroed to the origin, which is
    # closer to the GT points than the real prediction: 1 + 4. Sum 23 / (2 * 2 points * 1 line) = 5.75 m^2.
    assert r["map_chamfer"] == pytest.approx(5.75)
    # the corrected set Chamfer in metres: every point is 3 m from the other set
    assert r["map_chamfer_corrected"] == pytest.approx(3.0)


def test_set_chamfer_hand_case():
    a = jnp.array([[0.0, 0.0], [4.0, 0.0], [99.0, 99.0]])
    b = jnp.array([[0.0, 3.0], [-50.0, 0.0]])
    d, ok = set_chamfer(a, jnp.array([True, True, False]), b, jnp.array([True, False]))
    # a->b: 3, 5 -> 4; b->a: 3 -> 3; mean 3.5 (invalid points ignored)
    assert bool(ok) and float(d) == pytest.approx(3.5)
    d, ok = set_chamfer(a, jnp.zeros(3, bool), b, jnp.array([True, False]))
    assert not bool(ok) and float(d) == 0.0


def test_map_corrected_skips_empty_frames():
    gt, gv, pred, logits = _map_case()  # no predicted lines at all
    r = map_metrics(pred, logits, gt, gv)
    assert np.isnan(r["map_chamfer_corrected"]) and r["map_chamfer_corrected_skipped"] == 1.0
    assert r["map_f1"] == 0.0  # nothing found: F1 0, not NaN


def test_map_batch_aggregation_exact_per_step():
    rng = np.random.default_rng(5)
    b, s, q, p = 7, 3, 6, 5  # 21 frames: one chunk of 16 and a remainder
    gt = rng.normal(size=(b, s, q, p, 2)).astype(np.float32) * 3
    gv = rng.random((b, s, q)) < 0.6
    pred = gt + rng.normal(size=gt.shape).astype(np.float32) * 0.8
    logits = rng.normal(size=(b, s, q)).astype(np.float32) * 3
    fn = jax.jit(functools.partial(map_metric_sums, step_axis=1, length_edges=LENGTH_EDGES_M))
    sums = fn(pred, logits, gt, gv)
    chex.assert_shape(sums["tp"], (s,))
    whole = reduce_map_metrics(sums)
    acc = None
    for i in range(b):
        acc = accumulate(acc, fn(pred[i:i + 1], logits[i:i + 1], gt[i:i + 1], gv[i:i + 1]))
    split = reduce_map_metrics(acc)
    for k in whole:
        np.testing.assert_allclose(split[k], whole[k], rtol=1e-5, err_msg=k)
    # per-step averaging differs in general from pooling every frame as one step, and both are finite
    pooled = map_metrics(pred, logits, gt, gv)
    assert np.isfinite(pooled["map_f1"]) and np.isfinite(whole["map_f1"])
    # the per-step F1 is the mean over steps of the single-step values
    per_step = [map_metrics(pred[:, j], logits[:, j], gt[:, j], gv[:, j])["map_f1"] for j in range(s)]
    assert whole["map_f1"] == pytest.approx(np.mean(per_step), rel=1e-5)
