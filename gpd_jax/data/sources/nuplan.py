"""The nuPlan importer: a log `.db` (SQLite) plus its city map `.gpkg` (GeoPackage) -> `RawLog` -> a store
(`build_nuplan`, one shard per log, with the shared job runner `gpd_jax.data.jobs`).

Only the standard library's sqlite3 and numpy are needed (pyproj is used for map projection when installed;
otherwise a built-in exact transverse Mercator covers WGS84 lon/lat and UTM, which is what nuPlan uses).
Schemas: nuPlan's SQLite log tables and map layers (docs/data.md).

What is read, and the conventions:

* **Frames.** `lidar_pc` rows of the `MergedPointCloud` lidar (the only lidar when there is one) in
  timestamp order are the 20 Hz frames; every second one is kept (rows 0, 2, 4, ...) as nuPlan's devkit
  does, giving 10 Hz. `RawLog.timestamps` are the kept `lidar_pc.timestamp`s in seconds from the first one;
  a step more than `max_step_error` away from 0.1 s (a dropped frame) is a `DataError`.
* **Ego** (track 0, `RawLog.ego_index == 0`, id "ego", type "ego"): `ego_pose` reached through
  `lidar_pc.ego_pose_token`. Its x, y are the *rear axle*; the heading is the quaternion's yaw
  atan2(2(qw qz + qx qy), 1 - 2(qy^2 + qz^2)). The box centre is the rear axle moved forward along the
  heading by `EGO_REAR_AXLE_TO_CENTER` = 1.461 m; the box is `EGO_LENGTH` x `EGO_WIDTH` = 5.176 x 2.297 m.
  These are the nuPlan vehicle (Chrysler Pacifica) parameters: rear axle -> front bumper 4.049 m, rear
  axle -> rear bumper 1.127 m, so length 5.176 m and rear axle -> centre = 5.176 / 2 - 1.127 = 1.461 m.
* **Vehicles**: `lidar_box` joined to `track` and `category`, category name `vehicle` only (pedestrians,
  bicycles and static objects are dropped). One track per `track_token` (id = the token in hex), in order
  of first appearance; `agent_valid[f, n]` says whether the track has a box in kept frame f. x, y are the
  box centre, `yaw` the heading (global frame). Size (length, width) comes from the `track` row, or from the
  median of the track's boxes where the track row has none. When a track has two boxes in one frame, the
  one with the higher confidence is kept.
* **Vehicle type** (`vehicle_type`): nuPlan has one `vehicle` category, so the type comes from the box
  length: < 6.5 m "car", 6.5-10 m "truck", >= 10 m "bus" (constants `TRUCK_MIN_LENGTH`, `BUS_MIN_LENGTH`).
* **Map**: the map name is `log.map_version` (a `.gpkg` suffix is stripped), or derived from `log.location`
  ("las_vegas" -> "us-nv-las-vegas-strip", ...) when that names no map. It is looked for under `maps_root`
  (see `find_map`). Lane centrelines are every geometry of the `baseline_paths` layer, which holds the
  centrelines of both lanes (`lane_fid`) and lane connectors (`lane_connector_fid`). As SLEDGE does, lanes
  and connectors are concatenated into maximal unbranched chains through `lane_connectors.exit_lane_fid` /
  `entry_lane_fid` (`merge_chains`; `merge_lanes=False` keeps one polyline per row; the parts of a
  MultiLineString are separate polylines and never merged). Coordinates are projected from
  the layer's SRS (`gpkg_geometry_columns.srs_id`) to the logs' frame, which is the map's
  `meta.projectedCoordSystem`, else the `ego_pose.epsg` of the log, else the known UTM zone of the four
  nuPlan cities (`MAP_UTM_EPSG`). Lanes are cropped to the bounding box of the log's boxes grown by
  `map_margin` metres (lanes are kept whole); no lane there is a `DataError` (it means a projection or map
  mismatch).
* **Drivable area** (`read_map_areas`, `RawLog.areas`): the polygons of the `AREA_LAYERS` the map has —
  `lanes_polygons` and `lane_groups_polygons` (kind "lane"), `intersections` ("junction"),
  `generic_drivable_areas` and `carpark_areas` ("other") — projected like the lanes and cropped to the same
  box (polygons whose bounds meet it, kept whole). Their outline is the road's edge (`RawLog.areas_outline`
  "drivable_area": the map road edges the realism metric reads).
* **Traffic lights** (`RawLog.signals`): `traffic_light_status` rows of the kept frames (`LIGHT_STATUS`: red ->
  stop, yellow -> caution, green -> go; a frame without a row is unknown) for every lane connector of the map
  (`MapLanes.connectors`): stop point at the connector's start, the connector's centreline as the lane.
* `RawLog.location` is the map name (e.g. "us-nv-las-vegas-strip"); `RawLog.name` is the file stem.
* **Build** (`build_nuplan`): one job and one shard per log, split by map (`log.map_version` from the log headers,
  read first) unless `split` is given; the jobs then run on the shared job runner (local processes or Ray, each
  worker reading a map once for its logs); a bad log is skipped, counted (`logs_skipped_bad`) and named in the
  build's rejections.

Every problem with an input file raises `gpd_jax.data.errors.DataError` naming the file and the reason.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import shutil
import sqlite3
import time
from collections import Counter
from pathlib import Path
from typing import Hashable, Iterable, Iterator, Sequence

import numpy as np

from gpd_jax.data import preprocess, store
from gpd_jax.data.errors import DataError
from gpd_jax.data.jobs import (assign_splits, check_count, check_settings, existing_shard, finish, job_marker,
                               run_jobs)
from gpd_jax.data.raw import RawLog
from gpd_jax.data.roadgeom import Area
from gpd_jax.data.signals import RawSignals
from gpd_jax.data.sources import gpkg
from gpd_jax.geometry import AREA_KIND_ID, SIGNAL_STATE_ID
from gpd_jax.scene import TYPE_ID

log = logging.getLogger(__name__)

# The nuPlan ego vehicle (Chrysler Pacifica), metres.
EGO_LENGTH = 5.176
EGO_WIDTH = 2.297
EGO_REAR_AXLE_TO_CENTER = 1.461

LIDAR_CHANNEL = "MergedPointCloud"
SOURCE_HZ = 20
TARGET_HZ = 10
FRAME_STEP = SOURCE_HZ // TARGET_HZ

VEHICLE_CATEGORY = "vehicle"
TRUCK_MIN_LENGTH = 6.5
BUS_MIN_LENGTH = 10.0

BASELINE_LAYER = "baseline_paths"
MAPS_JSON = "nuplan-maps-v1.0.json"

# `log.location` -> map name, for logs whose map_version does not name a map folder.
MAP_NAMES_BY_LOCATION = {
    "las_vegas": "us-nv-las-vegas-strip",
    "boston": "us-ma-boston",
    "pittsburgh": "us-pa-pittsburgh-hazelwood",
    "singapore": "sg-one-north",
}
# The UTM zone each nuPlan city's logs are in; used only when neither the map's `meta` table nor the log's
# `ego_pose.epsg` says.
MAP_UTM_EPSG = {
    "us-nv-las-vegas-strip": 32611,
    "us-ma-boston": 32619,
    "us-pa-pittsburgh-hazelwood": 32617,
    "sg-one-north": 32648,
}

_LOG_TABLES = ("log", "lidar", "lidar_pc", "ego_pose", "lidar_box", "track", "category")


# ---------------------------------------------------------------------------------------------------------
# Small pure helpers
# ---------------------------------------------------------------------------------------------------------


def quaternion_yaw(qw, qx, qy, qz) -> np.ndarray:
    """Yaw (rotation about z, counter-clockwise from +x) of unit quaternions, f64[...]."""
    qw, qx, qy, qz = (np.asarray(q, np.float64) for q in (qw, qx, qy, qz))
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def rear_axle_to_center(xy: np.ndarray, heading: np.ndarray, offset: float = EGO_REAR_AXLE_TO_CENTER) -> np.ndarray:
    """Moves rear-axle positions f64[..., 2] forward along `heading` f64[...] by `offset` m (box centres)."""
    heading = np.asarray(heading, np.float64)
    return np.asarray(xy, np.float64) + offset * np.stack([np.cos(heading), np.sin(heading)], axis=-1)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Wraps angles to [-pi, pi)."""
    return (np.asarray(a, np.float64) + np.pi) % (2 * np.pi) - np.pi


