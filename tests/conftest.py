"""Shared fixtures: the tiny GPD config and model (built once per session to keep compiles few)."""

import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# The decode attention path is pinned for the tests (and the command lines they start): "auto" would time every
# candidate at each new shape on a fresh machine, which costs CI minutes and tests nothing about results. The
# tests of "auto" itself (tests/test_attention.py, tests/test_bench.py) unset it; the native kernel has its own
# equality tests.
os.environ.setdefault("GPD_JAX_DECODE_ATTENTION", "xla")

# The suite is bound by XLA compile time on a CPU (tiny programs, many shapes): the tests compile with LLVM's
# backend optimisation off, which cut the compile-heavy tests by about a third (the shipped sampling model's test
# 284 -> 191 s, the tokenizer's train / resume test 68 -> 47 s, back to back on the 2-core CI machine). The programs
# are the same; only their machine code is less optimised. Flags already set are kept.
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()

# One XLA compilation cache for the whole test session: the xdist workers and the command lines the tests start
# (benchmarks, the data-parallel step, the CLIs) compile many of the same programs (the tiny model's steps and
# rollouts, the shipped model's rollout); each is compiled once and read back by the other processes. It starts
# empty in every session (a fresh temporary folder, removed at the end by the process that made it), so CI times
# a cold run and no test reads executables from an earlier checkout. An already set JAX_COMPILATION_CACHE_DIR is
# kept (the xdist workers inherit the controller's).
_OWN_XLA_CACHE = None
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    import tempfile

    _OWN_XLA_CACHE = tempfile.mkdtemp(prefix="gpd-jax-test-xla-cache-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _OWN_XLA_CACHE
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.2")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
    if "jax" in sys.modules:  # a plugin imported jax before this file: its config has read the environment
        import jax

        jax.config.update("jax_compilation_cache_dir", _OWN_XLA_CACHE)
        jax.config.update("jax_persistent_cache_min_compile_time_secs",
                          float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))


def pytest_unconfigure(config):
    if _OWN_XLA_CACHE is not None and not hasattr(config, "workerinput"):
        import shutil

        shutil.rmtree(_OWN_XLA_CACHE, ignore_errors=True)


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
