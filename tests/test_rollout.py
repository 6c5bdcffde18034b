"""Cached rollout == recompute rollout (every task), mask semantics, tasks as data, one trace per batch."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from gpd_jax.model import forward
from gpd_jax.decoding import rollout, rollout_batch, rollout_recompute, rollout_tasks
from gpd_jax.tasks import TASK_NAMES, TASKS, make_task, make_tasks


@pytest.fixture(scope="module")
def setup(tiny_model, tiny_config, tiny_scenes):
    graphdef, state = nnx.split(tiny_model)
    return graphdef, state, tiny_config.model, jax.tree.map(jnp.asarray, tiny_scenes)


@pytest.mark.parametrize("temperature", [0.0, 1.0])
def test_cached_equals_recompute_every_task(setup, temperature):
    graphdef, state, m, scenes = setup
    tasks = jax.tree.map(jnp.asarray, make_tasks(["all"], m.num_map_tokens, m.num_agents))
    h = m.num_history

    @jax.jit
    def both(state, scenes, tasks):
        model = nnx.merge(graphdef, state)
        key = jax.random.key(3)
        cached = rollout_tasks(model, scenes, tasks, key, h, temperature)
        keys = jax.random.split(key, scenes.xy.shape[0] * tasks.from_log.shape[0]).reshape(
            scenes.xy.shape[0], tasks.from_log.shape[0])
        rec = jax.vmap(lambda sc, ks: jax.vmap(
            lambda t, k: rollout_recompute(model, sc, t, k, h, temperature))(tasks, ks))(scenes, keys)
        return cached, rec

    cached, rec = both(state, scenes, tasks)
    assert cached.xy.shape == (3, len(TASK_NAMES), m.num_frames, m.num_agents, 2)
    np.testing.assert_allclose(cached.xy, rec.xy, atol=1e-4)
    np.testing.assert_allclose(cached.heading, rec.heading, atol=1e-4)
    np.testing.assert_allclose(cached.valid_logit, rec.valid_logit, atol=1e-4)
    np.testing.assert_array_equal(cached.valid, rec.valid)
    np.testing.assert_array_equal(cached.map_tokens, rec.map_tokens)
    # history is the log; the generated frames differ from it
    np.testing.assert_array_equal(cached.map_tokens[:, :, :h], np.broadcast_to(
        scenes.map_tokens[:, None, :h], cached.map_tokens[:, :, :h].shape))
    if temperature > 0:  # sampling actually used the key: some generated map token is not the argmax
        greedy = jax.jit(lambda s, sc, t: rollout_tasks(nnx.merge(graphdef, s), sc, t, jax.random.key(3), h))(
            state, scenes, tasks)
        assert (np.asarray(greedy.map_tokens) != np.asarray(cached.map_tokens)).any()


def test_tasks_take_log_slots_and_hide_agents(setup):
    graphdef, state, m, scenes = setup
    tasks = make_tasks(["all"], m.num_map_tokens, m.num_agents)
    out = jax.jit(lambda s, sc, t: rollout_tasks(nnx.merge(graphdef, s), sc, t, jax.random.key(0),
                                                 m.num_history))(state, scenes, jax.tree.map(jnp.asarray, tasks))
    h = m.num_history
    for i, name in enumerate(TASK_NAMES):
        map_log, ego_log, agents_log, hide = TASKS[name]
        o = jax.tree.map(lambda x: np.asarray(x[:, i, h:]), out)
        log_map = np.asarray(scenes.map_tokens[:, h:])
        if map_log:
            np.testing.assert_array_equal(o.map_tokens, log_map)
        else:  # map-generating tasks generate: the model's tokens, not the log's
            assert (o.map_tokens != log_map).any(), name
        if ego_log:
            np.testing.assert_array_equal(o.xy[:, :, 0], np.asarray(scenes.xy[:, h:, 0]))
            np.testing.assert_array_equal(o.valid[:, :, 0], np.asarray(scenes.valid[:, h:, 0]))
        else:
            assert not np.allclose(o.xy[:, :, 0], np.asarray(scenes.xy[:, h:, 0]))
        if agents_log:
            np.testing.assert_array_equal(o.xy[:, :, 1:], np.asarray(scenes.xy[:, h:, 1:]))
        if hide:
            assert not np.asarray(out.valid[:, i, :, 1:]).any()  # hidden in every frame, history too
            assert np.asarray(out.valid[:, i, :, 0]).all()


def test_one_trace_for_mixed_task_batches(setup):
    graphdef, state, m, scenes = setup
    h = m.num_history

    @jax.jit
    @chex.assert_max_traces(n=1)
    def run(state, scenes, tasks, keys):
        return rollout_batch(nnx.merge(graphdef, state), scenes, tasks, keys, h)

    keys = jax.random.split(jax.random.key(0), 3)
    mix_a = make_tasks(["scene_generation", "motion_planning", "map_prediction_ego_only"], m.num_map_tokens,
                       m.num_agents)
    mix_b = make_tasks(["closed_loop", "closed_loop", "traffic_simulation"], m.num_map_tokens, m.num_agents)
    out_a = run(state, scenes, mix_a, keys)
    out_b = run(state, scenes, mix_b, keys)  # different tasks, same compiled function
    assert out_a.xy.shape == out_b.xy.shape
    # each element of the mixed batch equals its own single-task rollout
    single = jax.jit(lambda s, sc, t: rollout(nnx.merge(graphdef, s), sc, t, jax.random.key(0), h))
    for i in range(3):
        one = single(state, jax.tree.map(lambda x: x[i], scenes), jax.tree.map(lambda x: x[i], mix_a))
        np.testing.assert_allclose(np.asarray(out_a.xy[i]), np.asarray(one.xy), atol=1e-4)


def test_xla_and_native_decode_attention_give_the_same_rollout(setup):
    """The rollout's two attention kernels give the same rollout (the other tests run the XLA path)."""
    from gpd_jax.model import native

    graphdef, state, m, scenes = setup
    if jax.default_backend() != "cpu" or not native.available():
        pytest.skip("the native attention kernel is unavailable here")
    tasks = make_tasks(["scene_generation", "closed_loop", "map_prediction"], m.num_map_tokens, m.num_agents)
    keys = jax.random.split(jax.random.key(0), 3)
    outs = {}
    for kernel in ("xla", "native"):
        model = nnx.merge(graphdef, state)
        model.decode_attention = kernel
        g = nnx.graphdef(model)
        outs[kernel] = jax.jit(lambda s, sc, t, k: rollout_batch(nnx.merge(g, s), sc, t, k, m.num_history))(
            state, scenes, tasks, keys)
    np.testing.assert_allclose(outs["xla"].xy, outs["native"].xy, atol=1e-4)
    np.testing.assert_array_equal(outs["xla"].map_tokens, outs["native"].map_tokens)
    np.testing.assert_array_equal(outs["xla"].valid, outs["native"].valid)


