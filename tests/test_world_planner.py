"""The world planner (gpd_jax.sim.world_planner): candidates, the futures the world model imagines for them, their
scores, and the policy in the simulator.

A hand-built straight two-way road (test_sim's): the ego at 10 m/s in the right lane, a follower 25 m behind it and
a car parked 35 m ahead in the ego's lane. The world model is the shipped sampling model.
"""

from __future__ import annotations

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpd_jax
from gpd_jax import sim
from gpd_jax.sim import world_planner as W

from test_sim import _lanes, straight_scenes

PARKED_X = 35.0
SMALL = W.WorldPlannerOptions(samples=2, horizon=4, speeds=(4.0, 10.0), side_speeds=(), nudges_m=(),
                              lane_width_m=0.0, use_head=False)


def parked_scenes(n: int = 2):
    """test_sim's straight scenes with a car parked PARKED_X m ahead of the ego in its lane (slot 2)."""
    sc = straight_scenes(n)
    xy, valid = sc.xy.copy(), sc.valid.copy()
    xy[:, :, 2] = (PARKED_X, -1.6)
    valid[:, :, 2] = True
    return sc.replace(xy=xy, valid=valid)


@pytest.fixture(scope="module")
def world():
    return gpd_jax.load_model("gpd_sampling")


@pytest.fixture(scope="module")
def sims(world):
    return sim.make_sim_scenes(world, parked_scenes(2))


@pytest.fixture(scope="module")
def obs(world, sims):
    """The observation at the current frame of the first scene, and the world model's state after that frame."""
    one = jax.tree.map(lambda x: x[0], sims)
    state = sim.reset(world, one, agents="log")
    return sim.observe(world, state), state.decode


def _straight(v0: float, accel: float, n: int = 80, dt: float = 0.1):
    """Stored-rate poses along the right lane from x = 0 at v0 with a constant acceleration (stopping at 0)."""
    t = np.arange(1, n + 1) * dt
    stop = np.inf if accel >= 0 else v0 / -accel
    tt = np.minimum(t, stop)
    x = v0 * tt + 0.5 * accel * tt ** 2
    return np.stack([x, np.full(n, -1.6), np.zeros(n)], -1).astype(np.float32)


def _two(into_car, braking):
    return W.Candidates(poses=jnp.asarray(np.stack([into_car, braking])), valid=jnp.ones(2, bool))


def test_the_scorer_picks_braking_over_driving_into_a_parked_car(world, obs):
    o, decode = obs
    spec = world.spec
    cands = _two(_straight(10.0, 0.0), _straight(10.0, -4.0))
    parts = sim.core._parts(world)
    for futures, opts in ((W.cv_futures(o, spec, SMALL, 2), SMALL),
                          (W.gpd_futures(parts, decode, o, spec, SMALL, cands.poses, jax.random.key(0)), SMALL)):
        sc = W.candidate_scores(o, spec, opts, cands, futures)
        assert int(jnp.argmax(sc["score"])) == 1, sc
        assert np.all(np.asarray(sc["no_ego_at_fault_collisions"][0]) == 0.0)   # into the car in every future
        assert np.all(np.asarray(sc["no_ego_at_fault_collisions"][1]) == 1.0)
        assert float(sc["score"][1]) > 0.0 == float(sc["score"][0])


def test_futures_differ_between_candidates_where_the_agents_react(world, obs):
    o, decode = obs
    spec = world.spec
    cands = _two(_straight(10.0, 0.0), _straight(10.0, -4.0))
    parts = sim.core._parts(world)
    greedy = dataclasses.replace(SMALL, temperature=0.0, samples=1)
    f = W.gpd_futures(parts, decode, o, spec, greedy, cands.poses, jax.random.key(0))
    n = greedy.horizon * spec.frame_stride
    assert f.xy.shape == (2, 1, n + 1, spec.num_agents, 2)
    np.testing.assert_allclose(np.asarray(f.xy[:, 0, 1:, 0]), np.asarray(cands.poses[:, :n, :2]), atol=1e-5)
    # the follower behind a braking ego falls back; behind the one that drives on it does not
    follower = np.asarray(f.xy[:, 0, -1, 1, 0])
    assert follower[0] - follower[1] > 1.0, follower
    # the same candidates at temperature 0.5: the K futures are draws, not copies
    f2 = W.gpd_futures(parts, decode, o, spec, SMALL, cands.poses, jax.random.key(1))
    assert float(jnp.max(jnp.abs(f2.xy[:, 0, -1, 1:] - f2.xy[:, 1, -1, 1:]))) > 0.05


def test_neighbouring_lanes_are_candidates_only_where_the_map_has_them(world, obs):
    o, _ = obs
    opts = W.WorldPlannerOptions(speeds=(5.0,), side_speeds=(5.0,), nudges_m=(1.0,), lane_width_m=3.2, max_decel=0.0)
    # the two-way road: left of the ego runs the oncoming lane, right of it is the kerb: no lane change
    c = W.candidate_plans(o, world.spec, opts)
    assert c.poses.shape == (5, world.spec.num_future * world.spec.frame_stride, 3)
    np.testing.assert_array_equal(np.asarray(c.valid), [True, True, True, False, False])
    # the left lane turned to the ego's direction: changing into it is a candidate, and it ends up there
    lanes, lv = _lanes()
    lanes[1] = lanes[1][::-1]
    road = o.road.replace(lanes=jnp.asarray(lanes), lane_valid=jnp.asarray(lv))
    c = W.candidate_plans(o.replace(road=road), world.spec, opts)
    np.testing.assert_array_equal(np.asarray(c.valid), [True, True, True, True, False])
    left = np.asarray(c.poses[3])
    np.testing.assert_allclose(left[-1, 1], 1.6, atol=0.05)
    assert np.all(np.diff(left[:, 1]) >= -1e-4)                                 # a smooth move to the left


