"""Writes small nuPlan-schema fixture files (a log `.db` and a map `.gpkg`) at test time.

The tables and column names/types follow nuPlan's log database and map GeoPackage
(`shared/reference/sledge_nuplan.md` §3-4); tokens are 8-byte blobs. Nothing here is copied from nuPlan.

The scene: a straight two-lane road heading 30 degrees (north-east of east) near the Las Vegas strip in UTM
zone 11N, a lane connector turning left off lane 1 into lane 2, and a far-away lane 5 km east. Over 3 s at 20 Hz (60 lidar_pc
rows) the ego drives along lane 0 at 10 m/s; three vehicles and one pedestrian are boxed:

  car   4.6 x 1.9 m ahead in lane 0, in every frame;
  truck 8.0 x 2.5 m in lane 1, in 20 Hz frames 10..40 only;
  bus   12 x 2.6 m in lane 1, the `track` row has NULL length/width (boxes say 12 x 2.6);
  a vehicle seen only in odd 20 Hz frames (dropped by 20 -> 10 Hz subsampling);
  a pedestrian walking beside the road (must be ignored).
"""

from __future__ import annotations

import dataclasses
import json
import math
import sqlite3
import struct
from pathlib import Path

import numpy as np

from gpd_jax.data.sources import gpkg as gp

MAP_NAME = "us-nv-las-vegas-strip"
MAP_VERSION_DIR = "9.15.1915"
LOCATION = "las_vegas"
UTM_EPSG = 32611
ORIGIN = np.array([664450.0, 3998216.0])  # UTM 11N, near (-115.1728, 36.1147)
ROAD_HEADING = math.radians(30.0)
DIRECTION = np.array([math.cos(ROAD_HEADING), math.sin(ROAD_HEADING)])
NORMAL = np.array([-math.sin(ROAD_HEADING), math.cos(ROAD_HEADING)])
LANE_WIDTH = 3.5
NUM_PC = 60  # 3 s at 20 Hz
T0_US = 1_620_000_000_000_000
PC_STEP_US = 50_000
EGO_SPEED = 10.0
EGO_S0 = 10.0

CATEGORIES = ("vehicle", "bicycle", "pedestrian", "traffic_cone", "barrier", "czone_sign", "generic_object")


def _connect(path: Path) -> sqlite3.Connection:
    conn = sqlite3.connect(path)
    conn.execute("PRAGMA synchronous = OFF")  # fixture files: no fsync per statement, keeps tests quick
    conn.execute("PRAGMA journal_mode = MEMORY")
    return conn


def token(kind: int, i: int) -> bytes:
    """An 8-byte token, distinct per table (`kind`) and row (`i`)."""
    return struct.pack(">II", kind, i)


def road_point(s: float, lateral: float = 0.0) -> np.ndarray:
    return ORIGIN + s * DIRECTION + lateral * NORMAL


def lane_polylines_utm() -> dict[str, np.ndarray]:
    """The map's centrelines in UTM 11N: name -> f64[P, 2]."""
    s = np.linspace(0.0, 200.0, 41)
    lane0 = ORIGIN + s[:, None] * DIRECTION + 0.0 * NORMAL
    lane1 = ORIGIN + s[:, None] * DIRECTION + LANE_WIDTH * NORMAL
    # A connector: quarter circle of radius 20 m turning left from the end of lane 1.
    a = np.linspace(0.0, math.pi / 2, 12)
    start = road_point(200.0, LANE_WIDTH)
    centre = start + 20.0 * NORMAL
    conn = centre + 20.0 * (np.sin(a)[:, None] * DIRECTION - np.cos(a)[:, None] * NORMAL)
    lane2 = conn[-1] + np.linspace(0.0, 50.0, 11)[:, None] * NORMAL  # continues the connector
    far = ORIGIN + np.array([5000.0, 0.0]) + np.linspace(0, 50, 6)[:, None] * DIRECTION
    return {"lane0": lane0, "lane1": lane1, "connector": conn, "lane2": lane2, "far": far}


