"""ADE / FDE split by motion at the current frame: hand-built scenes whose stationary, moving and first-seen
agents (and a moving and a stationary ego) have known errors, through `agent_metric_sums` and the evaluation's
scoring, reduction (per layout too) and table."""

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpd_jax.evaluation import add_sums, format_tables, reduce_results, score_batch
from gpd_jax.evaluation.scoring import current_speed
from gpd_jax.decoding import RolloutOutput
from gpd_jax.metrics import (MOTION_CLASSES, STATIONARY_MPS, TRACK_COMPONENTS, agent_metric_sums,
                             reduce_agent_metrics)
from gpd_jax.scene import TYPE_ID, Scene
from gpd_jax.spec import ModelSpec

# 9 model frames (3 history + 6 future) at stride 2 of a 0.25 s store; horizons 1, 2, 3 s; the current stored
# frame is 4
SPEC = ModelSpec(num_frames=9, num_history=3, num_agents=4, num_map_tokens=64, frame_stride=2,
                 stored_period_s=0.25, horizons=(2, 4, 6))
T_FULL, A_FULL, CUR = 17, 5, 4
TASKS = ("traffic_simulation", "closed_loop", "motion_planning")
# rollout error per model slot in the future frames: ego, stationary agent 1, moving agent 2, first-seen agent 3
OFFSET = np.array([0.5, 1.0, 3.0, 2.0], np.float32)


def full_scene(ego_speed: float = 8.0) -> Scene:
    """Stored-rate scene: ego on y=0 at `ego_speed`; agent 1 creeping at 0.2 m/s (stationary); agent 2 at 4 m/s
    (moving); agent 3 at 6 m/s but first seen at the current frame (speed unknown); slot 4 beyond the model's."""
    t = np.arange(T_FULL) * SPEC.stored_period_s
    xy = np.zeros((T_FULL, A_FULL, 2), np.float32)
    for a, (x0, v, y) in enumerate([(0.0, ego_speed, 0.0), (5.0, 0.2, 10.0), (-5.0, 4.0, 20.0), (0.0, 6.0, 30.0),
                                    (0.0, 0.0, 40.0)]):
        xy[:, a, 0], xy[:, a, 1] = x0 + v * t, y
    valid = np.ones((T_FULL, A_FULL), bool)
    valid[:CUR, 3] = False
    heading = np.zeros((T_FULL, A_FULL), np.float32)
    atype = np.full((A_FULL,), TYPE_ID["car"], np.int32)
    atype[0] = TYPE_ID["ego"]
    return Scene(xy=xy, heading=heading, valid=valid, size=np.tile(np.array([[4.5, 1.9]], np.float32), (A_FULL, 1)),
                 agent_type=atype, map_tokens=np.zeros((T_FULL, 64), np.int32), map_valid=np.ones((T_FULL,), bool),
                 ego_pose=np.concatenate([xy[:, 0], heading[:, :1]], -1))


def stack(*scenes):
    return jax.tree.map(lambda *x: np.stack(x), *scenes)


def predictions(scene: Scene) -> RolloutOutput:
    """Every task's 'rollout': the model-rate log moved sideways by each slot's OFFSET in the future frames."""
    xy = np.array(scene.xy)
    xy[..., SPEC.num_history:, :, 1] += OFFSET
    rep = lambda a: np.repeat(np.asarray(a)[:, None], len(TASKS), axis=1)
    return RolloutOutput(xy=rep(xy), heading=rep(scene.heading), valid=rep(scene.valid),
                         valid_logit=rep(np.zeros(scene.valid.shape, np.float32)), map_tokens=rep(scene.map_tokens))


def score(fulls, per_scenario=False):
    full = stack(*fulls)
    scene = full.subsample(SPEC.frame_stride, SPEC.num_frames, SPEC.num_agents)
    return score_batch(predictions(scene), scene, full, np.ones(len(fulls), bool), SPEC, TASKS,
                       per_scenario=per_scenario)


def test_current_speed_is_the_stored_rate_difference_and_unknown_when_first_seen():
    sp = np.asarray(current_speed(jax.tree.map(jnp.asarray, stack(full_scene(8.0), full_scene(0.0))), SPEC))
    np.testing.assert_allclose(sp[:, :3], [[8.0, 0.2, 4.0], [0.0, 0.2, 4.0]], rtol=1e-4, atol=1e-5)
    assert np.isnan(sp[:, 3]).all() and sp.shape == (2, SPEC.num_agents)


@pytest.fixture(scope="module")
def batch_sums():
    """Sums of one batch: a scenario with a moving ego and one with a stationary ego."""
    return score([full_scene(8.0), full_scene(0.0)])


