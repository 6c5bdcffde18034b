"""A reader of Lanelet2 maps (`.osm` files, as the INTERACTION dataset ships them): lanelets -> directed lane
centrelines and drivable-area polygons in a local metric frame. Pure numpy and the standard library's XML parser;
Lanelet2 itself is not needed.

A Lanelet2 `.osm` file is OpenStreetMap XML: `node`s (`id`, `lat`, `lon`; some tools also write local `x` / `y`
tags, which are ignored), `way`s (linestrings: `nd ref=` node ids and `tag`s such as `type=curbstone`) and
`relation`s. A relation tagged `type=lanelet` has exactly one member way of role `left` and one of role `right`;
its `subtype` (`road`, `highway`, `crosswalk`, ...; `road` when absent) says who uses it. Other relations
(`regulatory_element`, `multipolygon` keep-out areas, ...) are counted, not used.

Conventions:

* **Projection.** Lanelet2's `UtmProjector(Origin(lat0, lon0))`: the UTM zone (WGS84) of the origin, and
  coordinates relative to the origin's UTM coordinates (`LocalProjection`). INTERACTION uses the origin
  lat = lon = 0 for every map ("we decided to use (0|0) for every scenario", its `map_vis_lanelet2.py`), which
  puts its maps ~1 km north-east of the origin in UTM zone 31, in the metres its track files use. Points in
  another zone are projected in the origin's zone (Lanelet2 transfers them the same way). pyproj does the
  projection (`gpd_jax.data.sources.gpkg.make_transform`).
* **Bounds and direction.** Lanelet2's loader aligns the bounds (`lanelet::geometry::align`): the left bound is
  reversed when the right bound's middle point is not on its right, then the right bound is reversed when the
  left bound's middle point is not on its left. `align_bounds` does the same. The lanelet's direction of travel
  is then the bounds' direction: the left bound on the left.
* **Centreline** (`centreline`): the average of the aligned left and right bounds, both sampled at the union of
  their vertices' arc-length fractions (Lanelet2's own centreline is a more elaborate construction with the same
  end points; the average differs from it by centimetres on the near-parallel bounds of road lanelets).
* **Drivable area** (`lanelet_ring`): the polygon of the left bound followed by the reversed right bound.
* **Who uses it.** Lanelets whose subtype is in `VEHICLE_SUBTYPES` are vehicle lanes; the others (crosswalk,
  walkway, bicycle lane, ...) are kept in `Lanelet2Map.lanelets` with their subtype but left out of
  `vehicle_lanelets`. A lanelet tagged `one_way=no` is driven both ways: `vehicle_centrelines` gives it in both
  directions.

Parsing uses `xml.etree.ElementTree` (expat >= 2.4 refuses entity-expansion bombs; external entities are never
fetched); nothing in a map is executed. Every problem raises `gpd_jax.data.errors.DataError` naming the file and
what is wrong: not XML, a node without numeric `lat` / `lon`, a way naming a missing node, a lanelet without a
left or right bound or with a bound of fewer than two points, a bound of several ways that do not meet end to
end, no lanelet at all.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections import Counter

import numpy as np

from gpd_jax.data.errors import DataError
from gpd_jax.data.sources.xmlmap import xml_root

# Lanes vehicles travel on. Left out as in the CommonRoad and Apollo readers: `emergency_lane` (a hard shoulder),
# pedestrian, bicycle and crosswalk lanelets. `main_road` is not Lanelet2's: SinD's Changchun map tags its through
# lanes so.
VEHICLE_SUBTYPES = ("road", "highway", "play_street", "bus_lane", "main_road")
DEFAULT_SUBTYPE = "road"  # Lanelet2's default when a lanelet has no subtype tag
# Way types that bound the road physically (Lanelet2's line-string types): the map's road edges.
ROAD_BORDER_TYPES = ("curbstone", "road_border", "guard_rail", "wall", "fence")


@dataclasses.dataclass(frozen=True)
class Lanelet:
    """One lanelet, projected, its bounds aligned to its direction of travel.

    Attributes:
      id: the relation id (a string).
      subtype: its `subtype` tag (`road` when absent).
      one_way: False only when tagged `one_way=no`.
      left, right: f64[P, 2], f64[Q, 2] the aligned left and right bounds (metres, local frame).
      centreline: f64[R, 2] their average, in the direction of travel (`centreline`).
    """

    id: str
    subtype: str
    one_way: bool
    left: np.ndarray
    right: np.ndarray
    centreline: np.ndarray

    @property
    def is_vehicle_lane(self) -> bool:
        return self.subtype in VEHICLE_SUBTYPES


@dataclasses.dataclass(frozen=True)
class Lanelet2Map:
    """A Lanelet2 map in a local metric frame.

    Attributes:
      path: the file read.
      origin: (lat, lon) degrees of the projection's origin (the local frame's (0, 0)).
      lanelets: every lanelet, in file order.
      counts: what the file holds (`nodes`, `ways`, `lanelets`, `lanelet_<subtype>`, `relation_<type>_<subtype>`,
        `bounds_reversed`, `road_border_ways`), for build statistics.
      road_borders: f64[P, 2] the ways whose `type` is in `ROAD_BORDER_TYPES` (curbs, road borders, guard
        rails, walls, fences), in file order and their own direction: the map's road edges.
    """

    path: str
    origin: tuple[float, float]
    lanelets: tuple[Lanelet, ...]
    counts: dict
    road_borders: tuple = ()

    @property
    def vehicle_lanelets(self) -> tuple[Lanelet, ...]:
        return tuple(ll for ll in self.lanelets if ll.is_vehicle_lane)

    def vehicle_centrelines(self) -> tuple[np.ndarray, ...]:
        """The vehicle lanes' centrelines f64[R, 2], each in its direction of travel; a two-way lanelet
        (`one_way=no`) twice, once reversed."""
        out = []
        for ll in self.vehicle_lanelets:
            out.append(ll.centreline)
            if not ll.one_way:
                out.append(ll.centreline[::-1].copy())
        return tuple(out)

    def vehicle_rings(self) -> tuple[np.ndarray, ...]:
        """The vehicle lanes' drivable polygons f64[V, 2] (`lanelet_ring`)."""
        return tuple(lanelet_ring(ll.left, ll.right) for ll in self.vehicle_lanelets)


