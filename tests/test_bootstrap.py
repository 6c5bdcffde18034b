"""Scene-bootstrap intervals and paired comparisons (`gpd_jax.evaluation.bootstrap`) on hand-made per-scene
sums whose ratios are known."""

import numpy as np
import pytest

from gpd_jax.evaluation.bootstrap import (SceneSums, compare_runs, draws, load_scene_sums, ratio_draws,
                                          save_scene_sums, scene_sums_from_batches)
from gpd_jax.spec import EvalError

N = 40


def run(model_err, cv_err, agents=None, ids=None, labels=("3s", "8s"), locations=()) -> SceneSums:
    """Per-scene sums: scene i has agents[i] agents, each with model error model_err[i] and CV error cv_err[i]."""
    agents = np.full(N, 5.0) if agents is None else np.asarray(agents, float)
    sums = {}
    for lb in labels:
        for where, err in (("tasks/traffic_simulation/paper", model_err),
                           ("baselines/constant_velocity/paper", cv_err)):
            sums[f"{where}/{lb}/agent_ade_num"] = np.asarray(err, float) * agents
            sums[f"{where}/{lb}/agent_ade_den"] = agents
            sums[f"{where}/{lb}/agent_ade_along_moving_num"] = 0.5 * np.asarray(err, float) * agents
            sums[f"{where}/{lb}/agent_ade_moving_num"] = np.asarray(err, float) * agents
            sums[f"{where}/{lb}/agent_ade_moving_den"] = agents
    return SceneSums(tuple(ids or (f"s{i}" for i in range(N))), sums, tuple(locations))


def test_the_ratio_is_a_ratio_of_sums_over_the_drawn_scenes():
    rng = np.random.default_rng(1)
    m, c, a = rng.uniform(1, 3, N), rng.uniform(2, 4, N), rng.integers(1, 9, N)
    ss = run(m, c, a)
    w = np.zeros((2, N))
    w[0] = 1
    w[1, :3] = [2, 0, 1]
    got = ratio_draws(ss, w, label="8s")
    want0 = (m * a).sum() / a.sum() / ((c * a).sum() / a.sum())
    den = 2 * a[0] + a[2]
    want1 = ((2 * m[0] * a[0] + m[2] * a[2]) / den) / ((2 * c[0] * a[0] + c[2] * a[2]) / den)
    np.testing.assert_allclose(got, [want0, want1], rtol=1e-12)
    # a track component shares the moving class's denominator
    np.testing.assert_allclose(ratio_draws(ss, w[:1], metric="agent_ade_along_moving"), [want0], rtol=1e-12)


def test_paired_comparison_finds_a_uniform_improvement_and_intervals_cover_the_truth():
    rng = np.random.default_rng(2)
    c = rng.uniform(2, 4, N)
    a = run(0.7 * c * rng.uniform(0.8, 1.2, N), c)
    better = run(np.asarray(a.sums["tasks/traffic_simulation/paper/3s/agent_ade_num"]) / 5.0 * 0.9, c)
    res = compare_runs([a, better], resamples=500, seed=3)
    for lb in ("3s", "8s"):
        r0, r1 = res["runs"][0][lb]["ratio"], res["runs"][1][lb]["ratio"]
        assert r1 == pytest.approx(0.9 * r0, rel=1e-9)
        lo, hi = res["runs"][0][lb]["interval"]
        assert lo < r0 < hi and 0.6 < lo and hi < 0.8
        d = res["versus_first"][0][lb]
        assert d["difference"] == pytest.approx(r1 - r0) and d["share_lower"] == 1.0
        assert d["interval"][0] <= d["difference"] <= d["interval"][1] < 0
    assert compare_runs([a, better], resamples=500, seed=3) == res  # deterministic for a seed
    # unpaired noise of the same size: the difference's interval straddles 0
    noisy = run(0.7 * c * rng.uniform(0.8, 1.2, N), c)
    lo, hi = compare_runs([a, noisy], resamples=500)["versus_first"][0]["3s"]["interval"]
    assert lo < 0 < hi


