"""ScenarioNet scenarios written by the tests themselves, in ScenarioNet's documented layout (no downloaded data).

Layout (MetaDrive `ScenarioDescription`; ScenarioNet dataset = `dataset_summary.pkl` + `dataset_mapping.pkl` +
scenario `.pkl` files, possibly in sub-folders named by the mapping):

    scenario = {"id", "version", "length": T,
                "metadata": {"ts": f32[T], "sdc_id": str, "dataset", "scenario_id", "coordinate": "waymo",
                             "metadrive_processed": False, optional "map"},
                "tracks": {id: {"type": "VEHICLE" | "PEDESTRIAN" | "CYCLIST" | ...,
                                "state": {"position": f32[T, 3], "heading": f32[T], "velocity": f32[T, 2],
                                          "length": f32[T], "width": f32[T], "height": f32[T], "valid": bool[T]},
                                "metadata": {"type", "object_id", "track_length"}}},
                "map_features": {id: {"type": "LANE_SURFACE_STREET" | "ROAD_EDGE_BOUNDARY" | ...,
                                      "polyline": f32[P, 3], optional "polygon": f32[Q, 3]}},
                "dynamic_map_states": {id: {"type": "TRAFFIC_LIGHT", "state": {"object_state": [T strings]},
                                            "metadata": {...}}}}

The road of `make_scenario`: the ego (the sdc) drives at `speed` m/s along a straight road whose direction in the
world is `theta` (a world frame rotated and shifted against the road, so frame conversions are exercised), on the
middle of three lanes 3.5 m apart. Special tracks (road coordinates: along, lateral-left):

* "ahead": a 4.5 x 1.9 m car 12 m ahead in the ego's lane, same speed;
* "left": an 8 x 2.5 m truck 3.5 m to the left (lateral +3.5), 2 m ahead, same speed;
* "bus": a 12 x 2.55 m bus 25 m ahead in the right lane (lateral -3.5), valid from 0.5 s on; its length is
  99 m in the frames where it is not valid (a size must come from valid frames only);
* "late": a car 40 m ahead that appears only from 5 s on (frame 50 at 10 Hz);
* a pedestrian, a cyclist and a traffic cone (dropped by the reader);
* `extra_tracks` more cars spread over the lanes behind and ahead (for realistic sizes).

Drivable area: the right and middle lanes carry `width` (P, 2) = 1.75 m to each side, the left lane a real
`polygon` (lateral 1.75 .. 5.25); a `DRIVEWAY` polygon left of the road at along 80 .. 90, lateral 5.25 .. 15.
The union is lateral -5.25 .. 5.25 (where the `ROAD_EDGE_BOUNDARY` lines are) plus the driveway.

Usage as a script (writes a dataset of realistic size for timing the importer):

    python tests/scenarionet_fixtures.py OUT_DIR --scenarios 20 --frames 91 --tracks 100 --lanes 300
"""

from __future__ import annotations

import os
import pickle

import numpy as np

THETA = 2.0  # road direction in the world: beyond pi/2, so sign errors in x or y show
ORIGIN = np.array([1234.5, -987.0])
SDC = "172"