# ---------------------------------------------------------------------------------------------------- projection
def utm_zone(lat: float, lon: float) -> tuple[int, bool]:
    """(UTM zone 1-60, south) of a WGS84 point, as GeographicLib's standard zone (without the Norway / Svalbard
    exceptions, which Lanelet2 maps at lat = lon = 0 never meet)."""
    zone = int(math.floor((lon + 180.0) / 6.0)) % 60 + 1
    return zone, lat < 0


def local_projector(origin_lat: float = 0.0, origin_lon: float = 0.0):
    """Lanelet2's `UtmProjector(Origin(origin_lat, origin_lon))` as a function (lat f[...], lon f[...]) ->
    (x f64[...], y f64[...]) metres east / north of the origin, in the origin's UTM zone."""
    from gpd_jax.data.sources.gpkg import make_transform

    zone, south = utm_zone(origin_lat, origin_lon)
    tf = make_transform("EPSG:4326", (32700 if south else 32600) + zone)
    x0, y0 = tf(np.array([origin_lon]), np.array([origin_lat]))

    def project(lat, lon):
        x, y = tf(np.asarray(lon, np.float64), np.asarray(lat, np.float64))
        return x - x0[0], y - y0[0]

    return project


# ------------------------------------------------------------------------------------------------------ geometry
def signed_distance(line: np.ndarray, point: np.ndarray) -> float:
    """Distance of `point` f[2] from the polyline `line` f[P >= 2, 2] (its nearest segment), positive when the
    point lies left of that segment (Lanelet2's `signedDistance`)."""
    a, b = line[:-1], line[1:]
    d = b - a
    dd = np.maximum(np.sum(d * d, -1), 1e-18)
    t = np.clip(np.sum((point - a) * d, -1) / dd, 0.0, 1.0)
    near = a + t[:, None] * d
    dist = np.linalg.norm(point - near, axis=-1)
    i = int(np.argmin(dist))
    cross = d[i, 0] * (point[1] - a[i, 1]) - d[i, 1] * (point[0] - a[i, 0])
    return float(dist[i]) if cross >= 0 else -float(dist[i])


