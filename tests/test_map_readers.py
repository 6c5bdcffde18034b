"""Map-only readers of CommonRoad (`.xml`) and Apollo (`base_map.bin`) maps, on tiny maps the tests write
themselves: an XML file of a few lanelets, and an `apollo.hdmap.Map` protobuf built by the small wire-format
encoder below (independent of the reader's decoder).

Covers which lanes are kept (types and road users dropped, two-way lanes given both ways), centrelines and
directions against hand-computed values, drivable rings, the local frame of the Apollo map, the fields a reader
must skip, and bad files (not XML / not a protobuf, truncated, a lane without a bound or central curve, a bound
of fewer than two points, no lane at all), which raise `DataError` naming the file.
"""

import struct

import numpy as np
import pytest

from gpd_jax.data.errors import DataError
from gpd_jax.data.sources import apollo, commonroad

EPS = np.finfo(np.float64).eps


def _close(a, b, scale=1.0):
    """Equal to within a few ulps of the coordinates' magnitude."""
    np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), rtol=0,
                               atol=64 * EPS * max(scale, 1.0))


# ------------------------------------------------------------------------------------------------ CommonRoad
def _bound(tag, pts, marking=True):
    body = "".join(f"<point><x>{x}</x><y>{y}</y></point>" for x, y in pts)
    return f"<{tag}>{body}{'<lineMarking>dashed</lineMarking>' if marking else ''}</{tag}>"


def _lanelet(lid, left, right, types=("urban",), one_way=("vehicle",), bidirectional=(), extra=""):
    return (f'<lanelet id="{lid}">' + (_bound("leftBound", left) if left is not None else "")
            + (_bound("rightBound", right) if right is not None else "") + extra
            + "".join(f"<laneletType>{t}</laneletType>" for t in types)
            + "".join(f"<userOneWay>{u}</userOneWay>" for u in one_way)
            + "".join(f"<userBidirectional>{u}</userBidirectional>" for u in bidirectional) + "</lanelet>")


LANELETS = [
    # 1: eastbound, bounds of 3 and 2 points
    _lanelet(1, [(0, 3.5), (50, 3.5), (100, 3.5)], [(0, 0), (100, 0)],
             extra='<successor ref="4"/><adjacentLeft ref="2" drivingDir="opposite"/>'),
    # 2: westbound (stored west-going: the left bound is the south one)
    _lanelet(2, [(100, -3.5), (0, -3.5)], [(100, 0), (0, 0)], extra='<adjacentLeft ref="1" drivingDir="opposite"/>'),
    # 3: a sidewalk (dropped)
    _lanelet(3, [(0, 6), (100, 6)], [(0, 3.5), (100, 3.5)], types=("sidewalk",), one_way=("pedestrian",)),
    # 4: northbound, two-way for cars; its bounds' vertices sit at different arc-length fractions
    _lanelet(4, [(110, 0), (110, 10), (110, 100)], [(113.5, 0), (113.5, 90), (113.5, 100)],
             types=("urban", "intersection"), one_way=(), bidirectional=("car", "priorityVehicle"),
             extra='<predecessor ref="1"/>'),
    # 5: a hard shoulder (dropped)
    _lanelet(5, [(0, -3.5), (100, -3.5)], [(0, -6), (100, -6)], types=("highway", "shoulder"), one_way=()),
    # 6: both ways only for priority vehicles: one-way for the map
    _lanelet(6, [(200, 3.5), (300, 3.5)], [(200, 0), (300, 0)], types=("unknown",), one_way=(),
             bidirectional=("priorityVehicle",)),
    # 7: only for bicycles (dropped), 8: restricted (dropped), 9: a bus lane (kept)
    _lanelet(7, [(0, 9), (100, 9)], [(0, 6), (100, 6)], one_way=("bicycle",)),
    _lanelet(8, [(0, 12), (100, 12)], [(0, 9), (100, 9)], types=("urban", "restricted")),
    _lanelet(9, [(300, 3.5), (400, 3.5)], [(300, 0), (400, 0)], types=("busLane",), one_way=("bus",)),
]

EXTRAS = ("<location><geoNameId>-999</geoNameId><gpsLatitude>48.1</gpsLatitude><gpsLongitude>11.6</gpsLongitude>"
          "<geoTransformation><geoReference>+proj=utm +zone=32 +ellps=WGS84</geoReference>"
          "</geoTransformation></location>")
