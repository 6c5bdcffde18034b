"""Scoring closed-loop runs with nuPlan's planning scores, one run batch at a time (`score`) or planners x agent
models over a set of scenes (`evaluate_planners`, the library under `python -m gpd_jax.plan evaluate`).

    out = sim.run(model, sims, my_policy, jax.random.key(0), agents="idm")   # or sim.run_host(...)
    s = sim.score(model, sims, out)        # {"CLS": f32[B], "ego_is_comfortable": f32[B], ... (+ "OLS", ...)}

    results = sim.evaluate_planners(model, scenes, {"expert": "log", "mine": my_policy}, agents=("log", "idm"))
    print(sim.planning_table(results))     # results["planners"]["mine"]["NR-CLS"], ...["subscores"]

Both score a run the same way: CLS and its terms (`gpd_jax.sim.scores.cls_scores`) over the stored frames from
the current one to the end, and OLS (`gpd_jax.sim.scores.ols_scores`) of the policy's open-loop plan at the current
frame against the logged ego at the model's future frames.

Columns of `evaluate_planners`: OLS (open loop), NR-CLS (log-replay agents), R-CLS-idm (IDM agents, nuPlan's R-CLS)
and R-CLS-gpd (GPD agents). A policy's open-loop plan is its own `Policy.plan` where it has one (log, cv, idm,
gpd_head); a policy without one (the GPD zero-shot, or your own policy without `plan`) is scored on its closed-loop
run with GPD agents instead (for the GPD zero-shot: the model's imagined future from the current frame, nothing from
the log's future); that run is made for the purpose when GPD agents are not among `agents`.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from gpd_jax import distributed
from gpd_jax.checkpoint import Model
from gpd_jax.geometry import ROAD_MISSING, project_on_path
from gpd_jax.scene import Scene
from gpd_jax.sim.agents import make_paths
from gpd_jax.sim.core import AGENT_MODELS, Policy, SimError, SimResult, SimScene, as_policy, make_sim_scenes, run
from gpd_jax.sim.policies import HEAD_PLANNERS, PLANNERS, make_policy
from gpd_jax.sim.scores import cls_scores, ols_scores, road_queries
from gpd_jax.sim.tracker import Tracker
from gpd_jax.spec import ModelSpec

COLUMNS = {"log": "NR-CLS", "idm": "R-CLS-idm", "gpd": "R-CLS-gpd"}
PLANNER_TITLES = {"log": "Log replay (expert)", "cv": "Constant velocity", "idm": "IDM (route)",
                  "gpd": "GPD zero-shot", "gpd_head": "GPD + planning head",
                  "gpd_head_scratch": "  head w/o pre-training"}


# ------------------------------------------------------------------------------------------------ one batch of runs
def _future(spec: ModelSpec, x, axis: int = 0):
    c = spec.full_history - 1
    return jax.lax.slice_in_dim(x, c, spec.stored_frames_needed, axis=axis)


def _cls_one(spec: ModelSpec, scene: SimScene, fine_xy, fine_heading, fine_valid) -> dict:
    """CLS and its terms of one closed-loop run (stored-rate arrays [Ts, A, ...] of the run, unbatched)."""
    c = spec.full_history - 1
    exy, eh = _future(spec, fine_xy[:, 0]), _future(spec, fine_heading[:, 0])
    size = scene.view.size
    speed = jnp.linalg.norm(scene.log_velocity[c:], axis=-1)
    paths = make_paths(scene.log_xy[c:], scene.log_heading[c:], scene.log_valid[c:], speed)
    log_ego = _future(spec, scene.log_xy[:, 0])
    arcs, _, _ = project_on_path(paths.xy[0], paths.s[0], log_ego[jnp.array([0, log_ego.shape[0] - 1])])
    rq = road_queries(scene.road, exy, eh, size[0])
    return cls_scores(exy, eh, size[0], _future(spec, fine_xy[:, 1:]), _future(spec, fine_heading[:, 1:]),
                      _future(spec, fine_valid[:, 1:]), size[1:], paths.xy[0], paths.s[0], arcs[1] - arcs[0],
                      spec.stored_period_s, rq)


@functools.partial(jax.jit, static_argnames=("spec",))
def _cls_batch(spec: ModelSpec, scenes: SimScene, fine_xy, fine_heading, fine_valid) -> dict:
    """`_cls_one` vmapped over a batch: dict of f32[B]."""
    return jax.vmap(lambda s, x, h, v: _cls_one(spec, s, x, h, v))(scenes, fine_xy, fine_heading, fine_valid)


@functools.partial(jax.jit, static_argnames=("spec",))
def _ols_batch(spec: ModelSpec, scenes: SimScene, plan) -> dict:
    """OLS of plans f32[B, F, 3] against the logged ego at the model's future frames: dict of f32[B]."""
    h = spec.num_history

    def one(sc, p):
        expert = jnp.concatenate([sc.view.xy[h:, 0], sc.view.heading[h:, 0, None]], -1)
        return ols_scores(p[: expert.shape[0]], expert, spec.horizons, spec.frame_period_s)

    return jax.vmap(one)(scenes, plan)


