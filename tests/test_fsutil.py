"""Atomic export directories keep what the export does not write."""

import os

from gpd_jax.fsutil import swap_in_directory


def _write(path, text):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        f.write(text)


def test_swap_in_directory_replaces_exported_files_and_keeps_the_others(tmp_path):
    out, tmp = str(tmp_path / "model"), str(tmp_path / ".export-1")
    _write(f"{out}/params.npz", "old params")
    _write(f"{out}/config.json", "old config")
    _write(f"{out}/README.md", "notes")
    _write(f"{out}/map_tokenizer/params.npz", "old tokenizer")
    _write(f"{out}/render/0000.png", "picture")
    _write(f"{tmp}/params.npz", "new params")
    _write(f"{tmp}/config.json", "new config")
    _write(f"{tmp}/map_tokenizer/params.npz", "new tokenizer")
    swap_in_directory(tmp, out)
    read = lambda p: open(os.path.join(out, p)).read()
    assert (read("params.npz"), read("config.json"), read("map_tokenizer/params.npz")) == (
        "new params", "new config", "new tokenizer")
    assert (read("README.md"), read("render/0000.png")) == ("notes", "picture")
    assert sorted(os.listdir(tmp_path)) == ["model"]  # no temporary or .old directory left behind


def test_swap_in_directory_creates_a_missing_directory(tmp_path):
    tmp = str(tmp_path / ".export-1")
    _write(f"{tmp}/params.npz", "p")
    swap_in_directory(tmp, str(tmp_path / "new"))
    assert os.listdir(tmp_path / "new") == ["params.npz"] and not os.path.exists(tmp)


def test_atomic_directory_leaves_the_old_export_alone_when_writing_fails(tmp_path):
    import pytest

    from gpd_jax.fsutil import atomic_directory

    out = str(tmp_path / "model")
    _write(f"{out}/params.npz", "old params")
    with pytest.raises(RuntimeError):
        with atomic_directory(out) as tmp:
            _write(f"{tmp}/params.npz", "half written")
            raise RuntimeError("disk full")
    assert open(f"{out}/params.npz").read() == "old params"
    assert sorted(os.listdir(tmp_path)) == ["model"]
    with atomic_directory(out) as tmp:
        _write(f"{tmp}/params.npz", "new params")
    assert open(f"{out}/params.npz").read() == "new params"
