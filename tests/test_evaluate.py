"""Scoring path of the evaluation: known offsets -> known ADE / FDE, overlapping boxes -> collisions, baselines,
scored slots, padding, map metrics, horizons, the metrics.json key scheme and the tables."""

import json
import math
import os

import numpy as np
import pytest

from gpd_jax.evaluation import add_sums, format_tables, reduce_results, score_batch, to_json_compatible
from gpd_jax.evaluation.keys import AGENT_METRICS
from gpd_jax.evaluation.maps import gt_future_lanes, persistence_future_lanes
from gpd_jax.spec import EvalError, ModelSpec, horizon_frames, spec_from_config
from gpd_jax.tasks import generated
from gpd_jax.decoding import RolloutOutput
from gpd_jax.scene import TYPE_ID, Scene

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# model: 9 frames (3 history + 6 future) at stride 2 of a 0.25 s store -> 0.5 s frames; horizons 1, 2, 3 s
SPEC = ModelSpec(num_frames=9, num_history=3, num_agents=4, num_map_tokens=64, frame_stride=2,
                stored_period_s=0.25, horizons=(2, 4, 6))
TASKS3 = ("traffic_simulation", "closed_loop", "motion_planning")
T_FULL, A_FULL = 17, 5  # the stored scene: 17 frames, one slot more than the model takes
CUR_FULL = 4  # stored index of the model's current frame (model frame 2)


def full_scene(overlap: bool = False) -> Scene:
    """Stored-rate scene: ego on y=0 at 8 m/s; agent 1 on y=10 accelerating; agent 2 on y=20 at 4 m/s;
    agent 3 (y=30) appears only after the current frame (never scored); slot 4 empty. With `overlap`, agent 2
    drives on top of agent 1 in every future frame."""
    t = np.arange(T_FULL) * SPEC.stored_period_s
    xy = np.zeros((T_FULL, A_FULL, 2), np.float32)
    xy[:, 0, 0] = 8.0 * t
    xy[:, 1, 0] = 5.0 + 2.0 * t + 1.5 * t ** 2
    xy[:, 1, 1] = 10.0
    xy[:, 2, 0] = -5.0 + 4.0 * t
    xy[:, 2, 1] = 20.0
    xy[:, 3, 0] = 3.0 * t
    xy[:, 3, 1] = 30.0
    if overlap:
        xy[CUR_FULL + 1:, 2] = xy[CUR_FULL + 1:, 1] + np.array([0.5, 0.3], np.float32)
    valid = np.zeros((T_FULL, A_FULL), bool)
    valid[:, :3] = True
    valid[CUR_FULL + 2:, 3] = True
    heading = np.zeros((T_FULL, A_FULL), np.float32)
    size = np.tile(np.array([[4.5, 1.9]], np.float32), (A_FULL, 1))
    atype = np.full((A_FULL,), TYPE_ID["car"], np.int32)
    atype[0] = TYPE_ID["ego"]
    ego_pose = np.concatenate([xy[:, 0], heading[:, :1]], -1)
    return Scene(xy=xy, heading=heading, valid=valid, size=size, agent_type=atype,
                 map_tokens=np.zeros((T_FULL, 64), np.int32), map_valid=np.ones((T_FULL,), bool), ego_pose=ego_pose)


def stack(*scenes):
    import jax
    return jax.tree.map(lambda *x: np.stack(x), *scenes)


def predictions(scene: Scene, offset=(1.0, 0.0), k: int = len(TASKS3)) -> RolloutOutput:
    """A 'rollout' of every task that equals the model-rate log shifted by `offset` in the future frames
    (agent 3, never scored, is shifted by 50 m)."""
    xy = np.array(scene.xy)
    h = SPEC.num_history
    xy[..., h:, :, :] += np.asarray(offset, np.float32)
    xy[..., h:, 3, :] += 50.0
    rep = lambda a: np.repeat(np.asarray(a)[:, None], k, axis=1)
    return RolloutOutput(xy=rep(xy), heading=rep(scene.heading), valid=rep(scene.valid),
                         valid_logit=rep(np.zeros(scene.valid.shape, np.float32)), map_tokens=rep(scene.map_tokens))


def run(fulls, preds_fn, weight=None, tasks=TASKS3, variant="paper", **kw):
    full = stack(*fulls)
    scene = full.subsample(SPEC.frame_stride, SPEC.num_frames, SPEC.num_agents)
    pred = preds_fn(scene)
    weight = np.ones(len(fulls), bool) if weight is None else np.asarray(weight)
    sums = score_batch(pred, scene, full, weight, SPEC, tasks, **kw)
    return reduce_results(add_sums(None, sums), SPEC, tasks, variant), sums


