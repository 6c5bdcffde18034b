"""A reader of CommonRoad maps (`.xml` scenario or map files, format 2020a and the map-only 3.0 format, which
store lanelets the same way; the older 2017a / 2018b files too): lanelets -> directed lane centrelines and
drivable-area polygons in the file's metric frame. Pure numpy and the standard library's XML parser;
`commonroad-io` is not needed.

A CommonRoad file's root `<commonRoad>` holds `<lanelet id=>` elements (its direct children; the `<lanelet ref=>`
elements inside planning problems and obstacle states are references, not lanelets), each with a `<leftBound>`
and a `<rightBound>` (a list of `<point><x>..</x><y>..</y></point>`, metres, and an optional `<lineMarking>`),
`<predecessor ref=>` / `<successor ref=>`, optional `<adjacentLeft|adjacentRight ref= drivingDir=same|opposite>`,
one or more `<laneletType>` (2020a on; a 2018b file has none) and optional `<userOneWay>` / `<userBidirectional>`
road users. Traffic signs, lights, intersections, obstacles and planning problems are counted, not used.

Conventions:

* **Frame.** CommonRoad coordinates are already metric and local (the file's own Cartesian frame), so nothing
  is projected. A `<location><geoTransformation>` (a proj string and a translation / rotation to a geographic
  frame, as the dataset converters write it) is ignored: the map-only use needs no geographic position.
* **Bounds and direction.** The format defines a lanelet's direction of travel by the order of its bound points,
  with the left bound on the left, so the bounds are taken as stored. Lanelet2's alignment heuristic
  (`lanelet2.align_bounds`) is not applied: on the 41 real maps of `commonroad-dataset-converter` every lanelet's
  left bound lies left of its centreline along most of its length and successors start where their predecessors
  end, while the heuristic would reverse a bound of 10 of these vehicle lanelets (parallel bounds, both running
  in the direction of travel, whose middle vertices are far apart).
* **Centreline**: `lanelet2.centreline`, the average of the two bounds sampled at the union of their vertices'
  arc-length fractions. (The format pairs the bounds' points one to one and `commonroad-io` averages the pairs;
  the two agree to < 1 mm on half of the real lanelets, and where they differ by > 0.3 m the arc-length average
  is the better centred of the two on 80 % of them.)
* **Drivable area** (`lanelet2.lanelet_ring`): the left bound followed by the reversed right bound.
* **Who uses it.** A lanelet is a vehicle lane when
  - none of its types is in `NON_VEHICLE_TYPES`: sidewalk, crosswalk, bicycleLane, border, parking, busStop,
    shoulder (a hard shoulder is not a lane of travel; nor is Lanelet2's `emergency_lane` to its reader),
    restricted ("cars not allowed", `commonroad-io`'s definition; on the real maps these are roundabout aprons
    and hatched islands) and restricted_area;
  - at least one of its types is in `VEHICLE_TYPES` (urban, country, highway, interstate, intersection,
    driveWay, mainCarriageWay, accessRamp, exitRamp, busLane, unknown: `unknown` lanelets of the real maps are
    ordinary lanes at intersections), or it has no type at all (2018b);
  - it names no road user, or at least one of `VEHICLE_USERS`.
  Bus lanes are kept as Lanelet2's reader keeps `bus_lane`: they are lanes of the carriageway on a car's map.
  A vehicle lane with a motor vehicle (`TWO_WAY_USERS`, i.e. not only `priorityVehicle`, which converters
  allow both ways on every urban lanelet) among its `<userBidirectional>` is driven both ways:
  `vehicle_centrelines` gives it in both directions.

Parsing uses `xml.etree.ElementTree` (expat >= 2.4 refuses entity-expansion bombs; external entities are never
fetched); nothing in a map is executed. Every problem raises `gpd_jax.data.errors.DataError` naming the file and
what is wrong: not XML, not a `<commonRoad>` root, a lanelet without an id, without a left or right bound, with a
point whose x / y is not a finite number, or with a bound of fewer than two distinct points; no lanelet at all.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections import Counter

import numpy as np

from gpd_jax.data.errors import DataError
from gpd_jax.data.sources.xmlmap import xml_root
from gpd_jax.data.sources.lanelet2 import centreline, lanelet_ring

VEHICLE_TYPES = ("urban", "country", "highway", "interstate", "intersection", "driveWay", "mainCarriageWay",
                 "accessRamp", "exitRamp", "busLane", "unknown")
NON_VEHICLE_TYPES = ("sidewalk", "crosswalk", "bicycleLane", "border", "parking", "busStop", "shoulder",
                     "restricted", "restricted_area")
VEHICLE_USERS = ("vehicle", "car", "truck", "bus", "motorcycle", "taxi", "priorityVehicle")
TWO_WAY_USERS = ("vehicle", "car", "truck", "bus", "motorcycle", "taxi")


@dataclasses.dataclass(frozen=True)
class CommonRoadLanelet:
    """One lanelet, bounds as stored (the direction of travel).

    Attributes:
      id: its `id` attribute (a string).
      types: its `<laneletType>`s, in file order (empty in a 2018b file).
      users_one_way, users_bidirectional: its `<userOneWay>` / `<userBidirectional>` road users.
      predecessors, successors: the lanelet ids they name.
      adjacent_left, adjacent_right: (id, same direction?) or None.
      left, right: f64[P, 2], f64[Q, 2] the left and right bounds (metres).
      centreline: f64[R, 2] their average (`lanelet2.centreline`), in the direction of travel.
    """

    id: str
    types: tuple[str, ...]
    users_one_way: tuple[str, ...]
    users_bidirectional: tuple[str, ...]
    predecessors: tuple[str, ...]
    successors: tuple[str, ...]
    adjacent_left: tuple[str, bool] | None
    adjacent_right: tuple[str, bool] | None
    left: np.ndarray
    right: np.ndarray
    centreline: np.ndarray

    @property
    def is_vehicle_lane(self) -> bool:
        types = set(self.types)
        if types & set(NON_VEHICLE_TYPES) or (types and not types & set(VEHICLE_TYPES)):
            return False
        users = set(self.users_one_way) | set(self.users_bidirectional)
        return not users or bool(users & set(VEHICLE_USERS))

    @property
    def two_way(self) -> bool:
        return bool(set(self.users_bidirectional) & set(TWO_WAY_USERS))


@dataclasses.dataclass(frozen=True)
class CommonRoadMap:
    """A CommonRoad map in its own metric frame.

    Attributes:
      path: the file read.
      version: the root's `commonRoadVersion` ('' when absent).
      lanelets: every lanelet, in file order.
      counts: what the file holds (`lanelets`, `lanelet_<type>`, `<element>` for the root's other children), for
        build statistics.
    """

    path: str
    version: str
    lanelets: tuple[CommonRoadLanelet, ...]
    counts: dict

    @property
    def vehicle_lanelets(self) -> tuple[CommonRoadLanelet, ...]:
        return tuple(ll for ll in self.lanelets if ll.is_vehicle_lane)

    def vehicle_centrelines(self) -> tuple[np.ndarray, ...]:
        """The vehicle lanes' centrelines f64[R, 2], each in its direction of travel; a two-way lanelet twice,
        once reversed."""
        out = []
        for ll in self.vehicle_lanelets:
            out.append(ll.centreline)
            if ll.two_way:
                out.append(ll.centreline[::-1].copy())
        return tuple(out)

    def vehicle_rings(self) -> tuple[np.ndarray, ...]:
        """The vehicle lanes' drivable polygons f64[V, 2] (`lanelet2.lanelet_ring`)."""
        return tuple(lanelet_ring(ll.left, ll.right) for ll in self.vehicle_lanelets)


def _text(elem) -> str:
    return (elem.text or "").strip()


def _bound(path: str, lanelet: str, elem, role: str) -> np.ndarray:
    if elem is None:
        raise DataError(path, f"lanelet {lanelet} has no {role}")
    pts = []
    for i, p in enumerate(elem.findall("point")):
        x, y = p.find("x"), p.find("y")
        try:
            xy = (float(_text(x)), float(_text(y)))
        except (AttributeError, ValueError):
            raise DataError(path, f"lanelet {lanelet}: point {i} of its {role} has no numeric <x> and <y>") from None
        if not (math.isfinite(xy[0]) and math.isfinite(xy[1])):
            raise DataError(path, f"lanelet {lanelet}: point {i} of its {role} is not finite: {xy}")
        pts.append(xy)
    pts = np.array(pts, np.float64).reshape(-1, 2)
    if len(pts):
        pts = pts[np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=-1) > 1e-6])]
    if len(pts) < 2:
        raise DataError(path, f"lanelet {lanelet}: its {role} has {len(pts)} distinct point(s); a bound needs two")
    return pts