def check_road(scenes: Scene | SimScene, where: str = "the scenes") -> None:
    """Raises SimError naming `where` when the scenes carry no road geometry (the CLS scores need it)."""
    if getattr(scenes, "road", None) is None:
        raise SimError(f"{where}: {ROAD_MISSING} (the CLS scores need the drivable area and lane directions)")


def score(model: Model, scenes: SimScene, out: SimResult) -> dict[str, np.ndarray]:
    """nuPlan's scores of a batch of closed-loop runs, per scenario, as `evaluate_planners` scores every planner.

    scenes: the SimScene [B, ...] the runs were given (`make_sim_scenes`; with road geometry). out: the SimResult of
    `run` or `run_host` on them (any policy, any agent model). Returns a dict of numpy f32[B]: "CLS" and its terms
    (the multipliers `no_ego_at_fault_collisions`, `drivable_area_compliance`, `driving_direction_compliance`,
    `ego_is_making_progress`; the weighted `ego_progress_along_expert_route`, `time_to_collision_within_bound`,
    `ego_is_comfortable`; counts such as `num_collisions`, `num_at_fault_collisions`; see `gpd_jax.sim.scores`),
    and where the run carries its policy's open-loop plan (`out.plan`, a policy with `Policy.plan`) also "OLS"
    and its terms. Scores are in [0, 1] (the tables print them x100).
    """
    if not isinstance(scenes, SimScene):
        raise SimError(f"score needs the SimScene the runs were given (sim.make_sim_scenes(model, scenes)); got "
                       f"{type(scenes).__name__}")
    if not isinstance(out, SimResult):
        raise SimError(f"score needs the SimResult of sim.run / sim.run_host; got {type(out).__name__}")
    check_road(scenes)
    b, bo = np.shape(scenes.log_xy)[0], np.shape(out.fine_xy)[0]
    if b != bo:
        raise SimError(f"score: the runs are of {bo} scenarios, the scenes {b}: pass the SimScene the runs were given")
    spec = model.spec
    result = dict(_cls_batch(spec, scenes, out.fine_xy, out.fine_heading, out.fine_valid))
    if out.plan is not None:
        result.update(_ols_batch(spec, scenes, out.plan))
    return {k: np.asarray(v) for k, v in result.items()}


# ------------------------------------------------------------------------------------------------ planners x agents
def _policies(model: Model, planners) -> dict[str, Policy]:
    """{row name: Policy} from a mapping {name: shipped planner name | Policy | select callable} or a sequence of
    shipped planner names / Policies."""
    if isinstance(planners, str):
        raise SimError(f"planners: give a sequence or a mapping, not the string {planners!r} "
                       f"(e.g. [{', '.join(repr(p) for p in planners.split(','))}])")
    items = list(planners.items()) if isinstance(planners, Mapping) else [(None, p) for p in planners]
    if not items:
        raise SimError("planners: none given")
    out: dict[str, Policy] = {}
    for name, spec in items:
        if isinstance(spec, str):
            if spec not in PLANNERS:
                raise SimError(f"unknown planner {spec!r}; known planners: {', '.join(PLANNERS)} (or pass your own "
                               f"gpd_jax.sim.Policy)")
            if spec in HEAD_PLANNERS:
                raise SimError(f"planner {spec} needs the model with the planning head: pass "
                               f"sim.make_policy({spec!r}, head_model) instead of the name")
            policy = make_policy(spec, model)
            name = spec if name is None else name
        else:
            policy = as_policy(spec)
            name = policy.name if name is None else name
        if name in out:
            raise SimError(f"planner name {name!r} given twice")
        out[str(name)] = policy
    return out


