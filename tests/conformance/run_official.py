"""Scores the conformance scenes with the official WOSAC code and records its figures (no gpd_jax here).

Runs in the official package's own environment (TensorFlow; `setup_official_env.sh` builds it):

    VENV/bin/python tests/conformance/run_official.py \\
        [--scenes tests/conformance/scenes.npz] [--out tests/conformance/official.json]

For each scene of the `.npz` (format: `make_scenes.py`) it writes a `Scenario` (91 states per agent, invalid states
as the arrays hold them, the current index 10; the first evaluated agent is the SDC, the others
`tracks_to_predict`; the road edges as `road_edge` map features, z = 0 everywhere) and a `ScenarioRollouts` of the
submission arrays (`sub_xy`, `sub_heading`: every agent valid at the current frame, every future frame), and runs
`waymo_open_dataset.wdl_limited.sim_agents_metrics.metrics.compute_scenario_metrics_for_bundle` under the 2025
sim-agents configuration and the 2024 one. Where the `.npz` has traffic signals (`signal_*`, `official_lanes`),
the `Scenario` gets them as lanes and dynamic map states (`add_signals`) and the traffic-light term is computed.
It records every likelihood, the meta-metric, ADE, minADE and the simulated collision, offroad and traffic-light
violation rates per scene and configuration, the seconds each scene took, and their means
over the scenes ("means", with "metametric_without_traffic_light": the meta-metric renormalised without the
traffic-light term, what the project reports where the data has no signal states). Scenes with no evaluated
agent or no road edge are skipped (the official code refuses them).

The `.npz` may also come from `rollout.py --samples K --export-official DIR` (one per task and baseline: compare
"means" with metrics.json's "realism_official") or `gpd-jax bench realism --export-official`.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import time

import numpy as np

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")

import tensorflow as tf  # noqa: E402
from google.protobuf import text_format  # noqa: E402
from waymo_open_dataset.protos import map_pb2, scenario_pb2, sim_agents_metrics_pb2  # noqa: E402
from waymo_open_dataset.protos import sim_agents_submission_pb2  # noqa: E402
from waymo_open_dataset.wdl_limited.sim_agents_metrics import metrics  # noqa: E402

HERE = pathlib.Path(__file__).parent
CURRENT = 10
CONFIGS = {"2025": "challenge_2025_sim_agents_config.textproto", "2024": "challenge_2024_config.textproto"}
FIELDS = ("metametric", "average_displacement_error", "min_average_displacement_error",
          "linear_speed_likelihood", "linear_acceleration_likelihood", "angular_speed_likelihood",
          "angular_acceleration_likelihood", "distance_to_nearest_object_likelihood",
          "collision_indication_likelihood", "time_to_collision_likelihood", "distance_to_road_edge_likelihood",
          "offroad_indication_likelihood", "traffic_light_violation_likelihood", "simulated_collision_rate",
          "simulated_offroad_rate", "simulated_traffic_light_violation_rate")


def load_config(name: str):
    # by absolute path: `metrics.load_metrics_config` opens the textproto relative to the working directory
    path = pathlib.Path(metrics.__file__).with_name(CONFIGS[name])
    return text_format.Parse(path.read_text(), sim_agents_metrics_pb2.SimAgentMetricsConfig())


def scenario_of(d, i: int) -> scenario_pb2.Scenario:
    xy, h, valid = d["log_xy"][i], d["log_heading"][i], d["log_valid"][i]
    t, a = valid.shape
    ev = np.flatnonzero(d["evaluated"][i])
    sc = scenario_pb2.Scenario(scenario_id=f"{i}_{d['names'][i]}", current_time_index=CURRENT,
                               timestamps_seconds=[0.1 * k for k in range(t)], sdc_track_index=int(ev[0]))
    vehicle, pedestrian = scenario_pb2.Track.ObjectType.TYPE_VEHICLE, scenario_pb2.Track.ObjectType.TYPE_PEDESTRIAN
    for j in range(a):
        track = sc.tracks.add(id=j + 1, object_type=vehicle if d["is_vehicle"][i, j] else pedestrian)
        length, width = (float(x) for x in d["size"][i, j])
        for k in range(t):
            track.states.add(center_x=float(xy[k, j, 0]), center_y=float(xy[k, j, 1]), center_z=0.0,
                             length=length, width=width, height=1.5, heading=float(h[k, j]),
                             velocity_x=0.0, velocity_y=0.0, valid=bool(valid[k, j]))
    for j in ev[1:]:
        sc.tracks_to_predict.add(track_index=int(j))
    for e in range(d["edges"].shape[1]):
        pts = d["edges"][i, e][d["edge_valid"][i, e]]
        if len(pts) >= 2:
            feature = sc.map_features.add(id=100 + e)
            feature.road_edge.CopyFrom(map_pb2.RoadEdge(
                polyline=[map_pb2.MapPoint(x=float(x), y=float(y), z=0.0) for x, y in pts]))
    if "signal_state" in d:
        add_signals(sc, d, i)
    return sc


def add_signals(sc, d, i: int):
    """The scene's traffic signals and lanes as the project hands them over (`official_lanes`,
    `signal_row`, `signal_present`: `gpd_jax.metrics.realism.official_signal_arrays`): each handed-over row a
    surface-street lane (id 1000 + row), a dynamic map state per frame holding every signal handed over (its
    state, 0 unknown, its lane and its stop point). Nothing for a scene without a signal."""
    present = np.flatnonzero(d["signal_present"][i])
    if not len(present):
        return
    street = map_pb2.LaneCenter.LaneType.TYPE_SURFACE_STREET
    for r, (q, v) in enumerate(zip(d["official_lanes"][i], d["official_lane_valid"][i])):
        if v.sum() >= 2:
            feature = sc.map_features.add(id=1000 + r)
            feature.lane.CopyFrom(map_pb2.LaneCenter(
                type=street, polyline=[map_pb2.MapPoint(x=float(x), y=float(y), z=0.0) for x, y in q[v]]))
    for t in range(d["signal_state"].shape[1]):
        states = sc.dynamic_map_states.add()
        for j in present:
            x, y = (float(c) for c in d["signal_stop"][i, j])
            states.lane_states.add(lane=1000 + int(d["signal_row"][i, j]), state=int(d["signal_state"][i, t, j]),
                                   stop_point=map_pb2.MapPoint(x=x, y=y, z=0.0))


def rollouts_of(d, i: int, scenario) -> sim_agents_submission_pb2.ScenarioRollouts:
    present = np.flatnonzero(d["log_valid"][i, CURRENT])
    xy, h = d["sub_xy"][i], d["sub_heading"][i]  # [K, F, A, 2], [K, F, A]
    scenes = []
    for k in range(xy.shape[0]):
        trajs = [sim_agents_submission_pb2.SimulatedTrajectory(
            center_x=xy[k, :, j, 0].tolist(), center_y=xy[k, :, j, 1].tolist(), center_z=[0.0] * xy.shape[1],
            heading=h[k, :, j].tolist(), object_id=int(j + 1)) for j in present]
        scenes.append(sim_agents_submission_pb2.JointScene(simulated_trajectories=trajs))
    return sim_agents_submission_pb2.ScenarioRollouts(scenario_id=scenario.scenario_id, joint_scenes=scenes)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", default=str(HERE / "scenes.npz"))
    p.add_argument("--out", default=str(HERE / "official.json"))
    p.add_argument("--configs", nargs="+", choices=tuple(CONFIGS), default=list(CONFIGS),
                   help="the configurations to score (the seconds are the 2025 configuration's)")
    args = p.parse_args()
    d = dict(np.load(args.scenes))
    configs = {name: load_config(name) for name in args.configs}
    results, seconds = [], []
    for i in range(len(d["names"])):
        if not d["evaluated"][i].any() or not d["edge_valid"][i].any():
            # the official code needs an SDC among the evaluated agents and road edges; the project leaves such a
            # scene out too (no evaluated agent) or leaves out the map terms (no edges)
            results.append({"name": str(d["names"][i]), "skipped": "no evaluated agent or no road edge"})
            continue
        sc = scenario_of(d, i)
        ro = rollouts_of(d, i, sc)
        scene = {"name": str(d["names"][i])}
        for name, cfg in configs.items():
            t0 = time.perf_counter()
            m = metrics.compute_scenario_metrics_for_bundle(cfg, sc, ro)
            if name == "2025":
                seconds.append(time.perf_counter() - t0)
            scene[name] = {f: float(getattr(m, f)) for f in FIELDS}
        results.append(scene)
        first = next(iter(configs))
        print(f"{scene['name']}: {first} meta-metric {scene[first]['metametric']:.6f} "
              f"({time.perf_counter() - t0:.1f} s)", flush=True)
    scored = [r for r in results if "skipped" not in r]
    means = {name: {f: float(np.mean([r[name][f] for r in scored])) for f in FIELDS} for name in configs}
    for name, m in means.items():  # the project's meta-metric where no store has signal states: that term left out
        terms = [x.removesuffix("_likelihood") for x in FIELDS if x.endswith("_likelihood")]
        w = {f: getattr(configs[name], f).metametric_weight for f in terms if f != "traffic_light_violation"}
        per_scene = [sum(wt * r[name][f"{f}_likelihood"] for f, wt in w.items()) / sum(w.values()) for r in scored]
        m["metametric_without_traffic_light"] = float(np.mean(per_scene))
    out = {"package": "waymo-open-dataset-tf-2-12-0==1.6.7", "tensorflow": tf.__version__,
           "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
           "rollouts": int(d["sub_xy"].shape[1]), "agents": int(d["log_valid"].shape[2]),
           "seconds_per_scene_2025": seconds, "means": means, "scenes": results}
    pathlib.Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.out}" + (f": {np.mean(seconds):.2f} s per scene (2025 configuration)" if seconds else ""))


if __name__ == "__main__":
    main()
