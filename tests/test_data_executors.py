"""The store builder's executors: a SUMO build on Ray tasks (a local Ray instance, loopback only) writes the store a
local build writes, also when a job fails once and is retried; the local executor and bad executor input."""

import dataclasses
import json
import os

import numpy as np
import pytest

from gpd_jax.data import loader, store
from gpd_jax.data.errors import DataError
from gpd_jax.data.executors import FAIL_ONCE_ENV, InjectedFailure, LocalExecutor, make_executor, run_all
from gpd_jax.data.sources import sumo, sumo_traffic

SIM = sumo_traffic.SimConfig(warmup_s=60.0, record_s=30.0)
BUILD = dict(num_scenarios=4, seed=5, per_job=2, sim_cfg=SIM)  # 2 jobs (2 samples each) on 2 generated networks


class Job:
    def __init__(self, index):
        self.index = index


def _square(job):
    return job.index * job.index


def _scenes(out: str) -> dict:
    """Every split's samples (every stored array, ids and locations) and the job summaries without wall times."""
    got = {}
    for split in store.list_splits(out):
        got[split] = loader.load_split(out, split)
        for j in store.shard_indices(out, split):
            got[f"{split}/{j}"] = store.Shard(store.shard_dir(out, split, j)).meta  # ids, locations, settings
    jobs = {}
    for name in sorted(os.listdir(os.path.join(out, "_jobs"))):
        if name.startswith("job_"):
            with open(os.path.join(out, "_jobs", name)) as f:
                rec = json.load(f)
            rec.pop("wall_s", None)
            jobs[name] = rec
    return got, jobs


def _assert_same_store(a: str, b: str) -> None:
    (sa, ja), (sb, jb) = _scenes(a), _scenes(b)
    assert sa.keys() == sb.keys() and ja == jb
    for k in sa:
        if isinstance(sa[k], dict):
            assert sa[k] == sb[k], k
            continue
        for f in dataclasses.fields(sa[k]):
            name = f.name
            x, y = getattr(sa[k], name), getattr(sb[k], name)
            if x is None:
                assert y is None, name
            else:
                np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=f"{k} {name}")
    ma, mb = (store.read_manifest(d) for d in (a, b))
    for m in (ma, mb):
        for key in ("build_wall_s", "build_wall_s_all_invocations"):
            m["build"].pop(key)
        m["build"]["near_duplicate_check"].pop("wall_s")
    assert ma == mb


def test_local_executor_runs_every_item_and_honours_the_test_failure(tmp_path, monkeypatch):
    jobs = [Job(i) for i in range(5)]
    assert run_all(LocalExecutor(1), _square, jobs) == [0, 1, 4, 9, 16]
    assert run_all(LocalExecutor(2), _square, jobs) == [0, 1, 4, 9, 16]  # spawned processes, any order
    monkeypatch.setenv(FAIL_ONCE_ENV, f"3:{tmp_path / 'fail'}")
    with pytest.raises(InjectedFailure):  # the local executor does not retry: the build stops (and resumes)
        run_all(LocalExecutor(1), _square, jobs)
    assert run_all(LocalExecutor(1), _square, jobs) == [0, 1, 4, 9, 16]  # once only
    with pytest.raises(DataError, match="--address is for --executor ray"):
        make_executor("local", 2, "127.0.0.1:6379")


@pytest.fixture(scope="module")
def local_build(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("local") / "store")
    sumo.build_sumo(out, workers=1, **BUILD)
    return out


@pytest.mark.multiprocess
def test_ray_build_equals_local_build_with_a_job_retried(local_build, tmp_path, monkeypatch):
    # Ray's servers listen on loopback only when it takes the node for a single-machine one (its switch for
    # Windows and macOS; read at import, and by Ray's own processes from the environment)
    monkeypatch.setenv("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    ray = pytest.importorskip("ray")
    from ray._private import ray_constants

    from gpd_jax.data.executors import RayExecutor

    monkeypatch.setattr(ray_constants, "ENABLE_RAY_CLUSTER", False)
    monkeypatch.setenv(FAIL_ONCE_ENV, f"1:{tmp_path / 'fail'}")  # job 1 raises the first time it runs
    out = str(tmp_path / "ray_store")
    try:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False,
                 runtime_env={"env_vars": {FAIL_ONCE_ENV: os.environ[FAIL_ONCE_ENV]}})
        assert [n["NodeManagerAddress"] for n in ray.nodes()] == ["127.0.0.1"]
        man = sumo.build_sumo(out, workers=2, executor=RayExecutor(max_retries=2), **BUILD)
    finally:
        ray.shutdown()
    assert os.path.isfile(tmp_path / "fail" / "failed_1")  # it did fail once, and was run again
    assert man["num_samples"] == store.read_manifest(local_build)["num_samples"] > 0
    _assert_same_store(local_build, out)


def _sigint_blocked_at_init():
    import signal

    from gpd_jax import interrupt
    os.environ["GPD_JAX_TEST_BLOCKED_AT_INIT"] = str(signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, []))
    interrupt.quiet_worker()


def _sigint_state():
    import signal
    return os.environ["GPD_JAX_TEST_BLOCKED_AT_INIT"], signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, [])


def test_pool_workers_start_with_ctrl_c_blocked_until_their_quiet_handler_is_in_place():
    """A Ctrl-C while a worker's interpreter starts (its `site` import, before any handler) would print a
    traceback per worker: workers are spawned with SIGINT blocked and `quiet_worker` unblocks it."""
    import signal

    from gpd_jax import interrupt
    with interrupt.worker_pool(1, initializer=_sigint_blocked_at_init) as ex:
        at_init, in_job = ex.submit(_sigint_state).result()
    assert (at_init, in_job) == ("True", False)
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, [])  # the parent's mask is restored
