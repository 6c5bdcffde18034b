"""A reader of Apollo HD maps (`base_map.bin`, a serialized `apollo.hdmap.Map` protobuf, as Apollo and the LGSVL
simulator ship them): lanes -> directed lane centrelines and drivable-area polygons in a local metric frame. Pure
Python: a small decoder of the protobuf wire format that reads only the fields below; neither protobuf nor
Apollo's generated classes are needed.

The field numbers are facts of Apollo's schema, `modules/map/proto/{map,map_lane,map_geometry,map_id}.proto` and
`modules/common/proto/geometry.proto` of github.com/lgsvl/apollo-5.0 at commit
105f7fd19220dc4c04be1e075b1a5d932eaa2f3f (unchanged in ApolloAuto/apollo 20e2ef0e0fdc5ba7825a8e93e746d58df0805cb7,
`modules/common_msgs/map_msgs/`):

    Map          header = 1 (Header), lane = 4 (Lane, repeated)
    Header       projection = 3 (Projection: proj = 1, a string)
    Lane         id = 1 (Id: id = 1, a string), central_curve = 2 (Curve), left_boundary = 3,
                 right_boundary = 4 (LaneBoundary: curve = 1), predecessor_id = 8, successor_id = 9 (Id, repeated),
                 type = 12 (LaneType: NONE 1, CITY_DRIVING 2, BIKING 3, SIDEWALK 4, PARKING 5, SHOULDER 6),
                 junction_id = 16 (Id), direction = 19 (LaneDirection: FORWARD 1, BACKWARD 2, BIDIRECTION 3)
    Curve        segment = 1 (CurveSegment, repeated)
    CurveSegment line_segment = 1 (LineSegment: point = 1, PointENU, repeated)
    PointENU     x = 1, y = 2, z = 3 (doubles, wire type 1)

Everything else (overlaps, junctions, signals, crosswalks, roads, ...) is skipped by its length without decoding.

Conventions:

* **Frame.** Apollo's coordinates are the projection of `Header.projection` (UTM metres in every map read so
  far). The local frame subtracts the mean of all lanes' central-curve points (`ApolloMap.origin`), so the
  numbers stay small and the map sits around (0, 0); nothing is re-projected.
* **Centreline.** `Lane.central_curve`, its segments' points concatenated (repeated points dropped), in the
  curve's order: Apollo's lanes run in their direction of travel. (The curve is Apollo's reference line, "not
  necessary to be the geometry central", which is what Apollo's planner follows.)
* **Direction.** A lane without `direction` is FORWARD (proto2's default, the first value). BACKWARD lanes are
  driven against the curve's order: their centreline is reversed. A BIDIRECTION lane is given both ways.
* **Drivable area.** The left boundary's curve followed by the reversed right boundary's curve (as
  `lanelet2.lanelet_ring`); a lane missing either boundary has no ring.
* **Who uses it.** Lanes whose type is in `VEHICLE_LANE_TYPES` (CITY_DRIVING, and NONE: the type of a lane that
  names none) are vehicle lanes; BIKING, SIDEWALK, PARKING and SHOULDER lanes are kept in `ApolloMap.lanes` but
  left out of `vehicle_lanes` (a hard shoulder is not a lane of travel, as in `commonroad`).

Every problem raises `gpd_jax.data.errors.DataError` naming the file and what is wrong: a truncated or corrupt
protobuf (a varint, length or fixed-size value running past its message, an unknown wire type, a field of the
wrong wire type), a lane without a central curve, a curve with fewer than two distinct points, a point without a
finite x / y, no lane at all.
"""

from __future__ import annotations

import dataclasses
import math
import os
import struct
from collections import Counter

import numpy as np

from gpd_jax.data.errors import DataError
from gpd_jax.data.sources.lanelet2 import lanelet_ring

LANE_TYPES = {1: "NONE", 2: "CITY_DRIVING", 3: "BIKING", 4: "SIDEWALK", 5: "PARKING", 6: "SHOULDER"}
DIRECTIONS = {1: "FORWARD", 2: "BACKWARD", 3: "BIDIRECTION"}
VEHICLE_LANE_TYPES = ("CITY_DRIVING", "NONE")

