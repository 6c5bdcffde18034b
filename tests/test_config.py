import os

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


def _train(cfg) -> dict:
    """A config's train section as the shipped models recorded it: keys added since they shipped (holding their
    defaults) left out."""
    t = cfg.train.to_dict()
    assert t.pop("best_metric") == ""
    assert t.pop("eval_at_start") is False
    return t


def test_shipped_model_is_the_sumo_configs():
    import json

    ship = json.load(open(f"{ROOT}/checkpoints/gpd_sumo/config.json"))
    for name in ("gpd_sumo", "gpd_sumo_finetune", "gpd_sumo_map_feedback"):
        m = json.loads(load_config(f"{ROOT}/configs/{name}.py").model.to_json())
        assert {k: v for k, v in m.items() if k != "map_tokenizer"} == {
            k: v for k, v in ship["model"].items() if k != "map_tokenizer"}, name
    ft = load_config(f"{ROOT}/configs/gpd_sumo_finetune.py").train
    assert ft.rollout_passes == 8 and ft.init_from
    # the shipped model's last stage was trained with configs/gpd_sumo_map_feedback.py's schedule
    last = _train(load_config(f"{ROOT}/configs/gpd_sumo_map_feedback.py"))
    for k, v in last.items():
        if k not in ("init_from",):
            assert ship["train"][k] == v, k
    assert last["init_from"] == "runs/gpd_sumo_ft/export" and last["map_feedback"] == 1.0


def test_shipped_real_traffic_model_is_its_config():
    """checkpoints/gpd_sumo_real: the shipped model's architecture, fine-tuned with configs/gpd_sumo_real.py's
    schedule (its data paths given on the command line)."""
    import json

    ship = json.load(open(f"{ROOT}/checkpoints/gpd_sumo_real/config.json"))
    base = json.load(open(f"{ROOT}/checkpoints/gpd_sumo/config.json"))
    assert {k: v for k, v in ship["model"].items() if k != "map_tokenizer"} == {
        k: v for k, v in base["model"].items() if k != "map_tokenizer"}
    cfg = load_config(f"{ROOT}/configs/gpd_sumo_real.py")
    assert ship["train"] == _train(cfg)
    assert cfg.train.init_from == "checkpoints/gpd_sumo" and cfg.train.rollout_passes == 2
    assert [os.path.basename(d.rsplit(":", 1)[0]) for d in ship["data"]["dir"].split(",")] == [
        os.path.basename(d.rsplit(":", 1)[0]) for d in cfg.data.dir.split(",")]


def test_shipped_curved_road_model_is_its_config():
    """checkpoints/gpd_sumo_real_curved: checkpoints/gpd_sumo_real's architecture, fine-tuned from it with
    configs/gpd_sumo_real_curved.py (8 rollout passes over a mixture with curved generated streets)."""
    import json

    ship = json.load(open(f"{ROOT}/checkpoints/gpd_sumo_real_curved/config.json"))
    base = json.load(open(f"{ROOT}/checkpoints/gpd_sumo_real/config.json"))
    assert ship["model"] == base["model"]
    cfg = load_config(f"{ROOT}/configs/gpd_sumo_real_curved.py")
    assert ship["train"] == _train(cfg) and ship["data"] == cfg.data.to_dict()
    assert cfg.train.init_from == "checkpoints/gpd_sumo_real" and cfg.train.rollout_passes == 8