def _middle(line: np.ndarray) -> np.ndarray:
    return line[len(line) // 2] if len(line) > 2 else (line[0] + line[-1]) / 2


def align_bounds(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Lanelet2's `geometry::align`: (left, right, number of bounds reversed) with both bounds f[., 2] pointing in
    the lanelet's direction of travel (the left bound on the left)."""
    flips = 0
    if signed_distance(left, _middle(right)) >= 0:  # the right bound is not on the left bound's right
        left, flips = left[::-1], flips + 1
    if signed_distance(right, _middle(left)) <= 0:  # the left bound is not on the right bound's left
        right, flips = right[::-1], flips + 1
    return np.ascontiguousarray(left), np.ascontiguousarray(right), flips


def _fractions(line: np.ndarray) -> np.ndarray:
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=-1))])
    return s / s[-1] if s[-1] > 0 else np.linspace(0.0, 1.0, len(line))


def _at(line: np.ndarray, frac: np.ndarray, at: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(at, frac, line[:, 0]), np.interp(at, frac, line[:, 1])], -1)


def centreline(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The average f64[R, 2] of two aligned bounds, both sampled at the union of their vertices' arc-length
    fractions (R <= P + Q)."""
    fl, fr = _fractions(left), _fractions(right)
    at = np.unique(np.concatenate([fl, fr]))
    return (_at(left, fl, at) + _at(right, fr, at)) / 2


def lanelet_ring(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The lanelet's polygon f64[P + Q, 2]: the left bound, then the right bound reversed."""
    return np.concatenate([left, right[::-1]])


# -------------------------------------------------------------------------------------------------------- reading
def _tags(elem) -> dict[str, str]:
    return {t.get("k"): t.get("v") for t in elem.findall("tag")}


def read_lanelet2(path: str | os.PathLike, origin: tuple[float, float] | None = (0.0, 0.0)) -> Lanelet2Map:
    """Reads a Lanelet2 `.osm` file, projected around `origin` (lat, lon) (conventions: module docstring); `None`
    is the mean of the file's nodes (a map that is not in INTERACTION's frame around lat = lon = 0: the local
    coordinates stay small enough for float32).

    Raises `DataError` naming the file and the problem.
    """
    path = os.fspath(path)
    root = xml_root(path, "Lanelet2 .osm", "osm")
    counts: Counter = Counter()
    ids, lats, lons = [], [], []
    for n in root.iter("node"):
        nid = n.get("id")
        try:
            lats.append(float(n.get("lat")))
            lons.append(float(n.get("lon")))
        except (TypeError, ValueError):
            raise DataError(path, f"node {nid}: lat={n.get('lat')!r}, lon={n.get('lon')!r} are not numbers") from None
        if not (math.isfinite(lats[-1]) and math.isfinite(lons[-1]) and abs(lats[-1]) <= 90):
            raise DataError(path, f"node {nid}: lat={lats[-1]}, lon={lons[-1]} is not a point on the earth")
        ids.append(nid)
    counts["nodes"] = len(ids)
    if not ids:
        raise DataError(path, "holds no node")
    if origin is None:
        origin = (float(np.mean(lats)), float(np.mean(lons)))
    x, y = local_projector(*origin)(np.array(lats), np.array(lons))
    node_xy = {nid: (float(a), float(b)) for nid, a, b in zip(ids, x, y)}
    ways: dict[str, list[str]] = {}
    borders = []
    for w in root.iter("way"):
        ways[w.get("id")] = [nd.get("ref") for nd in w.findall("nd")]
        if _tags(w).get("type") in ROAD_BORDER_TYPES:
            pts = np.array([node_xy[r] for r in ways[w.get("id")] if r in node_xy], np.float64).reshape(-1, 2)
            if len(pts) >= 2:
                borders.append(pts)
    counts["ways"] = len(ways)
    counts["road_border_ways"] = len(borders)

    def chained_refs(wids: list[str], lanelet: str, role: str) -> list[str]:
        """The node refs of a bound made of one way or of several that meet end to end (the levelXData maps:
        inD, rounD, highD), in the first way's direction."""
        for wid in wids:
            if wid not in ways:
                raise DataError(path, f"lanelet {lanelet}: its {role} bound names way {wid}, which is not in the file")
        refs, rest = list(ways[wids[0]]), [list(ways[w]) for w in wids[1:]]
        while rest:
            for k, w in enumerate(rest):
                if w and refs and w[0] == refs[-1]:
                    refs += w[1:]
                elif w and refs and w[-1] == refs[-1]:
                    refs += w[::-1][1:]
                elif w and refs and w[-1] == refs[0]:
                    refs = w[:-1] + refs
                elif w and refs and w[0] == refs[0]:
                    refs = w[::-1][:-1] + refs
                else:
                    continue
                rest.pop(k)
                break
            else:
                raise DataError(path, f"lanelet {lanelet}: the ways {', '.join(wids)} of its {role} bound do not "
                                      "meet end to end")
        return refs

    def way_points(wids: list[str], lanelet: str, role: str) -> np.ndarray:
        refs = chained_refs(wids, lanelet, role)
        missing = [r for r in refs if r not in node_xy]
        if missing:
            raise DataError(path, f"way {'/'.join(wids)} (the {role} bound of lanelet {lanelet}) names node "
                                  f"{missing[0]}, which is not in the file")
        pts = np.array([node_xy[r] for r in refs], np.float64).reshape(-1, 2)
        keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=-1) > 1e-6]) if len(pts) else []
        pts = pts[keep]
        if len(pts) < 2:
            raise DataError(path, f"way {'/'.join(wids)} (the {role} bound of lanelet {lanelet}) has {len(pts)} "
                                  "distinct point(s); a bound needs two")
        return pts

    lanelets = []
    for r in root.iter("relation"):
        tags = _tags(r)
        rid = r.get("id")
        if tags.get("type") != "lanelet":
            counts[f"relation_{tags.get('type')}_{tags.get('subtype')}"] += 1
            continue
        bounds: dict[str, list[str]] = {}
        for m in r.findall("member"):
            role = m.get("role")
            if role in ("left", "right") and m.get("type") == "way":
                bounds.setdefault(role, []).append(m.get("ref"))
        for role in ("left", "right"):
            if role not in bounds:
                raise DataError(path, f"lanelet {rid} has no {role} bound (a member way with role '{role}')")
        left, right, flips = align_bounds(way_points(bounds["left"], rid, "left"),
                                          way_points(bounds["right"], rid, "right"), )
        counts["bounds_reversed"] += flips
        subtype = tags.get("subtype") or DEFAULT_SUBTYPE
        counts[f"lanelet_{subtype}"] += 1
        lanelets.append(Lanelet(str(rid), subtype, tags.get("one_way", "yes") != "no", left, right,
                                centreline(left, right)))
    counts["lanelets"] = len(lanelets)
    if not lanelets:
        raise DataError(path, "holds no lanelet (no relation tagged type=lanelet): not a Lanelet2 map")
    return Lanelet2Map(path, (float(origin[0]), float(origin[1])), tuple(lanelets), dict(counts), tuple(borders))


def read_lanelet2_lanes(path: str | os.PathLike,
                        origin: tuple[float, float] | None = None) -> tuple[np.ndarray, ...]:
    """The map-only view of a Lanelet2 map: its vehicle lanes' directed centrelines f64[R, 2] in the local frame
    (by default around the mean of its nodes), what `gpd_jax.data.preprocess.lane_points` takes (e.g. to draw
    map-tokenizer training frames from a map with no traffic: `gpd_jax.map_tokenizer.netframes`)."""
    return read_lanelet2(path, origin).vehicle_centrelines()