# field numbers (module docstring)
_MAP_HEADER, _MAP_LANE = 1, 4
_HEADER_PROJECTION, _PROJECTION_PROJ = 3, 1
_LANE_ID, _LANE_CENTRAL, _LANE_LEFT, _LANE_RIGHT = 1, 2, 3, 4
_LANE_PRED, _LANE_SUCC, _LANE_TYPE, _LANE_JUNCTION, _LANE_DIRECTION = 8, 9, 12, 16, 19
_BOUNDARY_CURVE, _CURVE_SEGMENT, _SEGMENT_LINE, _LINE_POINT, _ID_ID = 1, 1, 1, 1, 1
_POINT_X, _POINT_Y = 1, 2
_VARINT, _FIXED64, _LEN, _FIXED32 = 0, 1, 2, 5


@dataclasses.dataclass(frozen=True)
class ApolloLane:
    """One lane, in the map's local frame.

    Attributes:
      id: its `Id.id`.
      type: its LaneType name (`LANE_TYPES`; `TYPE_<n>` for a number the schema does not name).
      direction: its LaneDirection name (`DIRECTIONS`).
      junction: the id of the junction it lies in ('' when none).
      predecessors, successors: the lane ids they name.
      curve: f64[R, 2] its central curve, in the curve's order.
      left, right: f64[P, 2], f64[Q, 2] its boundaries' curves (shape (0, 2) when absent).
    """

    id: str
    type: str
    direction: str
    junction: str
    predecessors: tuple[str, ...]
    successors: tuple[str, ...]
    curve: np.ndarray
    left: np.ndarray
    right: np.ndarray

    @property
    def is_vehicle_lane(self) -> bool:
        return self.type in VEHICLE_LANE_TYPES

    def centrelines(self) -> tuple[np.ndarray, ...]:
        """Its centreline in each direction it is driven (`direction`)."""
        if self.direction == "BACKWARD":
            return (self.curve[::-1].copy(),)
        if self.direction == "BIDIRECTION":
            return self.curve, self.curve[::-1].copy()
        return (self.curve,)


@dataclasses.dataclass(frozen=True)
class ApolloMap:
    """An Apollo HD map in a local metric frame.

    Attributes:
      path: the file read.
      projection: `Header.projection.proj` ('' when absent).
      origin: (x, y) the map coordinates of the local frame's (0, 0): the mean of all central-curve points.
      lanes: every lane, in file order.
      counts: what the file holds (`lanes`, `lane_<type>`, `direction_<direction>`, `map_field_<n>` for the
        Map's other fields), for build statistics.
    """

    path: str
    projection: str
    origin: tuple[float, float]
    lanes: tuple[ApolloLane, ...]
    counts: dict

    @property
    def vehicle_lanes(self) -> tuple[ApolloLane, ...]:
        return tuple(lane for lane in self.lanes if lane.is_vehicle_lane)

    def vehicle_centrelines(self) -> tuple[np.ndarray, ...]:
        """The vehicle lanes' centrelines f64[R, 2], each in its direction of travel; a BIDIRECTION lane twice."""
        return tuple(c for lane in self.vehicle_lanes for c in lane.centrelines())

    def vehicle_rings(self) -> tuple[np.ndarray, ...]:
        """The vehicle lanes' drivable polygons f64[V, 2] (left boundary, then the right one reversed), for the
        lanes with both boundaries."""
        return tuple(lanelet_ring(lane.left, lane.right) for lane in self.vehicle_lanes
                     if len(lane.left) >= 2 and len(lane.right) >= 2)