def _quad(s0: float, s1: float, l0: float, l1: float) -> np.ndarray:
    """Closed ring (UTM 11N) of the road-aligned rectangle s in [s0, s1], lateral in [l0, l1]."""
    return np.stack([road_point(s0, l0), road_point(s1, l0), road_point(s1, l1), road_point(s0, l1),
                     road_point(s0, l0)])


def intersection_ring_utm() -> np.ndarray:
    """The `intersections` polygon: where lane 1 turns left into lane 2 (s in [200, 222], lateral in
    [-1.75, 25])."""
    return _quad(200.0, 222.0, -1.75, LANE_WIDTH + 21.5)


def layby_ring_utm() -> np.ndarray:
    """A `generic_drivable_areas` lay-by right of lane 0 (s in [40, 70], lateral in [-8, -1.75])."""
    return _quad(40.0, 70.0, -8.0, -1.75)


def merged_polylines_utm() -> dict[str, np.ndarray]:
    """The centrelines as SLEDGE-style chains: lane1 -> connector -> lane2 is one polyline."""
    u = lane_polylines_utm()
    chain = np.concatenate([u["lane1"], u["connector"][1:], u["lane2"][1:]])
    return {"lane0": u["lane0"], "chain": chain, "far": u["far"]}


# ---------------------------------------------------------------------------------------------------------
# Log database
# ---------------------------------------------------------------------------------------------------------

LOG_DDL = {
    "log": """CREATE TABLE log (token BLOB NOT NULL, vehicle_name VARCHAR(64), date VARCHAR(64),
        timestamp INTEGER, logfile VARCHAR(64), location VARCHAR(64), map_version VARCHAR(64),
        PRIMARY KEY (token))""",
    "lidar": """CREATE TABLE lidar (token BLOB NOT NULL, log_token BLOB NOT NULL, channel VARCHAR(64),
        model VARCHAR(64), translation BLOB, rotation BLOB, PRIMARY KEY (token))""",
    "lidar_pc": """CREATE TABLE lidar_pc (token BLOB NOT NULL, next_token BLOB, prev_token BLOB,
        ego_pose_token BLOB NOT NULL, lidar_token BLOB NOT NULL, scene_token BLOB, filename VARCHAR(128),
        timestamp INTEGER, PRIMARY KEY (token))""",
    "ego_pose": """CREATE TABLE ego_pose (token BLOB NOT NULL, timestamp INTEGER, x FLOAT, y FLOAT, z FLOAT,
        qw FLOAT, qx FLOAT, qy FLOAT, qz FLOAT, vx FLOAT, vy FLOAT, vz FLOAT, acceleration_x FLOAT,
        acceleration_y FLOAT, acceleration_z FLOAT, angular_rate_x FLOAT, angular_rate_y FLOAT,
        angular_rate_z FLOAT, epsg INTEGER, log_token BLOB NOT NULL, PRIMARY KEY (token))""",
    "lidar_box": """CREATE TABLE lidar_box (token BLOB NOT NULL, lidar_pc_token BLOB NOT NULL,
        track_token BLOB NOT NULL, next_token BLOB, prev_token BLOB, x FLOAT, y FLOAT, z FLOAT, width FLOAT,
        length FLOAT, height FLOAT, vx FLOAT, vy FLOAT, vz FLOAT, yaw FLOAT, confidence FLOAT,
        PRIMARY KEY (token))""",
    "track": """CREATE TABLE track (token BLOB NOT NULL, category_token BLOB NOT NULL, width FLOAT,
        length FLOAT, height FLOAT, PRIMARY KEY (token))""",
    "category": """CREATE TABLE category (token BLOB NOT NULL, name VARCHAR(64), description TEXT,
        PRIMARY KEY (token))""",
    "scene": """CREATE TABLE scene (token BLOB NOT NULL, log_token BLOB NOT NULL, name TEXT,
        goal_ego_pose_token BLOB, roadblock_ids TEXT, PRIMARY KEY (token))""",
    "scenario_tag": """CREATE TABLE scenario_tag (token BLOB NOT NULL, lidar_pc_token BLOB NOT NULL,
        type TEXT, agent_track_token BLOB, PRIMARY KEY (token))""",
    "traffic_light_status": """CREATE TABLE traffic_light_status (token BLOB NOT NULL,
        lidar_pc_token BLOB NOT NULL, lane_connector_id INTEGER, status VARCHAR(8), PRIMARY KEY (token))""",
}