def test_mask_future_frames_do_not_leak(setup):
    """A token's output is unchanged when a later frame changes and changes when its own frame changes."""
    graphdef, state, m, scenes = setup
    sc = jax.tree.map(lambda x: jnp.asarray(x[0]), scenes)

    @jax.jit
    def hidden_of(state, xy, map_tokens):
        model = nnx.merge(graphdef, state)
        return forward(model, model.embed(xy, sc.heading, sc.valid, map_tokens, jnp.arange(m.num_frames)))

    base = hidden_of(state, sc.xy, sc.map_tokens)
    t = 4
    later = hidden_of(state, sc.xy.at[t + 1:, 0].add(5.0), sc.map_tokens.at[t + 1:].set(0))
    np.testing.assert_allclose(later[: t + 1], base[: t + 1], atol=1e-5)
    assert not np.allclose(later[t + 1:], base[t + 1:], atol=1e-3)
    # changing one agent of frame t changes every token of frame t (bi-directional within the frame)
    own = hidden_of(state, sc.xy.at[t, 0].add(5.0), sc.map_tokens)
    np.testing.assert_allclose(own[:t], base[:t], atol=1e-5)
    diff = np.abs(np.asarray(own[t] - base[t])).max(axis=-1)
    assert (diff > 1e-4).all(), diff