PROBLEM = ('<planningProblem id="100"><goalState><position><lanelet ref="4"/></position></goalState>'
           '</planningProblem>')


def write_commonroad(path, lanelets=None, root="commonRoad"):
    body = "\n".join(LANELETS if lanelets is None else lanelets)
    with open(path, "w") as f:
        f.write(f'<?xml version="1.0" encoding="UTF-8"?>\n<{root} commonRoadVersion="2020a" benchmarkID="TST-1">'
                f"{EXTRAS}\n{body}\n{PROBLEM}\n</{root}>\n")
    return path


def test_commonroad_lanes_kept_directed_and_averaged(tmp_path):
    p = write_commonroad(tmp_path / "map.xml")
    m = commonroad.read_commonroad(p)
    assert m.version == "2020a" and m.counts["lanelets"] == 9 and m.counts["planningProblem"] == 1
    assert [ll.id for ll in m.vehicle_lanelets] == ["1", "2", "4", "6", "9"]
    by = {ll.id: ll for ll in m.lanelets}
    assert by["1"].successors == ("4",) and by["4"].predecessors == ("1",) and by["1"].adjacent_left == ("2", False)
    assert by["4"].two_way and not by["6"].two_way and not by["1"].two_way

    lanes = commonroad.read_commonroad_lanes(p)
    assert len(lanes) == 6
    east, west, north, south, six, bus = lanes
    _close(east, [(0, 1.75), (50, 1.75), (100, 1.75)], 100)          # union of the fractions {0, .5, 1}
    _close(west, [(100, -1.75), (0, -1.75)], 100)                    # stored direction kept (west)
    _close(north, [(111.75, 0), (111.75, 10), (111.75, 90), (111.75, 100)], 100)  # not the pairwise average
    _close(south, north[::-1], 100)
    _close(six, [(200, 1.75), (300, 1.75)], 300)
    _close(bus, [(300, 1.75), (400, 1.75)], 400)
    assert all(c.dtype == np.float64 and c.shape[1] == 2 for c in lanes)

    rings = commonroad.read_commonroad_areas(p)
    assert len(rings) == 5
    _close(rings[0], [(0, 3.5), (50, 3.5), (100, 3.5), (100, 0), (0, 0)], 100)


def test_commonroad_2018b_lanelets_without_type(tmp_path):
    ll = _lanelet(1, [(0, 3), (10, 3)], [(0, 0), (10, 0)], types=(), one_way=())
    m = commonroad.read_commonroad(write_commonroad(tmp_path / "old.xml", [ll]))
    assert m.lanelets[0].types == () and m.counts["lanelet_(none)"] == 1
    _close(commonroad.read_commonroad_lanes(m.path)[0], [(0, 1.5), (10, 1.5)], 10)


@pytest.mark.parametrize("content, reason", [
    ("this is not xml <", r"not a CommonRoad \(XML\) file"),
    (None, "root element is <osm>"),
    ([_lanelet(1, [(0, 3), (10, 3)], None)], "lanelet 1 has no rightBound"),
    ([_lanelet(2, [(0, 3)], [(0, 0), (10, 0)])], "lanelet 2: its leftBound has 1 distinct point"),
    ([_lanelet(3, [(0, 3), (0, 3)], [(0, 0), (10, 0)])], "lanelet 3: its leftBound has 1 distinct point"),
    ([_lanelet(4, [(0, 3), ("x", 3)], [(0, 0), (10, 0)])], "point 1 of its leftBound has no numeric"),
    ([_lanelet(5, [(0, 3), ("nan", 3)], [(0, 0), (10, 0)])], "is not finite"),
    ([], "holds no lanelet"),
])
def test_commonroad_bad_files(tmp_path, content, reason):
    p = tmp_path / "bad.xml"
    if isinstance(content, str):
        p.write_text(content)
    elif content is None:
        write_commonroad(p, root="osm")
    else:
        write_commonroad(p, content)
    with pytest.raises(DataError, match=reason) as e:
        commonroad.read_commonroad_lanes(p)
    assert e.value.path == str(p)
    with pytest.raises(DataError, match="no such map file"):
        commonroad.read_commonroad_lanes(tmp_path / "none.xml")


