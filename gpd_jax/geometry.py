"""Drivable-area geometry of a scene and the jit-able queries that planning and realism metrics share.

A `RoadGeometry` lives in the *scene frame* (the ego frame of the current frame, like `Scene.polylines`) and
holds three things, all fixed-shape with validity masks (never ragged):

* **drivable areas** as polygon rings, each tagged with a kind (`AREA_KINDS`: lanes and roads, junctions /
  intersections, other drivable surfaces such as car parks). Within one kind the rings are the boundary rings
  of that kind's union, so they never cross: a ring may be a hole, and a point is inside kind k's area when it
  lies inside an odd number of kind k's rings (even-odd rule). A polygon's valid vertices are a prefix of its
  row; the ring closes implicitly from its last valid vertex back to the first.
* **road edges**: open polylines along the boundary of the union of every drivable area (computed when the
  sample is built). Where the geometry was clipped to the sample's region, the clip box's sides are *not*
  edges. A closed edge repeats its first point at the end. Segments join consecutive valid points.
* **map road edges** (optional, stores of format 2 on): the road edges the official realism metric reads,
  *oriented with the drivable side on their left*, from the source map where it draws them (curbs, road
  borders, the drivable area's outline) or the lane union's outline where it has none; `edge_source` says
  which (`EDGE_SOURCES`). None for older stores (consumers then orient `edges` themselves).
* **lane centrelines**, directed (points in driving order), the same arrays as `Scene.polylines` /
  `Scene.polyline_valid`; stores keep them only once (the loader fills them in from the polylines).

Queries take one unbatched road and points `xy f32[..., 2]` with any leading dims (vmap over scenes):
`on_road`, `area_kinds`, `signed_distance_to_edge`, `lane_direction`, `lane_trace`. They are pure, jit- and
vmap-able and loop over nothing in Python; segment scans run in fixed-size blocks of points (`lax.map`) so
memory stays bounded whatever the number of points.

This module is at the bottom of the package's layers: it imports only jax, numpy and flax.
"""

from __future__ import annotations

from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

# Kinds of drivable area (index = `RoadGeometry.polygon_kind`).
AREA_KINDS = ("lane", "junction", "other")
AREA_KIND_ID = {name: i for i, name in enumerate(AREA_KINDS)}
# Where a scene's map road edges come from (index = `RoadGeometry.edge_source`): "none" (no map geometry),
# "lane_union" (the outline of the union of the lanes' areas: the source draws no road edge, e.g. ScenarioNet's
# nuScenes conversions), "drivable_area" (the outline of the source's drivable area, which is the whole road:
# nuPlan's drivable layers, SUMO's lanes and junctions), "map_lines" (the map's own road-edge lines: ScenarioNet
# `ROAD_EDGE_*`, Lanelet2 bounds of type curbstone / road_border / guard_rail / wall / fence).
EDGE_SOURCES = ("none", "lane_union", "drivable_area", "map_lines")
EDGE_SOURCE_ID = {name: i for i, name in enumerate(EDGE_SOURCES)}
# Traffic-signal lane states, WOSAC's enum in its order (index = `TrafficSignals.state`); 0 is also "no signal".
SIGNAL_STATES = ("unknown", "arrow_stop", "arrow_caution", "arrow_go", "stop", "caution", "go", "flashing_stop",
                 "flashing_caution")
SIGNAL_STATE_ID = {name: i for i, name in enumerate(SIGNAL_STATES)}
STOP_STATES = (SIGNAL_STATE_ID["arrow_stop"], SIGNAL_STATE_ID["stop"])  # what the violation feature calls stop

# What a consumer that needs the geometry says when a scene has none (a store built before it existed).
ROAD_MISSING = ("these scenes carry no road geometry (Scene.road is None): the data store was built before "
                "drivable-area geometry was stored; rebuild it with `python -m gpd_jax.data build ...`")

# Points handled per block in the segment scans (bounded memory: block x segments floats).
_BLOCK = 256