def test_stationary_and_moving_agents_land_in_their_rows(batch_sums):
    res = reduce_results(add_sums(None, batch_sums), SPEC, TASKS)
    ms = res["motion_split"]
    assert ms["stationary_below_mps"] == STATIONARY_MPS and ms["classes"] == list(MOTION_CLASSES)
    ts = ms["tasks"]["traffic_simulation"]
    for lb in SPEC.labels:
        d = ts[lb]
        for suffix in ("", "_corrected"):
            assert d[f"agent_ade_stationary{suffix}"] == pytest.approx(1.0, rel=1e-5)
            assert d[f"agent_ade_moving{suffix}"] == pytest.approx(3.0, rel=1e-5)
            assert d[f"agent_ade_speed_unknown{suffix}"] == pytest.approx(2.0, rel=1e-5)
            assert d[f"agent_fde_moving{suffix}"] == pytest.approx(3.0, rel=1e-5)
            assert d[f"ego_ade_moving{suffix}"] == pytest.approx(0.5, rel=1e-5)
            assert d[f"ego_ade_stationary{suffix}"] == pytest.approx(0.5, rel=1e-5)
            # the offset is sideways to the motion (along x): all of it is cross-track
            for n in ("ade", "fde"):
                assert d[f"agent_{n}_cross_moving{suffix}"] == pytest.approx(3.0, rel=1e-5)
                assert d[f"agent_{n}_along_moving{suffix}"] == pytest.approx(0.0, abs=1e-4)
            assert d[f"ego_ade_cross_moving{suffix}"] == pytest.approx(0.5, rel=1e-5)
        assert (d["agent_n_stationary"], d["agent_n_moving"], d["agent_n_speed_unknown"]) == (2, 2, 2)
        assert (d["ego_n_stationary"], d["ego_n_moving"], d["ego_n_speed_unknown"]) == (1, 1, 0)
        assert np.isnan(d["ego_ade_speed_unknown"])
        # the unsplit figures are untouched: the mean over the three agents' rows
        assert res["tasks"]["traffic_simulation"][lb]["agent_ade"] == pytest.approx(2.0, rel=1e-5)
    # only the groups a task generates; the baselines have both; constant velocity is exact for constant speeds
    assert not any(k.startswith("ego") for k in ms["tasks"]["closed_loop"]["3s"])
    assert not any(k.startswith("agent") for k in ms["tasks"]["motion_planning"]["3s"])
    cv = ms["baselines"]["constant_velocity"]["3s"]
    assert cv["agent_ade_moving"] == pytest.approx(0.0, abs=1e-4) and cv["ego_ade_stationary"] == 0.0
    assert ms["baselines"]["log_replay"]["3s"]["agent_ade_stationary"] == 0.0
    r = ms["ratios"]["traffic_simulation_over_constant_velocity"]
    assert set(r) == ({f"{g}_{k}" for g in ("agent", "ego") for k in MOTION_CLASSES}
                      | {f"{g}_moving_{c}" for g in ("agent", "ego") for c in TRACK_COMPONENTS})
    table = format_tables(res)
    assert "| agents stationary (< 0.5 m/s) | 2 | 1.00 / 1.00 / 1.00 |" in table
    assert "| agents moving | 2 | 3.00 / 3.00 / 3.00 |" in table
    assert "| · cross-track | | 3.00 / 3.00 / 3.00 |" in table and "| · along-track | | 0.00 / 0.00 / 0.00 |" in table
    assert "| ego moving | 1 | 0.50 / 0.50 / 0.50 |" in table
    assert "ego speed unknown" not in table and "agents speed unknown" in table


def test_rows_add_up_to_the_overall_sums_and_layouts_reduce_alike(batch_sums):
    sums = batch_sums
    for part in ("tasks", "baselines"):
        for name, by_variant in sums[part].items():
            for variant in ("paper", "corrected"):
                for lb, d in by_variant[variant].items():
                    for g in ("ego", "agent"):
                        for n in ("ade", "fde"):
                            for q in ("num", "den"):
                                total = sum(float(d[f"{g}_{n}_{k}_{q}"]) for k in MOTION_CLASSES)
                                assert total == pytest.approx(float(d[f"{g}_{n}_{q}"]), rel=1e-6, abs=1e-6), (
                                    part, name, variant, lb, g, n, q)
    # per scenario (what figures per layout are summed from): the parts add up to the batch, and each part
    # reduces to its own scenario's rows (scenario 0's ego moves, scenario 1's stands)
    per = jax.tree.map(np.asarray, jax.device_get(score([full_scene(8.0), full_scene(0.0)], per_scenario=True)))
    total = flat(jax.tree.map(lambda x: x.sum(0), per))
    whole = flat(jax.device_get(sums))
    np.testing.assert_allclose([total[k] for k in whole], [whole[k] for k in whole], rtol=1e-6, atol=1e-6)
    layouts = {}
    for i, (row, layout) in enumerate((("ego_n_moving", "grid"), ("ego_n_stationary", "real"))):
        layouts[layout] = {"scenarios": 1, **reduce_results(add_sums(None, jax.tree.map(lambda x: x[i], per)),
                                                            SPEC, TASKS)}
        d = layouts[layout]["motion_split"]["tasks"]["traffic_simulation"]["3s"]
        assert d[row] == 1 and d["ego_n_moving"] + d["ego_n_stationary"] == 1 and d["agent_n_moving"] == 1
        assert d["agent_ade_stationary"] == pytest.approx(1.0, rel=1e-5)
    # the layout table carries the stationary and moving ratios at the longest horizon (constant velocity is
    # exact for the moving agent: no ratio, "-")
    res = {"scenarios": 2, **reduce_results(add_sums(None, sums), SPEC, TASKS), "by_layout": layouts}
    table = format_tables(res).split("Per road-network layout")[1].splitlines()
    assert "stat/CV 3s" in table[1] and "mov/CV 3s" in table[1]
    for line, r in zip(table[3:6], (res, layouts["grid"], layouts["real"])):
        cells = line.split()  # name, scenarios, TS ADE, CV ADE, TS/CV, stat/CV, mov/CV, ...
        want = r["motion_split"]["ratios"]["traffic_simulation_over_constant_velocity"]["agent_stationary"]["3s"]
        assert float(cells[5]) == pytest.approx(want, rel=1e-3) and cells[6] == "-", line