def vehicle_type(length: np.ndarray) -> np.ndarray:
    """`gpd_jax.scene.TYPE_ID` of nuPlan 'vehicle' boxes from their length f[...]: car < 6.5 m <= truck < 10
    m <= bus. Returns i32[...]."""
    length = np.asarray(length, np.float64)
    out = np.full(length.shape, TYPE_ID["car"], np.int32)
    out[length >= TRUCK_MIN_LENGTH] = TYPE_ID["truck"]
    out[length >= BUS_MIN_LENGTH] = TYPE_ID["bus"]
    return out


def _token_str(token) -> str:
    if isinstance(token, (bytes, bytearray, memoryview)):
        return bytes(token).hex()
    return str(token)


def _map_name(map_version: str) -> str:
    name = str(map_version).strip()
    return name[: -len(".gpkg")] if name.endswith(".gpkg") else name


# ---------------------------------------------------------------------------------------------------------
# Log database
# ---------------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class LogHeader:
    """The `log` row of a nuPlan database."""

    path: str
    token: str
    location: str
    map_version: str
    vehicle_name: str
    logfile: str


def _query(conn: sqlite3.Connection, path, sql: str, args=()) -> list:
    try:
        return conn.execute(sql, args).fetchall()
    except sqlite3.Error as e:
        raise DataError(path, f"SQLite error ({e}) in: {' '.join(sql.split())[:120]}") from e


def _check_tables(conn: sqlite3.Connection, path) -> None:
    rows = _query(conn, path, "SELECT name FROM sqlite_master WHERE type IN ('table', 'view')")
    have = {r[0] for r in rows}
    missing = [t for t in _LOG_TABLES if t not in have]
    if missing:
        raise DataError(path, f"not a nuPlan log database: missing table(s) {', '.join(missing)}")


def _read_header(conn: sqlite3.Connection, path) -> LogHeader:
    rows = _query(conn, path, "SELECT token, location, map_version, vehicle_name, logfile FROM log")
    if len(rows) != 1:
        raise DataError(path, f"expected one row in table log, found {len(rows)}")
    token, location, map_version, vehicle, logfile = rows[0]
    if not map_version and not location:
        raise DataError(path, "log row has neither map_version nor location")
    return LogHeader(
        path=os.fspath(path),
        token=_token_str(token),
        location=str(location or ""),
        map_version=str(map_version or ""),
        vehicle_name=str(vehicle or ""),
        logfile=str(logfile or ""),
    )


def read_log_header(db_path: str | os.PathLike) -> LogHeader:
    """Reads the `log` row of a nuPlan log database (raises `DataError` for a bad file)."""
    conn = gpkg.open_sqlite(db_path, "nuPlan log database")
    try:
        _check_tables(conn, db_path)
        return _read_header(conn, db_path)
    finally:
        conn.close()


@dataclasses.dataclass(frozen=True)
class _Frames:
    tokens: list  # F lidar_pc tokens (raw, as stored)
    timestamps_us: np.ndarray  # i64[F]
    ego: np.ndarray  # f64[F, 6] x, y, qw, qx, qy, qz (rear axle)
    epsg: tuple  # distinct non-null ego_pose.epsg values


