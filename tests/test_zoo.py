"""The shipped models by name (`gpd_jax.zoo`): the registry, where folders are found, and model folders that load
wherever they are copied."""

import json
import os
import shutil

import numpy as np
import pytest

import gpd_jax
from gpd_jax import zoo
from gpd_jax.config import config_from_json


def test_the_registry_lists_a_few_models_the_default_first():
    cards = gpd_jax.list_models()
    assert cards[0].name == gpd_jax.DEFAULT_MODEL == "gpd_traffic"
    gpds = gpd_jax.list_models("gpd")
    assert 1 <= len(gpds) <= 4 and {c.name for c in gpds} <= {c.name for c in cards}
    tokenizers = {c.name for c in gpd_jax.list_models("map_tokenizer")}
    for c in cards:
        assert c.purpose and c.data and c.figures and c.path, c.name
        config = config_from_json(os.path.join(c.path, "config.json"))
        assert config.stage == c.kind, c.name
        assert os.path.isfile(os.path.join(c.path, "README.md")), c.name  # its card
        if c.kind == "gpd":
            assert c.tokenizer in tokenizers and config.model.map_tokenizer == c.tokenizer, c.name
    with pytest.raises(ValueError, match="kind"):
        gpd_jax.list_models("tokenizer")
    with pytest.raises(KeyError, match="shipped: gpd_traffic"):
        zoo.card("gpd_sumo")


def test_names_resolve_through_the_models_folder_of_the_environment_first(tmp_path, monkeypatch):
    models = tmp_path / "models"
    shutil.copytree(zoo.find("map_tokenizer_directional"), models / "map_tokenizer_directional")
    monkeypatch.setenv(zoo.MODELS_ENV, str(models))
    assert zoo.model_dirs()[0] == str(models)
    assert zoo.find("map_tokenizer_directional") == str(models / "map_tokenizer_directional")
    assert zoo.find("gpd_maps").startswith(zoo._CHECKOUT_MODELS)  # not there: the checkout's
    assert zoo.find("../checkpoints") is None and zoo.find("") is None  # names, not paths
    with pytest.raises(FileNotFoundError, match=r"model 'gpd_sumo' not found: .*models.*shipped: gpd_traffic"):
        zoo.resolve("gpd_sumo")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="no config.json"):
        zoo.resolve(str(empty))


def test_a_model_folder_loads_wherever_it_is_copied(tmp_path, monkeypatch):
    """A copy of a shipped model elsewhere names its tokenizer, found by name; an export carrying its tokenizer
    inside loads with no models folder at all; a tokenizer found nowhere is one message saying where it looked."""
    from gpd_jax.checkpoint import export_model, resolve_tokenizer_path

    ref = gpd_jax.load_model("gpd_maps")
    copy = tmp_path / "elsewhere" / "mine"
    shutil.copytree(ref.path, copy)
    moved = gpd_jax.load_model(str(copy))
    assert moved.tokenizer.fingerprint() == ref.tokenizer.fingerprint()
    np.testing.assert_array_equal(np.asarray(moved.params["pos_head"]["linears"][0]["kernel"]),
                                  np.asarray(ref.params["pos_head"]["linears"][0]["kernel"]))
    # an export with its tokenizer inside, then no models folder anywhere
    tok_dir = resolve_tokenizer_path(ref.config.model.map_tokenizer, ref.path)
    out = export_model(ref.params, ref.config, str(tmp_path / "export"), tokenizer_dir=tok_dir)
    assert json.load(open(os.path.join(out, "config.json")))["model"]["map_tokenizer"] == "map_tokenizer_directional"
    monkeypatch.delenv(zoo.MODELS_ENV, raising=False)
    monkeypatch.setattr(zoo, "_CHECKOUT_MODELS", str(tmp_path / "nowhere"))
    assert gpd_jax.load_model(out).tokenizer.fingerprint() == ref.tokenizer.fingerprint()
    with pytest.raises(FileNotFoundError) as err:
        resolve_tokenizer_path("map_tokenizer", str(copy))
    msg = str(err.value)
    assert "map tokenizer 'map_tokenizer' not found" in msg and "GPD_JAX_MODELS is not set" in msg
    assert msg.count(str(copy / "map_tokenizer")) == 1
