import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpd_jax.config import load_config
from gpd_jax.model.agent_tokenizer import AgentTokenizer, LevelSpec, dequantize, quantize, sinusoid_table

from conftest import ROOT


@pytest.fixture(scope="module")
def tok():
    return AgentTokenizer.from_config(load_config(f"{ROOT}/configs/gpd_paper.py").model)


def test_paper_bins(tok):
    assert tok.x.bins == (600, 100)
    assert tok.heading.bins == (18, 20)
    assert tok.dim == 4 * 48 + 2 * 32


def test_known_values(tok):
    # paper eqs. 3-4 after the +300 m offset: 1.23 m -> 301.23 -> (301, 23); -0.3 -> 299.70 -> (299, 70)
    q, _ = quantize(jnp.array([1.23, -0.3, -300.0, 0.0]), tok.x)
    np.testing.assert_array_equal(np.asarray(q), [[301, 23], [299, 70], [0, 0], [300, 0]])
    # heading 45 deg -> 225 deg -> (11, 5); -180 deg -> (0, 0)
    qh, _ = quantize(jnp.deg2rad(jnp.array([45.0, -180.0])), tok.heading)
    np.testing.assert_array_equal(np.asarray(qh), [[11, 5], [0, 0]])


def test_round_trip_within_finest_step(tok):
    rng = np.random.default_rng(0)
    xy = rng.uniform(-299.99, 299.99, (2000, 2)).astype(np.float32)
    h = rng.uniform(-np.pi, np.pi - 1e-3, 2000).astype(np.float32)
    (qx, qy, qh), clamped = tok.quantize(jnp.asarray(xy), jnp.asarray(h))
    assert not bool(clamped.any())
    rxy, rh = tok.decode(qx, qy, qh)
    err = np.asarray(jnp.asarray(xy) - rxy)
    assert (err >= -1e-3).all() and (err < 0.01 + 1e-3).all(), (err.min(), err.max())
    herr = np.rad2deg(np.asarray(jnp.asarray(h) - rh))
    assert (herr >= -1e-3).all() and (herr < 1.0 + 1e-3).all()
    assert (xy < 0).sum() > 500  # negative values were exercised


def test_clamping_never_indexes_out_of_bounds(tok):
    xy = jnp.array([[500.0, -1000.0], [299.999, -300.0], [jnp.nan, 0.0], [1.0, 2.0]])
    h = jnp.array([0.0, 0.0, 0.0, 10.0])  # 10 rad is outside [-pi, pi)
    (qx, qy, qh), clamped = tok.quantize(xy, h)
    assert np.asarray(clamped).tolist() == [True, False, True, True]
    for q, spec in ((qx, tok.x), (qy, tok.y), (qh, tok.heading)):
        q = np.asarray(q)
        assert (q >= 0).all() and (q < np.array(spec.bins)).all()
    assert int(tok.count_clamped(xy, h)) == 3
    assert int(tok.count_clamped(xy, h, valid=jnp.array([True, True, False, False]))) == 1
    codes = tok.encode(xy, h)
    assert codes.shape == (4, tok.dim) and bool(jnp.isfinite(codes).all())
    rxy, _ = tok.decode(qx, qy, qh)
    np.testing.assert_allclose(np.asarray(rxy[0]), [299.99, -300.0], atol=1e-3)


def test_codes_are_true_sinusoids_and_distinct():
    t = sinusoid_table(600, 48, max_period=2400.0)
    np.testing.assert_allclose(t[:, 0], np.sin(np.arange(600)), atol=1e-5)
    np.testing.assert_allclose(t[:, 1], np.cos(np.arange(600)), atol=1e-5)
    # neighbouring indices differ, and all rows are distinct
    assert np.unique(t.round(5), axis=0).shape[0] == 600


def test_generic_levels_and_jit():
    spec = LevelSpec(offset=10.0, scales=(5.0, 1.0, 0.5), code_dim=4)
    assert spec.bins == (4, 5, 2)
    q, _ = jax.jit(lambda p: quantize(p, spec))(jnp.array([-10.0, 3.7, 9.9]))
    np.testing.assert_array_equal(np.asarray(q), [[0, 0, 0], [2, 3, 1], [3, 4, 1]])
    np.testing.assert_allclose(np.asarray(dequantize(q, spec)), [-10.0, 3.5, 9.5])


def test_velocity_codes_are_optional_and_appended():
    cfg = load_config(f"{ROOT}/configs/gpd_paper.py", ["--config.model.velocity_inputs=true"]).model
    vt = AgentTokenizer.from_config(cfg)
    plain = AgentTokenizer.from_config(load_config(f"{ROOT}/configs/gpd_paper.py").model)
    assert vt.velocity.bins == (100, 20)
    assert vt.dim == plain.dim + 2 * 2 * cfg.velocity_code_dim
    xy, hd = jnp.array([[1.5, -2.0]]), jnp.array([0.3])
    a = vt.encode(xy, hd, jnp.array([[12.0, -0.5]]))
    b = vt.encode(xy, hd, jnp.array([[12.0, -0.55]]))
    np.testing.assert_allclose(a[..., : plain.dim], plain.encode(xy, hd))
    assert not np.allclose(a, b)
    with pytest.raises(ValueError, match="velocity"):
        vt.encode(xy, hd)