# ------------------------------------------------------------------------------------------------ wire format
class _Reader:
    """Decodes protobuf messages of one file's bytes; every error names the file."""

    def __init__(self, path: str, buf: bytes):
        self.path, self.buf = path, buf

    def fail(self, what: str, pos: int, problem: str):
        raise DataError(self.path, f"not a valid Apollo map protobuf: {what} at byte {pos}: {problem}")

    def varint(self, pos: int, end: int, what: str) -> tuple[int, int]:
        buf, result, shift = self.buf, 0, 0
        while True:
            if pos >= end:
                self.fail(what, pos, "a varint runs past the end of its message (truncated file?)")
            b = buf[pos]
            pos += 1
            result |= (b & 0x7F) << shift
            if b < 0x80:
                return result, pos
            shift += 7
            if shift >= 70:
                self.fail(what, pos, "a varint longer than 10 bytes")

    def fields(self, start: int, end: int, what: str):
        """Yields (field number, wire type, value, position) of the message buf[start:end]: value is the integer
        of a varint, and the (start, end) byte range of the others."""
        pos = start
        while pos < end:
            at = pos
            key, pos = self.varint(pos, end, what)
            field, wire = key >> 3, key & 7
            if field == 0:
                self.fail(what, at, "field number 0")
            if wire == _VARINT:
                value, pos = self.varint(pos, end, what)
            elif wire in (_FIXED64, _FIXED32, _LEN):
                if wire == _LEN:
                    n, pos = self.varint(pos, end, what)
                else:
                    n = 8 if wire == _FIXED64 else 4
                if pos + n > end:
                    self.fail(what, at, f"field {field} needs {n} bytes, {end - pos} are left in its message "
                                        "(truncated file?)")
                value = (pos, pos + n)
                pos += n
            else:
                self.fail(what, at, f"field {field} has wire type {wire} (groups are not used by Apollo's maps)")
            yield field, wire, value, at

    def expect(self, field: int, wire: int, want: int, what: str, at: int):
        if wire != want:
            self.fail(what, at, f"field {field} has wire type {wire}, the schema's is {want}")

    def string(self, rng) -> str:
        return self.buf[rng[0]:rng[1]].decode("utf-8", "replace")

    def id(self, rng, what: str) -> str:
        out = ""
        for field, wire, value, at in self.fields(*rng, what):
            if field == _ID_ID:
                self.expect(field, wire, _LEN, what, at)
                out = self.string(value)
        return out

    def point(self, rng, what: str) -> tuple[float, float]:
        x = y = math.nan
        for field, wire, value, at in self.fields(*rng, what):
            if field in (_POINT_X, _POINT_Y):
                self.expect(field, wire, _FIXED64, what, at)
                v = struct.unpack_from("<d", self.buf, value[0])[0]
                if field == _POINT_X:
                    x = v
                else:
                    y = v
        if not (math.isfinite(x) and math.isfinite(y)):
            self.fail(what, rng[0], f"a point without a finite x and y ({x}, {y})")
        return x, y

    def curve(self, rng, what: str) -> np.ndarray:
        """A Curve's line-segment points f64[P, 2], consecutive repeats dropped."""
        pts = []
        for field, wire, value, at in self.fields(*rng, what):
            if field != _CURVE_SEGMENT:
                continue
            self.expect(field, wire, _LEN, what, at)
            for f2, w2, v2, at2 in self.fields(*value, what):
                if f2 != _SEGMENT_LINE:
                    continue
                self.expect(f2, w2, _LEN, what, at2)
                for f3, w3, v3, at3 in self.fields(*v2, what):
                    if f3 == _LINE_POINT:
                        self.expect(f3, w3, _LEN, what, at3)
                        pts.append(self.point(v3, what))
        pts = np.array(pts, np.float64).reshape(-1, 2)
        if len(pts):
            pts = pts[np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=-1) > 1e-6])]
        return pts