def _read_frames(conn: sqlite3.Connection, path, max_step_error: float) -> _Frames:
    lidars = _query(conn, path, "SELECT token, channel FROM lidar")
    merged = [t for t, ch in lidars if ch == LIDAR_CHANNEL]
    if len(merged) == 1:
        lidar_token = merged[0]
    elif len(lidars) == 1:
        lidar_token = lidars[0][0]
    else:
        raise DataError(path, f"expected one '{LIDAR_CHANNEL}' lidar, found {len(merged)} among {len(lidars)}")
    n_pc = _query(conn, path, "SELECT count(*) FROM lidar_pc WHERE lidar_token = ?", (lidar_token,))[0][0]
    rows = _query(
        conn,
        path,
        "SELECT lp.token, lp.timestamp, ep.x, ep.y, ep.qw, ep.qx, ep.qy, ep.qz, ep.epsg "
        "FROM lidar_pc AS lp JOIN ego_pose AS ep ON ep.token = lp.ego_pose_token "
        "WHERE lp.lidar_token = ? ORDER BY lp.timestamp, lp.rowid",
        (lidar_token,),
    )
    if len(rows) != n_pc:
        raise DataError(path, f"{n_pc - len(rows)} of {n_pc} lidar_pc rows have no ego_pose row")
    rows = rows[::FRAME_STEP]
    if len(rows) < 2:
        raise DataError(path, f"log has {len(rows)} frame(s) at {TARGET_HZ} Hz; need at least 2")
    ts = np.array([r[1] if r[1] is not None else -1 for r in rows], np.int64)
    if (ts < 0).any():
        raise DataError(path, "lidar_pc.timestamp is NULL or negative")
    steps = np.diff(ts) * 1e-6
    bad = np.flatnonzero(np.abs(steps - 1.0 / TARGET_HZ) > max_step_error)
    if bad.size:
        i = int(bad[0])
        raise DataError(
            path,
            f"frames are not {TARGET_HZ} Hz after subsampling: step {steps[i]:.3f} s between kept frames "
            f"{i} and {i + 1} ({bad.size} such step(s); dropped or duplicated lidar_pc rows?)",
        )
    ego = np.array([r[2:8] for r in rows], np.float64)  # NULL -> NaN
    if not np.isfinite(ego).all():
        f = int(np.flatnonzero(~np.isfinite(ego).all(axis=1))[0])
        raise DataError(path, f"ego_pose of kept frame {f} has a NaN/NULL value")
    qnorm = np.linalg.norm(ego[:, 2:6], axis=1)
    if (np.abs(qnorm - 1.0) > 1e-3).any():
        f = int(np.flatnonzero(np.abs(qnorm - 1.0) > 1e-3)[0])
        raise DataError(path, f"ego_pose of kept frame {f} has a non-unit quaternion (norm {qnorm[f]:.4f})")
    epsg = tuple(sorted({int(r[8]) for r in rows if isinstance(r[8], (int, float)) and r[8] and r[8] > 0}))
    return _Frames([r[0] for r in rows], ts, ego, epsg)


@dataclasses.dataclass(frozen=True)
class _Tracks:
    ids: tuple  # N track ids (hex)
    xy: np.ndarray  # f64[F, N, 2]
    heading: np.ndarray  # f64[F, N]
    valid: np.ndarray  # bool[F, N]
    size: np.ndarray  # f32[N, 2] (length, width)


def _read_vehicles(conn: sqlite3.Connection, path, frames: _Frames) -> _Tracks:
    # The kept frames go into a temporary table so that SQLite joins only their boxes.
    _query(conn, path, "CREATE TEMP TABLE IF NOT EXISTS gpd_kept_pc (token PRIMARY KEY) WITHOUT ROWID")
    _query(conn, path, "DELETE FROM temp.gpd_kept_pc")
    try:
        conn.executemany("INSERT OR IGNORE INTO temp.gpd_kept_pc VALUES (?)", [(t,) for t in frames.tokens])
    except sqlite3.Error as e:
        raise DataError(path, f"SQLite error ({e}) while selecting frames") from e
    rows = _query(
        conn,
        path,
        "SELECT lb.lidar_pc_token, lb.track_token, lb.x, lb.y, lb.yaw, lb.length, lb.width, lb.confidence, "
        "t.length, t.width "
        "FROM lidar_box AS lb JOIN temp.gpd_kept_pc AS k ON k.token = lb.lidar_pc_token "
        "JOIN track AS t ON t.token = lb.track_token "
        "JOIN category AS c ON c.token = t.category_token WHERE c.name = ? ORDER BY lb.rowid",
        (VEHICLE_CATEGORY,),
    )
    frame_of = {tok: i for i, tok in enumerate(frames.tokens)}
    rows = [r for r in rows if r[0] in frame_of]
    num_frames = len(frames.tokens)
    if not rows:
        empty = np.zeros((num_frames, 0))
        return _Tracks((), np.zeros((num_frames, 0, 2)), empty, empty.astype(bool), np.zeros((0, 2), np.float32))
    track_of: dict = {}
    fi = np.empty(len(rows), np.int64)
    ti = np.empty(len(rows), np.int64)
    for k, r in enumerate(rows):
        fi[k] = frame_of[r[0]]
        ti[k] = track_of.setdefault(r[1], len(track_of))
    # Order tracks by first appearance (frame, then row order): stable and reproducible.
    first = np.full(len(track_of), np.iinfo(np.int64).max)
    np.minimum.at(first, ti, fi * len(rows) + np.arange(len(rows)))
    rank = np.empty(len(track_of), np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(track_of))
    ti = rank[ti]
    tokens = [None] * len(track_of)
    for tok, i in track_of.items():
        tokens[rank[i]] = tok

    vals = np.array([r[2:] for r in rows], np.float64)  # x, y, yaw, len, wid, conf, t.len, t.wid; NULL->NaN
    bad = ~np.isfinite(vals[:, :3]).all(axis=1)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise DataError(
            path, f"lidar_box of track {_token_str(tokens[ti[k]])} in kept frame {fi[k]} has a NaN/NULL x/y/yaw"
        )
    num = len(tokens)
    xy = np.full((num_frames, num, 2), np.nan)
    heading = np.full((num_frames, num), np.nan)
    valid = np.zeros((num_frames, num), bool)
    conf = np.nan_to_num(vals[:, 5], nan=-np.inf)
    order = np.lexsort((conf,))  # ascending confidence: the most confident box of a (frame, track) wins
    xy[fi[order], ti[order]] = vals[order, 0:2]
    heading[fi[order], ti[order]] = wrap_angle(vals[order, 2])
    valid[fi, ti] = True

    size = _track_sizes(ti, vals[:, 6:8], vals[:, 3:5], num)
    bad = ~np.isfinite(size).all(axis=1)
    if bad.any():
        n = int(np.flatnonzero(bad)[0])
        raise DataError(path, f"track {_token_str(tokens[n])} has no valid length/width in track or lidar_box")
    return _Tracks(tuple(_token_str(t) for t in tokens), xy, heading, valid, size.astype(np.float32))