def _model_rate_plan(spec: ModelSpec, out: SimResult) -> jax.Array:
    """The ego's poses at the model's future frames of a run: f32[B, F, 3]."""
    h = spec.num_history
    return jnp.concatenate([out.xy[:, h:, 0], out.heading[:, h:, 0, None]], -1)


def evaluate_planners(model: Model, scenes: Scene,
                      planners: Mapping[str, Any] | Sequence[Any] = ("log", "cv", "idm", "gpd"),
                      agents: Sequence[str] = ("log", "idm", "gpd"), *, batch_size: int = 8, seed: int = 0,
                      tracker: Tracker | None = Tracker(), progress: bool = False, keep_runs: int = 0,
                      per_scenario: bool = False) -> dict:
    """Every planner against every agent model on stored-rate scenes (`gpd_jax.load_scenes`: Scene [n, ...] with
    road geometry and lane polylines), scored as `score` scores a run.

    planners: a mapping {row name: planner} or a sequence of planners, a planner being a shipped planner's name
    (`PLANNERS`; ``gpd_head`` / ``gpd_head_scratch`` as ``make_policy(name, head_model)``), a `Policy` (your own,
    or a shipped one from `make_policy`), or a callable ``select(params, obs, state, key) -> (ego, state)``.
    agents: agent models among `AGENT_MODELS` (one column each). Scenes run in batches of `batch_size` (the last
    padded, so every batch has one shape and each planner x agent model compiles once); `seed` seeds the runs.
    Every planner's output is followed by `tracker` (`run`'s; None places the ego on it).

    Returns the structure `python -m gpd_jax.plan evaluate` writes to planning.json: {"scenarios": n, "planners":
    {name: {"OLS": x, "NR-CLS": x, "R-CLS-idm": x, "R-CLS-gpd": x, "subscores": {column: {term: mean}}}},
    "run_seconds": {"name/agents": wall seconds of the runs}}: scores are means x100 (subscores unscaled, in
    [0, 1]), only the agent columns asked for. With `per_scenario`, also "per_scenario": {name: {column: {term:
    numpy f32[n]}}}; with `keep_runs` = K > 0, also "runs": {(name, agents): SimResult of the first K scenarios
    (numpy)}; these two are not JSON. `planning_table(results)` formats the table. With several processes
    (`gpd_jax.distributed`), every process calls it alike: each runs its share of the batches, process 0 returns the
    results of all (the same as one process), the others None.
    """
    if isinstance(scenes, SimScene):
        raise SimError("evaluate_planners takes the stored-rate scenes (gpd_jax.load_scenes: a Scene with road "
                       "geometry), not a SimScene: it makes the SimScenes of each batch itself")
    policies = _policies(model, planners)
    agents = list(agents)
    if not agents:
        raise SimError("agents: none given; known agent models: " + ", ".join(AGENT_MODELS))
    for a in agents:
        if a not in AGENT_MODELS:
            raise SimError(f"unknown agent model {a!r}; known: {', '.join(AGENT_MODELS)}")
    if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
        raise SimError(f"batch_size must be an integer >= 1, got {batch_size!r}")
    check_road(scenes)
    n = int(np.shape(scenes.xy)[0])
    spec = model.spec
    per: dict = {p: {} for p in policies}
    runs: dict = {}
    seconds: dict = {}
    batches = [(i, min(i + batch_size, n)) for i in range(0, n, batch_size)]
    # Several processes (`gpd_jax.distributed`): each runs its share of the batches (round-robin); process 0 gathers
    # every batch's per-scenario scores and puts them in batch order, so the means are those of one process.
    several = jax.process_count() > 1
    if several and keep_runs:
        raise SimError("keep_runs (--render) keeps runs in one process; render without --coordinator / --distributed")
    mine = distributed.my_share(len(batches))
    kept: dict = {}
    pairs = [(p, a) for p in policies for a in agents]
    bar = None
    if progress and distributed.is_lead():
        from tqdm import tqdm
        bar = tqdm(total=len(mine) * len(policies) * len(agents), desc="closed loop", unit="run")
    key = jax.random.key(seed)
    for bi in mine:
        lo, hi = batches[bi]
        rec: dict = {p: {} for p in policies}
        sub = jax.tree.map(lambda x: x[lo:hi], scenes)
        if hi - lo < batch_size:  # pad the last batch so every batch has one shape (one compile)
            pad = batch_size - (hi - lo)
            sub = jax.tree.map(lambda x: np.concatenate([np.asarray(x), np.repeat(np.asarray(x)[-1:], pad, 0)]), sub)
        sims = make_sim_scenes(model, sub)
        bkey = jax.random.fold_in(key, bi)
        for p, policy in policies.items():
            plan = None
            for a in agents:
                t0 = time.perf_counter()
                out = run(model, sims, policy, bkey, agents=a, tracker=tracker)
                jax.block_until_ready(out.fine_xy)
                seconds[(p, a)] = seconds.get((p, a), 0.0) + time.perf_counter() - t0
                sc = _cls_batch(spec, sims, out.fine_xy, out.fine_heading, out.fine_valid)
                _put(rec[p], COLUMNS[a], sc, hi - lo)
                if out.plan is not None:
                    plan = out.plan if plan is None else plan
                elif a == "gpd":
                    plan = _model_rate_plan(spec, out)
                if keep_runs and lo < keep_runs:
                    runs.setdefault((p, a), []).append(jax.tree.map(lambda x: np.asarray(x)[: hi - lo], out))
                if bar is not None:
                    bar.update(1)
            if plan is None:  # no plan of its own and no GPD-agent run: run one for its open-loop plan
                plan = _model_rate_plan(spec, run(model, sims, policy, bkey, agents="gpd", tracker=tracker))
            _put(rec[p], "OLS", _ols_batch(spec, sims, plan), hi - lo)
        if several:
            kept[f"{bi:09d}"] = rec
        else:
            _fold(per, rec)
    if bar is not None:
        bar.close()
    if several:
        gathered = distributed.gather_to_lead("planning", {
            "batches": kept, "seconds": np.array([seconds.get(pa, 0.0) for pa in pairs])})
        if gathered is None:  # not process 0: it returns the results
            return None
        for _, rec in sorted((b, rec) for g in gathered for b, rec in g["batches"].items()):
            _fold(per, rec)
        total = sum(np.asarray(g["seconds"], np.float64) for g in gathered)
        seconds = {pa: float(t) for pa, t in zip(pairs, total)}
    per = {p: {col: {k: np.concatenate(v) for k, v in d.items()} for col, d in cols.items()} for p, cols in per.items()}
    results: dict = {"scenarios": n, "planners": {}}
    for p in policies:
        entry: dict = {}
        subs: dict = {}
        for col, d in per[p].items():
            main = "OLS" if col == "OLS" else "CLS"
            entry[col] = 100.0 * float(np.mean(d[main]))
            subs[col] = {k: float(np.mean(v)) for k, v in d.items() if k != main}
        results["planners"][p] = {**{c: entry[c] for c in ["OLS"] + [COLUMNS[a] for a in agents]},
                                  "subscores": subs}
    results["run_seconds"] = {f"{p}/{a}": round(s, 2) for (p, a), s in seconds.items()}
    if per_scenario:
        results["per_scenario"] = per
    if keep_runs:
        results["runs"] = {k: jax.tree.map(lambda *xs: np.concatenate(xs), *v) for k, v in runs.items()}
    return results


