"""Planning command line (thin over `gpd_jax.sim`).

    python -m gpd_jax.plan evaluate --data DIR [--split test] --planners log,cv,idm,gpd,gpd_head[,gpd_head_scratch] \
        --agents log,idm,gpd --out DIR [--render K] [--checkpoint MODEL] [--head-model M] [--scratch-head-model M]
    python -m gpd_jax.plan bench --data DIR [--batch 8] [--planners ...] [--agents ...]

`evaluate` prints a table shaped like GPD-1's Table 2 (one row per planner: OLS, NR-CLS, R-CLS with IDM agents,
R-CLS with GPD agents) and writes OUT/planning.json ({"scenarios": n, "planners": {NAME: {"OLS", "NR-CLS",
"R-CLS-idm", "R-CLS-gpd", "subscores"}}}), OUT/planning_table.txt and with --render K GIFs of the first K
scenarios' runs under OUT/render/. `bench` times batched closed-loop runs per planner x agent model on this
machine and compares them with nuPlan's ~1 minute per 15 s scenario. Bad input exits with status 2.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

DEFAULT_HEAD = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                            "checkpoints", "gpd_sumo_plan_head")
NUPLAN_S_PER_SCENARIO = 60.0      # nuPlan devkit: about a minute of wall time per closed-loop scenario
NUPLAN_SCENARIO_S = 15.0          # of 15 s simulated


def _names(text: str, known, what: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if n not in known]
    if bad or not names:
        raise ValueError(f"unknown {what} {', '.join(map(repr, bad)) or '(none given)'}; known: {', '.join(known)}")
    return names


def _load(args, planners):
    import gpd_jax
    from gpd_jax.sim import SimError

    if not os.path.isdir(os.path.join(args.data, args.split)):
        raise SimError(f"split {args.split!r} not found in {args.data}")
    heads = {}
    for name, path, cfg in (("gpd_head", args.head_model or DEFAULT_HEAD, "gpd_sumo_plan_head.py"),
                            ("gpd_head_scratch", args.scratch_head_model or DEFAULT_HEAD + "_scratch",
                             "gpd_sumo_plan_head_scratch.py")):
        if name not in planners:
            continue
        if not os.path.exists(os.path.join(path, "config.json")):
            raise SimError(f"planner {name}: no planning-head model at {path} (train one with configs/{cfg} and "
                           f"pass --{'scratch-' if 'scratch' in name else ''}head-model)")
        heads[name] = gpd_jax.load_model(path)
        if not heads[name].config.get("plan_head"):
            raise SimError(f"planner {name}: {path} has no plan_head section (not a planning-head model)")
    model = gpd_jax.load_model(args.checkpoint)
    from gpd_jax.data.loader import SplitSource
    n_all = len(SplitSource(args.data, args.split, with_polylines=True))
    n = n_all if args.num_scenarios is None else min(args.num_scenarios, n_all)
    scenes = gpd_jax.load_scenes(args.data, args.split, indices=range(n))
    return model, heads, scenes


def cmd_evaluate(args) -> int:
    from gpd_jax.fsutil import atomic_write_json, atomic_write_text
    from gpd_jax.sim import AGENT_MODELS, PLANNERS
    from gpd_jax.sim.evaluate import check_road, evaluate_planners, format_table

    planners = _names(args.planners, PLANNERS, "planner")
    agents = _names(args.agents, AGENT_MODELS, "agent model")
    model, heads, scenes = _load(args, planners)
    check_road(scenes, f"{args.data}/{args.split}")
    t0 = time.perf_counter()
    results, extra = evaluate_planners(model, scenes, planners, agents, head_models=heads, batch_size=args.batch_size,
                                       seed=args.seed, progress=not args.quiet, keep_runs=args.render)
    results["seconds"] = round(time.perf_counter() - t0, 1)
    results["data"] = os.path.abspath(args.data)
    results["split"] = args.split
    results["run_seconds"] = {f"{p}/{a}": round(s, 2) for (p, a), s in extra["seconds"].items()}
    table = format_table(results)
    print(table)
    os.makedirs(args.out, exist_ok=True)
    atomic_write_json(os.path.join(args.out, "planning.json"), results)
    atomic_write_text(os.path.join(args.out, "planning_table.txt"), table + "\n")
    if args.render:
        from gpd_jax.sim.render import render_run
        import jax
        k = min(args.render, results["scenarios"])
        for (p, a), out in extra["runs"].items():
            for i in range(k):
                road = jax.tree.map(lambda x: np.asarray(x)[i], scenes.road)
                plan = None if out.plan is None else out.plan[i]
                render_run(os.path.join(args.out, "render", f"{i:03d}_{p}_{a}.gif"), fine_xy=out.fine_xy[i],
                           fine_heading=out.fine_heading[i], fine_valid=out.fine_valid[i],
                           size=np.asarray(scenes.size)[i, : out.fine_xy.shape[2]], road=road,
                           polylines=np.asarray(scenes.polylines)[i], polyline_valid=np.asarray(scenes.polyline_valid)[i],
                           plan=plan, start=model.spec.full_history - 1, title=f"{p} / {a} agents #{i}")
        print(f"rendered {k} scenario(s) x {len(extra['runs'])} runs under {os.path.join(args.out, 'render')}")
    print(f"wrote {os.path.join(args.out, 'planning.json')}")
    return 0


def cmd_bench(args) -> int:
    import jax
    from gpd_jax.sim import AGENT_MODELS, PLANNERS, make_policy, make_sim_scenes, run

    planners = _names(args.planners, PLANNERS, "planner")
    agents = _names(args.agents, AGENT_MODELS, "agent model")
    args.num_scenarios = args.batch
    model, heads, scenes = _load(args, planners)
    sim = make_sim_scenes(model, scenes)
    b = int(np.shape(sim.log_xy)[0])
    sim_s = model.spec.num_future * model.spec.frame_period_s
    nuplan = NUPLAN_SCENARIO_S / NUPLAN_S_PER_SCENARIO
    rows = []
    print(f"closed-loop throughput, batch {b}, {sim_s:g} s simulated per scenario, {os.cpu_count()} CPU cores "
          f"(nuPlan: ~{NUPLAN_S_PER_SCENARIO:g} s per {NUPLAN_SCENARIO_S:g} s scenario = {nuplan:.2f} simulated s/s)")
    print(f"{'planner':<10}{'agents':<8}{'compile s':>10}{'run s':>9}{'scen/s':>9}{'sim s/s':>9}{'x nuPlan':>10}")
    for p in planners:
        pol = make_policy(p, heads.get(p, model))
        for a in agents:
            t0 = time.perf_counter()
            jax.block_until_ready(run(model, sim, pol, jax.random.key(0), agents=a).fine_xy)
            compile_s = time.perf_counter() - t0
            best = np.inf
            for r in range(args.repeats):
                t0 = time.perf_counter()
                jax.block_until_ready(run(model, sim, pol, jax.random.key(r + 1), agents=a).fine_xy)
                best = min(best, time.perf_counter() - t0)
            sps = b / best
            rows.append({"planner": p, "agents": a, "batch": b, "compile_s": compile_s, "run_s": best,
                         "scenarios_per_s": sps, "simulated_s_per_s": sps * sim_s,
                         "speedup_vs_nuplan": sps * sim_s / nuplan})
            print(f"{p:<10}{a:<8}{compile_s:>10.1f}{best:>9.2f}{sps:>9.2f}{sps * sim_s:>9.1f}"
                  f"{sps * sim_s / nuplan:>10.0f}")
    if args.out:
        from gpd_jax.fsutil import atomic_write_json
        atomic_write_json(args.out, {"rows": rows, "cpu_count": os.cpu_count(), "simulated_s": sim_s,
                                     "nuplan_s_per_15s_scenario": NUPLAN_S_PER_SCENARIO})
        print(f"wrote {args.out}")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m gpd_jax.plan", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    for name in ("evaluate", "bench"):
        s = sub.add_parser(name)
        s.add_argument("--data", required=True, help="a data store (python -m gpd_jax.data build ...)")
        s.add_argument("--split", default="test")
        s.add_argument("--planners", default="log,cv,idm,gpd" if name == "evaluate" else "log,cv,idm,gpd")
        s.add_argument("--agents", default="log,idm,gpd")
        s.add_argument("--checkpoint", default=None, help="the GPD world model (default: the shipped one)")
        s.add_argument("--head-model", default=None, help=f"the planning-head model for gpd_head (default {DEFAULT_HEAD})")
        s.add_argument("--scratch-head-model", default=None,
                       help=f"the head trained without pre-training, for gpd_head_scratch (default {DEFAULT_HEAD}_scratch)")
        s.add_argument("--seed", type=int, default=0)
    e = sub.choices["evaluate"]
    e.add_argument("--out", required=True)
    e.add_argument("--render", type=int, default=0, metavar="K", help="GIFs of the first K scenarios' runs")
    e.add_argument("--num-scenarios", type=int, default=None)
    e.add_argument("--batch-size", type=int, default=8)
    e.add_argument("--quiet", action="store_true")
    bn = sub.choices["bench"]
    bn.add_argument("--batch", type=int, default=8)
    bn.add_argument("--repeats", type=int, default=2)
    bn.add_argument("--out", default=None, help="write the figures as JSON here")
    args = p.parse_args(argv)
    from gpd_jax.data.errors import DataError
    from gpd_jax.sim import SimError
    try:
        if getattr(args, "num_scenarios", 1) is not None and getattr(args, "num_scenarios", 1) < 1:
            raise ValueError("--num-scenarios must be >= 1")
        return cmd_evaluate(args) if args.cmd == "evaluate" else cmd_bench(args)
    except (SimError, DataError, FileNotFoundError, ValueError, KeyError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