def test_known_offset_gives_known_ade_fde_and_baselines():
    res, sums = run([full_scene(), full_scene()], predictions)
    assert SPEC.labels == ("1s", "2s", "3s")
    ts = res["tasks"]["traffic_simulation"]
    for lb in SPEC.labels:
        for g in ("ego", "agent"):
            for suffix in ("", "_corrected"):  # paper (main) and corrected (suffix) agree on this scene
                assert ts[lb][f"{g}_ade{suffix}"] == pytest.approx(1.0, abs=1e-5), (lb, g, suffix)
                assert ts[lb][f"{g}_fde{suffix}"] == pytest.approx(1.0, abs=1e-5)
                assert ts[lb][f"{g}_collision{suffix}"] == 0.0
    # only what a task generates is reported
    assert set(res["tasks"]["closed_loop"]["3s"]) == {f"agent_{n}{s}" for n in AGENT_METRICS
                                                      for s in ("", "_corrected")}
    assert set(res["tasks"]["motion_planning"]["3s"]) == {f"ego_{n}{s}" for n in AGENT_METRICS
                                                          for s in ("", "_corrected")}
    # scored slots: ego + agents 1, 2 (agent 3 is not valid at the current frame), in both scenarios
    assert float(sums["counts"]["scored_agents"]) == 4 and float(sums["counts"]["scenarios"]) == 2
    # log replay: zero error; constant velocity: exact for the constant-speed ego, not for the accelerating agent 1
    lr, cv = res["baselines"]["log_replay"], res["baselines"]["constant_velocity"]
    for lb in SPEC.labels:
        for k in ("ego_ade", "ego_fde", "agent_ade", "agent_fde", "ego_collision", "agent_collision"):
            assert lr[lb][k] == 0.0, (lb, k)
        assert cv[lb]["ego_ade"] == pytest.approx(0.0, abs=1e-4)
    # agent 1: x = 5 + 2t + 1.5t^2, velocity from the last two 0.25 s frames before t0 = 1 s: 2 + 3 * 0.875 m/s;
    # error at future time t0 + d = 1.5 d^2 + 0.375 d, averaged with agent 2's zero error (paper and corrected)
    d = np.arange(1, 7) * 0.5
    err1 = 1.5 * d ** 2 + 3 * 0.125 * d
    for lb, h in zip(SPEC.labels, SPEC.horizons):
        assert cv[lb]["agent_ade"] == pytest.approx(err1[:h].mean() / 2, rel=1e-4)
        assert cv[lb]["agent_fde"] == pytest.approx(err1[h - 1] / 2, rel=1e-4)
        assert res["ratios"]["traffic_simulation_agent_ade_over_constant_velocity"][lb] == pytest.approx(
            1.0 / cv[lb]["agent_ade"], rel=1e-4)
    # at the model's rate (0.5 s frames) the velocity is (x(1) - x(0.5)) / 0.5 = 4.25 m/s: error 1.5 d^2 + 0.75 d
    cvm = res["baselines"]["constant_velocity_model_rate"]
    err_m = 1.5 * d ** 2 + 0.75 * d
    for lb, h in zip(SPEC.labels, SPEC.horizons):
        assert cvm[lb]["ego_ade"] == pytest.approx(0.0, abs=1e-4)
        assert cvm[lb]["agent_ade"] == pytest.approx(err_m[:h].mean() / 2, rel=1e-4)
        assert res["ratios"]["traffic_simulation_agent_ade_over_constant_velocity_model_rate"][lb] == pytest.approx(
            1.0 / cvm[lb]["agent_ade"], rel=1e-4)


def test_overlapping_boxes_collide_and_separate_boxes_do_not():
    same = lambda s: predictions(s, offset=(0.0, 0.0))
    res, _ = run([full_scene(overlap=True), full_scene(overlap=True)], same)
    res0, _ = run([full_scene(), full_scene()], same)
    for lb in SPEC.labels:
        for suffix in ("", "_corrected"):
            # agents 1 and 2 overlap at every future frame: both collide, every step
            for k in ("agent_collision", "agent_collision_frames"):
                assert res["tasks"]["closed_loop"][lb][f"{k}{suffix}"] == pytest.approx(100.0)
                assert res["baselines"]["log_replay"][lb][f"{k}{suffix}"] == pytest.approx(100.0)
            assert res["tasks"]["traffic_simulation"][lb][f"ego_collision{suffix}"] == 0.0
            assert res0["tasks"]["closed_loop"][lb][f"agent_collision{suffix}"] == 0.0
            assert res0["baselines"]["log_replay"][lb][f"agent_collision{suffix}"] == 0.0
        assert res["baselines"]["log_replay"][lb]["agent_ade"] == 0.0


