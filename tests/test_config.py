import os

import pytest

from gpd_jax.config import load_config, split_config_args

from conftest import ROOT


def test_overrides_typed():
    c = load_config(f"{ROOT}/configs/gpd_tiny.py:test",
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
        load_config(f"{ROOT}/configs/gpd_tiny.py:test", [bad])


def test_split_args():
    o, r = split_config_args(["rollout", "--config.a=1", "--batch", "1"])
    assert o == ["--config.a=1"] and r == ["rollout", "--batch", "1"]


# each shipped model and the recipe that made it (configs/*.py[:variant])
SHIPPED = (("gpd_traffic", "gpd_traffic.py"), ("gpd_sampling", "gpd_sampling.py"), ("gpd_maps", "gpd_maps.py"), ("gpd_planner", "gpd_planner.py"),
           ("map_tokenizer", "map_tokenizer.py"), ("map_tokenizer_directional", "map_tokenizer.py:directional"))


@pytest.mark.parametrize("name, recipe", SHIPPED)
def test_shipped_model_is_its_recipe(name, recipe):
    """Every shipped model's config.json is exactly its recipe's last stage (configs/), and names its tokenizer by
    a shipped model's name (no machine path)."""
    import json

    from gpd_jax import zoo
    from gpd_jax.config import config_from_json

    ship = config_from_json(f"{ROOT}/checkpoints/{name}/config.json")
    cfg = load_config(f"{ROOT}/configs/{recipe}")
    assert json.loads(ship.to_json()) == json.loads(cfg.to_json())
    card = zoo.card(name)
    if card.kind == "gpd":
        assert ship.model.map_tokenizer == card.tokenizer and zoo.find(card.tokenizer)


def test_recipe_stages_change_only_what_they_say():
    """The default model's recipe: each stage starts from the previous one's export; the lane residual, the
    Euclidean loss and the mixtures arrive where the recipe says, and an unknown stage is refused."""
    first = load_config(f"{ROOT}/configs/gpd_traffic.py:sumo")
    real = load_config(f"{ROOT}/configs/gpd_traffic.py:real")
    last = load_config(f"{ROOT}/configs/gpd_traffic.py")
    assert first.train.init_from == "" and first.model.agent_lane_residual is False
    assert real.train.init_from == "runs/sumo_map_feedback/export" and real.train.rollout_passes == 2
    assert real.model.to_dict() == first.model.to_dict()
    assert last.model.agent_lane_residual is True and last.loss.agent_norm == "euclidean"
    assert last.loss.agent_norm_delta == 0.01 and last.train.lane_context_drop == 0.25
    with pytest.raises(ValueError, match="stage 'nope'"):
        load_config(f"{ROOT}/configs/gpd_traffic.py:nope")


def test_configs_are_few_and_self_contained():
    """At most eight config files, each importing nothing but gpd_jax.config (no chains through sys.path)."""
    import ast

    files = sorted(f for f in os.listdir(os.path.join(ROOT, "configs")) if f.endswith(".py"))
    assert 0 < len(files) <= 8
    for f in files:
        tree = ast.parse(open(os.path.join(ROOT, "configs", f)).read())
        imports = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
        assert [getattr(n, "module", None) for n in imports] == ["gpd_jax.config"], f


def test_config_json_is_read_onto_the_schema(tmp_path):
    """A config.json missing fields gets the schema's defaults; an unknown field or stage is refused naming the
    file and the field; a config file whose result lacks or adds fields is refused."""
    import json

    from gpd_jax.config import config_from_json

    d = json.loads(load_config(f"{ROOT}/configs/gpd_tiny.py:test").to_json())
    del d["train"]["best_metric"]
    p = tmp_path / "config.json"
    p.write_text(json.dumps(d))
    assert config_from_json(str(p)).train.best_metric == ""
    d["model"]["lane_attention"] = True
    p.write_text(json.dumps(d))
    with pytest.raises(ValueError, match="config.json: unknown config field 'model.lane_attention'"):
        config_from_json(str(p))
    # fields of removed options: an earlier export that left them off loads; one that used them is refused
    del d["model"]["lane_attention"]
    d["model"]["agent_map_context"], d["model"]["map_extent_m"], d["rollout"] = False, 64.0, {"temperature": 0.0}
    p.write_text(json.dumps(d))
    assert "rollout" not in config_from_json(str(p)) and "agent_map_context" not in config_from_json(str(p)).model
    d["model"]["agent_map_context"] = True
    p.write_text(json.dumps(d))
    with pytest.raises(ValueError, match="model.agent_map_context = True: that option was removed"):
        config_from_json(str(p))
    p.write_text(json.dumps({"stage": "nope"}))
    with pytest.raises(ValueError, match="stage is 'nope'"):
        config_from_json(str(p))
    bad = tmp_path / "bad.py"
    bad.write_text("from gpd_jax.config import gpd_config\n\ndef get_config():\n    c = gpd_config()\n"
                   "    c.model.extra = 1\n    return c\n")
    with pytest.raises(ValueError, match="unknown config field 'model.extra'"):
        load_config(str(bad))
