import jax.numpy as jnp
import numpy as np
import pytest

from gpd_jax.evaluation.baselines import Trajectories, constant_velocity, follow_lanes, log_replay
from gpd_jax.geometry import LANE_SNAP_M
from gpd_jax.metrics import agent_metrics
from gpd_jax.scene import empty_scene

T, H, A = 12, 4, 4


def _scene(batch=()):
    s = empty_scene(T, A, 4, batch_shape=batch)
    t = np.arange(T, dtype=np.float32)[:, None]
    xy = np.zeros(batch + (T, A, 2), np.float32)
    xy[..., 0] = t * np.array([1.0, 0.0, -0.5, 2.0])  # straight lines at different speeds
    xy[..., 1] = t * np.array([0.0, 0.3, 0.2, 0.0]) + np.array([0.0, 10.0, 20.0, 30.0])
    heading = np.broadcast_to(np.array([0.0, 0.29, 2.76, 0.0], np.float32), batch + (T, A)).copy()
    valid = np.ones(batch + (T, A), bool)
    valid[..., [0, 2], 2] = False  # agent 2: gaps in the history (last two valid frames are 1 and 3)
    valid[..., H - 1, 3] = False  # agent 3: not valid at the current frame
    return s.replace(xy=jnp.asarray(xy), heading=jnp.asarray(heading), valid=jnp.asarray(valid))


def test_constant_velocity_extrapolates_straight_lines_exactly():
    s = _scene()
    p = constant_velocity(s, H)  # jitted
    assert p.xy.shape == s.xy.shape and p.valid.shape == s.valid.shape
    np.testing.assert_allclose(p.xy[:, :3], s.xy[:, :3], atol=1e-5)  # ego, agent 1 and the gappy agent 2
    np.testing.assert_allclose(p.heading[:, :3], s.heading[:, :3], atol=1e-6)
    np.testing.assert_array_equal(p.valid[:, :3], s.valid[:, :3])
    # agent 3 was not observed at the current frame: it stays invalid for the whole future
    assert not np.any(np.asarray(p.valid[H:, 3]))
    np.testing.assert_array_equal(p.valid[:H], s.valid[:H])  # history is the log


def test_constant_velocity_single_observation_stands_still_and_batches():
    s = _scene(batch=(2,))
    v = np.asarray(s.valid).copy()
    v[1, : H - 1, 1] = False  # in scenario 1, agent 1 is seen only at the current frame
    s = s.replace(valid=jnp.asarray(v))
    p = constant_velocity(s, H)
    np.testing.assert_allclose(p.xy[1, H:, 1], np.broadcast_to(s.xy[1, H - 1, 1], (T - H, 2)), atol=1e-6)
    np.testing.assert_allclose(p.xy[0, H:, 1], s.xy[0, H:, 1], atol=1e-5)


@pytest.mark.parametrize("variant", ["paper", "corrected"])
def test_log_replay_zero_error(variant):
    s = _scene()
    p = log_replay(s, H)
    r = agent_metrics(p.xy, p.heading, s.xy, s.valid, s.size, num_history=H, pred_valid=p.valid,
                      horizons=(4, 8), variant=variant)
    for h in r:
        for k in ("ego_ade", "ego_fde", "agent_ade", "agent_fde", "ego_collision", "agent_collision"):
            assert r[h][k] == 0.0, (h, k)
    # constant velocity is also exact on straight lines (agent 3, unobserved at the current frame, is not scored)
    cv = constant_velocity(s, H)
    em = jnp.array([True, True, True, False])
    r = agent_metrics(cv.xy, cv.heading, s.xy, s.valid, s.size, num_history=H, pred_valid=cv.valid,
                      eval_mask=em, horizons=(8,), variant=variant)
    assert r["0.8s"]["agent_ade"] == pytest.approx(0.0, abs=1e-5)


def test_follow_lanes_keeps_constant_velocitys_speed_along_a_curved_lane():
    # a counter-clockwise circle of radius 30 and, 3.5 m outside it, the opposing lane
    th = np.linspace(-np.pi, np.pi, 361)
    lanes = np.stack([np.stack([30 * np.cos(th), 30 * np.sin(th)], -1),
                      np.stack([33.5 * np.cos(th[::-1]), 33.5 * np.sin(th[::-1])], -1)]).astype(np.float32)
    ok = np.ones(lanes.shape[:2], bool)
    t = np.arange(T, dtype=np.float32)
    # constant velocity of four agents: on the lane at 5 m per frame tangentially, 1 m outside it, standing,
    # and far from every lane
    start = np.array([[30.0, 0.0], [31.0, 0.0], [0.0, -30.0], [0.0, 0.0]], np.float32)
    vel = np.array([[0.0, 5.0], [0.0, 5.0], [0.0, 0.0], [4.0, 0.0]], np.float32)
    xy = start[None] + (t - (H - 1))[:, None, None] * vel[None]
    heading = np.broadcast_to(np.array([np.pi / 2, np.pi / 2, 0.0, 0.0], np.float32), (T, A)).copy()
    cv = Trajectories(xy=jnp.asarray(xy), heading=jnp.asarray(heading), valid=jnp.ones((T, A), bool))
    out = follow_lanes(cv, H, jnp.asarray(lanes), jnp.asarray(ok), stride=1)
    np.testing.assert_array_equal(np.asarray(out.xy[:H]), xy[:H])
    fut = np.asarray(out.xy[H:])
    k = np.arange(1, T - H + 1)
    # agent 0 rides the circle, 5 m of arc per frame (chords of 1-degree segments: within a few cm)
    np.testing.assert_allclose(np.hypot(fut[:, 0, 0], fut[:, 0, 1]), 30.0, atol=0.05)
    np.testing.assert_allclose(np.arctan2(fut[:, 0, 1], fut[:, 0, 0]) * 30.0, 5.0 * k, rtol=0.02)
    np.testing.assert_allclose(np.asarray(out.heading[H:, 0]), np.arctan2(fut[:, 0, 1], fut[:, 0, 0]) + np.pi / 2,
                               atol=0.03)
    # agent 1 keeps its 1 m offset outside the lane, turned with the lane
    np.testing.assert_allclose(np.hypot(fut[:, 1, 0], fut[:, 1, 1]), 31.0, atol=0.05)
    # standing stays; far from every lane (> LANE_SNAP_M) keeps constant velocity
    np.testing.assert_allclose(fut[:, 2], xy[H:, 2], atol=1e-5)
    assert 30.0 - np.hypot(*start[3]) > LANE_SNAP_M
    np.testing.assert_allclose(fut[:, 3], xy[H:, 3], atol=1e-5)
    np.testing.assert_array_equal(np.asarray(out.valid), np.asarray(cv.valid))