# Token kinds.
K_LOG, K_LIDAR, K_PC, K_EGO, K_BOX, K_TRACK, K_CAT, K_SCENE, K_TL = range(1, 10)


@dataclasses.dataclass(frozen=True)
class Track:
    """A fixture box track: which 20 Hz frames it is in, where, and its size."""

    name: str
    category: str
    length: float
    width: float
    track_row_size: bool  # write length/width into the `track` row (else NULL)
    frames: tuple[int, ...]

    def pose(self, i: int) -> tuple[np.ndarray, float]:
        t = i * PC_STEP_US * 1e-6
        if self.name == "car":
            return road_point(EGO_S0 + 25.0 + 8.0 * t, 0.0), ROAD_HEADING
        if self.name == "truck":
            return road_point(EGO_S0 - 5.0 + 12.0 * t, LANE_WIDTH), ROAD_HEADING
        if self.name == "bus":
            # Heading just below -pi + 2 pi to check wrapping: stored as 2 pi + (heading) in the table.
            return road_point(EGO_S0 + 40.0 + 6.0 * t, LANE_WIDTH), ROAD_HEADING + 2 * math.pi
        if self.name == "ghost":
            return road_point(60.0, LANE_WIDTH), ROAD_HEADING
        return road_point(EGO_S0 + 5.0 + 1.4 * t, -4.0), ROAD_HEADING + math.pi / 2


TRACKS = (
    Track("car", "vehicle", 4.6, 1.9, True, tuple(range(NUM_PC))),
    Track("truck", "vehicle", 8.0, 2.5, True, tuple(range(10, 41))),
    Track("bus", "vehicle", 12.0, 2.6, False, tuple(range(NUM_PC))),
    Track("ghost", "vehicle", 4.5, 1.8, True, tuple(range(1, NUM_PC, 2))),
    Track("pedestrian", "pedestrian", 0.7, 0.7, True, tuple(range(NUM_PC))),
)


def ego_rear_axle(i: int) -> tuple[np.ndarray, float]:
    """Ego rear-axle position and heading at 20 Hz frame i."""
    t = i * PC_STEP_US * 1e-6
    return road_point(EGO_S0 + EGO_SPEED * t, 0.0), ROAD_HEADING


def track_token(n: int) -> bytes:
    return token(K_TRACK, n)


