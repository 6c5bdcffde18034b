"""Stage-2 training loop: resume after a stop is the same run; data-parallel steps equal single-device steps."""

import json
import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest
from flax import nnx

from conftest import ROOT
from data_fixtures import write_small_store


def _store(path):
    from gpd_jax.data import store

    write_small_store(path, n_shards=2, per_shard=4, split="train")
    write_small_store(path, n_shards=1, per_shard=4, split="val")
    rng = np.random.default_rng(0)
    for split in ("train", "val"):
        for j in store.shard_indices(path, split):
            # only the model's frames (every 10th), as `encode --frame-stride 10` writes them
            tokens = np.full((4, 101, 64), store.MISSING_MAP_TOKEN, np.uint8)
            tokens[:, ::10] = rng.integers(0, 32, (4, 11, 64))
            store.save_map_tokens(path, split, j, tokens, frame_stride=10)
    return path


def _config(data_dir, **train):
    from gpd_jax.config import load_config

    c = load_config(os.path.join(ROOT, "configs", "gpd_tiny.py:test"))
    c.data.dir = data_dir
    c.data.frame_stride = 10
    c.model.num_frames = 6
    c.model.num_history = 3
    c.model.num_map_tokens = 64
    c.model.attn_chunk_frames = 3
    c.model.predict_delta = True
    c.model.velocity_residual = True
    c.model.velocity_inputs = True  # model views carry stored-rate velocities (train batches and validation)
    t = c.train
    t.batch_size, t.steps, t.warmup_steps = 4, 6, 2
    t.log_every, t.eval_every, t.checkpoint_every = 1, 3, 2
    t.eval_batches, t.eval_rollout_scenarios, t.loader_threads = 1, 2, 1
    for k, v in train.items():
        t[k] = v
    return c


@pytest.fixture(scope="module")
def store_dir(tmp_path_factory):
    return _store(str(tmp_path_factory.mktemp("gpdstore")))


@pytest.fixture(scope="module")
def trained(store_dir, tmp_path_factory):
    """(workdir, result) of the uninterrupted 6-step run of `_config(store_dir)`: the reference of the resume test,
    the workdir the model-config check refuses, and the exported model fine-tunes start from (one training run
    and one compiled train step for all of them). Tests copy the workdir before they write to it."""
    from gpd_jax.training.loop import train_and_evaluate

    full = str(tmp_path_factory.mktemp("trained") / "full")
    return full, train_and_evaluate(_config(store_dir), full, quiet=True)


def _params(workdir):
    from gpd_jax.checkpoint import load_model

    return load_model(workdir).params


def test_resume_after_stop_equals_uninterrupted_run(store_dir, trained, tmp_path):
    from gpd_jax.training.loop import train_and_evaluate

    full, out = trained
    assert out["step"] == 6 and out["export"]
    part = str(tmp_path / "part")
    assert train_and_evaluate(_config(store_dir), part, stop_after=4, quiet=True)["step"] == 4
    assert train_and_evaluate(_config(store_dir), part, quiet=True)["step"] == 6

    a, b = _params(full), _params(part)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=1e-6)
    # The export is loadable and equals the final checkpoint.
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(_params(os.path.join(full, "export")))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # Each record once per step: the resumed run logged steps 5 and 6 and the evaluation at step 6.
    recs = [json.loads(l) for l in open(os.path.join(part, "metrics.jsonl"))]
    train_steps = [r["step"] for r in recs if r["split"] == "train"]
    assert train_steps == [1, 2, 3, 4, 5, 6]
    evals = [r for r in recs if r["split"] == "val"]
    assert [r["step"] for r in evals] == [3, 6]
    assert np.isfinite(evals[-1]["loss"]) and "rollout_agent_ade_3s" in evals[-1] and "cv_agent_ade_3s" in evals[-1]


def test_store_without_map_tokens_is_refused(tmp_path):
    from gpd_jax.data.errors import DataError
    from gpd_jax.training.loop import train_and_evaluate

    d = str(tmp_path / "raw")
    write_small_store(d, n_shards=1, per_shard=4)
    with pytest.raises(DataError, match="map tokens"):
        train_and_evaluate(_config(d), str(tmp_path / "w"), quiet=True)
    assert not os.path.exists(tmp_path / "w" / "checkpoints")