def test_shipped_euclidean_loss_model_is_its_configs():
    """checkpoints/gpd_sumo_real_euclid: gpd_sumo_real_curved's architecture, fine-tuned from it in two stages with
    the Euclidean agent loss (configs/gpd_sumo_real_euclid.py, then configs/gpd_sumo_real_euclid_narrow.py)."""
    import json

    ship = json.load(open(f"{ROOT}/checkpoints/gpd_sumo_real_euclid/config.json"))
    base = json.load(open(f"{ROOT}/checkpoints/gpd_sumo_real_curved/config.json"))
    assert ship["model"] == base["model"]
    first = load_config(f"{ROOT}/configs/gpd_sumo_real_euclid.py")
    assert first.train.init_from == "checkpoints/gpd_sumo_real_curved" and first.loss.agent_norm == "euclidean"
    cfg = load_config(f"{ROOT}/configs/gpd_sumo_real_euclid_narrow.py")
    assert ship["train"] == _train(cfg) and ship["data"] == cfg.data.to_dict()
    # keys added to the loss since it shipped hold their defaults (an absent key reads as the default)
    loss = cfg.loss.to_dict()
    assert set(loss) - set(ship["loss"]) == {"moving_weight"} and loss.pop("moving_weight") == 1.0
    assert ship["loss"] == loss and cfg.loss.agent_norm_delta == 0.01
    # the two stages differ from each other only in where they start and the loss's width
    assert {k: v for k, v in first.train.to_dict().items() if k != "init_from"} == {
        k: v for k, v in cfg.train.to_dict().items() if k != "init_from"}


def test_shipped_lane_residual_model_is_its_config():
    """checkpoints/gpd_sumo_real_lane_residual: gpd_sumo_real_euclid's architecture with `agent_lane_residual` (no
    parameters of its own), fine-tuned from it with configs/gpd_sumo_real_lane_residual.py, whose recipe is the
    narrow Euclidean stage's plus the lanes."""
    import json

    ship = json.load(open(f"{ROOT}/checkpoints/gpd_sumo_real_lane_residual/config.json"))
    base = json.load(open(f"{ROOT}/checkpoints/gpd_sumo_real_euclid/config.json"))
    model = dict(ship["model"])
    assert model.pop("agent_lane_residual") is True and model.pop("lane_context_stride") == 4
    assert model == base["model"]
    cfg = load_config(f"{ROOT}/configs/gpd_sumo_real_lane_residual.py")
    assert ship["train"] == _train(cfg) and ship["data"] == cfg.data.to_dict()
    assert ship["loss"] == cfg.loss.to_dict()
    assert cfg.train.init_from == "checkpoints/gpd_sumo_real_euclid" and cfg.train.lane_context_drop == 0.25
    narrow = load_config(f"{ROOT}/configs/gpd_sumo_real_euclid_narrow.py")
    assert {k: v for k, v in cfg.train.to_dict().items() if k not in ("init_from", "lane_context_drop")} == {
        k: v for k, v in narrow.train.to_dict().items() if k != "init_from"}


def test_shipped_lane_residual_mix_model_is_its_configs():
    """checkpoints/gpd_sumo_real_lane_residual_mix: gpd_sumo_real_lane_residual's architecture, fine-tuned in two
    stages whose recipe is the lane-residual one with legacy-traffic scenes in the mixture; the export is the second
    stage's config (its start, a workdir of this session, aside)."""
    import json

    ship = json.load(open(f"{ROOT}/checkpoints/gpd_sumo_real_lane_residual_mix/config.json"))
    base = json.load(open(f"{ROOT}/checkpoints/gpd_sumo_real_lane_residual/config.json"))
    assert ship["model"] == base["model"] and ship["loss"] == base["loss"]
    first = load_config(f"{ROOT}/configs/gpd_sumo_real_lane_residual_mix.py")
    second = load_config(f"{ROOT}/configs/gpd_sumo_real_lane_residual_mix_legacy.py")
    assert first.train.init_from == "checkpoints/gpd_sumo_real_lane_residual"
    assert second.train.init_from == "runs/lane_residual_mix/export"
    assert ship["data"] == second.data.to_dict() and ship["loss"] == second.loss.to_dict()
    assert "legacy_train" in first.data.dir and "legacy_train:0.4" in second.data.dir
    lane = load_config(f"{ROOT}/configs/gpd_sumo_real_lane_residual.py")
    for cfg in (first, second):  # the lane-residual recipe, only the start and the mixture changed
        assert {k: v for k, v in cfg.train.to_dict().items() if k != "init_from"} == {
            k: v for k, v in lane.train.to_dict().items() if k != "init_from"}
    assert {k: v for k, v in ship["train"].items() if k != "init_from"} == {
        k: v for k, v in _train(second).items() if k != "init_from"}


