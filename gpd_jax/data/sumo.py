"""SUMO data source: generate (or take) road networks, make demand, simulate, record -> `RawLog`.

One *job* = one network + one demand seed + one SUMO run. The pipeline of a job:

1. network: `netgenerate` (random / grid / spider layouts, 1-3 lanes, traffic lights or priority junctions,
   sizes, street lengths and netgenerate's random node perturbation all drawn from the job seed, so that no
   two seeds give the same roads: `NetSpec`; optionally curved streets, `NetSpec.bend`), a given `.net.xml[.gz]`,
   or one of the real OSM-derived networks shipped with SUMO (`real_networks`);
2. demand: `randomTrips.py --insertion-density` (vehicles per hour and km of lane, so that big and small
   networks get comparable traffic) with `departLane="best" departSpeed="max"`; each vehicle's type is drawn
   by us from a size mix (car, SUV, van, truck, bus) with the job's RNG, so the FCD needs no string columns;
   real traffic (`SimConfig` traffic options, on by default; `LEGACY_TRAFFIC` turns them off): road-side
   parking areas with parked vehicles, some of which leave during the recording (`plan_traffic`), pick-up /
   drop-off stops (`add_short_stops`) and heterogeneous drivers (`driver_types_xml`: a vTypeDistribution of
   Krauss / IDM / EIDM drivers per size class); generated networks may drive on the left (`netconvert
   --lefthand`) and have fixed-cycle traffic lights (`NetSpec.lefthand`, `NetSpec.tls_type`);
3. `sumo --step-length 0.1 --lanechange.duration 3` (continuous lane changes), FCD written as CSV from
   the C++ side every step (10 Hz), after a warm-up. This measured faster than recording through TraCI:
   on one generated network (270 simulated s, ~240 vehicles) trips + SUMO + FCD parsing took 2.8 s, the
   same simulation stepped through TraCI with subscriptions 5.6 s; it also needs no libsumo;
4. quality gate: runs with teleports (SUMO's jam resolution) or where more than `max_stopped_fraction` of
   recorded vehicle-frames stand still (gridlock; frames of vehicles at a planned stop, from SUMO's stop
   output, are not counted: parked cars are no jam) are rejected (`SumoRunRejected`), and the caller
   retries with lower demand and another seed;
5. conversion: SUMO reports the *front bumper* position and a *compass* angle (degrees, 0 = north,
   clockwise). heading = radians(90 - angle) (counter-clockwise from +x / east), box centre =
   front - length / 2 * (cos heading, sin heading).

Lane centrelines come from the network file (normal and internal junction lanes usable by passenger
cars), merged into chains the SLEDGE way: a lane-to-lane link is merged when the upstream lane has exactly
one successor and the downstream lane exactly one predecessor.
"""

from __future__ import annotations

import dataclasses
import gzip
import logging
import os
import re
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET

import numpy as np

from gpd_jax.data.errors import DataError
from gpd_jax.data.raw import RawLog
from gpd_jax.data.roadgeom import Area, lane_area
from gpd_jax.geometry import AREA_KIND_ID
from gpd_jax.scene import TYPE_ID

log = logging.getLogger(__name__)


def sumo_home() -> str:
    """The SUMO installation directory (SUMO_HOME, else the `eclipse-sumo` package)."""
    home = os.environ.get("SUMO_HOME")
    if home and os.path.isdir(os.path.join(home, "bin")):
        return home
    try:
        import sumo  # the eclipse-sumo wheel
    except ImportError as e:  # pragma: no cover - depends on the install
        raise RuntimeError("SUMO not found: pip install eclipse-sumo or set SUMO_HOME") from e
    return sumo.SUMO_HOME


def _bin(name: str) -> str:
    return os.path.join(sumo_home(), "bin", name)


# (name, length, width, probability, scene type, max speed m/s, accel, decel)
VEHICLE_MIX = (
    ("g_car", 4.6, 1.85, 0.55, "car", 50.0, 2.6, 4.5),
    ("g_suv", 5.1, 2.0, 0.17, "car", 50.0, 2.4, 4.5),
    ("g_van", 6.5, 2.1, 0.12, "van", 36.0, 2.0, 4.0),
    ("g_truck", 10.0, 2.5, 0.09, "truck", 30.0, 1.3, 4.0),
    ("g_bus", 12.0, 2.55, 0.07, "bus", 28.0, 1.2, 4.0),
)


class SumoRunRejected(RuntimeError):
    """A simulation whose traffic is not usable (teleports, gridlock, too few vehicles)."""


LAYOUTS = ("grid", "spider", "random")  # generated layouts; networks given as files are "real" or "given"


@dataclasses.dataclass(frozen=True)
class NetSpec:
    """How to generate one synthetic network (all drawn from a seed by `random_net_spec`).

    netgenerate ignores `--seed` for grid and spider layouts, so two specs with equal sizes would give the same
    network. Every spec therefore also carries seed-drawn shape parameters (junction counts per axis, street
    lengths per axis, arm and circle counts), `jitter` and `perturb`, so that two seeds never give the same roads
    (`gpd_jax.data.netgeom` checks it; node noise alone is not enough: two spiders with the same arm and circle
    counts and 10-20 m of node noise measured only ~4 m apart):

    * grid / spider: netgenerate's regular network is rewritten before netconvert builds it: every column and
      row gap of a grid (every ring gap and arm angle of a spider) is scaled by its own factor in
      [1 - jitter, 1 + jitter], then every node gets normal noise of `perturb` metres cut at 2 sigma, all drawn
      from `seed`;
    * random: netgenerate's own node perturbation (`--perturb-x/-y`, sigma `perturb`, cut at 2 sigma) on top
      of its seeded random network.
    """

    layout: str  # "grid" | "spider" | "random"
    lanes: int
    junction: str  # "traffic_light" | "priority" | "mixed" (priority + guessed traffic lights)
    speed: float
    seed: int
    size: int  # junctions along x (grid), arms (spider), iterations (random)
    spacing: float  # street length along x (grid), circle spacing (spider), min edge length (random)
    size2: int = 0  # junctions along y (grid), circles (spider)
    spacing2: float = 0.0  # street length along y (grid), max edge length (random)
    perturb: float = 0.0  # sigma in metres of the random node perturbation
    jitter: float = 0.0  # grid / spider: relative spread of the gaps between rows / columns / rings and arms
    connectivity: float = 0.95  # random: probability that a road continues at a node
    lefthand: bool = False  # left-hand traffic (`netconvert --lefthand`; the network's <net lefthand="true">)
    tls_type: str = "actuated"  # traffic-light programs: "actuated" (gap-based) or "static" (fixed cycles: queues)
    bend: float = 0.0  # curved streets: the largest sideways bulge of a street as a share of its length (0: straight)


BEND_RANGE = (0.08, 0.22)  # `NetSpec.bend` of a curved network, drawn uniformly


def random_net_spec(seed: int, layout: str | None = None, lefthand_share: float = 0.0,
                    static_tls_share: float = 0.0, curved_share: float = 0.0) -> NetSpec:
    """A network spec drawn from `seed` (the layout too, unless given: "grid", "spider" or "random").

    `lefthand_share` / `static_tls_share` / `curved_share`: probabilities that the network has left-hand
    traffic / fixed-cycle traffic lights / curved streets (`NetSpec.bend` drawn from `BEND_RANGE`), each drawn
    from a stream of its own (with all three 0 every spec is the one drawn before they existed)."""
    spec = _random_net_spec(seed, layout)
    rng = np.random.default_rng([seed, 19])
    u_left, u_tls = rng.uniform(size=2)
    u_curve, bend = np.random.default_rng([seed, 23]).uniform(size=2)
    return dataclasses.replace(spec, lefthand=bool(u_left < lefthand_share),
                               tls_type="static" if u_tls < static_tls_share else "actuated",
                               bend=float(BEND_RANGE[0] + (BEND_RANGE[1] - BEND_RANGE[0]) * bend)
                               if u_curve < curved_share else 0.0)