def test_unknown_task_is_a_clear_error():
    with pytest.raises(KeyError, match="unknown task 'planning'"):
        make_task("planning", 4, 3)


@pytest.fixture(scope="module")
def velocity_setup(tiny_config, tiny_scenes):
    from gpd_jax.model import GPD

    cfg = tiny_config.model.copy_and_resolve_references()
    cfg.predict_delta = True
    cfg.velocity_residual = True
    model = GPD(cfg, nnx.Rngs(1))
    return model, cfg, jax.tree.map(jnp.asarray, tiny_scenes)


def _cached_and_recompute(model, scene, task_names, m):
    """Both rollouts of one scene under each named task (one jitted call; outputs with a leading task dim)."""
    tasks = make_tasks(task_names, m.num_map_tokens, m.num_agents)
    graphdef, state = nnx.split(model)

    @jax.jit
    def both(state):
        mdl = nnx.merge(graphdef, state)
        key = jax.random.key(0)
        one = lambda t: (rollout(mdl, scene, t, key, m.num_history),
                         rollout_recompute(mdl, scene, t, key, m.num_history))
        return jax.vmap(one)(tasks)

    return both(state)


def _with_zero_heads(model, *heads):
    """A copy of `model` whose named heads output exactly 0 (last layer's kernel and bias zeroed)."""
    graphdef, state = nnx.split(model)
    mdl = nnx.merge(graphdef, jax.tree.map(lambda x: x, state))
    for name in heads:
        last = getattr(mdl, name).linears[-1]
        last.kernel[...] = jnp.zeros(last.kernel.shape)
        last.bias[...] = jnp.zeros(last.bias.shape)
    return mdl


def test_velocity_residual_cached_equals_recompute(velocity_setup):
    model, m, scenes = velocity_setup
    cached, rec = _cached_and_recompute(model, jax.tree.map(lambda x: x[0], scenes), ["scene_generation"], m)
    np.testing.assert_allclose(cached.xy, rec.xy, atol=1e-4)
    np.testing.assert_array_equal(cached.valid, rec.valid)


def test_velocity_residual_with_a_zero_head_is_constant_velocity(velocity_setup):
    model, m, scenes = velocity_setup
    mdl = _with_zero_heads(model, "pos_head")
    scene = jax.tree.map(lambda x: x[0], scenes)
    task = make_task("traffic_simulation", m.num_map_tokens, m.num_agents)
    out = jax.jit(lambda: rollout(mdl, scene, task, jax.random.key(0), m.num_history))()
    h = m.num_history
    # Agents the model keeps valid move on at their last history velocity, frame after frame.
    v = np.asarray(scene.xy[h - 1] - scene.xy[h - 2])
    both = np.asarray(scene.valid[h - 1] & scene.valid[h - 2] & out.valid[h:].all(0))
    assert both.any()
    for k in range(1, m.num_frames - h + 1):
        np.testing.assert_allclose(np.asarray(out.xy[h - 1 + k])[both],
                                   (np.asarray(scene.xy[h - 1]) + k * v)[both], atol=1e-3)


@pytest.fixture(scope="module")
def kinematic_setup(tiny_config, tiny_scenes):
    """A velocity_inputs model (positions regressed over xy + velocity * period) and scenes with velocities."""
    from gpd_jax.model import GPD

    cfg = tiny_config.model.copy_and_resolve_references()
    cfg.predict_delta = True
    cfg.velocity_residual = True
    cfg.velocity_inputs = True
    model = GPD(cfg, nnx.Rngs(2), frame_period_s=0.5)
    scenes = jax.tree.map(jnp.asarray, tiny_scenes).with_velocity(0.5)
    return model, cfg, scenes


