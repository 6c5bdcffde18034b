"""Drivable-area geometry of a sample, built from a log's world-frame areas (numpy + shapely, build time only).

Every source turns its map into `Area`s in the world frame (`RawLog.areas`): SUMO lanes buffered by their
width and junction shapes, nuPlan's lane / lane-group / intersection / generic-drivable / car-park polygons,
ScenarioNet lane polygons (or centrelines buffered by their width). `RoadIndex` merges them once per log;
`clip_road` cuts one sample's geometry out of it, in the sample's scene frame, as the fixed-shape arrays of
`gpd_jax.geometry.RoadGeometry` (stored under the `ROAD_KEYS`):

* the union of each kind's areas (`gpd_jax.geometry.AREA_KINDS`), simplified once per log (`tolerance`
  metres), clipped to the sample's region (the box around the ego's path that the lane clip uses: ego
  positions +- the window's half diagonal, grown to hold every valid agent position +- 10 m), and written as
  rings: each polygon's exterior and holes; a polygon with more than V vertices in a ring is split into
  quarters of its bounding box until every piece fits. If more than G rings remain, whole polygons farthest
  from the ego's path are dropped (counted: `road_rings_dropped`);
* road edges: the boundary of the union of every area (unclipped, so the region's box is never an edge),
  simplified once per log, cut to the region, split into runs of at most P points sharing end points, the E
  nearest to the ego's path kept (`road_edges_dropped` counts the rest);
* map road edges (`MAP_EDGE_KEYS`, what the realism metric reads): the source map's own road-edge lines where
  it has them (`RawLog.road_edges`: ScenarioNet `ROAD_EDGE_*`, Lanelet2 curbs / road borders), each oriented with
  the drivable side on its left by a vote against the areas' union (probes `ORIENT_PROBES_M` either side of
  every segment, the side nearer the union wins, weighted by segment length); otherwise the outline of the
  areas' union, oriented by construction (exteriors counter-clockwise, holes clockwise). Cut, split and kept
  like the road edges (`map_edges_dropped`); `road_edge_source` names which (`gpd_jax.geometry.EDGE_SOURCES`).
"""

from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np
import shapely
from shapely.geometry import LineString, MultiPolygon, Point, Polygon

from gpd_jax.geometry import AREA_KIND_ID, AREA_KINDS, EDGE_SOURCE_ID

ROAD_KEYS = ("road_polygons", "road_polygon_valid", "road_polygon_kind", "road_edges", "road_edge_valid")
# Optional since store format 2 (older stores lack them and read as before).
MAP_EDGE_KEYS = ("road_map_edges", "road_map_edge_valid", "road_edge_source")
ORIENT_PROBES_M = (0.5, 2.0)  # metres either side of a map road-edge segment where its drivable side is probed


@dataclasses.dataclass(frozen=True)
class Area:
    """One drivable area in the world frame: `kind` (index into `AREA_KINDS`), exterior f64[V, 2], holes."""

    kind: int
    exterior: np.ndarray
    holes: tuple[np.ndarray, ...] = ()


def lane_area(centreline: np.ndarray, width: float | np.ndarray, kind: int = AREA_KIND_ID["lane"],
              offset: float | np.ndarray = 0.0) -> Area | None:
    """The polygon a lane of `width` metres (scalar or per point) covers around its centreline f[P, 2], shifted
    `offset` metres to the left (scalar or per point; for lanes whose centreline is off their middle)."""
    pts = np.asarray(centreline, np.float64)
    if len(pts) < 2:
        return None
    w = np.broadcast_to(np.asarray(width, np.float64), (len(pts),))
    off = np.broadcast_to(np.asarray(offset, np.float64), (len(pts),))
    d = np.gradient(pts, axis=0) if len(pts) > 2 else np.repeat(pts[1:] - pts[:1], 2, axis=0)
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    keep = n[:, 0] > 1e-9
    if keep.sum() < 2:
        return None
    pts, d, n, w, off = pts[keep], d[keep], n[keep], w[keep], off[keep]
    left = np.stack([-d[:, 1], d[:, 0]], -1) / n
    ring = np.concatenate([pts + left * (off + w / 2)[:, None], (pts + left * (off - w / 2)[:, None])[::-1]])
    return Area(kind, ring)


