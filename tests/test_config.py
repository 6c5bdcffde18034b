import pytest

from gpd_jax.config import load_config, split_config_args

from conftest import ROOT


def test_overrides_typed():
    c = load_config(f"{ROOT}/configs/gpd_tiny.py",
                    ["--config.model.num_layers=3", "--config.model.predict_delta=true",
                     "--config.train.learning_rate=1e-2", "--config.model.xy_levels=(2.0, 0.5)"])
    assert c.model.num_layers == 3 and c.model.predict_delta is True
    assert c.train.learning_rate == 0.01 and c.model.xy_levels == (2.0, 0.5)


def test_paper_values():
    m = load_config(f"{ROOT}/configs/gpd_paper.py").model
    assert (m.num_frames, m.num_history, m.num_agents, m.num_map_tokens) == (101, 21, 33, 64)
    assert (m.codebook_size, m.d_model, m.num_layers, m.num_heads, m.ffn_dim) == (128, 128, 6, 8, 2048)


@pytest.mark.parametrize("bad, err", [("--config.model.nope=1", KeyError),
                                      ("--config.model.num_layers=abc", ValueError),
                                      ("--config.model.num_layers=1.5", ValueError)])
def test_bad_overrides(bad, err):
    with pytest.raises(err):
        load_config(f"{ROOT}/configs/gpd_tiny.py", [bad])


def test_split_args():
    o, r = split_config_args(["rollout", "--config.a=1", "--batch", "1"])
    assert o == ["--config.a=1"] and r == ["rollout", "--batch", "1"]
