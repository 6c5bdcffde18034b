"""Planning command line (thin over `gpd_jax.sim`).

    python -m gpd_jax.plan evaluate --data DIR [--split test] --planners log,cv,idm,gpd,gpd_head[,gpd_head_scratch] \
        --agents log,idm,gpd --out DIR [--render K] [--checkpoint MODEL] [--head-model M] [--scratch-head-model M] \
        [--replan-every N | --no-tracker]
    python -m gpd_jax.plan bench --data DIR [--batch 8] [--planners ...] [--agents ...]

`--planners` is a comma list of shipped planners (`gpd_jax.sim.PLANNERS`) and your own policies, each given as
`FILE.py:NAME` (a Python file) or `MODULE:NAME` (an importable module), NAME being a `gpd_jax.sim.Policy`, a
callable `(params, obs, state, key) -> (ego, state)` (the policy's `select`), or a factory `(model) -> Policy`
called with the world model; its table row is NAME. Your policies are scored exactly as the shipped ones
(`gpd_jax.sim.evaluate_planners`).

Every planner's output is followed by the plan tracker (`gpd_jax.sim.Tracker`: pure pursuit and a speed law on the
bicycle model, nuPlan's way of executing plans), replanning every `--replan-every` model frames; `--no-tracker`
places the ego on the output instead. `evaluate` prints a table shaped like GPD-1's Table 2 (one row per planner: OLS, NR-CLS, R-CLS with IDM agents,
R-CLS with GPD agents) and writes OUT/planning.json ({"scenarios": n, "planners": {NAME: {"OLS", "NR-CLS",
"R-CLS-idm", "R-CLS-gpd", "subscores"}}, "run_seconds", ...}), OUT/planning_table.txt and with --render K GIFs of
the first K scenarios' runs under OUT/render/. `bench` times batched closed-loop runs per planner x agent model on
this machine and compares them with nuPlan's ~1 minute per 15 s scenario. Bad input (a bad flag value, an unknown
planner, policy file or attribute, a store without road geometry, a missing head model) prints one line and exits
with status 2.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import os
import sys
import time

import numpy as np

from gpd_jax import distributed
from gpd_jax.cliargs import ArgumentParser as Parser
from gpd_jax.cliargs import UsageError, count, count0, output_dir, output_file, program, run_command

PROG = "python -m gpd_jax.plan"
NUPLAN_S_PER_SCENARIO = 60.0      # nuPlan devkit: about a minute of wall time per closed-loop scenario
NUPLAN_SCENARIO_S = 15.0          # of 15 s simulated
HEAD_CONFIGS = {"gpd_head": "gpd_planner.py:frozen", "gpd_head_scratch": "gpd_planner.py:frozen_scratch"}


def _default_head(planner: str = "gpd_head") -> str:
    """The planning-head model a head planner (`gpd_head`, `gpd_head_scratch`) loads when no --head-model /
    --scratch-head-model is given: a shipped model's name (`gpd_planner`; no scratch head is shipped, so the
    name `gpd_planner_scratch` resolves only in a models folder that holds one)."""
    return "gpd_planner_scratch" if planner == "gpd_head_scratch" else "gpd_planner"


# ------------------------------------------------------------------------------------------------ planners
def _import_file(path: str, shown: str):
    """Imports a Python file as a module of its own (its directory on sys.path while it runs, as `python FILE`)."""
    tag = hashlib.sha1(path.encode()).hexdigest()[:12]
    spec = importlib.util.spec_from_file_location(f"_gpd_plan_policy_{tag}", path)
    if spec is None or spec.loader is None:
        raise UsageError(f"--planners: {shown} is not a Python file that can be imported")
    module = importlib.util.module_from_spec(spec)
    folder = os.path.dirname(path)
    sys.path.insert(0, folder)
    try:
        spec.loader.exec_module(module)
    except Exception as e:  # the user's own file: say what failed, in one line
        raise UsageError(f"--planners: policy file {shown} failed to import: {type(e).__name__}: {e}") from None
    finally:
        if folder in sys.path:
            sys.path.remove(folder)
    return module


def _import_module(name: str):
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as e:
        if e.name and (name == e.name or name.startswith(e.name + ".")):
            raise UsageError(f"--planners: no module {name!r} (a policy file must end in .py)") from None
        raise UsageError(f"--planners: module {name} failed to import: {type(e).__name__}: {e}") from None
    except Exception as e:
        raise UsageError(f"--planners: module {name} failed to import: {type(e).__name__}: {e}") from None


def _user_policy(entry: str):
    """`FILE.py:NAME` or `MODULE:NAME` -> ("policy", Policy) | ("select", callable) | ("factory", callable)."""
    from gpd_jax.sim import Policy

    where, _, attr = entry.rpartition(":")
    if not where or not attr:
        raise UsageError(f"--planners: {entry!r} is neither a shipped planner nor FILE.py:NAME / MODULE:NAME")
    if where.endswith(".py") or os.sep in where or "/" in where:
        path = os.path.abspath(os.path.expanduser(where))
        if not os.path.isfile(path):
            raise UsageError(f"--planners: no policy file {where}")
        module = _import_file(path, where)
    else:
        module = _import_module(where)
    if not hasattr(module, attr):
        raise UsageError(f"--planners: {where} has no attribute {attr!r}")
    obj = getattr(module, attr)
    if isinstance(obj, Policy):
        return "policy", obj
    if callable(obj):
        try:
            sig = inspect.signature(obj)
        except (TypeError, ValueError):  # no signature to read (a builtin): take it as a select function
            return "select", obj
        for kind, args in (("select", (0, 0, 0, 0)), ("factory", (0,))):
            try:
                sig.bind(*args)
                return kind, obj
            except TypeError:
                pass
    raise UsageError(f"--planners: {where}:{attr} is a {type(obj).__name__}, not a gpd_jax.sim.Policy, a callable "
                     f"(params, obs, state, key) -> (ego, state) or a factory (model) -> Policy")


def _parse_planners(text: str) -> list[tuple[str, object]]:
    """The --planners list -> [(row name, shipped planner name | (kind, object))]; user files are imported here,
    before any model loads, so a typo costs no wait."""
    from gpd_jax.sim import PLANNERS, WORLD_PLANNERS

    entries = [n.strip() for n in text.split(",") if n.strip()]
    if not entries:
        raise UsageError(f"--planners: none given; known planners: {', '.join(PLANNERS)} (or FILE.py:NAME, "
                         f"MODULE:NAME)")
    out, seen = [], set()
    for e in entries:
        if e in PLANNERS or e in WORLD_PLANNERS:
            item = (e, e)
        elif ":" in e:
            item = (e.rpartition(":")[2], _user_policy(e))
        else:
            raise UsageError(f"unknown planner {e!r}; known: {', '.join(PLANNERS + tuple(WORLD_PLANNERS))}, or "
                             f"your own policy as "
                             f"FILE.py:NAME or MODULE:NAME")
        if item[0] in seen:
            raise UsageError(f"--planners: planner name {item[0]!r} given twice")
        seen.add(item[0])
        out.append(item)
    return out


def _policies(parsed, model, heads) -> dict:
    """{row name: Policy} for `gpd_jax.sim.evaluate_planners` (factories called with the world model)."""
    from gpd_jax.sim import Policy, as_policy, make_policy

    out = {}
    for name, spec in parsed:
        if isinstance(spec, str) and spec in _world_names():
            out.update(_world_policies(spec, heads))
            continue
        if isinstance(spec, str):
            out[name] = make_policy(spec, heads.get(spec, model))
            continue
        kind, obj = spec
        if kind == "factory":
            pol = obj(model)
            if not isinstance(pol, Policy):
                raise UsageError(f"--planners: the factory {name} returned a {type(pol).__name__}, not a "
                                 f"gpd_jax.sim.Policy")
            out[name] = pol
        else:
            out[name] = as_policy(obj)
    return out


def _world_names():
    from gpd_jax.sim import WORLD_PLANNERS
    return WORLD_PLANNERS


def _world_policies(name: str, heads) -> dict:
    """{row name: Policy} of a world planner (`gpd_jax.sim.world_planner`): one row, or one per --world-samples
    value (NAME_kK) for the world model's scorer; `heads` holds the world model ("world") and its head
    ("world_head")."""
    from gpd_jax.sim import WorldPlannerOptions, make_world_policy

    args = heads["world_args"]
    samples = args.world_samples if name == "gpd_world" else args.world_samples[:1]
    out = {}
    for k in samples:
        opts = WorldPlannerOptions(samples=k, temperature=args.world_temperature, horizon=args.world_horizon,
                                   reduce=args.world_reduce, use_head=heads["world_head"] is not None)
        row = name if len(samples) == 1 else f"{name}_k{k}"
        out[row] = make_world_policy(name, heads["world"], heads["world_head"], opts)
    return out


def _samples(text: str) -> list[int]:
    try:
        out = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        out = []
    if not out or min(out) < 1:
        raise UsageError(f"argument --world-samples: expected a comma list of integers >= 1, got {text!r}")
    return out


def _agents(text: str) -> list[str]:
    from gpd_jax.sim import AGENT_MODELS

    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if n not in AGENT_MODELS]
    if bad or not names:
        raise UsageError(f"--agents: unknown agent model {', '.join(map(repr, bad)) or '(none given)'}; "
                         f"known: {', '.join(AGENT_MODELS)}")
    return names


# ------------------------------------------------------------------------------------------------ loading
def _load(args, parsed):
    import gpd_jax
    from gpd_jax.sim import SimError

    if not os.path.isdir(os.path.join(args.data, args.split)):
        raise SimError(f"split {args.split!r} not found in {args.data}")
    heads = {}
    given = {"gpd_head": args.head_model, "gpd_head_scratch": args.scratch_head_model}
    for name, spec in parsed:
        if not isinstance(spec, str) or spec not in HEAD_CONFIGS:
            continue
        path = given[spec] or _default_head(spec)
        flag = "--scratch-head-model" if spec == "gpd_head_scratch" else "--head-model"
        try:
            heads[spec] = gpd_jax.load_model(path)
        except FileNotFoundError as e:
            raise SimError(f"planner {spec}: no planning-head model at {path} ({e}); train one with "
                           f"configs/{HEAD_CONFIGS[spec]} and pass {flag}") from None
        except (ValueError, LookupError) as e:
            raise SimError(f"planner {spec}: {path} is not a usable planning-head model ({e}); pass {flag}") from None
        if "plan_head" not in heads[spec].config:
            raise SimError(f"planner {spec}: {path} has no plan_head section (not a planning-head model)")
    if any(isinstance(spec, str) and spec in _world_names() for _, spec in parsed):
        heads["world_args"] = args
        heads["world"] = gpd_jax.load_model(args.world_model)
        heads["world_head"] = None if args.world_no_head else heads.get("gpd_head") or gpd_jax.load_model(
            args.head_model or _default_head())
    model = gpd_jax.load_model(args.checkpoint)
    from gpd_jax.data.loader import SplitSource
    n_all = len(SplitSource(args.data, args.split, with_polylines=True))
    n = n_all if args.num_scenarios is None else min(args.num_scenarios, n_all)
    scenes = gpd_jax.load_scenes(args.data, args.split, indices=range(n))
    return model, heads, scenes


def _tracker(args):
    from gpd_jax.sim import Tracker
    if args.no_tracker and args.replan_every != 1:
        raise UsageError("argument --replan-every: plans are held only by the tracker; drop --no-tracker or --replan-every")
    return None if args.no_tracker else Tracker(replan_every=args.replan_every)


def cmd_evaluate(args) -> int:
    from gpd_jax.fsutil import atomic_write_json, atomic_write_text
    from gpd_jax.sim import evaluate_planners, planning_table
    from gpd_jax.sim.scoring import check_road

    parsed = _parse_planners(args.planners)
    agents = _agents(args.agents)
    tracker = _tracker(args)
    cluster = distributed.from_args(args)
    if cluster.enabled and args.render:
        raise UsageError("--render runs in one process; leave out --coordinator / --distributed")
    distributed.initialize(cluster)
    model, heads, scenes = _load(args, parsed)
    check_road(scenes, f"{args.data}/{args.split}")
    policies = _policies(parsed, model, heads)
    t0 = time.perf_counter()
    results = evaluate_planners(model, scenes, policies, agents, batch_size=args.batch_size, seed=args.seed,
                                tracker=tracker, progress=not args.quiet, keep_runs=args.render)
    if results is None:  # another process than 0 of a multi-process run: process 0 writes the outputs
        return 0
    runs = results.pop("runs", {})
    results["seconds"] = round(time.perf_counter() - t0, 1)
    results["data"] = os.path.abspath(args.data)
    results["split"] = args.split
    results["tracker"] = None if args.no_tracker else {"replan_every": args.replan_every}
    table = planning_table(results)
    print(table)
    os.makedirs(args.out, exist_ok=True)
    atomic_write_json(os.path.join(args.out, "planning.json"), results)
    atomic_write_text(os.path.join(args.out, "planning_table.txt"), table + "\n")
    if args.render:
        from gpd_jax.sim.render import render_run
        import jax
        k = min(args.render, results["scenarios"])
        for (p, a), out in runs.items():
            for i in range(k):
                road = jax.tree.map(lambda x: np.asarray(x)[i], scenes.road)
                plan = None if out.plan is None else out.plan[i]
                render_run(os.path.join(args.out, "render", f"{i:03d}_{p}_{a}.gif"), fine_xy=out.fine_xy[i],
                           fine_heading=out.fine_heading[i], fine_valid=out.fine_valid[i],
                           size=np.asarray(scenes.size)[i, : out.fine_xy.shape[2]], road=road,
                           polylines=np.asarray(scenes.polylines)[i], polyline_valid=np.asarray(scenes.polyline_valid)[i],
                           plan=plan, start=model.spec.full_history - 1, title=f"{p} / {a} agents #{i}")
        print(f"rendered {k} scenario(s) x {len(runs)} runs under {os.path.join(args.out, 'render')}")
    print(f"wrote {os.path.join(args.out, 'planning.json')}")
    return 0


def cmd_bench(args) -> int:
    import jax
    from gpd_jax.sim import make_sim_scenes, run

    parsed = _parse_planners(args.planners)
    agents = _agents(args.agents)
    tracker = _tracker(args)
    args.num_scenarios = args.batch
    model, heads, scenes = _load(args, parsed)
    policies = _policies(parsed, model, heads)
    sim = make_sim_scenes(model, scenes)
    b = int(np.shape(sim.log_xy)[0])
    sim_s = model.spec.num_future * model.spec.frame_period_s
    nuplan = NUPLAN_SCENARIO_S / NUPLAN_S_PER_SCENARIO
    rows = []
    print(f"closed-loop throughput, batch {b}, {sim_s:g} s simulated per scenario, {os.cpu_count()} CPU cores "
          f"(nuPlan: ~{NUPLAN_S_PER_SCENARIO:g} s per {NUPLAN_SCENARIO_S:g} s scenario = {nuplan:.2f} simulated s/s)")
    print(f"{'planner':<10}{'agents':<8}{'compile s':>10}{'run s':>9}{'scen/s':>9}{'sim s/s':>9}{'x nuPlan':>10}"
          f"{'ms/replan':>11}")
    for p, pol in policies.items():
        for a in agents:
            t0 = time.perf_counter()
            jax.block_until_ready(run(model, sim, pol, jax.random.key(args.seed), agents=a,
                                      tracker=tracker).fine_xy)
            compile_s = time.perf_counter() - t0
            best = np.inf
            for r in range(args.repeats):
                t0 = time.perf_counter()
                jax.block_until_ready(run(model, sim, pol, jax.random.key(args.seed + r + 1), agents=a,
                                          tracker=tracker).fine_xy)
                best = min(best, time.perf_counter() - t0)
            sps = b / best
            per_replan_ms = 1000.0 * best / (b * model.spec.num_future)  # one scenario's step, the sim's share included
            rows.append({"planner": p, "agents": a, "batch": b, "compile_s": compile_s, "run_s": best,
                         "scenarios_per_s": sps, "simulated_s_per_s": sps * sim_s,
                         "speedup_vs_nuplan": sps * sim_s / nuplan, "ms_per_replan": per_replan_ms})
            print(f"{p:<10}{a:<8}{compile_s:>10.1f}{best:>9.2f}{sps:>9.2f}{sps * sim_s:>9.1f}"
                  f"{sps * sim_s / nuplan:>10.0f}{per_replan_ms:>11.1f}")
    if args.out:
        from gpd_jax.fsutil import atomic_write_json
        atomic_write_json(args.out, {"rows": rows, "cpu_count": os.cpu_count(), "simulated_s": sim_s,
                                     "nuplan_s_per_15s_scenario": NUPLAN_S_PER_SCENARIO})
        print(f"wrote {args.out}")
    return 0


def build_parser() -> Parser:
    p = Parser(prog=program(PROG), description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    planners_help = ("comma list of shipped planners (log, cv, idm, gpd, gpd_head, gpd_head_scratch; the world "
                     "planner gpd_world and its ablations gpd_world_cv, gpd_world_log) and your own "
                     "policies as FILE.py:NAME or MODULE:NAME (a gpd_jax.sim.Policy, a callable (params, obs, state, "
                     "key) -> (ego, state), or a factory (model) -> Policy)")
    for name in ("evaluate", "bench"):
        s = sub.add_parser(name)
        s.add_argument("--data", required=True, help="a data store (python -m gpd_jax.data build ...)")
        s.add_argument("--split", default="test")
        s.add_argument("--planners", default="log,cv,idm,gpd", help=planners_help)
        s.add_argument("--agents", default="log,idm,gpd", help="comma list of agent models: log, idm, gpd")
        s.add_argument("--checkpoint", default=None, help="the GPD world model (default: the shipped one)")
        s.add_argument("--head-model", default=None,
                       help=f"the planning-head model for gpd_head (default {_default_head('gpd_head')})")
        s.add_argument("--scratch-head-model", default=None,
                       help="the head trained without pre-training, for gpd_head_scratch "
                            f"(default {_default_head('gpd_head_scratch')})")
        s.add_argument("--world-model", default="gpd_sampling",
                       help="the model gpd_world imagines the agents' futures with (default gpd_sampling)")
        s.add_argument("--world-samples", type=_samples, default=[4], metavar="K[,K...]",
                       help="futures per candidate of gpd_world (a list: one row each, NAME_kK; default 4)")
        s.add_argument("--world-temperature", type=float, default=0.5, help="gpd_world's sampling temperature")
        s.add_argument("--world-horizon", type=count, default=4, metavar="F", help="model frames gpd_world imagines")
        s.add_argument("--world-reduce", choices=("min", "mean"), default="mean",
                       help="gpd_world's score over the futures: their mean or the worst case")
        s.add_argument("--world-no-head", action="store_true",
                       help="no planning-head candidate in gpd_world (otherwise --head-model's plan is one)")
        s.add_argument("--seed", type=int, default=0)
        s.add_argument("--replan-every", type=count, default=1, metavar="N",
                       help="model frames between replans; the tracker follows each plan in between (default 1)")
        s.add_argument("--no-tracker", action="store_true",
                       help="place the ego on each planner's output instead of tracking it on the bicycle model")
    e = sub.choices["evaluate"]
    e.add_argument("--out", type=output_dir, required=True)
    e.add_argument("--render", type=count0, default=0, metavar="K", help="GIFs of the first K scenarios' runs")
    e.add_argument("--num-scenarios", type=count, default=None, metavar="N",
                   help="the first N scenarios (default all)")
    e.add_argument("--batch-size", type=count, default=8, metavar="B", help="scenarios per compiled batch")
    e.add_argument("--quiet", action="store_true")
    distributed.add_arguments(e)  # the scenes' batches shared over processes / hosts; process 0 writes the outputs
    bn = sub.choices["bench"]
    bn.add_argument("--batch", type=count, default=8, metavar="B", help="scenarios in the timed batch")
    bn.add_argument("--repeats", type=count, default=2, metavar="R", help="timed runs after the compiling one")
    bn.add_argument("--out", type=output_file, default=None, help="write the figures as JSON here")
    return p


def main(argv=None) -> int:
    from gpd_jax.data.errors import DataError

    def work():
        args = build_parser().parse_args(argv)
        return cmd_evaluate(args) if args.cmd == "evaluate" else cmd_bench(args)

    return run_command(PROG, work, ("gpd_jax.spec:EvalError", DataError, FileNotFoundError, ValueError, KeyError),
                       kept="nothing was written (the scores are written at the end)")


if __name__ == "__main__":
    raise SystemExit(main())