def test_velocity_inputs_cached_equals_recompute(kinematic_setup):
    model, m, scenes = kinematic_setup
    scene = jax.tree.map(lambda x: x[0], scenes)
    cached, rec = _cached_and_recompute(model, scene, ["scene_generation", "closed_loop"], m)
    np.testing.assert_allclose(cached.xy, rec.xy, atol=1e-4)
    np.testing.assert_array_equal(cached.valid, rec.valid)
    # The velocity input matters: the same scene with other velocities rolls out differently.
    task = make_task("scene_generation", m.num_map_tokens, m.num_agents)
    other = jax.jit(lambda s: rollout(model, s, task, jax.random.key(0),
                                      m.num_history))(scene.replace(velocity=scene.velocity + 1.0))
    assert not np.allclose(other.xy[m.num_history:], cached.xy[0, m.num_history:], atol=1e-3)


def test_velocity_inputs_with_zero_heads_is_constant_velocity(kinematic_setup):
    """Zero position and velocity heads: every agent continues at its logged current velocity (m/s x period)."""
    model, m, scenes = kinematic_setup
    mdl = _with_zero_heads(model, "pos_head", "velocity_head")
    scene = jax.tree.map(lambda x: x[0], scenes)
    scene = scene.replace(velocity=scene.velocity.at[m.num_history - 1].set(jnp.array([3.0, -1.0])))
    task = make_task("traffic_simulation", m.num_map_tokens, m.num_agents)
    out = jax.jit(lambda: rollout(mdl, scene, task, jax.random.key(0), m.num_history))()
    h = m.num_history
    keep = np.asarray(scene.valid[h - 1] & out.valid[h:].all(0))
    assert keep.any()
    for k in range(1, m.num_frames - h + 1):
        np.testing.assert_allclose(np.asarray(out.xy[h - 1 + k])[keep],
                                   (np.asarray(scene.xy[h - 1]) + k * 0.5 * np.array([3.0, -1.0]))[keep], atol=1e-3)


def test_velocity_inputs_without_velocities_is_a_clear_error(kinematic_setup):
    model, m, scenes = kinematic_setup
    scene = jax.tree.map(lambda x: x[0], scenes).replace(velocity=None)
    task = make_task("traffic_simulation", m.num_map_tokens, m.num_agents)
    with pytest.raises(ValueError, match="velocity"):
        rollout(model, scene, task, jax.random.key(0), m.num_history)


def _pose_encoder(num_tokens: int, codebook: int):
    """A stand-in map encoder whose tokens depend on the pose (to 0.1 m / 0.1 rad) and on the lanes."""
    def enc(polylines, valid, pose):
        code = jnp.floor(pose[0] * 10) * 7 + jnp.floor(pose[1] * 10) * 3 + jnp.floor(pose[2] * 10) * 5
        code = code + jnp.floor(jnp.sum(jnp.where(valid[..., None], polylines, 0.0)))
        return (code.astype(jnp.int32) + jnp.arange(num_tokens)) % codebook
    return enc


