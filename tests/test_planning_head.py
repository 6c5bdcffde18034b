"""The fine-tuned planning head: shapes and frames, targets, the loss going down, a frozen backbone staying put,
one compile of plan_trajectory, the training loop's resume / export / load round trip, and the scratch ablation
not loading pre-trained parameters."""

import json
import os

import chex
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest
from flax import nnx

from conftest import ROOT


def _with_head(config):
    """The tiny test model with the planning head's section and training fields at their defaults
    (`gpd_jax.config.gpd_config(plan_head=True)`), a smaller head."""
    from gpd_jax.config import gpd_config

    c = gpd_config(plan_head=True)
    c.update(config.to_dict())
    c.plan_head.num_future = 4
    c.plan_head.ffn_dim = 32
    c.data.val_dir = ""
    c.model.train_attention = "dense"  # faster than the chunked kernel at these sizes; the head does not care
    return c


@pytest.fixture(scope="module")
def head_config(tiny_config):
    return _with_head(tiny_config)


def _close(a, b, rel=1e-5):
    a, b = np.asarray(a), np.asarray(b)
    np.testing.assert_allclose(a, b, rtol=0, atol=rel * max(1.0, float(np.max(np.abs(b)))))


def test_head_shapes_frames_and_one_compile(head_config):
    from gpd_jax.checkpoint import build_model
    from gpd_jax.model import PlanningHead, plan_trajectory, to_ego_frame, to_scene_frame

    model = build_model(head_config)
    assert isinstance(model.plan_head, PlanningHead)
    m = head_config.model
    n, d = m.num_map_tokens + m.num_agents, m.d_model
    hidden = jax.random.normal(jax.random.key(1), (2, 3, n, d))
    other = hidden.at[..., m.num_map_tokens, :].add(jax.random.normal(jax.random.key(2), (d,)))
    pose = jnp.array([[3.0, -2.0, 2.5], [0.0, 0.0, -3.0]])[:, None, :].repeat(3, 1)
    with pytest.raises(TypeError, match="PlanningHead"):
        plan_trajectory(object(), hidden)

    # Pure in (params, hidden, pose) and compiled once for every call of the same shapes.
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def plan_fn(p, h, e):
        module = nnx.merge(graphdef, p, rest)
        return plan_trajectory(module, h), plan_trajectory(module.plan_head, h, e)

    plan, scene = plan_fn(params, hidden, pose)
    assert plan.shape == (2, 3, 4, 3) and scene.shape == (2, 3, 4, 3)
    assert bool(jnp.all(jnp.abs(plan[..., 2]) <= jnp.pi))
    # The scene-frame output is the ego-frame one moved to the ego's pose.
    _close(to_ego_frame(scene[..., :2], scene[..., 2], pose), plan, 1e-4)
    _close(to_scene_frame(plan, pose), scene)
    # The ego token matters: changing it changes the plan.
    assert float(jnp.max(jnp.abs(plan_fn(params, other, pose)[0] - plan))) > 1e-4
    plan_fn(params, hidden + 1.0, pose)

    # A head that reads the route: it starts as the head without one (the route's output layer is zero) and, once
    # that layer moves, where the route goes changes the plan; a missing or misshapen route is refused.
    c = ml_collections.ConfigDict(head_config.to_dict())
    c.plan_head.route_points = 3
    routed = build_model(c).plan_head
    with pytest.raises(ValueError, match="route of 3 points"):
        routed(hidden)
    with pytest.raises(ValueError, match="reads no route"):
        model.plan_head(hidden, jnp.zeros((2, 3, 3, 2)))
    left, right = jnp.zeros((2, 3, 3, 2)).at[..., 1].set(5.0), jnp.zeros((2, 3, 3, 2)).at[..., 1].set(-5.0)
    np.testing.assert_array_equal(np.asarray(routed(hidden, left)), np.asarray(routed(hidden, right)))
    routed.route_out.kernel[...] = 0.1 * jax.random.normal(jax.random.key(3), routed.route_out.kernel[...].shape)
    assert float(jnp.max(jnp.abs(routed(hidden, left) - routed(hidden, right)))) > 1e-3

    # A head that chooses its plan among candidate plans: it returns the best-scored one, unchanged; its scores
    # read the candidates; missing or misshapen candidates, or candidates given to a head that draws its plan, are
    # refused.
    c = ml_collections.ConfigDict(head_config.to_dict())
    c.plan_head.candidates, c.plan_head.idm_speeds = "idm", (4.0, 8.0, 12.0)
    chooses = build_model(c).plan_head
    one = jnp.stack([jnp.linspace(1.0, 8.0, 4), jnp.linspace(0.0, 0.6, 4), jnp.linspace(0.0, 0.3, 4)], -1)
    cands = jnp.broadcast_to(jnp.stack([one, 2 * one, 3 * one]), (2, 3, 3, 4, 3))
    logits = chooses.scores(hidden, None, cands)
    assert logits.shape == (2, 3, 3)
    best = jnp.take_along_axis(cands, jnp.argmax(logits, -1)[..., None, None, None], -3)[..., 0, :, :]
    np.testing.assert_array_equal(np.asarray(chooses(hidden, candidates=cands)), np.asarray(best))
    assert float(jnp.max(jnp.abs(chooses.scores(hidden, None, cands[..., ::-1, :, :]) - logits[..., ::-1]))) < 1e-5
    with pytest.raises(ValueError, match=r"3 candidate plans \(idm"):
        chooses(hidden)
    with pytest.raises(ValueError, match="candidate plans"):
        chooses(hidden, candidates=cands[..., :2, :, :])
    with pytest.raises(ValueError, match="reads no candidate plans"):
        model.plan_head(hidden, candidates=cands)
    c.plan_head.idm_speeds = (4.0,)
    with pytest.raises(ValueError, match="at least 2"):
        build_model(c)


