"""Minimal GeoPackage reading with the standard library's sqlite3, and the map projections nuPlan needs.

A GeoPackage (OGC 12-128r18) is an SQLite file. Each vector layer is a table listed in
`gpkg_geometry_columns (table_name, column_name, geometry_type_name, srs_id, z, m)`, whose SRS is a row of
`gpkg_spatial_ref_sys (srs_name, srs_id, organization, organization_coordsys_id, definition, description)`.
Each geometry cell is a "GeoPackage binary" blob:

  bytes 0-1  b"GP"
  byte  2    version (0 for version 1)
  byte  3    flags: bit 0 byte order of the header (1 = little endian), bits 1-3 envelope kind
             (0: none, 1: xy = 32 B, 2: xyz = 48 B, 3: xym = 48 B, 4: xyzm = 64 B), bit 4 empty geometry,
             bit 5 extended (non-standard) geometry type
  bytes 4-7  srs_id (int32)
  envelope   doubles, size from the flags
  then       a WKB geometry (its own byte order byte per (sub)geometry)

WKB types handled: Point, LineString, Polygon, MultiPoint, MultiLineString, MultiPolygon and
GeometryCollection, in 2D, Z, M and ZM, written as ISO codes (1002, 2002, 3002, ...) or with the EWKB high
flag bits (0x80000000 Z, 0x40000000 M, 0x20000000 embedded SRID). Only x and y are returned.

Projection: `make_transform(src, dst)` maps x, y arrays between two coordinate systems. It uses pyproj when
it is installed; otherwise a built-in exact transverse Mercator (Krüger series to sixth order in n, with a
Newton solve for the inverse; sub-millimetre inside a UTM zone and a few degrees beyond it) covers what
nuPlan maps use: WGS84 lon/lat (EPSG:4326) and WGS84 UTM zones (EPSG:326zz north, 327zz south).

Every failure raises `DataError` naming the file and the reason.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import sqlite3
import struct
from pathlib import Path
from typing import Callable

import numpy as np

from gpd_jax.data.errors import DataError

# ---------------------------------------------------------------------------------------------------------
# Geometry blobs
# ---------------------------------------------------------------------------------------------------------

_ENVELOPE_BYTES = {0: 0, 1: 32, 2: 48, 3: 48, 4: 64}
_WKB_NAMES = {
    1: "Point",
    2: "LineString",
    3: "Polygon",
    4: "MultiPoint",
    5: "MultiLineString",
    6: "MultiPolygon",
    7: "GeometryCollection",
}


class GeometryError(ValueError):
    """A malformed geometry blob (turned into `DataError` with the file name by the layer readers)."""


@dataclasses.dataclass(frozen=True)
class Geometry:
    """One parsed geometry.

    Attributes:
      kind: the WKB type name ("LineString", "MultiLineString", ...).
      parts: tuple of f64[P, 2] xy arrays: the points of a Point/MultiPoint (one part each), the line of a
        LineString, each line of a MultiLineString, each ring of a (Multi)Polygon, the parts of the members
        of a GeometryCollection, in order. Empty for an empty geometry.
      srs_id: the srs_id written in the GeoPackage header (None for bare WKB).
    """

    kind: str
    parts: tuple[np.ndarray, ...]
    srs_id: int | None = None

    @property
    def is_empty(self) -> bool:
        return not self.parts


def parse_gpkg_blob(blob: bytes) -> Geometry:
    """Parses a GeoPackage binary geometry (header + WKB). Raises `GeometryError` when malformed."""
    if not isinstance(blob, (bytes, bytearray, memoryview)):
        raise GeometryError(f"geometry is {type(blob).__name__}, not a blob")
    blob = bytes(blob)
    if len(blob) < 8 or blob[:2] != b"GP":
        raise GeometryError("geometry blob does not start with the GeoPackage magic 'GP'")
    flags = blob[3]
    if flags & 0b1100_0000:
        raise GeometryError(f"reserved flag bits set in GeoPackage header (flags={flags:#04x})")
    endian = "<" if flags & 1 else ">"
    envelope_kind = (flags >> 1) & 0b111
    if envelope_kind not in _ENVELOPE_BYTES:
        raise GeometryError(f"invalid envelope indicator {envelope_kind} in GeoPackage header")
    (srs_id,) = struct.unpack(endian + "i", blob[4:8])
    start = 8 + _ENVELOPE_BYTES[envelope_kind]
    if len(blob) < start:
        raise GeometryError("geometry blob truncated inside the envelope")
    if flags & 0b1_0000 and len(blob) == start:
        return Geometry("Empty", (), srs_id)
    geometry = parse_wkb(blob[start:])
    return dataclasses.replace(geometry, srs_id=srs_id)


def parse_wkb(buf: bytes) -> Geometry:
    """Parses a WKB (ISO or EWKB) geometry; returns its xy parts. Raises `GeometryError` when malformed."""
    reader = _WkbReader(bytes(buf))
    kind, parts = reader.geometry(depth=0)
    if reader.pos != len(reader.buf):
        raise GeometryError(f"{len(reader.buf) - reader.pos} trailing bytes after the WKB geometry")
    return Geometry(kind, tuple(parts))


class _WkbReader:
    def __init__(self, buf: bytes):
        self.buf = buf
        self.pos = 0

    def _take(self, n: int) -> bytes:
        if self.pos + n > len(self.buf):
            raise GeometryError("WKB truncated")
        out = self.buf[self.pos : self.pos + n]
        self.pos += n
        return out

    def _uint32(self, endian: str) -> int:
        return struct.unpack(endian + "I", self._take(4))[0]

    def _points(self, endian: str, count: int, dims: int) -> np.ndarray:
        if count > (len(self.buf) - self.pos) // (8 * dims):
            raise GeometryError(f"WKB truncated: {count} points announced, fewer present")
        raw = np.frombuffer(self._take(8 * dims * count), dtype=np.dtype(endian + "f8"))
        return raw.reshape(count, dims)[:, :2].astype(np.float64)

    def geometry(self, depth: int) -> tuple[str, list[np.ndarray]]:
        if depth > 32:
            raise GeometryError("WKB nested too deeply")
        order = self._take(1)[0]
        if order not in (0, 1):
            raise GeometryError(f"invalid WKB byte-order byte {order}")
        endian = "<" if order == 1 else ">"
        code = self._uint32(endian)
        has_z = bool(code & 0x8000_0000)
        has_m = bool(code & 0x4000_0000)
        if code & 0x2000_0000:  # EWKB embedded SRID
            self._take(4)
        code &= 0x0FFF_FFFF
        family, base = divmod(code, 1000)
        if family > 3 or base not in _WKB_NAMES:
            raise GeometryError(f"unsupported WKB geometry type code {code}")
        has_z = has_z or family in (1, 3)
        has_m = has_m or family in (2, 3)
        dims = 2 + has_z + has_m
        kind = _WKB_NAMES[base]
        if base == 1:
            pt = self._points(endian, 1, dims)
            return kind, ([] if np.isnan(pt).all() else [pt])
        if base == 2:
            n = self._uint32(endian)
            return kind, ([self._points(endian, n, dims)] if n else [])
        if base == 3:
            rings = [self._points(endian, self._uint32(endian), dims) for _ in range(self._uint32(endian))]
            return kind, [r for r in rings if len(r)]
        parts: list[np.ndarray] = []
        for _ in range(self._uint32(endian)):
            sub_kind, sub_parts = self.geometry(depth + 1)
            expected = {4: "Point", 5: "LineString", 6: "Polygon"}.get(base)
            if expected is not None and sub_kind != expected:
                raise GeometryError(f"{kind} contains a {sub_kind}")
            parts.extend(sub_parts)
        return kind, parts


# ---------------------------------------------------------------------------------------------------------
# GeoPackage files
# ---------------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SpatialRef:
    """A row of `gpkg_spatial_ref_sys`."""

    srs_id: int
    organization: str
    organization_coordsys_id: int
    definition: str

    @property
    def user_input(self) -> str:
        """The best description to hand to a projection library ("EPSG:4326" or the WKT definition)."""
        if self.organization.upper() == "EPSG" and self.organization_coordsys_id > 0:
            return f"EPSG:{self.organization_coordsys_id}"
        return self.definition


@dataclasses.dataclass(frozen=True)
class Layer:
    """The geometries of one vector layer.

    Attributes:
      name: table name.
      fids: i64[R] primary keys of the rows that have a non-empty geometry.
      geometries: R parsed geometries, in fid order.
      columns: other requested attribute columns, name -> tuple of R values.
      srs: the layer's spatial reference.
    """

    name: str
    fids: np.ndarray
    geometries: tuple[Geometry, ...]
    columns: dict
    srs: SpatialRef


def open_sqlite(path: str | os.PathLike, what: str = "SQLite database") -> sqlite3.Connection:
    """Opens an existing SQLite file read-only; raises `DataError` if it is missing or not a database."""
    p = Path(path)
    if not p.is_file():
        raise DataError(p, f"{what} not found")
    try:
        conn = sqlite3.connect(p.resolve().as_uri() + "?mode=ro", uri=True)
        conn.execute("SELECT count(*) FROM sqlite_master").fetchone()
    except sqlite3.Error as e:
        raise DataError(p, f"not a readable {what} ({e})") from e
    return conn


def table_columns(conn: sqlite3.Connection, table: str) -> list[str]:
    """Column names of `table` (empty when the table does not exist)."""
    return [row[1] for row in conn.execute(f'PRAGMA table_info("{table}")')]


def read_spatial_ref(conn: sqlite3.Connection, path: str | os.PathLike, srs_id: int) -> SpatialRef:
    """Reads one `gpkg_spatial_ref_sys` row."""
    try:
        row = conn.execute(
            "SELECT srs_id, organization, organization_coordsys_id, definition FROM gpkg_spatial_ref_sys "
            "WHERE srs_id = ?",
            (srs_id,),
        ).fetchone()
    except sqlite3.Error as e:
        raise DataError(path, f"cannot read gpkg_spatial_ref_sys ({e})") from e
    if row is None:
        raise DataError(path, f"srs_id {srs_id} is not in gpkg_spatial_ref_sys")
    return SpatialRef(int(row[0]), str(row[1] or ""), int(row[2] if row[2] is not None else -1), str(row[3] or ""))


def read_layer(
    path: str | os.PathLike,
    layer: str,
    columns: tuple[str, ...] = (),
    conn: sqlite3.Connection | None = None,
) -> Layer:
    """Reads every geometry of a GeoPackage vector layer (and optional attribute columns).

    Rows with a NULL or empty geometry are skipped. Raises `DataError` naming `path` for a file that is not a
    GeoPackage, a missing layer, a malformed blob (with its fid) or a non-finite coordinate.
    """
    own = conn is None
    conn = open_sqlite(path, "GeoPackage") if own else conn
    try:
        try:
            row = conn.execute(
                "SELECT column_name, srs_id FROM gpkg_geometry_columns WHERE table_name = ?", (layer,)
            ).fetchone()
        except sqlite3.Error as e:
            raise DataError(path, f"not a GeoPackage: cannot read gpkg_geometry_columns ({e})") from e
        if row is None:
            raise DataError(path, f"layer '{layer}' not found in gpkg_geometry_columns")
        geom_col, srs_id = str(row[0]), int(row[1])
        srs = read_spatial_ref(conn, path, srs_id)
        have = table_columns(conn, layer)
        if not have:
            raise DataError(path, f"layer '{layer}' is listed but its table is missing")
        if geom_col not in have:
            raise DataError(path, f"layer '{layer}' has no geometry column '{geom_col}'")
        missing = [c for c in columns if c not in have]
        if missing:
            raise DataError(path, f"layer '{layer}' lacks column(s) {missing}")
        fid_col = "fid" if "fid" in have else "rowid"
        extra = "".join(f', "{c}"' for c in columns)
        try:
            rows = conn.execute(
                f'SELECT {fid_col}, "{geom_col}"{extra} FROM "{layer}" ORDER BY {fid_col}'
            ).fetchall()
        except sqlite3.Error as e:
            raise DataError(path, f"cannot read layer '{layer}' ({e})") from e
    finally:
        if own:
            conn.close()

    fids, geometries, values = [], [], [[] for _ in columns]
    for r in rows:
        if r[1] is None:
            continue
        try:
            g = parse_gpkg_blob(r[1])
        except GeometryError as e:
            raise DataError(path, f"layer '{layer}' fid {r[0]}: bad geometry blob ({e})") from e
        if g.is_empty:
            continue
        if not all(np.isfinite(p).all() for p in g.parts):
            raise DataError(path, f"layer '{layer}' fid {r[0]}: non-finite coordinate in geometry")
        fids.append(int(r[0]))
        geometries.append(g)
        for v, x in zip(values, r[2:]):
            v.append(x)
    return Layer(
        name=layer,
        fids=np.asarray(fids, np.int64),
        geometries=tuple(geometries),
        columns={c: tuple(v) for c, v in zip(columns, values)},
        srs=srs,
    )


def read_meta(conn: sqlite3.Connection) -> dict[str, str]:
    """The nuPlan map `meta` key/value table (e.g. projectedCoordSystem -> 'epsg:32611'); {} if absent."""
    cols = table_columns(conn, "meta")
    if "key" not in cols or "value" not in cols:
        return {}
    try:
        return {str(k): str(v) for k, v in conn.execute('SELECT "key", "value" FROM meta') if k is not None}
    except sqlite3.Error:
        return {}


# ---------------------------------------------------------------------------------------------------------
# Coordinate systems
# ---------------------------------------------------------------------------------------------------------

Transform = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]

# WGS84 ellipsoid.
_WGS84_A = 6378137.0
_WGS84_F = 1.0 / 298.257223563


@dataclasses.dataclass(frozen=True)
class _BuiltinCrs:
    """A coordinate system the built-in projection handles: WGS84 lon/lat (zone None) or a WGS84 UTM zone."""

    zone: int | None
    south: bool = False


def parse_crs(spec: str | int) -> _BuiltinCrs | None:
    """Recognizes WGS84 lon/lat and WGS84 UTM from an EPSG code, 'EPSG:n', a proj string or an OGC WKT.

    Returns None when the description is not one of those (pyproj is then required).
    """
    if isinstance(spec, (int, np.integer)):
        code = int(spec)
    else:
        s = str(spec).strip()
        m = re.fullmatch(r"(?i)(?:epsg:|urn:ogc:def:crs:epsg::)?\s*(\d+)", s)
        if m:
            code = int(m.group(1))
        else:
            low = s.lower()
            if low.startswith("+proj") or " +proj=" in low:
                if re.search(r"\+proj=(longlat|latlong|lonlat)\b", low) and re.search(r"wgs84", low):
                    return _BuiltinCrs(None)
                zm = re.search(r"\+zone=(\d+)", low)
                if "+proj=utm" in low and zm and ("wgs84" in low):
                    return _BuiltinCrs(int(zm.group(1)), "+south" in low)
                return None
            ids = re.findall(r'(?:AUTHORITY|ID)\[\s*"EPSG"\s*,\s*"?(\d+)"?\s*\]', s, flags=re.I)
            if not ids:
                return None
            code = int(ids[-1])  # the outermost (last) identifier names the whole CRS
    if code in (4326, 4979):
        return _BuiltinCrs(None)
    if 32601 <= code <= 32660:
        return _BuiltinCrs(code - 32600, False)
    if 32701 <= code <= 32760:
        return _BuiltinCrs(code - 32700, True)
    return None


def _kruger_coefficients(n: float) -> tuple[list[float], list[float], float]:
    n2, n3, n4, n5, n6 = n**2, n**3, n**4, n**5, n**6
    alpha = [
        n / 2 - 2 * n2 / 3 + 5 * n3 / 16 + 41 * n4 / 180 - 127 * n5 / 288 + 7891 * n6 / 37800,
        13 * n2 / 48 - 3 * n3 / 5 + 557 * n4 / 1440 + 281 * n5 / 630 - 1983433 * n6 / 1935360,
        61 * n3 / 240 - 103 * n4 / 140 + 15061 * n5 / 26880 + 167603 * n6 / 181440,
        49561 * n4 / 161280 - 179 * n5 / 168 + 6601661 * n6 / 7257600,
        34729 * n5 / 80640 - 3418889 * n6 / 1995840,
        212378941 * n6 / 319334400,
    ]
    beta = [
        n / 2 - 2 * n2 / 3 + 37 * n3 / 96 - n4 / 360 - 81 * n5 / 512 + 96199 * n6 / 604800,
        n2 / 48 + n3 / 15 - 437 * n4 / 1440 + 46 * n5 / 105 - 1118711 * n6 / 3870720,
        17 * n3 / 480 - 37 * n4 / 840 - 209 * n5 / 4480 + 5569 * n6 / 90720,
        4397 * n4 / 161280 - 11 * n5 / 504 - 830251 * n6 / 7257600,
        4583 * n5 / 161280 - 108847 * n6 / 3991680,
        20648693 * n6 / 638668800,
    ]
    rect = 1 / (1 + n) * (1 + n2 / 4 + n4 / 64 + n6 / 256)
    return alpha, beta, rect


_N = _WGS84_F / (2 - _WGS84_F)
_E = math.sqrt(_WGS84_F * (2 - _WGS84_F))
_ALPHA, _BETA, _RECT = _kruger_coefficients(_N)
_UTM_K0 = 0.9996


def _utm_constants(zone: int, south: bool) -> tuple[float, float, float]:
    """(central meridian in radians, false easting, false northing)."""
    return math.radians(6 * zone - 183), 500000.0, (10000000.0 if south else 0.0)


def lonlat_to_utm(lon: np.ndarray, lat: np.ndarray, zone: int, south: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """WGS84 degrees -> UTM easting/northing (m), f64[...] each; exact TM via the Krüger series."""
    lam0, fe, fn = _utm_constants(zone, south)
    phi = np.radians(np.asarray(lat, np.float64))
    lam = np.radians(np.asarray(lon, np.float64)) - lam0
    s = np.sin(phi)
    tau_c = np.sinh(np.arctanh(s) - _E * np.arctanh(_E * s))  # tan of the conformal latitude
    xi_p = np.arctan2(tau_c, np.cos(lam))
    eta_p = np.arctanh(np.sin(lam) / np.sqrt(1 + tau_c**2))
    xi, eta = xi_p.copy(), eta_p.copy()
    for j, a in enumerate(_ALPHA, start=1):
        xi = xi + a * np.sin(2 * j * xi_p) * np.cosh(2 * j * eta_p)
        eta = eta + a * np.cos(2 * j * xi_p) * np.sinh(2 * j * eta_p)
    k = _UTM_K0 * _WGS84_A * _RECT
    return fe + k * eta, fn + k * xi


def utm_to_lonlat(x: np.ndarray, y: np.ndarray, zone: int, south: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """UTM easting/northing (m) -> WGS84 degrees (lon, lat), f64[...] each; inverse Krüger series + Newton."""
    lam0, fe, fn = _utm_constants(zone, south)
    k = _UTM_K0 * _WGS84_A * _RECT
    xi = (np.asarray(y, np.float64) - fn) / k
    eta = (np.asarray(x, np.float64) - fe) / k
    xi_p, eta_p = xi.copy(), eta.copy()
    for j, b in enumerate(_BETA, start=1):
        xi_p = xi_p - b * np.sin(2 * j * xi) * np.cosh(2 * j * eta)
        eta_p = eta_p - b * np.cos(2 * j * xi) * np.sinh(2 * j * eta)
    tau_p = np.sin(xi_p) / np.sqrt(np.sinh(eta_p) ** 2 + np.cos(xi_p) ** 2)  # tan of the conformal latitude
    lam = np.arctan2(np.sinh(eta_p), np.cos(xi_p))
    # Newton solve of tau' = tau*sqrt(1+sigma^2) - sigma*sqrt(1+tau^2), sigma = sinh(e*atanh(e*sin(phi))).
    e2 = _E**2
    tau = tau_p.copy()
    for _ in range(6):
        sigma = np.sinh(_E * np.arctanh(_E * tau / np.sqrt(1 + tau**2)))
        tau_i = tau * np.sqrt(1 + sigma**2) - sigma * np.sqrt(1 + tau**2)
        tau = tau + (tau_p - tau_i) / np.sqrt(1 + tau_i**2) * (1 + (1 - e2) * tau**2) / (
            (1 - e2) * np.sqrt(1 + tau**2)
        )
    return np.degrees(lam + lam0), np.degrees(np.arctan(tau))


def _builtin_transform(src: _BuiltinCrs, dst: _BuiltinCrs) -> Transform:
    def to_lonlat(x, y):
        return (x, y) if src.zone is None else utm_to_lonlat(x, y, src.zone, src.south)

    def from_lonlat(lon, lat):
        return (lon, lat) if dst.zone is None else lonlat_to_utm(lon, lat, dst.zone, dst.south)

    def transform(x, y):
        if src == dst:
            return np.asarray(x, np.float64), np.asarray(y, np.float64)
        return from_lonlat(*to_lonlat(np.asarray(x, np.float64), np.asarray(y, np.float64)))

    return transform


def have_pyproj() -> bool:
    try:
        import pyproj  # noqa: F401
    except ImportError:
        return False
    return True


def make_transform(src: str | int, dst: str | int, backend: str = "auto") -> Transform:
    """An (x, y) -> (x, y) map from coordinate system `src` to `dst` (lon/lat in degrees, x = lon).

    Args:
      src, dst: EPSG codes, 'EPSG:n' / 'epsg:n', proj strings or WKT.
      backend: "pyproj", "builtin" (WGS84 lon/lat and UTM only) or "auto" (pyproj if installed, else
        builtin).
    Raises:
      ValueError: the systems are not understood by the chosen backend.
    """
    if backend not in ("auto", "pyproj", "builtin"):
        raise ValueError(f"unknown projection backend {backend!r}")
    if backend == "pyproj" or (backend == "auto" and have_pyproj()):
        import pyproj

        try:
            crs_src = pyproj.CRS.from_user_input(src)
            crs_dst = pyproj.CRS.from_user_input(dst)
        except pyproj.exceptions.CRSError as e:
            raise ValueError(f"unknown coordinate system ({e})") from e
        if crs_src == crs_dst:
            return lambda x, y: (np.asarray(x, np.float64), np.asarray(y, np.float64))
        tf = pyproj.Transformer.from_crs(crs_src, crs_dst, always_xy=True)

        def transform(x, y):
            ox, oy = tf.transform(np.asarray(x, np.float64), np.asarray(y, np.float64))
            return np.asarray(ox, np.float64), np.asarray(oy, np.float64)

        return transform
    a, b = parse_crs(src), parse_crs(dst)
    if a is None or b is None:
        bad = src if a is None else dst
        raise ValueError(
            f"coordinate system {str(bad)[:80]!r} needs pyproj (built-in projection: WGS84 lon/lat and UTM only)"
        )
    return _builtin_transform(a, b)


def is_geographic(spec: str | int) -> bool | None:
    """True for a lon/lat system, False for a projected one, None when unknown (no pyproj, unrecognized)."""
    c = parse_crs(spec)
    if c is not None:
        return c.zone is None
    if have_pyproj():
        import pyproj

        try:
            return bool(pyproj.CRS.from_user_input(spec).is_geographic)
        except pyproj.exceptions.CRSError:
            return None
    return None