def _track_sizes(ti: np.ndarray, track_lw: np.ndarray, box_lw: np.ndarray, num: int) -> np.ndarray:
    """(length, width) per track, f64[num, 2]: the `track` row's value (constant over a track's rows
    `track_lw` f64[R, 2]), else the median of its boxes' `box_lw` f64[R, 2]; NaN when neither is positive."""
    size = np.full((num, 2), np.nan)
    size[ti] = track_lw  # the same value on every row of a track
    size[~(size > 0)] = np.nan
    need = np.flatnonzero(np.isnan(size).any(axis=1))
    if need.size:
        order = np.argsort(ti, kind="stable")
        starts = np.searchsorted(ti[order], np.arange(num + 1))
        for n in need:
            rows = box_lw[order[starts[n] : starts[n + 1]]]
            for j in range(2):
                if np.isnan(size[n, j]):
                    ok = rows[:, j][np.isfinite(rows[:, j]) & (rows[:, j] > 0)]
                    size[n, j] = np.median(ok) if ok.size else np.nan
    return size


# ---------------------------------------------------------------------------------------------------------
# Maps
# ---------------------------------------------------------------------------------------------------------


def _version_key(name: str) -> tuple:
    return tuple(int(p) if p.isdigit() else -1 for p in re.split(r"[.\-_]", name))


def _map_candidates(maps_root: Path, name: str) -> list[Path]:
    """Where the map `name` may live under `maps_root`, most authoritative first."""
    out: list[Path] = []
    roots = [maps_root, maps_root / "maps", maps_root / "nuplan-maps-v1.0"]
    for root in roots:
        if not root.is_dir():
            continue
        for js in [root / MAPS_JSON] + sorted(p for p in root.glob("*.json") if p.name != MAPS_JSON):
            try:
                version = json.loads(js.read_text())[name]["version"]
            except (OSError, ValueError, KeyError, TypeError):
                continue
            out.append(root / name / str(version) / "map.gpkg")
        versions = sorted((p for p in (root / name).glob("*/map.gpkg")), key=lambda p: _version_key(p.parent.name))
        out.extend(reversed(versions))  # newest version first
        out.append(root / name / "map.gpkg")
        out.append(root / f"{name}.gpkg")
        out.extend(sorted((root / name).glob("*.gpkg")))
    return out


def find_map(maps_root: str | os.PathLike, map_version: str, location: str = "") -> tuple[str, Path]:
    """Finds the GeoPackage of a log's map. Returns (map name, path).

    `map_version` is `log.map_version` (e.g. "us-nv-las-vegas-strip", a ".gpkg" suffix is stripped); when
    it names no map, `location` (`log.location`, e.g. "las_vegas") is mapped to a map name. Layouts searched
    under `maps_root`, and under `maps_root/maps` and `maps_root/nuplan-maps-v1.0`:

      <name>/<version>/map.gpkg  with <version> from nuplan-maps-v1.0.json ({name: {"version": ...}}),
                                 else the highest version folder present;
      <name>/map.gpkg;  <name>.gpkg;  <name>/*.gpkg.

    Raises:
      FileNotFoundError: listing what was tried (callers turn it into a `DataError` naming the log).
    """
    root = Path(maps_root)
    names = [n for n in (_map_name(map_version), MAP_NAMES_BY_LOCATION.get(location.strip().lower(), "")) if n]
    tried: list[str] = []
    for name in dict.fromkeys(names):
        for cand in _map_candidates(root, name):
            if cand.is_file():
                return name, cand
            tried.append(os.fspath(cand))
    if not root.is_dir():
        raise FileNotFoundError(f"maps root {os.fspath(root)} is not a directory")
    shown = ", ".join(dict.fromkeys(tried[:6])) or "nothing"
    raise FileNotFoundError(
        f"no map file for map_version {map_version!r} (location {location!r}) under {os.fspath(root)}; "
        f"tried {shown}"
    )


@dataclasses.dataclass(frozen=True)
class MapLanes:
    """Lane centrelines of one map, in the logs' frame.

    Attributes:
      path: the GeoPackage file.
      crs: the coordinate system they were projected to (as given to the projection library).
      lanes: tuple of L f64[P_i, 2] centrelines (lanes and lane connectors, P_i >= 2).
      is_connector: bool[L] the polyline is a lane connector's (False: a lane's, or unknown).
      bounds: f64[L, 4] (xmin, ymin, xmax, ymax) of each centreline.
      connectors: lane connector fid (str) -> its own centreline f64[P, 2] (before merging): what a traffic light
        controls (`traffic_light_status.lane_connector_id`).
    """

    path: str
    crs: str
    lanes: tuple[np.ndarray, ...]
    is_connector: np.ndarray
    bounds: np.ndarray
    connectors: dict = dataclasses.field(default_factory=dict)

    def crop(self, box: np.ndarray) -> tuple[np.ndarray, ...]:
        """The centrelines whose bounds meet the box f64[4] (xmin, ymin, xmax, ymax), kept whole."""
        b = self.bounds
        keep = (b[:, 0] <= box[2]) & (b[:, 2] >= box[0]) & (b[:, 1] <= box[3]) & (b[:, 3] >= box[1])
        return tuple(self.lanes[i] for i in np.flatnonzero(keep))


def map_crs(gpkg_path: str | os.PathLike, map_name: str = "", log_epsg: tuple = ()) -> str:
    """The projected frame a nuPlan map's logs are in: `meta.projectedCoordSystem`, else the log's
    `ego_pose.epsg`, else `MAP_UTM_EPSG[map_name]`, else the layer's own SRS when it is projected."""
    conn = gpkg.open_sqlite(gpkg_path, "GeoPackage")
    try:
        meta = gpkg.read_meta(conn)
        if meta.get("projectedCoordSystem"):
            return meta["projectedCoordSystem"]
        if len(log_epsg) == 1:
            return f"EPSG:{log_epsg[0]}"
        if map_name in MAP_UTM_EPSG:
            return f"EPSG:{MAP_UTM_EPSG[map_name]}"
        rows = conn.execute(
            "SELECT srs_id FROM gpkg_geometry_columns WHERE table_name = ?", (BASELINE_LAYER,)
        ).fetchall()
        if rows:
            srs = gpkg.read_spatial_ref(conn, gpkg_path, int(rows[0][0]))
            if gpkg.is_geographic(srs.user_input) is False:
                return srs.user_input
    except sqlite3.Error as e:
        raise DataError(gpkg_path, f"cannot read GeoPackage metadata ({e})") from e
    finally:
        conn.close()
    raise DataError(gpkg_path, "cannot tell the logs' projected frame (no meta.projectedCoordSystem, no epsg)")