def test_padding_scenarios_are_weighted_out():
    def preds(scene):  # scenario 1 (padding) has a wild prediction
        p = predictions(scene)
        xy = np.array(p.xy)
        xy[1, :, SPEC.num_history:] += 1000.0
        return p.replace(xy=xy)

    res, sums = run([full_scene(), full_scene(overlap=True)], preds, weight=[True, False])
    ref, _ = run([full_scene(), full_scene()], predictions)
    assert float(sums["counts"]["scenarios"]) == 1
    for name in TASKS3:
        for lb in SPEC.labels:
            for k, v in ref["tasks"][name][lb].items():
                assert res["tasks"][name][lb][k] == pytest.approx(v, abs=1e-5), (name, lb, k)
    for lb in SPEC.labels:
        assert res["baselines"]["log_replay"][lb]["agent_collision"] == 0.0


def test_variant_switch_swaps_main_and_suffixed_keys():
    res_p, sums = run([full_scene(), full_scene()], predictions)
    res_c = reduce_results(add_sums(None, sums), SPEC, TASKS3, "corrected")
    for lb in SPEC.labels:
        p, c = res_p["tasks"]["closed_loop"][lb], res_c["tasks"]["closed_loop"][lb]
        assert set(c) == {f"agent_{n}{s}" for n in AGENT_METRICS for s in ("", "_paper")}
        for n in AGENT_METRICS:
            assert c[f"agent_{n}"] == p[f"agent_{n}_corrected"] and c[f"agent_{n}_paper"] == p[f"agent_{n}"]
    with pytest.raises(EvalError, match="variant"):
        reduce_results(add_sums(None, sums), SPEC, TASKS3, "best")


def _lines(y0s, shift=0.0):
    """f32[50, 20, 2] lines along x at the given y (+ shift), the rest zero; bool[50]."""
    pts = np.zeros((50, 20, 2), np.float32)
    ok = np.zeros((50,), bool)
    for i, y in enumerate(y0s):
        pts[i, :, 0] = np.linspace(-20, 20, 20)
        pts[i, :, 1] = y + shift
        ok[i] = True
    return pts, ok


def test_map_metrics_of_laterally_shifted_lines():
    tasks = ("map_prediction", "traffic_simulation")
    assert generated("map_prediction") == ("map",) and "map" not in generated("traffic_simulation")
    f = SPEC.max_horizon
    gt, gv = _lines([10.0, 14.0, 18.0])
    pr, pv = _lines([10.0, 14.0, 18.0], shift=0.5)
    perm = np.roll(np.arange(50), 7)  # predictions in another query order: the Hungarian matching undoes it
    pr, pv = pr[perm], pv[perm]
    logits = np.where(pv, 10.0, -10.0).astype(np.float32)
    b = 2
    map_pred = (np.broadcast_to(pr, (b, 1, f) + pr.shape).copy(), np.broadcast_to(logits, (b, 1, f, 50)).copy())
    gt_lanes = (np.broadcast_to(gt, (b, f) + gt.shape).copy(), np.broadcast_to(gv, (b, f, 50)).copy())
    # the persistence baseline scored with the same (unpermuted) shifted lines: the same values
    kept = (np.broadcast_to(pr[np.argsort(perm)], gt_lanes[0].shape).copy(),
            np.broadcast_to(pv[np.argsort(perm)], gt_lanes[1].shape).copy())
    res, _ = run([full_scene(), full_scene()], lambda s: predictions(s, k=2), tasks=tasks, map_pred=map_pred,
                 gt_lanes=gt_lanes, kept_lanes=kept)
    assert res["baselines"]["map_persistence"] == res["tasks"]["map_prediction"]
    # carried lines that coincide with the ground truth are hits (the paper's F1 would score them 0)
    _, sums = run([full_scene(), full_scene()], lambda s: predictions(s, k=2), tasks=tasks, map_pred=map_pred,
                  gt_lanes=gt_lanes, kept_lanes=gt_lanes)
    m = reduce_results(add_sums(None, sums), SPEC, tasks)["baselines"]["map_persistence"]["3s"]
    assert m["map_f1"] == pytest.approx(1.0) and m["map_chamfer_corrected"] == pytest.approx(0.0, abs=1e-6)
    assert "current lanes carried forward (map persistence):" in format_tables(res)
    for lb in SPEC.labels:
        m = res["tasks"]["map_prediction"][lb]
        assert not any(k.startswith(("ego_", "agent_")) for k in m)
        assert m["map_f1"] == pytest.approx(1.0) and m["map_precision"] == pytest.approx(1.0)
        assert m["map_recall"] == pytest.approx(1.0)
        assert m["map_lateral"] == pytest.approx(0.5, abs=1e-5)
        assert m["map_chamfer"] == pytest.approx(0.25, abs=1e-5)  # paper: squared, index-aligned
        assert m["map_chamfer_corrected"] == pytest.approx(0.5, abs=1e-5)  # set-based, metres
        # the cut-invariant score reaches the results beside the paper's: lines 0.5 m off lie within 1.5 m
        assert m["map_f1_cutfree"] == pytest.approx(1.0) and m["map_chamfer_cutfree"] == pytest.approx(0.5, rel=1e-3)
        assert m["map_f1_cutfree_directed"] == pytest.approx(1.0)  # shifted, not reversed
        assert m["map_chamfer_corrected_skipped"] == 0
        assert not any(k.startswith("map_") for k in res["tasks"]["traffic_simulation"][lb])
    assert "F1 cutfr" in format_tables(res) and "F1 cfdir" in format_tables(res)


