"""The job runner every importer (`gpd_jax.data.sources`) shares: jobs -> shards, with workers, progress, resume,
splits by location and the manifest.

A build is a list of *jobs*; each job is one SUMO run, one nuPlan log or one chunk of ScenarioNet scenario files,
and writes one shard; an executor (`gpd_jax.data.executors`: local processes, or Ray tasks over a cluster) runs
them. A job that finished leaves `DIR/_jobs/job_<j>.json` (`job_marker`), so a stopped build
started again with the same arguments skips it and resumes where it left off (`run_jobs`). Splits are made by
location (road network / map, `assign_splits`): every job of a location goes to the same split, so no test scene
shares a road with training. Settings are recorded in `DIR/_jobs/settings.json` only once the inputs are
validated (`check_settings`); `finish` writes the manifest (`dataset.json`) with the build's settings, statistics
and `build.overlap_gate` (how many candidate windows had two overlapping recorded boxes and whether the gate
removed them, `overlap_gate_summary`).

Nothing here knows a source: the importers (`gpd_jax.data.sources`) import this module, never the reverse.
"""

from __future__ import annotations

import json
import logging
import os
from collections import Counter

import numpy as np

from gpd_jax.data import preprocess, store
from gpd_jax.data.errors import DataError
from gpd_jax.data import executors

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


def check_count(name: str, value, allow_none: bool = False) -> None:
    """Raises DataError unless `value` is an integer >= 1 (counts of scenarios, workers, ...)."""
    if value is None and allow_none:
        return
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise DataError(None, f"{name} must be an integer >= 1, got {value!r}")


def job_marker(out_dir: str, index: int) -> str:
    """`DIR/_jobs/job_<index>.json`: the summary a finished job leaves (its presence marks the job done)."""
    return os.path.join(out_dir, "_jobs", f"job_{index:05d}.json")


def existing_shard(out_dir: str, index: int) -> str | None:
    """The shard directory of job `index` in any split (left by an interrupted earlier attempt), else None."""
    for sp in store.list_splits(out_dir) if os.path.isdir(out_dir) else []:
        p = store.shard_dir(out_dir, sp, index)
        if os.path.isdir(p):
            return p
    return None


def run_jobs(jobs, fn, out_dir: str, workers: int, desc: str, executor=None) -> list[dict]:
    """Runs jobs not yet done (resume) with a tqdm bar over samples, on `executor` (`gpd_jax.data.executors`;
    default: `workers` local processes)."""
    from tqdm import tqdm

    done, todo = [], []
    for j in jobs:
        m = job_marker(out_dir, j.index)
        if os.path.isfile(m):
            with open(m) as f:
                done.append(json.load(f))
        else:
            todo.append(j)
    total = sum(j.num_samples for j in jobs)
    bar = tqdm(total=total, initial=sum(d["requested"] for d in done), desc=desc, unit="scn", smoothing=0.1)
    if done:
        log.info("resuming: %d of %d jobs already done", len(done), len(jobs))
    results = list(done)
    with executors.results(executor or executors.LocalExecutor(workers), fn, todo) as it:
        for _, r in it:
            results.append(r)
            bar.update(r["requested"])
    bar.close()
    return sorted(results, key=lambda r: r["index"])


def check_settings(out_dir: str, settings: dict) -> bool:
    """Records a build's settings in DIR/_jobs/settings.json, or checks them against those recorded there.

    Call it only once the inputs are validated. Settings of a build that finished no job are replaced;
    otherwise other settings raise DataError saying how to go on. Returns True when settings were replaced."""
    p = os.path.join(out_dir, "_jobs", "settings.json")
    if os.path.isfile(p):
        try:
            with open(p) as f:
                old = json.load(f)
        except ValueError:
            old = None
        finished = any(n.startswith("job_") and n.endswith(".json") for n in os.listdir(os.path.dirname(p)))
        if old != json.loads(json.dumps(settings)) and finished:
            diff = sorted(k for k in set(old or {}) | set(settings) if (old or {}).get(k) != settings.get(k))
            hint = (" It was built before the SUMO traffic options: resume it with --traffic legacy."
                    if "traffic" in diff and old and "traffic" not in old else "")
            raise DataError(out_dir, f"holds a build with other settings (differing: {', '.join(diff)}; see {p}). "
                                     f"Run the same command as before to resume it, use another --out, or delete "
                                     f"{out_dir} to start again.{hint}")
        if old == json.loads(json.dumps(settings)):
            return False
        store.atomic_write_json(p, settings)
        return True
    store.atomic_write_json(p, settings)
    return False


def overlap_gate_summary(stats: dict, reject_overlaps: bool) -> dict:
    """How many candidate windows had two overlapping recorded boxes, and whether the gate removed them."""
    checked = int(stats.get("overlap_gate_checked", 0))
    removed = int(stats.get("skip_overlapping_boxes", 0))
    overlapping = removed if reject_overlaps else int(stats.get("overlapping_windows_kept", 0))
    return {"enabled": bool(reject_overlaps), "windows_checked": checked, "windows_with_overlaps": overlapping,
            "windows_removed": removed, "share_with_overlaps": round(overlapping / checked, 4) if checked else None}


def finish(out_dir: str, settings: dict, results: list[dict], wall: float, extra_build: dict | None = None) -> dict:
    """Writes the manifest of a build from its settings and job summaries (`build`: settings, wall times, summed
    statistics, `overlap_gate`, `layouts` where jobs have one, `extra_build`, the first 200 rejections); adds
    `wall` to the build time of earlier invocations (`DIR/_jobs/build_time.json`). Returns the manifest."""
    tp = os.path.join(out_dir, "_jobs", "build_time.json")
    prev = 0.0
    if os.path.isfile(tp):
        with open(tp) as f:
            prev = json.load(f).get("total_s", 0.0)
    store.atomic_write_json(tp, {"total_s": prev + wall})
    stats: Counter = Counter()
    for r in results:
        stats.update(r.get("stats", {}))
    reject = settings["sample_config"].get("reject_overlaps", False)
    layouts: dict = {}
    for r in results:
        if r.get("layout"):
            e = layouts.setdefault(r["layout"], {"locations": set(), "samples": Counter()})
            e["locations"].add(r["location"])
            e["samples"][r["split"]] += r["num_samples"]
    layouts = {k: {"locations": len(v["locations"]), "samples": dict(v["samples"])} for k, v in sorted(layouts.items())}
    extra = {"build": {**settings, "build_wall_s": wall, "build_wall_s_all_invocations": prev + wall,
                       "jobs": len(results), "jobs_without_samples": sum(r["num_samples"] == 0 for r in results),
                       "stats": dict(stats), "overlap_gate": overlap_gate_summary(stats, reject),
                       **({"layouts": layouts} if layouts else {}), **(extra_build or {}),
                       "rejections": [x for r in results for x in r.get("rejections", [])][:200]}}
    manifest = store.write_manifest(out_dir, extra, preprocess.sample_spec(
        preprocess.SampleConfig(**{k: v for k, v in settings["sample_config"].items()})))
    skipped = {k: v for k, v in stats.items() if k.startswith(("skip", "agent_frames", "lane_"))}
    gate = manifest["build"]["overlap_gate"]
    log.info("built %d samples in %.1f s (%s); skips/clamps: %s; windows with overlapping boxes: %s of %s (%s)",
                manifest["num_samples"], wall, {k: v["num_samples"] for k, v in manifest["splits"].items()}, skipped,
                gate["windows_with_overlaps"], gate["windows_checked"], "removed" if reject else "kept")
    return manifest
