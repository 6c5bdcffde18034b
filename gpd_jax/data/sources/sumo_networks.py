"""SUMO road networks: generate them (netgenerate), read them (lanes, drivable areas, edges), SUMO's real ones,
left-hand copies; and the helpers that find and run SUMO's tools.

The networks of a SUMO build (`gpd_jax.data.sources.sumo`) are one of:

* generated: `netgenerate` (random / grid / spider layouts, 1-3 lanes, traffic lights or priority junctions,
  sizes, street lengths and netgenerate's random node perturbation all drawn from the job seed, so that no
  two seeds give the same roads: `NetSpec`, `random_net_spec`, `generate_network`; optionally curved streets,
  `NetSpec.bend`); generated networks may drive on the left (`netconvert --lefthand`) and have fixed-cycle
  traffic lights (`NetSpec.lefthand`, `NetSpec.tls_type`);
* a given `.net.xml[.gz]`, which may be simulated as a left-hand copy (`make_lefthand`; `is_lefthand` tells);
* one of the real OSM-derived networks shipped with SUMO (`real_networks`).

Lane centrelines come from the network file (`read_network_lanes`: normal and internal junction lanes usable by
passenger cars), merged into chains the SLEDGE way: a lane-to-lane link is merged when the upstream lane has
exactly one successor and the downstream lane exactly one predecessor. The drivable area is every car lane
buffered by its width plus every junction's shape (`read_network_areas`); the traffic planner
(`gpd_jax.data.sources.sumo_traffic`) reads each normal edge's outer lane and successors (`read_network_edges`).

SUMO itself: `sumo_home` (SUMO_HOME, else the `eclipse-sumo` wheel), `sumo_bin` and `run_sumo_tool` (a tool that
times out raises `SumoRunRejected`, the rejection of a run that `sumo_traffic.simulate` raises too).
"""

from __future__ import annotations

import dataclasses
import gzip
import os
import re
import subprocess
import tempfile
import xml.etree.ElementTree as ET

import numpy as np

from gpd_jax.data.errors import DataError
from gpd_jax.data.roadgeom import Area, lane_area
from gpd_jax.geometry import AREA_KIND_ID


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


def sumo_bin(name: str) -> str:
    """The path of SUMO's binary `name` (netgenerate, netconvert, sumo, ...)."""
    return os.path.join(sumo_home(), "bin", name)


class SumoRunRejected(RuntimeError):
    """A simulation whose traffic is not usable (teleports, gridlock, too few vehicles)."""