def _random_net_spec(seed: int, layout: str | None = None) -> NetSpec:
    rng = np.random.default_rng([seed, 7])
    drawn = LAYOUTS[int(rng.integers(3))]
    layout = drawn if layout is None else layout
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; expected one of {LAYOUTS}")
    lanes = int(rng.integers(1, 4))
    junction = ["traffic_light", "priority", "mixed"][int(rng.integers(3))]
    speed = float(rng.choice([11.11, 13.89, 16.67, 19.44]))
    seed31 = int(seed) % (2**31)
    if layout == "random":
        lo = float(rng.uniform(100, 160))
        return NetSpec(layout, lanes, junction, speed, seed31, int(rng.integers(30, 60)), lo,
                       spacing2=lo * float(rng.uniform(1.8, 2.6)), perturb=float(rng.uniform(0.03, 0.08)) * lo,
                       connectivity=float(rng.uniform(0.8, 0.97)))
    if layout == "grid":
        lx, ly = float(rng.uniform(120, 220)), float(rng.uniform(120, 220))
        return NetSpec(layout, lanes, junction, speed, seed31, int(rng.integers(3, 7)), lx,
                       size2=int(rng.integers(3, 7)), spacing2=ly, perturb=float(rng.uniform(0.05, 0.08)) * min(lx, ly),
                       jitter=float(rng.uniform(0.25, 0.4)))
    r = float(rng.uniform(90, 160))
    # 4-7 arms, 3-4 rings: smaller spiders (two rings of a pentagon) leave too little to vary
    return NetSpec(layout, lanes, junction, speed, seed31, int(rng.integers(4, 8)), r,
                   size2=int(rng.integers(3, 5)), perturb=float(rng.uniform(0.05, 0.08)) * r,
                   jitter=float(rng.uniform(0.3, 0.45)))


def generate_network(spec: NetSpec, out_path: str) -> str:
    """Runs netgenerate for `spec`, writing `out_path` (.net.xml, or .net.xml.gz compressed). Returns the path."""
    flag = {"random": "rand", "rand": "rand"}.get(spec.layout, spec.layout)
    jitter = flag in ("grid", "spider") and (spec.jitter > 0 or spec.perturb > 0)
    rewrite = jitter or spec.bend > 0  # netgenerate's plain files are edited, then netconvert builds the network
    if spec.tls_type not in ("actuated", "static"):
        raise ValueError(f"unknown tls_type {spec.tls_type!r}; expected 'actuated' or 'static'")
    common = ["--no-turnarounds", "true", "--junctions.join", "false", "--no-warnings", "true",
              "--tls.default-type", spec.tls_type] + (["--lefthand", "true"] if spec.lefthand else [])
    os.makedirs(os.path.dirname(os.path.abspath(out_path)), exist_ok=True)
    plain = tempfile.mkdtemp(prefix="gpd_net_", dir=os.path.dirname(os.path.abspath(out_path))) if rewrite else None
    args = [_bin("netgenerate"), f"--{flag}", "--seed", str(spec.seed), "-o",
            os.path.join(plain, "regular.net.xml") if rewrite else out_path,
            "--default.lanenumber", str(spec.lanes), "--default.speed", f"{spec.speed:.2f}", *common]
    if rewrite:
        args += ["--plain-output-prefix", os.path.join(plain, "p")]
    if spec.perturb > 0 and not jitter:
        s = spec.perturb
        args += ["--perturb-x", f"normc(0,{s:.2f},{-2 * s:.2f},{2 * s:.2f})",
                 "--perturb-y", f"normc(0,{s:.2f},{-2 * s:.2f},{2 * s:.2f})"]
    if spec.junction == "traffic_light":
        args += ["--default-junction-type", "traffic_light"]
    elif spec.junction == "priority":
        args += ["--default-junction-type", "priority"]
    else:
        args += ["--default-junction-type", "priority", "--tls.guess", "true"]
    if flag == "rand":
        args += ["--rand.iterations", str(spec.size), "--rand.min-distance", f"{spec.spacing:.1f}",
                 "--rand.min-angle", "60", "--rand.connectivity", f"{spec.connectivity:.3f}",
                 "--rand.max-distance", f"{(spec.spacing2 or spec.spacing * 2.2):.1f}",
                 "--rand.random-lanenumber", "true"]
    elif flag == "grid":
        ly = spec.spacing2 or spec.spacing
        args += ["--grid.x-number", str(spec.size), "--grid.y-number", str(spec.size2 or spec.size),
                 "--grid.x-length", f"{spec.spacing:.1f}", "--grid.y-length", f"{ly:.1f}",
                 "--grid.x-attach-length", f"{spec.spacing:.1f}", "--grid.y-attach-length", f"{ly:.1f}"]
    else:
        args += ["--spider.arm-number", str(spec.size), "--spider.circle-number", str(spec.size2 or 3),
                 "--spider.space-radius", f"{spec.spacing:.1f}", "--spider.omit-center", "true"]
    env = dict(os.environ, SUMO_HOME=sumo_home())  # else netgenerate warns that it cannot validate XML
    try:
        _run(args, what=f"netgenerate {spec}", env=env)
        if rewrite:
            nod, edg = os.path.join(plain, "p.nod.xml"), os.path.join(plain, "p.edg.xml")
            with open(nod) as f:
                text = f.read()
            if jitter:
                text = _jitter_nodes(text, spec)
                with open(nod, "w") as f:
                    f.write(text)
            if spec.bend > 0:
                with open(edg) as f:
                    edges = f.read()
                with open(edg, "w") as f:
                    f.write(_bend_edges(edges, text, spec))
            _run([_bin("netconvert"), "--node-files", nod, "--edge-files", edg,
                  "-o", out_path, *common] + (["--tls.guess", "true"] if spec.junction == "mixed" else []),
                 what=f"netconvert {spec}", env=env)
    finally:
        if plain:
            import shutil
            shutil.rmtree(plain, ignore_errors=True)
    return out_path


_NODE_ID = re.compile(r'<node [^>]*?\bid="([^"]+)"[^>]*?\bx="([-\d.]+)"[^>]*?\by="([-\d.]+)"')
_EDGE_ENDS = re.compile(r'<edge [^>]*?\bfrom="([^"]+)"[^>]*?\bto="([^"]+)"[^>]*?(/?>)')


def _bend_edges(edg_text: str, nod_text: str, spec: NetSpec, step_m: float = 4.0, min_len_m: float = 40.0) -> str:
    """netgenerate's plain edges with curved shapes (`NetSpec.bend`); deterministic in `spec.seed`.

    Each street (node pair; both directions share one centreline, reversed, so that a two-way road stays one road)
    longer than `min_len_m` is drawn as a one-sided bulge (`sin(pi s)`, 55 %), an S-bend (`0.6 sin(2 pi s)`, 30 %)
    or kept straight (15 %), with an amplitude of U(0.5, 1) * `spec.bend` * its length and a random side. A bulge
    of 0.22 x length bends a 150 m street to a 69 m radius at its middle and meets its junctions 35 degrees off
    the chord; an S-bend of a 200 m street at the same bend turns at a 47 m radius."""
    nodes = {m.group(1): np.array([float(m.group(2)), float(m.group(3))]) for m in _NODE_ID.finditer(nod_text)}
    rng = np.random.default_rng([spec.seed, 17])
    shapes: dict[tuple[str, str], np.ndarray | None] = {}
    out, k = [], 0
    for m in _EDGE_ENDS.finditer(edg_text):
        a, b = m.group(1), m.group(2)
        if a not in nodes or b not in nodes:
            raise RuntimeError(f"netgenerate's edge {a}->{b} names a node it did not write ({spec})")
        key = (a, b) if a <= b else (b, a)
        if key not in shapes:
            p, q = nodes[key[0]], nodes[key[1]]
            chord = float(np.linalg.norm(q - p))
            kind, amp, side = rng.uniform(), rng.uniform(0.5, 1.0), rng.choice([-1.0, 1.0])
            if chord < min_len_m or kind >= 0.85 or "shape=" in m.group(0):
                shapes[key] = None
            else:
                s = np.linspace(0.0, 1.0, max(8, int(np.ceil(chord / step_m)) + 1))
                wave = np.sin(np.pi * s) if kind < 0.55 else 0.6 * np.sin(2 * np.pi * s)
                d = (q - p) / chord
                normal = np.array([-d[1], d[0]])
                shapes[key] = p + s[:, None] * (q - p) + (side * amp * spec.bend * chord * wave)[:, None] * normal
        pts = shapes[key]
        if pts is None:
            continue
        pts = pts if (a, b) == key else pts[::-1]
        attr = ' shape="' + " ".join(f"{x:.2f},{y:.2f}" for x, y in pts) + '"'
        out += [edg_text[k:m.start(3)], attr]
        k = m.start(3)
    return "".join(out) + edg_text[k:]


