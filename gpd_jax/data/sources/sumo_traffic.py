"""SUMO traffic: demand, simulation and recording of one run on a network -> `RawLog` (`simulate`).

One run = one network (`gpd_jax.data.sources.sumo_networks`) + one demand seed + one SUMO run:

1. demand: `randomTrips.py --insertion-density` (vehicles per hour and km of lane, so that big and small
   networks get comparable traffic) with `departLane="best" departSpeed="max"`; each vehicle's type is drawn
   by us from a size mix (car, SUV, van, truck, bus: `VEHICLE_MIX`) with the job's RNG, so the FCD needs no
   string columns; real traffic (`SimConfig` traffic options, on by default; `LEGACY_TRAFFIC` turns them off):
   road-side parking areas with parked vehicles, some of which leave during the recording (`plan_traffic`),
   pick-up / drop-off stops (`add_short_stops`) and heterogeneous drivers (`driver_types_xml`: a
   vTypeDistribution of Krauss / IDM / EIDM drivers per size class);
2. `sumo --step-length 0.1 --lanechange.duration 3` (continuous lane changes), FCD written as CSV from
   the C++ side every step (10 Hz), after a warm-up. This measured faster than recording through TraCI:
   on one generated network (270 simulated s, ~240 vehicles) trips + SUMO + FCD parsing took 2.8 s, the
   same simulation stepped through TraCI with subscriptions 5.6 s; it also needs no libsumo;
3. quality gate: runs with teleports (SUMO's jam resolution) or where more than `max_stopped_fraction` of
   recorded vehicle-frames stand still (gridlock; frames of vehicles at a planned stop, from SUMO's stop
   output, are not counted: parked cars are no jam) are rejected (`SumoRunRejected`), and the caller
   retries with lower demand and another seed; tracks of the few teleports a run may tolerate are dropped
   (`drop_discontinuous_tracks`);
4. conversion: SUMO reports the *front bumper* position and a *compass* angle (degrees, 0 = north,
   clockwise). heading = radians(90 - angle) (counter-clockwise from +x / east), box centre =
   front - length / 2 * (cos heading, sin heading) (`bumper_to_centre`); the sideways jumps into and out of
   a parking space are spread over frames (`smooth_parking_jumps`).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
import sys
import tempfile

import numpy as np

from gpd_jax.data.errors import DataError
from gpd_jax.data.raw import RawLog
from gpd_jax.data.roadgeom import Area, lane_area
from gpd_jax.data.signals import RawSignals
from gpd_jax.data.sources.sumo_networks import (SUMO_LINK_STATES, NetEdge, SumoRunRejected, read_network_areas,
                                                read_network_edges, read_network_signals,
                                                read_network_lanes, run_sumo_tool, sumo_bin, sumo_home)
from gpd_jax.geometry import AREA_KIND_ID, SIGNAL_STATE_ID
from gpd_jax.scene import TYPE_ID

log = logging.getLogger(__name__)


# (name, length, width, probability, scene type, max speed m/s, accel, decel)
VEHICLE_MIX = (
    ("g_car", 4.6, 1.85, 0.55, "car", 50.0, 2.6, 4.5),
    ("g_suv", 5.1, 2.0, 0.17, "car", 50.0, 2.4, 4.5),
    ("g_van", 6.5, 2.1, 0.12, "van", 36.0, 2.0, 4.0),
    ("g_truck", 10.0, 2.5, 0.09, "truck", 30.0, 1.3, 4.0),
    ("g_bus", 12.0, 2.55, 0.07, "bus", 28.0, 1.2, 4.0),
)


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
        run_sumo_tool([sys.executable, os.path.join(tools, "randomTrips.py"), "-n", net_path, "-o", trips, "-r", routes,
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
        # the traffic lights' states as simulated, every step (an output only: the run is the same without it)
        tls_out, tls_add = os.path.join(wd, "tls.csv"), os.path.join(wd, "tls.add.xml")
        with open(tls_add, "w") as f:
            f.write(f'<additional><timedEvent type="SaveTLSStates" dest="{tls_out}"/></additional>\n')
        adds.append(tls_add)
        run_sumo_tool([sumo_bin("sumo"), "-n", net_path, "-r", ",".join(route_files), "-a", ",".join(adds),
                       "--step-length", "0.1", "--lanechange.duration", "3", "--fcd-output", fcd,
                       "--output.format", "csv", "--fcd-output.attributes", "x,y,angle,speed",
                       "--device.fcd.begin", f"{cfg.warmup_s:.1f}",
                       "-e", f"{end - 0.05:.2f}", "--statistic-output", stats, "--time-to-teleport",
                       f"{cfg.time_to_teleport:.0f}", "--no-step-log", "true", "--no-warnings", "true",
                       "--seed", str(seed % (2**31)), "--collision.action", "warn", "--precision", "3",
                       "--stop-output", stops, "--stop-output.write-unfinished", "true",
                       "--ignore-route-errors", "true", *cfg.extra_sumo_args],
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
        signals = read_signal_states(tls_out, read_network_signals(net_path), raw.timestamps)
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
    # SUMO's lanes, junctions and parking strips are the whole road: their outline is the road's edge
    return dataclasses.replace(raw, lanes=lanes, areas=tuple(areas) + extra_areas, areas_outline="drivable_area",
                               signals=signals)


def read_signal_states(path: str, links, timestamps: np.ndarray) -> RawSignals | None:
    """The states of `links` (`read_network_signals`) in each frame of a log (`timestamps` f64[F], simulation
    seconds) from SUMO's `SaveTLSStates` output at `path`; None when the network has no traffic light. A frame
    before a light's first record is unknown (0); a record holds until the next."""
    if not links:
        return None
    F = len(timestamps)
    col = {(ln.tl, ln.index): j for j, ln in enumerate(links)}
    by_tl: dict[str, list[tuple[int, int]]] = {}
    for (tl, index), j in col.items():
        by_tl.setdefault(tl, []).append((index, j))
    code = {c: SIGNAL_STATE_ID[v] for c, v in SUMO_LINK_STATES.items()}
    state = np.zeros((F, len(links)), np.int8)
    records = []  # SUMO writes its outputs as CSV here (--output.format csv): tlsState_time;..._id;..._state
    try:
        with open(path) as f:
            rows = [ln.rstrip("\n").split(";") for ln in f if ln.strip()]
        if rows:
            col_of = {k.rsplit("_", 1)[-1]: i for i, k in enumerate(rows[0])}
            i_t, i_id, i_st = col_of["time"], col_of["id"], col_of["state"]
            records = [(float(r[i_t]), r[i_id], r[i_st]) for r in rows[1:]]
    except (OSError, ValueError, KeyError, IndexError) as e:
        raise DataError(path, f"unreadable traffic-light output: {e}") from e
    seen = np.zeros((F, len(links)), bool)
    for time, tl, st in sorted(records, key=lambda r: r[0]):
        f = min(int(np.searchsorted(timestamps, time - 0.05)), F - 1)  # the first frame at or after the record
        if time - 0.05 > timestamps[-1]:
            continue
        for index, j in by_tl.get(tl, ()):
            if index < len(st):
                state[f, j] = code.get(st[index], 0)
                seen[f, j] = True
    # a record holds until the next: carry each link's last recorded frame forward
    last = np.maximum.accumulate(np.where(seen, np.arange(F)[:, None], -1), axis=0)
    state = np.where(last >= 0, np.take_along_axis(state, np.maximum(last, 0), axis=0), 0).astype(np.int8)
    return RawSignals(stop=np.stack([ln.stop for ln in links]), lane=tuple(ln.lane for ln in links), state=state)


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
