"""Two processes on this machine (JAX's multi-controller runtime over a loopback coordinator, CPU collectives):
training gives the parameters of one process on the same global batches, a killed two-process run resumes exactly
(also on another process count), an evaluation writes the figures of one process, and bad flags or an unreachable
coordinator are one line with exit status 2, not a hang."""

import json
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import ROOT
from test_train_loop import _store

pytestmark = pytest.mark.multiprocess

STEPS = 24  # of the killed run: the kill comes at its first checkpoint, long before the end
TASKS = "traffic_simulation,closed_loop,motion_planning"  # the tiny model has no map tokenizer
TIMEOUT_S = 420

CONFIG = """
import sys
sys.path.insert(0, {tests!r})
from test_train_loop import _config


def get_config():
    return _config({store!r}, eval_every=0, steps={steps}, checkpoint_every=4, log_every=4)
"""


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(devices: int = 1) -> dict:
    flags = os.environ.get("XLA_FLAGS", "")
    if devices > 1:
        flags += f" --xla_force_host_platform_device_count={devices}"
    return dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu", PYTHONUNBUFFERED="1")


class Procs:
    """Processes started together; every one still running is killed on exit (a failed test leaves none)."""

    def __init__(self):
        self.procs: list[subprocess.Popen] = []

    def start(self, argv: list[str], devices: int = 1) -> subprocess.Popen:
        p = subprocess.Popen([sys.executable, *argv], cwd=ROOT, env=_env(devices), stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, start_new_session=True)
        self.procs.append(p)
        return p

    def wait(self, timeout: float = TIMEOUT_S) -> list[tuple[int, str, str]]:
        deadline = time.monotonic() + timeout
        out = []
        for p in self.procs:
            o, e = p.communicate(timeout=max(1.0, deadline - time.monotonic()))
            out.append((p.returncode, o, e))
        self.procs = []
        return out

    def kill(self):
        for p in self.procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
        self.procs = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.kill()


def _cluster(port: int, n: int, i: int) -> list[str]:
    return ["--coordinator", f"127.0.0.1:{port}", "--num-processes", str(n), "--process-id", str(i),
            "--init-timeout", "120"]


def run_all(argvs: list[list[str]], devices: int = 1) -> list[tuple[int, str, str]]:
    with Procs() as procs:
        for argv in argvs:
            procs.start(argv, devices)
        res = procs.wait()
    for rc, o, e in res:
        assert rc == 0, (o[-2000:], e[-4000:])
    return res


def train(config: str, workdir: str, processes: int = 1, devices: int = 1, extra=()) -> None:
    """train.py on `processes` local processes (a loopback coordinator on a free port) of `devices` each."""
    argv = [os.path.join(ROOT, "train.py"), "--config", config, "--workdir", workdir, *extra]
    if processes == 1:
        run_all([argv], devices)
        return
    port = free_port()
    run_all([argv + _cluster(port, processes, i) for i in range(processes)], devices)


def params(workdir: str) -> list[np.ndarray]:
    import jax

    from gpd_jax.checkpoint import load_model

    return [np.asarray(x) for x in jax.tree.leaves(load_model(workdir).params)]


def assert_same_params(a: str, b: str) -> None:
    pa, pb = params(a), params(b)
    assert len(pa) == len(pb)
    for x, y in zip(pa, pb):
        np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-6 * max(1.0, float(np.abs(x).max())))


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """The tiny store and config of tests/test_train_loop.py, and the reference: one process with two devices
    (the global batch laid out as two processes lay it out), STEPS steps."""
    d = tmp_path_factory.mktemp("dist")
    store = _store(str(d / "store"))
    config = str(d / "tiny_dist.py")
    with open(config, "w") as f:
        f.write(CONFIG.format(tests=os.path.dirname(os.path.abspath(__file__)), store=store, steps=STEPS))
    ref = str(d / "one_process")
    train(config, ref, processes=1, devices=2)
    return d, store, config, ref


@pytest.fixture(scope="module")
def two_process_run(setup):
    d, _, config, _ = setup
    w = str(d / "two_processes")
    train(config, w, processes=2)
    return w


def test_two_processes_train_the_parameters_of_one(setup, two_process_run):
    _, _, _, ref = setup
    assert_same_params(ref, two_process_run)
    # one checkpoint folder, one export and one metrics log, written by process 0
    recs = [json.loads(x) for x in open(os.path.join(two_process_run, "metrics.jsonl"))]
    assert [r["step"] for r in recs if r["split"] == "train"] == list(range(4, STEPS + 1, 4))
    ref_recs = [json.loads(x) for x in open(os.path.join(ref, "metrics.jsonl"))]
    np.testing.assert_allclose([r["loss"] for r in recs], [r["loss"] for r in ref_recs], rtol=1e-6)
    assert_same_params(ref, os.path.join(two_process_run, "export"))


def test_killed_two_process_run_resumes_exactly_on_two_then_one_process(setup):
    d, _, config, ref = setup
    w = str(d / "killed")
    port = free_port()
    argv = [os.path.join(ROOT, "train.py"), "--config", config, "--workdir", w]
    first = os.path.join(w, "checkpoints", "4")
    with Procs() as procs:
        for i in range(2):
            procs.start(argv + _cluster(port, 2, i))
        deadline = time.monotonic() + TIMEOUT_S
        while not os.path.isdir(first) and time.monotonic() < deadline:  # orbax renames a step in when committed
            assert all(p.poll() is None for p in procs.procs), "a process ended before its first checkpoint"
            time.sleep(0.02)
        procs.kill()  # SIGKILL both, mid-run
    assert os.path.isdir(first)
    assert not os.path.isdir(os.path.join(w, "export")), "the run ended before it was killed"
    # restarted on two processes for 4 more steps, then finished on one process (two devices)
    port = free_port()
    res = run_all([argv + ["--stop-after", "4"] + _cluster(port, 2, i) for i in range(2)])
    resumed = [line for line in res[0][1].splitlines() if line.startswith("resumed")]
    assert resumed and int(resumed[0].split()[-1]) < STEPS, res[0][1][-2000:]
    train(config, w, processes=1, devices=2)
    assert_same_params(ref, w)


