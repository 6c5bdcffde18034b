"""The official mode of the realism metric against the official WOSAC code: `rules="official"` on the
conformance scenes (`tests/conformance/scenes.npz`, written by `make_scenes.py`) reproduces every per-scene
likelihood, the meta-metric, ADE and minADE the official package recorded (`official.json`, by `run_official.py` in
its own TensorFlow environment; docs/evaluation.md says how to rerun it) to 1e-4, without TensorFlow here."""

import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpd_jax.geometry import RoadGeometry, TrafficSignals
from gpd_jax.metrics import realism as R
from gpd_jax.scene import TYPE_ID

HERE = pathlib.Path(__file__).parent / "conformance"
H = 11
LIKELIHOODS = [f"{n}_likelihood" for n in R.FEATURES if n != "traffic_light_violation"]
# ours -> the official record's name
OTHER = {"ade": "average_displacement_error", "min_ade": "min_average_displacement_error",
         "collision_rate": "simulated_collision_rate", "offroad_rate": "simulated_offroad_rate"}


@pytest.fixture(scope="module")
def scenes():
    d = dict(np.load(HERE / "scenes.npz"))
    return d, json.loads((HERE / "official.json").read_text())


def score(d, config, rules, signals=False, agent_type=None):
    """Our per-scene metrics of every conformance scene (one compiled call, vmapped over scenes); with `signals`
    the traffic-light term is scored from the scenes' signals and lanes (meaningful for those with signals)."""
    s = d["sim_xy"].shape[1]
    rep = lambda x: np.repeat(x[:, None, :H], s, 1)  # noqa: E731  the log's history
    sim_xy = np.concatenate([rep(d["log_xy"]), d["sim_xy"]], 2)
    sim_h = np.concatenate([rep(d["log_heading"]), d["sim_heading"]], 2)
    sim_v = np.concatenate([rep(d["log_valid"]), d["sim_valid"]], 2)
    n = len(d["names"])
    road = RoadGeometry(polygons=d["polygons"], polygon_valid=d["polygon_valid"],
                        polygon_kind=np.zeros(d["polygons"].shape[:2], np.int32), edges=d["edges"],
                        edge_valid=d["edge_valid"], lanes=np.zeros((n, 1, 2, 2), np.float32),
                        lane_valid=np.zeros((n, 1, 2), bool))

    sig = TrafficSignals(state=d["signal_state"], stop=d["signal_stop"], lane=d["signal_lane"],
                         lane_valid=d["signal_lane_valid"]) if signals else None

    def one(sx, sh, sv, lx, lh, lv, size, rd, ev, at, sg, ln, lnv):
        return R.scenario_realism(sx, sh, sv, lx, lh, lv, size, H, rd, ev, config=config, rules=rules,
                                  agent_type=at, signals=sg, lanes=ln, lane_valid=lnv)

    args = (sim_xy, sim_h, sim_v, d["log_xy"], d["log_heading"], d["log_valid"], d["size"], road, d["evaluated"],
            d["agent_type"] if agent_type is None else agent_type, sig, d["lanes"], d["lane_valid"])
    out = jax.jit(jax.vmap(one))(*jax.tree.map(jnp.asarray, args))
    return {k: np.asarray(v, np.float64) for k, v in out.items()}


def renormalised_metametric(official_scene: dict, config: str) -> float:
    """The official likelihoods weighted as ours are: the traffic-light term left out (no signal states)."""
    w = R.realism_weights(config)
    return sum(wt * official_scene[f"{k}_likelihood"] for k, wt in w.items())


@pytest.mark.parametrize("config", ["2025", "2024"])
def test_official_mode_reproduces_the_official_code(scenes, config):
    d, rec = scenes
    ours = score(d, config, "official")
    for i, scene in enumerate(rec["scenes"]):
        if d["signal_present"][i].any():
            continue  # scored with its signals below
        off = scene[config]
        for key in LIKELIHOODS:
            assert abs(ours[key][i] - off[key]) <= 1e-4, (scene["name"], key, ours[key][i], off[key])
        assert abs(ours["metametric"][i] - renormalised_metametric(off, config)) <= 1e-4, scene["name"]
        for key, name in OTHER.items():
            assert abs(ours[key][i] - off[name]) <= 1e-4 * max(1.0, abs(off[name])), (scene["name"], key)
    if config == "2024":  # no traffic-light weight in 2024: the official meta-metric itself
        np.testing.assert_allclose(ours["metametric"], [s["2024"]["metametric"] for s in rec["scenes"]], atol=1e-4)


