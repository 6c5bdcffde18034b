"""Weight-space averages of GPDs (`gpd_jax.checkpoint.average_models`, `python -m gpd_jax.checkpoint average`)."""

import json

import numpy as np
import pytest
from flax import nnx

from gpd_jax.checkpoint import average_models, build_model, export_model, load_model, main
from gpd_jax.config import load_config
from gpd_jax.fsutil import flatten_params

from conftest import ROOT


def _export(tmp_path, name, seed, **model):
    cfg = load_config(f"{ROOT}/configs/gpd_tiny.py:test")
    for k, v in model.items():
        cfg.model[k] = v
    return export_model(nnx.state(build_model(cfg, seed=seed), nnx.Param), cfg, str(tmp_path / name))


def test_average_is_the_weighted_sum_and_takes_the_chosen_config(tmp_path):
    a = _export(tmp_path, "a", 1)
    b = _export(tmp_path, "b", 2, agent_lane_residual=True, predict_delta=True, velocity_residual=True)
    fa, fb = flatten_params(load_model(a).params), flatten_params(load_model(b).params)
    soup = average_models([a, b], [0.25, 0.75], config_from=1)
    got = flatten_params(soup.params)
    assert set(got) == set(fa)
    for k in fa:
        np.testing.assert_allclose(got[k], 0.25 * fa[k] + 0.75 * fb[k], rtol=1e-6, atol=1e-7 * np.abs(fb[k]).max())
    assert soup.config.model.agent_lane_residual and soup.path is None
    # a model averaged with itself is itself; equal weights by default
    same = flatten_params(average_models([a, a]).params)
    for k in fa:
        np.testing.assert_allclose(same[k], fa[k], rtol=1e-6, atol=0)


def test_average_refuses_what_cannot_be_averaged(tmp_path):
    a = _export(tmp_path, "a", 1)
    wide = _export(tmp_path, "wide", 1, d_model=64)
    with pytest.raises(ValueError, match="shape"):
        average_models([a, wide])
    with pytest.raises(ValueError, match="sum to 1"):
        average_models([a, a], [0.5, 0.6])
    with pytest.raises(ValueError, match="two or more"):
        average_models([a])
    with pytest.raises(ValueError, match="2 weights for 3 models"):
        average_models([a, a, a], [0.5, 0.5])


def test_average_cli_writes_the_model_and_its_sources(tmp_path, capsys):
    a, b = _export(tmp_path, "a", 1), _export(tmp_path, "b", 2)
    out = tmp_path / "soup"
    assert main(["average", a, b, "--weights", "0.5", "0.5", "--out", str(out)]) == 0
    rec = json.load(open(out / "soup.json"))
    assert [s["weight"] for s in rec["sources"]] == [0.5, 0.5] and len(rec["sources"][0]["params_sha256"]) == 64
    got = flatten_params(load_model(str(out)).params)
    ref = flatten_params(average_models([a, b]).params)
    for k in ref:
        np.testing.assert_array_equal(got[k], ref[k])
    assert main(["average", a, b, "--weights", "0.9", "0.9", "--out", str(tmp_path / "bad")]) == 2
    assert "sum to 1" in capsys.readouterr().err and not (tmp_path / "bad").exists()


def test_average_across_map_tokenizers_only_when_asked(tmp_path):
    """Models reading different map tokenizers' tokens are refused, unless `mixed_tokenizers` (a GPD moved to a
    re-fitted tokenizer averaged back with its parent): then the average reads the --config-from model's."""
    from gpd_jax.map_tokenizer.tokenizer import export_tokenizer
    from gpd_jax.training.map_tokenizer import build_model as build_tokenizer
    from test_map_tokenizer import small_config

    toks = []
    for seed in (1, 2):
        tcfg = small_config("--config.model.num_codes=32")
        _, tparams = build_tokenizer(tcfg, seed=seed)
        toks.append(export_tokenizer(tparams, tcfg, str(tmp_path / f"tok{seed}"), dtype=np.float32) or
                    str(tmp_path / f"tok{seed}"))
    a = _export(tmp_path, "a", 1, map_tokenizer=toks[0])
    b = _export(tmp_path, "b", 2, map_tokenizer=toks[1])
    assert load_model(a).tokenizer.fingerprint() != load_model(b).tokenizer.fingerprint()
    with pytest.raises(ValueError, match="tokens mean other things"):
        average_models([a, b])
    soup = average_models([a, b], config_from=1, mixed_tokenizers=True)
    assert soup.tokenizer.fingerprint() == load_model(b).tokenizer.fingerprint()
    out = tmp_path / "soup"
    assert main(["average", a, b, "--config-from", "1", "--mixed-tokenizers", "--out", str(out)]) == 0
    assert json.load(open(out / "soup.json"))["mixed_tokenizers"] is True
