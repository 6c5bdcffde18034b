"""Command line of the map tokenizer.

  python -m gpd_jax.map_tokenizer evaluate [--checkpoint NAME_OR_DIR] --data DIR [--split test] [--json PATH]
  python -m gpd_jax.map_tokenizer diagnose --data DIR [--split test] [--json PATH]
  python -m gpd_jax.map_tokenizer encode [--checkpoint NAME_OR_DIR] --data DIR [--splits train val test] [--force]
  python -m gpd_jax.map_tokenizer export --workdir WORKDIR --out DIR
  python -m gpd_jax.map_tokenizer bench [--batch 64] [--encoders NAME_OR_DIR ...]
  python -m gpd_jax.map_tokenizer netframes --out DIR [--generated N] [--seed S] [--real NET ...] [--real-lefthand]
  python -m gpd_jax.map_tokenizer pack-netframes DIR [DIR ...] --out OUTDIR [--networks N]

`evaluate` reconstructs frames (raster -> tokens -> lanes) and reports the map metrics of
`gpd_jax.metrics.map` against the frames' SLEDGE vector lanes: f1 (paper-faithful, 1.5 m), precision, recall,
lateral, chamfer (paper-faithful, m^2), chamfer_corrected (set-based, metres), the cut-invariant
f1/precision/recall/chamfer/chamfer_within_cutfree (lengths of line within 1.5 m of the other set, whatever
the cut into lines; *_cutfree_directed: only where the other set runs the same way), the raster-level
reconstruction raster_iou and raster_precision/recall/f1 (decoded lines drawn with the tokenizer's rasterizer
against its input raster, 1.5 m tolerance), plus codebook_usage (fraction of codes used by the evaluated tokens)
and perplexity, and the paper's recall by GT line length and by how many of a line's ends lie inside the window
rather than on its border (recall_by_gt_ends); the reconstruction figures: f1@T and f1_cutfree@T at T = 0.5 / 1 /
1.5 m and connectivity (the share of GT successor pairs whose matched predictions still join; successor_pairs
counts them). Frames 0, s, 2s, ... (`--frame-stride s`) of every sample are evaluated, or with `--draw-seed`
one seeded random frame per sample (training validation's draw). `diagnose` (no tokenizer) describes the GT cut of the same frames: lines per frame before and after the 50-line cap,
line lengths, what 20 points per line lose, and the learnability probe: the paper's F1 of the GT re-cut
(`recut_polylines`: lines split at their middle, or joined where one-to-one) against the GT, beside the cut-invariant
F1. `encode` writes every frame's 64 tokens next to the samples (`save_map_tokens`) and
records the tokenizer's fingerprint with them; shards this tokenizer already encoded (at the same frames or
more) are skipped, so an interrupted run resumes (`--force` re-encodes). `--frame-stride S` encodes only
frames 0, S, 2S, ... (S times faster): enough for a model that reads every S-th frame
(`config.data.frame_stride` a multiple of S); the other frames are stored as not encoded.
The checkpoint is a shipped tokenizer's name (`gpd_jax.list_models("map_tokenizer")`; default `map_tokenizer`) or
a folder (an export or a training workdir). `netframes` builds map-only
training frames (`gpd_jax.map_tokenizer.netframes`: many networks, poses drawn on their lanes, no traffic) that
stand in a training mixture beside stores; it resumes where it stopped. `pack-netframes` writes each as
OUTDIR/<name>.tar.xz (centimetre-rounded, ~13x smaller) to carry to another machine: `tar xf` gives the directory
back (stores: `python -m gpd_jax.data pack STORE --agents 1 --drop-road` keeps what the tokenizer reads).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

from gpd_jax import interrupt
from gpd_jax.cliargs import (ArgumentParser, UsageError, count, count0, output_dir, output_file, program, run_command,
                             share)
from gpd_jax.data.errors import DataError

PROG = "python -m gpd_jax.map_tokenizer"
DEFAULT_CHECKPOINT = "map_tokenizer"


def _tokenizer(ref: str):
    """The tokenizer a --checkpoint names (a shipped name or a folder)."""
    from gpd_jax.map_tokenizer.tokenizer import load_tokenizer

    return load_tokenizer(ref)


def cmd_evaluate(args) -> dict:
    import jax

    from gpd_jax.data.lanes import RECUT_MODES

    if args.gt_recut is not None and args.gt_recut not in RECUT_MODES:
        raise UsageError(f"--gt-recut {args.gt_recut}: one of {', '.join(RECUT_MODES)}")
    from gpd_jax.map_tokenizer.store import frame_batches
    from gpd_jax.map_tokenizer.evaluation import make_eval_step, tokenizer_metrics

    tok = _tokenizer(args.checkpoint)
    if args.draw_seed is None:
        batches = frame_batches(args.data, args.split, args.batch_size, seed=0, shuffle=False, repeat=False,
                                frame_stride=args.frame_stride, max_batches=args.max_batches, gt_recut=args.gt_recut)
    else:  # training validation's draw: one seeded random frame per sample, samples shuffled
        batches = frame_batches(args.data, args.split, args.batch_size, seed=args.draw_seed, shuffle=True,
                                repeat=False, max_batches=args.max_batches, gt_recut=args.gt_recut)
    t0 = time.perf_counter()
    m = tokenizer_metrics(tok.graphdef, tok.params, tok.config, batches,
                          jax.jit(make_eval_step(tok.graphdef, tok.config, quantized=not args.continuous)))
    m.update(split=args.split, data=os.path.abspath(args.data), checkpoint=args.checkpoint,
             frame_stride=None if args.draw_seed is not None else args.frame_stride, draw_seed=args.draw_seed,
             f1_threshold_m=1.5, gt_recut=args.gt_recut, latents="continuous" if args.continuous else "codes",
             wall_s=round(time.perf_counter() - t0, 1))
    print(json.dumps(m, indent=2))
    if args.json:
        from gpd_jax.fsutil import atomic_write_json
        atomic_write_json(args.json, m, indent=2)
    return m


def cmd_diagnose(args) -> dict:
    from gpd_jax.map_tokenizer.evaluation import cut_diagnostics
    from gpd_jax.map_tokenizer.store import frame_batches

    batches = frame_batches(args.data, args.split, args.batch_size, seed=0, shuffle=False, repeat=False,
                            frame_stride=args.frame_stride, max_batches=args.max_batches)
    t0 = time.perf_counter()
    m = cut_diagnostics(batches)
    m.update(split=args.split, data=os.path.abspath(args.data), frame_stride=args.frame_stride,
             wall_s=round(time.perf_counter() - t0, 1))
    print(json.dumps(m, indent=2))
    if args.json:
        from gpd_jax.fsutil import atomic_write_json
        atomic_write_json(args.json, m, indent=2)
    return m


def cmd_encode(args) -> None:
    import numpy as np

    from gpd_jax.data.store import (MISSING_MAP_TOKEN, NUM_MAP_TOKENS, Shard, list_splits, map_tokens_record,
                                    save_map_tokens, shard_dir, shard_indices)

    tok = _tokenizer(args.checkpoint)
    fingerprint = tok.fingerprint()
    stride = int(args.frame_stride)
    if int(tok.config.model.num_codes) > MISSING_MAP_TOKEN:
        raise UsageError(f"{args.checkpoint}: {tok.config.model.num_codes} codes do not fit the store's uint8 map "
                         f"tokens (at most {MISSING_MAP_TOKEN})")

    from tqdm import tqdm

    interrupt.keep(f"the shards encoded so far are kept in {args.data} (a rerun skips them)")
    splits = args.splits or list_splits(args.data)
    bar = tqdm(desc="encode (compiles on the first sample)", unit="sample", dynamic_ncols=True)
    for split in splits:
        for j in shard_indices(args.data, split):
            rec = map_tokens_record(args.data, split, j)
            if (not args.force and rec is not None and rec.get("tokenizer") == fingerprint
                    and stride % int(rec["frame_stride"]) == 0):
                print(f"{split} shard {j}: already encoded by this tokenizer ({fingerprint}, every "
                      f"{rec['frame_stride']} frame(s)), skipped")
                continue
            shard = Shard(shard_dir(args.data, split, j))
            a = shard.arrays
            n, t = a["ego_pose"].shape[:2]
            tokens = np.full((n, t, NUM_MAP_TOKENS), MISSING_MAP_TOKEN, np.uint8)
            for i in range(n):  # one sample at a time: the same program as the on-the-fly encoding (Model.prepare)
                tokens[i, ::stride] = np.asarray(tok.encode_frames(a["polylines"][i:i + 1],
                                                                   a["polyline_valid"][i:i + 1],
                                                                   a["ego_pose"][i:i + 1, ::stride]))[0]
                bar.set_description(f"encode {split} shard {j}")
                bar.update(1)
            path = save_map_tokens(args.data, split, j, tokens, tokenizer=fingerprint, frame_stride=stride)
            bar.write(f"{split} shard {j}: {n} samples x {len(range(0, t, stride))} of {t} frames -> {path}")
    bar.close()


def cmd_export(args) -> None:
    from gpd_jax.map_tokenizer.tokenizer import export_tokenizer, load_tokenizer

    tok = load_tokenizer(args.workdir)
    export_tokenizer(tok.params, tok.config, args.out)
    size = sum(os.path.getsize(os.path.join(args.out, f)) for f in os.listdir(args.out))
    print(f"exported {args.workdir} -> {args.out} ({size / 1e6:.2f} MB)")


def cmd_bench(args) -> None:
    from gpd_jax.map_tokenizer.bench import encode_speed, run
    if args.encoders:
        print(json.dumps(encode_speed([_tokenizer(r) for r in args.encoders], args.encoders, batch=args.batch),
                         indent=2))
    else:
        print(json.dumps(run(batch=args.batch), indent=2))


def cmd_netframes(args) -> None:
    from gpd_jax.map_tokenizer.netframes import build_netframes

    try:
        man = build_netframes(args.out, args.generated, args.seed, args.real, args.real_lefthand,
                              args.lefthand_share, args.curved_share, args.ignore_turnarounds)
    except DataError as e:
        raise UsageError(str(e)) from None
    gen = [r for r in man["networks"] if r["source"] == "generated"]
    print(f"{man['num_networks']} networks ({len(gen)} generated, {man['num_networks'] - len(gen)} real), "
          f"{sum(r['lane_km'] for r in man['networks']):.0f} lane km -> {args.out}")


def cmd_pack_netframes(args) -> None:
    from gpd_jax.map_tokenizer.netframes import pack_netframes

    for d in args.dirs:
        try:
            path = pack_netframes(d, args.out, args.networks)
        except DataError as e:
            raise UsageError(str(e)) from None
        print(f"{d} -> {path} ({os.path.getsize(path) / 1e6:.1f} MB)")


def main(argv=None) -> int:
    p = ArgumentParser(prog=program(PROG), description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)

    def split_args(q):  # the store, split and batching that evaluate and diagnose both read
        q.add_argument("--data", required=True)
        q.add_argument("--split", default="test")
        q.add_argument("--json", type=output_file, default=None)
        q.add_argument("--batch-size", type=count, default=32)
        q.add_argument("--frame-stride", type=count, default=10)
        q.add_argument("--max-batches", type=count, default=None)

    e = sub.add_parser("evaluate", help="reconstruction metrics of a checkpoint on a data split")
    e.add_argument("--checkpoint", default=DEFAULT_CHECKPOINT)
    split_args(e)
    e.add_argument("--gt-recut", default=None, metavar="MODE",  # one of gpd_jax.data.lanes.RECUT_MODES (checked first)
                   help="score against the GT of the polylines re-cut this way (the raster stays as stored): a "
                        "probe of how much the GT's cut costs, or the figure of a tokenizer trained on that cut "
                        "(config data.gt_recut); beside the stored cut's, never instead of it")
    e.add_argument("--continuous", action="store_true",
                   help="decode the encoder's continuous latents, not their codes: the figure of a tokenizer "
                        "trained without its codebook (a probe of what the quantiser costs; no tokens to ship)")
    e.add_argument("--draw-seed", type=int, default=None,
                   help="instead of frames 0, S, 2S, ...: one random frame per sample, samples shuffled, drawn with "
                        "this seed as training's validation draws them (--draw-seed 12345 --max-batches 8: the 256 "
                        "dev frames of docs/results.md's tokenizer probes)")
    split_args(sub.add_parser("diagnose", help="how the GT vector lanes cut the road; the paper F1 of the GT re-cut"))
    c = sub.add_parser("encode", help="write map tokens of every frame next to the samples")
    c.add_argument("--checkpoint", default=DEFAULT_CHECKPOINT)
    c.add_argument("--data", required=True)
    c.add_argument("--splits", nargs="*", default=None)
    c.add_argument("--frame-stride", type=count, default=1,
                   help="encode frames 0, S, 2S, ... only (enough for models with data.frame_stride a multiple "
                        "of S)")
    c.add_argument("--force", action="store_true",
                   help="re-encode shards whose tokens this tokenizer already wrote (skipped by default, so an "
                        "interrupted encode resumes)")
    x = sub.add_parser("export", help="write a training workdir's latest params as a compact checkpoint")
    x.add_argument("--workdir", required=True)
    x.add_argument("--out", type=output_dir, required=True, help="the export's folder")
    b = sub.add_parser("bench", help="rasterizer and matching throughput, or the tokenizers' encoding speed")
    b.add_argument("--batch", type=count, default=64)
    b.add_argument("--encoders", nargs="*", default=None, metavar="NAME_OR_DIR",
                   help="instead: frames encoded per second by each of these tokenizers (raster or vector) on the "
                        "same synthetic frames, in one run, with the ratio to the first")
    n = sub.add_parser("netframes", help="map-only training frames: many networks, poses on their lanes")
    n.add_argument("--out", type=output_dir, required=True)
    n.add_argument("--generated", type=count0, default=0, help="generated networks (sumo_networks.random_net_spec)")
    n.add_argument("--seed", type=int, default=0)
    n.add_argument("--real", nargs="*", default=[], help="real map files used as they are: SUMO .net.xml[.gz], Lanelet2 .osm, CommonRoad .xml, Apollo .bin")
    n.add_argument("--real-lefthand", action="store_true", help="also a left-hand copy of each --real map")
    n.add_argument("--lefthand-share", type=share, default=0.25)
    n.add_argument("--curved-share", type=share, default=0.5)
    n.add_argument("--ignore-turnarounds", action="store_true")
    k = sub.add_parser("pack-netframes", help="netframes directories as .tar.xz archives to carry elsewhere")
    k.add_argument("dirs", nargs="+", metavar="DIR")
    k.add_argument("--out", type=output_dir, required=True, help="folder of the archives (DIR's name + .tar.xz)")
    k.add_argument("--networks", type=count, default=None, help="only the first N networks of each")
    commands = {"evaluate": cmd_evaluate, "diagnose": cmd_diagnose, "encode": cmd_encode, "export": cmd_export,
                "bench": cmd_bench, "netframes": cmd_netframes, "pack-netframes": cmd_pack_netframes}

    def work():
        args = p.parse_args(argv)
        commands[args.cmd](args)

    return run_command(PROG, work, (DataError, FileNotFoundError, ValueError))


if __name__ == "__main__":
    sys.exit(main())
