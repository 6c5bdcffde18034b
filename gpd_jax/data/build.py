"""Dataset building: sources -> samples -> shards, with workers, progress, resume and splits by location.

A build is a list of *jobs*; each job is one SUMO run (or one nuPlan log) and writes one shard. A job that
finished leaves `DIR/_jobs/job_<j>.json`, so a stopped build started again with the same arguments skips
it and resumes where it left off. Splits are made by location (road network / map): every job of a
location goes to the same split, so no test scene shares a road with training.
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import json
import logging
import math
import multiprocessing
import os
import shutil
import time
from collections import Counter

import numpy as np

from gpd_jax.data import preprocess, store

log = logging.getLogger(__name__)

DEFAULT_FRACTIONS = (("train", 0.8), ("val", 0.1), ("test", 0.1))


def assign_splits(locations: list[str], seed: int, fractions=DEFAULT_FRACTIONS) -> dict[str, str]:
    """Location -> split. Deterministic in `seed`; every split with a positive fraction gets at least one
    location when there are enough (val and test need >= 3 locations; with 2: train and test; 1: train)."""
    locs = sorted(set(locations))
    n = len(locs)
    perm = [locs[i] for i in np.random.default_rng([seed, 3]).permutation(n)]
    names = [f[0] for f in fractions]
    counts = [0] * len(fractions)
    if n >= len(fractions):
        counts = [max(1, int(round(fr * n))) for _, fr in fractions]
        counts[0] = n - sum(counts[1:])
    elif n == 2 and len(fractions) >= 2:
        counts = [1] + [0] * (len(fractions) - 2) + [1]
    else:
        counts = [n] + [0] * (len(fractions) - 1)
    out, k = {}, 0
    for name, c in zip(names, counts):
        for loc in perm[k:k + c]:
            out[loc] = name
        k += c
    return out


@dataclasses.dataclass(frozen=True)
class SumoJob:
    index: int
    seed: int
    num_samples: int
    location: str
    split: str
    net_path: str | None = None  # None: generate from seed


def plan_sumo_jobs(num_scenarios: int, seed: int, nets: list[str] | None, per_job: int = 50,
                   split: str | None = None) -> list[SumoJob]:
    """Jobs of a SUMO build: `ceil(num_scenarios / per_job)` runs, one network each when generating,
    cycling over the given networks (with different demand seeds) otherwise."""
    n_jobs = max(1, math.ceil(num_scenarios / per_job))
    counts = [per_job] * n_jobs
    counts[-1] = num_scenarios - per_job * (n_jobs - 1)
    if nets:
        locs = [_net_location(nets[i % len(nets)]) for i in range(n_jobs)]
    else:
        locs = [f"gen_{seed}_{i:04d}" for i in range(n_jobs)]
    splits = {l: split for l in locs} if split else assign_splits(locs, seed)
    ss = np.random.SeedSequence([seed, 1234])
    seeds = [int(s.generate_state(1)[0]) for s in ss.spawn(n_jobs)]
    return [SumoJob(i, seeds[i], counts[i], locs[i], splits[locs[i]],
                    nets[i % len(nets)] if nets else None) for i in range(n_jobs)]


def _net_location(path: str) -> str:
    base = os.path.basename(path)
    for suf in (".gz", ".xml", ".net"):
        if base.endswith(suf):
            base = base[: -len(suf)]
    parent = os.path.basename(os.path.dirname(os.path.abspath(path)))
    return f"{parent}_{base}"


def _job_marker(out_dir: str, index: int) -> str:
    return os.path.join(out_dir, "_jobs", f"job_{index:05d}.json")


def _existing_shard(out_dir: str, index: int) -> str | None:
    for sp in store.list_splits(out_dir) if os.path.isdir(out_dir) else []:
        p = store.shard_dir(out_dir, sp, index)
        if os.path.isdir(p):
            return p
    return None


def run_sumo_job(job: SumoJob, out_dir: str, sample_cfg: preprocess.SampleConfig,
                 sim_cfg=None, max_tries: int = 4) -> dict:
    """Runs one SUMO job (network, demand, simulation, samples, shard). Returns its summary."""
    from gpd_jax.data import sumo

    sim_cfg = sim_cfg or (sumo.REAL_NETWORK_SIM if job.net_path else sumo.SimConfig())
    t0 = time.time()
    work = os.path.join(out_dir, "_work", f"job_{job.index:05d}")
    shutil.rmtree(work, ignore_errors=True)
    os.makedirs(work)
    stats: Counter = Counter()
    rejections = []
    samples, ids = [], []
    try:
        density = sim_cfg.insertion_density
        for attempt in range(max_tries):
            seed = job.seed + 7919 * attempt
            if job.net_path is None:
                spec = sumo.random_net_spec(seed if attempt >= 2 else job.seed)  # new network after 2 tries
                if spec.junction == "priority":
                    density_eff = density * 0.6  # unsignalized networks saturate earlier
                else:
                    density_eff = density
                net = sumo.generate_network(spec, os.path.join(work, "net.net.xml"))
            else:
                spec, net, density_eff = None, job.net_path, density
            cfg = dataclasses.replace(sim_cfg, insertion_density=density_eff)
            try:
                raw = sumo.simulate(net, f"{job.location}_s{seed}", job.location, seed, cfg, workdir=work)
            except sumo.SumoRunRejected as e:
                rejections.append(str(e))
                stats["sumo_runs_rejected"] += 1
                density *= 0.7
                continue
            for sid, s in preprocess.iter_samples(raw, sample_cfg, num=job.num_samples, seed=seed, stats=stats):
                ids.append(sid)
                samples.append(s)
            if samples:
                break
            rejections.append(f"{job.location}: no usable windows")
        if samples:
            arrays = store.stack_samples(samples, preprocess.sample_spec(sample_cfg))
            existing = _existing_shard(out_dir, job.index)
            if existing:
                shutil.rmtree(existing)
            store.write_shard(out_dir, job.split, job.index, arrays, ids, [job.location] * len(ids),
                              extra={"source": "sumo", "job_seed": job.seed,
                                     "net": job.net_path or dataclasses.asdict(spec)})
    finally:
        shutil.rmtree(work, ignore_errors=True)
    summary = {"index": job.index, "split": job.split, "location": job.location, "num_samples": len(samples),
               "requested": job.num_samples, "wall_s": time.time() - t0, "stats": dict(stats),
               "rejections": rejections}
    store.atomic_write_json(_job_marker(out_dir, job.index), summary)
    return summary


def _worker_init():
    logging.basicConfig(level=logging.WARNING)


def run_jobs(jobs, fn, out_dir: str, workers: int, desc: str) -> list[dict]:
    """Runs jobs not yet done (resume), `workers` processes, with a tqdm bar over samples."""
    from tqdm import tqdm

    done, todo = [], []
    for j in jobs:
        m = _job_marker(out_dir, j.index)
        if os.path.isfile(m):
            with open(m) as f:
                done.append(json.load(f))
        else:
            todo.append(j)
    total = sum(j.num_samples for j in jobs)
    bar = tqdm(total=total, initial=sum(d["requested"] for d in done), desc=desc, unit="scn", smoothing=0.1)
    if done:
        log.warning("resuming: %d of %d jobs already done", len(done), len(jobs))
    results = list(done)
    if workers <= 1:
        for j in todo:
            r = fn(j)
            results.append(r)
            bar.update(r["requested"])
    else:
        ctx = multiprocessing.get_context("spawn")
        with cf.ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init) as ex:
            futs = {ex.submit(fn, j): j for j in todo}
            for fut in cf.as_completed(futs):
                r = fut.result()
                results.append(r)
                bar.update(r["requested"])
    bar.close()
    return sorted(results, key=lambda r: r["index"])


class _Bound:
    """Picklable job runner bound to its settings."""

    def __init__(self, out_dir, sample_cfg, sim_cfg):
        self.out_dir, self.sample_cfg, self.sim_cfg = out_dir, sample_cfg, sim_cfg

    def __call__(self, job):
        return run_sumo_job(job, self.out_dir, self.sample_cfg, self.sim_cfg)


def build_sumo(out_dir: str, num_scenarios: int, seed: int = 0, nets: list[str] | None = None,
               workers: int = 2, split: str | None = None, per_job: int = 50,
               sample_cfg: preprocess.SampleConfig | None = None, sim_cfg=None) -> dict:
    """Builds (or resumes) a SUMO dataset in `out_dir`. Returns the manifest."""
    t0 = time.time()
    sample_cfg = sample_cfg or default_sumo_sample_config()
    os.makedirs(out_dir, exist_ok=True)
    store.clean_temporaries(out_dir)
    shutil.rmtree(os.path.join(out_dir, "_work"), ignore_errors=True)
    if nets:
        for n in nets:
            if not os.path.isfile(n):
                from gpd_jax.data.errors import DataError
                raise DataError(n, "network file not found")
    settings = {"source": "sumo", "num_scenarios": num_scenarios, "seed": seed,
                "nets": [os.path.abspath(n) for n in nets] if nets else None, "split": split,
                "per_job": per_job, "sample_config": dataclasses.asdict(sample_cfg),
                "sim_config": dataclasses.asdict(sim_cfg) if sim_cfg else None}
    _check_settings(out_dir, settings)
    jobs = plan_sumo_jobs(num_scenarios, seed, nets, per_job, split)
    results = run_jobs(jobs, _Bound(out_dir, sample_cfg, sim_cfg), out_dir, workers, "sumo build")
    return _finish(out_dir, settings, results, time.time() - t0)


def default_sumo_sample_config() -> preprocess.SampleConfig:
    return preprocess.SampleConfig(min_neighbours=6, min_ego_travel=30.0, reject_overlaps=True)


def _check_settings(out_dir: str, settings: dict) -> None:
    p = os.path.join(out_dir, "_jobs", "settings.json")
    if os.path.isfile(p):
        with open(p) as f:
            old = json.load(f)
        if old != json.loads(json.dumps(settings)):
            raise ValueError(f"{out_dir} holds a build with other settings ({p}); use another --out "
                             f"or delete it")
    else:
        store.atomic_write_json(p, settings)


def _finish(out_dir: str, settings: dict, results: list[dict], wall: float) -> dict:
    tp = os.path.join(out_dir, "_jobs", "build_time.json")
    prev = 0.0
    if os.path.isfile(tp):
        with open(tp) as f:
            prev = json.load(f).get("total_s", 0.0)
    store.atomic_write_json(tp, {"total_s": prev + wall})
    stats: Counter = Counter()
    for r in results:
        stats.update(r.get("stats", {}))
    extra = {"build": {**settings, "build_wall_s": wall, "build_wall_s_all_invocations": prev + wall,
                       "jobs": len(results), "jobs_without_samples": sum(r["num_samples"] == 0 for r in results),
                       "stats": dict(stats),
                       "rejections": [x for r in results for x in r.get("rejections", [])][:200]}}
    manifest = store.write_manifest(out_dir, extra, preprocess.sample_spec(
        preprocess.SampleConfig(**{k: v for k, v in settings["sample_config"].items()})))
    skipped = {k: v for k, v in stats.items() if k.startswith(("skip", "agent_frames", "lane_"))}
    log.warning("built %d samples in %.1f s (%s); skips/clamps: %s", manifest["num_samples"], wall,
                {k: v["num_samples"] for k, v in manifest["splits"].items()}, skipped)
    return manifest


# ---------------------------------------------------------------------------------------------- nuPlan
@dataclasses.dataclass(frozen=True)
class LogJob:
    index: int
    path: str
    num_samples: int  # 0 = all windows
    split: str | None


def build_nuplan(out_dir: str, db: str, maps_root: str, seed: int = 0, split: str | None = None,
                 max_per_log: int | None = None, sample_cfg: preprocess.SampleConfig | None = None) -> dict:
    """Builds a dataset from nuPlan logs (`gpd_jax.data.nuplan.iter_logs`), one shard per log."""
    from gpd_jax.data import nuplan  # written separately; imported lazily

    t0 = time.time()
    sample_cfg = sample_cfg or preprocess.SampleConfig()
    os.makedirs(out_dir, exist_ok=True)
    store.clean_temporaries(out_dir)
    settings = {"source": "nuplan", "db": os.path.abspath(db), "maps": os.path.abspath(maps_root), "seed": seed,
                "split": split, "max_per_log": max_per_log, "sample_config": dataclasses.asdict(sample_cfg)}
    _check_settings(out_dir, settings)
    # Splits by map: read only the log headers first, then stream the logs one at a time (flat memory).
    paths = nuplan.find_logs(db)
    if split:
        split_of = {p: split for p in paths}
    else:
        key = {}
        for p in paths:
            try:
                key[p] = nuplan.read_log_header(p).map_version.removesuffix(".gpkg")
            except Exception:  # noqa: BLE001 - a bad file is reported (and skipped) when it is read
                pass
        by_loc = assign_splits(list(key.values()), seed)
        split_of = {p: by_loc.get(key.get(p), "train") for p in paths}
    results = []
    errors: list = []
    from tqdm import tqdm

    bar = tqdm(total=len(paths), desc="nuplan build", unit="log")
    done = {}
    for i, p in enumerate(paths):
        m = _job_marker(out_dir, i)
        if os.path.isfile(m):
            with open(m) as f:
                done[i] = json.load(f)
    todo = [p for i, p in enumerate(paths) if i not in done]
    results = list(done.values())
    bar.update(len(done))
    index_of = {p: i for i, p in enumerate(paths)}
    raws = nuplan.iter_logs(todo[0] if len(todo) == 1 else db, maps_root, skip_bad=True, errors=errors) if todo else []
    for raw in raws:
        i = next((index_of[p] for p in todo if os.path.splitext(os.path.basename(p))[0] == raw.name), None)
        if i is None or i in done:
            continue
        t1 = time.time()
        stats: Counter = Counter()
        pairs = list(preprocess.iter_samples(raw, sample_cfg, num=max_per_log, seed=seed, stats=stats))
        sp = split_of[paths[i]]
        if pairs:
            arrays = store.stack_samples([q[1] for q in pairs], preprocess.sample_spec(sample_cfg))
            existing = _existing_shard(out_dir, i)
            if existing:
                shutil.rmtree(existing)
            store.write_shard(out_dir, sp, i, arrays, [q[0] for q in pairs], [raw.location] * len(pairs),
                              extra={"source": "nuplan", "log": raw.name})
        r = {"index": i, "split": sp, "location": raw.location, "num_samples": len(pairs),
             "requested": len(pairs), "wall_s": time.time() - t1, "stats": dict(stats), "rejections": []}
        store.atomic_write_json(_job_marker(out_dir, i), r)
        results.append(r)
        bar.update(1)
    bar.close()
    if errors:
        log.warning("skipped %d bad nuPlan logs: %s", len(errors), "; ".join(map(str, errors[:5])))
        results.append({"index": -1, "num_samples": 0, "requested": 0, "stats": {"logs_skipped_bad": len(errors)},
                        "rejections": [str(e) for e in errors]})
    return _finish(out_dir, settings, results, time.time() - t0)


# ------------------------------------------------------------------------------------------ ScenarioNet
@dataclasses.dataclass(frozen=True)
class ScenarioNetJob:
    """Scenario files of one split and one dataset ("waymo", "nuscenes", ...) that make one shard.

    `paths` and `locations` (the split key of each file) are parallel tuples; `num_samples` is the number of
    scenarios (what `run_jobs` counts on its progress bar)."""

    index: int
    split: str
    dataset: str
    paths: tuple[str, ...]
    locations: tuple[str, ...]

    @property
    def num_samples(self) -> int:
        return len(self.paths)


def _scenarionet_index(out_dir: str, files, fingerprint: str) -> list[tuple[str, str]]:
    """(location, dataset) of every scenario file: from `dataset_summary.pkl` where there is one, otherwise by
    reading each file once (cached in `_jobs/scenario_index.json`, so a resumed build does not read them again)."""
    from tqdm import tqdm

    from gpd_jax.data import safe_pickle, scenarionet

    if all(f.metadata is not None for f in files):
        return [(scenarionet.scenario_location(f.metadata, scenarionet.file_stem(f.path)),
                 scenarionet.scenario_dataset(f.metadata)) for f in files]
    p = os.path.join(out_dir, "_jobs", "scenario_index.json")
    if os.path.isfile(p):
        with open(p) as fh:
            cached = json.load(fh)
        if cached.get("fingerprint") == fingerprint and len(cached.get("index", [])) == len(files):
            return [tuple(x) for x in cached["index"]]
    out = []
    for f in tqdm(files, desc="scenarionet index", unit="scn"):
        md = f.metadata
        if md is None:
            sc = safe_pickle.load(f.path)
            md = sc.get("metadata") if isinstance(sc, dict) else None
        out.append((scenarionet.scenario_location(md, scenarionet.file_stem(f.path)), scenarionet.scenario_dataset(md)))
    store.atomic_write_json(p, {"fingerprint": fingerprint, "index": out})
    return out


def _plan_scenarionet_jobs(paths: list[str], index: list[tuple[str, str]], seed: int, split: str | None,
                           per_job: int) -> list[ScenarioNetJob]:
    """Splits by location (`assign_splits`), then chunks of `per_job` files of one split and one dataset, in
    order of (split, dataset, location, path)."""
    locs = [loc for loc, _ in index]
    split_of = {loc: split for loc in locs} if split else assign_splits(locs, seed)
    rows = sorted(((split_of[loc], ds, loc, p) for p, (loc, ds) in zip(paths, index)))
    jobs: list[ScenarioNetJob] = []
    a = 0
    while a < len(rows):
        sp, ds = rows[a][0], rows[a][1]
        b = a
        while b < len(rows) and b - a < per_job and rows[b][:2] == (sp, ds):
            b += 1
        chunk = rows[a:b]
        jobs.append(ScenarioNetJob(len(jobs), sp, ds, tuple(r[3] for r in chunk), tuple(r[2] for r in chunk)))
        a = b
    return jobs


def run_scenarionet_job(job: ScenarioNetJob, out_dir: str, sample_cfg: preprocess.SampleConfig,
                        max_per_log: int | None = None, seed: int = 0, skip_bad: bool = False) -> dict:
    """Reads the job's scenario files (`gpd_jax.data.scenarionet.read_scenario`), cuts their windows and writes
    one shard. Returns the job summary; a bad file (`DataError`) is skipped and counted with `skip_bad`,
    otherwise the summary carries `error` = [path, reason] and no job marker is written (the job reruns)."""
    from gpd_jax.data import scenarionet
    from gpd_jax.data.errors import DataError

    t0 = time.time()
    stats: Counter = Counter()
    ids, samples, locs, rejections = [], [], [], []
    for path, loc in zip(job.paths, job.locations):
        try:
            raw = scenarionet.read_scenario(path, loc, stats)
            pairs = list(preprocess.iter_samples(raw, sample_cfg, num=max_per_log, seed=seed, stats=stats))
        except DataError as e:
            if not skip_bad:
                return {"index": job.index, "split": job.split, "num_samples": 0, "requested": len(job.paths),
                        "stats": {}, "rejections": [], "error": [e.path, e.reason]}
            stats["scenarios_skipped_bad"] += 1
            rejections.append(str(e))
            continue
        stats["scenarios_read"] += 1
        stats["scenarios_without_samples"] += not pairs
        for sid, s in pairs:
            ids.append(sid)
            samples.append(s)
            locs.append(raw.location)
    if samples:
        arrays = store.stack_samples(samples, preprocess.sample_spec(sample_cfg))
        for sp in store.list_splits(out_dir):  # a shard of an interrupted earlier attempt
            shutil.rmtree(store.shard_dir(out_dir, sp, job.index), ignore_errors=True)
        store.write_shard(out_dir, job.split, job.index, arrays, ids, locs,
                          extra={"source": "scenarionet", "dataset": job.dataset})
    summary = {"index": job.index, "split": job.split, "dataset": job.dataset, "num_samples": len(samples),
               "requested": len(job.paths), "wall_s": time.time() - t0, "stats": dict(stats),
               "rejections": rejections}
    store.atomic_write_json(_job_marker(out_dir, job.index), summary)
    return summary


class _ScenarioNetBound:
    """Picklable ScenarioNet job runner bound to its settings."""

    def __init__(self, out_dir, sample_cfg, max_per_log, seed, skip_bad):
        self.args = (out_dir, sample_cfg, max_per_log, seed, skip_bad)

    def __call__(self, job):
        return run_scenarionet_job(job, *self.args)


def build_scenarionet(out_dir: str, db: str, seed: int = 0, split: str | None = None,
                      max_per_log: int | None = None, workers: int = 1, per_job: int = 50,
                      skip_bad: bool = False, sample_cfg: preprocess.SampleConfig | None = None) -> dict:
    """Builds (or resumes) a dataset from ScenarioNet scenarios (`gpd_jax.data.scenarionet`).

    Args:
      out_dir: the store to write.
      db: a ScenarioNet dataset directory, a plain folder of scenario `.pkl` files, or one file.
      seed: split assignment and window choice seed.
      split: put everything into this split (default: splits by location, see `scenario_location`).
      max_per_log: at most this many windows per scenario (default: every `window_stride` frames).
      workers: processes; per_job: scenario files per job (one shard each, of one split and one dataset).
      skip_bad: skip (and count) files that raise `DataError` instead of stopping with that error.
    Raises `DataError` (naming the file) for a bad input file unless `skip_bad`, and `ValueError` when `out_dir`
    holds a build with other settings or of another set of files.
    """
    import hashlib

    from gpd_jax.data import scenarionet
    from gpd_jax.data.errors import DataError

    t0 = time.time()
    sample_cfg = sample_cfg or preprocess.SampleConfig()
    files = scenarionet.find_scenarios(db)
    h = hashlib.sha256()
    for f in files:
        h.update(f"{f.key}\0{os.path.getsize(f.path)}\n".encode())
    os.makedirs(out_dir, exist_ok=True)
    store.clean_temporaries(out_dir)
    settings = {"source": "scenarionet", "db": os.path.abspath(db), "seed": seed, "split": split,
                "max_per_log": max_per_log, "per_job": per_job, "skip_bad": skip_bad,
                "num_files": len(files), "files_sha256": h.hexdigest(),
                "sample_config": dataclasses.asdict(sample_cfg)}
    _check_settings(out_dir, settings)
    index = _scenarionet_index(out_dir, files, h.hexdigest())
    jobs = _plan_scenarionet_jobs([f.path for f in files], index, seed, split, per_job)
    bound = _ScenarioNetBound(out_dir, sample_cfg, max_per_log, seed, skip_bad)
    results = run_jobs(jobs, bound, out_dir, workers, "scenarionet build")
    failed = [r for r in results if r.get("error")]
    if failed:
        raise DataError(*failed[0]["error"])
    stats: Counter = Counter()
    for r in results:
        stats.update(r.get("stats", {}))
    short = stats.get("skip_log_too_short", 0)
    if short:
        log.warning("%d of %d scenarios are shorter than the %d frames (%.1f s at 10 Hz) a sample needs and gave "
                    "no sample (Waymo's scenarios are 91 frames)", short, len(files), sample_cfg.num_frames,
                    sample_cfg.num_frames / 10)
    man = _finish(out_dir, settings, results, time.time() - t0)
    return man