def write_log_db(
    path: str | Path,
    *,
    map_version: str = MAP_NAME,
    location: str = LOCATION,
    epsg: int | None = UTM_EPSG,
    num_pc: int = NUM_PC,
    drop_tables: tuple[str, ...] = (),
    nan_ego_frame: int | None = None,
    nan_box: bool = False,
    skip_pc: tuple[int, ...] = (),
    lights: dict | None = None,
) -> Path:
    """Writes a nuPlan log database (see the module docstring). Returns its path.

    Args:
      drop_tables: tables left out (to make a bad file).
      nan_ego_frame: 20 Hz frame whose ego_pose x is NaN.
      nan_box: make one car box's x NaN.
      skip_pc: 20 Hz frames left out of lidar_pc (to make a timing gap).
      lights: lane connector id -> function of the 20 Hz frame giving its traffic-light status ('red', 'green',
        ...; None: no row), written to `traffic_light_status`.
    """
    path = Path(path)
    path.unlink(missing_ok=True)
    conn = _connect(path)
    for name, ddl in LOG_DDL.items():
        if name not in drop_tables:
            conn.execute(ddl)
    ins = lambda table, row: (  # noqa: E731
        conn.execute(f"INSERT INTO {table} VALUES ({','.join('?' * len(row))})", row)
        if table not in drop_tables
        else None
    )
    log_tok = token(K_LOG, 0)
    ins("log", (log_tok, "veh-35", "2021.05.12", T0_US, path.stem, location, map_version))
    ins("lidar", (token(K_LIDAR, 0), log_tok, "MergedPointCloud", "merged", None, None))
    ins("lidar", (token(K_LIDAR, 1), log_tok, "LidarTop", "top", None, None))  # no lidar_pc rows of its own
    for c, name in enumerate(CATEGORIES):
        ins("category", (token(K_CAT, c), name, f"{name}."))
    ins("scene", (token(K_SCENE, 0), log_tok, "scene-0000", token(K_EGO, 2 * (num_pc - 1)), "1 2 3"))

    frames = [i for i in range(num_pc) if i not in skip_pc]
    # lidar_pc rows are inserted in a scrambled order: readers must sort by timestamp.
    for i in sorted(frames, key=lambda i: (i * 7919) % num_pc):
        pos = frames.index(i)
        prev_tok = token(K_PC, frames[pos - 1]) if pos > 0 else None
        next_tok = token(K_PC, frames[pos + 1]) if pos + 1 < len(frames) else None
        ins(
            "lidar_pc",
            (token(K_PC, i), next_tok, prev_tok, token(K_EGO, 2 * i), token(K_LIDAR, 0), token(K_SCENE, 0),
             f"pc_{i}.pcd", T0_US + i * PC_STEP_US + (i % 3)),
        )
    for lc, status_of in (lights or {}).items():
        for i in frames:
            if status_of(i) is not None:
                ins("traffic_light_status", (token(K_TL, i * 100 + int(lc)), token(K_PC, i), int(lc), status_of(i)))
    # ego_pose has more rows than lidar_pc (odd tokens are poses no lidar_pc points at) and its own timestamps.
    for j in range(2 * num_pc):
        i = j / 2
        xy, h = ego_rear_axle(i)
        if j % 2 == 1:
            xy = xy + 1000.0  # a pose nobody references; reading it would be a bug
        x = float("nan") if (nan_ego_frame is not None and j == 2 * nan_ego_frame) else xy[0]
        ins(
            "ego_pose",
            (token(K_EGO, j), T0_US + int(i * PC_STEP_US) + 333, x, xy[1], 0.0, math.cos(h / 2), 0.0, 0.0,
             math.sin(h / 2), EGO_SPEED, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0, epsg, log_tok),
        )
    cat_tok = {name: token(K_CAT, c) for c, name in enumerate(CATEGORIES)}
    box = 0
    for n, tr in enumerate(TRACKS):
        size = (tr.width, tr.length) if tr.track_row_size else (None, None)
        ins("track", (track_token(n), cat_tok[tr.category], *size, 1.5))
        for i in tr.frames:
            if i not in frames:
                continue
            xy, h = tr.pose(i)
            x = float("nan") if (nan_box and tr.name == "car" and i == 20) else xy[0]
            ins(
                "lidar_box",
                (token(K_BOX, box), token(K_PC, i), track_token(n), None, None, x, xy[1], 0.5, tr.width,
                 tr.length, 1.5, 0.0, 0.0, 0.0, h, 0.9),
            )
            box += 1
    # A low-confidence duplicate box of the car in frame 0, far off: the confident one must win.
    xy, h = TRACKS[0].pose(0)
    ins("lidar_box", (token(K_BOX, box), token(K_PC, 0), track_token(0), None, None, xy[0] + 50, xy[1], 0.5,
                      1.9, 4.6, 1.5, 0.0, 0.0, 0.0, h, 0.1))
    conn.commit()
    conn.close()
    return path


# ---------------------------------------------------------------------------------------------------------
# Map GeoPackage
# ---------------------------------------------------------------------------------------------------------


def wkb_linestring(xy: np.ndarray, *, little: bool = True, z: bool = False) -> bytes:
    e = "<" if little else ">"
    pts = np.asarray(xy, np.float64)
    if z:
        pts = np.concatenate([pts, np.full((len(pts), 1), 601.5)], axis=1)
    code = 1002 if z else 2
    return struct.pack(e + "BII", int(little), code, len(pts)) + pts.astype(e + "f8").tobytes()


def wkb_multilinestring(parts: list[np.ndarray], *, little: bool = True) -> bytes:
    e = "<" if little else ">"
    body = b"".join(wkb_linestring(p, little=not little) for p in parts)  # members in the other byte order
    return struct.pack(e + "BII", int(little), 5, len(parts)) + body


