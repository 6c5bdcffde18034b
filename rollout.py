"""Multi-task evaluation of a trained GPD model: rollouts of every task, metrics, baselines, pictures.

    python rollout.py --data data/sumo6k --out runs/eval                         # checkpoints/gpd_sumo, test split
    python rollout.py --checkpoint DIR --data DIR [--split test] [--tasks all|a,b] --out DIR
                      [--scenarios N] [--batch B] [--render K] [--seed S] [--variant paper|corrected]
                      [--horizons 3,5,8] [--config.rollout.temperature=0.5]

Runs every requested task (keys of gpd_jax/tasks.py) on the first N scenarios of the split (store order) in one
compiled rollout per batch, scores them at 3 / 5 / 8 s next to the constant-velocity and log-replay baselines,
prints tables shaped like the paper's Tables 1 and 2 and writes OUT/metrics.json (and OUT/tables.txt); with
`--render K`, a GIF and a PNG strip per task of the first K scenarios go to OUT/render/. Agents scored: those
valid at the current frame. See gpd_jax/evaluate.py for the definitions and the metrics.json layout.

Bad input (missing checkpoint, data or split, unknown task, too many scenarios, model/data shape mismatch)
exits with status 2 and a message naming the problem; nothing is written to OUT then.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time

REPO_ROOT = os.path.dirname(os.path.abspath(__file__))
DEFAULT_CHECKPOINT = os.path.join(REPO_ROOT, "checkpoints", "gpd_sumo")
PROG = "rollout.py"


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse exits on its own; main() turns it into a return code
        raise _UsageError(message)


class _UsageError(Exception):
    pass


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description=__doc__.split("\n\n")[0],
                epilog="Any --config.rollout.X=value overrides that field of the model's rollout config.")
    p.add_argument("--checkpoint", default=DEFAULT_CHECKPOINT,
                   help="exported model directory or train.py workdir (default: checkpoints/gpd_sumo)")
    p.add_argument("--data", required=True, help="data store directory (python -m gpd_jax.data build)")
    p.add_argument("--split", default="test")
    p.add_argument("--tasks", default="all", help="'all' or a comma list of task keys")
    p.add_argument("--out", required=True, help="output directory (metrics.json, tables.txt, render/)")
    p.add_argument("--scenarios", type=int, default=None, help="first N scenarios of the split (default: all)")
    p.add_argument("--batch", type=int, default=8, help="scenarios per compiled rollout call (every task each)")
    p.add_argument("--render", type=int, default=0, metavar="K", help="GIF + PNG of every task for the first K")
    p.add_argument("--render-size", type=int, default=320, help="pixels per rendered frame")
    p.add_argument("--seed", type=int, default=0, help="rollout PRNG seed (used at temperature > 0)")
    p.add_argument("--variant", default="paper", choices=("paper", "corrected"),
                   help="metric variant of the main keys; the other is written with its name as a suffix")
    p.add_argument("--horizons", default="3,5,8", help="horizons in seconds (comma list)")
    p.add_argument("--log-map", default="tokens", choices=("tokens", "lanes"),
                   help="what tasks that take the map from the log but generate the ego (traffic simulation, "
                        "motion planning) are fed: the logged map tokens, encoded around the logged ego (the "
                        "paper's choice), or the log's lanes re-encoded around the generated ego every frame")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _fail(msg: str) -> int:
    print(f"{PROG}: error: {msg}", file=sys.stderr)
    return 2


def _atomic_write(path: str, text: str) -> None:
    from gpd_jax.fsutil import umask_mode

    d = os.path.dirname(path)
    fd, tmp = tempfile.mkstemp(dir=d, prefix=".tmp-", suffix=os.path.basename(path))
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        umask_mode(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    from gpd_jax.config import split_config_args

    overrides, rest = split_config_args(argv)
    try:
        args = _parser().parse_args(rest)
    except _UsageError as e:
        _parser().print_usage(sys.stderr)
        return _fail(str(e))
    except SystemExit as e:  # --help
        return int(e.code or 0)
    for o in overrides:
        if not o.startswith("--config.rollout."):
            return _fail(f"{o}: only --config.rollout.* fields can be overridden here")
    try:
        horizons = tuple(float(x) for x in args.horizons.split(",") if x.strip())
    except ValueError:
        return _fail(f"--horizons {args.horizons!r}: expected seconds, e.g. 3,5,8")
    if args.batch < 1:
        return _fail(f"--batch must be >= 1, got {args.batch}")
    if args.render < 0:
        return _fail(f"--render must be >= 0, got {args.render}")

    # cheap checks first (before JAX and the model load)
    from gpd_jax.tasks import resolve_task_names

    listed = [t for t in args.tasks.split(",") if t]
    if "all" in listed and len(listed) > 1:
        return _fail(f"--tasks {args.tasks}: 'all' cannot be combined with other task names")
    try:
        task_names = resolve_task_names(args.tasks)
    except KeyError as e:
        return _fail(f"--tasks: {e.args[0]}")
    if not task_names:
        return _fail("--tasks: no task given")
    ckpt = os.path.abspath(args.checkpoint)
    if not os.path.isdir(ckpt):
        return _fail(f"checkpoint directory not found: {ckpt}")
    if not os.path.isfile(os.path.join(ckpt, "config.json")):
        return _fail(f"{ckpt} is not a GPD checkpoint (no config.json)")
    data = os.path.abspath(args.data)
    out_dir = os.path.abspath(args.out)
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        return _fail(f"--out {out_dir} exists and is not a directory")

    from gpd_jax.checkpoint import config_from_json, load_model, resolve_tokenizer_path
    from gpd_jax.config import apply_overrides
    from gpd_jax.evaluate import EvalError, evaluate, format_tables, preflight, to_json_compatible

    # everything that needs only the config and the data, before the (slow) model load
    try:
        config = config_from_json(os.path.join(ckpt, "config.json"))
    except ValueError as e:
        return _fail(str(e))
    if config.get("stage") != "gpd" or "model" not in config:
        return _fail(f"{ckpt}/config.json: stage is {config.get('stage')!r}, not a GPD model")
    try:
        apply_overrides(config, overrides, source=os.path.join(ckpt, "config.json"))
    except (KeyError, ValueError) as e:
        return _fail(str(e.args[0]) if e.args else str(e))
    tok_path = config.model.get("map_tokenizer") or ""
    try:
        if tok_path:
            tok_path = resolve_tokenizer_path(tok_path, ckpt)
        if args.log_map == "lanes" and not tok_path:
            raise EvalError(f"--log-map lanes re-encodes the log's lanes with the model's map tokenizer, and {ckpt} "
                            "has none (config.model.map_tokenizer is empty)")
        preflight(config, data, args.split, task_names=task_names, num_scenarios=args.scenarios,
                  variant=args.variant, horizons_s=horizons, has_tokenizer=bool(tok_path))
    except FileNotFoundError as e:
        return _fail(f"map tokenizer of {ckpt}: {e}")
    except EvalError as e:
        return _fail(str(e))

    t0 = time.perf_counter()
    try:
        _, model = load_model(ckpt)
    except (FileNotFoundError, ValueError, KeyError) as e:
        return _fail(f"cannot load the model from {ckpt}: {e}")
    tok = None
    if tok_path:
        from gpd_jax.map_tokenizer import load_tokenizer

        try:
            tok = load_tokenizer(tok_path)
        except (FileNotFoundError, ValueError) as e:
            return _fail(f"map tokenizer {tok_path} of {ckpt}: {e}")
    print(f"model {ckpt} loaded in {time.perf_counter() - t0:.1f} s "
          f"({config.model.num_frames} frames, {config.model.num_history} history, {config.model.num_agents} slots, "
          f"map tokenizer: {tok_path or 'none'})", flush=True)

    try:
        results, items = evaluate(model, config, data, args.split, task_names=task_names,
                                  num_scenarios=args.scenarios, batch_size=args.batch, seed=args.seed,
                                  variant=args.variant, tokenizer=tok, horizons_s=horizons,
                                  render_count=args.render, log_map=args.log_map, progress=not args.no_progress)
    except EvalError as e:
        return _fail(str(e))
    if args.render > len(items):
        print(f"note: --render {args.render} but only {len(items)} scenarios evaluated", flush=True)
    results = {"checkpoint": ckpt, **results}
    tables = format_tables(results, args.variant)
    print(tables, flush=True)

    os.makedirs(out_dir, exist_ok=True)
    if items:
        from gpd_jax.fsutil import umask_mode
        from gpd_jax.render import render_items

        t1 = time.perf_counter()
        tmp = tempfile.mkdtemp(prefix=".render-", dir=out_dir)
        try:
            paths = render_items(items, task_names, tmp, num_history=int(config.model.num_history),
                                 frame_period_s=results["frame_period_s"], tokenizer=tok, size_px=args.render_size)
            final = os.path.join(out_dir, "render")
            if os.path.exists(final):
                old = tempfile.mkdtemp(prefix=".render-old-", dir=out_dir)
                os.replace(final, os.path.join(old, "render"))
                shutil.rmtree(old, ignore_errors=True)
            umask_mode(tmp, directory=True)
            os.replace(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        results["timing_s"]["render"] = round(time.perf_counter() - t1, 2)
        results["render"] = {"dir": "render", "files": sorted(os.path.basename(p) for p in paths),
                             "scenarios": [{"index": it.index, "scenario_id": it.scenario_id} for it in items]}
        print(f"rendered {len(paths)} files to {final} in {results['timing_s']['render']:.1f} s", flush=True)
    _atomic_write(os.path.join(out_dir, "tables.txt"), tables + "\n")
    _atomic_write(os.path.join(out_dir, "metrics.json"),
                  json.dumps(to_json_compatible(results), indent=2, allow_nan=False) + "\n")
    print(f"wrote {os.path.join(out_dir, 'metrics.json')}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