_NODE_XY = re.compile(r'(<node [^>]*?\bx=")([-\d.]+)("[^>]*?\by=")([-\d.]+)(")')


def _jitter_nodes(nod_text: str, spec: NetSpec) -> str:
    """netgenerate's plain nodes of a regular grid / spider with the gaps and angles of `spec` made irregular
    (see `NetSpec`); deterministic in `spec.seed`."""
    rng = np.random.default_rng([spec.seed, 13])
    m = list(_NODE_XY.finditer(nod_text))
    xy = np.array([[float(a.group(2)), float(a.group(4))] for a in m])
    if len(xy) == 0:
        raise RuntimeError(f"netgenerate wrote no nodes for {spec}")
    j = spec.jitter

    def remap(v):  # sorted distinct coordinates -> the same count with gaps scaled by [1 - j, 1 + j]
        u = np.unique(np.round(v, 2))
        gaps = np.diff(u) * rng.uniform(1 - j, 1 + j, len(u) - 1)
        new = u[0] + np.concatenate([[0.0], np.cumsum(gaps)])
        return new[np.searchsorted(u, np.round(v, 2))]

    if spec.layout == "grid":
        new = np.stack([remap(xy[:, 0]), remap(xy[:, 1])], -1)
    else:
        c = xy.mean(0)
        d = xy - c
        r, th = np.hypot(d[:, 0], d[:, 1]), np.arctan2(d[:, 1], d[:, 0])
        step = 2 * np.pi / spec.size
        arm = np.rint(th / step).astype(np.int64) % spec.size
        ang = np.arange(spec.size) * step + rng.uniform(-j, j, spec.size) * step / 2 + rng.uniform(0, 2 * np.pi)
        r_new = remap(np.concatenate([[0.0], r]))[1:]  # ring gaps, from the centre
        new = c + np.stack([r_new * np.cos(ang[arm]), r_new * np.sin(ang[arm])], -1)
    if spec.perturb > 0:
        new = new + np.clip(rng.normal(0.0, spec.perturb, new.shape), -2 * spec.perturb, 2 * spec.perturb)
    out, k = [], 0
    for a, (x, y) in zip(m, new):
        out += [nod_text[k:a.start()], f"{a.group(1)}{x:.2f}{a.group(3)}{y:.2f}{a.group(5)}"]
        k = a.end()
    return "".join(out) + nod_text[k:]