def wkb_polygon(ring: np.ndarray, *, little: bool = True) -> bytes:
    e = "<" if little else ">"
    ring = np.asarray(ring, np.float64)
    return struct.pack(e + "BIII", int(little), 3, 1, len(ring)) + ring.astype(e + "f8").tobytes()


def gp_blob(wkb: bytes, srs_id: int, *, little: bool = True, envelope: int = 1, xy: np.ndarray | None = None) -> bytes:
    """GeoPackage binary: header (magic, version, flags, srs_id, envelope) + WKB."""
    e = "<" if little else ">"
    flags = int(little) | (envelope << 1)
    head = b"GP" + bytes([0, flags]) + struct.pack(e + "i", srs_id)
    if envelope:
        lo, hi = (xy.min(0), xy.max(0)) if xy is not None else (np.zeros(2), np.zeros(2))
        env = [lo[0], hi[0], lo[1], hi[1]] + [0.0, 0.0] * (envelope >= 2) + [0.0, 0.0] * (envelope == 4)
        head += struct.pack(e + "d" * len(env), *env)
    return head + wkb


SRS_ROWS = {
    4326: ("WGS 84 geodetic", 4326, "EPSG", 4326,
           'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563,AUTHORITY["EPSG","7030"]],'
           'AUTHORITY["EPSG","6326"]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433],'
           'AUTHORITY["EPSG","4326"]]'),
}


def _utm_srs_row(code: int) -> tuple:
    zone = code - 32600
    wkt = (
        f'PROJCS["WGS 84 / UTM zone {zone}N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,'
        f'298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],'
        f'PROJECTION["Transverse_Mercator"],PARAMETER["central_meridian",{6 * zone - 183}],'
        f'PARAMETER["scale_factor",0.9996],PARAMETER["false_easting",500000],UNIT["metre",1],'
        f'AUTHORITY["EPSG","{code}"]]'
    )
    return (f"WGS 84 / UTM zone {zone}N", code, "EPSG", code, wkt)


def project_from_utm11(xy: np.ndarray, srs: int) -> np.ndarray:
    """UTM 11N points f64[P, 2] -> the map's storage SRS (4326 lon/lat or another UTM north zone)."""
    if srs == UTM_EPSG:
        return np.asarray(xy, np.float64)
    lon, lat = gp.utm_to_lonlat(xy[:, 0], xy[:, 1], 11)
    if srs == 4326:
        return np.stack([lon, lat], axis=-1)
    x, y = gp.lonlat_to_utm(lon, lat, srs - 32600)
    return np.stack([x, y], axis=-1)