def run_sumo_tool(args: list[str], what: str, timeout: float = 600, env: dict | None = None) -> str:
    """Runs a SUMO tool and returns its stdout; a non-zero exit raises RuntimeError with the end of its stderr,
    a timeout `SumoRunRejected`."""
    try:
        p = subprocess.run(args, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired as e:
        raise SumoRunRejected(f"{what}: timed out after {timeout} s") from e
    if p.returncode != 0:
        raise RuntimeError(f"{what} failed (exit {p.returncode}):\n{p.stderr[-2000:]}")
    return p.stdout


# ----------------------------------------------------------------------------------- generated networks
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
    args = [sumo_bin("netgenerate"), f"--{flag}", "--seed", str(spec.seed), "-o",
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
        run_sumo_tool(args, what=f"netgenerate {spec}", env=env)
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
            run_sumo_tool([sumo_bin("netconvert"), "--node-files", nod, "--edge-files", edg,
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


# ------------------------------------------------------------------------------------- reading networks
def _open_xml(path: str):
    return gzip.open(path, "rb") if path.endswith(".gz") else open(path, "rb")


def _passenger_allowed(attrib: dict) -> bool:
    allow = attrib.get("allow")
    if allow is not None:
        toks = allow.split()
        return "all" in toks or "passenger" in toks
    disallow = attrib.get("disallow", "").split()
    return not ("all" in disallow or "passenger" in disallow)


def parse_shape(s: str) -> np.ndarray:
    """A SUMO `shape` attribute ("x,y[,z] x,y[,z] ...") -> f64[P, 2]."""
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
                                a = lane_area(parse_shape(ln.get("shape")),
                                              float(ln.get("width", DEFAULT_LANE_WIDTH)))
                                if a is not None:
                                    areas.append(a)
                    el.clear()
                elif el.tag == "junction":
                    if el.get("type") != "internal" and el.get("shape"):
                        shp = parse_shape(el.get("shape"))
                        if len(shp) >= 3:
                            areas.append(Area(AREA_KIND_ID["junction"], shp))
                    el.clear()
    except (ET.ParseError, ValueError, OSError, EOFError) as e:
        raise DataError(net_path, f"not a readable SUMO network: {e}") from e
    return tuple(areas)


@dataclasses.dataclass(frozen=True)
class SignalLink:
    """One link a traffic light controls: `tl` (its id), `index` (the link's character in the light's state),
    `stop` f64[2] (the end of the incoming lane, where a vehicle waits), `lane` f64[P, 2] (the incoming lane's
    shape followed by the junction lane the link goes through, driving order)."""

    tl: str
    index: int
    stop: np.ndarray
    lane: np.ndarray


# SUMO's link state characters -> WOSAC lane states (`gpd_jax.geometry.SIGNAL_STATES`): red and red-yellow are
# stop, yellow caution, green (priority or not) go, 's' (stop, then go: right turn on red) a flashing stop, 'o'
# (off, blinking) a flashing caution, 'O' (off, no signal) unknown.
SUMO_LINK_STATES = {"r": "stop", "u": "stop", "y": "caution", "Y": "caution", "G": "go", "g": "go",
                    "s": "flashing_stop", "o": "flashing_caution", "O": "unknown"}


def read_network_signals(net_path: str) -> tuple[SignalLink, ...]:
    """Every link of a SUMO network controlled by a traffic light (`connection` elements with `tl` and
    `linkIndex` whose incoming lane passenger cars may use), in file order."""
    shapes: dict[str, np.ndarray] = {}
    conns: list[tuple[str, int, str, str]] = []
    try:
        with _open_xml(net_path) as f:
            for _, el in ET.iterparse(f, events=("end",)):
                if el.tag == "edge":
                    for ln in el.findall("lane"):
                        if _passenger_allowed(ln.attrib) and ln.get("shape"):
                            shapes[ln.get("id")] = parse_shape(ln.get("shape"))
                    el.clear()
                elif el.tag == "connection":
                    if el.get("tl") is not None and el.get("linkIndex") is not None:
                        conns.append((el.get("tl"), int(el.get("linkIndex")),
                                      f"{el.get('from')}_{el.get('fromLane')}", el.get("via") or ""))
                    el.clear()
    except (ET.ParseError, ValueError, OSError, EOFError) as e:
        raise DataError(net_path, f"not a readable SUMO network: {e}") from e
    out = []
    for tl, index, a, via in conns:
        if a not in shapes or len(shapes[a]) < 2:
            continue
        lane = shapes[a] if via not in shapes else np.concatenate([shapes[a], shapes[via]])
        out.append(SignalLink(tl, index, shapes[a][-1].copy(), lane))
    return tuple(out)


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
                                shp = parse_shape(ln.get("shape"))
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


# -------------------------------------------------------------------------------- shipped real networks
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


# ----------------------------------------------------------------------------- edges, left-hand traffic
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
                                                 parse_shape(ln.get("shape")), _passenger_allowed(ln.attrib)))
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
        run_sumo_tool([sumo_bin("netconvert"), "-s", src, "--lefthand", "true", "--no-warnings", "true", "-o", tmp],
                      what=f"netconvert --lefthand {src}", env=dict(os.environ, SUMO_HOME=sumo_home()))
        os.replace(tmp, out_path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return out_path
