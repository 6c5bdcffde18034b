"""Shared fixtures: the tiny GPD config and model (built once per session to keep compiles few)."""

import os

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# The decode attention path is pinned for the tests (and the command lines they start): "auto" would time every
# candidate at each new shape on a fresh machine, which costs CI minutes and tests nothing about results. The
# tests of "auto" itself (tests/test_attention.py, tests/test_bench.py) unset it; the native kernel has its own
# equality tests.
os.environ.setdefault("GPD_JAX_DECODE_ATTENTION", "xla")


@pytest.fixture(scope="session")
def tiny_config():
    from gpd_jax.config import load_config

    return load_config(os.path.join(ROOT, "configs", "gpd_tiny.py:test"))


@pytest.fixture(scope="session")
def tiny_model(tiny_config):
    from flax import nnx

    from gpd_jax.model import GPD

    return GPD(tiny_config.model, nnx.Rngs(0))


@pytest.fixture(scope="session")
def tiny_scenes(tiny_config):
    from gpd_jax.synthetic import synthetic_scenes

    m = tiny_config.model
    return synthetic_scenes(0, 3, m.num_frames, m.num_history, m.num_agents, m.num_map_tokens, m.codebook_size)