def test_targets_in_each_frames_ego_frame():
    from gpd_jax.scene import Scene
    from gpd_jax.training.planning import plan_targets

    t, a = 6, 2
    # Ego driving straight along +y at 5 m per frame, heading pi/2; invalid at frame 4.
    xy = np.zeros((t, a, 2), np.float32)
    xy[:, 0, 1] = 5.0 * np.arange(t)
    heading = np.full((t, a), np.pi / 2, np.float32)
    valid = np.ones((t, a), bool)
    valid[4, 0] = False
    scene = Scene(xy=xy, heading=heading, valid=valid, size=np.ones((a, 2), np.float32),
                  agent_type=np.zeros(a, np.int32), map_tokens=np.zeros((t, 4), np.int32),
                  map_valid=np.ones(t, bool), ego_pose=np.zeros((t, 3), np.float32))
    target, mask = plan_targets(jax.tree.map(jnp.asarray, scene), num_future=3, first_frame=1)
    assert target.shape == (t - 1, 3, 3) and mask.shape == (t - 1, 3)
    # In the ego frame the ego drives along +x: k + 1 frames ahead is 5 (k + 1) m forward, heading 0.
    _close(target[1, :, 0], [5.0, 10.0, 15.0])
    _close(target[1, :, 1:], np.zeros((3, 2)))
    np.testing.assert_array_equal(mask[0], [False] * 3)            # before first_frame
    np.testing.assert_array_equal(mask[1], [True, True, False])    # targets 2, 3, 4; frame 4 invalid
    np.testing.assert_array_equal(mask[2], [True, False, True])    # targets 3, 4, 5
    np.testing.assert_array_equal(mask[3], [False, True, False])   # targets 4, 5 and past the scene's end
    np.testing.assert_array_equal(mask[4], [False] * 3)            # the ego invalid at the source frame


def _scenes(config, batch=4, seed=0):
    from gpd_jax.synthetic import synthetic_scenes

    m = config.model
    s = synthetic_scenes(seed, batch, m.num_frames, m.num_history, m.num_agents, m.num_map_tokens, m.codebook_size)
    return jax.tree.map(jnp.asarray, s)