def test_bad_input_names_what_is_wrong(tmp_path):
    a = run(np.ones(N), np.ones(N))
    with pytest.raises(EvalError, match=r"scenario 7 \('x'"):
        ids = [f"s{i}" for i in range(N)]
        ids[7] = "x"
        compare_runs([a, run(np.ones(N), np.ones(N), ids=ids)], resamples=100)
    with pytest.raises(EvalError, match="same scenes"):
        compare_runs([a, SceneSums(a.scenario_ids[:5], {k: v[:5] for k, v in a.sums.items()})], resamples=100)
    with pytest.raises(EvalError, match="there are: agent_ade, agent_ade_along_moving, agent_ade_moving"):
        compare_runs([a], metric="ego_ade", resamples=100)
    with pytest.raises(EvalError, match="no sums of task 'closed_loop'"):
        compare_runs([a], task="closed_loop", resamples=100)
    with pytest.raises(EvalError, match="at least 2 scenes"):
        draws(1, 100, 0)
    with pytest.raises(EvalError, match="resamples"):
        draws(5, 10, 0)
    with pytest.raises(EvalError, match="no per-scene sums"):
        load_scene_sums(str(tmp_path))
    bad = tmp_path / "bad.npz"
    np.savez(bad, x=np.zeros(3))
    with pytest.raises(EvalError, match="not a scene-sums file"):
        load_scene_sums(str(bad))


def test_save_load_round_trip_and_batches_concatenate(tmp_path):
    b1 = {"tasks": {"t": {"paper": {"3s": {"agent_ade_num": np.array([1.0, 2.0]), "agent_ade_den": np.ones(2)}}}},
          "counts": {"scenarios": np.ones(2)}}
    b2 = {"tasks": {"t": {"paper": {"3s": {"agent_ade_num": np.array([3.0]), "agent_ade_den": np.ones(1)}}}},
          "counts": {"scenarios": np.ones(1)}}
    ss = scene_sums_from_batches([b1, b2], ["a", "", "c"], ["r1", "r1", "r2"])
    assert ss.scenario_ids == ("a", "1", "c") and ss.locations == ("r1", "r1", "r2")
    np.testing.assert_array_equal(ss.sums["tasks/t/paper/3s/agent_ade_num"], [1.0, 2.0, 3.0])
    path = str(tmp_path / "s.npz")
    save_scene_sums(path, ss)
    back = load_scene_sums(path)
    assert back.scenario_ids == ss.scenario_ids and back.sums.keys() == ss.sums.keys()
    assert back.locations == ss.locations
    for k in ss.sums:
        np.testing.assert_array_equal(back.sums[k], ss.sums[k])
    with pytest.raises(EvalError, match="has 2 scenarios, the run 3"):
        scene_sums_from_batches([b1], ["a", "b", "c"])


def test_a_location_bootstrap_draws_whole_networks_and_is_wider_when_networks_differ():
    groups = ["net_a"] * 10 + ["net_b"] * 10 + ["net_c"] * 10 + ["net_d"] * 5 + ["net_e"] * 5
    w = draws(N, 300, 4, groups)
    starts = (0, 10, 20, 30, 35)
    for lo, hi in zip(starts, starts[1:] + (40,)):  # a network's scenes are drawn together
        assert (w[:, lo:hi] == w[:, lo:lo + 1]).all()
    assert (w[:, list(starts)].sum(1) == 5).all()  # five of the five networks, with replacement
    groups = ["net_a"] * 10 + ["net_b"] * 10 + ["net_c"] * 20
    # each network has its own level of difficulty for the model: scenes inside one agree, networks disagree
    rng = np.random.default_rng(5)
    level = {"net_a": 0.55, "net_b": 0.75, "net_c": 0.65}
    c = rng.uniform(2, 4, N)
    m = np.array([level[g] for g in groups]) * c * rng.uniform(0.97, 1.03, N)
    locs = [f"{g}_{i % 2}" for i, g in enumerate(groups)]  # 6 networks, so a draw has some variety
    ss = run(m, c, locations=locs)
    by_scene = compare_runs([ss], resamples=1000)["runs"][0]["3s"]
    res = compare_runs([ss], resamples=1000, unit="location")
    by_loc = res["runs"][0]["3s"]
    assert by_loc["ratio"] == by_scene["ratio"] and res["locations"] == 6 and res["unit"] == "location"
    width = lambda r: r["interval"][1] - r["interval"][0]  # noqa: E731
    assert width(by_loc) > 1.2 * width(by_scene)
    with pytest.raises(EvalError, match="needs every scenario's road network"):
        compare_runs([run(m, c)], resamples=100, unit="location")
    with pytest.raises(EvalError, match="at least 5 locations, the scenes have 4"):
        compare_runs([run(m, c, locations=[f"n{i % 4}" for i in range(N)])], resamples=100, unit="location")
    with pytest.raises(EvalError, match="unit must be one of"):
        compare_runs([ss], resamples=100, unit="network")
