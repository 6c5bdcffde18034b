"""The SUMO importer: generated or given road networks -> SUMO runs -> samples -> shards (`build_sumo`).

A SUMO build is a list of `SumoJob`s (`plan_sumo_jobs`): each one network + one demand seed + one SUMO run that
writes one shard, run by the shared job runner (`gpd_jax.data.jobs`: workers, resume, splits by location, the
manifest). Networks, their generation and reading are `gpd_jax.data.sources.sumo_networks`; demand, simulation and
FCD -> `RawLog` are `gpd_jax.data.sources.sumo_traffic`; this module cuts the runs into samples (`sumo_windows`,
`iter_sumo_samples`: which vehicle is the ego, `EgoChoice`) and writes the shards (`run_sumo_job`).

SUMO builds first make every job's network (`prepare_networks`: generated into `DIR/_networks`, or the given
files) with a fingerprint of its lane geometry, and check that no val/test network nearly matches a train
network (`check_near_duplicates`, `gpd_jax.data.netgeom`), before simulating anything. Each job's layout
("grid", "spider", "random", "real", "given") is recorded in its shard's `meta.json` ("layout", per sample
via `store.sample_layouts`), in the manifest's shard list and in `build.layouts`; generated locations are
named `gen_<seed>_<jjjj>_<layout>`, and scenario ids start with the location. `build.overlap_gate` says
how many candidate windows had two overlapping recorded boxes and whether the gate removed them.

SUMO builds simulate real traffic by default (`sumo_traffic.SimConfig` traffic options: parked and stopping
vehicles, heterogeneous drivers; left-hand and fixed-cycle generated networks) and choose egos as a recording car
would be (`EgoChoice`: 25 % stationary at the current frame); the options are recorded as `build.traffic` and in
every shard's meta (`traffic_settings`). `sumo_traffic.LEGACY_TRAFFIC` + `LEGACY_EGO` (CLI `--traffic legacy`)
give the stores built before.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import shutil
import time
from collections import Counter

import numpy as np

from gpd_jax.data import netgeom, preprocess, store
from gpd_jax.data.boxes import sample_has_overlap
from gpd_jax.data.errors import DataError
from gpd_jax.data.executors import LocalExecutor, run_all
from gpd_jax.data.jobs import (assign_splits, check_count, check_settings, existing_shard, finish, job_marker,
                               run_jobs)
from gpd_jax.data.sources import sumo_networks, sumo_traffic

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class SumoJob:
    index: int
    seed: int
    num_samples: int
    location: str
    split: str
    net_path: str | None = None  # None: generated from seed (into DIR/_networks/<location>.net.xml.gz)
    layout: str = ""  # "grid" | "spider" | "random" (generated), "real" (--real-networks) or "given" (--net)
    lefthand_share: float = 0.0  # generated networks: probability of left-hand traffic (`random_net_spec`)
    static_tls_share: float = 0.0  # generated networks: probability of fixed-cycle traffic lights
    curved_share: float = 0.0  # generated networks: probability of curved streets (`NetSpec.bend`)
    lefthand_net: bool = False  # given networks: simulate a left-hand copy (`make_lefthand`, in DIR/_networks)

    def net_spec(self):
        """The `sumo_networks.NetSpec` of a generated network (None for given networks)."""
        if self.net_path is not None:
            return None
        return sumo_networks.random_net_spec(self.seed, self.layout or None, self.lefthand_share,
                                             self.static_tls_share, self.curved_share)


@dataclasses.dataclass(frozen=True)
class EgoChoice:
    """How a SUMO build picks the ego of a window (`sumo_windows`).

    rule "mixed" (default): as a recording car would be: `stationary_share` of the windows take an ego that
      stands (< 0.5 m/s) at the current frame but moves at some time in the window (waiting at a light or in
      a queue; never a parked car), the others an ego that moves (>= 0.5 m/s) at the current frame, with no
      minimum distance travelled. 0.25 = the real logs' share (29 of 115 windows had a stationary ego).
    rule "travel" (stores built before): an ego whose centre moves `SampleConfig.min_ego_travel` (30 m)
      between the first and the last frame of the window (`preprocess.sample_windows`).
    Both: present throughout, at least `min_neighbours` vehicles within `agent_radius`, egos drawn with
    probability proportional to their neighbour count plus one.
    """

    rule: str = "mixed"
    stationary_share: float = 0.25
    min_path_m: float = 2.0  # a stationary ego still moves this far along its path within the window

    def __post_init__(self):
        if self.rule not in EGO_RULES:
            raise DataError(None, f"ego rule must be one of {EGO_RULES}, got {self.rule!r}")
        if not 0.0 <= self.stationary_share <= 1.0:
            raise DataError(None, f"ego stationary share must be in [0, 1], got {self.stationary_share!r}")


EGO_RULES = ("mixed", "travel")
LEGACY_EGO = EgoChoice("travel", 0.0)
STATIONARY_MPS = 0.5


def _assign_by_layout(locs: list[str], layouts: list[str], seed: int) -> dict[str, str]:
    """Splits by location, stratified by layout when every layout has >= 3 locations (so that val and test
    hold every layout and figures can be reported per layout), otherwise over all locations at once."""
    groups: dict[str, list[str]] = {}
    for loc, lay in zip(locs, layouts):
        groups.setdefault(lay, []).append(loc)
    if len(groups) < 2 or min(len(set(g)) for g in groups.values()) < 3:
        return assign_splits(locs, seed)
    out = {}
    for lay in sorted(groups):
        out.update(assign_splits(groups[lay], seed))
    return out


def plan_sumo_jobs(num_scenarios: int, seed: int, nets: list[str] | None, per_job: int = 50,
                   split: str | None = None, net_layout: str = "given", lefthand_share: float = 0.0,
                   static_tls_share: float = 0.0, curved_share: float = 0.0) -> list[SumoJob]:
    """Jobs of a SUMO build: `ceil(num_scenarios / per_job)` runs, one network each when generating,
    cycling over the given networks (with different demand seeds) otherwise; with fewer jobs than given
    networks, one job per network (as long as there are scenarios for it), the scenarios spread evenly.

    Generated networks take turns over the layouts grid / spider / random (in a seeded order), and their
    location names end in the layout (`gen_<seed>_<jjjj>_<layout>`); given networks get `net_layout`.
    `lefthand_share`: generated networks: probability of left-hand traffic (drawn from each network's seed);
    given networks: probability that a network is simulated as a left-hand copy (every job of it; its location
    gets the suffix "_lh"), drawn from `seed` and the network's name. `static_tls_share` / `curved_share`:
    generated networks: probability of fixed-cycle lights / curved streets (`sumo_networks.random_net_spec`).
    """
    check_count("num_scenarios", num_scenarios)
    check_count("per_job", per_job)
    n_jobs = max(1, math.ceil(num_scenarios / per_job))
    if nets and n_jobs < len(nets):
        n_jobs = min(len(nets), num_scenarios)
        counts = [num_scenarios // n_jobs + (i < num_scenarios % n_jobs) for i in range(n_jobs)]
    else:
        counts = [per_job] * n_jobs
        counts[-1] = num_scenarios - per_job * (n_jobs - 1)
    lh_net = [False] * n_jobs
    if nets:
        import zlib

        def lefthand_copy(path):
            key = zlib.crc32(_net_location(path).encode())
            return bool(np.random.default_rng([seed, 29, key]).uniform() < lefthand_share)

        lh_net = [lefthand_copy(nets[i % len(nets)]) for i in range(n_jobs)]
        locs = [_net_location(nets[i % len(nets)]) + ("_lh" if lh_net[i] else "") for i in range(n_jobs)]
        layouts = [net_layout] * n_jobs
    else:
        turn = np.random.default_rng([seed, 5]).permutation(n_jobs)
        layouts = [sumo_networks.LAYOUTS[int(turn[i]) % len(sumo_networks.LAYOUTS)] for i in range(n_jobs)]
        locs = [f"gen_{seed}_{i:04d}_{layouts[i]}" for i in range(n_jobs)]
    splits = {l: split for l in locs} if split else _assign_by_layout(locs, layouts, seed)
    ss = np.random.SeedSequence([seed, 1234])
    seeds = [int(s.generate_state(1)[0]) for s in ss.spawn(n_jobs)]
    return [SumoJob(i, seeds[i], counts[i], locs[i], splits[locs[i]],
                    nets[i % len(nets)] if nets else None, layouts[i], 0.0 if nets else lefthand_share,
                    0.0 if nets else static_tls_share, 0.0 if nets else curved_share, lh_net[i])
            for i in range(n_jobs)]


def _net_location(path: str) -> str:
    base = os.path.basename(path)
    for suf in (".gz", ".xml", ".net"):
        if base.endswith(suf):
            base = base[: -len(suf)]
    parent = os.path.basename(os.path.dirname(os.path.abspath(path)))
    return f"{parent}_{base}"


# --------------------------------------------------------------------------------------------- networks
def _generated_net_path(out_dir: str, location: str) -> str:
    return os.path.join(netgeom.networks_dir(out_dir), f"{location}.net.xml.gz")


def _prepare_network(args) -> tuple[str, dict]:
    """(location, index record) of one job's network: generates it (generated layouts) and writes its
    fingerprint, both beside the store in DIR/_networks; files already there are reused (resume)."""
    out_dir, job = args
    d = netgeom.networks_dir(out_dir)
    os.makedirs(d, exist_ok=True)
    fp_path = os.path.join(d, f"{job.location}.fp.npz")
    rec = {"layout": job.layout, "split": job.split, "fingerprint": os.path.basename(fp_path)}
    if job.net_path is None:
        spec = job.net_spec()
        net = _generated_net_path(out_dir, job.location)
        if not os.path.isfile(net):
            tmp = os.path.join(d, f".tmp-{job.location}-{os.getpid()}.net.xml.gz")
            try:
                sumo_networks.generate_network(spec, tmp)
                os.replace(tmp, net)
            finally:
                if os.path.exists(tmp):
                    os.remove(tmp)
        rec.update(net=os.path.relpath(net, out_dir), spec=dataclasses.asdict(spec))
    elif job.lefthand_net:
        net = _lefthand_net(out_dir, job)
        rec.update(net=os.path.relpath(net, out_dir), spec=None, source_net=os.path.abspath(job.net_path))
    else:
        net = job.net_path
        rec.update(net=os.path.abspath(net), spec=None)
    if os.path.isfile(fp_path):
        fp = netgeom.load_fingerprint(fp_path)
    else:
        fp = netgeom.fingerprint_network(net, job.location)
        netgeom.save_fingerprint(fp, fp_path)
    rec["lane_km"] = round(fp.length / 1000.0, 3)
    rec["lefthand"] = sumo_networks.is_lefthand(net)
    return job.location, rec


def _lefthand_net(out_dir: str, job: SumoJob) -> str:
    """The left-hand copy of a given network (made once, beside the store in DIR/_networks)."""
    net = _generated_net_path(out_dir, job.location)
    if not os.path.isfile(net):
        sumo_networks.make_lefthand(job.net_path, net)
    return net


def prepare_networks(jobs: list[SumoJob], out_dir: str, workers: int = 1, executor=None) -> dict[str, dict]:
    """Generates (or reuses) every job's network and fingerprint before any simulation, and writes
    `DIR/_networks/index.json`: location -> {"layout", "split", "net", "spec", "fingerprint", "lane_km"}
    (see `gpd_jax.data.netgeom.read_network_index`). Returns that index. Runs on `executor` (default: `workers`
    local processes when there are more than 4 networks)."""
    first = {}
    for j in jobs:
        first.setdefault(j.location, j)
    todo = [(out_dir, j) for j in first.values()]
    executor = executor or LocalExecutor(workers if len(todo) > 4 else 1)
    recs = run_all(executor, _prepare_network, todo)
    index = dict(sorted(recs))
    store.atomic_write_json(os.path.join(netgeom.networks_dir(out_dir), netgeom.NETWORKS_INDEX), index)
    return index


def check_near_duplicates(out_dir: str, index: dict[str, dict], against: list[str] | tuple = (),
                          tol: float | None = None) -> tuple[list[dict], dict]:
    """Near-duplicate networks (`gpd_jax.data.netgeom`): every val/test network of this build against every
    train network of this build, and, for each store in `against`, this build's val/test networks against
    its train networks and this build's train networks against its val/test networks.

    Returns (pairs, summary): pairs `{"evaluated", "evaluated_split", "reference", "reference_split",
    "reference_store", "distance_m"}`; summary `{"pairs_compared", "wall_s", "tol_m"}`.
    """
    tol = netgeom.DEFAULT_TOL if tol is None else tol
    t0 = time.time()
    d = netgeom.networks_dir(out_dir)
    mine = {loc: dataclasses.replace(netgeom.load_fingerprint(os.path.join(d, r["fingerprint"])), name=loc)
            for loc, r in index.items()}
    split_of = {loc: r["split"] for loc, r in index.items()}
    rows, n = [], 0

    def compare(ev, ref, ref_split, ref_store):
        nonlocal n
        for e in ev:
            for r in ref:
                n += 1
                dist = netgeom.geometry_distance(e, r)
                if dist < tol:
                    rows.append({"evaluated": e.name, "evaluated_split": split_of[e.name], "reference": r.name,
                                 "reference_split": ref_split[r.name], "reference_store": ref_store,
                                 "distance_m": round(float(dist), 3)})

    ev = [f for loc, f in mine.items() if split_of[loc] != "train"]
    tr = [f for loc, f in mine.items() if split_of[loc] == "train"]
    compare(ev, tr, split_of, None)
    for other in against:
        oidx = netgeom.read_network_index(other)
        ofp = {f.name: f for f in netgeom.store_fingerprints(other)}
        osplit = {loc: r.get("split") for loc, r in oidx.items()}
        compare(ev, [f for k, f in ofp.items() if osplit[k] == "train"], osplit, os.path.abspath(other))
        compare(tr, [f for k, f in ofp.items() if osplit[k] != "train"], osplit, os.path.abspath(other))
    return sorted(rows, key=lambda r: r["distance_m"]), {"pairs_compared": n, "wall_s": round(time.time() - t0, 3),
                                                         "tol_m": tol}


# ----------------------------------------------------------------------------------- windows -> samples
def sumo_windows(log, cfg: preprocess.SampleConfig, num: int | None, rng: np.random.Generator,
                 ego: EgoChoice = EgoChoice(), stats: Counter | None = None) -> list[tuple[int, int]]:
    """(start frame, ego track) pairs of a SUMO log under the ego rule `ego` (see `EgoChoice`); the "travel"
    rule is `preprocess.sample_windows`. "mixed": window starts in random order; at each, the egos present
    throughout with at least `min_neighbours` vehicles within `agent_radius` at the current frame are split
    into stationary (speed at the current frame < 0.5 m/s, path over the window >= `min_path_m`) and moving
    (>= 0.5 m/s); each kind takes egos (probability proportional to neighbours + 1) until it holds its quota
    (`stationary_share` of `num`, rounded); the two lists are interleaved in that share. A log with too few
    stationary candidates gives fewer stationary windows (counted in `stats` as "ego_windows_<kind>"). Counts in `stats`
    ("ego_windows_stationary" / "ego_windows_moving")."""
    if ego.rule == "travel":
        return preprocess.sample_windows(log, cfg, num, rng)
    T, c, F = cfg.num_frames, cfg.current, log.num_frames
    if F < T or log.ego_index is not None:
        return preprocess.sample_windows(log, cfg, num, rng)
    num = 1 if num is None else num
    quota = {"stationary": int(round(ego.stationary_share * num))}
    quota["moving"] = num - quota["stationary"]
    picked: dict[str, list[tuple[int, int]]] = {"stationary": [], "moving": []}
    starts = rng.permutation(F - T + 1)
    per_start = max(1, int(np.ceil(num / max(1, len(starts)))))
    cv = np.concatenate([np.zeros((1, log.num_agents), np.int64), np.cumsum(log.agent_valid, 0)], 0)
    for s in starts:
        if all(len(picked[k]) >= quota[k] for k in picked):
            break
        cand = np.nonzero((cv[s + T] - cv[s]) == T)[0]
        if len(cand) == 0:
            continue
        pc = log.agent_xy[s + c]
        others = pc[log.agent_valid[s + c]]
        nb = np.sum(np.linalg.norm(pc[cand][:, None] - others[None], axis=-1) <= cfg.agent_radius, axis=1) - 1
        cand, nb = cand[nb >= cfg.min_neighbours], nb[nb >= cfg.min_neighbours]
        if len(cand) == 0:
            continue
        step = np.linalg.norm(np.diff(log.agent_xy[s:s + T, cand], axis=0), axis=-1)  # [T-1, n]
        speed_c = step[c - 1] / 0.1
        kinds = {"stationary": (speed_c < STATIONARY_MPS) & (step.sum(0) >= ego.min_path_m),
                 "moving": speed_c >= STATIONARY_MPS}
        for kind, ok in kinds.items():
            take = min(per_start, int(ok.sum()), quota[kind] - len(picked[kind]))
            if take <= 0:
                continue
            p = (nb[ok] + 1.0) / np.sum(nb[ok] + 1.0)
            picked[kind] += [(int(s), int(e)) for e in rng.choice(cand[ok], size=take, replace=False, p=p)]
    # interleave in the stated share (stationary while fewer than the share of those so far, rounded), so that
    # the first windows that pass the later gates keep it; a kind that ran out leaves its turns to the other
    out: list[tuple[int, int]] = []
    i = {"stationary": 0, "moving": 0}
    while any(i[k] < len(picked[k]) for k in picked):
        turn = "stationary" if i["stationary"] < ego.stationary_share * (len(out) + 1) - 0.5 + 1e-9 else "moving"
        if i[turn] >= len(picked[turn]):
            turn = "moving" if turn == "stationary" else "stationary"
        out.append(picked[turn][i[turn]])
        i[turn] += 1
        if stats is not None:
            stats[f"ego_windows_{turn}"] += 1
    return out[:num]


def iter_sumo_samples(log, cfg: preprocess.SampleConfig, num: int | None, seed: int, stats: Counter,
                      ego: EgoChoice = EgoChoice()):
    """`preprocess.iter_samples` with the windows of `sumo_windows` (the same with the "travel" rule): yields
    (scenario id, sample); with the overlap gate, 3 x `num` candidate windows are drawn so that `num` come out."""
    if ego.rule == "travel":
        yield from preprocess.iter_samples(log, cfg, num=num, seed=seed, stats=stats)
        return
    preprocess.check_rawlog(log)
    if log.num_frames < cfg.num_frames:
        stats["skip_log_too_short"] += 1
        return
    rng = np.random.default_rng(seed)
    lp = preprocess.lane_points(log.lanes, cfg.lane_spacing)
    road = preprocess.road_index(log, cfg)
    want = None if num is None else (3 * num if cfg.reject_overlaps else num)
    made = 0
    windows = sumo_windows(log, cfg, want, rng, ego, stats)
    # the kinds come interleaved in the stated share: the first `num` windows that pass the gates keep it
    for start, e in windows:
        if num is not None and made >= num:
            break
        s = preprocess.make_sample(log, start, e, cfg, lp, stats, road)
        if s is None:
            continue
        if cfg.reject_overlaps:
            stats["overlap_gate_checked"] += 1
            if sample_has_overlap(s["xy"], s["heading"], s["valid"], s["size"]):
                stats["skip_overlapping_boxes"] += 1
                stats["samples"] -= 1
                continue
        made += 1
        still = float(np.linalg.norm(s["xy"][cfg.current, 0] - s["xy"][cfg.current - 1, 0])) / 0.1 < STATIONARY_MPS
        stats["ego_stationary_at_current"] += int(still)
        yield f"{log.name}/{start}/{log.agent_ids[e]}", s


# ----------------------------------------------------------------------------------- runs and the build
def traffic_settings(sim_cfg, ego: EgoChoice, lefthand_share: float, static_tls_share: float,
                     curved_share: float = 0.0) -> dict:
    """The real-traffic options of a SUMO build as recorded in its settings and shards (`curved_share` only
    where it is not 0, so that builds from before it resume)."""
    def plain(v):  # as JSON gives it back (tuples -> lists), so that recorded and fresh settings compare equal
        return list(v) if isinstance(v, tuple) else v

    return {**{k: plain(getattr(sim_cfg, k)) for k in sumo_traffic.TRAFFIC_FIELDS}, "ego_rule": ego.rule,
            "ego_stationary_share": ego.stationary_share, "lefthand_share": lefthand_share,
            "static_tls_share": static_tls_share, **({"curved_share": curved_share} if curved_share else {})}


def run_sumo_job(job: SumoJob, out_dir: str, sample_cfg: preprocess.SampleConfig,
                 sim_cfg=None, max_tries: int = 4, ego: EgoChoice = EgoChoice(), traffic: dict | None = None,
                 record: dict | None = None) -> dict:
    """Runs one SUMO job (demand, simulation, samples, shard) on its network (prepared by
    `prepare_networks`). A rejected run is retried on the same network with another demand seed and 30 %
    less demand, up to `max_tries` runs. `traffic`: `SimConfig` traffic fields set over the simulation
    config (REAL_NETWORK_SIM for given networks, SimConfig() for generated ones, unless `sim_cfg`). `record`:
    the build's traffic settings, written into the shard's meta (default: this job's). Returns the job summary."""
    sim_cfg = sim_cfg or (sumo_traffic.REAL_NETWORK_SIM if job.net_path else sumo_traffic.SimConfig())
    if traffic:
        sim_cfg = dataclasses.replace(sim_cfg, **traffic)
    t0 = time.time()
    work = os.path.join(out_dir, "_work", f"job_{job.index:05d}")
    shutil.rmtree(work, ignore_errors=True)
    os.makedirs(work)
    stats: Counter = Counter()
    rejections = []
    samples, ids = [], []
    if job.net_path is None:
        spec = job.net_spec()
        net = _generated_net_path(out_dir, job.location)
        if not os.path.isfile(net):  # run without prepare_networks (e.g. a direct call)
            os.makedirs(os.path.dirname(net), exist_ok=True)
            sumo_networks.generate_network(spec, net)
        # unsignalized networks saturate earlier
        density = sim_cfg.insertion_density * (0.6 if spec.junction == "priority" else 1.0)
    else:
        spec, density = None, sim_cfg.insertion_density
        net = _lefthand_net(out_dir, job) if job.lefthand_net else job.net_path
    try:
        lanes = sumo_networks.read_network_lanes(net)
        areas = sumo_networks.read_network_areas(net)
        for attempt in range(max_tries):
            seed = job.seed + 7919 * attempt
            cfg = dataclasses.replace(sim_cfg, insertion_density=density)
            info: dict = {}
            try:
                raw = sumo_traffic.simulate(net, f"{job.location}_s{seed}", job.location, seed, cfg, workdir=work,
                                            lanes=lanes, areas=areas, info=info)
            except sumo_networks.SumoRunRejected as e:
                rejections.append(str(e))
                stats["sumo_runs_rejected"] += 1
                density *= 0.7
                continue
            for k, v in info.items():
                if k in ("short_stops", "parking_spaces", "parked_vehicles", "parking_jumps_smoothed",
                         "planned_stop_frames", "vehicle_frames"):
                    stats[f"sim_{k}"] += int(v)
            for sid, s in iter_sumo_samples(raw, sample_cfg, job.num_samples, seed, stats, ego):
                if not sample_cfg.reject_overlaps:  # gate off: count what it would have removed
                    stats["overlap_gate_checked"] += 1
                    stats["overlapping_windows_kept"] += sample_has_overlap(s["xy"], s["heading"], s["valid"],
                                                                            s["size"])
                ids.append(sid)
                samples.append(s)
            if samples:
                break
            rejections.append(f"{job.location}: no usable windows")
        if samples:
            arrays = store.stack_samples(samples, preprocess.sample_spec(sample_cfg))
            existing = existing_shard(out_dir, job.index)
            if existing:
                shutil.rmtree(existing)
            store.write_shard(out_dir, job.split, job.index, arrays, ids, [job.location] * len(ids),
                              extra={"source": "sumo", "job_seed": job.seed, "layout": job.layout,
                                     "net": job.net_path or dataclasses.asdict(spec),
                                     "lefthand": sumo_networks.is_lefthand(net),
                                     "traffic": record or traffic_settings(sim_cfg, ego, job.lefthand_share,
                                                                           job.static_tls_share, job.curved_share)})
    finally:
        shutil.rmtree(work, ignore_errors=True)
    summary = {"index": job.index, "split": job.split, "location": job.location, "layout": job.layout,
               "num_samples": len(samples), "requested": job.num_samples, "wall_s": time.time() - t0,
               "stats": dict(stats), "rejections": rejections}
    store.atomic_write_json(job_marker(out_dir, job.index), summary)
    return summary


class _Bound:
    """Picklable job runner bound to its settings."""

    def __init__(self, out_dir, sample_cfg, sim_cfg, ego=EgoChoice(), traffic=None, record=None):
        self.out_dir, self.sample_cfg, self.sim_cfg, self.ego, self.traffic = out_dir, sample_cfg, sim_cfg, ego, traffic
        self.record = record

    def __call__(self, job):
        return run_sumo_job(job, self.out_dir, self.sample_cfg, self.sim_cfg, ego=self.ego, traffic=self.traffic,
                            record=self.record)


NETGEN_VERSION = 2  # 2: seed-drawn shapes + node perturbation, networks generated before the runs


def build_sumo(out_dir: str, num_scenarios: int, seed: int = 0, nets: list[str] | None = None,
               workers: int = 2, split: str | None = None, per_job: int = 50,
               sample_cfg: preprocess.SampleConfig | None = None, sim_cfg=None, *, net_layout: str = "given",
               keep_overlaps: bool = False, refuse_near_duplicates: bool = True,
               near_duplicate_tol: float | None = None, against: list[str] | tuple = (),
               traffic: dict | None = None, ego: EgoChoice = EgoChoice(), lefthand_share: float | None = None,
               static_tls_share: float = 0.5, curved_share: float = 0.0, executor=None) -> dict:
    """Builds (or resumes) a SUMO dataset in `out_dir`. Returns the manifest.

    Args:
      nets: networks to use instead of generating them (`sumo_networks.real_networks()` for SUMO's real ones);
        each is parsed before anything is written (a bad file raises DataError naming it).
      net_layout: the layout recorded for the given networks ("real" for `sumo_networks.real_networks()`).
      keep_overlaps: turn off the gate that drops windows in which two recorded boxes overlap.
      refuse_near_duplicates: raise DataError, before any simulation, when a val/test network's lane
        geometry nearly matches a train network's (`check_near_duplicates`); otherwise only warn. Either
        way the pairs go into the manifest (`build.near_duplicates`).
      against: other stores whose networks are checked against this build's (see `check_near_duplicates`).
      traffic: `sumo_traffic.SimConfig` traffic fields (`sumo_traffic.TRAFFIC_FIELDS`: parking, short stops,
        drivers) set over the simulation config; None keeps those of `sim_cfg` (default: `SimConfig`'s, parked
        vehicles, stops and heterogeneous drivers on); `sumo_traffic.LEGACY_TRAFFIC` = the behaviour of stores
        built before them.
      ego: how egos are chosen (`EgoChoice`; `LEGACY_EGO` = the 30 m travel rule of stores built before).
      lefthand_share: probability of left-hand traffic (`netconvert --lefthand`) per network: generated ones
        are built so, given ones simulated as a left-hand copy (`plan_sumo_jobs`). None: 0.25 for generated
        networks, 0 for given ones (a test store of given networks stays as it was unless asked).
      static_tls_share: generated networks: probability of fixed-cycle traffic lights (queues), drawn per
        network from its seed.
      curved_share: generated networks: probability of curved streets (bulges and S-bends,
        `sumo_networks.NetSpec.bend`), drawn per network from its seed; 0 (default) = straight streets as in
        every store built before it.
    All of them are recorded in the settings (`build.traffic` in the manifest) and in every shard's meta.
      executor: where the networks and the jobs run (`gpd_jax.data.executors`; default: `workers` local
        processes); the store is the same whatever runs them.
    """
    t0 = time.time()
    check_count("num_scenarios", num_scenarios)
    check_count("per_job", per_job)
    check_count("workers", workers)
    sample_cfg = sample_cfg or default_sumo_sample_config()
    if lefthand_share is None:
        lefthand_share = 0.0 if nets else 0.25
    for name, v in (("lefthand_share", lefthand_share), ("static_tls_share", static_tls_share),
                    ("curved_share", curved_share)):
        if not 0.0 <= v <= 1.0:
            raise DataError(None, f"{name} must be a share in [0, 1], got {v!r}")
    if nets and curved_share:
        raise DataError(None, f"curved_share={curved_share} bends generated networks only; given networks (--net, "
                              "--real-networks) keep their own shapes")
    if traffic:
        unknown = sorted(set(traffic) - set(sumo_traffic.TRAFFIC_FIELDS))
        if unknown:
            raise DataError(None, f"unknown traffic option(s) {unknown}; expected some of "
                                  f"{sumo_traffic.TRAFFIC_FIELDS}")
    eff_sim = dataclasses.replace(sim_cfg or sumo_traffic.SimConfig(), **(traffic or {}))
    sumo_traffic.check_sim_config(eff_sim)
    if ego.rule == "mixed":  # the mixed rule has no travel minimum: say so in the recorded sample config
        sample_cfg = dataclasses.replace(sample_cfg, min_ego_travel=0.0)
    if keep_overlaps:
        sample_cfg = dataclasses.replace(sample_cfg, reject_overlaps=False)
    for n in nets or []:  # parse every given network now, not after SUMO fails on it
        if not os.path.isfile(n):
            raise DataError(n, "network file not found")
        sumo_networks.read_network_lanes(n, merge_chains=False)
    for other in against:
        netgeom.read_network_index(other)
    os.makedirs(out_dir, exist_ok=True)
    store.clean_temporaries(out_dir)
    shutil.rmtree(os.path.join(out_dir, "_work"), ignore_errors=True)
    settings = {"source": "sumo", "num_scenarios": num_scenarios, "seed": seed,
                "nets": [os.path.abspath(n) for n in nets] if nets else None, "split": split,
                "per_job": per_job, "sample_config": dataclasses.asdict(sample_cfg),
                "sim_config": dataclasses.asdict(sim_cfg) if sim_cfg else None,
                "netgen_version": None if nets else NETGEN_VERSION, "net_layout": net_layout if nets else None,
                "traffic": traffic_settings(eff_sim, ego, lefthand_share, 0.0 if nets else static_tls_share,
                                            curved_share)}
    if _built_before_traffic_options(out_dir) and settings["traffic"] == traffic_settings(
            dataclasses.replace(eff_sim, **sumo_traffic.LEGACY_TRAFFIC), LEGACY_EGO, 0.0, 0.0):
        settings.pop("traffic")  # resuming a build from before the traffic options, with --traffic legacy
    if check_settings(out_dir, settings):  # an abandoned start with other settings: its networks go too
        shutil.rmtree(netgeom.networks_dir(out_dir), ignore_errors=True)
    jobs = plan_sumo_jobs(num_scenarios, seed, nets, per_job, split, net_layout, lefthand_share,
                          0.0 if nets else static_tls_share, curved_share)
    index = prepare_networks(jobs, out_dir, workers, executor)
    dups, dup_summary = check_near_duplicates(out_dir, index, against, near_duplicate_tol)
    if dups:
        lines = "; ".join(f"{d['evaluated']} ({d['evaluated_split']}) ~ {d['reference']} ({d['reference_split']}"
                          f"{', ' + d['reference_store'] if d['reference_store'] else ''}) {d['distance_m']} m"
                          for d in dups[:10])
        if refuse_near_duplicates:
            raise DataError(out_dir, f"{len(dups)} evaluation network(s) nearly match training networks (mean lane "
                                     f"distance < {dup_summary['tol_m']} m after rigid alignment): {lines}. Use other "
                                     f"networks, or build with --allow-near-duplicates to record them and go on")
        log.warning("%d evaluation network(s) nearly match training networks: %s", len(dups), lines)
    results = run_jobs(jobs, _Bound(out_dir, sample_cfg, sim_cfg, ego, traffic, settings.get("traffic")), out_dir,
                       workers, "sumo build", executor)
    extra = {"near_duplicates": dups, "near_duplicate_check": dup_summary,
             "networks": {loc: {k: r.get(k) for k in ("layout", "split", "lane_km", "lefthand")}
                          for loc, r in index.items()}}
    return finish(out_dir, settings, results, time.time() - t0, extra)


def default_sumo_sample_config() -> preprocess.SampleConfig:
    return preprocess.SampleConfig(min_neighbours=6, min_ego_travel=30.0, reject_overlaps=True)


def _built_before_traffic_options(out_dir: str) -> bool:
    """Whether `out_dir` holds SUMO build settings recorded before the traffic options existed."""
    p = os.path.join(out_dir, "_jobs", "settings.json")
    try:
        with open(p) as f:
            old = json.load(f)
    except (OSError, ValueError):
        return False
    return old.get("source") == "sumo" and "traffic" not in old