def rot(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def road_to_world(along, lat, theta=THETA, origin=ORIGIN):
    """Road coordinates (along, lateral-left) -> world xy f[..., 2]."""
    local = np.stack([np.asarray(along, np.float64), np.broadcast_to(lat, np.shape(along)).astype(np.float64)], -1)
    return local @ rot(theta).T + origin


def _track(ttype, xy, heading, valid, length, width, oid, z=0.0):
    T = len(valid)
    pos = np.zeros((T, 3), np.float32)
    pos[:, :2] = np.where(valid[:, None], xy, 0.0)
    pos[:, 2] = np.where(valid, z, 0.0)
    hd = np.where(valid, heading, 0.0).astype(np.float32)
    vel = np.zeros((T, 2), np.float32)
    vel[1:] = np.diff(pos[:, :2], axis=0) * 10
    ln = np.where(valid, length, 0.0).astype(np.float32)
    wd = np.where(valid, width, 0.0).astype(np.float32)
    state = {"position": pos, "heading": hd, "velocity": vel, "length": ln, "width": wd,
             "height": np.where(valid, 1.6, 0.0).astype(np.float32), "valid": valid.astype(bool)}
    return {"type": ttype, "state": state, "metadata": {"type": ttype, "object_id": oid, "track_length": T}}


def make_scenario(num_frames: int = 121, hz: float = 10.0, speed: float = 10.0, theta: float = THETA,
                  origin=ORIGIN, map_name: str | None = "us-test-town", dataset: str = "testset",
                  scenario_id: str = "s0", extra_tracks: int = 0, extra_lanes: int = 0, seed: int = 0,
                  ts_start: float = 3.0) -> dict:
    """One ScenarioNet scenario dict (see the module docstring). `num_frames` frames at `hz`."""
    rng = np.random.default_rng(seed)
    T = num_frames
    t = np.arange(T) / hz
    hd = np.full(T, theta)
    ones = np.ones(T, bool)

    def on_road(along0, lat):
        return road_to_world(along0 + speed * t, lat, theta, origin)

    tracks = {}
    tracks["ahead"] = _track("VEHICLE", on_road(12.0, 0.0), hd, ones, 4.5, 1.9, "ahead")
    tracks["left"] = _track("VEHICLE", on_road(2.0, 3.5), hd, ones, 8.0, 2.5, "left")
    bus_valid = t >= 0.5 - 1e-9
    bus = _track("VEHICLE", on_road(25.0, -3.5), hd, bus_valid, 12.0, 2.55, "bus")
    bus["state"]["length"][~bus_valid] = 99.0  # garbage where invalid: must not enter the size
    tracks["bus"] = bus
    late_valid = t >= 5.0 - 1e-9
    tracks["late"] = _track("VEHICLE", on_road(40.0, 0.0), hd, late_valid, 4.6, 1.8, "late")
    tracks[SDC] = _track("VEHICLE", on_road(0.0, 0.0), hd, ones, 4.8, 2.0, SDC, z=187.3)
    walker = road_to_world(5.0 + 1.2 * t, 6.0, theta, origin)
    tracks["ped1"] = _track("PEDESTRIAN", walker, hd, ones, 0.6, 0.6, "ped1")
    tracks["cyc1"] = _track("CYCLIST", on_road(-8.0, 5.5), hd, ones, 1.8, 0.7, "cyc1")
    tracks["cone1"] = _track("TRAFFIC_CONE", road_to_world(np.full(T, 30.0), 7.0, theta, origin), hd, ones,
                             0.4, 0.4, "cone1")
    for j in range(extra_tracks):
        along0 = float(rng.uniform(-150, 150))
        lat = float(rng.choice([-3.5, 0.0, 3.5]))
        if abs(along0) < 20 and lat == 0.0:
            along0 += 60.0
        v = rng.random(T) > 0.1
        tracks[str(1000 + j)] = _track("VEHICLE", road_to_world(along0 + speed * 0.8 * t, lat, theta, origin), hd,
                                       v, 4.6, 1.9, str(1000 + j))
    s = np.linspace(-200.0, 600.0, 401)
    feats = {}
    for i, lat in enumerate((-3.5, 0.0, 3.5)):
        pl = np.zeros((len(s), 3), np.float32)
        pl[:, :2] = road_to_world(s, lat, theta, origin)
        feats[str(100 + i)] = {"type": "LANE_FREEWAY" if i == 0 else "LANE_SURFACE_STREET", "polyline": pl,
                               "polygon": pl[::40], "width": np.full((len(s), 2), 1.75, np.float32),
                               "entry_lanes": [], "exit_lanes": [], "left_neighbor": [], "right_neighbor": []}
    # the left lane carries a real polygon (as nuPlan / nuScenes conversions do); the others a width
    left_poly = np.zeros((4, 3), np.float32)
    left_poly[:, :2] = road_to_world(np.array([-200.0, 600.0, 600.0, -200.0]), np.array([1.75, 1.75, 5.25, 5.25]),
                                     theta, origin)
    feats["102"]["polygon"] = left_poly
    dw = np.zeros((4, 3), np.float32)
    dw[:, :2] = road_to_world(np.array([80.0, 90.0, 90.0, 80.0]), np.array([5.25, 5.25, 15.0, 15.0]), theta, origin)
    feats["600"] = {"type": "DRIVEWAY", "polygon": dw}
    bike = np.zeros((len(s), 3), np.float32)
    bike[:, :2] = road_to_world(s, 6.0, theta, origin)
    feats["200"] = {"type": "LANE_BIKE_LANE", "polyline": bike}
    for i, lat in enumerate((-5.25, 5.25)):
        edge = np.zeros((len(s), 3), np.float32)
        edge[:, :2] = road_to_world(s, lat, theta, origin)
        feats[str(300 + i)] = {"type": "ROAD_EDGE_BOUNDARY", "polyline": edge}
    line = np.zeros((len(s), 3), np.float32)
    line[:, :2] = road_to_world(s, 1.75, theta, origin)
    feats["400"] = {"type": "ROAD_LINE_BROKEN_SINGLE_WHITE", "polyline": line}
    cw = np.zeros((4, 3), np.float32)
    cw[:, :2] = road_to_world(np.array([50.0, 54.0, 54.0, 50.0]), np.array([-6.0, -6.0, 6.0, 6.0]), theta, origin)
    feats["500"] = {"type": "CROSSWALK", "polygon": cw}
    for j in range(extra_lanes):  # short lane pieces around the road (realistic feature counts)
        a0 = float(rng.uniform(-150, 300))
        lat = float(rng.uniform(-20, 20))
        pl = np.zeros((30, 3), np.float32)
        pl[:, :2] = road_to_world(np.linspace(a0, a0 + 30, 30), lat, theta + float(rng.normal(0, 0.3)), origin)
        feats[str(10000 + j)] = {"type": "LANE_SURFACE_STREET", "polyline": pl}
    lights = {"tl1": {"type": "TRAFFIC_LIGHT", "state": {"object_state": ["LANE_STATE_GO"] * T},
                      "lane": "101", "stop_point": np.zeros(3, np.float32),
                      "metadata": {"type": "TRAFFIC_LIGHT", "track_length": T}}}
    md = {"ts": (ts_start + t).astype(np.float32), "sdc_id": SDC, "dataset": dataset, "scenario_id": scenario_id,
          "coordinate": "waymo", "metadrive_processed": False, "source_file": "fixture", "id": scenario_id}
    if map_name is not None:
        md["map"] = map_name
    return {"id": scenario_id, "version": "MetaDrive v0.4.2.3", "length": T, "metadata": md, "tracks": tracks,
            "map_features": feats, "dynamic_map_states": lights}


def scenario_file_name(sc: dict) -> str:
    md = sc["metadata"]
    return f"sd_{md['dataset']}_v1_{md['scenario_id']}.pkl"


def _summary_entry(md: dict) -> dict:
    return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in md.items()}