def test_persistence_lanes_are_the_current_window_seen_from_the_logged_future_poses():
    full = full_scene()  # ego along y = 0 at 8 m/s, heading 0; current stored frame 4 (x = 8 m)
    x = np.linspace(-100.0, 200.0, 301, dtype=np.float32)
    poly = np.stack([x, np.full_like(x, 3.0)], -1)[None]  # one long lane 3 m left of the ego's path
    pv = np.ones(poly.shape[:2], bool)
    kp, kv = persistence_future_lanes(poly[None], pv[None], np.asarray(full.ego_pose)[None], SPEC)
    gp, gv = gt_future_lanes(poly[None], pv[None], np.asarray(full.ego_pose)[None], SPEC)
    assert kp.shape == gp.shape == (1, SPEC.max_horizon, 50, 20, 2) and kv.sum() == gv.sum() == SPEC.max_horizon
    ego_x = np.asarray(full.ego_pose)[:, 0]
    for j, fr in enumerate(SPEC.future_stored_frames()):
        moved = ego_x[fr] - ego_x[CUR_FULL]
        np.testing.assert_allclose(kp[0, j, 0, [0, -1], 0], [-32.0, 32.0 - moved], atol=1e-3)  # cut at the old edge
        np.testing.assert_allclose(gp[0, j, 0, [0, -1], 0], [-32.0, 32.0], atol=1e-3)
        np.testing.assert_allclose(kp[0, j, 0, :, 1], 3.0, atol=1e-4)


def test_horizons_in_model_frames():
    assert horizon_frames((3, 5, 8), 0.5, 16) == ((6, 10, 16), ())
    assert horizon_frames((3, 5, 8), 0.1, 80) == ((30, 50, 80), ())
    assert horizon_frames((3, 5, 8), 1.0, 6) == ((3, 5), (8,))
    with pytest.raises(EvalError, match="9.3 s is not a positive whole number"):
        horizon_frames((3, 9.3), 1.0, 10)
    with pytest.raises(EvalError, match="no horizon"):
        horizon_frames((3, 5, 8), 0.1, 6)
    from gpd_jax.config import load_config

    cfg = load_config(os.path.join(ROOT, "configs", "gpd_paper.py"))
    spec, _ = spec_from_config(cfg)
    assert spec.horizons == (30, 50, 80) and spec.labels == ("3s", "5s", "8s") and spec.full_history == 21
    cfg.data.frame_stride, cfg.model.num_frames, cfg.model.num_history = 5, 21, 5  # 2 Hz
    spec, skipped = spec_from_config(cfg)
    assert spec.horizons == (6, 10, 16) and spec.labels == ("3s", "5s", "8s") and not skipped
    assert spec.frame_period_s == pytest.approx(0.5) and spec.stored_frames_needed == 101
    assert spec.full_history == 21  # the 10 Hz history ends at the same current frame (stored frame 20)
    assert list(spec.future_stored_frames(3)) == [25, 30, 35]


def test_tables_and_json_nulls():
    res, _ = run([full_scene(), full_scene()], predictions)
    res["tasks"]["closed_loop"]["1s"]["agent_ade"] = float("nan")
    text = format_tables(res)
    assert "Table 1" in text and "traffic simulation:" in text and "log replay (baseline):" in text
    assert "traffic simulation agent ADE / constant velocity (stored rate) agent ADE" in text
    assert "traffic simulation agent ADE / constant velocity (model rate) agent ADE" in text
    out = json.loads(json.dumps(to_json_compatible(res), allow_nan=False))
    assert out["tasks"]["closed_loop"]["1s"]["agent_ade"] is None
    assert math.isfinite(out["tasks"]["traffic_simulation"]["3s"]["agent_ade"])