def _polygon(a: Area):
    try:
        p = Polygon(a.exterior, [h for h in a.holes if len(h) >= 3])
    except (ValueError, TypeError):
        return None
    if not p.is_valid:
        p = shapely.make_valid(p)
        p = shapely.union_all([g for g in getattr(p, "geoms", [p]) if isinstance(g, (Polygon, MultiPolygon))]) \
            if not isinstance(p, (Polygon, MultiPolygon)) else p
    return None if p.is_empty or p.area <= 1e-6 else p


# Every area is grown by this much (metres) before the union, so that neighbouring lanes whose shared side
# differs by float rounding (float32 maps, polygons next to buffered centrelines) merge without slivers.
SEAM = 0.01


class RoadIndex:
    """A log's drivable areas, merged once per log: the union of each kind's areas and the boundary of the union
    of all (the road edges), in the world frame. Samples then only cut their region out of them."""

    def __init__(self, areas, tolerance: float = 0.1, edge_lines=(), edge_source: str = "lane_union"):
        geoms: list[list] = [[] for _ in AREA_KINDS]
        for a in areas:
            p = _polygon(a)
            if p is not None:
                geoms[int(a.kind)].append(p)
        # simplified here, once per log and not per sample: each area and the unions by half of `tolerance` each
        half = tolerance / 2
        grown = [shapely.buffer(shapely.simplify(np.asarray(g, dtype=object), half, preserve_topology=True), SEAM,
                                join_style="mitre") if g else None for g in geoms]
        unions = [None if g is None else shapely.union_all(g) for g in grown]
        present = [u for u in unions if u is not None]
        self.unions = [None if u is None else u.simplify(half, preserve_topology=True) for u in unions]
        whole = shapely.union_all(present) if present else None
        self.boundary = whole.boundary.simplify(half) if present else None
        for g in [*self.unions, self.boundary]:
            if g is not None:
                shapely.prepare(g)
        lines = [np.asarray(ln, np.float64) for ln in edge_lines if len(ln) >= 2]
        if lines:
            self.map_edges = shapely.MultiLineString(orient_lines(lines, whole)).simplify(half)
            self.edge_source = EDGE_SOURCE_ID["map_lines"]
        elif whole is not None:
            self.map_edges = shapely.orient_polygons(whole).boundary.simplify(half)
            self.edge_source = EDGE_SOURCE_ID[edge_source]
        else:
            self.map_edges, self.edge_source = None, EDGE_SOURCE_ID["none"]

    @property
    def empty(self) -> bool:
        return self.boundary is None and self.map_edges is None


def orient_lines(lines: list[np.ndarray], area) -> list[np.ndarray]:
    """Each polyline f64[P, 2] turned so that `area` (a shapely geometry, or None: lines kept as they are) lies on
    its left: per segment, the probe points `ORIENT_PROBES_M` to its left and right are compared by their distance
    to `area` (0 inside); the length-weighted vote decides (a tie keeps the line)."""
    if area is None:
        return list(lines)
    out = []
    for ln in lines:
        d = np.diff(ln, axis=0)
        length = np.linalg.norm(d, axis=-1)
        keep = length > 1e-9
        if not keep.any():
            continue
        n = np.stack([-d[keep, 1], d[keep, 0]], -1) / length[keep, None]
        mid = (ln[:-1][keep] + ln[1:][keep]) / 2
        vote = 0.0
        for r in ORIENT_PROBES_M:
            left = shapely.distance(area, shapely.points(mid + r * n))
            right = shapely.distance(area, shapely.points(mid - r * n))
            vote += float(np.sum(length[keep] * np.sign(right - left)))
        out.append(ln[::-1].copy() if vote < 0 else ln)
    return out


