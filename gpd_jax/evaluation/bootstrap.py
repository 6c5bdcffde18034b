"""How sure is a figure? Scene-level bootstrap intervals for the model / baseline ADE ratios, and paired
comparisons of models evaluated on the same scenes.

An evaluation's figures are ratios of sums over scenes (ADE = sum of per-agent errors / number of agents, and
the traffic-simulation ratio divides the model's ADE by constant velocity's on the same agents). Scenes, not
agents, are the independent draws (agents of one scene share its road and its traffic), so the intervals here
resample scenes: each bootstrap draw picks n of the n scenes with replacement and recomputes every ratio from
the drawn scenes' sums. Scenes simulated on one road network are not independent of each other either, and
held-out figures are about other roads: `unit="location"` draws whole road networks (the store's per-sample
locations) instead, the honest interval for "on networks it never saw" (wide, with few networks). Two runs on the
same scenes (the same store, split and scenario ids) are compared with the same draws for both (a paired
bootstrap), so what the scenes have in common cancels.

`evaluate(..., scene_sums=True)` (and every `rollout.py` run, as OUT/scene_sums.npz) keeps each scenario's sums:

    python -m gpd_jax.evaluation compare RUN_A RUN_B [RUN_C ...] [--unit scene|location] [--json OUT]

prints each run's ratio with its interval and every later run's difference to the first (`compare_runs`).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from gpd_jax.fsutil import atomic_path
from gpd_jax.metrics import TRACK_COMPONENTS
from gpd_jax.spec import EvalError

SCENE_SUMS_FILE = "scene_sums.npz"
_IDS = "__scenario_ids__"
_LOCATIONS = "__locations__"
UNITS = ("scene", "location")
MIN_LOCATIONS = 5  # a location bootstrap over fewer networks cannot see how much networks differ: refused
FEW_LOCATIONS = 10  # below this many networks a location bootstrap's interval is rough (said in the table)


@dataclasses.dataclass(frozen=True)
class SceneSums:
    """Every scenario's metric sums, in evaluation order.

    scenario_ids: tuple of n ids (the store's; the index as a string where it has none).
    sums: {path: f64[n, ...]}, path "tasks/<task>/<variant>/<horizon>/<key>" (agent sums: `<key>` ends in
      `_num` / `_den`), "baselines/<name>/<variant>/<horizon>/<key>", "counts/<key>"; summed over the scenarios
      they are the sums the run's metrics were reduced from.
    locations: n road-network names ('' where unknown; empty when none is known), for `unit="location"`.
    """

    scenario_ids: tuple[str, ...]
    sums: Mapping[str, np.ndarray]
    locations: tuple[str, ...] = ()

    @property
    def num_scenarios(self) -> int:
        return len(self.scenario_ids)


def flatten_sums(tree: Mapping[str, Any], prefix: str = "") -> dict[str, np.ndarray]:
    """A nested dict of arrays -> {"a/b/c": array}."""
    out: dict[str, np.ndarray] = {}
    for k, v in tree.items():
        path = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out |= flatten_sums(v, path + "/")
        else:
            out[path] = np.asarray(v, np.float64)
    return out


def scene_sums_from_batches(batches: Sequence[Mapping[str, Any]], scenario_ids: Sequence[str],
                            locations: Sequence[str] = ()) -> SceneSums:
    """Per-scenario sums pytrees of consecutive batches (leaves [b_i, ...], padding already dropped) -> SceneSums."""
    flat = [flatten_sums(b) for b in batches]
    sums = {k: np.concatenate([f[k] for f in flat], axis=0) for k in flat[0]} if flat else {}
    n = len(scenario_ids)
    for k, v in sums.items():
        if v.shape[0] != n:
            raise EvalError(f"scene sums: {k} has {v.shape[0]} scenarios, the run {n}")
    ids = tuple(s if s else str(i) for i, s in enumerate(scenario_ids))
    locs = tuple(str(x) for x in locations)
    if locs and len(locs) != n:
        raise EvalError(f"scene sums: {len(locs)} locations for {n} scenarios")
    return SceneSums(ids, sums, locs if any(locs) else ())


def save_scene_sums(path: str, ss: SceneSums) -> None:
    """Writes `ss` as an .npz (no pickles: ids are a unicode array), to a temporary file renamed into place."""
    arrays = {k.replace("/", "|"): v for k, v in ss.sums.items()}
    arrays[_IDS] = np.asarray(ss.scenario_ids, dtype=np.str_)
    arrays[_LOCATIONS] = np.asarray(ss.locations, dtype=np.str_)
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, **arrays)


def load_scene_sums(path: str) -> SceneSums:
    """Reads what `save_scene_sums` wrote; a run directory means its scene_sums.npz. Never unpickles."""
    if os.path.isdir(path):
        path = os.path.join(path, SCENE_SUMS_FILE)
    if not os.path.exists(path):
        raise EvalError(f"{path}: no per-scene sums (rollout.py writes {SCENE_SUMS_FILE} beside metrics.json; "
                        "runs made before it existed must be run again)")
    try:
        with np.load(path, allow_pickle=False) as z:
            if _IDS not in z.files:
                raise EvalError(f"{path}: not a scene-sums file (no scenario ids)")
            ids = tuple(str(s) for s in z[_IDS])
            locs = tuple(str(s) for s in z[_LOCATIONS]) if _LOCATIONS in z.files else ()
            sums = {k.replace("|", "/"): np.asarray(z[k], np.float64) for k in z.files if k not in (_IDS, _LOCATIONS)}
    except (OSError, ValueError) as e:
        raise EvalError(f"{path}: cannot read the per-scene sums: {e}") from None
    for k, v in sums.items():
        if v.ndim == 0 or v.shape[0] != len(ids):
            raise EvalError(f"{path}: {k} has shape {v.shape}, expected {len(ids)} scenarios first")
    if locs and len(locs) != len(ids):
        raise EvalError(f"{path}: {len(locs)} locations for {len(ids)} scenarios")
    return SceneSums(ids, sums, locs)


def _metric_sums(ss: SceneSums, where: str, metric: str, label: str) -> tuple[np.ndarray, np.ndarray]:
    """(num f64[n], den f64[n]) of `metric` (e.g. agent_ade, agent_ade_moving) under `where` at `label`."""
    num, den = f"{where}/{label}/{metric}_num", f"{where}/{label}/{metric}_den"
    if num not in ss.sums:
        have = sorted({k.split("/")[-1][:-4] for k in ss.sums if k.startswith(f"{where}/{label}/") and
                       k.endswith("_num")})
        raise EvalError(f"no {metric!r} sums under {where} at {label}" +
                        (f" (there are: {', '.join(have)})" if have else " (wrong task, baseline, variant or horizon)"))
    for comp in TRACK_COMPONENTS:  # along / cross-track errors share the moving class's denominator
        if den not in ss.sums:
            den = f"{where}/{label}/{metric.replace(f'_{comp}_', '_')}_den"
    if den not in ss.sums:
        raise EvalError(f"no denominator for {metric!r} under {where} at {label}")
    return ss.sums[num], ss.sums[den]


def horizon_labels(ss: SceneSums, task: str, variant: str) -> list[str]:
    """The horizon labels ("3s", ...) the sums hold for `task`, in time order."""
    pre = f"tasks/{task}/{variant}/"
    labels = sorted({k[len(pre):].split("/")[0] for k in ss.sums if k.startswith(pre)},
                    key=lambda s: float(s[:-1]))  # "3s", "0.5s": `gpd_jax.metrics.horizon_label`
    if not labels:
        tasks = sorted({k.split("/")[1] for k in ss.sums if k.startswith("tasks/")})
        raise EvalError(f"no sums of task {task!r} (variant {variant!r}); the run has: {', '.join(tasks)}")
    return labels


def ratio_draws(ss: SceneSums, weights: np.ndarray, *, task: str = "traffic_simulation",
                baseline: str = "constant_velocity", metric: str = "agent_ade", variant: str = "paper",
                label: str = "3s") -> np.ndarray:
    """The model / baseline ratio of `metric` for each row of scene weights f64[R, n] (1 for every scene: the
    run's own figure): f64[R], NaN where a draw has nothing to score."""
    tn, td = _metric_sums(ss, f"tasks/{task}/{variant}", metric, label)
    bn, bd = _metric_sums(ss, f"baselines/{baseline}/{variant}", metric, label)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (weights @ tn / (weights @ td)) / (weights @ bn / (weights @ bd))


def draws(n: int, resamples: int, seed: int, groups: Sequence[str] | None = None) -> np.ndarray:
    """f64[resamples, n]: how often each of n scenes is drawn in each bootstrap resample.

    Without `groups` scenes are drawn (n of n with replacement, a multinomial); with `groups` (one label per scene)
    whole groups are (G of the G groups with replacement), and each scene counts as often as its group."""
    if resamples < 100:
        raise EvalError(f"resamples must be >= 100, got {resamples}")
    rng = np.random.default_rng(seed)
    if groups is None:
        if n < 2:
            raise EvalError(f"a bootstrap needs at least 2 scenes, got {n}")
        return rng.multinomial(n, np.full(n, 1.0 / n), size=resamples).astype(np.float64)
    if len(groups) != n:
        raise EvalError(f"{len(groups)} group labels for {n} scenes")
    names, member = np.unique(np.asarray(groups, dtype=np.str_), return_inverse=True)
    g = len(names)
    if g < MIN_LOCATIONS:
        raise EvalError(f"a location bootstrap needs at least {MIN_LOCATIONS} locations, the scenes have {g} "
                        f"({', '.join(repr(str(x)) for x in names)}): with so few, its draws cannot show how much "
                        "networks differ; use unit='scene' and say how many networks the figure stands on")
    return rng.multinomial(g, np.full(g, 1.0 / g), size=resamples).astype(np.float64)[:, member]


def compare_runs(runs: Sequence[SceneSums], *, task: str = "traffic_simulation",
                 baseline: str = "constant_velocity", metric: str = "agent_ade", variant: str = "paper",
                 resamples: int = 2000, level: float = 0.95, seed: int = 0, unit: str = "scene") -> dict[str, Any]:
    """Each run's model / baseline ratio with a bootstrap interval, and each later run against the first.

    `unit`: what a draw resamples, "scene" or "location" (whole road networks: needs the runs' locations).

    Runs after the first must be on the same scenes in the same order (paired draws). Returns
    {"runs": [{label: {"ratio", "interval": [lo, hi]}}], "versus_first": [{label: {"difference" (this run's
    ratio minus the first's), "interval", "share_lower" (share of draws where this run's ratio is lower)}}],
    "scenarios", "locations" (how many), "unit", "resamples", "level", ...}. Percentile intervals; deterministic
    for a given `seed`.
    """
    if not runs:
        raise EvalError("compare_runs needs at least one run")
    if unit not in UNITS:
        raise EvalError(f"unit must be one of {', '.join(UNITS)}, got {unit!r}")
    if not 0.5 < level < 1.0:
        raise EvalError(f"level must be in (0.5, 1), got {level}")
    first = runs[0]
    for i, r in enumerate(runs[1:], 1):
        if r.scenario_ids != first.scenario_ids:
            if r.num_scenarios != first.num_scenarios:
                raise EvalError(f"run {i} has {r.num_scenarios} scenarios, run 0 has {first.num_scenarios}: a paired "
                                "comparison needs the same scenes")
            j = next(k for k, (a, b) in enumerate(zip(r.scenario_ids, first.scenario_ids)) if a != b)
            raise EvalError(f"run {i} differs from run 0 at scenario {j} ({r.scenario_ids[j]!r} against "
                            f"{first.scenario_ids[j]!r}): a paired comparison needs the same scenes in the same order")
    labels = horizon_labels(first, task, variant)
    locs = first.locations
    if unit == "location" and (not locs or "" in locs):
        raise EvalError("unit='location' needs every scenario's road network, and these sums do not have them "
                        "(stores record them per shard: `locations` in meta.json; rerun rollout.py on a store)")
    w = draws(first.num_scenarios, resamples, seed, locs if unit == "location" else None)
    ones = np.ones((1, first.num_scenarios))
    q = [(1 - level) / 2, 1 - (1 - level) / 2]
    kw = dict(task=task, baseline=baseline, metric=metric, variant=variant)
    per_run, versus = [], []
    boot = {lb: [ratio_draws(r, w, label=lb, **kw) for r in runs] for lb in labels}
    point = {lb: [float(ratio_draws(r, ones, label=lb, **kw)[0]) for r in runs] for lb in labels}
    for i in range(len(runs)):
        per_run.append({lb: {"ratio": point[lb][i], "interval": _interval(boot[lb][i], q)} for lb in labels})
        if i:
            d = {}
            for lb in labels:
                diff = boot[lb][i] - boot[lb][0]
                ok = np.isfinite(diff)
                d[lb] = {"difference": point[lb][i] - point[lb][0], "interval": _interval(diff, q),
                         "share_lower": float(np.mean(diff[ok] < 0)) if ok.any() else float("nan")}
            versus.append(d)
    return {"task": task, "baseline": baseline, "metric": metric, "variant": variant, "unit": unit,
            "scenarios": first.num_scenarios, "locations": len(set(locs)) if locs else None,
            "resamples": int(resamples), "level": level, "seed": seed,
            "runs": per_run, "versus_first": versus}


def _interval(x: np.ndarray, q: Sequence[float]) -> list[float]:
    x = x[np.isfinite(x)]
    return [float("nan")] * 2 if x.size == 0 else [float(v) for v in np.quantile(x, q)]


def format_comparison(res: dict[str, Any], names: Sequence[str]) -> str:
    """A text table of `compare_runs`' result; `names` label the runs."""
    labels = list(res["runs"][0])
    pct = f"{100 * res['level']:g} %"
    nloc = res.get("locations")
    where = f"{res['scenarios']} scenes" + (f" on {nloc} road networks" if nloc else "")
    head = (f"{res['task']} {res['metric']} / {res['baseline']} ({res['variant']}), {where}, "
            f"{res['resamples']} {res['unit']}-bootstrap draws, {pct} intervals")
    if res["unit"] == "location" and nloc < FEW_LOCATIONS:
        head += f" (only {nloc} networks: the intervals are rough)"
    w = max(len(n) for n in names)
    lines = [head, f"{'run'.ljust(w)} | " + " | ".join(f"{lb:>24}" for lb in labels)]
    for n, r in zip(names, res["runs"]):
        lines.append(f"{n.ljust(w)} | " + " | ".join(
            f"{r[lb]['ratio']:.4f} [{r[lb]['interval'][0]:.4f}, {r[lb]['interval'][1]:.4f}]" for lb in labels))
    if res["versus_first"]:
        lines.append(f"difference to {names[0]} (negative: lower ratio), interval, share of draws lower:")
        for n, d in zip(names[1:], res["versus_first"]):
            lines.append(f"{n.ljust(w)} | " + " | ".join(
                f"{d[lb]['difference']:+.4f} [{d[lb]['interval'][0]:+.4f}, {d[lb]['interval'][1]:+.4f}] "
                f"{d[lb]['share_lower']:.2f}" for lb in labels))
    return "\n".join(lines)
