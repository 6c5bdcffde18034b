"""Bad build input ends in a clear error (exit status 2, naming the argument or file), never a traceback, and
leaves nothing behind that a corrected retry trips over."""

import os

import pytest

from gpd_jax.data import jobs, store
from gpd_jax.data.__main__ import main
from gpd_jax.data.errors import DataError
from gpd_jax.data.sources import nuplan, sumo


@pytest.mark.parametrize("content", ["<net><edge id='a'><lane", "<routes></routes>\n", "\x1f\x8b garbage"])
def test_bad_network_is_refused_before_anything_runs(tmp_path, capsys, content):
    bad = tmp_path / "bad.net.xml"
    bad.write_text(content)
    out = tmp_path / "out"
    assert main(["build", "--source", "sumo", "--net", str(bad), "--out", str(out), "--scenarios", "2"]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "Traceback" not in err
    assert not out.exists()  # validated before the store was started


def test_missing_network(tmp_path, capsys):
    assert main(["build", "--net", str(tmp_path / "nope.net.xml"), "--out", str(tmp_path / "o")]) == 2
    assert "nope.net.xml: network file not found" in capsys.readouterr().err


def test_nuplan_wrong_db_leaves_no_settings_and_retry_works(tmp_path, capsys):
    nfx = pytest.importorskip("nuplan_fixtures")
    nfx.write_maps_root(tmp_path / "maps")
    (tmp_path / "logs").mkdir()
    nfx.write_log_db(tmp_path / "logs" / "2021.05.12.22.00.38_veh-35_01008_01518.db")
    out = tmp_path / "out"
    args = ["build", "--source", "nuplan", "--out", str(out), "--maps", str(tmp_path / "maps")]
    assert main(args + ["--db", str(tmp_path / "wrong")]) == 2
    assert str(tmp_path / "wrong") in capsys.readouterr().err
    assert not (out / "_jobs" / "settings.json").exists()
    assert main(args + ["--db", str(tmp_path / "logs"), "--maps", str(tmp_path / "no_maps")]) == 2
    assert "no_maps" in capsys.readouterr().err
    assert main(args + ["--db", str(tmp_path / "logs")]) == 0  # the corrected retry
    # a finished build with other settings: a clear error that says how to go on, not a ValueError traceback
    assert main(args + ["--db", str(tmp_path / "logs"), "--seed", "1"]) == 2
    err = capsys.readouterr().err
    assert "other settings" in err and "seed" in err and "another --out" in err
    assert main(args + ["--db", str(tmp_path / "logs")]) == 0  # the same command still resumes


def test_settings_of_a_build_without_finished_jobs_are_replaced(tmp_path):
    out = str(tmp_path / "o")
    assert jobs.check_settings(out, {"source": "sumo", "seed": 0}) is False  # recorded
    assert jobs.check_settings(out, {"source": "sumo", "seed": 1}) is True  # nothing finished: replaced
    assert jobs.check_settings(out, {"source": "sumo", "seed": 1}) is False  # the same: resumed
    store.atomic_write_json(jobs.job_marker(out, 0), {"index": 0})
    with pytest.raises(DataError, match="differing: seed"):
        jobs.check_settings(out, {"source": "sumo", "seed": 2})


@pytest.mark.parametrize("flag,value", [("--per-job", "0"), ("--scenarios", "0"), ("--scenarios", "-5"),
                                        ("--workers", "0"), ("--max-per-log", "0"), ("--per-job", "x")])
def test_counts_must_be_positive(tmp_path, capsys, flag, value):
    assert main(["build", "--out", str(tmp_path / "o"), flag, value]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"error: argument {flag}" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("source", ["sumo", "nuplan", "scenarionet"])
def test_split_must_be_train_val_or_test(tmp_path, capsys, source):
    assert main(["build", "--source", source, "--out", str(tmp_path / "o"), "--split", "tset"]) == 2
    errors = capsys.readouterr().err.splitlines()
    assert len(errors) == 1  # one line, naming the flag, the value and what is allowed
    assert "argument --split" in errors[0] and "'tset'" in errors[0]
    assert all(f"'{s}'" in errors[0] for s in ("train", "val", "test"))
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("kw", [{"per_job": 0}, {"num_scenarios": 0}, {"num_scenarios": -5}, {"workers": 0}])
def test_counts_must_be_positive_in_the_library(tmp_path, kw):
    args = {"num_scenarios": 4, "per_job": 2, "workers": 1, **kw}
    with pytest.raises(DataError, match=next(iter(kw))):
        sumo.build_sumo(str(tmp_path / "o"), args.pop("num_scenarios"), **args)
    assert not os.path.exists(tmp_path / "o")
    with pytest.raises(DataError, match="max_per_log"):
        nuplan.build_nuplan(str(tmp_path / "n"), str(tmp_path), str(tmp_path), max_per_log=0)


def test_a_data_error_crosses_a_process_boundary_whole():
    """A worker process sends its DataError back pickled: the file and the reason arrive, not a broken pool."""
    import pickle

    from gpd_jax.data.executors import LocalExecutor, run_all

    e = pickle.loads(pickle.dumps(DataError("a/b.csv", "row 3: no x")))
    assert (e.path, e.reason, str(e)) == ("a/b.csv", "row 3: no x", "a/b.csv: row 3: no x")
    with pytest.raises(DataError, match="broken") as raised:
        run_all(LocalExecutor(2), _raise_data_error, ["bad.csv", "other.csv"])
    assert raised.value.path in ("bad.csv", "other.csv")


def _raise_data_error(path):
    raise DataError(path, "broken")