def test_map_tokens_encoded_at_a_coarser_stride_than_the_model_are_refused(tmp_path):
    from gpd_jax.data import store
    from gpd_jax.data.errors import DataError
    from gpd_jax.training.loop import train_and_evaluate

    d = str(tmp_path / "strided")
    write_small_store(d, n_shards=1, per_shard=4)
    tokens = np.full((4, 101, 64), store.MISSING_MAP_TOKEN, np.uint8)
    tokens[:, ::20] = 3  # every 20th frame; the test config reads every 10th
    store.save_map_tokens(d, "train", 0, tokens, tokenizer="t", frame_stride=20)
    with pytest.raises(DataError, match="missing at some of the model's frames.*--frame-stride 10"):
        train_and_evaluate(_config(d), str(tmp_path / "w"), quiet=True)


def test_map_tokens_of_another_tokenizer_are_refused(tmp_path):
    from gpd_jax.data import store
    from gpd_jax.data.errors import DataError
    from gpd_jax.map_tokenizer import load_tokenizer
    from gpd_jax.training.loop import train_and_evaluate

    d = _store(str(tmp_path / "s"))
    tok = os.path.join(ROOT, "checkpoints", "map_tokenizer")
    fp = load_tokenizer(tok).fingerprint()
    tokens = np.asarray(store.Shard(store.shard_dir(d, "train", 1)).map_tokens)
    store.save_map_tokens(d, "train", 1, tokens, tokenizer=fp, frame_stride=10)
    store.save_map_tokens(d, "train", 0, tokens, tokenizer="0" * 16, frame_stride=10)
    assert store.foreign_map_token_shards(d, "train", fp) == [0]  # shards without a record are not listed
    c = _config(d)
    c.model.map_tokenizer, c.model.codebook_size = tok, 128
    with pytest.raises(DataError, match="shard_00000.*made by tokenizer 0000000000000000, not by the model's"):
        train_and_evaluate(c, str(tmp_path / "w"), quiet=True)
    assert not os.path.exists(tmp_path / "w" / "checkpoints")
    # validation reads the val split's tokens: checked too
    store.save_map_tokens(d, "train", 0, tokens, tokenizer=fp, frame_stride=10)
    store.save_map_tokens(d, "val", 0, tokens, tokenizer="0" * 16, frame_stride=10)
    with pytest.raises(DataError, match="split 'val'.*made by tokenizer 0000000000000000"):
        train_and_evaluate(c, str(tmp_path / "w"), quiet=True)


def test_workdir_with_another_model_is_refused(store_dir, trained, tmp_path):
    import shutil

    from gpd_jax.training.loop import train_and_evaluate

    w = str(tmp_path / "w")
    shutil.copytree(trained[0], w)  # a workdir that trained the model of _config
    c = _config(store_dir, eval_every=0)
    c.model.d_model = 48
    with pytest.raises(ValueError, match="different model config"):
        train_and_evaluate(c, w, quiet=True)
    with open(os.path.join(w, "config.json")) as f:  # left as it was
        assert json.load(f)["model"] == json.loads(_config(store_dir).to_json())["model"]


_DP_SCRIPT = textwrap.dedent("""
    import os, sys
    import jax, numpy as np
    sys.path.insert(0, {tests!r})
    from test_train_loop import _config
    from gpd_jax.checkpoint import build_model
    from gpd_jax.parallel import data_mesh
    from gpd_jax.synthetic import synthetic_scenes
    from gpd_jax.training.step import batch_loss, make_trainer
    from gpd_jax.training.loop import _global_batch
    from jax.sharding import NamedSharding, PartitionSpec
    assert len(jax.devices()) == 4, jax.devices()
    c = _config("unused")
    m = c.model
    scenes = synthetic_scenes(1, 4, m.num_frames, m.num_history, m.num_agents, m.num_map_tokens, m.codebook_size)
    scenes = scenes.with_velocity(1.0)
    out = []
    for n in (1, 4):
        mesh = data_mesh(n)
        trainer, state = make_trainer(build_model(c, seed=0), c, donate=False)
        state = jax.device_put(state, NamedSharding(mesh, PartitionSpec()))
        batch = _global_batch(scenes, mesh)
        assert len(batch.xy.sharding.device_set) == n
        loss = lambda p, b: batch_loss(trainer.merge(p), b, c.loss)[0]
        grads = jax.jit(jax.grad(loss))(state.params, batch)
        state, parts = trainer.train_step(state, batch)
        out.append((jax.device_get(grads), jax.device_get(state.params), float(parts["loss"])))
    (g1, p1, l1), (g4, p4, l4) = out
    assert abs(l1 - l4) < 1e-5 * max(1.0, abs(l1)), (l1, l4)
    for a, b, pa, pb in zip(*(jax.tree.leaves(t) for t in (g1, g4, p1, p4))):
        a, b, pa, pb = (np.asarray(x) for x in (a, b, pa, pb))
        scale = np.abs(a).max() + 1e-12
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * scale)
        # Adam's first update is ~lr * sign(g): compare the step where the gradient is not rounding noise.
        big = np.abs(a) > 1e-3 * scale
        np.testing.assert_allclose(pa[big], pb[big], rtol=0, atol=1e-6)
    print("OK", l1, l4)
""")