def _adjacent(elem) -> tuple[str, bool] | None:
    if elem is None:
        return None
    return str(elem.get("ref")), elem.get("drivingDir", "same") != "opposite"


def read_commonroad(path: str | os.PathLike) -> CommonRoadMap:
    """Reads a CommonRoad `.xml` file's lanelets (conventions: module docstring).

    Raises `DataError` naming the file and the problem.
    """
    path = os.fspath(path)
    root = xml_root(path, "CommonRoad", "commonRoad")
    counts: Counter = Counter()
    lanelets = []
    for elem in root:
        if elem.tag != "lanelet":
            counts[str(elem.tag)] += 1
            continue
        lid = elem.get("id")
        if not lid:
            raise DataError(path, f"lanelet number {len(lanelets) + 1} has no id attribute")
        left = _bound(path, lid, elem.find("leftBound"), "leftBound")
        right = _bound(path, lid, elem.find("rightBound"), "rightBound")
        types = tuple(_text(t) for t in elem.findall("laneletType"))
        for t in types or ("(none)",):
            counts[f"lanelet_{t}"] += 1
        lanelets.append(CommonRoadLanelet(
            id=str(lid), types=types,
            users_one_way=tuple(_text(u) for u in elem.findall("userOneWay")),
            users_bidirectional=tuple(_text(u) for u in elem.findall("userBidirectional")),
            predecessors=tuple(str(p.get("ref")) for p in elem.findall("predecessor")),
            successors=tuple(str(s.get("ref")) for s in elem.findall("successor")),
            adjacent_left=_adjacent(elem.find("adjacentLeft")), adjacent_right=_adjacent(elem.find("adjacentRight")),
            left=left, right=right, centreline=centreline(left, right)))
    counts["lanelets"] = len(lanelets)
    if not lanelets:
        raise DataError(path, "holds no lanelet (no <lanelet> child of <commonRoad>): not a CommonRoad map")
    return CommonRoadMap(path, root.get("commonRoadVersion", ""), tuple(lanelets), dict(counts))


def read_commonroad_lanes(path: str | os.PathLike) -> tuple[np.ndarray, ...]:
    """The map-only view of a CommonRoad map: its vehicle lanes' directed centrelines f64[R, 2] in the file's
    metric frame, what `gpd_jax.data.preprocess.lane_points` takes (as `lanelet2.read_lanelet2_lanes`)."""
    return read_commonroad(path).vehicle_centrelines()


def read_commonroad_areas(path: str | os.PathLike) -> tuple[np.ndarray, ...]:
    """The vehicle lanes' drivable polygons f64[V, 2] of a CommonRoad map (`CommonRoadMap.vehicle_rings`)."""
    return read_commonroad(path).vehicle_rings()