def write_map_gpkg(
    path: str | Path,
    *,
    srs: int = UTM_EPSG,
    meta: bool = True,
    little: bool = True,
    envelope: int = 1,
    multi: bool = False,
    with_z: bool = False,
    bad_blob: bool = False,
    nan_point: bool = False,
    layers: tuple[str, ...] = ("baseline_paths", "lanes_polygons", "lane_connectors", "intersections",
                               "generic_drivable_areas"),
) -> Path:
    """Writes a nuPlan-style map GeoPackage with the fixture's lanes stored in `srs`. Returns its path.

    Args:
      srs: 32611 (the logs' own UTM zone), 4326 (WGS84 lon/lat) or another UTM north zone (e.g. 32612).
      meta: write the `meta` table with projectedCoordSystem = epsg:32611.
      little, envelope: byte order of the blobs and their envelope kind (0-4).
      multi: store lane1 and the far lane as one two-part MultiLineString.
      with_z: store the lanes as LineString Z.
      bad_blob: corrupt the connector's blob.
      nan_point: put a NaN coordinate in lane0.
      layers: which geometry layers to create (leave out baseline_paths for a "missing layer" file).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.unlink(missing_ok=True)
    conn = _connect(path)
    conn.execute("PRAGMA application_id = 1196444487")  # 'GPKG'
    conn.execute("PRAGMA user_version = 10200")
    conn.execute(
        """CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT NOT NULL, srs_id INTEGER NOT NULL PRIMARY KEY,
        organization TEXT NOT NULL, organization_coordsys_id INTEGER NOT NULL, definition TEXT NOT NULL,
        description TEXT)"""
    )
    conn.execute(
        """CREATE TABLE gpkg_contents (table_name TEXT NOT NULL PRIMARY KEY, data_type TEXT NOT NULL,
        identifier TEXT UNIQUE, description TEXT DEFAULT '', last_change DATETIME NOT NULL DEFAULT
        (strftime('%Y-%m-%dT%H:%M:%fZ','now')), min_x DOUBLE, min_y DOUBLE, max_x DOUBLE, max_y DOUBLE,
        srs_id INTEGER, CONSTRAINT fk_gc_r_srs_id FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys(srs_id))"""
    )
    conn.execute(
        """CREATE TABLE gpkg_geometry_columns (table_name TEXT NOT NULL, column_name TEXT NOT NULL,
        geometry_type_name TEXT NOT NULL, srs_id INTEGER NOT NULL, z TINYINT NOT NULL, m TINYINT NOT NULL,
        CONSTRAINT pk_geom_cols PRIMARY KEY (table_name, column_name),
        CONSTRAINT fk_gc_tn FOREIGN KEY (table_name) REFERENCES gpkg_contents(table_name),
        CONSTRAINT fk_gc_srs FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys (srs_id))"""
    )
    srs_rows = [
        ("Undefined cartesian SRS", -1, "NONE", -1, "undefined", None),
        ("Undefined geographic SRS", 0, "NONE", 0, "undefined", None),
        (*SRS_ROWS[4326], None),
    ]
    if srs != 4326:
        srs_rows.append((*_utm_srs_row(srs), None))
    conn.executemany("INSERT INTO gpkg_spatial_ref_sys VALUES (?,?,?,?,?,?)", srs_rows)

    if meta:
        conn.execute("CREATE TABLE meta (fid INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, key TEXT, value TEXT)")
        conn.executemany(
            "INSERT INTO meta (key, value) VALUES (?, ?)",
            [("geographicCoordSystem", "epsg:4326"), ("projectedCoordSystem", f"epsg:{UTM_EPSG}")],
        )
        conn.execute("INSERT INTO gpkg_contents (table_name, data_type, identifier) VALUES ('meta', 'attributes', 'meta')")

    utm = lane_polylines_utm()
    stored = {k: project_from_utm11(v, srs) for k, v in utm.items()}
    if nan_point:
        stored["lane0"] = stored["lane0"].copy()
        stored["lane0"][3, 0] = np.nan
    allpts = np.concatenate(list(stored.values()))
    bbox = (*np.nanmin(allpts, 0), *np.nanmax(allpts, 0))

    def blob(xy: np.ndarray) -> bytes:
        return gp_blob(wkb_linestring(xy, little=little, z=with_z), srs, little=little, envelope=envelope, xy=xy)

    def register(table: str, gtype: str) -> None:
        conn.execute(
            "INSERT INTO gpkg_contents (table_name, data_type, identifier, min_x, min_y, max_x, max_y, srs_id) "
            "VALUES (?, 'features', ?, ?, ?, ?, ?, ?)",
            (table, table, *bbox, srs),
        )
        conn.execute("INSERT INTO gpkg_geometry_columns VALUES (?, 'geom', ?, ?, ?, 0)", (table, gtype, srs, int(with_z)))

    if "lanes_polygons" in layers:
        conn.execute(
            """CREATE TABLE lanes_polygons (fid INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, geom POLYGON,
            lane_fid TEXT, lane_group_fid INTEGER, lane_index INTEGER, left_boundary_fid INTEGER,
            right_boundary_fid INTEGER, speed_limit_mps REAL)"""
        )
        register("lanes_polygons", "POLYGON")
        for fid, name in ((1, "lane0"), (2, "lane1"), (4, "far"), (6, "lane2")):
            c = utm[name]
            ring = np.concatenate([c - 1.75 * NORMAL, (c + 1.75 * NORMAL)[::-1], (c - 1.75 * NORMAL)[:1]])
            ring = project_from_utm11(ring, srs)
            wkb = wkb_polygon(ring, little=little)
            conn.execute(
                "INSERT INTO lanes_polygons VALUES (?, ?, ?, 1, ?, NULL, NULL, 13.4)",
                (fid, gp_blob(wkb, srs, little=little, envelope=envelope, xy=ring), str(fid), fid - 1),
            )
    for table, rings in (("intersections", [intersection_ring_utm()]),
                         ("generic_drivable_areas", [layby_ring_utm()])):
        if table not in layers:
            continue
        conn.execute(f"CREATE TABLE {table} (fid INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, geom POLYGON)")
        register(table, "POLYGON")
        for fid, ring in enumerate(rings, 1):
            ring = project_from_utm11(ring, srs)
            conn.execute(f"INSERT INTO {table} VALUES (?, ?)",
                         (fid, gp_blob(wkb_polygon(ring, little=little), srs, little=little, envelope=envelope,
                                       xy=ring)))
    if "lane_connectors" in layers:
        conn.execute(
            """CREATE TABLE lane_connectors (fid INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, geom LINESTRING,
            exit_lane_fid INTEGER, entry_lane_fid INTEGER, lane_group_connector_fid INTEGER,
            speed_limit_mps REAL, traffic_light_stop_line_fids TEXT)"""
        )
        register("lane_connectors", "LINESTRING")
        conn.execute("INSERT INTO lane_connectors VALUES (3, ?, 2, 6, 1, 8.0, '')", (blob(stored["connector"]),))
    if "baseline_paths" in layers:
        conn.execute(
            """CREATE TABLE baseline_paths (fid INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, geom LINESTRING,
            lane_fid INTEGER, lane_connector_fid INTEGER)"""
        )
        register("baseline_paths", "LINESTRING")
        rows = [(1, blob(stored["lane0"]), 1, None)]
        if multi:
            parts = [stored["lane1"], stored["far"]]
            wkb = wkb_multilinestring(parts, little=little)
            rows.append((2, gp_blob(wkb, srs, little=little, envelope=envelope, xy=np.concatenate(parts)), 2, None))
        else:
            rows.append((2, blob(stored["lane1"]), 2, None))
            rows.append((4, blob(stored["far"]), 4, None))
        conn_blob = blob(stored["connector"])
        if bad_blob:
            conn_blob = conn_blob[:-13]  # truncated WKB
        rows.append((3, conn_blob, None, 3))
        rows.append((6, blob(stored["lane2"]), 6, None))
        rows.append((5, None, None, None))  # a row without geometry is skipped
        conn.executemany("INSERT INTO baseline_paths VALUES (?, ?, ?, ?)", rows)
    conn.commit()
    conn.close()
    return path


def write_maps_root(root: str | Path, *, layout: str = "json", **gpkg_kwargs) -> Path:
    """Writes a nuPlan maps folder with the fixture map. Returns the map file.

    layout: "json" (nuplan-maps-v1.0.json + <name>/<version>/map.gpkg, plus a decoy older version),
      "versions" (<name>/<version>/map.gpkg without the json), "flat" (<name>.gpkg).
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    if layout == "json":
        (root / "nuplan-maps-v1.0.json").write_text(
            json.dumps({MAP_NAME: {"version": MAP_VERSION_DIR, "layers": {}}, "us-ma-boston": {"version": "9.12.1817"}})
        )
        decoy = root / MAP_NAME / "9.99.1" / "map.gpkg"
        decoy.parent.mkdir(parents=True, exist_ok=True)
        decoy.write_bytes(b"not the map the json names")
        return write_map_gpkg(root / MAP_NAME / MAP_VERSION_DIR / "map.gpkg", **gpkg_kwargs)
    if layout == "versions":
        old = write_map_gpkg(root / MAP_NAME / "9.2.100" / "map.gpkg", srs=4326)
        old.write_bytes(b"an older version: must not be chosen")
        return write_map_gpkg(root / MAP_NAME / "9.15.1915" / "map.gpkg", **gpkg_kwargs)
    if layout == "flat":
        return write_map_gpkg(root / f"{MAP_NAME}.gpkg", **gpkg_kwargs)
    raise ValueError(layout)
