"""What `rollout.py` runs: argument checks that need no model (cheap, first), then load, evaluate, print, write.

Every problem with the input is a `UsageError` naming it, raised before the model loads and before anything is
written (the command line turns it into exit status 2).
"""

from __future__ import annotations

import argparse
import os
import time

from gpd_jax.checkpoint import CONFIG_FILE, load_model, resolve_tokenizer_path
from gpd_jax.config import apply_overrides, config_from_json, split_config_args
from gpd_jax.evaluation.bootstrap import SCENE_SUMS_FILE, save_scene_sums
from gpd_jax.evaluation.driver import evaluate
from gpd_jax.evaluation.outputs import write_evaluation
from gpd_jax.evaluation.preflight import preflight
from gpd_jax.evaluation.report import format_tables, to_json_compatible
from gpd_jax.spec import EvalError
from gpd_jax.tasks import resolve_task_names


class UsageError(Exception):
    """Bad command-line input; the message names the argument or file."""


class Parser(argparse.ArgumentParser):
    """An ArgumentParser that raises `UsageError` instead of exiting (so the caller picks the exit status)."""

    def error(self, message):
        self.print_usage()
        raise UsageError(message)


def check_arguments(parser: argparse.ArgumentParser, argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
    """Parses `argv` and checks everything that needs only the arguments, the config and the data. Returns
    (args with `task_names`, `horizons`, `config` (overrides applied) and `tokenizer_path` added, overrides)."""
    overrides, rest = split_config_args(argv)
    args = parser.parse_args(rest)
    for o in overrides:
        if not o.startswith("--config.rollout."):
            raise UsageError(f"{o}: only --config.rollout.* fields can be overridden here")
    try:
        args.horizons = tuple(float(x) for x in args.horizons.split(",") if x.strip())
    except ValueError:
        raise UsageError(f"--horizons {args.horizons!r}: expected seconds, e.g. 3,5,8") from None
    for name in ("batch", "render"):
        low = 1 if name == "batch" else 0
        if getattr(args, name) < low:
            raise UsageError(f"--{name} must be >= {low}, got {getattr(args, name)}")
    listed = [t for t in args.tasks.split(",") if t]
    if "all" in listed and len(listed) > 1:
        raise UsageError(f"--tasks {args.tasks}: 'all' cannot be combined with other task names")
    try:
        args.task_names = resolve_task_names(args.tasks)
    except KeyError as e:
        raise UsageError(f"--tasks: {e.args[0]}") from None
    if not args.task_names:
        raise UsageError("--tasks: no task given")
    ckpt = args.checkpoint = os.path.abspath(args.checkpoint)
    if not os.path.isdir(ckpt):
        raise UsageError(f"checkpoint directory not found: {ckpt}")
    if not os.path.isfile(os.path.join(ckpt, CONFIG_FILE)):
        raise UsageError(f"{ckpt} is not a GPD checkpoint (no {CONFIG_FILE})")
    args.data, args.out = os.path.abspath(args.data), os.path.abspath(args.out)
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise UsageError(f"--out {args.out} exists and is not a directory")
    try:
        config = config_from_json(os.path.join(ckpt, CONFIG_FILE))
        if config.get("stage") != "gpd" or "model" not in config:
            raise UsageError(f"{ckpt}/{CONFIG_FILE}: stage is {config.get('stage')!r}, not a GPD model")
        apply_overrides(config, overrides, source=os.path.join(ckpt, CONFIG_FILE))
        args.tokenizer_path = resolve_tokenizer_path(config.model.map_tokenizer, ckpt)
        if args.log_map == "lanes" and not args.tokenizer_path:
            raise UsageError(f"--log-map lanes re-encodes the log's lanes with the model's map tokenizer, and {ckpt} "
                             "has none (config.model.map_tokenizer is empty)")
        if args.gen_map == "warp" and not args.tokenizer_path:
            raise UsageError(f"--gen-map warp moves generated maps through the model's map tokenizer, and {ckpt} "
                             "has none (config.model.map_tokenizer is empty)")
        preflight(config, args.data, args.split, task_names=args.task_names, num_scenarios=args.scenarios,
                  variant=args.variant, horizons_s=args.horizons, has_tokenizer=bool(args.tokenizer_path))
    except FileNotFoundError as e:
        raise UsageError(f"map tokenizer of {ckpt}: {e}") from None
    except (EvalError, KeyError, ValueError) as e:
        raise UsageError(str(e.args[0]) if e.args else str(e)) from None
    args.config = config
    args.prompts = _read_prompts(getattr(args, "prompt", None), bool(args.tokenizer_path), config)
    return args, overrides


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
        if "lanes" in obj and not has_tokenizer:
            raise UsageError(f"--prompt {path}: a vector-map prompt (lanes) needs the model's map tokenizer, and "
                             "the model has none (config.model.map_tokenizer is empty)")
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


def run_prompts(args: argparse.Namespace) -> int:
    """`rollout.py --prompt FILE[,FILE...]`: every scenario under every prompt (and the unconditioned traffic
    simulation), condition-respect scores to OUT/conditions.json, pictures with --render K."""
    from gpd_jax.evaluation.conditions import evaluate_prompts
    from gpd_jax.fsutil import atomic_write_json
    from gpd_jax.prompts import PromptError

    model = load_model(args.checkpoint).replace(config=args.config)
    render_dir = os.path.join(args.out, "render") if args.render else None
    try:
        res = evaluate_prompts(model, args.data, args.split, args.prompts, num_scenarios=args.scenarios,
                               batch_size=args.batch, seed=args.seed, render_count=args.render,
                               render_dir=render_dir, size_px=args.render_size)
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


def run(args: argparse.Namespace, overrides: list[str]) -> int:
    """Loads the model, evaluates, prints the tables and writes the outputs (see `rollout.py`)."""
    if getattr(args, "prompts", None):
        return run_prompts(args)
    t0 = time.perf_counter()
    try:
        model = load_model(args.checkpoint)
    except (FileNotFoundError, ValueError, KeyError) as e:
        raise UsageError(f"cannot load the model from {args.checkpoint}: {e}") from None
    model = model.replace(config=args.config)  # with the --config.rollout.* overrides
    m = model.config.model
    print(f"model {args.checkpoint} loaded in {time.perf_counter() - t0:.1f} s ({m.num_frames} frames, "
          f"{m.num_history} history, {m.num_agents} slots, map tokenizer: {args.tokenizer_path or 'none'})",
          flush=True)
    try:
        results, items = evaluate(model, args.data, args.split, task_names=args.task_names,
                                  num_scenarios=args.scenarios, batch_size=args.batch, seed=args.seed,
                                  variant=args.variant, horizons_s=args.horizons, render_count=args.render,
                                  log_map=args.log_map, gen_map=args.gen_map, progress=not args.no_progress,
                                  scene_sums=True)
    except EvalError as e:
        raise UsageError(str(e)) from None
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
