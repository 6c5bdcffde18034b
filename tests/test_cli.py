"""`gpd-jax`, the one command line over the library: its commands dispatch to the library's command lines, and bad
input is one line with exit status 2."""

import pytest

from gpd_jax import cli, zoo


def test_models_lists_the_shipped_models_and_where_they_are(capsys):
    assert cli.main(["models"]) == 0
    out = capsys.readouterr().out
    for card in zoo.list_models():
        assert card.name in out and card.purpose in out and card.path in out
    assert f"{zoo.DEFAULT_MODEL} (default)" in out
    assert cli.main(["models", "extra"]) == 2


def test_usage_and_unknown_commands(capsys):
    assert cli.main([]) == 2
    out = capsys.readouterr().out
    assert all(name in out for name in cli.COMMANDS)
    assert cli.main(["--help"]) == 0
    capsys.readouterr()
    assert cli.main(["evaluate"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown command 'evaluate'" in err and "eval" in err


@pytest.mark.parametrize("argv, message", [
    (["data", "build", "--out", "x", "--split", "tset"], "gpd-jax data: error: argument --split"),
    (["eval", "--data", "nowhere", "--out", "x", "--batch", "0"], "gpd-jax eval: error: argument --batch: must be an integer >= 1"),
    (["train", "--config", "configs/nope.py", "--workdir", "x"], "gpd-jax train: error: config file not found"),
    (["tokenizer", "encode", "--checkpoint", "nope", "--data", "x"], "model 'nope' not found"),
    (["plan", "evaluate", "--data", "x", "--batch-size", "0"], "argument --batch-size: must be an integer >= 1"),
    (["checkpoint", "export", "nowhere", "out"], "error:"),
])
def test_commands_dispatch_and_refuse_bad_input_in_one_line(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and "Traceback" not in err, err
    assert not (tmp_path / "x").exists()


def test_each_command_has_help(capsys):
    for name in cli.COMMANDS:
        if name == "models":
            continue
        assert cli.main([name, "--help"]) == 0, name
        assert "usage" in capsys.readouterr().out.lower(), name