def _to_frame_fn(pose):
    c, s = np.cos(pose[2]), np.sin(pose[2])

    def fn(xy):
        dx, dy = xy[:, 0] - pose[0], xy[:, 1] - pose[1]
        return np.stack([c * dx + s * dy, -s * dx + c * dy], -1)

    return fn


def _from_frame(xy, pose):
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.stack([pose[0] + c * xy[:, 0] - s * xy[:, 1], pose[1] + s * xy[:, 0] + c * xy[:, 1]], -1)


def _polys(g) -> list:
    if g.is_empty:
        return []
    if isinstance(g, Polygon):
        return [g]
    return [p for q in getattr(g, "geoms", []) for p in _polys(q)]


def _lines(g) -> list[np.ndarray]:
    if g.is_empty:
        return []
    if g.geom_type in ("LineString", "LinearRing"):
        return [np.asarray(g.coords)]
    return [c for q in getattr(g, "geoms", []) for c in _lines(q)]


def _fit(poly: Polygon, V: int, depth: int = 0) -> list[Polygon]:
    """Pieces of `poly` whose rings each have at most V vertices (quartering its bounding box)."""
    n = max([len(poly.exterior.coords) - 1] + [len(r.coords) - 1 for r in poly.interiors])
    if n <= V or depth >= 8:
        return [poly]
    x0, y0, x1, y1 = poly.bounds
    xm, ym = (x0 + x1) / 2, (y0 + y1) / 2
    out = []
    for q in ((x0, y0, xm, ym), (xm, y0, x1, ym), (x0, ym, xm, y1), (xm, ym, x1, y1)):
        for p in _polys(shapely.clip_by_rect(poly, *q)):
            if p.area > 1e-6:
                out.extend(_fit(p, V, depth + 1))
    return out


def _ring(coords, V: int) -> np.ndarray:
    c = np.asarray(coords)[:-1]  # shapely rings repeat the first point
    if len(c) > V:  # only after depth-limited splitting; keep an even subsample
        c = c[np.linspace(0, len(c) - 1, V).round().astype(int)]
    return c


def _path_distance(xy: np.ndarray, path: np.ndarray) -> float:
    return float(np.min(np.linalg.norm(xy[:, None, :] - path[None], axis=-1)))


def empty_road_arrays(G: int, V: int, E: int, P: int) -> dict[str, np.ndarray]:
    return {"road_polygons": np.zeros((G, V, 2), np.float32), "road_polygon_valid": np.zeros((G, V), bool),
            "road_polygon_kind": np.zeros((G,), np.int8), "road_edges": np.zeros((E, P, 2), np.float32),
            "road_edge_valid": np.zeros((E, P), bool), "road_map_edges": np.zeros((E, P, 2), np.float32),
            "road_map_edge_valid": np.zeros((E, P), bool),
            "road_edge_source": np.array(EDGE_SOURCE_ID["none"], np.int8)}


def _clip_runs(lines_world, world_box, to_scene, region_box, path, E: int, P: int, stats: Counter, what: str):
    """Polylines (a shapely geometry in the world) cut to the region in the scene frame, split into runs of at most
    P points sharing end points (direction kept), the E nearest to the ego's `path`; f32[E, P, 2], bool[E, P]."""
    pts, valid = np.zeros((E, P, 2), np.float32), np.zeros((E, P), bool)
    if lines_world is None:
        return pts, valid
    lines = _lines(shapely.clip_by_rect(shapely.transform(shapely.clip_by_rect(lines_world, *world_box), to_scene),
                                        *region_box))
    runs = []
    for ln in lines:
        if len(ln) < 2:
            continue
        for a in range(0, len(ln) - 1, P - 1):
            c = ln[a:a + P]
            if len(c) >= 2:
                runs.append(c)
    if len(runs) > E:
        stats[f"{what}_dropped"] += len(runs) - E
        runs = [runs[i] for i in np.argsort([_path_distance(r, path) for r in runs], kind="stable")[:E]]
    for i, r in enumerate(runs):
        pts[i, :len(r)] = r
        valid[i, :len(r)] = True
    return pts, valid