@flax.struct.dataclass(frozen=True)
class RoadGeometry:
    """Drivable area, road edges and directed lane centrelines of one scene (or a batch: leading dims `...`).

    Attributes:
      polygons: f32[..., G, V, 2] drivable-area rings in the scene frame (metres); valid vertices are a prefix
        of each row, the ring closes from the last valid vertex to the first.
      polygon_valid: bool[..., G, V] which vertices exist (a ring needs >= 3 to enclose anything).
      polygon_kind: i32[..., G] index into `AREA_KINDS` (any integer dtype is accepted).
      edges: f32[..., E, P, 2] road-edge polylines in the scene frame (boundary of the union of all areas).
      edge_valid: bool[..., E, P] which edge points exist; a segment joins two consecutive valid points.
      lanes: f32[..., L, Q, 2] directed lane centrelines in the scene frame (= `Scene.polylines`).
      lane_valid: bool[..., L, Q] which centreline points exist (= `Scene.polyline_valid`).
      map_edges: optional f32[..., Em, Pm, 2] the map's road edges, each with the drivable side on its left
        (module docstring); None for stores built before them.
      map_edge_valid: optional bool[..., Em, Pm] which map-edge points exist (a prefix of each row).
      edge_source: optional i32[...] index into `EDGE_SOURCES` of the map edges (given with `map_edges`).
    """

    polygons: jax.Array
    polygon_valid: jax.Array
    polygon_kind: jax.Array
    edges: jax.Array
    edge_valid: jax.Array
    lanes: jax.Array
    lane_valid: jax.Array
    map_edges: jax.Array | None = None
    map_edge_valid: jax.Array | None = None
    edge_source: jax.Array | None = None

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(np.shape(self.polygons)[:-3])

    def validate(self, batch_shape: tuple[int, ...] | None = None, where: str = "RoadGeometry") -> "RoadGeometry":
        """Checks shapes and dtype kinds of every field (and the leading dims against `batch_shape` if given).

        Raises ValueError naming every field that is wrong. Returns the geometry itself.
        """
        spec = {
            "polygons": (("G", "V", 2), "f"), "polygon_valid": (("G", "V"), "b"), "polygon_kind": (("G",), "i"),
            "edges": (("E", "P", 2), "f"), "edge_valid": (("E", "P"), "b"),
            "lanes": (("L", "Q", 2), "f"), "lane_valid": (("L", "Q"), "b"),
        }
        if self.map_edges is not None or self.map_edge_valid is not None or self.edge_source is not None:
            spec.update({"map_edges": (("Em", "Pm", 2), "f"), "map_edge_valid": (("Em", "Pm"), "b"),
                         "edge_source": ((), "i")})
        problems: list[str] = []
        dims: dict[str, tuple[int, str]] = {}
        lead_seen: tuple[tuple[int, ...], str] | None = (
            (tuple(batch_shape), "the scene") if batch_shape is not None else None)
        for name, (suffix, kind) in spec.items():
            v = getattr(self, name)
            if v is None:
                problems.append(f"{name}: missing")
                continue
            shape = tuple(np.shape(v))
            dt = np.dtype(v.dtype) if hasattr(v, "dtype") else np.asarray(v).dtype
            if not (dt.kind == kind or (kind == "i" and dt.kind == "u")):
                problems.append(f"{name}: dtype {dt}, expected {dict(f='float', i='integer', b='bool')[kind]}")
            if len(shape) < len(suffix):
                problems.append(f"{name}: shape {shape} has fewer than {len(suffix)} dims")
                continue
            lead, tail = shape[: len(shape) - len(suffix)], shape[len(shape) - len(suffix):]
            if lead_seen is None:
                lead_seen = (lead, name)
            elif lead != lead_seen[0]:
                problems.append(f"{name}: leading dims {lead} differ from {lead_seen[1]}'s {lead_seen[0]}")
            for want, got in zip(suffix, tail):
                if isinstance(want, int):
                    if want != got:
                        problems.append(f"{name}: shape {shape}, last dim must be {want}")
                elif want in dims and dims[want][0] != got:
                    problems.append(f"{name}: {want}={got} but {dims[want][1]} has {want}={dims[want][0]}")
                else:
                    dims.setdefault(want, (got, name))
        if problems:
            raise ValueError(f"invalid {where}:\n  " + "\n  ".join(problems))
        return self