def merge_chains(nodes: Sequence[Hashable], edges: Iterable[tuple[Hashable, Hashable]]) -> list[list[Hashable]]:
    """Groups the nodes of a directed lane graph into maximal chains, as SLEDGE merges lanes and connectors.

    An edge u -> v is merged when u has exactly one successor and v exactly one predecessor (counting only
    edges between `nodes`); chains are the maximal paths of merged edges, so a chain stops wherever lanes
    fork or join. Every node is in exactly one chain; a closed loop is cut at its first node in `nodes`
    order. Chains come in the `nodes` order of their first node (loops last).
    """
    index = {n: i for i, n in enumerate(nodes)}
    succ: dict = {}
    pred: dict = {}
    for u, v in edges:
        if u in index and v in index and u != v:
            succ.setdefault(u, set()).add(v)
            pred.setdefault(v, set()).add(u)
    nxt = {}
    for u, vs in succ.items():
        if len(vs) == 1:
            (v,) = vs
            if len(pred[v]) == 1:
                nxt[u] = v
    has_prev = set(nxt.values())
    chains: list[list[Hashable]] = []
    seen: set = set()
    for first_pass in (True, False):
        for n in nodes:
            if n in seen or (first_pass and n in has_prev):
                continue
            chain = [n]
            seen.add(n)
            while chain[-1] in nxt and nxt[chain[-1]] not in seen:
                chain.append(nxt[chain[-1]])
                seen.add(chain[-1])
            chains.append(chain)
    return chains


def _fid_key(value) -> str | None:
    if value is None:
        return None
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    text = str(value).strip()
    return text or None


def _lane_graph_edges(conn: sqlite3.Connection) -> list[tuple] | None:
    """Edges (("lane", fid) -> ("connector", fid) -> ("lane", fid)) from `lane_connectors`, or None when the
    map lacks the table or its exit_lane_fid / entry_lane_fid columns."""
    cols = set(gpkg.table_columns(conn, "lane_connectors"))
    if not {"exit_lane_fid", "entry_lane_fid"} <= cols:
        return None
    fid_col = "fid" if "fid" in cols else "rowid"
    edges = []
    for fid, exit_lane, entry_lane in conn.execute(
        f"SELECT {fid_col}, exit_lane_fid, entry_lane_fid FROM lane_connectors"
    ):
        c = ("connector", _fid_key(fid))
        if _fid_key(exit_lane) is not None:
            edges.append((("lane", _fid_key(exit_lane)), c))
        if _fid_key(entry_lane) is not None:
            edges.append((c, ("lane", _fid_key(entry_lane))))
    return edges


def _concat_polylines(parts: list[np.ndarray], tol: float = 1e-3) -> np.ndarray:
    out = [parts[0]]
    for p in parts[1:]:
        out.append(p[1:] if np.linalg.norm(p[0] - out[-1][-1]) < tol else p)
    return np.concatenate(out)


def _layer_transform(gpkg_path, layer, crs: str, projection: str):
    """The transform from a layer's spatial reference to `crs` (undefined Cartesian: already in it)."""
    src = layer.srs.user_input
    if layer.srs.srs_id == -1 or (layer.srs.organization.upper() == "NONE" and layer.srs.srs_id <= 0):
        src = crs  # "undefined Cartesian": taken to be already in the logs' frame
    elif layer.srs.srs_id == 0:
        src = "EPSG:4326"  # "undefined geographic": WGS84 lon/lat
    try:
        return gpkg.make_transform(src, crs, backend=projection)
    except ValueError as e:
        raise DataError(gpkg_path, f"cannot project layer '{layer.name}' to {str(crs)[:60]} ({e})") from e


# The map layers whose polygons make the drivable surface, and the area kind of each.
AREA_LAYERS = (("lanes_polygons", "lane"), ("lane_groups_polygons", "lane"), ("intersections", "junction"),
               ("generic_drivable_areas", "other"), ("carpark_areas", "other"))


@dataclasses.dataclass(frozen=True)
class MapAreas:
    """Drivable areas of one map in the logs' frame: `areas` tuple of `Area`, `bounds` f64[K, 4], `layers`
    the `AREA_LAYERS` the map has (a map without any has no geometry; its samples say so in the statistics)."""

    areas: tuple
    bounds: np.ndarray
    layers: tuple[str, ...]

    def crop(self, box: np.ndarray) -> tuple:
        b = self.bounds
        keep = (b[:, 0] <= box[2]) & (b[:, 2] >= box[0]) & (b[:, 1] <= box[3]) & (b[:, 3] >= box[1])
        return tuple(self.areas[i] for i in np.flatnonzero(keep))


def _polygon_rings(kind: str, parts: tuple[np.ndarray, ...]) -> list[tuple[np.ndarray, list[np.ndarray]]]:
    """(exterior, holes) of a Polygon's rings (first = exterior) or a MultiPolygon's (a ring inside a larger
    ring of the same geometry is that ring's hole)."""
    rings = [p for p in parts if len(p) >= 3]
    if kind == "Polygon":
        return [(rings[0], rings[1:])] if rings else []
    from shapely.geometry import Point, Polygon
    polys = [Polygon(r) for r in rings]
    area = [abs(p.area) for p in polys]
    owner = {}
    for i, p in enumerate(polys):
        if p.is_empty:
            continue
        pt = Point(rings[i][0]) if not p.is_valid else p.representative_point()
        outer = [j for j, q in enumerate(polys) if j != i and area[j] > area[i] and q.is_valid and q.contains(pt)]
        if outer:
            owner[i] = min(outer, key=lambda j: area[j])
    return [(rings[i], [rings[k] for k, o in owner.items() if o == i]) for i in range(len(rings)) if i not in owner]


