"""`model.agent_lane_residual` (not in the paper): the heads' base is an agent that keeps the lane it is on, walked
along the vector lanes where they are given (`gpd_jax.geometry.lane_trace` / `lane_follow`)."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from gpd_jax.config import load_config
from gpd_jax.decoding import lane_context, rollout_recompute, rollout_tasks
from gpd_jax.geometry import lane_trace
from gpd_jax.model import GPD, LaneContext
from gpd_jax.prompts import as_prompt, make_prompt
from gpd_jax.synthetic import synthetic_scenes
from gpd_jax.tasks import TASK_NAMES, make_tasks
from gpd_jax.training.step import batch_loss

from conftest import ROOT


def _arc(radius, start, stop, n=128, centre=(0.0, 0.0)):
    th = np.linspace(start, stop, n)
    return np.stack([centre[0] + radius * np.cos(th), centre[1] + radius * np.sin(th)], -1).astype(np.float32)


# ------------------------------------------------------------------------------------------------ the walk
def test_walk_follows_the_lane_that_runs_the_agents_way():
    inner = _arc(30.0, 0.0, np.pi)  # counter-clockwise
    outer = _arc(33.5, np.pi, 0.0)  # the opposing lane, clockwise, 3.5 m outside
    lanes, valid = jnp.asarray(np.stack([inner, outer])), jnp.ones((2, 128), bool)
    # a car between the two, nearer the opposing lane, heading counter-clockwise: it keeps its own lane
    xy, heading = jnp.array([[32.5, 0.5]]), jnp.array([np.pi / 2])
    pts, lane_h, dist = lane_trace(lanes, valid, xy, heading, 5.0, 4)
    r = np.hypot(pts[0, :, 0], pts[0, :, 1])
    np.testing.assert_allclose(r, 30.0, atol=0.05)
    # each step moves ~5 m along the arc, the heading turns with it (tangent = angle + pi/2)
    ang = np.unwrap(np.arctan2(pts[0, :, 1], pts[0, :, 0]))
    np.testing.assert_allclose(np.diff(ang) * 30.0, 5.0, rtol=0.05)
    np.testing.assert_allclose(np.unwrap(lane_h[0]), ang + np.pi / 2, atol=0.03)
    assert abs(float(dist[0, 0]) - 2.5) < 0.05 and float(dist[0, 1:].max()) < 0.5
    # the same car heading the other way takes the opposing lane
    pts2, lane_h2, _ = lane_trace(lanes, valid, xy, heading + np.pi, 5.0, 4)
    np.testing.assert_allclose(np.hypot(pts2[0, :, 0], pts2[0, :, 1]), 33.5, atol=0.05)
    # coarser segments (every 4th point) move the walk by centimetres only
    pts4, _, _ = lane_trace(lanes, valid, xy, heading, 5.0, 4, stride=4)
    assert float(jnp.abs(pts4 - pts).max()) < 0.1


def test_walk_without_lanes_stays_put_with_infinite_distance():
    lanes, valid = jnp.zeros((3, 8, 2)), jnp.zeros((3, 8), bool)
    xy, heading = jnp.array([[1.0, 2.0], [3.0, -4.0]]), jnp.array([0.3, -2.0])
    pts, lane_h, dist = lane_trace(lanes, valid, xy, heading, 5.0, 2)
    assert pts.shape == (2, 3, 2) and np.isinf(np.asarray(dist)).all()
    np.testing.assert_allclose(lane_h, np.repeat(np.asarray(heading)[:, None], 3, 1), atol=1e-6)


# ------------------------------------------------------------------------------------------------ the model
def _cfg():
    """The tiny test model with the lane residual (over constant velocity's step from the last two frames)."""
    c = load_config(f"{ROOT}/configs/gpd_tiny.py:test")
    c.model.predict_delta = c.model.velocity_residual = c.model.agent_lane_residual = True
    c.model.lane_context_stride = 2
    return c


def _scenes(cfg, n=2):
    m = cfg.model
    sc = synthetic_scenes(3, n, m.num_frames, m.num_history, m.num_agents, m.num_map_tokens, m.codebook_size)
    # three concentric arcs and a straight road through the scene frame, a lane slot left empty
    lines = np.zeros((5, 64, 2), np.float32)
    ok = np.zeros((5, 64), bool)
    for i, r in enumerate((20.0, 30.0, 40.0)):
        lines[i] = _arc(r, -np.pi, np.pi, 64)
        ok[i] = True
    lines[3] = np.stack([np.linspace(-60, 60, 64), np.zeros(64)], -1)
    ok[3, :50] = True
    return sc.replace(polylines=np.broadcast_to(lines, (n,) + lines.shape).copy(),
                      polyline_valid=np.broadcast_to(ok, (n,) + ok.shape).copy())


def _bends_through_agents(scenes, t: int, radius: float = 15.0):
    """`scenes` whose lanes are one left bend per agent slot, tangent to its motion at frame t (its heading when it
    stands; zero lanes for slots invalid there)."""
    n, a = scenes.xy.shape[0], scenes.xy.shape[2]
    lines, ok = np.zeros((n, a, 64, 2), np.float32), np.zeros((n, a, 64), bool)
    for i in range(n):
        for j in range(a):
            if not (scenes.valid[i, t, j] and scenes.valid[i, t - 1, j]):
                continue
            d = scenes.xy[i, t, j] - scenes.xy[i, t - 1, j]
            h = np.arctan2(d[1], d[0]) if np.hypot(*d) > 1e-6 else scenes.heading[i, t, j]
            centre = scenes.xy[i, t, j] + radius * np.array([-np.sin(h), np.cos(h)])
            start = h - np.pi / 2  # the agent's angle on the circle around the centre; counter-clockwise ahead
            lines[i, j], ok[i, j] = _arc(radius, start - 0.5, start + np.pi, 64, centre), True
    return scenes.replace(polylines=lines, polyline_valid=ok)


def test_rollout_reads_lanes_where_the_map_is_given_cached_equals_recompute_one_compile():
    chex.clear_trace_counter()  # the trace count is per test case
    cfg = _cfg()
    m = cfg.model
    model = GPD(cfg.model, nnx.Rngs(0))
    # the synthetic agents stand off the arcs: give each a bend through where it is at frame H - 1
    scenes = _bends_through_agents(_scenes(cfg), m.num_history - 1)
    model.valid_head.linears[-1].bias[...] = jnp.full((1,), 10.0)  # agents stay, so their lane steps add up
    scenes = jax.tree.map(jnp.asarray, scenes)
    tasks = jax.tree.map(jnp.asarray, make_tasks(["all"], m.num_map_tokens, m.num_agents))
    h = m.num_history
    # the frames with lanes: every frame where the map comes from the log, the history only where generated
    one = jax.tree.map(lambda x: x[0], scenes)
    for i, name in enumerate(TASK_NAMES):
        ctx = lane_context(model, one, as_prompt(jax.tree.map(lambda x: x[i], tasks), m.num_frames), h)
        on = np.asarray(ctx.on)
        assert on[:h].all(), name
        assert on[h:].all() == (not name.startswith(("scene_generation", "map_prediction"))), name
        assert on[h:].any() == on[h:].all(), name
    assert lane_context(model, one.replace(polylines=None, polyline_valid=None),
                        as_prompt(jax.tree.map(lambda x: x[0], tasks), m.num_frames), h) is None
    graphdef, state = nnx.split(model)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def both(state, scenes, tasks):
        mod = nnx.merge(graphdef, state)
        key = jax.random.key(0)
        cached = rollout_tasks(mod, scenes, tasks, key, h)
        rec = jax.vmap(lambda sc: jax.vmap(lambda t: rollout_recompute(mod, sc, t, key, h))(tasks))(scenes)
        plain = rollout_tasks(mod, scenes.replace(polylines=None, polyline_valid=None), tasks, key, h)
        return cached, rec, plain

    cached, rec, plain = both(state, scenes, tasks)
    both(state, scenes, tasks)  # the one trace serves again
    # which lane a walk takes, and whether one lies within LANE_SNAP_M, switch at thresholds: float-level
    # differences between the batched paths can flip them for the random model's wandering agents, rarely
    np.testing.assert_allclose(cached.xy[:, :, h], rec.xy[:, :, h], atol=1e-3, rtol=1e-4)
    assert np.isclose(cached.xy, rec.xy, atol=1e-3, rtol=1e-4).mean() > 0.99
    np.testing.assert_array_equal(cached.valid, rec.valid)
    np.testing.assert_array_equal(cached.map_tokens, rec.map_tokens)
    # in traffic simulation the lanes change the generated agents (the log's lanes are read), not the history
    k = TASK_NAMES.index("traffic_simulation")
    gen = np.asarray(cached.valid & plain.valid)[:, k, h:, 1:]
    moved = np.abs(np.asarray(cached.xy - plain.xy))[:, k, h:, 1:].max(-1) > 1e-3
    assert moved[gen].mean() > 0.5
    np.testing.assert_array_equal(cached.xy[:, :, :h], plain.xy[:, :, :h])


def test_a_prompts_own_lanes_replace_the_logs_for_its_agents():
    cfg = _cfg()
    m = cfg.model
    model = GPD(cfg.model, nnx.Rngs(0))
    one = jax.tree.map(lambda x: np.asarray(x[0]), _scenes(cfg))
    road = [[[-50.0, 5.0], [50.0, 5.0]], [[-50.0, -5.0], [0.0, -5.0], [40.0, 20.0]]]
    p = make_prompt(one, m.num_history, lanes=road)
    ctx = lane_context(model, jax.tree.map(jnp.asarray, one), jax.tree.map(jnp.asarray, p), m.num_history)
    assert np.asarray(ctx.on).all()
    pts = np.asarray(ctx.polylines)[np.asarray(ctx.valid)]
    # every readable point lies on the drawn lanes: none of the log's arcs is left
    segs = [(np.array(a_), np.array(b_)) for line in road for a_, b_ in zip(line[:-1], line[1:])]

    def off_road(q):
        return min(np.linalg.norm(q - (a_ + np.clip(np.dot(q - a_, b_ - a_) / np.dot(b_ - a_, b_ - a_), 0, 1)
                                       * (b_ - a_))) for a_, b_ in segs)

    assert len(pts) > 10 and max(off_road(q) for q in pts) < 1e-3


def test_lane_residual_moves_the_base_along_the_lane_keeping_the_offset():
    """`agent_lane_residual`: the heads' base is constant velocity's step walked along the lane (the walk steps
    along the tangent and projects back: on a circle of radius R a step s lands at angle atan(s / R)), the offset
    from the lane kept, heading and velocity turned with it; far from lanes and in frames without lanes it stays
    constant velocity's."""
    cfg = _cfg()
    cfg.model.velocity_inputs = True
    cfg.model.lane_context_stride = 1
    plain_cfg = cfg.copy_and_resolve_references()
    plain_cfg.model.agent_lane_residual = False
    lane_model, plain = GPD(cfg.model, nnx.Rngs(0), frame_period_s=1.0), GPD(plain_cfg.model, nnx.Rngs(0),
                                                                              frame_period_s=1.0)
    r = 30.0
    lanes = LaneContext(jnp.asarray(_arc(r, -np.pi / 2, np.pi, 512))[None], jnp.ones((1, 512), bool),
                        jnp.array([True]))
    a = cfg.model.num_agents
    xy = np.full((1, a, 2), np.nan, np.float32)
    xy[0, :3] = [[r, 0.0], [r + 1.0, 0.0], [100.0, 100.0]]  # on the lane, 1 m outside it, far from it
    heading = np.zeros((1, a), np.float32)
    heading[0, :3] = np.pi / 2
    vel = np.zeros((1, a, 2), np.float32)
    vel[0, :3] = [0.0, 10.0]
    valid = np.zeros((1, a), bool)
    valid[0, :3] = True
    hidden = jax.random.normal(jax.random.key(2), (1, cfg.model.num_map_tokens + a, cfg.model.d_model))
    args = (hidden, jnp.asarray(xy), jnp.asarray(heading), jnp.asarray(valid), None, None, jnp.asarray(vel))
    on, cv = lane_model.predict(*args, lanes=lanes), plain.predict(*args)
    # the base moved from constant velocity's (xy + v) to the lane's: the heads' outputs are the same
    base = np.asarray(on.xy - cv.xy)[0, :3] + (xy[0, :3] + vel[0, :3])
    turn = np.arctan(10.0 / r)
    for i, radius in enumerate((r, r + 1.0)):
        assert abs(np.hypot(*base[i]) - radius) < 0.02, (i, base[i])
        assert abs(np.arctan2(base[i, 1], base[i, 0]) - turn) < 0.01, (i, base[i])
    np.testing.assert_allclose(base[2], [100.0, 110.0], atol=1e-4)
    np.testing.assert_allclose(np.asarray(on.heading - cv.heading)[0, :3], [turn, turn, 0.0], atol=0.01)
    dv = np.asarray(on.velocity - cv.velocity)[0, :3]
    np.testing.assert_allclose(dv[:2], np.tile([-10 * np.sin(turn), 10 * np.cos(turn) - 10], (2, 1)), atol=0.1)
    np.testing.assert_allclose(dv[2], 0.0, atol=1e-5)
    assert np.isfinite(np.asarray(on.xy)[0, :3]).all()
    # a frame without lanes is constant velocity's
    off = lane_model.predict(*args, lanes=lanes.replace(on=jnp.array([False])))
    np.testing.assert_array_equal(np.asarray(off.xy), np.asarray(cv.xy))
    with pytest.raises(ValueError, match="velocity_residual"):
        bad = _cfg()
        bad.model.velocity_residual = False
        GPD(bad.model, nnx.Rngs(0))


# ------------------------------------------------------------------------------------------------ training
def test_training_reads_the_lanes_and_drops_them_from_a_share_of_the_futures():
    cfg = _cfg()
    m = cfg.model
    model = GPD(cfg.model, nnx.Rngs(0))
    scenes = jax.tree.map(jnp.asarray, _bends_through_agents(_scenes(cfg, 4), m.num_history))
    graphdef, state = nnx.split(model)
    # jitted (one compile per drop share) rather than op by op: the same loss, a fraction of the time
    position = jax.jit(lambda st, sc, drop: batch_loss(nnx.merge(graphdef, st), sc, cfg.loss, m.num_history, 0, 0.0,
                                                       drop)[1]["position"], static_argnums=2)
    loss = lambda sc, drop: float(position(state, sc, drop))
    full, none = loss(scenes, 0.0), loss(scenes, 1.0)
    assert np.isfinite(full) and np.isfinite(none) and full != none
    # dropping lanes from every scene's future equals a context that is off there (frames >= H)
    with pytest.raises(ValueError, match="polylines"):
        loss(scenes.replace(polylines=None, polyline_valid=None), 0.0)


def test_fine_tune_switches_the_lane_residual_on_over_a_model_without_it(tmp_path):
    """The lane residual adds no parameters: a fine-tune that switches it on starts from the source's own; any other
    difference in the model config is refused, naming the field."""
    from gpd_jax.checkpoint import build_model, export_model
    from gpd_jax.training.loop import initial_params

    res = _cfg()
    src = str(tmp_path / "src")
    plain = res.copy_and_resolve_references()
    plain.model.agent_lane_residual = False
    export_model(nnx.state(build_model(plain, seed=7), nnx.Param), plain, src)
    chex.assert_trees_all_equal(initial_params(src, res), initial_params(src, plain))
    res.model.num_layers = 1
    with pytest.raises(ValueError, match="num_layers"):
        initial_params(src, res)


def test_walk_goes_on_straight_where_its_lane_ends_with_a_gap_limit():
    lane = np.stack([np.linspace(0.0, 20.0, 21), np.zeros(21)], -1).astype(np.float32)  # ends at x = 20
    lanes, valid = jnp.asarray(lane[None]), jnp.ones((1, 21), bool)
    xy, heading = jnp.array([[2.0, 0.5]]), jnp.array([0.0])
    stall, _, _ = lane_trace(lanes, valid, xy, heading, 8.0, 4)
    np.testing.assert_allclose(np.asarray(stall[0, -2:, 0]), 20.0, atol=1e-4)  # pulled back to the lane's end
    on, h, dist = lane_trace(lanes, valid, xy, heading, 8.0, 4, max_gap_m=4.0)
    np.testing.assert_allclose(np.asarray(on[0, :, 0]), [2.0, 10.0, 18.0, 26.0, 34.0], atol=1e-4)
    np.testing.assert_allclose(np.asarray(on[0, :, 1]), 0.0, atol=1e-5)
    np.testing.assert_allclose(np.asarray(dist[0, 3:]), [6.0, 14.0], atol=1e-4)