def test_logged_map_is_re_encoded_around_the_generated_ego(setup):
    """With lanes + a pose encoder, tasks that take the map from the log but generate the ego get the log's
    lanes encoded at the generated ego pose; every other slot is what the plain rollout gives; cached ==
    recompute."""
    from gpd_jax.decoding import LogLanes

    graphdef, state, m, scenes = setup
    h, s = m.num_history, scenes.xy.shape[0]
    tasks = jax.tree.map(jnp.asarray, make_tasks(["all"], m.num_map_tokens, m.num_agents))
    rng = np.random.default_rng(0)
    lanes = LogLanes(jnp.asarray(rng.normal(0, 5, (s, 4, 6, 2)), jnp.float32), jnp.asarray(rng.random((s, 4, 6)) > 0.3))
    enc = _pose_encoder(m.num_map_tokens, m.codebook_size)

    @jax.jit
    def run(state, scenes, tasks, lanes):
        model = nnx.merge(graphdef, state)
        key = jax.random.key(1)
        plain = rollout_tasks(model, scenes, tasks, key, h)
        relaned = rollout_tasks(model, scenes, tasks, key, h, lanes=lanes, map_encoder=enc)
        rec = jax.vmap(lambda sc, ln: jax.vmap(lambda t: rollout_recompute(
            model, sc, t, key, h, lanes=ln, map_encoder=enc))(tasks))(scenes, lanes)
        return plain, relaned, rec

    plain, relaned, rec = jax.tree.map(np.asarray, run(state, scenes, tasks, lanes))
    np.testing.assert_array_equal(relaned.map_tokens, rec.map_tokens)
    np.testing.assert_allclose(relaned.xy, rec.xy, atol=1e-4)
    for i, name in enumerate(TASK_NAMES):
        map_log, ego_log = TASKS[name][:2]
        if not (map_log and not ego_log):  # untouched tasks: exactly the plain rollout
            for a, b in zip(jax.tree.leaves(relaned), jax.tree.leaves(plain)):
                np.testing.assert_array_equal(a[:, i], b[:, i], err_msg=name)
            continue
        np.testing.assert_array_equal(relaned.map_tokens[:, i, :h], plain.map_tokens[:, i, :h])  # history: log
        for j in range(s):
            for t in range(h, m.num_frames):
                pose = jnp.stack([relaned.xy[j, i, t, 0, 0], relaned.xy[j, i, t, 0, 1], relaned.heading[j, i, t, 0]])
                want = (np.asarray(enc(lanes.polylines[j], lanes.valid[j], pose)) if relaned.valid[j, i, t, 0]
                        else np.asarray(scenes.map_tokens[j, t]))
                np.testing.assert_array_equal(relaned.map_tokens[j, i, t], want, err_msg=f"{name} {j} {t}")
        assert (relaned.map_tokens[:, i, h:] != np.asarray(scenes.map_tokens[:, h:])).any(), name
    with pytest.raises(ValueError, match="needs both `lanes`"):
        rollout(nnx.merge(graphdef, state), jax.tree.map(lambda x: x[0], scenes),
                jax.tree.map(lambda x: x[0], tasks), jax.random.key(0), h, map_encoder=enc)


def _stand_in_warp(num_tokens: int, codebook: int):
    """A stand-in map warp: tokens depend on the anchor's tokens and both poses; cells 0-7 are always new."""
    def warp(tokens, anchor_pose, pose):
        code = jnp.floor((pose - anchor_pose) * 10) @ jnp.array([7.0, 3.0, 5.0])
        return (tokens + code.astype(jnp.int32) + 1) % codebook, jnp.arange(num_tokens) < 8
    return warp