@flax.struct.dataclass(frozen=True)
class TrafficSignals:
    """Traffic-light states of one scene (or a batch: leading dims `...`), per signal slot (a controlled lane).

    Attributes:
      state: i32[..., T, S] the state per frame (index into `SIGNAL_STATES`; 0: unknown or no signal in the slot),
        on the scene's frames (`Scene.slice_frames` / `subsample` cut it with them).
      stop: f32[..., S, 2] the stop point of each slot in the scene frame.
      lane: f32[..., S, Q, 2] the controlled lane around the stop point, in driving order (scene frame).
      lane_valid: bool[..., S, Q] which lane points exist (a prefix); a slot with fewer than 2 is empty.
    """

    state: jax.Array
    stop: jax.Array
    lane: jax.Array
    lane_valid: jax.Array


def edge_source_names(road: "RoadGeometry | None", batch_shape: tuple[int, ...] = ()) -> np.ndarray:
    """Per scene (on the host), where the road edges a realism metric reads come from: an `EDGE_SOURCES` name,
    "area_boundary_unoriented" (a store before format 2: the areas' boundary, oriented by the metric) or
    "no_road" (`road` None; then `batch_shape` gives the scenes)."""
    if road is None:
        return np.full(batch_shape, "no_road", dtype=object)
    if road.edge_source is None:
        return np.full(road.batch_shape, "area_boundary_unoriented", dtype=object)
    return np.asarray(EDGE_SOURCES, dtype=object)[np.asarray(road.edge_source)]


def require_road(road: "RoadGeometry | None", where: str = "") -> "RoadGeometry":
    """`road` itself, or ValueError with `ROAD_MISSING` (prefixed by `where`) when it is None."""
    if road is None:
        raise ValueError((f"{where}: " if where else "") + ROAD_MISSING)
    return road


def empty_road(num_polygons: int = 1, num_vertices: int = 4, num_edges: int = 1, num_edge_points: int = 2,
               num_lanes: int = 1, num_lane_points: int = 2, batch_shape: tuple[int, ...] = ()) -> RoadGeometry:
    """A geometry with no area, edge or lane (every point off the road)."""
    b = tuple(batch_shape)
    return RoadGeometry(
        polygons=jnp.zeros(b + (num_polygons, num_vertices, 2), jnp.float32),
        polygon_valid=jnp.zeros(b + (num_polygons, num_vertices), bool),
        polygon_kind=jnp.zeros(b + (num_polygons,), jnp.int32),
        edges=jnp.zeros(b + (num_edges, num_edge_points, 2), jnp.float32),
        edge_valid=jnp.zeros(b + (num_edges, num_edge_points), bool),
        lanes=jnp.zeros(b + (num_lanes, num_lane_points, 2), jnp.float32),
        lane_valid=jnp.zeros(b + (num_lanes, num_lane_points), bool))


# ------------------------------------------------------------------------------------------------ internals
def _map_points(fn, xy: jax.Array, trailing: tuple[int, ...] = ()):
    """Applies `fn: f32[N, 2] -> tuple of f32[N, *trailing]` to `xy f32[..., 2]` in blocks of `_BLOCK` points."""
    lead = xy.shape[:-1]
    pts = jnp.reshape(xy, (-1, 2)).astype(jnp.float32)
    if pts.shape[0] <= _BLOCK:
        outs = fn(pts)
    else:
        outs = jax.lax.map(lambda q: tuple(o[0] for o in fn(q[None])), pts, batch_size=_BLOCK)
    return tuple(jnp.reshape(o, lead + trailing) for o in outs)


def _segments(points: jax.Array, valid: jax.Array):
    """Open polylines f32[K, P, 2] + bool[K, P] -> segment starts f32[S, 2], ends f32[S, 2], valid bool[S]."""
    a, b = points[..., :-1, :], points[..., 1:, :]
    ok = valid[..., :-1] & valid[..., 1:]
    return a.reshape(-1, 2), b.reshape(-1, 2), ok.reshape(-1)


def _ring_edges(polygons: jax.Array, valid: jax.Array):
    """Rings f32[G, V, 2] (prefix-valid, implicitly closed) -> edge starts/ends f32[G, V, 2], valid bool[G, V]."""
    nxt = jnp.roll(polygons, -1, axis=-2)
    nxt_valid = jnp.roll(valid, -1, axis=-1)
    nxt = jnp.where(nxt_valid[..., None], nxt, polygons[..., :1, :])
    # the last vertex's roll wraps to the first, which is right; a ring with < 3 vertices encloses nothing
    enough = jnp.sum(valid, axis=-1, keepdims=True) >= 3
    return polygons, nxt, valid & enough


