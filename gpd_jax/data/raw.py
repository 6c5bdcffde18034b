"""`RawLog`: what every data source (SUMO, nuPlan, ...) produces before preprocessing into samples.

A raw log is a recording at 10 Hz in one metric world frame (metres, x east / y north or any right-handed
frame, headings counter-clockwise from +x, radians). Preprocessing (`gpd_jax.data.preprocess`) cuts it into
fixed-shape samples in the `gpd_jax.scene.Scene` convention.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class RawLog:
    """A 10 Hz recording of vehicles plus the lane centrelines of its road network.

    Attributes:
      name: unique name of the recording (a SUMO run or a nuPlan log file stem).
      location: the road network / map it was recorded on; splits are made by this key so that no test
        scene shares a road with training.
      timestamps: f64[F] seconds, 0.1 s apart.
      agent_ids: tuple of N unique string ids, one per track.
      agent_xy: f64[F, N, 2] box centres in the world frame (NaN where not observed).
      agent_heading: f64[F, N] headings (radians, counter-clockwise from +x).
      agent_valid: bool[F, N] observed in that frame.
      agent_size: f32[N, 2] (length, width) in metres.
      agent_type: i32[N] index into `gpd_jax.scene.AGENT_TYPES`.
      lanes: tuple of f64[P_i, 2] lane centrelines (junction/connector lanes included) in the world frame.
      ego_index: index of the track that is the recording vehicle (nuPlan), or None when any vehicle present
        for a whole window may serve as ego (SUMO).
      areas: tuple of `gpd_jax.data.roadgeom.Area` (kind, exterior ring f64[V, 2], holes) in the world frame:
        the drivable surface (lanes, junctions / intersections, other drivable areas); empty when the source
        has no geometry (samples then carry an all-invalid road geometry, counted in the build statistics).
      road_edges: tuple of f64[P_i, 2] the map's own road-edge lines in the world frame (curbs, road borders;
        any direction: `gpd_jax.data.roadgeom.orient_lines` turns them), empty where the map draws none.
      areas_outline: what the outline of `areas` is where `road_edges` is empty: "drivable_area" (the areas are
        the whole road surface: SUMO, nuPlan) or "lane_union" (only the lanes': a map without road edges).
      signals: optional `gpd_jax.data.signals.RawSignals`, the traffic-light states per frame (None: no signals).
    """

    name: str
    location: str
    timestamps: np.ndarray
    agent_ids: tuple[str, ...]
    agent_xy: np.ndarray
    agent_heading: np.ndarray
    agent_valid: np.ndarray
    agent_size: np.ndarray
    agent_type: np.ndarray
    lanes: tuple[np.ndarray, ...]
    ego_index: int | None = None
    areas: tuple = ()
    road_edges: tuple = ()
    areas_outline: str = "lane_union"
    signals: object = None

    @property
    def num_frames(self) -> int:
        return int(self.agent_xy.shape[0])

    @property
    def num_agents(self) -> int:
        return int(self.agent_xy.shape[1])