def with_signals(d):
    return [i for i in range(len(d["names"])) if d["signal_present"][i].any()]


@pytest.mark.parametrize("config", ["2025", "2024"])
def test_official_mode_reproduces_the_traffic_light_term(scenes, config):
    """On the scene with traffic signals (red runs, a crossing on green, a stop at red, caution, arrow, flashing
    and unknown states, a signal no agent uses, an agent leaving the log, a pedestrian on red), the official
    mode with the signals reproduces every likelihood, the traffic-light term among them, and the official
    meta-metric itself (2025: the traffic-light term weighed in)."""
    d, rec = scenes
    idx = with_signals(d)
    assert idx
    ours = score(d, config, "official", signals=True)
    for i in idx:
        off = rec["scenes"][i][config]
        for key in LIKELIHOODS + ["traffic_light_violation_likelihood", "metametric"]:
            if key == "traffic_light_violation_likelihood" and config == "2024":
                continue  # not a 2024 term
            assert abs(ours[key][i] - off[key]) <= 1e-4, (rec["scenes"][i]["name"], key, ours[key][i], off[key])
        for key, name in {**OTHER, "red_light_rate": "simulated_traffic_light_violation_rate"}.items():
            if key in ours:
                assert abs(ours[key][i] - off[name]) <= 1e-4 * max(1.0, abs(off[name])), (key, ours[key][i])
    assert 0.0 < min(rec["scenes"][i]["2025"]["simulated_traffic_light_violation_rate"] for i in idx)


def test_the_traffic_light_rule_set_back_fails(scenes, monkeypatch):
    """The scene tells the official rule from the corrected one: the corrected lane test (true distance, a
    crossing within 5 m of the stop point, the signal's own piece among the lanes), and every agent scored
    rather than vehicles alone, each move the traffic-light likelihood off the official record."""
    d, rec = scenes
    idx = with_signals(d)
    off = np.array([rec["scenes"][i]["2025"]["traffic_light_violation_likelihood"] for i in idx])
    everyone = np.where(d["agent_type"] == TYPE_ID["other"], TYPE_ID["car"], d["agent_type"])
    assert np.abs(score(d, "2025", "official", True, everyone)["traffic_light_violation_likelihood"][idx]
                  - off).max() > 1e-3
    monkeypatch.setattr(R, "official_signal_geometry", R.signal_geometry)  # the corrected violation test
    assert np.abs(score(d, "2025", "official", True)["traffic_light_violation_likelihood"][idx] - off).max() > 1e-3


def test_corrected_rules_differ_from_the_official_ones_where_they_should(scenes):
    """The corrected rules are not the official ones on these scenes: the kinematic terms move (the padding NaNs
    and the first future frames), the others agree wherever every agent stays in the log (the traffic-light scene
    has one that leaves)."""
    d, rec = scenes
    corrected = score(d, "2025", "corrected")
    official = [s["2025"] for s in rec["scenes"]]
    kin = np.array([[abs(corrected[f"{k}_likelihood"][i] - o[f"{k}_likelihood"]) for i, o in enumerate(official)]
                    for k in ("linear_speed", "linear_acceleration", "angular_speed", "angular_acceleration")])
    assert kin.max() > 1e-3
    stay = [i for i, n in enumerate(d["names"]) if n not in ("agents_leave", "traffic_lights")]
    for key in ("distance_to_nearest_object_likelihood", "collision_indication_likelihood",
                "distance_to_road_edge_likelihood", "offroad_indication_likelihood"):
        np.testing.assert_allclose(corrected[key][stay], [official[i][key] for i in stay], atol=1e-4)


