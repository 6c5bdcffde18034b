"""Planners x agent models on a set of scenes: closed-loop runs, nuPlan's scores per scenario, means (x100, as
papers print them) and every subscore. The library under `python -m gpd_jax.plan evaluate`.

Columns: OLS (open loop), NR-CLS (log-replay agents), R-CLS-idm (IDM agents, nuPlan's R-CLS) and R-CLS-gpd (GPD
agents). A policy's open-loop plan is its own `Policy.plan` where it has one (log, cv, idm, gpd_head); the GPD
zero-shot has none and its OLS reads its run with GPD agents (the model's imagined future from the current frame:
nothing from the log's future).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from gpd_jax.checkpoint import Model
from gpd_jax.geometry import ROAD_MISSING
from gpd_jax.scene import Scene
from gpd_jax.sim.agents import make_paths, project
from gpd_jax.sim.core import AGENT_MODELS, SimError, SimResult, SimScene, make_sim_scenes, run
from gpd_jax.sim.policies import HEAD_PLANNERS, PLANNERS, make_policy
from gpd_jax.sim.scores import cls_scores, ols_scores, road_queries
from gpd_jax.spec import ModelSpec

COLUMNS = {"log": "NR-CLS", "idm": "R-CLS-idm", "gpd": "R-CLS-gpd"}


def _future(spec: ModelSpec, x, axis: int = 0):
    c = spec.full_history - 1
    return jax.lax.slice_in_dim(x, c, spec.stored_frames_needed, axis=axis)


def score_one(spec: ModelSpec, scene: SimScene, fine_xy, fine_heading, fine_valid) -> dict:
    """CLS and its terms of one closed-loop run (stored-rate arrays [Ts, A, ...] of the run, unbatched)."""
    c = spec.full_history - 1
    exy, eh = _future(spec, fine_xy[:, 0]), _future(spec, fine_heading[:, 0])
    size = scene.view.size
    speed = jnp.linalg.norm(scene.log_velocity[c:], axis=-1)
    paths = make_paths(scene.log_xy[c:], scene.log_heading[c:], scene.log_valid[c:], speed)
    log_ego = _future(spec, scene.log_xy[:, 0])
    arcs, _, _ = project(paths.xy[0], paths.s[0], log_ego[jnp.array([0, log_ego.shape[0] - 1])])
    rq = road_queries(scene.road, exy, eh, size[0])
    return cls_scores(exy, eh, size[0], _future(spec, fine_xy[:, 1:]), _future(spec, fine_heading[:, 1:]),
                      _future(spec, fine_valid[:, 1:]), size[1:], paths.xy[0], paths.s[0], arcs[1] - arcs[0],
                      spec.stored_period_s, rq)


@functools.partial(jax.jit, static_argnames=("spec",))
def score_batch(spec: ModelSpec, scenes: SimScene, fine_xy, fine_heading, fine_valid) -> dict:
    """`score_one` vmapped over a batch: dict of f32[B]."""
    return jax.vmap(lambda s, x, h, v: score_one(spec, s, x, h, v))(scenes, fine_xy, fine_heading, fine_valid)


@functools.partial(jax.jit, static_argnames=("spec",))
def ols_batch(spec: ModelSpec, scenes: SimScene, plan) -> dict:
    """OLS of plans f32[B, F, 3] against the logged ego at the model's future frames: dict of f32[B]."""
    h = spec.num_history

    def one(sc, p):
        expert = jnp.concatenate([sc.view.xy[h:, 0], sc.view.heading[h:, 0, None]], -1)
        return ols_scores(p[: expert.shape[0]], expert, spec.horizons, spec.frame_period_s)

    return jax.vmap(one)(scenes, plan)


def check_road(scenes: Scene | SimScene, where: str = "the scenes") -> None:
    if getattr(scenes, "road", None) is None:
        raise SimError(f"{where}: {ROAD_MISSING} (the CLS scores need the drivable area and lane directions)")


