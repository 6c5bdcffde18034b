"""The plan tracker (`gpd_jax.sim.tracker`): pure pursuit and the speed law on the bicycle model follow a hand-made
path, stop on a braking reference, and a `Plan` without a tracker is placed as the planning head was."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpd_jax.sim.core import ego_path
from gpd_jax.sim.dynamics import pose_path
from gpd_jax.sim.tracker import Plan, Tracker, TrackState, extend, plan_path, track
from gpd_jax.spec import ModelSpec

DT = 0.1
TRACKER = Tracker()
LA = TRACKER.lookahead_steps(DT)


def _state(speed):
    return TrackState(speed=jnp.float32(speed), accel=jnp.float32(0.0), steer=jnp.float32(0.0))


@jax.jit
def _follow(reference, pose0, speed):
    return track(reference, pose0, _state(speed), jnp.float32(4.6), 80, DT, TRACKER)


@pytest.mark.parametrize("offset", [0.0, 1.0])
@pytest.mark.parametrize("turn", [1.0, -1.0])
def test_the_tracker_follows_a_hand_made_curve(offset, turn):
    """A 40 m radius curve at 10 m/s (left or right), started on it or 1 m beside it."""
    radius, v = 40.0, 10.0
    k = np.arange(0, 80 + LA + 1)
    th = v * k * DT / radius
    ref = np.stack([radius * np.sin(th), turn * (radius - radius * np.cos(th)), turn * th], -1).astype(np.float32)
    path, st = _follow(jnp.asarray(ref), jnp.array([0.0, -turn * offset, 0.0]), v)
    path = np.asarray(path)
    centre = np.array([0.0, turn * radius])
    lateral = np.abs(np.linalg.norm(path[:, :2] - centre, axis=1) - radius)
    arc = np.abs(np.arctan2(path[:, 0], turn * (centre[1] - path[:, 1]))) * radius
    along = arc - v * DT * np.arange(1, 81)
    assert lateral[0] < offset + 0.1
    assert lateral[40:].max() < 0.2, lateral[40:].max()                  # on the curve after 4 s
    assert np.abs(along[40:]).max() < 0.2                                # and on its timing
    assert abs(float(st.speed) - v) < 0.1
    heading_err = np.angle(np.exp(1j * (path[40:, 2] - turn * (arc[40:] / radius))))
    assert np.abs(heading_err).max() < 0.05


def test_a_braking_reference_stops_the_car_where_it_stops():
    v0, a = 12.0, 3.0
    t = np.arange(0, 80 + LA + 1) * DT
    stop = v0 / a
    s = np.where(t < stop, v0 * t - 0.5 * a * t**2, v0**2 / (2 * a))
    ref = np.stack([s, np.zeros_like(s), np.zeros_like(s)], -1).astype(np.float32)
    path, st = _follow(jnp.asarray(ref), jnp.zeros(3), v0)
    x = np.asarray(path[:, 0])
    assert abs(x[-1] - v0**2 / (2 * a)) < 0.3 and float(st.speed) < 0.05
    assert np.all(np.diff(x) >= 0) and x.max() < v0**2 / (2 * a) + 0.3   # no reversing, no overshoot
    np.testing.assert_allclose(np.asarray(path[:, 1]), 0.0, atol=1e-4)


def test_extend_goes_on_at_the_last_velocity_and_plan_path_passes_its_knots():
    path = jnp.array([[1.0, 0.0, 0.0], [2.0, 0.5, 0.1]])
    ext = np.asarray(extend(path, jnp.zeros(3), 5))
    np.testing.assert_allclose(ext[2:, :2], [[3.0, 1.0], [4.0, 1.5], [5.0, 2.0]], atol=1e-6)
    np.testing.assert_allclose(ext[2:, 2], 0.1)
    np.testing.assert_allclose(np.asarray(extend(path, jnp.zeros(3), 1)), path[:1])
    poses = jnp.array([[10.0, 0.0, 0.0], [20.0, 2.0, 0.2], [30.0, 5.0, 0.3]])
    ref = np.asarray(plan_path(jnp.zeros(3), jnp.array([10.0, 0.0]), poses, 1.0, 10))
    np.testing.assert_allclose(ref[9::10], np.asarray(poses), atol=1e-5)


def test_a_plan_without_a_tracker_is_placed_on_its_first_second():
    """Untracked, a Plan places the ego as the planning head did before the tracker: the Hermite curve to its first
    pose with the plan's central-difference velocity there."""
    spec = ModelSpec(num_frames=11, num_history=3, num_agents=4, num_map_tokens=16, frame_stride=10)
    pose0, vel0 = jnp.array([0.0, 0.0, 0.0]), jnp.array([9.0, 0.0])
    poses = jnp.array([[10.0, 0.5, 0.05], [20.0, 1.5, 0.1], [30.0, 3.0, 0.15]])
    path, vel = ego_path(Plan(poses=poses), pose0, vel0, jnp.float32(4.6), spec)
    want_vel = (poses[1, :2] - pose0[:2]) / 2.0
    want, _ = pose_path(pose0, vel0, poses[0], want_vel, 1.0, 10)
    np.testing.assert_allclose(np.asarray(path), np.asarray(want), atol=1e-5)
    np.testing.assert_allclose(np.asarray(vel), np.asarray(want_vel), atol=1e-6)
