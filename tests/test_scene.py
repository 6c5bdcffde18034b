import jax.numpy as jnp
import numpy as np
import pytest

from gpd_jax.scene import empty_scene, wrap_angle


def test_validate_accepts_batched_and_optional_lanes():
    s = empty_scene(7, 4, 16, batch_shape=(2, 3), num_lanes=50)
    assert s.validate().batch_shape == (2, 3)
    assert s.slice_frames(2, 5).validate().num_frames == 3
    assert s.slice_frames(2, 5).lanes.shape == (2, 3, 3, 50, 20, 2)


def test_validate_names_every_bad_field():
    s = empty_scene(7, 4, 16)
    bad = s.replace(heading=jnp.zeros((7, 5)), map_valid=jnp.zeros((7,), jnp.int32), size=jnp.zeros((2, 4, 2)))
    with pytest.raises(ValueError) as e:
        bad.validate()
    msg = str(e.value)
    assert "heading: dim A=5" in msg
    assert "map_valid: dtype int32" in msg
    assert "size: batch dims (2,)" in msg


def test_wrap_angle():
    a = jnp.array([np.pi, -np.pi, 3 * np.pi, 0.5, -7.0])
    w = np.asarray(wrap_angle(a))
    assert ((w >= -np.pi) & (w < np.pi)).all()
    np.testing.assert_allclose(np.cos(w), np.cos(np.asarray(a)), atol=1e-5)


def test_with_velocity_and_subsample_keep_the_stored_rate_velocity():
    """Velocities are backward differences at the full rate (zero without a valid previous frame), and a
    subsampled scene keeps each kept frame's full-rate velocity, not the difference of the kept frames."""
    t, a = 21, 3
    s = empty_scene(t, a, 4)
    time = np.arange(t, dtype=np.float32) * 0.1
    xy = np.zeros((t, a, 2), np.float32)
    xy[:, 0, 0] = 10.0 * time                    # ego: 10 m/s forward
    xy[:, 1, 1] = 2.0 * time ** 2 / 2            # agent 1 accelerating laterally at 2 m/s^2
    valid = np.ones((t, a), bool)
    valid[:5, 2] = False                         # agent 2 appears at frame 5
    s = s.replace(xy=jnp.asarray(xy), valid=jnp.asarray(valid))
    v = np.asarray(s.with_velocity(0.1).velocity)
    np.testing.assert_allclose(v[0], 0.0)
    np.testing.assert_allclose(v[1:, 0], [[10.0, 0.0]] * (t - 1), atol=1e-3)
    np.testing.assert_allclose(v[1:, 1, 1], 2.0 * (time[1:] - 0.05), atol=1e-3)
    np.testing.assert_allclose(v[:6, 2], 0.0)
    view = s.subsample(10, 3, 2, velocity_period_s=0.1).validate()
    assert view.velocity.shape == (3, 2, 2)
    np.testing.assert_allclose(np.asarray(view.velocity[2, 1, 1]), 2.0 * 1.95, atol=1e-3)
    # numpy leaves work too (the data loader's batches)
    npv = s.replace(xy=xy, valid=valid).with_velocity(0.1).velocity
    assert isinstance(npv, np.ndarray)
    np.testing.assert_allclose(npv, v, atol=1e-5)
    with pytest.raises(ValueError, match="positive"):
        s.with_velocity(0.0)


def test_velocity_over_a_tracking_gap_is_the_constant_velocity_baselines():
    """A track missing for a few frames (occlusion, sensor range) keeps its speed: the backward difference spans
    the gap, as `constant_velocity` extrapolates, instead of falling to zero, which a velocity-input model reads as
    standing. Zero where the agent was never seen before."""
    from gpd_jax.evaluation.baselines import constant_velocity
    t, a, h = 21, 3, 21
    s = empty_scene(t, a, 4)
    time = np.arange(t, dtype=np.float32) * 0.1
    xy = np.zeros((t, a, 2), np.float32)
    xy[:, 1, 0] = 8.0 * time                     # agent 1: 8 m/s, missing at frames 17-19
    xy[:, 2, 1] = -3.0 * time                    # agent 2: first seen at the last frame
    valid = np.ones((t, a), bool)
    valid[17:20, 1] = False
    valid[:20, 2] = False
    s = s.replace(xy=jnp.asarray(xy), valid=jnp.asarray(valid))
    v = np.asarray(s.with_velocity(0.1).velocity)
    np.testing.assert_allclose(v[20, 1], [8.0, 0.0], rtol=1e-4)
    np.testing.assert_allclose(v[17:20, 1], 0.0)
    np.testing.assert_allclose(v[20, 2], 0.0)
    np.testing.assert_allclose(s.replace(xy=xy, valid=valid).with_velocity(0.1).velocity, v, atol=1e-5)
    # the baseline's step per frame, from the same two frames
    future = s.replace(xy=jnp.concatenate([s.xy, s.xy[:2]]), valid=jnp.concatenate([s.valid, s.valid[:2]]),
                       heading=jnp.zeros((t + 2, a)))
    cv = constant_velocity(future, h)
    np.testing.assert_allclose((np.asarray(cv.xy[h, 1]) - xy[20, 1]) / 0.1, v[20, 1], rtol=1e-4)