def test_generated_map_moves_with_the_ego(setup):
    """With a map warp, generated map slots are the warp of the anchor's map (the last frame whose map was
    given: the last history frame, or a later frame a prompt gives the map of) from the anchor's ego to this
    frame's, except in new cells (the model's tokens); maps taken from the log are untouched; cached ==
    recompute."""
    from gpd_jax.prompts import as_prompt

    graphdef, state, m, scenes = setup
    h, s, t_total = m.num_history, scenes.xy.shape[0], m.num_frames
    tasks = make_tasks(["all"], m.num_map_tokens, m.num_agents)
    prompts = as_prompt(tasks, t_total)
    given_at = h + 1  # an extra prompt: map prediction with the map of frame h + 1 given
    mp = TASK_NAMES.index("map_prediction")
    extra = jax.tree.map(lambda x: np.asarray(x)[mp:mp + 1].copy(), prompts)
    extra.from_log[0, given_at, :m.num_map_tokens] = True
    prompts = jax.tree.map(lambda a, b: jnp.asarray(np.concatenate([np.asarray(a), b])), prompts, extra)
    names = list(TASK_NAMES) + ["map_prediction, map given at h+1"]
    warp = _stand_in_warp(m.num_map_tokens, m.codebook_size)

    @jax.jit
    def run(state, scenes, prompts):
        model = nnx.merge(graphdef, state)
        key = jax.random.key(1)
        plain = rollout_tasks(model, scenes, prompts, key, h)
        warped = rollout_tasks(model, scenes, prompts, key, h, map_warp=warp)
        rec = jax.vmap(lambda sc: jax.vmap(lambda t: rollout_recompute(model, sc, t, key, h, map_warp=warp))(
            prompts))(scenes)
        return plain, warped, rec

    plain, warped, rec = jax.tree.map(np.asarray, run(state, scenes, prompts))
    np.testing.assert_array_equal(warped.map_tokens, rec.map_tokens)
    np.testing.assert_allclose(warped.xy, rec.xy, atol=1e-4)
    checked = {}  # frames checked with both egos valid (the tiny model's own egos may all be invalid)
    for i, name in enumerate(names):
        if name in TASKS and TASKS[name][0]:  # the map comes from the log: exactly the plain rollout
            for a, b in zip(jax.tree.leaves(warped), jax.tree.leaves(plain)):
                np.testing.assert_array_equal(a[:, i], b[:, i], err_msg=name)
            continue
        np.testing.assert_array_equal(warped.map_tokens[:, i, :h], plain.map_tokens[:, i, :h])
        # the first generated frame's new cells are the model's prediction from the same history
        np.testing.assert_array_equal(warped.map_tokens[:, i, h, :8], plain.map_tokens[:, i, h, :8])
        checked[name] = 0
        for j in range(s):
            pose = lambda f: jnp.stack([warped.xy[j, i, f, 0, 0], warped.xy[j, i, f, 0, 1],
                                        warped.heading[j, i, f, 0]])
            for t in range(h, t_total):
                if name not in TASKS and t == given_at:
                    np.testing.assert_array_equal(warped.map_tokens[j, i, t], scenes.map_tokens[j, t])
                    continue
                a = given_at if name not in TASKS and t > given_at else h - 1
                if not (warped.valid[j, i, t, 0] and warped.valid[j, i, a, 0]):
                    continue
                want, _ = warp(jnp.asarray(warped.map_tokens[j, i, a]), pose(a), pose(t))
                np.testing.assert_array_equal(warped.map_tokens[j, i, t, 8:], np.asarray(want)[8:],
                                              err_msg=f"{name} {j} {t}")
                checked[name] += 1
        if checked[name]:
            assert (warped.map_tokens[:, i, h:] != plain.map_tokens[:, i, h:]).any(), name
    assert checked["map_prediction"] and checked[names[-1]], checked


def test_a_batched_rollout_holds_little_beyond_its_cache():
    """Compiled memory (XLA's analysis, on a CPU too) of a batched rollout with a 21-frame history: the history goes
    in frame by frame, so a scenario's temporaries stay near its KV cache (the one-block prefill held its
    [H, 21 N, chunk] scores and [21 N, ffn] activations: 5.3 cache sizes here), and, on an accelerator, a bfloat16
    cache takes less."""
    from gpd_jax.bench import memory_figures
    from gpd_jax.config import load_config
    from gpd_jax.model import GPD
    from gpd_jax.synthetic import synthetic_scenes

    cfg = load_config("configs/gpd_tiny.py:test", ["--config.model.num_frames=41", "--config.model.num_history=21",
                                                   "--config.model.ffn_dim=512"])
    m, b = cfg.model, 4
    scenes = synthetic_scenes(0, b, m.num_frames, m.num_history, m.num_agents, m.num_map_tokens, m.codebook_size)
    tasks = make_tasks(["traffic_simulation"] * b, m.num_map_tokens, m.num_agents)
    keys = jax.random.split(jax.random.key(0), b)
    temp = {}
    for dtype in ("float32", "bfloat16"):
        model = GPD(m, nnx.Rngs(0))
        model.decode_attention, model.decode_dtype = "xla_batched", dtype
        g, st = nnx.split(model)
        fn = jax.jit(lambda s, sc, t, k: rollout_batch(nnx.merge(g, s), sc, t, k, m.num_history))
        temp[dtype] = memory_figures(fn.lower(st, scenes, tasks, keys).compile(), b)["temp_bytes_per_scenario"]
    cache = 2 * m.num_layers * model.padded_len(m.num_frames) * m.d_model * 4
    assert temp["float32"] < 1.6 * cache, (temp, cache)  # 1.34 measured
    if jax.default_backend() != "cpu":  # XLA:CPU has no bf16 arithmetic: it keeps an f32 copy of each layer's cache
        assert temp["bfloat16"] < 0.75 * temp["float32"], temp