def _point_segment_distance(p: jax.Array, a: jax.Array, b: jax.Array):
    """p f32[N, 2], a/b f32[S, 2] -> (distance f32[N, S], projection parameter f32[N, S])."""
    ab = b - a  # [S, 2]
    ap = p[:, None, :] - a[None]  # [N, S, 2]
    den = jnp.sum(ab * ab, -1)
    t = jnp.clip(jnp.sum(ap * ab[None], -1) / jnp.where(den > 0, den, 1.0), 0.0, 1.0)
    d = ap - t[..., None] * ab[None]
    return jnp.sqrt(jnp.sum(d * d, -1)), t


def _crossings(p: jax.Array, road: RoadGeometry) -> jax.Array:
    """p f32[N, 2] -> i32[N, G] number of ring edges a ray from p towards +x crosses, per ring."""
    a, b, ok = _ring_edges(road.polygons.astype(jnp.float32), road.polygon_valid)
    x, y = p[:, 0, None, None], p[:, 1, None, None]  # [N, 1, 1]
    ya, yb = a[None, ..., 1], b[None, ..., 1]
    straddle = (ya > y) != (yb > y)
    dy = jnp.where(straddle, yb - ya, 1.0)
    x_cross = a[None, ..., 0] + (y - ya) * (b[None, ..., 0] - a[None, ..., 0]) / dy
    hit = straddle & (x < x_cross) & ok[None]
    return jnp.sum(hit, axis=-1, dtype=jnp.int32)


def _area_kinds_flat(p: jax.Array, road: RoadGeometry) -> jax.Array:
    cross = _crossings(p, road)  # [N, G]
    onehot = road.polygon_kind.astype(jnp.int32)[:, None] == jnp.arange(len(AREA_KINDS))[None]  # [G, K]
    per_kind = jnp.sum(jnp.where(onehot[None], cross[..., None], 0), axis=1)  # [N, K]
    return per_kind % 2 == 1


# ------------------------------------------------------------------------------------------------ queries
def area_kinds(road: RoadGeometry, xy: jax.Array) -> jax.Array:
    """bool[..., K]: whether each point `xy f32[..., 2]` lies in each kind of drivable area (`AREA_KINDS`)."""
    (out,) = _map_points(lambda p: (_area_kinds_flat(p, road),), xy, trailing=(len(AREA_KINDS),))
    return out


def on_road(road: RoadGeometry, xy: jax.Array) -> jax.Array:
    """bool[...]: whether points `xy f32[..., 2]` (scene frame) lie in any drivable area of the unbatched `road`.

    Points on a ring's boundary may go either way. Outside the region the geometry covers, points are off-road.
    """
    return jnp.any(area_kinds(road, xy), axis=-1)


def distance_to_edge(road: RoadGeometry, xy: jax.Array) -> jax.Array:
    """f32[...]: unsigned distance (metres) from `xy f32[..., 2]` to the nearest road edge; +inf with no edges."""
    a, b, ok = _segments(road.edges.astype(jnp.float32), road.edge_valid)

    def fn(p):
        d, _ = _point_segment_distance(p, a, b)
        return (jnp.min(jnp.where(ok[None], d, jnp.inf), axis=-1),)

    return _map_points(fn, xy)[0]


def signed_distance_to_edge(road: RoadGeometry, xy: jax.Array) -> jax.Array:
    """f32[...]: distance (metres) from `xy f32[..., 2]` to the nearest road edge, positive on the road (as
    `on_road` says) and negative off it. +inf / -inf where the geometry has no edge segment at all.
    """
    d = distance_to_edge(road, xy)
    return jnp.where(on_road(road, xy), d, -d)