def evaluate_planners(model: Model, scenes: Scene, planners: Sequence[str] = ("log", "cv", "idm", "gpd"),
                      agents: Sequence[str] = AGENT_MODELS, *, head_models: dict[str, Model] | None = None,
                      batch_size: int = 8, seed: int = 0, progress: bool = True,
                      log: Callable[[str], Any] = print, keep_runs: int = 0) -> tuple[dict, dict]:
    """Every planner against every agent model on stored-rate scenes Scene [n, ...] (with road geometry).

    Returns (results, extra): results = {"scenarios": n, "planners": {name: {"OLS": x, "NR-CLS": x, "R-CLS-idm": x,
    "R-CLS-gpd": x, "subscores": {column: {term: mean}}}}} (scores x100; only the agent columns asked for);
    extra = {"per_scenario": {planner: {column: {term: f32[n]}}}, "runs": {(planner, agents): SimResult of the
    first `keep_runs` scenarios}, "seconds": {(planner, agents): wall seconds of the runs}}.
    """
    for p in planners:
        if p not in PLANNERS:
            raise SimError(f"unknown planner {p!r}; known planners: {', '.join(PLANNERS)}")
    for a in agents:
        if a not in AGENT_MODELS:
            raise SimError(f"unknown agent model {a!r}; known: {', '.join(AGENT_MODELS)}")
    head_models = head_models or {}
    for p in planners:
        if p in HEAD_PLANNERS and p not in head_models:
            raise SimError(f"planner {p} needs a model with the planning head ({p}: --head-model / --scratch-head-model)")
    check_road(scenes)
    n = int(np.shape(scenes.xy)[0])
    spec = model.spec
    per: dict = {p: {} for p in planners}
    runs: dict = {}
    seconds: dict = {}
    batches = [(i, min(i + batch_size, n)) for i in range(0, n, batch_size)]
    jobs = [(p, a) for p in planners for a in agents]
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(batches) * len(jobs), desc="closed loop", unit="run")
    key = jax.random.key(seed)
    for bi, (lo, hi) in enumerate(batches):
        sub = jax.tree.map(lambda x: x[lo:hi], scenes)
        if hi - lo < batch_size:  # pad the last batch so every batch has one shape (one compile)
            pad = batch_size - (hi - lo)
            sub = jax.tree.map(lambda x: np.concatenate([np.asarray(x), np.repeat(np.asarray(x)[-1:], pad, 0)]), sub)
        sim = make_sim_scenes(model, sub)
        bkey = jax.random.fold_in(key, bi)
        for p in planners:
            pm = head_models.get(p, model)
            policy = make_policy(p, pm)
            plan = None
            for a in agents:
                t0 = time.perf_counter()
                out = run(model, sim, policy, bkey, agents=a)
                jax.block_until_ready(out.fine_xy)
                seconds[(p, a)] = seconds.get((p, a), 0.0) + time.perf_counter() - t0
                sc = score_batch(spec, sim, out.fine_xy, out.fine_heading, out.fine_valid)
                _append(per[p], COLUMNS[a], sc, hi - lo)
                if plan is None and out.plan is not None:
                    plan = out.plan
                if p == "gpd" and a == "gpd":
                    plan = jnp.concatenate([out.xy[:, spec.num_history:, 0], out.heading[:, spec.num_history:, 0, None]], -1)
                if keep_runs and lo < keep_runs:
                    runs.setdefault((p, a), []).append(jax.tree.map(lambda x: np.asarray(x)[: hi - lo], out))
                if bar is not None:
                    bar.update(1)
            if plan is None:  # the GPD zero-shot without a GPD-agent run: run one for its open-loop plan
                out = run(model, sim, policy, bkey, agents="gpd")
                plan = jnp.concatenate([out.xy[:, spec.num_history:, 0], out.heading[:, spec.num_history:, 0, None]], -1)
            _append(per[p], "OLS", ols_batch(spec, sim, plan), hi - lo)
    if bar is not None:
        bar.close()
    per = {p: {col: {k: np.concatenate(v) for k, v in d.items()} for col, d in cols.items()} for p, cols in per.items()}
    results = {"scenarios": n, "planners": {}}
    for p in planners:
        entry: dict = {}
        subs: dict = {}
        for col, d in per[p].items():
            main = "OLS" if col == "OLS" else "CLS"
            entry[col] = 100.0 * float(np.mean(d[main]))
            subs[col] = {k: float(np.mean(v)) for k, v in d.items() if k != main}
        results["planners"][p] = {**{c: entry[c] for c in ["OLS"] + [COLUMNS[a] for a in agents]},
                                  "subscores": subs}
    runs = {k: jax.tree.map(lambda *xs: np.concatenate(xs), *v) for k, v in runs.items()}
    return results, {"per_scenario": per, "runs": runs, "seconds": seconds}


def _append(store: dict, col: str, scores: dict, count: int) -> None:
    d = store.setdefault(col, {})
    for k, v in scores.items():
        d.setdefault(k, []).append(np.asarray(v)[:count])


def format_table(results: dict) -> str:
    """A Table-2-shaped table: one row per planner; OLS, NR-CLS, R-CLS-idm, R-CLS-gpd."""
    cols = ["OLS", "NR-CLS", "R-CLS-idm", "R-CLS-gpd"]
    names = {"log": "Log replay (expert)", "cv": "Constant velocity", "idm": "IDM (route)", "gpd": "GPD zero-shot",
             "gpd_head": "GPD + planning head", "gpd_head_scratch": "  head w/o pre-training"}
    present = [c for c in cols if any(c in r for r in results["planners"].values())]
    head = f"{'Planner':<24}" + "".join(f"{c:>11}" for c in present)
    lines = [f"Planning scores on {results['scenarios']} scenarios (nuPlan definitions, x100; CLS over 8 s at 10 Hz)",
             head, "-" * len(head)]
    for p, r in results["planners"].items():
        lines.append(f"{names.get(p, p):<24}" + "".join(f"{r[c]:>11.2f}" if c in r else f"{'':>11}" for c in present))
    return "\n".join(lines)