_SHARDED_SCRIPT = r"""
import sys
sys.path.insert(0, {tests!r})
import jax, jax.numpy as jnp, numpy as np
from flax import nnx
from gpd_jax.config import load_config
from gpd_jax.decoding import rollout_jit, rollout_prepared
from gpd_jax.model import GPD
from gpd_jax.options import RolloutOptions
from gpd_jax.synthetic import synthetic_scenes
from gpd_jax.tasks import make_tasks

assert jax.local_device_count() == 4
m = load_config("configs/gpd_tiny.py:test").model
graphdef, params, rest = nnx.split(GPD(m, nnx.Rngs(0)), nnx.Param, ...)
scenes = jax.tree.map(jnp.asarray, synthetic_scenes(0, 8, m.num_frames, m.num_history, m.num_agents,
                                                    m.num_map_tokens, m.codebook_size))
tasks = jax.tree.map(jnp.asarray, make_tasks(["all"], m.num_map_tokens, m.num_agents))
opts = RolloutOptions(temperature=1.0)  # sampled map tokens: each pair's key must be the one device's
key = jax.random.key(5)
sharded = rollout_jit(graphdef, params, rest, scenes, tasks, key, m.num_history, opts)
one = jax.jit(lambda p, sc, t, k: rollout_prepared(nnx.merge(graphdef, p, rest), sc, t, k, m.num_history, opts))(
    params, scenes, tasks, key)
assert len(sharded.xy.sharding.device_set) == 4, sharded.xy.sharding
np.testing.assert_allclose(np.asarray(sharded.xy), np.asarray(one.xy), rtol=1e-5, atol=1e-4)
np.testing.assert_array_equal(np.asarray(sharded.map_tokens), np.asarray(one.map_tokens))
np.testing.assert_array_equal(np.asarray(sharded.valid), np.asarray(one.valid))
odd = rollout_jit(graphdef, params, rest, jax.tree.map(lambda x: x[:3], scenes), tasks, key, m.num_history, opts)
assert odd.xy.shape[0] == 3 and len(odd.xy.sharding.device_set) == 3  # 3 scenarios: the 3 devices that divide them
print("OK")
"""


def test_rollout_is_split_over_local_devices_with_one_devices_results(tmp_path):
    """rollout_jit (what gpd_jax.rollout, evaluate and rollout.py run) splits the scenarios over 4 forced CPU
    devices; outputs equal one device's, sampled map tokens included (each (scenario, task) keeps its key)."""
    import os
    import subprocess
    import sys

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    script = tmp_path / "sharded.py"
    script.write_text(_SHARDED_SCRIPT.format(tests=os.path.dirname(os.path.abspath(__file__))))
    env = dict(os.environ, XLA_FLAGS=os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4",
               JAX_PLATFORMS="cpu")
    r = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, cwd=root, timeout=600)
    assert r.returncode == 0 and "OK" in r.stdout, r.stdout[-2000:] + r.stderr[-4000:]
