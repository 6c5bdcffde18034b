"""Careless inputs get one line naming the problem and exit status 2, never a traceback: damaged parameter archives
(models, map tokenizers), config files and overrides that cannot be loaded, bad data at the start of training.

No JAX compilation: config errors fail before any model is built, the stages' trainers are replaced where the real
failure would need a model, and the one subprocess (rollout.py on a damaged model) fails while reading its file."""

import importlib.util
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _import_train():
    spec = importlib.util.spec_from_file_location("train_cli_under_test", os.path.join(ROOT, "train.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


train = _import_train()


def run_train(capsys, *argv) -> tuple[int, str, str]:
    rc = train.main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def assert_one_line_error(rc: int, err: str, *named: str) -> str:
    assert rc == 2, err
    assert "Traceback" not in err
    lines = err.strip("\n").split("\n")
    assert len(lines) == 1 and lines[0].startswith("train.py: "), err
    for s in named:
        assert s in lines[0], (s, lines[0])
    return lines[0]


def shipped(name: str) -> str:
    """A shipped model's folder (`gpd_jax.zoo`)."""
    from gpd_jax import zoo

    return zoo.resolve(name)


def truncated_copy(src_dir: str, dst_dir, keep: float = 0.5) -> str:
    """`src_dir` copied to `dst_dir` with its params.npz cut to `keep` of its size (an interrupted download)."""
    dst = shutil.copytree(src_dir, dst_dir, ignore=shutil.ignore_patterns("eval", "*.md", "*.json", "checkpoints"))
    shutil.copy(os.path.join(src_dir, "config.json"), dst)
    npz = os.path.join(dst, "params.npz")
    with open(npz, "r+b") as f:
        f.truncate(int(os.path.getsize(npz) * keep))
    return npz


# ------------------------------------------------------------------------------------ parameter archives
def test_truncated_map_tokenizer_params_raise_a_value_error_naming_the_file(tmp_path):
    from gpd_jax.map_tokenizer import load_tokenizer

    npz = truncated_copy(shipped("map_tokenizer"), tmp_path / "tok")
    with pytest.raises(ValueError) as e:
        load_tokenizer(str(tmp_path / "tok"))
    assert npz in str(e.value) and "not a readable parameter archive" in str(e.value)
    assert "\n" not in str(e.value)


class _Boom:
    """Pickled into an archive: unpickling it would create a file (it must never happen)."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.mark.parametrize("case", ["empty", "truncated", "not_zip", "npy", "pickled", "strings", "directory"])
def test_damaged_archives_raise_a_value_error_naming_the_file_and_run_nothing(tmp_path, case):
    from gpd_jax.fsutil import load_params_npz, read_params_npz, save_params_npz

    template = {"dense": {"kernel": np.zeros((3, 2), np.float32), "bias": np.zeros(2, np.float32)}}
    path = str(tmp_path / "params.npz")
    marker = str(tmp_path / "pickle_ran")
    if case == "empty":
        open(path, "wb").close()
    elif case == "truncated":
        save_params_npz(path, template)
        with open(path, "r+b") as f:
            f.truncate(os.path.getsize(path) // 2)
    elif case == "not_zip":
        with open(path, "w") as f:
            f.write("<html>404 not found</html>\n")
    elif case == "npy":
        with open(path, "wb") as f:
            np.save(f, np.zeros(3))
    elif case == "pickled":
        np.savez(path, x=np.array([_Boom(marker)], dtype=object))
        live = str(tmp_path / "live.npz")  # the payload is live: loading with pickles allowed runs it
        np.savez(live, x=np.array([_Boom(marker + "_live")], dtype=object))
        with np.load(live, allow_pickle=True) as z:
            z["x"]
        assert os.path.exists(marker + "_live")
    elif case == "strings":
        np.savez(path, **{"dense/kernel": np.array(["a", "b"]), "dense/bias": np.zeros(2, np.float32)})
    elif case == "directory":
        os.makedirs(path)
    for read in (read_params_npz, lambda p: load_params_npz(p, template)):
        with pytest.raises(ValueError) as e:
            read(path)
        msg = str(e.value)
        assert msg.startswith(f"{path}: not a readable parameter archive ("), msg
        assert "\n" not in msg
    assert not os.path.exists(marker)


def test_a_missing_archive_is_file_not_found_naming_it(tmp_path):
    from gpd_jax.fsutil import read_params_npz

    with pytest.raises(FileNotFoundError, match="nope.npz"):
        read_params_npz(str(tmp_path / "nope.npz"))


def test_archives_of_another_model_name_the_file_and_the_keys(tmp_path):
    from gpd_jax.fsutil import load_params_npz, save_params_npz

    template = {"dense": {"kernel": np.zeros((3, 2), np.float32), "bias": np.zeros(2, np.float32)}}
    path = str(tmp_path / "params.npz")
    save_params_npz(path, {"dense": {"kernel": np.ones((4, 2), np.float32), "scale": np.ones(2, np.float32)}})
    with pytest.raises(ValueError) as e:
        load_params_npz(path, template)
    msg = str(e.value)
    assert msg.startswith(f"{path} does not match the model of its config")
    assert "missing 1 (dense/bias)" in msg and "dense/kernel: stored (4, 2), model (3, 2)" in msg
    assert "unexpected 1 (dense/scale)" in msg
    # and a matching archive loads, in the template's dtypes
    save_params_npz(path, template, cast=lambda k, a: a.astype(np.float16))
    out = load_params_npz(path, template)
    assert out["dense"]["kernel"].dtype == np.float32 and out["dense"]["kernel"].shape == (3, 2)


def test_rollout_on_a_truncated_model_prints_one_line_and_exits_2(tmp_path):
    """A copy of the shipped gpd_maps with half its params.npz, on a valid store (the store and the arguments are
    checked before the model loads): loading the model is what fails."""
    from data_fixtures import write_small_store

    model = tmp_path / "model"
    npz = truncated_copy(shipped("gpd_maps"), model)  # its tokenizer is found by name
    data = str(tmp_path / "store")
    write_small_store(data, n_shards=1, per_shard=1, split="test")
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, os.path.join(ROOT, "rollout.py"), "--checkpoint", str(model), "--data", data,
                        "--out", str(out), "--scenarios", "1", "--no-progress"],
                       capture_output=True, text=True, cwd=str(tmp_path), timeout=300,
                       env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr
    lines = p.stderr.strip("\n").split("\n")
    assert len(lines) == 1, p.stderr
    assert npz in lines[0] and "not a readable parameter archive" in lines[0], lines[0]
    assert not out.exists()


# ---------------------------------------------------------------------------------- train.py config errors
GPD_TINY = os.path.join(ROOT, "configs", "gpd_tiny.py")
MAP_TOKENIZER_TINY = os.path.join(ROOT, "configs", "map_tokenizer.py:tiny")


def test_unknown_override_field(capsys, tmp_path):
    rc, _, err = run_train(capsys, "--config", GPD_TINY, "--workdir", str(tmp_path), "--config.train.stpes=5")
    line = assert_one_line_error(rc, err, "--config.train.stpes=5", "train.stpes")
    assert line.startswith("train.py: error: override "), line  # KeyError's quotes are not printed around the message


def test_missing_config_file(capsys, tmp_path):
    rc, _, err = run_train(capsys, "--config", "configs/nope.py", "--workdir", str(tmp_path))
    assert_one_line_error(rc, err, "configs/nope.py", "not found")


def test_override_of_the_wrong_type(capsys, tmp_path):
    rc, _, err = run_train(capsys, "--config", GPD_TINY, "--workdir", str(tmp_path), "--config.train.steps=five")
    assert_one_line_error(rc, err, "--config.train.steps=five")
    rc, _, err = run_train(capsys, "--config", GPD_TINY, "--workdir", str(tmp_path), "--config.train.steps=2.5")
    assert_one_line_error(rc, err, "--config.train.steps=2.5", "expected int")


def test_override_without_a_value(capsys, tmp_path):
    rc, _, err = run_train(capsys, "--config", GPD_TINY, "--workdir", str(tmp_path), "--config.train.steps")
    assert_one_line_error(rc, err, "--config.train.steps")


@pytest.mark.parametrize("name,text,named", [
    ("syntax.py", "def get_config(:\n    pass\n", ["syntax.py:1", "SyntaxError"]),
    ("no_get_config.py", '"""A config without get_config."""\nX = 1\n', ["no_get_config.py", "get_config"]),
    ("raises.py", "def get_config():\n    return undefined_name\n", ["raises.py:2", "NameError", "undefined_name"]),
    ("key.py", "def get_config():\n    return {}['model']\n", ["key.py:2", "KeyError"]),
    ("config.json", "{}\n", ["config.json", "not a python config file"]),
])
def test_config_files_that_cannot_load(capsys, tmp_path, name, text, named):
    path = tmp_path / name
    path.write_text(text)
    rc, _, err = run_train(capsys, "--config", str(path), "--workdir", str(tmp_path / "w"))
    assert_one_line_error(rc, err, *named)
    assert not (tmp_path / "w").exists()


def test_a_config_variant_that_does_not_exist(capsys, tmp_path):
    path = tmp_path / "variants.py"
    path.write_text("def get_config(arg):\n    if arg != 'a':\n        raise KeyError(f'no variant {arg!r}')\n"
                    "    return {}\n")
    rc, _, err = run_train(capsys, "--config", f"{path}:b", "--workdir", str(tmp_path / "w"))
    line = assert_one_line_error(rc, err, "variants.py:3", "no variant 'b'")
    assert "\"no variant" not in line


def test_a_config_of_no_known_stage(capsys, tmp_path):
    path = tmp_path / "stage.py"
    path.write_text("import ml_collections\ndef get_config():\n    return ml_collections.ConfigDict({'stage': 'x'})\n")
    rc, _, err = run_train(capsys, "--config", str(path), "--workdir", str(tmp_path / "w"))
    assert_one_line_error(rc, err, "stage.py", "'x'")


def test_bad_arguments_are_one_line_too(capsys, tmp_path):
    rc, _, err = run_train(capsys, "--config", GPD_TINY)
    assert_one_line_error(rc, err, "--workdir")
    rc, _, err = run_train(capsys, "--config", GPD_TINY, "--workdir", str(tmp_path), "--bogus")
    assert_one_line_error(rc, err, "--bogus")


# ------------------------------------------------------------------------------ train.py errors at the start
def test_gpd_stage_without_data(capsys, tmp_path):
    rc, _, err = run_train(capsys, "--config", GPD_TINY, "--workdir", str(tmp_path / "w"),
                           f"--config.data.dir={tmp_path / 'no_data'}")
    assert_one_line_error(rc, err, str(tmp_path / "no_data"))


@pytest.mark.parametrize("error", ["data", "value", "missing"])
def test_map_tokenizer_stage_reports_start_errors_like_the_gpd_stage(capsys, tmp_path, monkeypatch, error):
    """The real failure (a data dir without shards) comes after the tokenizer's model is built (tens of seconds on
    a CPU): the trainer is replaced by one raising what it raises."""
    import gpd_jax.training.map_tokenizer as stage
    from gpd_jax.data.errors import DataError

    bad = str(tmp_path / "no_data")

    def fake(config, workdir, stop_after=None):
        assert config.data.dir == bad and workdir == str(tmp_path / "w")
        if error == "data":
            raise DataError(bad, "no complete shards in split 'train'")
        if error == "value":
            raise ValueError(f"train.decoder_only trains the decoder of an existing tokenizer:\nset {bad}")
        raise FileNotFoundError(f"{bad} is not a map-tokenizer checkpoint (no config.json)")

    monkeypatch.setattr(stage, "train_and_evaluate", fake)
    rc, _, err = run_train(capsys, "--config", MAP_TOKENIZER_TINY,
                           "--workdir", str(tmp_path / "w"), f"--config.data.dir={bad}")
    assert_one_line_error(rc, err, bad)


def test_valid_inputs_still_train(capsys, tmp_path, monkeypatch):
    import gpd_jax.training.loop as loop
    import gpd_jax.training.map_tokenizer as stage

    seen = {}
    monkeypatch.setattr(loop, "train_and_evaluate",
                        lambda config, workdir, stop_after=None: seen.update(gpd=(config.train.steps, workdir,
                                                                                  stop_after)))
    monkeypatch.setattr(stage, "train_and_evaluate",
                        lambda config, workdir, stop_after=None: seen.update(tok=(config.train.num_steps, workdir)))
    rc, out, err = run_train(capsys, "--config", GPD_TINY, "--workdir", "w1", "--config.train.steps=7",
                             "--stop-after", "3")
    assert (rc, err) == (0, "") and seen["gpd"] == (7, "w1", 3)
    rc, out, err = run_train(capsys, "--config", MAP_TOKENIZER_TINY,
                             "--workdir", "w2", "--config.train.num_steps=9")
    assert (rc, err) == (0, "") and seen["tok"] == (9, "w2")


# ------------------------------------------------------------------------------------------ train.py --help
def _first_docstring_line(path: str) -> str:
    import ast

    with open(path) as f:
        return (ast.get_docstring(ast.parse(f.read())) or "").strip().splitlines()[0]


def test_help_lists_the_overrides_and_the_config_files(capsys):
    rc, out, err = run_train(capsys, "--help")
    assert rc == 0 and err == ""
    assert "--config.a.b=value" in out
    names = sorted(n for n in os.listdir(os.path.join(ROOT, "configs")) if n.endswith(".py"))
    assert names
    listed = {line.split()[0]: line for line in out.splitlines() if line.startswith("  ") and line.split()
              and line.split()[0].endswith(".py")}
    assert sorted(listed) == names
    for n in names:
        assert _first_docstring_line(os.path.join(ROOT, "configs", n)) in listed[n], n


def test_help_says_when_the_configs_folder_is_absent(capsys, tmp_path, monkeypatch):
    from gpd_jax.training import command

    monkeypatch.setattr(command, "CONFIGS_DIR", str(tmp_path / "configs"))
    rc, out, _ = run_train(capsys, "--help")
    assert rc == 0 and f"{tmp_path / 'configs'} does not exist" in out


# ------------------------------------------------------------------------- every command line, before JAX
POISON = "raise ImportError('jax was imported before the arguments were checked')\n"


def run_cli(tmp_path, argv, cwd=None, **kw) -> subprocess.CompletedProcess:
    """`gpd-jax ARGV` in a subprocess whose `import jax` fails: what refuses must refuse before importing it."""
    poison = tmp_path / "poison"
    (poison / "jax").mkdir(parents=True, exist_ok=True)
    (poison / "jax" / "__init__.py").write_text(POISON)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(poison), ROOT]), "JAX_PLATFORMS": "cpu"}
    return subprocess.run([sys.executable, "-m", "gpd_jax.cli", *argv], capture_output=True, text=True,
                          cwd=str(cwd or tmp_path), env=env, timeout=60, **kw)


# (argv with {tmp} for the test's folder, what the one line names); {tmp}/afile is a file, nothing else exists
CARELESS = [
    (["eval", "--data", "{tmp}/d", "--out", "{tmp}/o", "--batch", "0"], ["gpd-jax eval: error:", "--batch"]),
    (["eval", "--data", "{tmp}/d", "--out", "{tmp}/afile/o"], ["--out", "{tmp}/afile is a file"]),
    (["eval", "--data", "{tmp}/d", "--out", "{tmp}/afile"], ["--out {tmp}/afile", "not a directory"]),
    (["eval", "--data", "{tmp}/d", "--out", "{tmp}/o", "--temperature", "-1"], ["--temperature"]),
    (["eval", "--data", "{tmp}/d", "--out", "{tmp}/o", "--top-p", "2"], ["--top-p"]),
    (["eval", "--data", "{tmp}/d", "--out", "{tmp}/o", "--horizons", "0"], ["--horizons"]),
    (["eval", "--data", "{tmp}/d", "--out", "{tmp}/o", "--render", "-1"], ["--render"]),
    (["eval", "--data", "{tmp}/d", "--out", "{tmp}/o", "--prompt", "{tmp}/nope.json"], ["--prompt", "nope.json"]),
    (["train", "--config", GPD_TINY, "--workdir", "{tmp}/afile"], ["--workdir {tmp}/afile", "not a directory"]),
    (["train", "--config", GPD_TINY, "--workdir", "{tmp}/afile/w"], ["--workdir", "{tmp}/afile is a file"]),
    (["train", "--config", GPD_TINY, "--workdir", "{tmp}/w", "--config.train.batch_size=0"],
     ["--config.train.batch_size=0", ">= 1"]),
    (["train", "--config", GPD_TINY, "--workdir", "{tmp}/w", "--config.train.log_every=-5"], ["train.log_every"]),
    (["train", "--config", GPD_TINY, "--workdir", "{tmp}/w", "--stop-after", "0"], ["--stop-after"]),
    (["train", "--config", GPD_TINY, "--workdir", "{tmp}/w", "--config.train.stpes=5"], ["train.stpes"]),
    (["data", "build", "--out", "{tmp}/o", "--scenarios", "0"], ["gpd-jax data: error:", "--scenarios"]),
    (["data", "build", "--out", "{tmp}/afile/o"], ["--out", "{tmp}/afile is a file"]),
    (["data", "build", "--out", "{tmp}/o", "--workers", "0"], ["--workers"]),
    (["data", "inspect", "{tmp}/d", "--json", "{tmp}/afile/s.json"], ["--json", "{tmp}/afile"]),
    (["data", "sensor", "{tmp}/d", "--out", "{tmp}/o", "--gap-rate", "2"], ["--gap-rate"]),
    (["data", "near-duplicates", "--eval", "a", "--reference", "b", "--tol", "-1"], ["--tol"]),
    (["tokenizer", "encode", "--data", "{tmp}/d", "--frame-stride", "0"], ["gpd-jax tokenizer", "--frame-stride"]),
    (["tokenizer", "export", "--workdir", "{tmp}/w", "--out", "{tmp}/afile/x"], ["--out", "{tmp}/afile is a file"]),
    (["plan", "evaluate", "--data", "{tmp}/d", "--out", "{tmp}/afile/p"], ["gpd-jax plan", "--out"]),
    (["plan", "bench", "--data", "{tmp}/d", "--batch", "0"], ["--batch"]),
    (["compare", "{tmp}/a", "--resamples", "0"], ["gpd-jax: error:", "--resamples"]),
    (["compare", "{tmp}/a", "--level", "2"], ["--level"]),
    (["models", "extra"], ["gpd-jax models", "extra"]),
    (["nonsense"], ["unknown command 'nonsense'"]),
]


@pytest.mark.parametrize("argv,named", CARELESS, ids=[" ".join(a[:2]) + f" #{i}" for i, (a, _) in enumerate(CARELESS)])
def test_every_command_refuses_careless_input_in_one_line_before_jax_and_writes_nothing(tmp_path, argv, named):
    (tmp_path / "afile").write_text("a file where a folder is expected\n")
    before = sorted(os.listdir(tmp_path))
    p = run_cli(tmp_path, [a.replace("{tmp}", str(tmp_path)) for a in argv])
    assert p.returncode == 2, (p.returncode, p.stderr[-2000:])
    assert "Traceback" not in p.stderr, p.stderr[-2000:]
    lines = p.stderr.strip("\n").split("\n")
    assert len(lines) == 1, p.stderr
    for s in named:
        assert s.replace("{tmp}", str(tmp_path)) in lines[0], (s, lines[0])
    assert sorted(n for n in os.listdir(tmp_path) if n != "poison") == before  # nothing written
    assert (tmp_path / "afile").is_file()


@pytest.mark.parametrize("argv,usage", [(["plan", "evaluate", "--help"], "usage: gpd-jax plan evaluate "),
                                        (["data", "build", "--help"], "usage: gpd-jax data build "),
                                        (["tokenizer", "--help"], "usage: gpd-jax tokenizer "),
                                        (["train", "--help"], "usage: gpd-jax train ")])
def test_usage_names_the_program_typed(tmp_path, argv, usage):
    p = run_cli(tmp_path, argv)
    assert p.returncode == 0 and p.stdout.startswith(usage), p.stdout[:300] + p.stderr[-1000:]


def test_train_errors_at_the_start_leave_no_workdir(capsys, tmp_path):
    rc, _, err = run_train(capsys, "--config", GPD_TINY, "--workdir", str(tmp_path / "w"),
                           f"--config.data.dir={tmp_path / 'no_data'}")
    assert_one_line_error(rc, err, str(tmp_path / "no_data"))
    assert not (tmp_path / "w").exists()


def test_a_damaged_npy_header_is_named_without_numpy_pickle_advice(tmp_path):
    from data_fixtures import write_small_store

    from gpd_jax.data.errors import DataError
    from gpd_jax.data.store import Shard, shard_dir

    data = str(tmp_path / "store")
    write_small_store(data, n_shards=1, per_shard=1, split="test")
    shard = shard_dir(data, "test", 0)
    f = os.path.join(shard, "xy.npy")
    raw = open(f, "rb").read()
    i = raw.index(b"'<f4'")
    with open(f, "wb") as fh:  # the same size, a header that declares Python objects
        fh.write(raw[:i] + b"'|O' " + raw[i + 5:])
    with pytest.raises(DataError) as e:
        Shard(shard)
    msg = str(e.value)
    assert f in msg and "Python objects" in msg and "allow_pickle" not in msg and "\n" not in msg


# ------------------------------------------------------------------------------------------------ Ctrl-C
def _interrupted_line(err: str, prog: str) -> str:
    assert "Traceback" not in err, err[-3000:]
    lines = [ln for ln in err.replace("\r", "\n").split("\n") if "interrupted" in ln]
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: interrupted; "), err[-3000:]
    assert "run the same command again: " in lines[0], lines[0]
    return lines[0]


def test_ctrl_c_ends_a_command_stuck_past_its_grace_with_one_line_and_130(tmp_path):
    """The watchdog: work that does not unwind on Ctrl-C (here it swallows KeyboardInterrupt, as native code
    that holds the main thread would) still ends within the grace period, with the one line and status 130."""
    import signal
    import time

    code = ("import sys, time\nfrom gpd_jax.cliargs import run_command\n"
            "def work():\n    print('ready', flush=True)\n    while True:\n        try:\n            time.sleep(0.05)\n"
            "        except KeyboardInterrupt:\n            pass\n"
            "sys.exit(run_command('stuck', work, kept='nothing is kept', grace_s=1.0))\n")
    p = subprocess.Popen([sys.executable, "-c", code, "--flag"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, cwd=ROOT)
    assert p.stdout.readline().strip() == "ready"
    t = time.monotonic()
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=30)
    assert p.returncode == 130 and time.monotonic() - t < 10, (p.returncode, err)
    line = _interrupted_line(err, "stuck")
    assert "nothing is kept" in line and line.endswith("-c --flag"), line


def test_ctrl_c_in_a_data_build_stops_its_workers_says_what_is_kept_and_exits_130(tmp_path):
    """A SUMO build with two worker processes: SIGINT to the command (as Ctrl-C sends it to the whole group)
    stops it within seconds, with one line naming the store and the command that resumes, and no worker left."""
    import signal
    import time

    out = tmp_path / "store"
    argv = [sys.executable, "-m", "gpd_jax.cli", "data", "build", "--source", "sumo", "--traffic", "legacy",
            "--out", str(out), "--scenarios", "4", "--per-job", "2", "--workers", "2", "--seed", "5"]
    p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=str(tmp_path),
                         start_new_session=True)
    deadline = time.monotonic() + 120
    while not (out / "_jobs" / "settings.json").exists() and time.monotonic() < deadline and p.poll() is None:
        time.sleep(0.2)
    assert p.poll() is None, p.communicate()[1][-3000:]
    time.sleep(2.0)  # the workers are simulating
    t = time.monotonic()
    os.killpg(p.pid, signal.SIGINT)
    _, err = p.communicate(timeout=60)
    took = time.monotonic() - t
    assert p.returncode == 130, err[-3000:]
    assert took < 15, took
    line = _interrupted_line(err, "gpd-jax data")
    assert f"kept in {out}" in line and f"data build --source sumo --traffic legacy --out {out}" in line, line
    assert "leaked semaphore" not in err
    # no worker (or SUMO) of the session outlives the command; a dead one that init has not reaped yet (a zombie,
    # "Z") is not running, and one caught in its last moments of exiting (listed as "[python]", its memory already
    # gone) is given a few seconds to finish
    deadline = time.monotonic() + 5
    while True:
        ps = subprocess.run(["ps", "-o", "pid=,stat=,args=", "-s", str(p.pid)], capture_output=True, text=True).stdout
        left = [line for line in ps.splitlines() if line.split() and "Z" not in line.split()[1]]
        if not left or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert not left, left


def test_training_ends_by_saying_where_it_stopped_and_where_it_exported(capsys, tmp_path):
    from gpd_jax.config import load_config
    from gpd_jax.training.command import say_where_it_stopped

    config = load_config(GPD_TINY)  # 300 steps
    work = tmp_path / "w"
    (work / "checkpoints" / "100").mkdir(parents=True)
    say_where_it_stopped(config, str(work))
    assert capsys.readouterr().out == "stopped at step 100 of 300; rerun the same command to resume\n"
    (work / "checkpoints" / "300").mkdir()
    (work / "export").mkdir()
    say_where_it_stopped(config, str(work))
    assert capsys.readouterr().out == f"finished at step 300; exported to {work / 'export'}\n"