def test_jerk_limited_candidates_start_at_the_ego_acceleration(world, obs):
    o, _ = obs
    spec, dt = world.spec, world.spec.stored_period_s
    opts = dataclasses.replace(SMALL, speeds=(1.0, 13.89), max_jerk=3.0, max_decel=0.0)
    free = W.candidate_plans(o, spec, dataclasses.replace(opts, max_jerk=0.0)).poses
    for a0 in (0.0, -2.0):
        poses = np.asarray(W.candidate_plans(o, spec, opts, jnp.float32(a0)).poses)
        xy = np.concatenate([np.broadcast_to(np.asarray(o.ego_pose[:2]), (2, 1, 2)), poses[:, :, :2]], 1)
        v = np.linalg.norm(np.diff(xy, axis=1), axis=-1) / dt                  # [C, N]
        a = np.diff(np.concatenate([np.full((2, 1), 10.0), v], 1), axis=1) / dt
        moving = v[:, 1:] > 0.05                                                # a stop ends the braking
        assert np.all(np.abs(a[:, 0] - a0) <= 3.0 * dt + 0.05), a[:, :3]       # continuous with the ego's
        jerk = np.abs(np.diff(a, axis=1))[moving] / dt
        assert jerk.max() <= 3.0 + 0.5, jerk.max()
        assert a[0].min() < a0 - 1.0                                            # it does brake, gradually
    # without the limit the slow candidate brakes hard at once (IDM far above its target speed)
    vf = np.linalg.norm(np.diff(np.asarray(free[0, :3, :2]), axis=0), axis=-1) / dt
    assert vf[0] < 10.0 - 0.5


def test_the_held_plan_is_the_last_one_moved_on_a_model_frame(world):
    spec = world.spec
    n, s = spec.num_future * spec.frame_stride, spec.frame_stride
    plan = jnp.asarray(_straight(8.0, 0.0, n))
    held = np.asarray(W.held_plan(plan, spec))
    assert held.shape == (n, 3)
    np.testing.assert_allclose(held[: n - s], np.asarray(plan[s:]), atol=1e-5)
    np.testing.assert_allclose(np.diff(held[:, 0]), 0.8, rtol=1e-4)         # continued at its last velocity


def test_the_policy_is_one_compiled_step_and_stops_for_the_parked_car(world, sims):
    pol = W.world_planner_policy(world, None, SMALL)        # the shipped smoothing: jerk limit, held plan, stop
    traced = dataclasses.replace(pol, select=chex.assert_max_traces(pol.select, n=1))
    chex.clear_trace_counter()
    out = sim.run(world, sims, traced, jax.random.key(0), agents="log")
    again = sim.run(world, jax.tree.map(lambda x: x[::-1], sims), traced, jax.random.key(1), agents="log")
    sc = sim.score(world, sims, out)
    assert np.all(np.asarray(sc["no_ego_at_fault_collisions"]) == 1.0), sc
    ego = np.asarray(out.fine_xy[:, :, 0, 0])
    assert np.all(ego[:, -1] < PARKED_X - 4.0)                                   # stopped behind the car
    assert np.all(np.isfinite(np.asarray(again.fine_xy[:, :, 0])))
    assert np.asarray(out.plan).shape == (2, world.spec.num_future, 3)


def test_world_planner_options_are_checked():
    with pytest.raises(sim.SimError, match="scorer"):
        W.WorldPlannerOptions(scorer="oracle")
    with pytest.raises(sim.SimError, match="samples"):
        W.WorldPlannerOptions(samples=0)
    with pytest.raises(sim.SimError, match="unknown world planner"):
        W.make_world_policy("gpd_world_x", None)


def test_plan_command_rejects_bad_world_samples(capsys):
    from gpd_jax.plan.__main__ import main

    assert main(["evaluate", "--data", "nowhere", "--out", "x", "--planners", "gpd_world",
                 "--world-samples", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--world-samples" in err[0], err


def test_braking_is_bounded_and_an_emergency_stop_is_a_candidate(world, obs):
    o, _ = obs
    spec, dt = world.spec, world.spec.stored_period_s
    opts = dataclasses.replace(SMALL, speeds=(1.0,), max_jerk=0.0, max_decel=3.0)
    c = W.candidate_plans(o, spec, opts)
    assert c.poses.shape[0] == 2 and bool(jnp.all(c.valid))
    xy = np.concatenate([np.broadcast_to(np.asarray(o.ego_pose[:2]), (2, 1, 2)), np.asarray(c.poses[:, :, :2])], 1)
    v = np.linalg.norm(np.diff(xy, axis=1), axis=-1) / dt
    a = np.diff(np.concatenate([np.full((2, 1), 10.0), v], 1), axis=1) / dt
    assert a[0].min() >= -3.0 - 0.05                                            # bounded
    assert a[1].min() < -5.0                                                    # IDM's own braking
