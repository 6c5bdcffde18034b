"""What `rollout.py` runs: argument checks that need no model (cheap, first), then load, evaluate, print, write.

Every problem with the input is a `UsageError` naming it, raised before the model loads and before anything is
written (the command line turns it into exit status 2). The flags and the output folder are checked before JAX is
imported (this module imports it only in its functions), so a bad flag is refused at once.
"""

from __future__ import annotations

import argparse
import os
import time

from gpd_jax import distributed, zoo
from gpd_jax.cliargs import ArgumentParser as Parser
from gpd_jax.cliargs import UsageError, check_output_dir, count, count0, nonnegative, run_command
from gpd_jax.options import GEN_MAPS, LOG_MAPS, RolloutOptions

PROG = "rollout.py"


def parser(prog: str = PROG) -> Parser:
    """The evaluation command line's arguments (`rollout.py`, `gpd-jax eval`)."""
    p = Parser(prog=prog, description="Multi-task evaluation of a GPD model: rollouts of every task on a split, "
                                      "metrics at 3 / 5 / 8 s next to the baselines, tables, pictures.")
    p.add_argument("--checkpoint", default=None,
                   help=f"a shipped model's name (gpd-jax models) or an exported model / train.py workdir "
                        f"(default: {zoo.DEFAULT_MODEL})")
    p.add_argument("--data", required=True, help="data store directory (python -m gpd_jax.data build)")
    p.add_argument("--split", default="test")
    p.add_argument("--tasks", default="all", help="'all' or a comma list of task keys")
    p.add_argument("--out", required=True, help="output directory (metrics.json, tables.txt, render/)")
    p.add_argument("--scenarios", type=count, default=None, help="first N scenarios of the split (default: all)")
    p.add_argument("--batch", type=count, default=8, help="scenarios per compiled rollout call (every task each)")
    p.add_argument("--render", type=count0, default=0, metavar="K", help="GIF + PNG of every task for the first K")
    p.add_argument("--render-size", type=count, default=320, help="pixels per rendered frame")
    p.add_argument("--seed", type=int, default=0, help="rollout PRNG seed (used at temperature > 0)")
    p.add_argument("--variant", default="paper", choices=("paper", "corrected"),
                   help="metric variant of the main keys; the other is written with its name as a suffix")
    p.add_argument("--horizons", default="3,5,8", help="horizons in seconds (comma list)")
    p.add_argument("--temperature", type=nonnegative, default=0.0,
                   help="sampling temperature of map tokens and, for a model with a sampling agent head "
                        "(gpd_sampling), of the agents (0: the most likely token and the regressed agents, the "
                        "paper's)")
    p.add_argument("--top-k", type=count0, default=0, help="sample among the k most likely map tokens / agent "
                                                        "cells only (0: all)")
    p.add_argument("--top-p", type=float, default=1.0, help="nucleus sampling: the smallest set of most likely "
                                                            "tokens / agent cells whose probability reaches p")
    p.add_argument("--avoid-collisions", action="store_true",
                   help="collision-aware decoding (a sampling-head model): a generated agent whose next state "
                        "would overlap an agent ahead of it or leave the road takes instead its sampling head's clear "
                        "cell nearest that state (a draw among the clear cells above temperature 0; "
                        "docs/evaluation.md)")
    p.add_argument("--log-map", default="tokens", choices=LOG_MAPS,
                   help="tasks that take the map from the log but generate the ego get the logged map tokens "
                        "(the paper's choice) or the log's lanes re-encoded around the generated ego every frame")
    p.add_argument("--gen-map", default="model", choices=GEN_MAPS,
                   help="where the map is generated: every token the model's (the paper's choice) or the last "
                        "given map moved with the ego, the model's tokens only in cells newly in view")
    p.add_argument("--prompt", default=None, metavar="FILE[,FILE]",
                   help="JSON prompt file(s) (examples/prompt_*.json): roll out every scenario under each prompt "
                        "and score how the conditions are respected (OUT/conditions.json) instead of the tasks")
    p.add_argument("--samples", type=count0, default=0, metavar="K",
                   help="also score the realism of K rollouts per scenario in the form of the Waymo sim-agents "
                        "challenge (a realism table and 'realism' in metrics.json; docs/evaluation.md)")
    p.add_argument("--realism-config", default="2025", choices=("2024", "2025"),
                   help="the challenge configuration of --samples (weights)")
    p.add_argument("--export-official", default=None, metavar="DIR",
                   help="with --samples: write every task's and baseline's rollouts as the official mode scores "
                        "them (DIR/<group>.npz) for the official code, tests/conformance/run_official.py "
                        "(docs/evaluation.md)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    distributed.add_arguments(p)  # the scenes sharded over processes / hosts; process 0 writes the outputs
    return p


def main(argv: list[str], prog: str = PROG) -> int:
    """Runs the evaluation command line: exit 0, or 2 with one line naming the problem."""
    return run_command(prog, lambda: run(check_arguments(parser(prog), argv)),
                       kept="nothing was written (the outputs are written at the end)")


def check_flags(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace:
    """Parses `argv` and checks what needs only the arguments (numbers, lists, the output folder), before JAX is
    imported."""
    args = parser.parse_args(argv)
    args.cluster = distributed.from_args(args)
    if args.cluster.enabled and args.prompt:
        raise UsageError("--prompt runs in one process; leave out --coordinator / --distributed")
    try:
        args.horizons = tuple(float(x) for x in args.horizons.split(",") if x.strip())
    except ValueError:
        raise UsageError(f"--horizons {args.horizons!r}: expected seconds, e.g. 3,5,8") from None
    if not args.horizons or any(not 0 < h < float("inf") for h in args.horizons):
        raise UsageError(f"--horizons {args.horizons}: expected positive seconds, e.g. 3,5,8")
    listed = [t for t in args.tasks.split(",") if t]
    if "all" in listed and len(listed) > 1:
        raise UsageError(f"--tasks {args.tasks}: 'all' cannot be combined with other task names")
    try:
        args.options = RolloutOptions(temperature=args.temperature, top_k=args.top_k, top_p=args.top_p,
                                      log_map=args.log_map, gen_map=args.gen_map,
                                      avoid_collisions=args.avoid_collisions)
    except ValueError as e:
        flag = next((f for f in ("top-k", "top-p") if f.replace("-", "_") in str(e)), "temperature")
        raise UsageError(f"--{flag}: {e}") from None
    try:
        args.checkpoint = zoo.resolve(args.checkpoint)
    except FileNotFoundError as e:
        raise UsageError(f"--checkpoint: {e}") from None
    args.data = os.path.abspath(args.data)
    args.out = check_output_dir(args.out, "--out")
    if args.render and os.path.exists(os.path.join(args.out, "render")):
        check_output_dir(os.path.join(args.out, "render"), "--out (its render folder)")
    for path in args.prompt.split(",") if args.prompt else ():
        if not os.path.isfile(path):
            raise UsageError(f"--prompt {path}: file not found")
    return args


def check_arguments(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace:
    """Parses `argv` and checks everything that needs only the arguments, the config and the data. Returns the
    args with `task_names`, `horizons`, `options`, `config` and `tokenizer_path` added."""
    args = check_flags(parser, argv)
    ckpt = args.checkpoint
    from gpd_jax.checkpoint import CONFIG_FILE, resolve_tokenizer_path
    from gpd_jax.config import config_from_json
    from gpd_jax.evaluation.preflight import preflight
    from gpd_jax.spec import EvalError
    from gpd_jax.tasks import resolve_task_names

    try:
        args.task_names = resolve_task_names(args.tasks)
    except KeyError as e:
        raise UsageError(f"--tasks: {e.args[0]}") from None
    if not args.task_names:
        raise UsageError("--tasks: no task given")
    try:
        config = config_from_json(os.path.join(ckpt, CONFIG_FILE))
        if config.stage != "gpd":
            raise UsageError(f"{ckpt}/{CONFIG_FILE}: stage is {config.stage!r}, not a GPD model")
        args.tokenizer_path = resolve_tokenizer_path(config.model.map_tokenizer, ckpt)
        if args.options.needs_tokenizer and not args.tokenizer_path:
            flag = "--log-map lanes re-encodes the log's lanes" if args.log_map == "lanes" else \
                "--gen-map warp moves generated maps"
            raise UsageError(f"{flag} with the model's map tokenizer, and {ckpt} has none "
                             "(config.model.map_tokenizer is empty)")
        preflight(config, args.data, args.split, task_names=args.task_names, num_scenarios=args.scenarios,
                  variant=args.variant, horizons_s=args.horizons, has_tokenizer=bool(args.tokenizer_path))
    except FileNotFoundError as e:
        raise UsageError(f"map tokenizer of {ckpt}: {e}") from None
    except (EvalError, KeyError, ValueError) as e:
        raise UsageError(str(e.args[0]) if e.args else str(e)) from None
    args.config = config
    args.prompts = _read_prompts(getattr(args, "prompt", None), bool(args.tokenizer_path), config)
    return args


def _read_prompts(spec: str | None, has_tokenizer: bool, config) -> dict:
    """--prompt FILE[,FILE...]: {name: JSON content}, checked against the model's shapes (slots, frames, lanes)
    on an empty scene before the model loads (what depends on a scene's log is checked before the rollout)."""
    import json

    import jax
    import numpy as np

    from gpd_jax.prompts import PromptError, prompt_from_json
    from gpd_jax.scene import empty_scene
    from gpd_jax.spec import spec_from_config

    if not spec:
        return {}
    out = {}
    for path in [p for p in spec.split(",") if p]:
        if not os.path.isfile(path):
            raise UsageError(f"--prompt {path}: file not found")
        try:
            with open(path) as f:
                obj = json.load(f)
        except json.JSONDecodeError as e:
            raise UsageError(f"--prompt {path}: not valid JSON ({e})") from None
        if not isinstance(obj, dict):
            raise UsageError(f"--prompt {path}: expected a JSON object at the top level")
        mspec, _ = spec_from_config(config)
        blank = jax.tree.map(np.asarray, empty_scene(mspec.num_frames, mspec.num_agents, mspec.num_map_tokens)).replace(
            polylines=np.array([[[0.0, 0.0], [1.0, 0.0]]], np.float32), polyline_valid=np.ones((1, 2), bool))
        try:
            prompt_from_json(obj, blank, mspec.num_history, has_tokenizer=has_tokenizer, where=f"{path}: $",
                             frame_period_s=mspec.frame_period_s)
        except PromptError as e:
            raise UsageError(f"--prompt {e}") from None
        name = os.path.splitext(os.path.basename(path))[0]
        if name in out:
            raise UsageError(f"--prompt: two files named {name}")
        out[name] = obj
    return out


def _load(checkpoint: str):
    from gpd_jax.checkpoint import load_model

    try:
        return load_model(checkpoint)
    except (FileNotFoundError, ValueError, KeyError) as e:
        raise UsageError(f"cannot load the model from {checkpoint}: {e}") from None


def run_prompts(args: argparse.Namespace) -> int:
    """`rollout.py --prompt FILE[,FILE...]`: every scenario under every prompt (and the unconditioned traffic
    simulation), condition-respect scores to OUT/conditions.json, pictures with --render K."""
    from gpd_jax.evaluation.conditions import evaluate_prompts
    from gpd_jax.evaluation.report import to_json_compatible
    from gpd_jax.fsutil import atomic_write_json
    from gpd_jax.prompts import PromptError
    from gpd_jax.spec import EvalError

    model = _load(args.checkpoint)
    render_dir = os.path.join(args.out, "render") if args.render else None
    try:
        res = evaluate_prompts(model, args.data, args.split, args.prompts, num_scenarios=args.scenarios,
                               batch_size=args.batch, seed=args.seed, render_count=args.render,
                               render_dir=render_dir, size_px=args.render_size, options=args.options,
                               progress=not args.no_progress)
    except (PromptError, EvalError) as e:
        raise UsageError(str(e)) from None
    os.makedirs(args.out, exist_ok=True)
    # strict JSON: NaN (nothing to score, or no drivable area in the store) written as null
    atomic_write_json(os.path.join(args.out, "conditions.json"), to_json_compatible(res), allow_nan=False)
    keys = ("given_max_xy_m", "cap_violations", "max_valid_slots", "offroad_share", "offroad_corner_share",
            "offroad_share_lane_distance", "mean_lane_distance_m", "map_f1", "agent_ade_m", "agent_collision_share")
    print("prompt".ljust(30) + "".join(k.rjust(29) for k in keys))
    for name, r in res["prompts"].items():
        print(name.ljust(30) + "".join(f"{r.get(k, float('nan')):29.4g}" for k in keys))
    for source in sorted({r.get("offroad_source", "") for r in res["prompts"].values()} - {""}):
        which = ", ".join(n for n, r in res["prompts"].items() if r.get("offroad_source") == source)
        print(f"offroad_share drivable area ({which}): {source}")
    print(f"wrote {os.path.join(args.out, 'conditions.json')}", flush=True)
    return 0


def run(args: argparse.Namespace) -> int:
    """Loads the model, evaluates, prints the tables and writes the outputs (see `rollout.py`)."""
    if getattr(args, "prompts", None):
        return run_prompts(args)
    from gpd_jax.evaluation.bootstrap import SCENE_SUMS_FILE, save_scene_sums
    from gpd_jax.evaluation.driver import run_evaluation
    from gpd_jax.evaluation.outputs import write_evaluation
    from gpd_jax.evaluation.report import format_tables
    from gpd_jax.spec import EvalError

    distributed.initialize(args.cluster)
    t0 = time.perf_counter()
    model = _load(args.checkpoint)
    m = model.config.model
    print(f"model {args.checkpoint} loaded in {time.perf_counter() - t0:.1f} s ({m.num_frames} frames, "
          f"{m.num_history} history, {m.num_agents} slots, map tokenizer: {args.tokenizer_path or 'none'})",
          flush=True)
    try:
        results, items = run_evaluation(model, args.data, args.split, task_names=args.task_names,
                                        num_scenarios=args.scenarios, batch_size=args.batch, seed=args.seed,
                                        variant=args.variant, horizons_s=args.horizons, render_count=args.render,
                                        options=args.options, progress=not args.no_progress, scene_sums=True,
                                        samples=args.samples, realism_config=args.realism_config,
                                        export_official=args.export_official)
    except EvalError as e:
        raise UsageError(str(e)) from None
    if results is None:  # another process than 0 of a multi-process run: process 0 writes the outputs
        return 0
    if args.render > len(items):
        print(f"note: --render {args.render} but only {len(items)} scenarios evaluated", flush=True)
    results = {"checkpoint": args.checkpoint, **results}
    tables = format_tables(results, args.variant)
    print(tables, flush=True)
    per_scene = results.pop("scene_sums")
    write_evaluation(args.out, results, tables, items, args.task_names, tokenizer=model.tokenizer,
                     size_px=args.render_size)
    save_scene_sums(os.path.join(args.out, SCENE_SUMS_FILE), per_scene)
    if items:
        print(f"rendered {len(results['render']['files'])} files to {os.path.join(args.out, 'render')} in "
              f"{results['timing_s']['render']:.1f} s", flush=True)
    print(f"wrote {os.path.join(args.out, 'metrics.json')}", flush=True)
    return 0