def test_two_process_evaluation_writes_the_figures_of_one(setup, two_process_run, tmp_path):
    _, store, _, _ = setup
    model = os.path.join(two_process_run, "export")
    argv = [os.path.join(ROOT, "rollout.py"), "--checkpoint", model, "--data", store, "--split", "val", "--batch", "2",
            "--tasks", TASKS, "--no-progress"]
    one, two = str(tmp_path / "one"), str(tmp_path / "two")
    sys.path.insert(0, ROOT)
    import rollout

    assert rollout.main(argv[1:] + ["--out", one]) == 0  # the one-process reference, in this process
    port = free_port()
    res = run_all([argv + ["--out", two] + _cluster(port, 2, i) for i in range(2)])
    assert "wrote" in res[0][1] and "wrote" not in res[1][1]  # process 0 writes, process 1 only rolls out
    a, b = (json.load(open(os.path.join(x, "metrics.json"))) for x in (one, two))
    assert a.pop("timing_s")["processes"] == 1 and b.pop("timing_s")["processes"] == 2
    assert a["scenarios"] == 4 and a == b
    with np.load(os.path.join(one, "scene_sums.npz")) as za, np.load(os.path.join(two, "scene_sums.npz")) as zb:
        assert za.files == zb.files
        for k in za.files:
            np.testing.assert_array_equal(za[k], zb[k])


def _one_line_error(rc: int, err: str, prog: str) -> str:
    assert rc == 2, err[-2000:]
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"{prog}: error: "), err[-2000:]
    return last


@pytest.mark.parametrize("flags, names", [
    (["--coordinator", "127.0.0.1", "--num-processes", "2", "--process-id", "0"], "--coordinator '127.0.0.1'"),
    (["--coordinator", "127.0.0.1:1234", "--num-processes", "2", "--process-id", "2"], "--process-id 2"),
    (["--coordinator", "127.0.0.1:1234", "--num-processes", "0", "--process-id", "0"], "--num-processes 0"),
    (["--coordinator", "127.0.0.1:1234"], "without --num-processes, --process-id"),
    (["--distributed", "--process-id", "0"], "--distributed"),
    (["--coordinator", "127.0.0.1:1234", "--num-processes", "2", "--process-id", "0", "--init-timeout", "0"],
     "--init-timeout 0"),
])
def test_bad_cluster_flags_are_one_line(flags, names, tmp_path, capsys):
    sys.path.insert(0, ROOT)
    import rollout

    rc = rollout.main(["--data", str(tmp_path), "--out", str(tmp_path / "o"), *flags])
    assert names in _one_line_error(rc, capsys.readouterr().err, "rollout.py")
    assert not os.path.exists(tmp_path / "o")


def test_unreachable_coordinator_and_wrong_count_time_out_with_one_line(setup, tmp_path):
    _, _, config, _ = setup
    argv = [os.path.join(ROOT, "train.py"), "--config", config, "--workdir", str(tmp_path / "w")]
    nobody, alone = free_port(), free_port()
    with Procs() as procs:
        # process 1 of a coordinator nobody runs; process 0 told of 2 processes when it is the only one
        procs.start(argv + ["--coordinator", f"127.0.0.1:{nobody}", "--num-processes", "2", "--process-id", "1",
                            "--init-timeout", "3"])
        procs.start(argv + ["--coordinator", f"127.0.0.1:{alone}", "--num-processes", "2", "--process-id", "0",
                            "--init-timeout", "3"])
        t0 = time.monotonic()
        res = procs.wait(timeout=120)
    assert time.monotonic() - t0 < 100
    for (rc, _, err), port, who in zip(res, (nobody, alone), ("this one 1", "this one 0")):
        line = _one_line_error(rc, err, "train.py")
        assert f"coordinator 127.0.0.1:{port}, 2 processes, {who}" in line and "--init-timeout 3 s" in line
    assert not os.path.exists(tmp_path / "w")


def test_gathered_trees_round_trip_without_pickle():
    from gpd_jax.distributed import decode_tree, encode_tree

    tree = {"a": {"b": np.arange(6.0).reshape(2, 3), "empty": {}}, "n": np.int64(3), "s": np.str_("scene/7"),
            "c": {"d": np.zeros((0, 4), np.float32)}}
    back = decode_tree(encode_tree(tree))
    assert back.keys() == tree.keys() and back["a"]["empty"] == {} and str(back["s"]) == "scene/7"
    np.testing.assert_array_equal(back["a"]["b"], tree["a"]["b"])
    assert back["c"]["d"].shape == (0, 4) and back["c"]["d"].dtype == np.float32 and int(back["n"]) == 3
    with pytest.raises(ValueError, match="cannot be sent"):
        encode_tree({"a/b": 1})
    with pytest.raises(ValueError, match="Object arrays"):
        decode_tree(encode_tree({"o": np.array([{"x": 1}], dtype=object)}))
