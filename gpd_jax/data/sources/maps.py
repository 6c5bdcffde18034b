"""Real road maps read as lanes only: one entry point over the formats the importers read.

`read_map_lanes(path)` gives a map file's vehicle lanes as directed centrelines f64[P_i, 2] in a local metric
frame, what `gpd_jax.data.preprocess.lane_points` takes; the map tokenizer draws its map-only training and
evaluation frames from them (`gpd_jax.map_tokenizer.netframes`). The format is told by the file name:

| name ends with | format | reader |
|---|---|---|
| `.net.xml`, `.net.xml.gz` | SUMO network | `sumo_networks.read_network_lanes` (one-to-one lane chains merged) |
| `.osm` | Lanelet2 | `lanelet2.read_lanelet2_lanes` (projected around the map's centre) |
| `.xml` (other) | CommonRoad | `commonroad.read_commonroad_lanes` |
| `.bin` | Apollo HD map (`base_map.bin`) | `apollo.read_apollo_lanes` |

`mirror_lanes` turns a right-hand map into a left-hand one (and back): the geometry mirrored across the x axis,
each lane still in its direction of travel.
"""

from __future__ import annotations

import os

import numpy as np

from gpd_jax.data.errors import DataError

FORMATS = {"sumo": (".net.xml", ".net.xml.gz"), "lanelet2": (".osm",), "apollo": (".bin",), "commonroad": (".xml",)}


def map_format(path: str | os.PathLike) -> str:
    """The format of a map file by its name (see the module docstring); DataError naming the file otherwise."""
    name = os.path.basename(os.fspath(path)).lower()
    for fmt, ends in FORMATS.items():  # SUMO before CommonRoad: both end in .xml
        if name.endswith(ends):
            return fmt
    known = ", ".join(e for ends in FORMATS.values() for e in ends)
    raise DataError(os.fspath(path), f"unknown map format: the name ends with none of {known}")


def read_map_lanes(path: str | os.PathLike) -> tuple[np.ndarray, ...]:
    """A map file's vehicle lanes: directed centrelines f64[P_i, 2] in metres (see the module docstring)."""
    path = os.fspath(path)
    fmt = map_format(path)
    if fmt == "sumo":
        from gpd_jax.data.sources import sumo_networks
        return sumo_networks.read_network_lanes(path)
    if fmt == "lanelet2":
        from gpd_jax.data.sources import lanelet2
        return lanelet2.read_lanelet2_lanes(path)
    if fmt == "apollo":
        from gpd_jax.data.sources import apollo
        return apollo.read_apollo_lanes(path)
    from gpd_jax.data.sources import commonroad
    return commonroad.read_commonroad_lanes(path)


def mirror_lanes(lanes) -> tuple[np.ndarray, ...]:
    """Lanes mirrored across the x axis (y -> -y), each kept in its direction of travel: right-hand traffic
    becomes left-hand traffic."""
    return tuple(np.asarray(lane, np.float64) * np.array([1.0, -1.0]) for lane in lanes)