def read_map_areas(gpkg_path: str | os.PathLike, crs: str, projection: str = "auto") -> MapAreas:
    """The drivable surface of a nuPlan map (`AREA_LAYERS` that it has), projected to `crs`, as `Area`s."""
    conn = gpkg.open_sqlite(gpkg_path, "GeoPackage")
    try:
        present = {r[0] for r in _query(conn, gpkg_path, "SELECT table_name FROM gpkg_geometry_columns")}
        layers = [(name, kind) for name, kind in AREA_LAYERS if name in present]
        read = [(gpkg.read_layer(gpkg_path, name, (), conn=conn), kind) for name, kind in layers]
    finally:
        conn.close()
    areas, bounds = [], []
    for layer, kind in read:
        transform = _layer_transform(gpkg_path, layer, crs, projection)
        for k, g in enumerate(layer.geometries):
            if g.is_empty:
                continue
            if g.kind not in ("Polygon", "MultiPolygon"):
                raise DataError(gpkg_path, f"layer '{layer.name}' fid {layer.fids[k]} is a {g.kind}, not a polygon")
            for ext, holes in _polygon_rings(g.kind, g.parts):
                proj = []
                for r in [ext, *holes]:
                    x, y = transform(r[:, 0], r[:, 1])
                    proj.append(np.stack([x, y], -1))
                if not all(np.isfinite(p).all() for p in proj):
                    raise DataError(gpkg_path, f"projecting '{layer.name}' to {str(crs)[:60]} gave non-finite points")
                areas.append(Area(AREA_KIND_ID[kind], proj[0], tuple(proj[1:])))
                bounds.append([*proj[0].min(0), *proj[0].max(0)])
    return MapAreas(tuple(areas), np.asarray(bounds, np.float64).reshape(-1, 4), tuple(n for n, _ in layers))


def read_map_lanes(
    gpkg_path: str | os.PathLike, crs: str, projection: str = "auto", merge: bool = True
) -> MapLanes:
    """Reads every `baseline_paths` centreline of a nuPlan map and projects it to `crs`.

    Args:
      gpkg_path: the map GeoPackage.
      crs: target frame ('EPSG:32611', a proj string or WKT), usually from `map_crs`.
      projection: "auto" (pyproj if installed, else built-in), "pyproj" or "builtin" (WGS84/UTM only).
      merge: concatenate lanes and connectors into maximal unbranched chains (`merge_chains`, SLEDGE's
        rule), using `baseline_paths.lane_fid` / `lane_connector_fid` and `lane_connectors.exit_lane_fid` /
        `entry_lane_fid`. Maps without those columns are read unmerged.
    """
    conn = gpkg.open_sqlite(gpkg_path, "GeoPackage")
    try:
        have = set(gpkg.table_columns(conn, BASELINE_LAYER))
        cols = tuple(c for c in ("lane_fid", "lane_connector_fid") if c in have)
        layer = gpkg.read_layer(gpkg_path, BASELINE_LAYER, cols, conn=conn)
        try:
            edges = _lane_graph_edges(conn) if merge and len(cols) == 2 else None
        except sqlite3.Error as e:
            raise DataError(gpkg_path, f"cannot read lane_connectors ({e})") from e
    finally:
        conn.close()
    transform = _layer_transform(gpkg_path, layer, crs, projection)

    pieces: list[np.ndarray] = []
    keys: list = []  # graph node of each piece (None: not part of the lane graph)
    lane_col = layer.columns.get("lane_fid")
    conn_col = layer.columns.get("lane_connector_fid")
    for k, g in enumerate(layer.geometries):
        if g.kind not in ("LineString", "MultiLineString"):
            raise DataError(gpkg_path, f"layer '{BASELINE_LAYER}' fid {layer.fids[k]} is a {g.kind}, not a line")
        parts = [p for p in g.parts if len(p) >= 2]
        lane_key = _fid_key(lane_col[k]) if lane_col is not None else None
        conn_key = _fid_key(conn_col[k]) if conn_col is not None else None
        if conn_key is not None:
            key = ("connector", conn_key)
        elif lane_key is not None:
            key = ("lane", lane_key)
        else:
            key = ("row", int(layer.fids[k]))
        for j, part in enumerate(parts):
            pieces.append(part)
            keys.append(key if len(parts) == 1 else (*key, "part", j))
    if pieces:
        flat = np.concatenate(pieces)
        x, y = transform(flat[:, 0], flat[:, 1])
        flat = np.stack([x, y], axis=-1)
        if not np.isfinite(flat).all():
            raise DataError(gpkg_path, f"projecting '{BASELINE_LAYER}' to {str(crs)[:60]} gave non-finite points")
        pieces = np.split(flat, np.cumsum([len(p) for p in pieces])[:-1])

    connectors = {key[1]: pieces[i] for i, key in enumerate(keys) if len(key) == 2 and key[0] == "connector"}
    if edges is not None and len(set(keys)) == len(keys):
        chains = merge_chains(keys, edges)
        at = {key: i for i, key in enumerate(keys)}
        lanes = [_concat_polylines([pieces[at[key]] for key in chain]) for chain in chains]
        connector = [all(key[0] == "connector" for key in chain) for chain in chains]
    else:
        lanes = list(pieces)
        connector = [key[0] == "connector" for key in keys]
    bounds = np.array([[*p.min(0), *p.max(0)] for p in lanes], np.float64).reshape(-1, 4)
    return MapLanes(os.fspath(gpkg_path), str(crs), tuple(lanes), np.array(connector, bool), bounds, connectors)


# ---------------------------------------------------------------------------------------------------------
# Public entry points
# ---------------------------------------------------------------------------------------------------------


