"""The evaluation's batched scoring: one compiled call per batch shape, each scenario's sums add up to the batch's,
and per-frame exact hits in one map-metric call equal the two separate calls."""

import functools

import chex
import jax
import numpy as np
import pytest

from gpd_jax.evaluation import scoring
from gpd_jax.metrics.map import map_metric_sums
from test_evaluate import SPEC, _lines, full_scene, predictions, stack

TASKS = ("map_prediction", "traffic_simulation")


def _batch(shift: float):
    """Two scenarios, both tasks, decoded maps (and the logged map) shifted by `shift` m, the persistence lines."""
    full = stack(full_scene(), full_scene(overlap=True))
    scene = full.subsample(SPEC.frame_stride, SPEC.num_frames, SPEC.num_agents)
    f, b = SPEC.max_horizon, 2
    gt, gv = _lines([10.0, 14.0, 18.0])
    pr, pv = _lines([10.0, 14.0, 18.0], shift=shift)
    logits = np.where(pv, 10.0, -10.0).astype(np.float32)
    map_pred = (np.broadcast_to(pr, (b, 2, f) + pr.shape).copy(), np.broadcast_to(logits, (b, 2, f, 50)).copy())
    gt_lanes = (np.broadcast_to(gt, (b, f) + gt.shape).copy(), np.broadcast_to(gv, (b, f, 50)).copy())
    kept = (gt_lanes[0] + np.float32(shift / 2), gt_lanes[1])
    return predictions(scene, offset=(shift, 0.0), k=2), scene, full, np.array([True, False]), map_pred, gt_lanes, kept


def test_each_scenario_sums_add_up_to_the_batch_sums():
    pred, scene, full, weight, *maps = _batch(0.5)
    total = scoring.score_batch(pred, scene, full, weight, SPEC, TASKS, *maps)
    each = scoring.score_batch(pred, scene, full, weight, SPEC, TASKS, *maps, per_scenario=True)
    assert jax.tree.structure(total) == jax.tree.structure(each)
    assert set(total["baselines"]) >= {"constant_velocity", "map_persistence", "map_tokenizer_reconstruction"}
    for t, e in zip(jax.tree.leaves(total), jax.tree.leaves(each)):
        assert e.shape == (2,) + np.shape(t)
        np.testing.assert_allclose(e.sum(0), t, rtol=1e-6, atol=1e-6)
        assert not np.any(e[1])  # the padded scenario adds nothing
    assert float(total["counts"]["scenarios"]) == 1.0


def test_scoring_compiles_once_per_batch_shape():
    """Batches of the same shape (another rollout, other maps) reuse the one compiled scoring call."""
    traced = jax.jit(chex.assert_max_traces(scoring._score_stacked.__wrapped__, n=1),
                     static_argnames=("spec", "task_names", "per_scenario"))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(scoring, "_score_stacked", traced)
        for shift in (0.5, 2.0):
            pred, scene, full, weight, *maps = _batch(shift)
            scoring.score_batch(pred, scene, full, weight, SPEC, TASKS, *maps, per_scenario=True)


def test_exact_hits_per_frame_equal_the_separate_calls():
    """`count_exact_hits` as a per-frame array (the evaluation scores the tasks and the persistence baseline in one
    call) gives each frame the sums of the call with that frame's flag."""
    gt, gv = _lines([10.0, 14.0, 18.0])
    pr = np.stack([gt, gt + np.float32(0.5)])  # frame 0 on the GT (distance 0), frame 1 0.5 m off
    logits = np.where(np.stack([gv, gv]), 10.0, -10.0).astype(np.float32)
    args = (pr, logits, np.stack([gt, gt]), np.stack([gv, gv]))
    fn = jax.jit(functools.partial(map_metric_sums, step_axis=0))
    for flags in ([True, False], [False, True]):
        mixed = jax.device_get(fn(*args, count_exact_hits=np.array(flags)))
        for i, flag in enumerate(flags):
            one = jax.device_get(fn(*args, count_exact_hits=flag))
            for key in one:
                np.testing.assert_array_equal(mixed[key][i], one[key][i], err_msg=key)
    exact = jax.device_get(fn(*args, count_exact_hits=np.array([True, False])))
    paper = jax.device_get(fn(*args, count_exact_hits=np.array([False, False])))
    assert exact["tp"][0] > 0 and paper["tp"][0] == 0  # the distance-0 points: hits only where exact hits count