def clip_road(index: RoadIndex | None, scene_pose_world: np.ndarray, ego_pose: np.ndarray, *, reach: float,
              G: int, V: int, E: int, P: int, tolerance: float = 0.1, stats: Counter | None = None,
              agents_xy: np.ndarray | None = None, agent_margin: float = 10.0) -> dict[str, np.ndarray]:
    """One sample's geometry arrays (`ROAD_KEYS` and `MAP_EDGE_KEYS`) in the scene frame.

    Args:
      index: the log's areas (None or empty: an all-invalid geometry).
      scene_pose_world: f[3] the scene frame's pose in the world.
      ego_pose: f[T, 3] the ego's pose per frame in the scene frame.
      reach: metres around the ego's positions that the region covers.
      G, V, E, P: ring count, vertices per ring, edge count, points per edge.
      tolerance: unused (the index simplifies once per log: `RoadIndex(areas, tolerance)`); kept for callers.
      agents_xy: optional f[K, 2] valid agent positions in the scene frame; the region grows to hold them
        with `agent_margin` metres around (so that every recorded agent can be asked whether it is on the road).
    """
    out = empty_road_arrays(G, V, E, P)
    if index is None or index.empty:
        return out
    stats = Counter() if stats is None else stats
    lo, hi = ego_pose[:, :2].min(0) - reach, ego_pose[:, :2].max(0) + reach
    if agents_xy is not None and len(agents_xy):
        lo = np.minimum(lo, agents_xy.min(0) - agent_margin)
        hi = np.maximum(hi, agents_xy.max(0) + agent_margin)
    corners = _from_frame(np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]]),
                          scene_pose_world)
    region_world = Polygon(corners)
    world_box = (*corners.min(0), *corners.max(0))
    region_box = (lo[0], lo[1], hi[0], hi[1])
    to_scene = _to_frame_fn(scene_pose_world)
    path = ego_pose[::5, :2]
    path_line = LineString(path) if len(path) >= 2 else Point(path[0])
    # rings of each kind's union, clipped and simplified, in the scene frame
    pieces: list[tuple[float, int, list[np.ndarray]]] = []
    for kind, union in enumerate(index.unions):
        if union is None or not union.intersects(region_world):
            continue
        # cut the world-axis box around the region, turn it into the scene frame, cut the region's box there
        # (clip_by_rect is several times faster than a general intersection)
        u = shapely.transform(shapely.clip_by_rect(union, *world_box), to_scene)
        u = shapely.clip_by_rect(u, *region_box)
        for p in _polys(u):
            for q in _fit(p, V):
                rings = [_ring(q.exterior.coords, V)] + [_ring(r.coords, V) for r in q.interiors]
                rings = [r for r in rings if len(r) >= 3]
                if rings:
                    pieces.append((q.distance(path_line), kind, rings))
    pieces.sort(key=lambda x: x[0])
    g = 0
    for _, kind, rings in pieces:
        if g + len(rings) > G:
            stats["road_rings_dropped"] += len(rings)
            continue
        for r in rings:
            out["road_polygons"][g, :len(r)] = r
            out["road_polygon_valid"][g, :len(r)] = True
            out["road_polygon_kind"][g] = kind
            g += 1
    # road edges: boundary of the union of everything (unclipped), cut to the region; the map's edges alike
    out["road_edges"], out["road_edge_valid"] = _clip_runs(index.boundary, world_box, to_scene, region_box, path,
                                                           E, P, stats, "road_edges")
    out["road_map_edges"], out["road_map_edge_valid"] = _clip_runs(index.map_edges, world_box, to_scene, region_box,
                                                                   path, E, P, stats, "map_edges")
    out["road_edge_source"] = np.array(index.edge_source, np.int8)
    return out