def _read_log(
    db_path: Path,
    maps_root,
    map_margin: float | None,
    projection: str,
    max_step_error: float,
    merge_lanes: bool,
    map_cache: dict,
) -> RawLog:
    conn = gpkg.open_sqlite(db_path, "nuPlan log database")
    try:
        _check_tables(conn, db_path)
        header = _read_header(conn, db_path)
        frames = _read_frames(conn, db_path, max_step_error)
        tracks = _read_vehicles(conn, db_path, frames)
        lights = _read_lights(conn, db_path, frames)
    finally:
        conn.close()

    try:
        map_name, map_path = find_map(maps_root, header.map_version, header.location)
    except FileNotFoundError as e:
        raise DataError(db_path, str(e)) from e
    key = (os.fspath(map_path.resolve()), frames.epsg, projection, merge_lanes)
    if key not in map_cache:
        crs = map_crs(map_path, map_name, frames.epsg)
        map_cache[key] = (read_map_lanes(map_path, crs, projection, merge=merge_lanes),
                          read_map_areas(map_path, crs, projection))
    lanes_map: MapLanes = map_cache[key][0]
    areas_map: MapAreas = map_cache[key][1]

    ego_heading = wrap_angle(quaternion_yaw(*frames.ego[:, 2:6].T))
    ego_xy = rear_axle_to_center(frames.ego[:, :2], ego_heading)
    num_frames = len(frames.tokens)
    agent_xy = np.concatenate([ego_xy[:, None], tracks.xy], axis=1)
    agent_heading = np.concatenate([ego_heading[:, None], tracks.heading], axis=1)
    agent_valid = np.concatenate([np.ones((num_frames, 1), bool), tracks.valid], axis=1)
    agent_size = np.concatenate([np.array([[EGO_LENGTH, EGO_WIDTH]], np.float32), tracks.size], axis=0)
    agent_type = np.concatenate([[TYPE_ID["ego"]], vehicle_type(tracks.size[:, 0])]).astype(np.int32)

    if map_margin is None:
        lanes = lanes_map.lanes
        areas = areas_map.areas
    else:
        pts = agent_xy[agent_valid]
        box = np.array([*(pts.min(0) - map_margin), *(pts.max(0) + map_margin)])
        lanes = lanes_map.crop(box)
        areas = areas_map.crop(box)
        if not lanes:
            raise DataError(
                db_path,
                f"no lane of {lanes_map.path} ({len(lanes_map.lanes)} lanes, projected to {lanes_map.crs[:40]}) "
                f"lies within {map_margin} m of the log: map or projection mismatch",
            )
    return RawLog(
        name=db_path.stem,
        location=map_name,
        timestamps=(frames.timestamps_us - frames.timestamps_us[0]) * 1e-6,
        agent_ids=("ego",) + tracks.ids,
        agent_xy=agent_xy,
        agent_heading=agent_heading,
        agent_valid=agent_valid,
        agent_size=agent_size,
        agent_type=agent_type,
        lanes=tuple(lanes),
        ego_index=0,
        areas=tuple(areas),
        areas_outline="drivable_area",  # lanes, connectors, intersections, car parks, generic drivable: the road
        signals=_signals(lights, lanes_map),
    )


# nuPlan's traffic-light status -> WOSAC lane states (`gpd_jax.geometry.SIGNAL_STATES`)
LIGHT_STATUS = {"red": "stop", "yellow": "caution", "green": "go", "unknown": "unknown"}


def _read_lights(conn: sqlite3.Connection, path, frames) -> dict[str, np.ndarray]:
    """Lane connector id (str) -> i8[F] its light's state in each kept frame (0 where not recorded), from the
    `traffic_light_status` table (empty where the log has none)."""
    have = {r[0] for r in _query(conn, path, "SELECT name FROM sqlite_master WHERE type IN ('table', 'view')")}
    if "traffic_light_status" not in have:
        return {}
    at = {bytes(t) if isinstance(t, (bytes, memoryview)) else t: f for f, t in enumerate(frames.tokens)}
    out: dict[str, np.ndarray] = {}
    rows = _query(conn, path, "SELECT lidar_pc_token, lane_connector_id, status FROM traffic_light_status")
    for pc, lc, status in rows:
        f = at.get(bytes(pc) if isinstance(pc, (bytes, memoryview)) else pc)
        if f is None or lc is None:
            continue
        state = SIGNAL_STATE_ID[LIGHT_STATUS.get(str(status).lower(), "unknown")]
        out.setdefault(str(_fid_key(lc)), np.zeros(len(frames.tokens), np.int8))[f] = state
    return out


def _signals(lights: dict[str, np.ndarray], lanes_map) -> RawSignals | None:
    """The lights of lane connectors the map has: stop point at the connector's start, its centreline as the
    lane; None without any."""
    ids = [c for c in sorted(lights) if c in lanes_map.connectors]
    if not ids:
        return None
    lanes = tuple(lanes_map.connectors[c] for c in ids)
    return RawSignals(stop=np.stack([ln[0] for ln in lanes]), lane=lanes,
                      state=np.stack([lights[c] for c in ids], -1))


def read_log(
    db_path: str | os.PathLike,
    maps_root: str | os.PathLike,
    *,
    map_margin: float | None = 200.0,
    projection: str = "auto",
    max_step_error: float = 0.03,
    merge_lanes: bool = True,
    map_cache: dict | None = None,
) -> RawLog:
    """Reads one nuPlan log database and its map into a 10 Hz `RawLog` (see the module docstring).

    Args:
      db_path: the log's `.db` file.
      maps_root: the nuPlan maps folder (the one holding nuplan-maps-v1.0.json; see `find_map`).
      map_margin: keep the lanes within this many metres of the log's boxes (None: the whole map).
      projection: "auto", "pyproj" or "builtin" (see `gpd_jax.data.sources.gpkg.make_transform`).
      max_step_error: largest tolerated deviation (s) of a kept-frame step from 0.1 s.
      merge_lanes: join lanes and lane connectors into unbranched chains as SLEDGE does (see
        `read_map_lanes`); False keeps one polyline per `baseline_paths` row.
      map_cache: maps already read and projected (filled here), shared by the logs of one process.
    Returns:
      RawLog with F kept frames and N = 1 + vehicles tracks; track 0 is the ego (`ego_index == 0`).
    Raises:
      DataError: naming the `.db` or `.gpkg` file and the reason.
    """
    return _read_log(Path(db_path), maps_root, map_margin, projection, max_step_error, merge_lanes,
                     {} if map_cache is None else map_cache)


def find_logs(db_path_or_dir: str | os.PathLike) -> list[Path]:
    """The `.db` file itself, or every `*.db` under a directory (recursively, sorted)."""
    p = Path(db_path_or_dir)
    if p.is_dir():
        found = sorted(q for q in p.rglob("*.db") if q.is_file())
        if not found:
            raise DataError(p, "no *.db files in this directory")
        return found
    if p.is_file():
        return [p]
    raise DataError(p, "no such file or directory")