def flat(d, prefix=""):
    """Nested dict -> {"a/b/c": float}."""
    out = {}
    for k, v in d.items():
        out.update(flat(v, f"{prefix}{k}/") if isinstance(v, dict) else {prefix + k: float(v)})
    return out


def test_agent_metric_sums_split_under_jit_traces_once():
    """Direct use: speeds on both sides of the threshold and NaN; one compile for two calls."""
    f, h = 6, 3
    gt = jnp.zeros((f, 4, 2))
    pred = gt.at[h:, :, 0].add(jnp.array([1.0, 2.0, 4.0, 8.0]))
    valid = jnp.ones((f, 4), bool)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def sums(speed):
        fn = functools.partial(agent_metric_sums, num_history=h, horizons=(3,), variant="corrected")
        return fn(pred, jnp.zeros((f, 4)), gt, valid, jnp.ones((4, 2)), current_speed=speed)

    r = reduce_agent_metrics(sums(jnp.array([0.0, 0.49, 0.51, jnp.nan])))["0.3s"]
    assert (r["agent_ade_stationary"], r["agent_ade_moving"], r["agent_ade_speed_unknown"]) == (2.0, 4.0, 8.0)
    assert r["ego_ade_stationary"] == 1.0 and np.isnan(r["ego_ade_moving"]) and r["agent_n_moving"] == 1
    r = reduce_agent_metrics(sums(jnp.array([3.0, 3.0, 0.0, 0.0])))["0.3s"]
    assert r["agent_ade_stationary"] == 6.0 and r["agent_ade_moving"] == 2.0 and r["ego_ade_moving"] == 1.0
    assert r["agent_n_speed_unknown"] == 0 and np.isnan(r["agent_ade_speed_unknown"])
    # without speeds: no split keys (other users of agent_metric_sums are unaffected)
    plain = agent_metric_sums(pred, jnp.zeros((f, 4)), gt, valid, jnp.ones((4, 2)), num_history=h, horizons=(3,))
    assert not any("stationary" in k for k in plain["0.3s"])


def test_along_and_cross_track_components_of_moving_errors():
    """An error of (L, 0) against a direction of motion (0.6, 0.8) is 0.6 L along the motion and 0.8 L across;
    only moving slots get the components, and a direction without speeds is refused."""
    f, h = 6, 3
    gt = jnp.zeros((f, 4, 2))
    pred = gt.at[h:, :, 0].add(jnp.array([1.0, 2.0, 4.0, 8.0]))
    valid = jnp.ones((f, 4), bool)
    direction = jnp.tile(jnp.array([[0.6, 0.8]]), (4, 1))
    fn = functools.partial(agent_metric_sums, pred, jnp.zeros((f, 4)), gt, valid, jnp.ones((4, 2)), num_history=h,
                           horizons=(3,), current_direction=direction)
    for variant in ("paper", "corrected"):
        r = reduce_agent_metrics(fn(variant=variant, current_speed=jnp.array([5.0, 0.0, 5.0, 5.0])))["0.3s"]
        for n in ("ade", "fde"):
            assert r[f"agent_{n}_moving"] == pytest.approx(6.0, rel=1e-6)  # agents 2 and 3: errors 4 and 8
            assert r[f"agent_{n}_along_moving"] == pytest.approx(3.6, rel=1e-5)
            assert r[f"agent_{n}_cross_moving"] == pytest.approx(4.8, rel=1e-5)
            assert r[f"ego_{n}_cross_moving"] == pytest.approx(0.8, rel=1e-5)
    with pytest.raises(ValueError, match="current_speed"):
        fn()
