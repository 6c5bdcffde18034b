"""Hand-built RawLogs and small stores for the data tests."""

from __future__ import annotations

import numpy as np

from gpd_jax.data import preprocess, store
from gpd_jax.data.raw import RawLog
from gpd_jax.data.roadgeom import Area, lane_area
from gpd_jax.geometry import AREA_KIND_ID
from gpd_jax.scene import TYPE_ID

THETA = 0.5  # the world frame is rotated against the road so that frame conversions are exercised


def rot(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def straight_road_log(num_frames: int = 130, num_others: int = 40, seed: int = 0) -> RawLog:
    """An ego driving at 10 m/s along a straight road (heading THETA in the world) among `num_others`
    vehicles at increasing distance, all moving with the ego. Special tracks:

    * track 1 (nearest) disappears from frame 60 on (window frames >= 60 - start invalid);
    * the last track appears only from frame 100 (not valid at the current frame: never selected);
    * track 2 has a NaN position at frame 10.
    """
    F, N = num_frames, num_others + 1
    t = np.arange(F) * 0.1
    R = rot(THETA)
    # road coordinates (along, lateral)
    along = np.zeros((F, N))
    lat = np.zeros((F, N))
    along[:, 0] = 10.0 * t
    offsets = np.concatenate([[0.0], 6.0 + 3.0 * np.arange(num_others)])  # ego, then 6, 9, 12, ... m ahead
    for j in range(1, N):
        along[:, j] = 10.0 * t + offsets[j]
        lat[:, j] = (-3.5, 0.0, 3.5)[j % 3]  # same-lane vehicles 9 m apart: no overlapping boxes
    local = np.stack([along, lat], -1)
    xy = local @ R.T + np.array([100.0, -50.0])
    heading = np.full((F, N), THETA)
    valid = np.ones((F, N), bool)
    valid[60:, 1] = False
    valid[:100, N - 1] = False
    xy[~valid] = np.nan
    xy[10, 2] = np.nan
    size = np.tile(np.array([[4.6, 1.85]], np.float32), (N, 1))
    size[3] = (12.0, 2.55)
    atype = np.full((N,), TYPE_ID["car"], np.int32)
    atype[3] = TYPE_ID["bus"]
    # lanes: three parallel lanes along the road, 400 m long, plus a crossing road
    s = np.linspace(-100, 300, 201)
    lanes = []
    for off in (-3.5, 0.0, 3.5):
        lanes.append(np.stack([s, np.full_like(s, off)], -1) @ R.T + np.array([100.0, -50.0]))
    cross = np.stack([np.full(81, 40.0), np.linspace(-40, 40, 81)], -1) @ R.T + np.array([100.0, -50.0])
    lanes.append(cross)
    # drivable area: the three lanes 3.5 m wide (road lateral -5.25 .. 5.25), the crossing road 7 m wide and a
    # 20 x 20 m junction where they meet (road coordinates along 30 .. 50, lateral -10 .. 10)
    areas = [lane_area(ln, 3.5) for ln in lanes[:3]] + [lane_area(cross, 7.0)]
    jn = np.array([[30.0, -10.0], [50.0, -10.0], [50.0, 10.0], [30.0, 10.0]]) @ R.T + np.array([100.0, -50.0])
    areas.append(Area(AREA_KIND_ID["junction"], jn))
    return RawLog(name="straight", location="road_a", timestamps=t, agent_ids=tuple(f"v{j}" for j in range(N)),
                  agent_xy=xy, agent_heading=heading, agent_valid=valid, agent_size=size, agent_type=atype,
                  lanes=tuple(lanes), ego_index=None, areas=tuple(areas))


def write_small_store(path: str, n_shards: int = 3, per_shard: int = 4, split: str = "train",
                      offset: float = 0.0) -> list[str]:
    """A store of `n_shards` shards built from the hand-built log (different window starts); sample k's ego is
    moved by 0.001 k + `offset` m along x (to tell samples and stores apart)."""
    log = straight_road_log()
    lp = preprocess.lane_points(log.lanes)
    road = preprocess.road_index(log)
    ids = []
    k = 0
    for s in range(n_shards):
        samples, sids = [], []
        for _ in range(per_shard):
            start = k % 25
            smp = preprocess.make_sample(log, start, 0, lp=lp, road=road)
            smp["xy"][:, 0, 0] += 0.001 * k + offset  # make every sample distinguishable
            smp["ego_pose"][:, 0] = smp["xy"][:, 0, 0]
            samples.append(smp)
            sids.append(f"straight/{k}")
            k += 1
        store.write_shard(path, split, s, store.stack_samples(samples), sids, ["road_a"] * per_shard)
        ids += sids
    store.write_manifest(path)
    return ids