def _put(rec: dict, col: str, scores: dict, count: int) -> None:
    """One batch's scores of one column: the first `count` scenarios (the rest is padding)."""
    rec[col] = {k: np.asarray(v)[:count] for k, v in scores.items()}


def _fold(per: dict, rec: dict) -> None:
    """Appends one batch's scores {planner: {column: {term: f32[b]}}} to the run's lists (batch order)."""
    for p, cols in rec.items():
        for col, d in cols.items():
            for k, v in d.items():
                per[p].setdefault(col, {}).setdefault(k, []).append(np.asarray(v))


def planning_table(results: dict) -> str:
    """A Table-2-shaped text table of `evaluate_planners`' results: one row per planner; OLS, NR-CLS, R-CLS-idm,
    R-CLS-gpd (the columns present)."""
    cols = ["OLS"] + list(COLUMNS.values())
    present = [c for c in cols if any(c in r for r in results["planners"].values())]
    head = f"{'Planner':<24}" + "".join(f"{c:>11}" for c in present)
    lines = [f"Planning scores on {results['scenarios']} scenarios (nuPlan definitions, x100; CLS over 8 s at 10 Hz)",
             head, "-" * len(head)]
    for p, r in results["planners"].items():
        lines.append(f"{PLANNER_TITLES.get(p, p):<24}" + "".join(f"{r[c]:>11.2f}" if c in r else f"{'':>11}"
                                                              for c in present))
    return "\n".join(lines)