def test_four_device_data_parallel_step_equals_single_device(tmp_path):
    env = dict(os.environ, XLA_FLAGS=os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4",
               JAX_PLATFORMS="cpu")
    script = tmp_path / "dp.py"
    script.write_text(_DP_SCRIPT.format(tests=os.path.dirname(os.path.abspath(__file__))))
    r = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0 and "OK" in r.stdout, r.stdout[-2000:] + r.stderr[-4000:]


def test_learning_curves_from_metrics_log(tmp_path):
    from gpd_jax.training.curves import main

    recs = [{"step": s, "split": "train", "loss": 10.0 / s, "position": 1.0 / s} for s in range(1, 6)]
    recs += [{"step": 5, "split": "val", "loss": 2.0, "rollout_agent_ade_3s_vs_cv": 1.2}]
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    out = tmp_path / "c.png"
    assert main([str(tmp_path), str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main([str(tmp_path / "missing"), str(out)]) == 2


def test_init_from_starts_a_new_run_from_a_models_parameters(store_dir, tmp_path):
    from gpd_jax.checkpoint import export_model
    from gpd_jax.checkpoint import build_model
    from gpd_jax.training.loop import train_and_evaluate

    c = _config(store_dir, eval_every=0)
    src = str(tmp_path / "src")
    export_model(nnx.state(build_model(c, seed=7), nnx.Param), c, src)
    w = str(tmp_path / "w")
    assert train_and_evaluate(_config(store_dir, eval_every=0, init_from=src), w, stop_after=0, quiet=True)["step"] == 0
    fresh = nnx.state(build_model(c, seed=c.seed), nnx.Param)
    for x, y, z in zip(*(jax.tree.leaves(t) for t in (_params(w), _params(src), fresh))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert any(not np.array_equal(np.asarray(y), np.asarray(z))
               for y, z in zip(jax.tree.leaves(_params(src)), jax.tree.leaves(fresh)))
    other = _config(store_dir, eval_every=0, init_from=src)
    other.model.num_layers = 1
    with pytest.raises(ValueError, match="init_from .* num_layers"):
        train_and_evaluate(other, str(tmp_path / "w2"), stop_after=0, quiet=True)


def test_a_mixture_of_stores_trains_and_validates_on_val_dir(store_dir, tmp_path):
    from gpd_jax.data.errors import DataError
    from gpd_jax.training.loop import train_and_evaluate

    # a second store with only a train split: validation must read data.val_dir
    other = str(tmp_path / "other")
    write_small_store(other, n_shards=1, per_shard=4, offset=3.0)
    c = _config(f"{store_dir}:1,{other}:1", steps=2, eval_every=2)
    with pytest.raises(DataError, match=f"{other}.*map tokens"):  # every store of the mixture is checked
        train_and_evaluate(c, str(tmp_path / "w0"), quiet=True)
    from gpd_jax.data import store

    tokens = np.full((4, 101, 64), store.MISSING_MAP_TOKEN, np.uint8)
    tokens[:, ::10] = 5
    store.save_map_tokens(other, "train", 0, tokens, frame_stride=10)
    # the schedule of `_config` (6 steps): the train step compiled for the other runs of this file serves
    c = _config(f"{other}:1,{store_dir}:1", eval_every=6)
    with pytest.raises(DataError, match="no complete shards"):  # the first store has no val split
        train_and_evaluate(c, str(tmp_path / "w1"), quiet=True)
    c.data.val_dir = store_dir
    out = train_and_evaluate(c, str(tmp_path / "w2"), quiet=True)
    assert out["step"] == 6 and np.isfinite(out["eval"]["loss"]) and out["export"]


def test_best_validation_is_exported_and_kept_on_resume_over_several_val_stores(store_dir, tmp_path):
    """`data.val_dir` with two stores validates on each (keys prefixed by store name, the ratios' mean
    unprefixed); `train.best_metric` exports the best validation's parameters to WORKDIR/best with best.json,
    which a resumed run keeps and only a lower value replaces."""
    import shutil

    from gpd_jax.checkpoint import load_model
    from gpd_jax.training.loop import train_and_evaluate

    second = str(tmp_path / "second_val")
    shutil.copytree(store_dir, second)
    w = str(tmp_path / "w")
    metric = "rollout_agent_ade_vs_cv_mean"
    c = _config(store_dir, steps=6, eval_every=1, best_metric=metric)
    c.data.val_dir = f"{store_dir},{second}"
    assert train_and_evaluate(c, w, stop_after=3, quiet=True)["step"] == 3
    evals = [json.loads(l) for l in open(os.path.join(w, "metrics.jsonl"))]
    evals = [r for r in evals if r["split"] == "val"]
    name = os.path.basename(store_dir)
    for r in evals:
        own = [r[f"{n}/rollout_agent_ade_{h}_vs_cv"] for n in (name, "second_val") for h in ("3s",)]
        assert all(np.isfinite(own))
        ratios = [v for k, v in r.items() if k.endswith("_vs_cv")]
        assert len(ratios) == 2 * len([k for k in r if k.startswith(name + "/") and k.endswith("_vs_cv")]) > 0
        np.testing.assert_allclose(r[metric], np.mean(ratios), rtol=1e-6)
        # the same store twice: the same figures
        np.testing.assert_allclose(r[f"{name}/rollout_agent_ade_3s"], r["second_val/rollout_agent_ade_3s"], rtol=1e-6)
    best = json.load(open(os.path.join(w, "best.json")))
    values = [r[metric] for r in evals]
    assert best["metric"] == metric and best["value"] == pytest.approx(min(values))
    assert best["step"] == evals[int(np.argmin(values))]["step"]
    # the export is the parameters of that step: equal to the checkpoint at best["step"] when that is the last
    exported = load_model(os.path.join(w, "best")).params
    if best["step"] == 3:
        for x, y in zip(jax.tree.leaves(exported), jax.tree.leaves(load_model(w).params)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # resume: the best so far is read back; only a lower value replaces it
    assert train_and_evaluate(c, w, quiet=True)["step"] == 6
    evals = [r for r in (json.loads(l) for l in open(os.path.join(w, "metrics.jsonl"))) if r["split"] == "val"]
    assert [r["step"] for r in evals] == [1, 2, 3, 4, 5, 6]
    values = [r[metric] for r in evals]
    after = json.load(open(os.path.join(w, "best.json")))
    assert after["value"] == pytest.approx(min(values)) and after["step"] == evals[int(np.argmin(values))]["step"]
    # another metric in the same workdir is refused, naming both
    c2 = _config(store_dir, steps=8, eval_every=1, best_metric="loss")
    c2.data.val_dir = c.data.val_dir
    with pytest.raises(ValueError, match="rollout_agent_ade_vs_cv_mean.*'loss'"):
        train_and_evaluate(c2, w, quiet=True)
    # a metric the validation does not compute is refused at the first validation, naming the keys there
    c3 = _config(store_dir, steps=2, eval_every=1, best_metric="no_such_key")
    with pytest.raises(ValueError, match="no_such_key.*rollout_agent_ade_vs_cv_mean"):
        train_and_evaluate(c3, str(tmp_path / "w3"), quiet=True)


def test_eval_at_start_validates_step_0_and_it_can_stay_the_best(store_dir, trained, tmp_path):
    """`train.eval_at_start` validates the starting parameters (logged as step 0) and lets them be the best; a
    resumed run does not validate step 0 again."""
    from gpd_jax.checkpoint import load_model
    from gpd_jax.training.loop import train_and_evaluate

    src = trained[0]  # a trained model's export is where the fine-tune starts
    w = str(tmp_path / "w")
    # a learning rate this high makes the first steps worse than where the run started
    c = _config(store_dir, steps=2, eval_every=2, eval_at_start=True, best_metric="loss",
                init_from=os.path.join(src, "export"), learning_rate=50.0, warmup_steps=1)
    assert train_and_evaluate(c, w, stop_after=1, quiet=True)["step"] == 1
    assert train_and_evaluate(c, w, quiet=True)["step"] == 2
    evals = [r for r in (json.loads(l) for l in open(os.path.join(w, "metrics.jsonl"))) if r["split"] == "val"]
    assert [r["step"] for r in evals] == [0, 2]
    best = json.load(open(os.path.join(w, "best.json")))
    assert best["step"] == 0 and best["value"] == pytest.approx(evals[0]["loss"]) and evals[1]["loss"] > evals[0]["loss"]
    for x, y in zip(jax.tree.leaves(load_model(os.path.join(w, "best")).params),
                    jax.tree.leaves(load_model(os.path.join(src, "export")).params)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