def _run(args: list[str], what: str, timeout: float = 600, env: dict | None = None) -> str:
    try:
        p = subprocess.run(args, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired as e:
        raise SumoRunRejected(f"{what}: timed out after {timeout} s") from e
    if p.returncode != 0:
        raise RuntimeError(f"{what} failed (exit {p.returncode}):\n{p.stderr[-2000:]}")
    return p.stdout


# ------------------------------------------------------------------------------------------ network lanes
def _open_xml(path: str):
    return gzip.open(path, "rb") if path.endswith(".gz") else open(path, "rb")


def _passenger_allowed(attrib: dict) -> bool:
    allow = attrib.get("allow")
    if allow is not None:
        toks = allow.split()
        return "all" in toks or "passenger" in toks
    disallow = attrib.get("disallow", "").split()
    return not ("all" in disallow or "passenger" in disallow)


def _parse_shape(s: str) -> np.ndarray:
    pts = [tuple(map(float, p.split(",")[:2])) for p in s.split()]
    return np.asarray(pts, np.float64).reshape(-1, 2)


DEFAULT_LANE_WIDTH = 3.2  # SUMO's default where a lane has no `width`


def read_network_areas(net_path: str) -> tuple[Area, ...]:
    """The drivable surface of a SUMO network as `Area`s in the network's frame: every normal lane open to
    passenger cars as the polygon its `width` (default 3.2 m) covers around its `shape` (kind "lane"), and every
    junction's `shape` polygon (kind "junction", which covers its internal lanes)."""
    if not os.path.isfile(net_path):
        raise DataError(net_path, "network file not found")
    areas: list[Area] = []
    try:
        with _open_xml(net_path) as f:
            for _, el in ET.iterparse(f, events=("end",)):
                if el.tag == "edge":
                    if el.get("function", "normal") == "normal":
                        for ln in el.findall("lane"):
                            if _passenger_allowed(ln.attrib) and ln.get("shape"):
                                a = lane_area(_parse_shape(ln.get("shape")),
                                              float(ln.get("width", DEFAULT_LANE_WIDTH)))
                                if a is not None:
                                    areas.append(a)
                    el.clear()
                elif el.tag == "junction":
                    if el.get("type") != "internal" and el.get("shape"):
                        shp = _parse_shape(el.get("shape"))
                        if len(shp) >= 3:
                            areas.append(Area(AREA_KIND_ID["junction"], shp))
                    el.clear()
    except (ET.ParseError, ValueError, OSError, EOFError) as e:
        raise DataError(net_path, f"not a readable SUMO network: {e}") from e
    return tuple(areas)


def read_network_lanes(net_path: str, merge_chains: bool = True,
                       ignore_turnarounds: bool = False) -> tuple[np.ndarray, ...]:
    """Lane centrelines (normal and internal junction lanes open to passenger cars) of a SUMO network.

    Returns a tuple of f64[P_i, 2] polylines in the network's metric frame. With `merge_chains`, lanes
    linked one-to-one (the upstream lane has one successor, the downstream lane one predecessor) are
    concatenated into one polyline, as SLEDGE does for nuPlan lanes and connectors.

    With `ignore_turnarounds`, connections with dir="t" (SUMO's turnaround connectors, which it adds at most
    junctions of OSM imports, including where an OSM way is merely split) are left out of the successor and
    predecessor counts and their internal lanes out of the lanes, so a real lane runs on through a junction the
    raster does not show (the cut `gpd_jax.data.realnets.chain_statistics` measures; stores use the default).
    """
    if not os.path.isfile(net_path):
        raise DataError(net_path, "network file not found")
    shapes: dict[str, np.ndarray] = {}
    links: list[tuple[str, str, str]] = []
    try:
        with _open_xml(net_path) as f:
            for _, el in ET.iterparse(f, events=("end",)):
                if el.tag == "edge":
                    func = el.get("function", "normal")
                    if func in ("normal", "internal"):
                        for ln in el.findall("lane"):
                            if _passenger_allowed(ln.attrib) and ln.get("shape"):
                                shp = _parse_shape(ln.get("shape"))
                                if len(shp) >= 2:
                                    shapes[ln.get("id")] = shp
                    el.clear()
                elif el.tag == "connection":
                    a = f"{el.get('from')}_{el.get('fromLane')}"
                    b = el.get("via") or f"{el.get('to')}_{el.get('toLane')}"
                    links.append((a, b, el.get("dir", "")))
                    el.clear()
    except (ET.ParseError, ValueError, OSError, EOFError) as e:  # bad XML, bad shape numbers, bad gzip
        raise DataError(net_path, f"not a readable SUMO network: {e}") from e
    if ignore_turnarounds:
        turn_internal = {b for a, b, d in links if d == "t" and b.startswith(":")}
        shapes = {k: v for k, v in shapes.items() if k not in turn_internal}
        links = [(a, b, d) for a, b, d in links if d != "t"]
    if not shapes:
        raise DataError(net_path, "network has no lanes usable by passenger cars")
    ids = sorted(shapes)
    if not merge_chains:
        return tuple(shapes[i] for i in ids)
    succ: dict[str, list[str]] = {i: [] for i in ids}
    pred: dict[str, list[str]] = {i: [] for i in ids}
    for a, b in {(a, b) for a, b, _ in links}:
        if a in shapes and b in shapes and a != b:
            succ[a].append(b)
            pred[b].append(a)
    merge_next = {a: s[0] for a, s in succ.items() if len(s) == 1 and len(pred[s[0]]) == 1}
    has_merged_pred = set(merge_next.values())
    done: set[str] = set()
    out = []

    def walk(start):
        chain = [shapes[start]]
        done.add(start)
        cur = start
        while cur in merge_next and merge_next[cur] not in done:
            cur = merge_next[cur]
            done.add(cur)
            nxt = shapes[cur]
            if np.allclose(chain[-1][-1], nxt[0], atol=1e-3):
                nxt = nxt[1:]
            chain.append(nxt)
        return np.concatenate(chain, axis=0)

    for i in ids:
        if i not in has_merged_pred and i not in done:
            out.append(walk(i))
    for i in ids:  # pure cycles
        if i not in done:
            out.append(walk(i))
    return tuple(out)


# ------------------------------------------------------------------------------------------ simulation
@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Demand and recording settings of one SUMO run."""

    warmup_s: float = 120.0
    record_s: float = 150.0
    insertion_density: float = 220.0  # vehicles per hour per km of lane
    time_to_teleport: float = 90.0
    max_stopped_fraction: float = 0.5
    min_vehicles: int = 30
    # Runs with any jam teleport, or more yield / wrong-lane teleports than this fraction of the inserted
    # vehicles, are rejected. In accepted runs with teleports the teleported vehicles' tracks (gaps or
    # jumps in the FCD) are removed, never recorded. 0 for generated networks: any teleport rejects.
    tolerated_teleport_fraction: float = 0.0
    extra_sumo_args: tuple[str, ...] = ()
    # --- real-traffic options (`LEGACY_TRAFFIC` turns them all off: the behaviour of stores built before) ---
    # Road-side parking: this share of the edges that suit it (normal edges open to cars, >= 40 m, <= 60 km/h)
    # get a `parkingArea` along their outer lane (spaces of 7 m, 15 m clear of both junctions), and this share
    # of its spaces are filled by cars, SUVs and vans that drive in during the warm-up and stay parked.
    parking_edge_share: float = 0.4
    parking_occupancy: float = 0.6
    # Of the parked vehicles, this share leaves its space during the recording (and drives off).
    parked_leave_share: float = 0.1
    # This share of the moving vehicles makes one short stop (pick-up / drop-off) of `short_stop_s` seconds on
    # the outer lane of an edge of its route (not the first or the last), then goes on.
    short_stop_share: float = 0.1
    short_stop_s: tuple[float, float] = (5.0, 40.0)
    # "heterogeneous": every size class is a vTypeDistribution of `driver_variants` drivers drawn from the job
    # seed (speedFactor, sigma, tau, minGap, accel / decel scale, car-following model Krauss / IDM / EIDM,
    # lcAssertive, lcSpeedGain, lcCooperative, lcKeepRight, lcImpatience); "uniform": one IDM driver per class.
    drivers: str = "heterogeneous"
    driver_variants: int = 8


# Real (OSM-imported) networks have a few junctions where SUMO's right-of-way model leaves vehicles waiting
# whatever the demand (measured on the shipped bs3d and A10KW networks: 14-20 'yield' teleports at both 100
# and 200 veh/h/km, none from jams). For them: impatience and junction-blocker remedies, tolerate up to 10 %
# such teleports (whose tracks are dropped), and lower demand.
REAL_NETWORK_SIM = SimConfig(insertion_density=150.0, tolerated_teleport_fraction=0.1,
                             extra_sumo_args=("--time-to-impatience", "30", "--ignore-junction-blocker", "20"))

# The traffic options of `SimConfig` as stores were built before they existed: no parked or stopping vehicles,
# one driver per size class. `dataclasses.replace(cfg, **LEGACY_TRAFFIC)`.
LEGACY_TRAFFIC = dict(parking_edge_share=0.0, parking_occupancy=0.0, parked_leave_share=0.0, short_stop_share=0.0,
                      drivers="uniform")
TRAFFIC_FIELDS = ("parking_edge_share", "parking_occupancy", "parked_leave_share", "short_stop_share",
                  "short_stop_s", "drivers", "driver_variants")
DRIVERS = ("heterogeneous", "uniform")


def check_sim_config(cfg: SimConfig) -> None:
    """Raises DataError naming the field when a traffic option of `cfg` is out of range."""
    for k in ("parking_edge_share", "parking_occupancy", "parked_leave_share", "short_stop_share"):
        v = getattr(cfg, k)
        if not (isinstance(v, (int, float)) and 0.0 <= v <= 1.0):
            raise DataError(None, f"SimConfig.{k} must be a share in [0, 1], got {v!r}")
    lo, hi = cfg.short_stop_s
    if not 0.0 < lo <= hi:
        raise DataError(None, f"SimConfig.short_stop_s must be (min, max) seconds with 0 < min <= max, got "
                              f"{cfg.short_stop_s!r}")
    if cfg.drivers not in DRIVERS:
        raise DataError(None, f"SimConfig.drivers must be one of {DRIVERS}, got {cfg.drivers!r}")
    if cfg.driver_variants < 1:
        raise DataError(None, f"SimConfig.driver_variants must be >= 1, got {cfg.driver_variants!r}")


# ------------------------------------------------------------------------------------ shipped real networks
# Real (OSM-derived) road networks in the eclipse-sumo wheel, relative to SUMO_HOME/tools/game. Each was built
# with `build_sumo(..., nets=[net], per_job=10, split="test")` (REAL_NETWORK_SIM, default sample config) on
# SUMO 1.28 and gave 9-10 samples (wall time of that one-job build on one core in brackets). A second build
# of all six (`build --real-networks --split test --scenarios 60 --per-job 10`, other demand seeds, 150 s)
# gave 10 samples on each but bs3d, whose 4 runs were all rejected (gridlock, then 11-14 % 'yield'
# teleports against the 10 % tolerated): bs3d works for some demand seeds only.
REAL_NETWORKS = {
    "fokr_bs_demo/fokr_bs.net.xml.gz": "Braunschweig, the DLR research intersection (2 s)",
    "fkk_in/ingolstadt.net.xml.gz": "Ingolstadt, a crop of the city (2 s)",
    "highway/highway.net.xml": "motorway near Bremen (3 s; 21 of 30 candidate windows overlap-gated)",
    "bs3d/bs.net.xml": "Braunschweig centre, 1.6 x 2.1 km (9 s, one run rejected for gridlock)",
    "A10KW/osm.net.xml": "A10 motorway area south-west of Berlin, 2.5 x 3.2 km (18 s, 2 runs rejected)",
    "DRT/osm.net.xml": "Berlin district, 2.6 x 3.3 km (97 s, 3 runs rejected for jam teleports)",
}
# Also geo-referenced but no road network: game/racing/spreewaldring.net.xml, a race circuit whose lanes are
# closed to passenger cars (randomTrips: "No valid edges"). Everything else shipped (grid6, square, cross,
# corridor, kuehne, ramp, hiking, rail*, the sumolib RiLSA scenarios) is synthetic, with no projection.


def _net_projection(path: str) -> str | None:
    """The `projParameter` of a network's <location> element ("!" = not geo-referenced), None if absent."""
    try:
        with _open_xml(path) as f:
            head = f.read(1 << 16).decode("utf-8", "replace")
    except (OSError, EOFError):
        return None
    m = re.search(r'<location[^>]*projParameter="([^"]*)"', head)
    return m.group(1) if m else None


def real_networks(scan: bool = False, min_lane_km: float = 1.0, names: list[str] | None = None) -> list[str]:
    """Paths of the real (OSM-derived) road networks shipped with SUMO, sorted.

    Default: the `REAL_NETWORKS` that exist in this install (all six were checked to simulate and give samples);
    `names` keeps those whose folder (e.g. "fokr_bs_demo", "DRT") or file name is listed (DataError for a name
    that matches none). With `scan`: every `.net.xml[.gz]` under SUMO_HOME that is geo-referenced (a
    projection other than "!") and has at least `min_lane_km` km of lanes open to passenger cars (this finds
    the same six in SUMO 1.28).
    """
    home = sumo_home()
    if not scan:
        paths = sorted(p for p in (os.path.join(home, "tools", "game", rel) for rel in REAL_NETWORKS)
                       if os.path.isfile(p))
        if not paths:
            raise DataError(home, "no real networks found in this SUMO install")
        if names:
            key = {p: {os.path.basename(os.path.dirname(p)), os.path.basename(p).split(".")[0]} for p in paths}
            unknown = [n for n in names if not any(n in k for k in key.values())]
            if unknown:
                raise DataError(None, f"unknown real network(s) {unknown}; available: "
                                      f"{sorted(os.path.basename(os.path.dirname(p)) for p in paths)}")
            paths = [p for p in paths if key[p] & set(names)]
        return paths
    out = []
    for root, _, files in os.walk(home):
        for name in files:
            if not name.endswith((".net.xml", ".net.xml.gz")):
                continue
            p = os.path.join(root, name)
            proj = _net_projection(p)
            if not proj or proj == "!":
                continue
            try:
                lanes = read_network_lanes(p, merge_chains=False)
            except DataError:
                continue
            km = sum(float(np.sum(np.linalg.norm(np.diff(ln, axis=0), axis=-1))) for ln in lanes) / 1000.0
            if km >= min_lane_km:
                out.append(p)
    return sorted(out)


def _vtypes_xml() -> str:
    """One driver per size class (IDM, sigma 0.3): the vehicle types of stores built before `drivers`."""
    rows = []
    for name, length, width, _, _, vmax, accel, decel in VEHICLE_MIX:
        rows.append(f'  <vType id="{name}" vClass="passenger" length="{length}" width="{width}" '
                    f'maxSpeed="{vmax}" accel="{accel}" decel="{decel}" sigma="0.3" speedDev="0.1" '
                    f'minGap="2.5" carFollowModel="IDM"/>')
    return "<additional>\n" + "\n".join(rows) + "\n</additional>\n"


CAR_FOLLOW_MODELS = (("Krauss", 0.4), ("IDM", 0.3), ("EIDM", 0.3))


def driver_types_xml(rng: np.random.Generator, variants: int = 8) -> str:
    """Every size class of `VEHICLE_MIX` as a `vTypeDistribution` (id = the class name) of `variants` drivers,
    each drawn from `rng`: mean speed factor U(0.85, 1.15) (spread 0.1 around it per vehicle), sigma U(0.05,
    0.6), tau U(0.6, 1.8) s, minGap U(1.5, 3.5) m, accel x U(0.75, 1.25), decel x U(0.85, 1.15), car-following
    model Krauss / IDM / EIDM (0.4 / 0.3 / 0.3), lcAssertive U(0.8, 2.5), lcSpeedGain U(0.3, 3), lcCooperative
    U(0.3, 1), lcKeepRight U(0.3, 2), lcImpatience U(0, 0.8). SUMO draws each vehicle's driver (its --seed)."""
    names, probs = zip(*CAR_FOLLOW_MODELS)
    out = ["<additional>"]
    for name, length, width, _, _, vmax, accel, decel in VEHICLE_MIX:
        out.append(f'  <vTypeDistribution id="{name}">')
        for k in range(variants):
            u = rng.uniform(size=11)
            model = names[int(rng.choice(len(names), p=np.asarray(probs) / sum(probs)))]
            mu = 0.85 + 0.3 * u[0]
            out.append(
                f'    <vType id="{name}.{k}" vClass="passenger" length="{length}" width="{width}" maxSpeed="{vmax}" '
                f'accel="{accel * (0.75 + 0.5 * u[1]):.2f}" decel="{decel * (0.85 + 0.3 * u[2]):.2f}" '
                f'sigma="{0.05 + 0.55 * u[3]:.2f}" tau="{0.6 + 1.2 * u[4]:.2f}" minGap="{1.5 + 2.0 * u[5]:.2f}" '
                f'speedFactor="normc({mu:.3f},0.1,0.5,1.6)" carFollowModel="{model}" '
                f'lcAssertive="{0.8 + 1.7 * u[6]:.2f}" lcSpeedGain="{0.3 + 2.7 * u[7]:.2f}" '
                f'lcCooperative="{0.3 + 0.7 * u[8]:.2f}" lcKeepRight="{0.3 + 1.7 * u[9]:.2f}" '
                f'lcImpatience="{0.8 * u[10]:.2f}" probability="1"/>')
        out.append("  </vTypeDistribution>")
    return "\n".join(out + ["</additional>"]) + "\n"


@dataclasses.dataclass(frozen=True)
class NetEdge:
    """A normal edge of a network as the traffic planner sees it: its outermost lane open to passenger cars
    (lane 0 where it is; OSM-imported roads often have a sidewalk or bike lane at index 0), else lane 0."""

    id: str
    lane_id: str
    length: float  # SUMO lane length (positions along the lane are in these metres)
    speed: float
    width: float
    shape: np.ndarray  # f64[P, 2]
    cars: bool  # that lane is open to passenger cars
    next: tuple[str, ...] = ()  # normal edges this edge connects to


def read_network_edges(net_path: str) -> tuple[bool, list[NetEdge]]:
    """(left-hand traffic?, normal edges with their outer lane and successors) of a SUMO network."""
    edges: list[NetEdge] = []
    succ: dict[str, set[str]] = {}
    lefthand = False
    try:
        with _open_xml(net_path) as f:
            for ev, el in ET.iterparse(f, events=("start", "end")):
                if ev == "start":
                    if el.tag == "net":
                        lefthand = el.get("lefthand", "false").lower() == "true"
                    continue
                if el.tag == "edge":
                    if el.get("function", "normal") == "normal":
                        lanes = sorted(el.findall("lane"), key=lambda x: int(x.get("index", 0)))
                        car = [x for x in lanes if _passenger_allowed(x.attrib) and x.get("shape")]
                        ln = car[0] if car else (lanes[0] if lanes else None)
                        if ln is not None and ln.get("shape"):
                            edges.append(NetEdge(el.get("id"), ln.get("id"), float(ln.get("length", 0.0)),
                                                 float(ln.get("speed", 13.89)),
                                                 float(ln.get("width", DEFAULT_LANE_WIDTH)),
                                                 _parse_shape(ln.get("shape")), _passenger_allowed(ln.attrib)))
                    el.clear()
                elif el.tag == "connection":
                    a, b = el.get("from", ""), el.get("to", "")
                    if not a.startswith(":") and not b.startswith(":"):
                        succ.setdefault(a, set()).add(b)
                    el.clear()
    except (ET.ParseError, ValueError, OSError, EOFError) as e:
        raise DataError(net_path, f"not a readable SUMO network: {e}") from e
    return lefthand, [dataclasses.replace(e, next=tuple(sorted(succ.get(e.id, ())))) for e in edges]


def is_lefthand(net_path: str) -> bool:
    """Whether a SUMO network drives on the left (`<net lefthand="true">`, netconvert --lefthand)."""
    with _open_xml(net_path) as f:
        head = f.read(1 << 14).decode("utf-8", "replace")
    m = re.search(r"<net\b[^>]*>", head)
    return bool(m and re.search(r'\blefthand="true"', m.group(0)))


def make_lefthand(src: str, out_path: str) -> str:
    """A given network rebuilt for left-hand traffic (`netconvert -s SRC --lefthand`: every edge keeps its
    geometry, its lanes move to the other side of it, traffic lights and right of way follow). Writes `out_path`
    atomically; returns it."""
    if not os.path.isfile(src):
        raise DataError(src, "network file not found")
    d = os.path.dirname(os.path.abspath(out_path))
    os.makedirs(d, exist_ok=True)
    tmp = os.path.join(d, f".tmp-{os.getpid()}-{os.path.basename(out_path)}")
    try:
        _run([_bin("netconvert"), "-s", src, "--lefthand", "true", "--no-warnings", "true", "-o", tmp],
             what=f"netconvert --lefthand {src}", env=dict(os.environ, SUMO_HOME=sumo_home()))
        os.replace(tmp, out_path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return out_path


def _cut_polyline(pts: np.ndarray, a: float, b: float) -> np.ndarray:
    """The part of polyline `pts f64[P, 2]` between arc lengths a < b."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=-1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    a, b = max(0.0, a), min(float(s[-1]), b)
    inner = (s > a) & (s < b)
    t = np.concatenate([[a], s[inner], [b]])
    return np.stack([np.interp(t, s, pts[:, 0]), np.interp(t, s, pts[:, 1])], -1)


PARKING_SPACE_M = 7.0  # length of one road-side space (parked vehicles are at most 6.5 m long: car, SUV, van)
PARKING_WIDTH_M = 2.5  # width of the parking strip beside the outer lane
PARKING_MARGIN_M = 15.0  # clear of both ends of the edge (junction approaches)
PARKING_MAX_SPEED = 16.7  # m/s: edges faster than 60 km/h get no road-side parking and no pick-up stops
PARKED_ID_BASE = 10_000_000  # FCD ids of parked vehicles (randomTrips numbers its vehicles from 0)
PARKED_CLASSES = ("g_car", "g_suv", "g_van")


def _suits_parking(e: NetEdge) -> bool:
    return e.cars and e.speed <= PARKING_MAX_SPEED and e.length >= 40.0


@dataclasses.dataclass(frozen=True)
class TrafficPlan:
    """What `plan_traffic` adds to a run: parking areas (additional XML), parked vehicles (route XML, their
    ids and size classes) and the parking strips as drivable `Area`s of kind "other"."""

    parking_xml: str
    parked_xml: str
    parked_types: dict[str, str]
    areas: tuple[Area, ...]
    num_spaces: int


def plan_traffic(edges: list[NetEdge], lefthand: bool, cfg: SimConfig, rng: np.random.Generator, end_s: float
                 ) -> TrafficPlan:
    """Road-side parking areas and the vehicles parked in them (see `SimConfig.parking_edge_share`).

    Parked vehicles are cars, SUVs and vans with a `<stop parkingArea until>` on a route of their own edge,
    inserted at their own space (spaces fill from the end of the area) in the first quarter of the warm-up
    (checking only for a collision at insertion), so that they are parked when the recording starts. Those that
    leave (`parked_leave_share`) go at a time drawn in the recording, along a random walk of up to 5 more
    connected edges. `edges`, `lefthand`: `read_network_edges` of the network."""
    side = 1.0 if lefthand else -1.0  # the strip lies beyond the outer lane: right (left in left-hand traffic)
    areas, pa_rows, trips, types = [], [], [], {}
    by_id = {e.id: e for e in edges}

    def walk(e: NetEdge) -> list[str]:
        route = [e.id]
        while len(route) < 6 and by_id[route[-1]].next:
            nxt = [x for x in by_id[route[-1]].next if x in by_id and by_id[x].cars]
            if not nxt:
                break
            route.append(nxt[int(rng.integers(len(nxt)))])
        return route

    probs = np.array([m[3] for m in VEHICLE_MIX if m[0] in PARKED_CLASSES])
    names = [m[0] for m in VEHICLE_MIX if m[0] in PARKED_CLASSES]
    n_spaces = 0
    k = 0
    for e in edges:
        if not _suits_parking(e) or rng.uniform() >= cfg.parking_edge_share:
            continue
        a, b = PARKING_MARGIN_M, e.length - PARKING_MARGIN_M
        cap = int((b - a) // PARKING_SPACE_M)
        if cap < 1:
            continue
        b = a + cap * PARKING_SPACE_M
        pid = f"pa_{e.id}"
        pa_rows.append(f'  <parkingArea id="{pid}" lane="{e.lane_id}" startPos="{a:.2f}" endPos="{b:.2f}" '
                       f'roadsideCapacity="{cap}" length="{PARKING_SPACE_M}" width="{PARKING_WIDTH_M}"/>')
        n_spaces += cap
        geo_len = float(np.sum(np.linalg.norm(np.diff(e.shape, axis=0), axis=-1)))
        scale = geo_len / e.length if e.length > 0 else 1.0
        strip = lane_area(_cut_polyline(e.shape, a * scale, b * scale), PARKING_WIDTH_M, AREA_KIND_ID["other"],
                          offset=side * (e.width / 2 + PARKING_WIDTH_M / 2))
        if strip is not None:
            areas.append(strip)
        n_park = int(rng.binomial(cap, cfg.parking_occupancy))
        departs = np.sort(rng.uniform(0.0, 0.25 * cfg.warmup_s, n_park))
        for i, depart in enumerate(departs):
            vid = str(PARKED_ID_BASE + k)
            k += 1
            cls = names[int(rng.choice(len(names), p=probs / probs.sum()))]
            types[vid] = cls
            pos = b - i * PARKING_SPACE_M - 0.3  # the space SUMO gives it: spaces fill from the end of the area
            if rng.uniform() < cfg.parked_leave_share:
                until, route = rng.uniform(cfg.warmup_s, end_s), walk(e)
            else:
                until, route = end_s + 3600.0, [e.id]
            trips.append((depart, f'  <vehicle id="{vid}" type="{cls}" depart="{depart:.1f}" '
                                  f'departLane="{e.lane_id.rsplit("_", 1)[1]}" departPos="{pos:.1f}" departSpeed="0" '
                                  f'insertionChecks="collision">'
                                  f'<route edges="{" ".join(route)}"/><stop parkingArea="{pid}" '
                                  f'until="{until:.1f}"/></vehicle>'))
    trips.sort(key=lambda t: t[0])
    return TrafficPlan("<additional>\n" + "\n".join(pa_rows) + "\n</additional>\n",
                       "<routes>\n" + "\n".join(t for _, t in trips) + "\n</routes>\n", types, tuple(areas), n_spaces)


_VEHICLE_ROUTE = re.compile(r'(<vehicle id="([^"]+)"[^>]*>\s*<route edges="([^"]+)"\s*/>)')


def add_short_stops(routes_text: str, edges: list[NetEdge], cfg: SimConfig, rng: np.random.Generator
                    ) -> tuple[str, int]:
    """Routes with a pick-up / drop-off stop (`<stop lane endPos duration>` on the outer lane of an inner edge
    of its route that suits parking) added to `cfg.short_stop_share` of the vehicles. Returns (text, stops)."""
    by_id = {e.id: e for e in edges}
    lo, hi = cfg.short_stop_s
    n = 0

    def add(m):
        nonlocal n
        if rng.uniform() >= cfg.short_stop_share:
            return m.group(1)
        inner = [by_id[x] for x in m.group(3).split()[1:-1] if x in by_id and _suits_parking(by_id[x])]
        if not inner:
            return m.group(1)
        e = inner[int(rng.integers(len(inner)))]
        pos = rng.uniform(20.0, e.length - 10.0)
        n += 1
        return (m.group(1) + f'\n        <stop lane="{e.lane_id}" endPos="{pos:.1f}" '
                             f'duration="{rng.uniform(lo, hi):.1f}" friendlyPos="true"/>')

    return _VEHICLE_ROUTE.sub(add, routes_text), n


def _read_planned_stops(path: str) -> dict[int, list[tuple[float, float]]]:
    """SUMO's stop output (CSV): vehicle id -> [(started, ended)] in simulation seconds (unfinished: inf)."""
    out: dict[int, list[tuple[float, float]]] = {}
    if not os.path.isfile(path):
        return out
    with open(path) as f:
        rows = [ln.rstrip("\n").split(";") for ln in f if ln.strip()]
    if not rows:
        return out
    col = {k: i for i, k in enumerate(rows[0])}
    i_id, i_s, i_e = col.get("stopinfo_id"), col.get("stopinfo_started"), col.get("stopinfo_ended")
    if i_id is None or i_s is None or i_e is None:
        return out
    for r in rows[1:]:
        try:
            vid, s, e = int(float(r[i_id])), float(r[i_s]), float(r[i_e])
        except (ValueError, IndexError):
            continue
        out.setdefault(vid, []).append((s, np.inf if e < 0 else e))
    return out


def simulate(net_path: str, name: str, location: str, seed: int, cfg: SimConfig = SimConfig(),
             workdir: str | None = None, lanes: tuple[np.ndarray, ...] | None = None,
             areas: tuple[Area, ...] | None = None, info: dict | None = None) -> RawLog:
    """Makes demand on `net_path`, runs SUMO and returns the recording as a `RawLog` (10 Hz, box centres).

    With the traffic options of `cfg`: road-side parking areas and parked vehicles (`plan_traffic`; their
    strips join the drivable areas as kind "other"), short stops (`add_short_stops`) and heterogeneous drivers
    (`driver_types_xml`). `info`, when given, receives counts of what was added and of the planned stops.

    Raises `SumoRunRejected` for runs with teleports, gridlock or too little traffic.
    """
    check_sim_config(cfg)
    rng = np.random.default_rng([seed, 11])
    rng_traffic = np.random.default_rng([seed, 23])  # its own stream: the legacy draws stay as they were
    info = {} if info is None else info
    own_tmp = workdir is None
    wd = tempfile.mkdtemp(prefix="gpd_sumo_") if own_tmp else workdir
    try:
        vt = os.path.join(wd, "vtypes.add.xml")
        with open(vt, "w") as f:
            f.write(_vtypes_xml())
        vt_sim = vt
        if cfg.drivers == "heterogeneous":
            vt_sim = os.path.join(wd, "drivers.add.xml")
            with open(vt_sim, "w") as f:
                f.write(driver_types_xml(rng_traffic, cfg.driver_variants))
        trips, routes = os.path.join(wd, "trips.xml"), os.path.join(wd, "routes.xml")
        end = cfg.warmup_s + cfg.record_s
        tools = os.path.join(sumo_home(), "tools")
        _run([sys.executable, os.path.join(tools, "randomTrips.py"), "-n", net_path, "-o", trips, "-r", routes,
              "--seed", str(seed % (2**31)), "-b", "0", "-e", f"{end:.0f}",
              "--insertion-density", f"{cfg.insertion_density:.2f}", "--fringe-factor", "5",
              "--min-distance", "150", "--validate", "--additional-file", vt,
              "--trip-attributes", 'type="g_car" departLane="best" departSpeed="max"'],
             what=f"randomTrips on {net_path}")
        # Draw each vehicle's type from the size mix with our RNG (deterministic, numeric FCD).
        with open(routes) as f:
            text = f.read()
        probs = np.array([m[3] for m in VEHICLE_MIX])
        n_veh = text.count('type="g_car"')
        draws = rng.choice(len(VEHICLE_MIX), size=n_veh, p=probs / probs.sum())
        it = iter(draws)
        text = re.sub(r'type="g_car"', lambda _: f'type="{VEHICLE_MIX[next(it)][0]}"', text)
        text = re.sub(r"<vType [^>]*/>|<vType [^>]*>.*?</vType>", "", text, flags=re.S)  # ours come via -a
        adds, route_files, types = [vt_sim], [routes], _vehicle_types(text)
        extra_areas: tuple[Area, ...] = ()
        wants_parking = cfg.parking_edge_share > 0 and cfg.parking_occupancy > 0
        if wants_parking or cfg.short_stop_share > 0:
            lefthand, edges = read_network_edges(net_path)
            if cfg.short_stop_share > 0:
                text, info["short_stops"] = add_short_stops(text, edges, cfg, rng_traffic)
            if wants_parking:
                plan = plan_traffic(edges, lefthand, cfg, rng_traffic, end)
                info.update(parking_spaces=plan.num_spaces, parked_vehicles=len(plan.parked_types))
                if plan.parked_types:
                    pa, pr = os.path.join(wd, "parking.add.xml"), os.path.join(wd, "parked.rou.xml")
                    with open(pa, "w") as f:
                        f.write(plan.parking_xml)
                    with open(pr, "w") as f:
                        f.write(plan.parked_xml)
                    adds.append(pa)
                    route_files.append(pr)
                    types.update(plan.parked_types)
                    extra_areas = plan.areas
        with open(routes, "w") as f:
            f.write(text)
        fcd, stats = os.path.join(wd, "fcd.csv"), os.path.join(wd, "stats.csv")
        stops = os.path.join(wd, "stops.csv")
        _run([_bin("sumo"), "-n", net_path, "-r", ",".join(route_files), "-a", ",".join(adds), "--step-length", "0.1",
              "--lanechange.duration", "3", "--fcd-output", fcd, "--output.format", "csv",
              "--fcd-output.attributes", "x,y,angle,speed", "--device.fcd.begin", f"{cfg.warmup_s:.1f}",
              "-e", f"{end - 0.05:.2f}", "--statistic-output", stats, "--time-to-teleport",
              f"{cfg.time_to_teleport:.0f}", "--no-step-log", "true", "--no-warnings", "true",
              "--seed", str(seed % (2**31)), "--collision.action", "warn", "--precision", "3",
              "--stop-output", stops, "--stop-output.write-unfinished", "true", "--ignore-route-errors", "true",
              *cfg.extra_sumo_args],
             what=f"sumo on {net_path}")
        st = _read_stats(stats)
        teleports = int(float(st.get("teleports_total", 0) or 0))
        inserted = int(float(st.get("vehicles_inserted", 0) or 0))
        jams = int(float(st.get("teleports_jam", 0) or 0))
        if teleports and (jams or teleports > cfg.tolerated_teleport_fraction * max(inserted, 1)):
            raise SumoRunRejected(f"{name}: {teleports} teleports ({jams} in jams) of {inserted} vehicles")
        raw = _fcd_to_rawlog(fcd, types, name, location, cfg, planned_stops=_read_planned_stops(stops), info=info)
        if teleports:  # a few isolated teleports (deadlocks at odd real junctions): drop those tracks
            raw = drop_discontinuous_tracks(raw)
    finally:
        if own_tmp:
            import shutil
            shutil.rmtree(wd, ignore_errors=True)
    if raw.num_agents < cfg.min_vehicles:
        raise SumoRunRejected(f"{name}: only {raw.num_agents} vehicles recorded")
    if lanes is None:
        lanes = read_network_lanes(net_path)
    if areas is None:
        areas = read_network_areas(net_path)
    return dataclasses.replace(raw, lanes=lanes, areas=tuple(areas) + extra_areas)


def drop_discontinuous_tracks(raw: RawLog, max_speed: float = 70.0) -> RawLog:
    """Marks invalid every frame of tracks that vanish and reappear or jump (> max_speed m/s): teleports."""
    v = raw.agent_valid
    reappear = np.any(v[1:] & ~v[:-1] & (np.cumsum(v, 0)[:-1] > 0), axis=0)
    step = np.linalg.norm(np.diff(raw.agent_xy, axis=0), axis=-1)
    jump = np.any((v[1:] & v[:-1]) & (np.nan_to_num(step, nan=0.0) > max_speed * 0.1), axis=0)
    bad = reappear | jump
    if not bad.any():
        return raw
    log.info("%s: dropping %d teleported tracks", raw.name, int(bad.sum()))
    valid = v & ~bad[None]
    xy = np.where(valid[..., None], raw.agent_xy, np.nan)
    return dataclasses.replace(raw, agent_valid=valid, agent_xy=xy,
                               agent_heading=np.where(valid, raw.agent_heading, np.nan))


def _read_stats(path: str) -> dict[str, str]:
    """SUMO's statistic output in CSV: a header and sparse rows; the first non-empty value per column."""
    with open(path) as f:
        rows = [ln.rstrip("\n").split(";") for ln in f if ln.strip()]
    if not rows:
        return {}
    out: dict[str, str] = {}
    for row in rows[1:]:
        for k, v in zip(rows[0], row):
            if v != "" and k not in out:
                out[k] = v
    return out


def _vehicle_types(routes_text: str) -> dict[str, str]:
    return dict(re.findall(r'<vehicle id="([^"]+)" type="([^"]+)"', routes_text))


def bumper_to_centre(front_xy: np.ndarray, compass_deg: np.ndarray, length: np.ndarray):
    """SUMO front bumper + compass angle -> (box centre f64[..., 2], CCW heading f64[...] in [-pi, pi)).

    compass: degrees, 0 = north (+y), clockwise; heading: radians from +x (east), counter-clockwise.
    """
    heading = np.radians(90.0 - np.asarray(compass_deg, np.float64))
    heading = (heading + np.pi) % (2 * np.pi) - np.pi
    c = np.stack([np.cos(heading), np.sin(heading)], -1)
    centre = np.asarray(front_xy, np.float64) - 0.5 * np.asarray(length, np.float64)[..., None] * c
    return centre, heading


def _fcd_to_rawlog(fcd_path: str, types: dict[str, str], name: str, location: str, cfg: SimConfig,
                   planned_stops: dict[int, list[tuple[float, float]]] | None = None, info: dict | None = None
                   ) -> RawLog:
    """FCD CSV -> RawLog. The gridlock gate counts vehicle-frames under 0.5 m/s, leaving out the frames of
    vehicles at a planned stop (`planned_stops`: SUMO's stop output, parked vehicles and pick-ups): more than
    `cfg.max_stopped_fraction` of the rest is a jam (`SumoRunRejected`)."""
    try:
        data = np.loadtxt(fcd_path, delimiter=";", skiprows=1, dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise DataError(fcd_path, f"unreadable FCD output: {e}") from e
    if data.size == 0:
        raise SumoRunRejected(f"{name}: empty FCD output")
    t, vid, x, y, ang, spd = data.T
    frame = np.rint((t - t.min()) * 10).astype(np.int64)
    F = int(frame.max()) + 1
    uids, col = np.unique(vid.astype(np.int64), return_inverse=True)
    N = len(uids)
    planned = np.zeros(len(t), bool)
    for u, spans in (planned_stops or {}).items():
        j = np.searchsorted(uids, u)
        if j >= N or uids[j] != u:
            continue
        rows = col == j
        for a, b in spans:
            planned |= rows & (t >= a - 0.05) & (t <= b + 0.05)
    still = spd < 0.5
    counted = ~planned
    stopped = float(np.mean(still[counted])) if counted.any() else 0.0
    if info is not None:
        info.update(stopped_fraction=round(float(np.mean(still)), 4), jam_stopped_fraction=round(stopped, 4),
                    planned_stop_frames=int(planned.sum()), vehicle_frames=int(len(t)))
    if stopped > cfg.max_stopped_fraction:
        raise SumoRunRejected(f"{name}: {stopped:.0%} of vehicle-frames stopped (gridlock; frames at planned stops, "
                              f"{planned.mean():.0%} of all, not counted)")
    by_name = {m[0]: m for m in VEHICLE_MIX}
    size = np.zeros((N, 2), np.float32)
    atype = np.zeros((N,), np.int32)
    for j, u in enumerate(uids):
        m = by_name.get(types.get(str(u), "g_car"), VEHICLE_MIX[0])
        size[j] = (m[1], m[2])
        atype[j] = TYPE_ID[m[4]]
    centre, heading = bumper_to_centre(np.stack([x, y], -1), ang, size[col, 0])
    xy = np.full((F, N, 2), np.nan)
    hd = np.full((F, N), np.nan)
    sp = np.zeros((F, N))
    valid = np.zeros((F, N), bool)
    xy[frame, col] = centre
    hd[frame, col] = heading
    sp[frame, col] = spd
    valid[frame, col] = True
    n_smoothed = smooth_parking_jumps(xy, valid, sp)
    if info is not None:
        info["parking_jumps_smoothed"] = n_smoothed
    return RawLog(name=name, location=location, timestamps=np.arange(F) * 0.1 + cfg.warmup_s,
                  agent_ids=tuple(str(u) for u in uids), agent_xy=xy, agent_heading=hd, agent_valid=valid,
                  agent_size=size, agent_type=atype, lanes=(), ego_index=None)


def smooth_parking_jumps(xy: np.ndarray, valid: np.ndarray, speed: np.ndarray, span: int = 20, leave_span: int = 6,
                         min_jump: float = 1.0, max_jump: float = 8.0, max_speed: float = 3.0) -> int:
    """Spreads SUMO's sideways jumps into and out of a road-side parking space (the vehicle moves between the
    lane and the space, about 3 m, in one 0.1 s step) over `span` frames, in place. A jump: a step between two
    valid frames of more than `min_jump` (and less than `max_jump`) metres beyond what the reported speed covers,
    at speeds under `max_speed`. Only the frames on the lane side move, so the parked side never reaches into
    the lane where other vehicles pass: before the jump when the vehicle parks (over `span` frames), after it
    when it leaves (by the mean speeds on each side; over `leave_span` frames: 0.6 s, in which a car pulling out
    moves well under the 0.5 m to the car parked ahead, whose box it would otherwise cross). `xy f64[F, N, 2]`, `valid bool[F, N]`, `speed f64[F, N]`.
    Returns the number of jumps."""
    F = xy.shape[0]
    ok = valid[1:] & valid[:-1]
    step = np.linalg.norm(np.nan_to_num(xy[1:] - xy[:-1]), axis=-1)
    covered = 0.1 * np.maximum(speed[1:], speed[:-1])
    jump = ok & (step - covered > min_jump) & (step < max_jump) & (np.maximum(speed[1:], speed[:-1]) < max_speed)
    for t, n in zip(*np.nonzero(jump)):
        d = xy[t + 1, n] - xy[t, n]
        lo = max(0, t - span + 1)
        while lo < t and not valid[lo:t + 1, n].all():
            lo += 1
        hi = min(F - 1, t + max(span, leave_span))
        while hi > t + 1 and not valid[t + 1:hi + 1, n].all():
            hi -= 1
        leaving = speed[t + 1:hi + 1, n].mean() > speed[lo:t + 1, n].mean()
        if leaving:  # on the lane after the jump: start from the space, reach the lane after `leave_span` frames
            k = np.arange(t + 1, min(hi, t + leave_span) + 1)
            xy[k, n] -= d * np.maximum(0.0, 1.0 - (k - t) / leave_span)[:, None]
        else:  # on the lane before the jump: drift into the space over the `span` frames before it
            k = np.arange(lo, t + 1)
            xy[k, n] += d * (1.0 - (t + 1 - k) / span)[:, None]
    return int(jump.sum())