def test_loss_decreases_and_frozen_backbone_stays(head_config):
    from gpd_jax.checkpoint import build_model
    from gpd_jax.training.planning import PlanTrainer, is_head_path

    scenes = _scenes(head_config, batch=2)
    c = ml_collections.ConfigDict(head_config.to_dict())
    c.train.learning_rate, c.train.warmup_steps, c.train.steps = 3e-3, 1, 30
    trainer = PlanTrainer(build_model(c), c, donate=False)
    state = trainer.init_state(trainer.initial_params)
    first = float(trainer.eval_step(state.params, scenes)["loss"])
    for _ in range(15):
        state, parts = trainer.train_step(state, scenes)
    last = float(trainer.eval_step(state.params, scenes)["loss"])
    assert np.isfinite(first) and last < 0.5 * first, (first, last)

    c.train.backbone_lr_scale = 0.0
    trainer = PlanTrainer(build_model(c), c, donate=False)
    s0 = trainer.init_state(trainer.initial_params)
    s1 = s0
    for _ in range(2):
        s1, _ = trainer.train_step(s1, scenes)
    moved = {is_head_path(p): False for p, _ in jax.tree_util.tree_leaves_with_path(s0.params)}
    for (p, a), b in zip(jax.tree_util.tree_leaves_with_path(s0.params), jax.tree.leaves(s1.params)):
        moved[is_head_path(p)] |= bool(np.any(np.asarray(a) != np.asarray(b)))
    assert moved == {True: True, False: False}
    c.train.gpd_loss_weight = 1.0
    with pytest.raises(ValueError, match="frozen"):
        PlanTrainer(build_model(c), c)


@pytest.fixture(scope="module")
def store_dir(tmp_path_factory):
    from test_train_loop import _store

    return _store(str(tmp_path_factory.mktemp("planstore")))


def _loop_config(store_dir, init_from=""):
    from test_train_loop import _config

    c = _with_head(_config(store_dir))
    c.train.init_from = init_from
    c.train.eval_batches = 1
    c.train.steps = c.train.eval_every = c.train.checkpoint_every = 4
    return c