def write_dataset(root: str, scenarios: list[dict], layout: str = "nested", protocol: int = 4) -> list[str]:
    """Writes scenarios as a ScenarioNet dataset in `root`. Returns the scenario file paths.

    layout: "flat" (files beside `dataset_summary.pkl`, no mapping file, like ScenarioNet's Waymo sample),
    "nested" (files in sub-folders `part_<i % 2>` named by `dataset_mapping.pkl`, like its nuScenes sample), or
    "plain" (scenario files in sub-folders, no summary and no mapping).
    """
    os.makedirs(root, exist_ok=True)
    summary, mapping, paths = {}, {}, []
    for i, sc in enumerate(scenarios):
        name = scenario_file_name(sc)
        sub = "" if layout == "flat" else f"part_{i % 2}"
        os.makedirs(os.path.join(root, sub), exist_ok=True)
        path = os.path.join(root, sub, name)
        with open(path, "wb") as f:
            pickle.dump(sc, f, protocol=protocol)
        paths.append(path)
        summary[name] = _summary_entry(sc["metadata"])
        mapping[name] = sub
    if layout != "plain":
        with open(os.path.join(root, "dataset_summary.pkl"), "wb") as f:
            pickle.dump(summary, f, protocol=protocol)
    if layout == "nested":
        with open(os.path.join(root, "dataset_mapping.pkl"), "wb") as f:
            pickle.dump(mapping, f, protocol=protocol)
    return paths


def write_scenario(path: str, sc, protocol: int = 4) -> str:
    with open(path, "wb") as f:
        pickle.dump(sc, f, protocol=protocol)
    return path


# ------------------------------------------------------------------------------------ hostile pickles
MARKER_ENV = "GPD_SCENARIONET_PICKLE_RAN"


def touch_marker(path: str) -> str:
    """What a hostile pickle would run on load: creates `path` and sets the MARKER_ENV environment variable."""
    with open(path, "w") as f:
        f.write("pickle code ran\n")
    os.environ[MARKER_ENV] = path
    return path


class TouchOnLoad:
    """Pickles to a call of `touch_marker(path)`: loading it with plain pickle runs that call."""

    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return (touch_marker, (self.path,))


class MkdirOnLoad:
    """Pickles to `os.mkdir(path)` (the global `posix.mkdir`)."""

    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return (os.mkdir, (self.path,))


class ExecOnLoad:
    """Pickles to `builtins.exec(code)` creating `path`."""

    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return (exec, (f"open({self.path!r}, 'w').write('ran')",))


class Foreign:
    """A plain class instance (no __reduce__): its pickle names `scenarionet_fixtures.Foreign`."""

    def __init__(self):
        self.x = 1


if __name__ == "__main__":
    import argparse

    p = argparse.ArgumentParser(description="write a ScenarioNet dataset of fixture scenarios")
    p.add_argument("out")
    p.add_argument("--scenarios", type=int, default=20)
    p.add_argument("--frames", type=int, default=91)
    p.add_argument("--hz", type=float, default=10.0)
    p.add_argument("--tracks", type=int, default=100, help="tracks in all (the special ones included)")
    p.add_argument("--lanes", type=int, default=300, help="lane polylines in all")
    p.add_argument("--maps", type=int, default=4)
    a = p.parse_args()
    scs = [make_scenario(a.frames, a.hz, map_name=f"map_{i % a.maps}", scenario_id=f"b{i:05d}",
                         extra_tracks=max(0, a.tracks - 8), extra_lanes=max(0, a.lanes - 3), seed=i)
           for i in range(a.scenarios)]
    write_dataset(a.out, scs, layout="nested")
    print(f"wrote {len(scs)} scenarios to {a.out}")