def iter_logs(
    db_path_or_dir: str | os.PathLike,
    maps_root: str | os.PathLike,
    *,
    skip_bad: bool = False,
    errors: list | None = None,
    map_margin: float | None = 200.0,
    projection: str = "auto",
    max_step_error: float = 0.03,
    merge_lanes: bool = True,
) -> Iterator[RawLog]:
    """Yields a `RawLog` per nuPlan log (a `.db` file, or every `*.db` under a directory, sorted).

    Each map is read and projected once and shared by the logs that use it.

    Args:
      skip_bad: False: the first bad file raises its `DataError`. True: bad files are skipped, logged as
        warnings and appended to `errors` (so `len(errors)` is the skip count).
      errors: list receiving the `DataError`s of skipped files (only with skip_bad).
      map_margin, projection, max_step_error, merge_lanes: as in `read_log`.
    """
    map_cache: dict = {}
    for path in find_logs(db_path_or_dir):
        try:
            raw = _read_log(path, maps_root, map_margin, projection, max_step_error, merge_lanes, map_cache)
        except DataError as e:
            if not skip_bad:
                raise
            log.warning("skipping nuPlan log: %s", e)
            if errors is not None:
                errors.append(e)
            continue
        yield raw


# ----------------------------------------------------------------------------------------------- build
@dataclasses.dataclass(frozen=True)
class NuplanJob:
    """One log of a nuPlan build: its shard index, its file and the split it goes to."""

    index: int
    path: str
    split: str
    num_samples: int = 1  # what run_jobs counts on its progress bar: logs


_WORKER_MAPS: dict = {}  # the maps a worker process has read and projected, reused by its next logs (a few kept)
_WORKER_MAPS_KEPT = 2


def run_nuplan_job(job: NuplanJob, out_dir: str, maps_root: str, sample_cfg: preprocess.SampleConfig, seed: int,
                   max_per_log: int | None) -> dict:
    """Reads the job's log, cuts its windows and writes one shard. Returns the job summary; a bad log gives
    `error` (its reason) and no job marker (it is skipped, counted, and read again by a resumed build)."""
    t1 = time.time()
    if len(_WORKER_MAPS) > _WORKER_MAPS_KEPT:
        _WORKER_MAPS.clear()
    try:
        raw = read_log(job.path, maps_root, map_cache=_WORKER_MAPS)
    except DataError as e:
        log.warning("skipping nuPlan log: %s", e)
        return {"index": job.index, "split": job.split, "num_samples": 0, "requested": 1, "stats": {},
                "rejections": [], "error": str(e)}
    stats: Counter = Counter()
    pairs = list(preprocess.iter_samples(raw, sample_cfg, num=max_per_log, seed=seed, stats=stats))
    if pairs:
        arrays = store.stack_samples([q[1] for q in pairs], preprocess.sample_spec(sample_cfg))
        existing = existing_shard(out_dir, job.index)
        if existing:
            shutil.rmtree(existing)
        store.write_shard(out_dir, job.split, job.index, arrays, [q[0] for q in pairs], [raw.location] * len(pairs),
                          extra={"source": "nuplan", "log": raw.name})
    r = {"index": job.index, "split": job.split, "location": raw.location, "num_samples": len(pairs),
         "requested": 1, "wall_s": time.time() - t1, "stats": dict(stats), "rejections": []}
    store.atomic_write_json(job_marker(out_dir, job.index), r)
    return r


class _Bound:
    """Picklable job runner bound to its settings."""

    def __init__(self, out_dir, maps_root, sample_cfg, seed, max_per_log):
        self.args = (out_dir, maps_root, sample_cfg, seed, max_per_log)

    def __call__(self, job):
        return run_nuplan_job(job, *self.args)


def build_nuplan(out_dir: str, db: str, maps_root: str, seed: int = 0, split: str | None = None,
                 max_per_log: int | None = None, sample_cfg: preprocess.SampleConfig | None = None,
                 workers: int = 1, executor=None) -> dict:
    """Builds (or resumes) a dataset from nuPlan logs (`find_logs`), one job and shard per log, on `executor`
    (`gpd_jax.data.executors`; default: `workers` local processes, each reading a map once for its logs)."""
    t0 = time.time()
    sample_cfg = sample_cfg or preprocess.SampleConfig()
    check_count("max_per_log", max_per_log, allow_none=True)
    check_count("workers", workers)
    # inputs first: a wrong --db or --maps must not leave settings behind that a corrected retry trips over
    paths = find_logs(db)
    if not os.path.isdir(maps_root):
        raise DataError(maps_root, "maps root not found (the folder holding nuplan-maps-v1.0.json)")
    os.makedirs(out_dir, exist_ok=True)
    store.clean_temporaries(out_dir)
    settings = {"source": "nuplan", "db": os.path.abspath(db), "maps": os.path.abspath(maps_root), "seed": seed,
                "split": split, "max_per_log": max_per_log, "sample_config": dataclasses.asdict(sample_cfg)}
    check_settings(out_dir, settings)
    # Splits by map: read only the log headers first, then the logs one per job (flat memory).
    if split:
        split_of = {p: split for p in paths}
    else:
        key = {}
        for p in paths:
            try:
                key[p] = read_log_header(p).map_version.removesuffix(".gpkg")
            except Exception:  # noqa: BLE001 - a bad file is reported (and skipped) when it is read
                pass
        by_loc = assign_splits(list(key.values()), seed)
        split_of = {p: by_loc.get(key.get(p), "train") for p in paths}
    jobs = [NuplanJob(i, os.path.abspath(str(p)), split_of[p]) for i, p in enumerate(paths)]
    results = run_jobs(jobs, _Bound(out_dir, os.path.abspath(str(maps_root)), sample_cfg, seed, max_per_log),
                       out_dir, workers, "nuplan build", executor)
    errors = [r["error"] for r in results if r.get("error")]
    results = [r for r in results if not r.get("error")]
    if errors:
        log.warning("skipped %d bad nuPlan logs: %s", len(errors), "; ".join(errors[:5]))
        results.append({"index": -1, "num_samples": 0, "requested": 0, "stats": {"logs_skipped_bad": len(errors)},
                        "rejections": errors})
    return finish(out_dir, settings, results, time.time() - t0)