def test_loop_resume_export_and_pretrained_init(store_dir, tmp_path):
    from gpd_jax.checkpoint import build_model, export_model, load_model
    from gpd_jax.training.planning import is_head_path, train_and_evaluate

    cfg = _loop_config(store_dir)
    # A "pre-trained" GPD (no head) of the same model config, exported.
    plain = ml_collections.ConfigDict(cfg.to_dict())
    del plain["plan_head"]
    for k in ("backbone_lr_scale", "gpd_loss_weight", "cache_features"):  # the head's training fields
        del plain.train[k]
    src_module = build_model(plain, seed=7)
    assert not hasattr(src_module, "plan_head")
    src = export_model(nnx.split(src_module, nnx.Param, ...)[1], plain, str(tmp_path / "pretrained"))
    src_leaves = jax.tree.leaves(load_model(src).params)

    ft = str(tmp_path / "ft")
    train_and_evaluate(_loop_config(store_dir, src), ft, stop_after=0, quiet=True)
    init = load_model(ft).params  # step 0: the backbone is the pre-trained one, the head its initialisation
    backbone = [x for p, x in jax.tree_util.tree_leaves_with_path(init) if not is_head_path(p)]
    assert len(backbone) == len(src_leaves)
    for a, b in zip(backbone, src_leaves):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

    # Stopped and resumed equals uninterrupted; the export loads as a GPD with the head.
    assert train_and_evaluate(_loop_config(store_dir, src), ft, stop_after=2, quiet=True)["step"] == 2
    out = train_and_evaluate(_loop_config(store_dir, src), ft, quiet=True)
    assert out["step"] == 4 and out["export"] and np.isfinite(out["eval"]["plan_ade_current"])
    full = str(tmp_path / "full")
    train_and_evaluate(_loop_config(store_dir, src), full, quiet=True)
    exported = load_model(os.path.join(ft, "export"))
    assert hasattr(exported.module, "plan_head")
    for a, b in zip(jax.tree.leaves(load_model(full).params), jax.tree.leaves(exported.params)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-6)
    with open(os.path.join(ft, "metrics.jsonl")) as f:
        assert any("plan_position" in json.loads(line) for line in f)
    # A planning-head model of the same head config starts a run with its head too (more training on a trained
    # head, e.g. closed-loop rounds).
    again = str(tmp_path / "again")
    train_and_evaluate(_loop_config(store_dir, os.path.join(ft, "export")), again, stop_after=0, quiet=True)
    for a, b in zip(jax.tree.leaves(load_model(again).params), jax.tree.leaves(exported.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_scratch_config_does_not_load_pretrained(store_dir, tmp_path):
    from gpd_jax.checkpoint import build_model, load_model
    from gpd_jax.config import config_differences, config_from_json, load_config
    from gpd_jax.training.planning import train_and_evaluate

    recipe = lambda v: load_config(os.path.join(ROOT, "configs", f"gpd_planner.py:{v}"))
    ft, scratch, choice, choice_scratch = (recipe(v) for v in ("finetune", "scratch", "idm_choice",
                                                               "idm_choice_scratch"))
    shipped = config_from_json(os.path.join(ROOT, "checkpoints", "gpd_planner", "config.json"))
    assert ft.train.init_from == "runs/gpd_sumo" and ft.train.backbone_lr_scale > 0
    assert choice.train.init_from == "gpd_traffic" and config_differences(choice.model, shipped.model) == ""
    assert scratch.train.init_from == "" and scratch.train.gpd_loss_weight == 0
    assert choice_scratch.train.init_from == "" and choice_scratch.train.backbone_lr_scale == 0
    # Same head, data and budget; only the backbone's start (and, for the paper's, its learning rate) differ.
    same = lambda a, b: json.loads(a.to_json()) == json.loads(b.to_json())
    for a, b in ((ft, scratch), (choice, choice_scratch)):
        assert same(a.plan_head, b.plan_head) and same(a.model, b.model) and same(a.data, b.data)
        for k in ("steps", "batch_size", "learning_rate", "warmup_steps"):
            assert a.train[k] == b.train[k]

    # The loop with the scratch setting starts from the random initialisation of its own config.
    cfg = _loop_config(store_dir, "")
    cfg.train.init_from = scratch.train.init_from
    wd = str(tmp_path / "scratch")
    train_and_evaluate(cfg, wd, stop_after=0, quiet=True)
    fresh = nnx.split(build_model(cfg), nnx.Param, ...)[1]
    for a, b in zip(jax.tree.leaves(load_model(wd).params), jax.tree.leaves(fresh)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_cached_features_give_the_scene_loss_and_resume_exactly(head_config, store_dir, tmp_path):
    """A frozen backbone's cached outputs train the head as the backbone itself would: the same loss and head
    gradients; a stopped and resumed feature-cached run with a closed-loop round equals an uninterrupted one; a
    moving backbone is refused."""
    from gpd_jax.checkpoint import build_model, load_model
    from gpd_jax.training.planning import (PlanFeatures, PlanTrainer, _features_jit, closed_loop_steps,
                                           feature_batches, first_frame, train_and_evaluate)

    c = ml_collections.ConfigDict(head_config.to_dict())
    c.train.backbone_lr_scale = 0.0
    scenes = _scenes(c, batch=3)
    with pytest.raises(ValueError, match="frozen backbone"):
        PlanTrainer(build_model(head_config), head_config, features=True)
    on_scenes = PlanTrainer(build_model(c), c, donate=False)
    on_feats = PlanTrainer(build_model(c), c, donate=False, features=True)
    params = on_scenes.initial_params
    first = first_frame(c)
    h, t, m = _features_jit(on_scenes.graphdef, params, on_scenes.rest, scenes)
    feats = PlanFeatures(h[:, first:], t[:, first:], m[:, first:])
    a, b = on_scenes.eval_step(params, scenes), on_feats.eval_step(params, feats)
    for k in ("loss", "plan_position", "plan_heading", "plan_ade_current"):
        _close(b[k], a[k])
    sa, _ = on_scenes.train_step(on_scenes.init_state(params), scenes)
    sb, _ = on_feats.train_step(on_feats.init_state(params), feats)
    for x, y in zip(jax.tree.leaves(sb.params), jax.tree.leaves(sa.params)):
        _close(x, y, rel=1e-4)

    nb = feature_batches(jax.tree.map(np.asarray, feats), 2, seed=3)
    np.testing.assert_array_equal(nb(5).hidden, nb(5).hidden)  # a pure function of the step
    with pytest.raises(ValueError, match="batch_size"):
        feature_batches(feats, 4, seed=0)

    # With a closed-loop (DAgger) round halfway: at step 2 the head of that step drives the simulator on 3
    # training scenes and the states it reached join the training scenes, kept in the workdir; the run stops past
    # the round and resumes from it.
    def cfg():
        k = _loop_config(store_dir)
        k.model.map_tokenizer, k.model.codebook_size = "map_tokenizer", 128   # the simulator encodes maps with it
        k.train.backbone_lr_scale, k.train.cache_features = 0.0, True
        k.plan_head.closed_loop_rounds, k.plan_head.closed_loop_scenes = 1, 3
        k.plan_head.route_points = 4                                            # the head reads the route
        k.plan_head.candidates = "idm"                                          # and chooses among IDM's plans
        return k

    assert closed_loop_steps(cfg()) == [2]
    wd, full = str(tmp_path / "cached"), str(tmp_path / "cached_full")
    assert train_and_evaluate(cfg(), wd, stop_after=3, quiet=True)["step"] == 3
    with np.load(os.path.join(wd, "closed_loop", "round_1.npz")) as z:
        assert z["hidden"].shape[0] == 3 and z["mask"].any() and np.isfinite(z["target"]).all()
        assert z["route"].shape == z["target"].shape[:2] + (4, 2) and np.isfinite(z["route"]).all()
        c = len(cfg().plan_head.idm_speeds)
        assert z["candidates"].shape == z["target"].shape[:2] + (c,) + z["target"].shape[2:]
        assert np.isfinite(z["candidates"]).all()
    out = train_and_evaluate(cfg(), wd, quiet=True)
    assert out["step"] == 4 and np.isfinite(out["eval"]["plan_ade_current"])
    train_and_evaluate(cfg(), full, quiet=True)
    for x, y in zip(jax.tree.leaves(load_model(full).params), jax.tree.leaves(load_model(wd).params)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=1e-6)
    bad = cfg()
    bad.train.cache_features = False
    with pytest.raises(ValueError, match="route_points.*cache_features"):
        train_and_evaluate(bad, str(tmp_path / "bad"), quiet=True)
    bad.plan_head.route_points = 0
    with pytest.raises(ValueError, match="candidates.*cache_features"):
        train_and_evaluate(bad, str(tmp_path / "bad"), quiet=True)
    bad.plan_head.candidates = ""
    with pytest.raises(ValueError, match="closed_loop_rounds.*cache_features"):
        train_and_evaluate(bad, str(tmp_path / "bad"), quiet=True)


def test_the_candidates_are_the_simulators_idm_plans(store_dir):
    """A head that chooses among IDM's plans reads the same candidates in training (`plan_inputs`, from the stored
    scene) as in the simulator (at the idm planner's target speed, the `idm` planner's plan from the observation),
    and plans one of them; its training loss is the cross-entropy of the candidate closest to the log."""
    from gpd_jax import sim
    from gpd_jax.checkpoint import Model, build_model, resolve_tokenizer_path
    from gpd_jax.data import loader
    from gpd_jax.map_tokenizer import load_tokenizer
    from gpd_jax.model import to_scene_frame
    from gpd_jax.training.planning import plan_inputs, plan_terms, plan_targets

    k = _loop_config(store_dir)
    k.model.map_tokenizer, k.model.codebook_size = "map_tokenizer", 128
    k.plan_head.candidates, k.plan_head.route_points, k.plan_head.idm_speeds = "idm", 4, (5.0, 13.89)
    world = Model.from_module(build_model(k), k, tokenizer=load_tokenizer(resolve_tokenizer_path("map_tokenizer")))
    stored = loader.load_split(store_dir, "train", with_polylines=True, indices=range(2))[0]
    spec, h = world.spec, world.spec.num_history
    view = spec.view(stored)
    route, cands = plan_inputs(stored, view, spec, k)
    assert route.shape == (2, spec.num_frames - 1, 4, 2) and cands.shape == (2, spec.num_frames - 1, 2, 4, 3)
    sims = sim.make_sim_scenes(world, stored)
    head, idm = sim.make_policy("gpd_head", world), sim.make_policy("idm", world)
    key = jax.random.key(0)
    for i in range(2):
        obs = sim.observe(world, sim.reset(world, jax.tree.map(lambda a: a[i], sims), agents="log", with_model=False))
        want = idm.plan(None, obs, key)
        assert float(jnp.linalg.norm(want[-1, :2] - want[0, :2])) > 1.0          # it goes somewhere
        plans = [to_scene_frame(jnp.asarray(cands[i, h - 1, c]), obs.ego_pose)[:len(want)] for c in (0, 1)]
        _close(plans[1], want, 1e-4)                                                # F >= the model's frames
        gone = [float(jnp.linalg.norm(p[-1, :2] - obs.ego_pose[:2])) for p in plans]
        assert gone[0] < gone[1]                                                    # 5 m/s goes less far
        got = head.plan(world.params, obs, key)                                     # one of them, unchanged
        assert min(float(jnp.max(jnp.abs(got - p))) for p in plans) < 1e-3

    # The loss: the cross-entropy of the candidate closest to the logged future (here the log is made to drive
    # one of them exactly), and the ADE of the one the head chooses.
    target, mask = plan_targets(jax.tree.map(lambda a: jnp.asarray(a[0]), view), 4, h - 1)
    hidden = jax.random.normal(jax.random.key(1), (target.shape[0], spec.num_map_tokens + spec.num_agents,
                                                     k.model.d_model))
    c0 = jnp.asarray(cands[0])
    for label in (0, 1):
        terms = plan_terms(world.module.plan_head, hidden, c0[:, label], jnp.ones_like(mask), h - 1, jnp.asarray(
            route[0]), c0)
        logits = world.module.plan_head.scores(hidden, jnp.asarray(route[0]), c0)
        ce = jax.nn.logsumexp(logits, -1) - logits[:, label]
        _close(terms["select_sum"], jnp.sum(ce), 1e-5)
        pick = jnp.argmax(logits, -1)
        assert float(terms["select_hits"]) == float(jnp.sum(pick == label))
        ade = jnp.mean(jnp.linalg.norm(c0[h - 1, pick[h - 1], :, :2] - c0[h - 1, label, :, :2], axis=-1))
        _close(terms["ade_sum"] / terms["ade_count"], ade, 1e-5)


def test_closed_loop_targets_lead_back_to_the_log():
    """A reached ego 1 m left of the logged one (same heading) is told to go back: every target lies 1 m to its
    right at the log's positions; the log's own targets are unchanged by naming it the expert."""
    from gpd_jax.synthetic import synthetic_scenes
    from gpd_jax.training.planning import plan_targets

    log = jax.tree.map(jnp.asarray, synthetic_scenes(0, 1, 6, 3, 4, 8, 16))
    log = jax.tree.map(lambda x: x[0], log)
    log = log.replace(heading=jnp.zeros_like(log.heading), valid=jnp.ones_like(log.valid))
    reached = log.replace(xy=log.xy.at[:, 0, 1].add(1.0))
    own, own_mask = plan_targets(log, 3, 2)
    same, same_mask = plan_targets(log, 3, 2, log)
    np.testing.assert_array_equal(np.asarray(own), np.asarray(same))
    target, mask = plan_targets(reached, 3, 2, log)
    np.testing.assert_array_equal(np.asarray(mask), np.asarray(own_mask))
    m = np.asarray(mask)
    np.testing.assert_allclose(np.asarray(target[..., 1])[m], np.asarray(own[..., 1])[m] - 1.0, atol=1e-5)
    np.testing.assert_allclose(np.asarray(target[..., 0])[m], np.asarray(own[..., 0])[m], atol=1e-5)