def lane_direction(road: RoadGeometry, xy: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(heading f32[...], distance f32[...]) of the nearest directed lane-centreline segment to `xy f32[..., 2]`.

    `heading` is the segment's direction in the scene frame (radians, [-pi, pi)); `distance` is the
    Euclidean distance to the segment (metres). With no lane segment: heading 0 and distance +inf.
    """
    a, b, ok = _segments(road.lanes.astype(jnp.float32), road.lane_valid)
    seg_heading = jnp.arctan2(b[:, 1] - a[:, 1], b[:, 0] - a[:, 0])
    ok = ok & (jnp.sum((b - a) ** 2, -1) > 0)

    def fn(p):
        d, _ = _point_segment_distance(p, a, b)
        d = jnp.where(ok[None], d, jnp.inf)
        i = jnp.argmin(d, axis=-1)
        dist = jnp.take_along_axis(d, i[:, None], axis=-1)[:, 0]
        h = jnp.where(jnp.isfinite(dist), seg_heading[i], 0.0)
        return h, dist

    heading, dist = _map_points(fn, xy)
    heading = (heading + jnp.pi) % (2 * jnp.pi) - jnp.pi
    return heading, dist


def lane_trace(lanes: jax.Array, lane_valid: jax.Array, xy: jax.Array, heading: jax.Array, step_m,
               num_steps: int, turn_penalty_m: float = 10.0, stride: int = 1,
               max_gap_m=None) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Walks the directed lane centrelines ahead of each pose: where a driver keeping its lane would be.

    From each pose (`xy f32[..., 2]`, `heading f32[...]`, scene frame) it takes the lane segment that minimises
    distance + `turn_penalty_m` * (1 - cos(segment heading - travel direction)) / 2 (the nearest lane that runs
    the way the agent goes, rather than the opposing one beside it), projects onto it, and steps `step_m` along the
    segment's direction; `num_steps` times, each from the last point and along the last segment's heading.
    `step_m` is one length for every pose or f32[...] one per pose. With `max_gap_m` (one or per pose), a step that
    lands farther than that from every lane (the lane ended, as lanes clipped to a sample's region do) is not pulled
    back onto one: the walk goes on straight from there along its last heading until a lane is near again (without
    it, the walk stalls at the end of a lane).
    `lanes f32[L, Q, 2]` / `lane_valid bool[L, Q]` are one scene's (`RoadGeometry.lanes`); `stride` keeps every
    stride-th point of each line (coarser segments, cheaper queries; the last valid point is kept).

    Returns (points f32[..., K + 1, 2]: the projections onto the lane at the pose and after each step,
    headings f32[..., K + 1]: the chosen segments' directions, distances f32[..., K + 1]: from each query point
    to its chosen segment). Without any lane segment: points at the query points, headings the travel direction,
    distances +inf.
    """
    if stride > 1:
        last = jnp.maximum(jnp.sum(lane_valid, axis=-1) - 1, 0)  # index of the last valid point (prefix-valid)
        idx = jnp.arange(0, lanes.shape[-2], stride)
        keep = jnp.minimum(idx[None, :], last[:, None])  # [L, Q'] every stride-th point, clipped to the last
        keep = jnp.concatenate([keep, last[:, None]], axis=-1)
        lanes = jnp.take_along_axis(lanes, keep[..., None], axis=-2)
        lane_valid = jnp.take_along_axis(lane_valid, keep, axis=-1)
    a, b, ok = _segments(lanes.astype(jnp.float32), lane_valid)
    seg_heading = jnp.arctan2(b[:, 1] - a[:, 1], b[:, 0] - a[:, 0])
    ok = ok & (jnp.sum((b - a) ** 2, -1) > 0)
    seg_dir = jnp.stack([jnp.cos(seg_heading), jnp.sin(seg_heading)], -1)

    def walk(q):  # q f32[N, 5] (x, y, heading, step, gap) -> f32[N, K+1, 4] (x, y, heading, distance)
        def one(p, h):
            d, t = _point_segment_distance(p, a, b)
            cost = d + turn_penalty_m * 0.5 * (1.0 - jnp.cos(seg_heading[None] - h[:, None]))
            cost = jnp.where(ok[None], cost, jnp.inf)
            i = jnp.argmin(cost, axis=-1)
            found = jnp.isfinite(jnp.take_along_axis(cost, i[:, None], -1)[:, 0])
            ti = jnp.take_along_axis(t, i[:, None], -1)
            proj = a[i] + ti * (b[i] - a[i])
            dist = jnp.take_along_axis(d, i[:, None], -1)[:, 0]
            return (jnp.where(found[:, None], proj, p), jnp.where(found, seg_heading[i], h),
                    jnp.where(found, dist, jnp.inf), jnp.where(found[:, None], seg_dir[i], 0.0))

        p, h, step, gap = q[:, :2], q[:, 2], q[:, 3:4], q[:, 4]
        rows = []
        for k in range(num_steps + 1):  # a fixed, small number of steps (not a loop over time)
            proj, hk, dist, u = one(p, h)
            if max_gap_m is not None and k > 0:
                off = ~(dist <= gap)  # no lane near the stepped point: keep it, and the heading
                proj = jnp.where(off[:, None], p, proj)
                hk = jnp.where(off, h, hk)
                u = jnp.where(off[:, None], jnp.stack([jnp.cos(h), jnp.sin(h)], -1), u)
            rows.append(jnp.concatenate([proj, hk[:, None], dist[:, None]], -1))
            p = proj + step * jnp.where(jnp.isfinite(dist)[:, None], u, jnp.stack([jnp.cos(h), jnp.sin(h)], -1))
            h = hk
        return (jnp.stack(rows, 1),)

    lead = xy.shape[:-1]
    steps = jnp.broadcast_to(jnp.asarray(step_m, jnp.float32), lead)
    gaps = jnp.broadcast_to(jnp.asarray(jnp.inf if max_gap_m is None else max_gap_m, jnp.float32), lead)
    q = jnp.concatenate([xy.astype(jnp.float32), heading.astype(jnp.float32)[..., None], steps[..., None],
                         gaps[..., None]], -1)
    flat = q.reshape(-1, 5)
    if flat.shape[0] <= _BLOCK:
        (out,) = walk(flat)
    else:
        out = jax.lax.map(lambda r: walk(r[None])[0][0], flat, batch_size=_BLOCK)
    out = out.reshape(lead + (num_steps + 1, 4))
    return out[..., :2], _wrap(out[..., 2]), out[..., 3]


# An agent farther than this from every lane running its way is not moved along the lanes by `lane_follow` (m).
LANE_SNAP_M = 3.0


def lane_follow(lanes: jax.Array, lane_valid: jax.Array, xy: jax.Array, direction: jax.Array, step_m,
                num_steps: int, stride: int = 1, snap_m: float = LANE_SNAP_M):
    """Where an agent keeping its lane and its offset from it is after `num_steps` steps of `step_m` metres.

    From each pose (`xy f32[..., 2]`, travel `direction f32[...]`, scene frame; `step_m` one length or f32[...] one
    per pose) it walks the lanes (`lane_trace`, leaving a lane's clipped end straight: `max_gap_m` half a step and
    at least 1 m, since on a curve of radius R a step s lands about s^2 / 2R off the lane, under s / 2 while
    s < R) and adds the pose's current offset from the lane, turned with the lane. `lanes f32[L, Q, 2]` /
    `lane_valid bool[L, Q]`: one scene's directed lane centrelines; `stride` as in `lane_trace`.

    Returns (xy f32[..., K, 2] the positions after each step, turn f32[..., K] the lane's heading change from the
    pose's lane segment to each step's (wrapped), lane heading f32[..., K] at each step, use bool[...]: a lane lies
    within `snap_m`; where it does not, the caller keeps its own prediction)."""
    step = jnp.asarray(step_m, jnp.float32)
    pts, lane_h, dist = lane_trace(lanes, lane_valid, xy, direction, step, num_steps, stride=stride,
                                   max_gap_m=jnp.maximum(0.5 * step, 1.0))
    use = dist[..., 0] <= snap_m
    off = xy.astype(jnp.float32) - pts[..., 0, :]
    turn = _wrap(lane_h[..., 1:] - lane_h[..., :1])
    return pts[..., 1:, :] + rotate(off[..., None, :], turn), turn, lane_h[..., 1:], use


def project_on_path(path_xy: jax.Array, path_s: jax.Array, q: jax.Array):
    """Projects points q f32[Q, 2] on one path (xy f32[P, 2], s f32[P]): (arc f32[Q], lateral distance f32[Q],
    unit tangent f32[Q, 2])."""
    a, b = path_xy[:-1], path_xy[1:]
    ab = b - a
    len2 = jnp.sum(ab * ab, -1)
    t = jnp.clip(jnp.sum((q[:, None] - a[None]) * ab[None], -1) / jnp.maximum(len2, 1e-9)[None], 0.0, 1.0)
    foot = a[None] + t[..., None] * ab[None]
    d = jnp.linalg.norm(q[:, None] - foot, axis=-1)                              # [Q, P-1]
    d = jnp.where(len2[None] > 1e-9, d, jnp.inf)
    d = jnp.where(jnp.isfinite(jnp.min(d, -1, keepdims=True)), d, jnp.linalg.norm(q[:, None] - a[None], axis=-1))
    i = jnp.argmin(d, axis=-1)
    seg_len = jnp.sqrt(len2)
    arc = path_s[i] + jnp.take_along_axis(t, i[:, None], 1)[:, 0] * seg_len[i]
    tangent = ab[i] / jnp.maximum(seg_len[i], 1e-6)[:, None]
    return arc, jnp.take_along_axis(d, i[:, None], 1)[:, 0], tangent


def pose_on_path(path_xy: jax.Array, path_heading: jax.Array, path_s: jax.Array, s: jax.Array):
    """Pose on one path at arc s f32[]: (xy f32[2], heading f32[]); the heading interpolates the logged ones."""
    p = path_s.shape[0]
    i = jnp.clip(jnp.searchsorted(path_s, s, side="right") - 1, 0, p - 2)
    seg = path_s[i + 1] - path_s[i]
    frac = jnp.where(seg > 1e-6, jnp.clip((s - path_s[i]) / jnp.maximum(seg, 1e-6), 0.0, 1.0), 0.0)
    xy = path_xy[i] + frac * (path_xy[i + 1] - path_xy[i])
    h = _wrap(path_heading[i] + frac * _wrap(path_heading[i + 1] - path_heading[i]))
    return xy, h


def route_ahead(path_xy: jax.Array, path_s: jax.Array, pose: jax.Array, num_points: int,
                spacing_m: float) -> jax.Array:
    """Where a path goes from a pose on (or beside) it: the points `spacing_m`, 2 `spacing_m`, ... `num_points`
    `spacing_m` metres of arc ahead of the pose's projection on the path, in the pose's frame (x along its
    heading, y to its left). path_xy f32[P, 2], path_s f32[P] (arc length, non-decreasing), pose f32[3] ->
    f32[num_points, 2]. Past the path's end the points stay at its end (extend paths as far as you need)."""
    s0, _, _ = project_on_path(path_xy, path_s, pose[None, :2])
    s = s0[0] + spacing_m * jnp.arange(1, num_points + 1, dtype=path_xy.dtype)
    p = path_s.shape[0]
    i = jnp.clip(jnp.searchsorted(path_s, s, side="right") - 1, 0, p - 2)
    seg = path_s[i + 1] - path_s[i]
    frac = jnp.where(seg > 1e-6, jnp.clip((s - path_s[i]) / jnp.maximum(seg, 1e-6), 0.0, 1.0), 0.0)
    xy = path_xy[i] + frac[:, None] * (path_xy[i + 1] - path_xy[i])
    return rotate(xy - pose[:2], -pose[2])


def _wrap(a: jax.Array) -> jax.Array:
    """Angles wrapped to [-pi, pi) (`gpd_jax.scene.wrap_angle`; the bottom layer's modules do not import each
    other)."""
    return (a + jnp.pi) % (2 * jnp.pi) - jnp.pi


def rotate(v: jax.Array, angle: jax.Array) -> jax.Array:
    """f32[..., 2] vectors turned by angle f32[...] (radians, counter-clockwise)."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)


def road_from_arrays(arrays: dict[str, Any], lanes: Any, lane_valid: Any, prefix: str = "road_") -> RoadGeometry:
    """RoadGeometry from stored arrays named `<prefix>polygons`, ... (numpy or JAX leaves kept as they are); the
    map edges (`<prefix>map_edges`, `<prefix>map_edge_valid`, `<prefix>edge_source`) where the arrays have them."""
    has_map = prefix + "map_edges" in arrays
    source = arrays.get(prefix + "edge_source")
    return RoadGeometry(polygons=arrays[prefix + "polygons"], polygon_valid=arrays[prefix + "polygon_valid"],
                        polygon_kind=arrays[prefix + "polygon_kind"], edges=arrays[prefix + "edges"],
                        edge_valid=arrays[prefix + "edge_valid"], lanes=lanes, lane_valid=lane_valid,
                        map_edges=arrays[prefix + "map_edges"] if has_map else None,
                        map_edge_valid=arrays[prefix + "map_edge_valid"] if has_map else None,
                        edge_source=None if source is None or not has_map else source.astype(np.int32))
