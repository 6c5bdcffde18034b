"""The closed-loop simulator (gpd_jax.sim) and nuPlan's planning scores.

Behavioural tests use the shipped model on a hand-built straight road: an ego cruising at 10 m/s with a follower
14 m behind it in the same lane (both logged at constant speed). Score tests use hand-built trajectories.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpd_jax
from gpd_jax.geometry import RoadGeometry
from gpd_jax.scene import Scene
from gpd_jax import sim
from gpd_jax.sim import scores as S

T, A = 101, 33
SPEED = 10.0
GAP = 25.0


def _road(batch=()):
    x0, x1, w = -300.0, 420.0, 4.8
    ring = np.array([[x0, -w], [x1, -w], [x1, w], [x0, w]], np.float32)
    polygons = np.zeros((1, 8, 2), np.float32)
    polygons[0, :4] = ring
    pv = np.zeros((1, 8), bool)
    pv[0, :4] = True
    edges = np.stack([np.array([[x0, -w], [x1, -w]]), np.array([[x0, w], [x1, w]])]).astype(np.float32)
    lanes, lane_valid = _lanes()
    road = RoadGeometry(polygons=polygons, polygon_valid=pv, polygon_kind=np.zeros(1, np.int32), edges=edges,
                        edge_valid=np.ones((2, 2), bool), lanes=lanes, lane_valid=lane_valid)
    return jax.tree.map(lambda x: np.broadcast_to(x, batch + x.shape).copy(), road)


def _lanes():
    xs = np.linspace(-280.0, 400.0, 128, dtype=np.float32)
    fwd = lambda y: np.stack([xs, np.full_like(xs, y)], -1)
    lanes = np.stack([fwd(-1.6), fwd(1.6)[::-1].copy()])      # right lane +x, left lane -x (two-way road)
    return lanes.astype(np.float32), np.ones(lanes.shape[:2], bool)


def straight_scenes(n: int = 2) -> Scene:
    """n stored-rate scenes: ego in the right lane at 10 m/s, a follower GAP m behind (scene frame = ego at frame
    20), slight per-scene speed differences."""
    t = np.arange(T, dtype=np.float32)
    xy = np.zeros((n, T, A, 2), np.float32)
    valid = np.zeros((n, T, A), bool)
    for i in range(n):
        v = SPEED + 0.5 * i
        xy[i, :, 0, 0] = (t - 20) * 0.1 * v
        xy[i, :, 1, 0] = xy[i, :, 0, 0] - GAP
        xy[i, :, :2, 1] = -1.6
        valid[i, :, :2] = True
    heading = np.zeros((n, T, A), np.float32)
    size = np.broadcast_to(np.array([4.6, 1.9], np.float32), (n, A, 2)).copy()
    lanes, lv = _lanes()
    ego_pose = np.concatenate([xy[:, :, 0], heading[:, :, :1]], -1)
    return Scene(xy=xy, heading=heading, valid=valid, size=size, agent_type=np.ones((n, A), np.int32),
                 map_tokens=np.zeros((n, T, 64), np.int32), map_valid=np.zeros((n, T), bool), ego_pose=ego_pose,
                 polylines=np.broadcast_to(lanes, (n,) + lanes.shape).copy(),
                 polyline_valid=np.broadcast_to(lv, (n,) + lv.shape).copy(), road=_road((n,)))


@pytest.fixture(scope="module")
def model():
    return gpd_jax.load_model()


@pytest.fixture(scope="module")
def scenes():
    return straight_scenes(2)


@pytest.fixture(scope="module")
def sim_scenes(model, scenes):
    return sim.make_sim_scenes(model, scenes)


# A policy that replays the log or brakes to a stop (params["brake"]), as stored-rate poses: one compiled function
# serves both, so `assert_max_traces` proves a second run with other params and scenes does not retrace.
def _select(params, obs, state, key):
    log = jax.lax.dynamic_slice_in_dim(obs.log_ego, 10 * obs.t + 1, 10, axis=0)
    brake = sim.bicycle_path(obs.ego_pose, obs.ego_velocity, jnp.array([-3.0, 0.0]), obs.size[0, 0], 10, 0.1)
    return jnp.where(params["brake"], brake, log), state


_TRACED = chex.assert_max_traces(_select, n=1)
TEST_POLICY = sim.Policy(name="brake_or_log", select=_TRACED)
BRAKE, LOG = {"brake": jnp.array(True)}, {"brake": jnp.array(False)}


@pytest.fixture(scope="module")
def gpd_runs(model, scenes, sim_scenes):
    """The test policy braking and replaying the log, both with GPD agents (one compile: `assert_max_traces`), and
    the task rollouts they should reproduce (the ego placed on the policy's poses: no tracker, as the tasks place
    it)."""
    chex.clear_trace_counter()
    brake = sim.run(model, sim_scenes, TEST_POLICY, jax.random.key(0), agents="gpd", policy_params=BRAKE, tracker=None)
    log = sim.run(model, sim_scenes, TEST_POLICY, jax.random.key(1), agents="gpd", policy_params=LOG, tracker=None)
    ref = gpd_jax.rollout(model, scenes, ["closed_loop", "motion_planning"], jax.random.key(0),
                          gpd_jax.RolloutOptions(log_map="lanes"))
    return brake, log, jax.tree.map(np.asarray, ref)


def test_braking_ego_gpd_follower_slows_log_follower_hits_not_at_fault(model, sim_scenes, gpd_runs):
    out, out_log, _ = gpd_runs
    ego = np.asarray(out.fine_xy[:, :, 0, 0])
    assert np.all(ego[:, -1] - ego[:, 20] < 22.0)                       # the ego stopped within ~17-19 m
    assert np.all(np.abs(np.diff(ego[:, -20:], axis=1)) < 1e-3)
    # reactive: behind a braking ego the GPD follower slows down well below its pace behind the logged ego
    fol, fol_log = np.asarray(out.xy[:, :, 1, 0]), np.asarray(out_log.xy[:, :, 1, 0])
    h = model.spec.num_history
    travel, travel_log = fol[:, -1] - fol[:, h - 1], fol_log[:, -1] - fol_log[:, h - 1]
    assert np.all(travel < travel_log - 15.0), (travel, travel_log)
    speed = np.diff(fol[:, h - 1:], axis=1) / model.spec.frame_period_s
    speed_log = np.diff(fol_log[:, h - 1:], axis=1) / model.spec.frame_period_s
    assert np.all(speed.min(axis=1) < 0.6 * speed_log.min(axis=1)), (speed, speed_log)
    # non-reactive: the log-replay follower drives into the stopped ego; nuPlan does not blame the ego (another
    # agent model is another compiled run: a new trace is expected)
    chex.clear_trace_counter()
    out_nr = sim.run(model, sim_scenes, TEST_POLICY, jax.random.key(0), agents="log", policy_params=BRAKE)
    sc = sim.score(model, sim_scenes, out_nr)
    assert np.all(np.asarray(sc["num_collisions"]) >= 1)
    assert np.all(np.asarray(sc["num_at_fault_collisions"]) == 0)
    assert np.all(np.asarray(sc["no_ego_at_fault_collisions"]) == 1.0)
    # IDM followers (the same compiled policy) keep to their logged path and stop behind the ego
    chex.clear_trace_counter()
    out_idm = sim.run(model, sim_scenes, TEST_POLICY, jax.random.key(0), agents="idm", policy_params=BRAKE)
    f, e = np.asarray(out_idm.fine_xy[:, :, 1]), np.asarray(out_idm.fine_xy[:, :, 0])
    np.testing.assert_allclose(f[:, 20:, 1], -1.6, atol=1e-4)
    gap = e[:, -1, 0] - f[:, -1, 0] - 4.6
    assert np.all(gap > 0.5) and np.all(gap < 6.0), gap                  # IDM's minimum gap is 1 m


def _same(out, ref, name):
    np.testing.assert_array_equal(np.asarray(out.valid), ref.valid, err_msg=name)
    np.testing.assert_allclose(np.asarray(out.xy)[ref.valid], ref.xy[ref.valid], atol=1e-4, rtol=0, err_msg=name)
    np.testing.assert_array_equal(np.asarray(out.map_tokens), ref.map_tokens, err_msg=name)


def test_log_replay_ego_with_gpd_agents_is_the_closed_loop_task(gpd_runs):
    _, out_log, ref = gpd_runs
    _same(out_log, jax.tree.map(lambda x: x[:, 0], ref), "closed_loop")


def test_own_ego_replay_is_the_motion_planning_task_with_lane_reencoding(model, sim_scenes, gpd_runs):
    ref = jax.tree.map(lambda x: x[:, 1], gpd_runs[2])
    out = sim.run(model, sim_scenes, sim.make_policy("gpd", model), jax.random.key(0), agents="log", tracker=None)
    _same(out, ref, "motion_planning")
    # a real generated ego (not the log), and its map re-encoded around it (not the logged tokens)
    assert np.abs(ref.xy[:, 3:, 0] - np.asarray(sim_scenes.view.xy)[:, 3:, 0]).max() > 0.01
    assert (ref.map_tokens[:, 3:] != np.asarray(sim_scenes.view.map_tokens)[:, 3:]).any()


def test_host_loop_matches_the_scan_and_bad_policies_are_named(model, sim_scenes):
    def cv(obs):
        nxt = obs.ego_pose[:, :2] + obs.ego_velocity * 1.0
        return np.concatenate([nxt, obs.ego_pose[:, 2:], obs.ego_velocity], -1)

    host = sim.run_host(model, sim_scenes, cv, agents="idm", with_model=False)
    scan = sim.run(model, sim_scenes, sim.make_policy("cv", model), jax.random.key(0), agents="idm")
    np.testing.assert_allclose(np.asarray(host.fine_xy), np.asarray(scan.fine_xy), atol=1e-4)
    # both score alike; only the scan's policy has an open-loop plan (OLS)
    hs, ss = sim.score(model, sim_scenes, host), sim.score(model, sim_scenes, scan)
    assert "OLS" not in hs and ss["OLS"].shape == (2,)
    np.testing.assert_allclose(hs["CLS"], ss["CLS"], atol=1e-5)
    # the pure pieces under run: reset, observe, step
    one = jax.tree.map(lambda x: x[0], sim_scenes)
    state = jax.jit(lambda sc: sim.reset(model, sc, jax.random.key(0), agents="idm", with_model=False))(one)
    obs = jax.jit(lambda st: sim.observe(model, st))(state)
    step = jax.jit(lambda st, e: sim.step(model, st, e))
    for _ in range(model.spec.num_future):
        ego = cv(jax.tree.map(lambda x: np.asarray(x)[None], obs))[0]
        state, obs = step(state, jnp.asarray(ego))
    np.testing.assert_allclose(np.asarray(state.fine_xy), np.asarray(host.fine_xy[0]), atol=1e-4)
    nan = sim.Policy(name="nan_policy", select=lambda p, o, s, k: (jnp.full(3, jnp.nan), s))
    with pytest.raises(sim.SimError, match="nan_policy.*non-finite"):
        sim.run(model, sim_scenes, nan, jax.random.key(0), agents="log")
    wrong = sim.Policy(name="wrong_shape", select=lambda p, o, s, k: (jnp.zeros(4), s))
    with pytest.raises(sim.SimError, match="wrong_shape.*shape \\(4,\\)"):
        sim.run(model, sim_scenes, wrong, jax.random.key(0), agents="log")
    with pytest.raises(sim.SimError, match="unknown agent model"):
        sim.run(model, sim_scenes, nan, jax.random.key(0), agents="reactive")


def test_host_planner_of_a_wrong_shape_is_told_what_was_expected(model, sim_scenes):
    def per_scenario(obs):                       # forgot the batch axis: one pose for the whole batch
        return np.concatenate([obs.ego_pose[0, :2] + 10.0, obs.ego_pose[0, 2:]])

    with pytest.raises(sim.SimError, match=r"planner 'per_scenario' returned an array of shape \(3,\); expected one "
                                           r"ego per scenario of the batch of 2: \[2, 3\] \(pose\), \[2, 5\] "
                                           r"\(pose, velocity\), \[2, 2\] \(acceleration, steering\), "
                                           r"\[2, 10, 3\] \(stored-rate poses\)"):
        sim.run_host(model, sim_scenes, per_scenario, agents="idm", with_model=False)


# A user's own policy: 80 % of the current velocity (pose and velocity at the next model frame), with an open-loop
# plan. `assert_max_traces` proves `evaluate_planners` reuses the compiled run of `sim.run`.
def _cautious(params, obs, state, key):
    v = 0.8 * obs.ego_velocity
    return jnp.concatenate([obs.ego_pose[:2] + v * 1.0, obs.ego_pose[2:], v]), state


def _cautious_plan(params, obs, key):
    k = jnp.arange(1, 9, dtype=jnp.float32)[:, None]
    xy = obs.ego_pose[:2] + k * 0.8 * obs.ego_velocity
    return jnp.concatenate([xy, jnp.broadcast_to(obs.ego_pose[2], (8, 1))], -1)


CAUTIOUS = sim.Policy(name="cautious", select=chex.assert_max_traces(_cautious, n=1), plan=_cautious_plan)


def test_a_user_policy_scores_like_the_shipped_planners(model, scenes, sim_scenes):
    chex.clear_trace_counter()
    out = sim.run(model, sim_scenes, CAUTIOUS, jax.random.key(0), agents="idm")
    s = sim.score(model, sim_scenes, out)
    for k in ("CLS", "OLS", "ego_progress_along_expert_route", "no_ego_at_fault_collisions", "ego_is_comfortable"):
        assert s[k].shape == (2,) and np.all((s[k] >= 0) & (s[k] <= 1)), k
    res = sim.evaluate_planners(model, scenes, {"cv": "cv", "mine": CAUTIOUS}, agents=("idm",), batch_size=2,
                                per_scenario=True)
    assert res["scenarios"] == 2 and list(res["planners"]) == ["cv", "mine"]
    mine = res["planners"]["mine"]
    assert set(mine) == {"OLS", "R-CLS-idm", "subscores"} and set(mine["subscores"]) == {"OLS", "R-CLS-idm"}
    assert mine["R-CLS-idm"] == pytest.approx(100 * s["CLS"].mean(), abs=1e-4)
    assert mine["OLS"] == pytest.approx(100 * s["OLS"].mean(), abs=1e-4)
    assert mine["subscores"]["R-CLS-idm"]["ego_is_comfortable"] == pytest.approx(s["ego_is_comfortable"].mean())
    np.testing.assert_allclose(res["per_scenario"]["mine"]["R-CLS-idm"]["CLS"], s["CLS"], atol=1e-6)
    assert set(res["run_seconds"]) == {"cv/idm", "mine/idm"}
    assert "mine" in sim.planning_table(res) and "Constant velocity" in sim.planning_table(res)
    with pytest.raises(sim.SimError, match="unknown planner 'teleport'"):
        sim.evaluate_planners(model, scenes, ["log", "teleport"])
    with pytest.raises(sim.SimError, match=r"make_policy\('gpd_head', head_model\)"):
        sim.evaluate_planners(model, scenes, ["gpd_head"])
    with pytest.raises(sim.SimError, match="unknown agent model 'reactive'"):
        sim.evaluate_planners(model, scenes, ["log"], agents=("reactive",))
    with pytest.raises(sim.SimError, match="score needs the SimScene"):
        sim.score(model, scenes, out)
    with pytest.raises(sim.SimError, match="not a SimScene"):
        sim.evaluate_planners(model, sim_scenes, ["log"])


# ------------------------------------------------------------------------------------------------ scores
F = 81
DT = 0.1


@jax.jit
def _cls(exy, eh, axy, ah, av, route, rs, expert, road, speed_limit):
    size = jnp.array([4.6, 1.9])
    rq = S.road_queries(road, exy, eh, size)
    return S.cls_scores(exy, eh, size, axy, ah, av, jnp.array([[4.6, 1.9]]), route, rs, expert, DT, rq,
                        speed_limit=speed_limit)


@jax.jit
def _cls_no_limit(exy, eh, axy, ah, av, route, rs, expert, road):
    size = jnp.array([4.6, 1.9])
    rq = S.road_queries(road, exy, eh, size)
    return S.cls_scores(exy, eh, size, axy, ah, av, jnp.array([[4.6, 1.9]]), route, rs, expert, DT, rq)


def _case(ego_x, ego_y=None, ego_h=None, ag_x=None, ag_y=None, ag_h=None, speed_limit=None, expert=80.0):
    """Scores of a hand-built run on the straight road: ego along x (and y), one agent (invalid if ag_x None)."""
    ego_y = np.full(F, -1.6) if ego_y is None else ego_y
    ego_h = np.zeros(F) if ego_h is None else ego_h
    exy = np.stack([ego_x, ego_y], -1).astype(np.float32)
    road = jax.tree.map(jnp.asarray, _road())
    axy = np.zeros((F, 1, 2), np.float32)
    av = np.zeros((F, 1), bool)
    if ag_x is not None:
        axy[:, 0, 0] = ag_x
        axy[:, 0, 1] = -1.6 if ag_y is None else ag_y
        av[:] = True
    ah = np.zeros((F, 1), np.float32) if ag_h is None else ag_h
    route = np.stack([np.linspace(0, 400, 200), np.full(200, -1.6)], -1).astype(np.float32)
    rs = np.linspace(0, 400, 200).astype(np.float32)
    args = (jnp.asarray(exy), jnp.asarray(ego_h, jnp.float32), jnp.asarray(axy), jnp.asarray(ah, jnp.float32),
            jnp.asarray(av), jnp.asarray(route), jnp.asarray(rs), jnp.asarray(expert, jnp.float32), road)
    out = _cls_no_limit(*args) if speed_limit is None else _cls(*args, jnp.full(F, speed_limit, jnp.float32))
    return {k: float(v) for k, v in out.items()}


t = np.arange(F) * DT
CRUISE = 10.0 * t


def test_cls_clean_run_scores_one():
    r = _case(CRUISE)
    for k in S.CLS_MULTIPLIERS + ("ego_progress_along_expert_route", "time_to_collision_within_bound",
                                  "ego_is_comfortable"):
        assert r[k] == 1.0, k
    assert r["CLS"] == pytest.approx(1.0)
    assert "speed_limit_compliance" not in r


def test_cls_at_fault_and_not_at_fault_collisions():
    # the ego drives into a car standing 40 m ahead: front collision with a stopped track, at fault, TTC 0
    r = _case(CRUISE, ag_x=np.full(F, 40.0))
    assert r["num_at_fault_collisions"] == 1 and r["no_ego_at_fault_collisions"] == 0.0 and r["CLS"] == 0.0
    assert r["time_to_collision_within_bound"] == 0.0
    # a car drives into the stopped ego from behind: not at fault
    r = _case(np.zeros(F), ag_x=-30.0 + 12.0 * t)
    assert r["num_collisions"] == 1 and r["num_at_fault_collisions"] == 0 and r["no_ego_at_fault_collisions"] == 1.0
    # both moving, the ego catches up with a slower car ahead: its front bumper, at fault
    r = _case(CRUISE, ag_x=20.0 + 5.0 * t)
    assert r["num_at_fault_collisions"] == 1
    # a moving car beside the ego (not reaching its front bumper) sideswipes it from the left while the ego keeps
    # its lane: lateral, not at fault
    r = _case(CRUISE, ag_x=CRUISE - 1.5, ag_y=np.clip(1.6 - 0.5 * t, -0.5, 1.6), ag_h=np.zeros((F, 1)))
    assert r["num_collisions"] == 1 and r["num_at_fault_collisions"] == 0
    # ... and the same with the ego straddling the lane line (in two lanes): at fault
    r = _case(CRUISE, ego_y=np.full(F, 0.0), ag_x=CRUISE - 1.5, ag_y=np.clip(3.2 - 0.5 * t, 1.2, 3.2))
    assert r["num_at_fault_collisions"] == 1


def test_cls_drivable_area_direction_progress():
    r = _case(CRUISE, ego_y=-1.6 - 0.05 * np.arange(F))                  # drifts off the road (edge at -4.8)
    assert r["drivable_area_compliance"] == 0.0 and r["CLS"] == 0.0
    r = _case(CRUISE, ego_y=np.full(F, -3.5))                            # corner 0.15 m out: tolerated
    assert r["drivable_area_compliance"] == 1.0
    r = _case(-CRUISE, ego_y=np.full(F, -1.6), ego_h=np.full(F, np.pi))  # 10 m/s against the lane: 10 m in 1 s
    assert r["driving_direction_compliance"] == 0.0 and r["max_wrong_way_m"] == pytest.approx(10.0, rel=0.02)
    r = _case(-0.4 * t, ego_h=np.full(F, np.pi))                         # 0.4 m/s backwards: < 2 m per second
    assert r["driving_direction_compliance"] == 1.0
    r = _case(-4.0 * t, ego_h=np.full(F, np.pi))                         # 4 m in 1 s: 0.5
    assert r["driving_direction_compliance"] == 0.5
    r = _case(np.full(F, 0.0))                                           # standing still, expert made 80 m
    assert r["ego_is_making_progress"] == 0.0 and r["ego_progress_along_expert_route"] == pytest.approx(2 / 80)
    r = _case(5.0 * t)                                                   # half the expert's progress
    assert r["ego_is_making_progress"] == 1.0 and r["ego_progress_along_expert_route"] == pytest.approx(0.5, abs=0.01)


def test_cls_ttc_comfort_speed_limit():
    # the ego brakes hard behind a stopped car and stops 0.5 m short: no collision, but TTC < 0.95 s
    v = np.maximum(10.0 - 9.0 * t, 0.0)
    x = np.concatenate([[0.0], np.cumsum(v[1:] * DT)])
    r = _case(x, ag_x=np.full(F, x[-1] + 4.6 + 0.5))
    assert r["num_collisions"] == 0 and r["time_to_collision_within_bound"] == 0.0
    assert r["ego_is_comfortable"] == 0.0                                # -9 m/s^2 is below -4.05
    r = _case(CRUISE + 1.0 * t ** 2)                                     # +2 m/s^2: comfortable
    assert r["ego_is_comfortable"] == 1.0
    r = _case(CRUISE + 1.5 * t ** 2)                                     # +3 m/s^2: not
    assert r["ego_is_comfortable"] == 0.0
    r = _case(CRUISE, speed_limit=9.0)                                   # 1 m/s over for the whole run
    assert r["speed_limit_compliance"] == pytest.approx(1 - 1.0 / 2.23, abs=0.01)
    # weights renormalise: progress 5, TTC 5, speed 4, comfort 2
    assert r["CLS"] == pytest.approx((5 + 5 + 4 * r["speed_limit_compliance"] + 2) / 16, abs=1e-4)


def test_ols_terms():
    expert = jnp.stack([jnp.arange(1, 9.0) * 10, jnp.zeros(8), jnp.zeros(8)], -1)
    r = S.ols_scores(expert, expert, (3, 5, 8), 1.0)
    assert float(r["OLS"]) == 1.0
    r = S.ols_scores(expert.at[:, 1].add(4.0), expert, (3, 5, 8), 1.0)   # 4 m off everywhere
    assert float(r["planner_expert_avg_displacement_error_within_bound"]) == pytest.approx(0.5)
    assert float(r["planner_miss_rate_within_bound"]) == 1.0
    assert float(r["OLS"]) == pytest.approx((0.5 + 0.5 + 2 + 2) / 6)
    r = S.ols_scores(expert.at[:, 1].add(7.0), expert, (3, 5, 8), 1.0)   # > 6 m at 3 s: a miss
    assert float(r["OLS"]) == 0.0


def test_plan_command_errors_exit_2(tmp_path, capsys):
    from gpd_jax.plan.__main__ import main

    assert main(["evaluate", "--data", str(tmp_path), "--planners", "log,teleport", "--out", str(tmp_path)]) == 2
    assert "teleport" in capsys.readouterr().err
    assert main(["evaluate", "--data", str(tmp_path), "--out", str(tmp_path)]) == 2
    assert "split 'test' not found" in capsys.readouterr().err
    (tmp_path / "test").mkdir()
    assert main(["evaluate", "--data", str(tmp_path), "--planners", "gpd_head", "--head-model", str(tmp_path / "none"),
                 "--out", str(tmp_path)]) == 2
    assert "no planning-head model" in capsys.readouterr().err
    from gpd_jax.sim.scoring import check_road
    with pytest.raises(sim.SimError, match="no road geometry"):
        check_road(straight_scenes(1).replace(road=None), "store X")


# ------------------------------------------------------------------------------------------------ the plan command
POLICY_FILE = '''
import jax.numpy as jnp
from gpd_jax import sim


def factory(model):                                  # a factory (model) -> Policy
    return sim.make_policy("cv", model)


def select(params, obs, state, key):                 # a select function
    return jnp.array([-2.0, 0.0]), state


BRAKE = sim.Policy(name="brake", select=select)      # a Policy
NOT_A_POLICY = 3
'''


def _write_store(path, scenes: Scene) -> None:
    """The scenes as a one-shard store of their own sizes (so loading them back gives the same shapes: the plan
    command then reuses the compiled runs of the tests above)."""
    from gpd_jax.data import store

    r = scenes.road
    arrays = {"xy": scenes.xy, "heading": scenes.heading, "valid": scenes.valid, "size": scenes.size,
              "agent_type": scenes.agent_type.astype(np.int8), "ego_pose": scenes.ego_pose,
              "polylines": scenes.polylines, "polyline_valid": scenes.polyline_valid, "road_polygons": r.polygons,
              "road_polygon_valid": r.polygon_valid, "road_polygon_kind": r.polygon_kind.astype(np.int8),
              "road_edges": r.edges, "road_edge_valid": r.edge_valid}
    n = scenes.xy.shape[0]
    store.write_shard(path, "test", 0, arrays, [f"straight/{i}" for i in range(n)], ["straight"] * n)
    store.write_manifest(path)


@pytest.fixture()
def policy_file(tmp_path):
    f = tmp_path / "my_policies.py"
    f.write_text(POLICY_FILE)
    return str(f)


def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("python -m gpd_jax.plan: error: ") and "Traceback" not in err, err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def test_plan_command_scores_a_policy_file(tmp_path, policy_file, model, scenes, monkeypatch, capsys):
    import json

    from gpd_jax.plan.__main__ import main

    data = str(tmp_path / "store")
    _write_store(data, scenes)
    chex.assert_trees_all_equal_shapes_and_dtypes(gpd_jax.load_scenes(data), scenes)
    monkeypatch.setattr(gpd_jax, "load_model", lambda path=None, *a, **k: model)   # the module's model: no recompile
    out = str(tmp_path / "out")
    assert main(["evaluate", "--data", data, "--planners", f"cv,{policy_file}:factory", "--agents", "idm",
                 "--batch-size", "2", "--out", out, "--quiet"]) == 0
    res = json.load(open(f"{out}/planning.json"))
    assert list(res["planners"]) == ["cv", "factory"] and res["scenarios"] == 2
    assert res["planners"]["factory"] == res["planners"]["cv"]        # the same policy, scored the same way
    assert "factory" in capsys.readouterr().out


def test_plan_command_policy_file_kinds_and_errors(tmp_path, policy_file, capsys):
    from gpd_jax.plan.__main__ import _user_policy, main

    assert _user_policy(f"{policy_file}:BRAKE")[0] == "policy"
    assert _user_policy(f"{policy_file}:select")[0] == "select"
    assert _user_policy(f"{policy_file}:factory")[0] == "factory"
    base = ["evaluate", "--data", str(tmp_path), "--out", str(tmp_path / "out"), "--planners"]
    assert main(base + [f"log,{policy_file}:nope"]) == 2
    _one_line_error(capsys, policy_file, "has no attribute 'nope'")
    assert main(base + [f"{policy_file}:NOT_A_POLICY"]) == 2
    _one_line_error(capsys, f"{policy_file}:NOT_A_POLICY", "is a int, not a gpd_jax.sim.Policy")
    assert main(base + [f"{tmp_path}/missing.py:mine"]) == 2
    _one_line_error(capsys, f"no policy file {tmp_path}/missing.py")
    assert main(base + ["no_such_module_xyz:mine"]) == 2
    _one_line_error(capsys, "no module 'no_such_module_xyz'")
    (tmp_path / "broken.py").write_text("import jax\ndef (:\n")
    assert main(base + [f"{tmp_path}/broken.py:mine"]) == 2
    _one_line_error(capsys, f"{tmp_path}/broken.py failed to import: SyntaxError")
    assert main(base + ["mine"]) == 2
    _one_line_error(capsys, "unknown planner 'mine'", "FILE.py:NAME")
    assert main(base + [f"cv,{policy_file}:BRAKE,{policy_file}:BRAKE"]) == 2
    _one_line_error(capsys, "planner name 'BRAKE' given twice")


@pytest.mark.parametrize("argv, flag", [
    (["evaluate", "--batch-size", "0"], "--batch-size"),
    (["evaluate", "--batch-size", "two"], "--batch-size"),
    (["evaluate", "--num-scenarios", "0"], "--num-scenarios"),
    (["evaluate", "--num-scenarios", "-3"], "--num-scenarios"),
    (["evaluate", "--render", "-1"], "--render"),
    (["bench", "--batch", "0"], "--batch"),
    (["bench", "--repeats", "0"], "--repeats"),
    (["evaluate", "--replan-every", "0"], "--replan-every"),
    (["evaluate", "--replan-every", "2", "--no-tracker"], "--replan-every"),
])
def test_plan_command_bad_counts_exit_2_in_one_line(tmp_path, capsys, argv, flag):
    from gpd_jax.plan.__main__ import main

    extra = ["--out", str(tmp_path)] if argv[0] == "evaluate" else []
    assert main(argv + ["--data", str(tmp_path)] + extra) == 2
    _one_line_error(capsys, f"argument {flag}:")


# ------------------------------------------------------------------------------------------------ plan execution
# A policy that plans 8 s straight on at its speed on its first frame and afterwards plans to veer 6 m to the left:
# how much of the veer reaches the ego shows which plans the tracker followed.
def _veer(params, obs, state, key):
    k = jnp.arange(1, 9, dtype=jnp.float32)
    v = jnp.linalg.norm(obs.ego_velocity)
    first = obs.t == params["first"]
    y = obs.ego_pose[1] + jnp.where(first, 0.0, 2.0 * jnp.minimum(k, 3.0))
    return sim.Plan(poses=jnp.stack([obs.ego_pose[0] + k * v, y, jnp.zeros(8)], -1)), state


VEER = sim.Policy(name="veer", select=_veer)


def test_plans_are_held_between_replans(model, sim_scenes):
    h, c = model.spec.num_history, model.spec.full_history - 1
    params = {"first": jnp.asarray(h - 1)}
    ys = {}
    for every in (1, 2, 8):
        out = sim.run(model, sim_scenes, VEER, jax.random.key(0), agents="log", policy_params=params,
                      tracker=sim.Tracker(replan_every=every))
        ys[every] = np.asarray(out.fine_xy[:, c:, 0, 1])                  # the ego's y from the current frame on
        assert np.all(np.diff(np.asarray(out.fine_xy[:, c:, 0, 0]), axis=1) > 0.5)   # it keeps driving
    np.testing.assert_allclose(ys[8], -1.6, atol=0.05)                    # the first plan, held for the whole run
    assert np.all(ys[1][:, -1] > 2.0)                                     # replanning every frame follows the veer
    np.testing.assert_allclose(ys[2][:, :21], -1.6, atol=0.05)            # held for 2 frames, then the veer
    assert np.all(ys[2][:, -1] > 2.0)
    # a host planner's Plan is followed the same way
    first = h - 1

    def host_veer(obs):
        return jax.vmap(lambda o: _veer({"first": first}, o, (), None)[0])(jax.tree.map(jnp.asarray, obs))

    host = sim.run_host(model, sim_scenes, host_veer, agents="log", with_model=False,
                        tracker=sim.Tracker(replan_every=2))
    np.testing.assert_allclose(np.asarray(host.fine_xy[:, c:, 0, 1]), ys[2], atol=1e-4)
    with pytest.raises(sim.SimError, match=r"planner '_bad_plan' returned a Plan of shape \(2, 3\)"):
        sim.run_host(model, sim_scenes, _bad_plan, agents="log", with_model=False)
    with pytest.raises(sim.SimError, match="replan_every must be an integer >= 1"):
        sim.run(model, sim_scenes, VEER, jax.random.key(0), agents="log", policy_params=params,
                tracker=sim.Tracker(replan_every=0))


def _bad_plan(obs):
    return sim.Plan(poses=np.zeros((2, 3)))


def _brake_plan(params, obs, state, key):
    """Brake at 3 m/s^2 from the speed now to a stop, as poses at the next 8 model frames."""
    t = jnp.arange(1, 9, dtype=jnp.float32)
    v = jnp.linalg.norm(obs.ego_velocity)
    stop = v / 3.0
    s = jnp.where(t < stop, v * t - 1.5 * t**2, v * stop - 1.5 * stop**2)
    return sim.Plan(poses=jnp.stack([obs.ego_pose[0] + s, jnp.full(8, obs.ego_pose[1]), jnp.zeros(8)], -1)), state


def test_a_braking_plan_stops_the_car_and_the_route_is_observed(model, sim_scenes):
    c = model.spec.full_history - 1
    policy = sim.Policy(name="brake_plan", select=_brake_plan)
    out = sim.run(model, sim_scenes, policy, jax.random.key(0), agents="log", tracker=sim.Tracker(replan_every=8))
    x = np.asarray(out.fine_xy[:, c:, 0, 0])
    v0 = np.asarray(sim_scenes.log_velocity[:, c, 0, 0])
    np.testing.assert_allclose(x[:, -1] - x[:, 0], v0**2 / 6.0, atol=0.5)          # where the plan stops
    assert np.all(np.abs(np.diff(x[:, -30:], axis=1)) < 0.01)                       # stopped
    assert np.all(np.diff(x, axis=1) > -1e-4)                                       # never backwards
    # the route (the logged ego's path, no timing) is in the observation: from the ego now along its lane
    one = jax.tree.map(lambda a: a[0], sim_scenes)
    obs = sim.observe(model, sim.reset(model, one, agents="log", with_model=False))
    route, s = np.asarray(obs.route_xy), np.asarray(obs.route_s)
    np.testing.assert_allclose(route[0], np.asarray(obs.ego_pose[:2]), atol=1e-4)
    np.testing.assert_allclose(route[:, 1], -1.6, atol=1e-4)
    assert np.all(np.diff(s) >= 0) and s[-1] > 80.0