def test_shipped_tokenizer_is_the_decoder_config():
    """checkpoints/map_tokenizer is configs/map_tokenizer_tiny.py's model with the decoder deepened by
    configs/map_tokenizer_tiny_decoder.py (decoder-only, so its tokens are the first stage's), and its last
    decoder stage is configs/map_tokenizer_decoder_netframes.py."""
    import json

    ship = json.load(open(f"{ROOT}/checkpoints/map_tokenizer/config.json"))
    dec = load_config(f"{ROOT}/configs/map_tokenizer_tiny_decoder.py")
    assert json.loads(dec.model.to_json()) == ship["model"]
    assert dec.train.decoder_only and dec.train.init_from and ship["train"]["decoder_only"]
    first = json.loads(load_config(f"{ROOT}/configs/map_tokenizer_tiny.py").model.to_json())
    first["decoder"]["num_layers"] = dec.model.decoder.num_layers
    assert first == ship["model"]
    last = json.loads(load_config(f"{ROOT}/configs/map_tokenizer_decoder_netframes.py").to_json())
    # fields added after the export, at values that reproduce it (loader processes, the probe, a fresh decoder)
    for section, key, neutral in (("data", "processes", 0), ("train", "quantize", True),
                                  ("train", "init_decoder", True)):
        if key not in ship[section]:
            assert last[section].pop(key) == neutral
    assert {k: last[k] for k in ("data", "train", "model", "raster", "loss")} == {
        k: ship[k] for k in ("data", "train", "model", "raster", "loss")}


def test_refit_gpd_config_tokens():
    """configs/gpd_sumo_refit.py: the shipped refit recipe by default; `:directional` the same recipe moved onto the
    directional tokenizer's tokens (stores and tokenizer named alike), from the refit GPD."""
    r = load_config(os.path.join(ROOT, "configs/gpd_sumo_refit.py"))
    d = load_config(os.path.join(ROOT, "configs/gpd_sumo_refit.py:directional"))
    assert r.model.map_tokenizer == "checkpoints/map_tokenizer_refit"
    assert r.train.init_from == "checkpoints/gpd_sumo_real_lane_residual_soup_legacy2"
    assert r.data.dir == "data/refit/gen_curved_train:0.2,data/refit/legacy_train:0.4,data/refit/mix_real_train:0.4"
    assert d.model.map_tokenizer == "checkpoints/map_tokenizer_directional"
    assert d.train.init_from == "checkpoints/gpd_sumo_refit" and d.data.dir == r.data.dir.replace("refit", "directional")
    with pytest.raises(ValueError, match="tokens 'x'"):
        load_config(os.path.join(ROOT, "configs/gpd_sumo_refit.py:x"))


def test_shipped_directional_gpd_is_its_config():
    """checkpoints/gpd_sumo_directional: configs/gpd_sumo_refit.py:directional_cpu as run (the CPU settings on the
    directional stores, from the refit GPD), reading the directional tokenizer next to it."""
    import json

    ship = json.load(open(f"{ROOT}/checkpoints/gpd_sumo_directional/config.json"))
    cfg = json.loads(load_config(f"{ROOT}/configs/gpd_sumo_refit.py:directional_cpu").to_json())
    assert ship["model"].pop("map_tokenizer") == "../map_tokenizer_directional"
    assert cfg["model"].pop("map_tokenizer") == "checkpoints/map_tokenizer_directional"
    for section in ("data", "loss", "model", "rollout", "train"):
        assert ship[section] == cfg[section], section
    assert (cfg["train"]["batch_size"], cfg["train"]["rollout_passes"]) == (8, 2)