def _lane(r: _Reader, rng, number: int) -> ApolloLane:
    what = f"lane number {number}"
    lid, junction, type_, direction, preds, succs = "", "", 1, 1, [], []
    curve = None
    bounds = {_LANE_LEFT: np.zeros((0, 2)), _LANE_RIGHT: np.zeros((0, 2))}
    for field, wire, value, at in r.fields(*rng, what):
        if field == _LANE_ID:
            r.expect(field, wire, _LEN, what, at)
            lid = r.id(value, what)
            what = f"lane {lid}"
        elif field == _LANE_CENTRAL:
            r.expect(field, wire, _LEN, what, at)
            curve = r.curve(value, f"{what}, its central curve,")
        elif field in bounds:
            r.expect(field, wire, _LEN, what, at)
            side = "left" if field == _LANE_LEFT else "right"
            for f2, w2, v2, at2 in r.fields(*value, f"{what}, its {side} boundary,"):
                if f2 == _BOUNDARY_CURVE:
                    r.expect(f2, w2, _LEN, what, at2)
                    bounds[field] = r.curve(v2, f"{what}, its {side} boundary,")
        elif field in (_LANE_PRED, _LANE_SUCC, _LANE_JUNCTION):
            r.expect(field, wire, _LEN, what, at)
            ref = r.id(value, what)
            if field == _LANE_PRED:
                preds.append(ref)
            elif field == _LANE_SUCC:
                succs.append(ref)
            else:
                junction = ref
        elif field in (_LANE_TYPE, _LANE_DIRECTION):
            r.expect(field, wire, _VARINT, what, at)
            if field == _LANE_TYPE:
                type_ = value
            else:
                direction = value
    if curve is None:
        raise DataError(r.path, f"{what} has no central curve")
    if len(curve) < 2:
        raise DataError(r.path, f"{what}: its central curve has {len(curve)} distinct point(s); a lane needs two")
    if direction not in DIRECTIONS:
        raise DataError(r.path, f"{what}: direction {direction} is not a LaneDirection (1, 2 or 3)")
    return ApolloLane(lid, LANE_TYPES.get(type_, f"TYPE_{type_}"), DIRECTIONS[direction], junction, tuple(preds),
                      tuple(succs), curve, bounds[_LANE_LEFT], bounds[_LANE_RIGHT])


def read_apollo(path: str | os.PathLike) -> ApolloMap:
    """Reads an Apollo `base_map.bin` (conventions: module docstring).

    Raises `DataError` naming the file and the problem.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise DataError(path, "no such map file")
    with open(path, "rb") as f:
        buf = f.read()
    r = _Reader(path, buf)
    counts: Counter = Counter()
    projection, lanes = "", []
    for field, wire, value, at in r.fields(0, len(buf), "the Map"):
        if field == _MAP_LANE:
            r.expect(field, wire, _LEN, "the Map", at)
            lanes.append(_lane(r, value, len(lanes) + 1))
        elif field == _MAP_HEADER:
            r.expect(field, wire, _LEN, "the Map", at)
            for f2, w2, v2, at2 in r.fields(*value, "the Map's header"):
                if f2 == _HEADER_PROJECTION:
                    r.expect(f2, w2, _LEN, "the Map's header", at2)
                    for f3, w3, v3, at3 in r.fields(*v2, "the Map's projection"):
                        if f3 == _PROJECTION_PROJ:
                            r.expect(f3, w3, _LEN, "the Map's projection", at3)
                            projection = r.string(v3)
        else:
            counts[f"map_field_{field}"] += 1
    counts["lanes"] = len(lanes)
    if not lanes:
        raise DataError(path, "holds no lane (no field 4 of apollo.hdmap.Map): not an Apollo HD map")
    origin = np.concatenate([lane.curve for lane in lanes]).mean(0)
    local = []
    for lane in lanes:
        counts[f"lane_{lane.type}"] += 1
        counts[f"direction_{lane.direction}"] += 1
        local.append(dataclasses.replace(lane, curve=lane.curve - origin, left=lane.left - origin,
                                         right=lane.right - origin))
    return ApolloMap(path, projection, (float(origin[0]), float(origin[1])), tuple(local), dict(counts))


def read_apollo_lanes(path: str | os.PathLike) -> tuple[np.ndarray, ...]:
    """The map-only view of an Apollo HD map: its vehicle lanes' directed centrelines f64[R, 2] in the local
    frame, what `gpd_jax.data.preprocess.lane_points` takes (as `lanelet2.read_lanelet2_lanes`)."""
    return read_apollo(path).vehicle_centrelines()