# ------------------------------------------------------------------------------------------------ Apollo
# A tiny protobuf encoder (wire types 0, 1, 2, 5), written from the wire-format specification.
def _varint(n):
    out = bytearray()
    while True:
        out.append((n & 0x7F) | (0x80 if n > 0x7F else 0))
        n >>= 7
        if not n:
            return bytes(out)


def _key(field, wire):
    return _varint(field << 3 | wire)


def _msg(field, payload):
    return _key(field, 2) + _varint(len(payload)) + payload


def _double(field, v):
    return _key(field, 1) + struct.pack("<d", v)


def _enum(field, v):
    return _key(field, 0) + _varint(v)


def _point(x, y, z=0.0):
    return _double(1, x) + _double(2, y) + _double(3, z)


def _curve(*segments):
    """Curve (segment = 1) of CurveSegments (line_segment = 1 of LineSegment (point = 1), s = 6, heading = 8)."""
    out = b""
    for pts in segments:
        line = b"".join(_msg(1, _point(x, y)) for x, y in pts)
        out += _msg(1, _msg(1, line) + _double(6, 0.0) + _msg(7, _point(*pts[0])) + _double(8, 0.5))
    return out


def _id(s):
    return _msg(1, s.encode())


E0, N0 = 587000.0, 4141000.0  # a UTM-sized offset (zone 10, Sunnyvale)


def _lane(lid, centre, type_=2, direction=None, left=None, right=None, curve=True):
    out = _msg(1, _id(lid))
    if curve:
        out += _msg(2, _curve(*[[(E0 + x, N0 + y) for x, y in seg] for seg in centre]))
    if left is not None:
        out += _msg(3, _msg(1, _curve([(E0 + x, N0 + y) for x, y in left])) + _double(2, 1.0))
    if right is not None:
        out += _msg(4, _msg(1, _curve([(E0 + x, N0 + y) for x, y in right])) + _double(2, 1.0))
    out += _double(5, 100.0) + _double(6, 13.4) + _msg(7, _id("overlap_1")) + _msg(9, _id("next"))
    if type_ is not None:
        out += _enum(12, type_)
    out += _enum(13, 1) + _msg(16, _id("junction_1"))
    out += _msg(17, _double(1, 0.0) + _double(2, 1.75)) + _key(30, 5) + struct.pack("<f", 1.0)  # unknown fixed32
    if direction is not None:
        out += _enum(19, direction)
    return out


APOLLO_LANES = [
    _lane("a", [[(0, 0), (50, 0)], [(50, 0), (100, 0)]], left=[(0, 1.75), (100, 1.75)],
          right=[(0, -1.75), (100, -1.75)]),                                  # 2 segments; FORWARD by default
    _lane("b", [[(0, 10), (100, 10)]], type_=None, direction=2),               # NONE type; BACKWARD
    _lane("c", [[(0, 20), (0, 120)]], direction=3),                           # BIDIRECTION
    _lane("d", [[(10, 30), (20, 30)]], type_=3),                              # BIKING: dropped
    _lane("e", [[(30, 30), (40, 30)]], type_=6),                              # SHOULDER: dropped
]


def write_apollo(path, lanes=None):
    header = _msg(1, b"1.500000") + _msg(2, b"2018-03-23") + _msg(3, _msg(1, b"+proj=utm +zone=10 +ellps=WGS84"))
    body = _msg(1, header) + _msg(2, _msg(1, _id("crosswalk_1")))
    for lane in APOLLO_LANES if lanes is None else lanes:
        body += _msg(4, lane)
    body += _msg(8, _msg(1, _id("overlap_1")))
    with open(path, "wb") as f:
        f.write(body)
    return path


