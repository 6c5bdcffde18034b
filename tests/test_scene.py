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