def test_the_submission_the_official_code_scored_is_the_official_modes_continuation(scenes):
    """Where a rollout lacks an agent the official mode continues it (`continue_missing`); the official code was
    handed exactly that."""
    d, _ = scenes
    s = d["sim_xy"].shape[1]
    full = lambda log, sim: np.concatenate([np.repeat(log[:, None, :H], s, 1), sim], 2)  # noqa: E731
    xy, h = jax.vmap(lambda x, hh, v: R.continue_missing(x, hh, v, H))(
        jnp.asarray(full(d["log_xy"], d["sim_xy"])), jnp.asarray(full(d["log_heading"], d["sim_heading"])),
        jnp.asarray(full(d["log_valid"], d["sim_valid"])))
    present = d["log_valid"][:, H - 1][:, None, None, :]
    np.testing.assert_allclose(np.where(present[..., None], np.asarray(xy)[:, :, H:], 0),
                               np.where(present[..., None], d["sub_xy"], 0), atol=1e-5)
    np.testing.assert_allclose(np.where(present, np.asarray(h)[:, :, H:], 0), np.where(present, d["sub_heading"], 0),
                               atol=1e-6)
    assert (~d["sim_valid"] & present).any()  # the scenes do exercise it


def test_the_evaluations_export_writes_what_the_official_script_reads(scenes, tmp_path):
    """`write_official_scenes` (what `rollout.py --export-official` writes) holds every field `run_official.py`
    reads, in its shapes: the conformance scenes written through it come back as they went in (the log and the
    signal states cut to the official 11 + 80 frames from a longer history; the signals as handed over)."""
    from gpd_jax.evaluation.realism import write_official_scenes
    from gpd_jax.metrics.realism import edge_polylines

    d, _ = scenes
    pad = 4  # a longer history than the official format's, as the shipped models' 21 frames
    log = {k: np.concatenate([np.repeat(d[k][:, :1], pad, 1), d[k]], 1) for k in ("log_xy", "log_heading",
                                                                                  "log_valid")}
    n = len(d["names"])
    lines = np.empty(n, object)
    for i in range(n):
        road = RoadGeometry(polygons=d["polygons"][i], polygon_valid=d["polygon_valid"][i],
                            polygon_kind=np.zeros(d["polygons"].shape[1], np.int32), edges=d["edges"][i],
                            edge_valid=d["edge_valid"][i], lanes=np.zeros((1, 2, 2), np.float32),
                            lane_valid=np.zeros((1, 2), bool))
        lines[i] = edge_polylines(road)
    signals = {k: d[k] for k in ("official_lanes", "official_lane_valid", "signal_row", "signal_present",
                                 "signal_stop")}
    signals["signal_state"] = np.concatenate([np.repeat(d["signal_state"][:, :1], pad, 1), d["signal_state"]], 1)
    part = {**log, "size": d["size"], "agent_type": d["agent_type"], "edges": lines,
            "sub_xy": d["sub_xy"][:, None], "sub_heading": d["sub_heading"][:, None],
            "evaluated": d["evaluated"][:, None], **signals}
    halves = [{k: v[:3] for k, v in part.items()}, {k: v[3:] for k, v in part.items()}]  # two batches
    (path,) = write_official_scenes(str(tmp_path), ["traffic_simulation"], list(d["names"]), halves, H + pad)
    got = dict(np.load(path))
    for key in ("log_xy", "log_heading", "log_valid", "size", "is_vehicle", "evaluated", "sub_xy", "sub_heading",
                "official_lanes", "official_lane_valid", "signal_row", "signal_present", "signal_stop",
                "signal_state"):
        np.testing.assert_array_equal(got[key], d[key], err_msg=key)
    # the edges as polylines, each the same line as written (the conformance edges are kept whole)
    for i in range(n):
        want = [e[v] for e, v in zip(d["edges"][i], d["edge_valid"][i]) if v.any()]
        have = [e[v] for e, v in zip(got["edges"][i], got["edge_valid"][i]) if v.any()]
        assert len(have) == len(want) and all(np.allclose(a, b) for a, b in zip(have, want))