def test_apollo_lanes_kept_directed_in_local_frame(tmp_path):
    p = write_apollo(tmp_path / "base_map.bin")
    m = apollo.read_apollo(p)
    assert m.projection == "+proj=utm +zone=10 +ellps=WGS84"
    assert [(lane.id, lane.type, lane.direction) for lane in m.lanes] == [
        ("a", "CITY_DRIVING", "FORWARD"), ("b", "NONE", "BACKWARD"), ("c", "CITY_DRIVING", "BIDIRECTION"),
        ("d", "BIKING", "FORWARD"), ("e", "SHOULDER", "FORWARD")]
    assert m.lanes[0].successors == ("next",) and m.lanes[0].junction == "junction_1"
    assert m.counts["lanes"] == 5 and m.counts["map_field_2"] == 1 and m.counts["map_field_8"] == 1
    # the origin: the mean of every central-curve point (a's repeated (50, 0) counted once)
    pts = np.array([(0, 0), (50, 0), (100, 0), (0, 10), (100, 10), (0, 20), (0, 120), (10, 30), (20, 30),
                    (30, 30), (40, 30)], np.float64)
    ox, oy = pts.mean(0)
    _close(m.origin, (E0 + ox, N0 + oy), N0)

    lanes = apollo.read_apollo_lanes(p)
    assert len(lanes) == 4
    a, b, c_fwd, c_back = lanes
    _close(a, [(0 - ox, 0 - oy), (50 - ox, 0 - oy), (100 - ox, 0 - oy)], N0)
    _close(b, [(100 - ox, 10 - oy), (0 - ox, 10 - oy)], N0)
    _close(c_fwd, [(0 - ox, 20 - oy), (0 - ox, 120 - oy)], N0)
    _close(c_back, c_fwd[::-1], N0)
    assert all(lane.dtype == np.float64 and lane.shape[1] == 2 for lane in lanes)

    rings = m.vehicle_rings()  # only lane a has both boundaries
    assert len(rings) == 1
    _close(rings[0], [(0 - ox, 1.75 - oy), (100 - ox, 1.75 - oy), (100 - ox, -1.75 - oy), (0 - ox, -1.75 - oy)], N0)


def _truncated(path):
    data = write_apollo(path).read_bytes()
    path.write_bytes(data[: len(data) - 40])


@pytest.mark.parametrize("make, reason", [
    (_truncated, "truncated file"),
    (lambda p: p.write_text('lane {\n  id {\n    id: "a"\n  }\n}\n'), "wire type"),
    (lambda p: p.write_bytes(b""), "holds no lane"),
    (lambda p: p.write_bytes(_msg(1, _msg(1, b"1.0"))), "holds no lane"),
    (lambda p: write_apollo(p, [_lane("x", [], curve=False)]), "lane x has no central curve"),
    (lambda p: write_apollo(p, [_lane("y", [[(0, 0)]])]), "lane y: its central curve has 1 distinct point"),
    (lambda p: write_apollo(p, [_lane("z", [[(0, 0), (0, 0)]])]), "lane z: its central curve has 1 distinct"),
    (lambda p: p.write_bytes(_enum(4, 7)), "field 4 has wire type 0, the schema's is 2"),
    (lambda p: write_apollo(p, [_msg(1, _id("w")) + _msg(2, _msg(1, _msg(1, _msg(1, _double(1, 5.0)))))]),
     "a point without a finite x and y"),
    (lambda p: write_apollo(p, [_lane("v", [[(0, 0), (1, 0)]], direction=9)]), "direction 9 is not"),
])
def test_apollo_bad_files(tmp_path, make, reason):
    p = tmp_path / "bad.bin"
    make(p)
    with pytest.raises(DataError, match=reason) as e:
        apollo.read_apollo_lanes(p)
    assert e.value.path == str(p)
    with pytest.raises(DataError, match="no such map file"):
        apollo.read_apollo_lanes(tmp_path / "none.bin")


def test_map_files_read_by_their_names(tmp_path):
    """`maps.read_map_lanes` hands each format to its reader by the file's name (SUMO's `.net.xml` before
    CommonRoad's `.xml`), as the map tokenizer's netframes read them."""
    from gpd_jax.data.sources import maps

    cr = write_commonroad(tmp_path / "town.xml")
    ap = write_apollo(tmp_path / "apollo_town.bin")
    assert [maps.map_format(p) for p in (cr, ap, "x.net.xml.gz", "x.NET.XML", "m.osm")] == [
        "commonroad", "apollo", "sumo", "sumo", "lanelet2"]
    for got, want in ((maps.read_map_lanes(cr), commonroad.read_commonroad_lanes(cr)),
                      (maps.read_map_lanes(ap), apollo.read_apollo_lanes(ap))):
        assert len(got) == len(want) and all(np.array_equal(g, w) for g, w in zip(got, want))
    with pytest.raises(DataError, match="unknown map format"):
        maps.map_format(tmp_path / "town.geojson")
