"""Command line: `python -m gpd_jax.data {build,inspect} ...`.

  build --source sumo --out DIR --scenarios N --seed S [--net FILE.net.xml ...] [--workers W] [--split NAME]
  build --source nuplan --out DIR --db PATH_OR_DIR --maps DIR [--max-per-log K] [--split NAME]
  build --source scenarionet --out DIR --db DATASET_DIR_OR_PKL [--max-per-log K] [--split NAME] [--workers W]
  inspect DIR [--json PATH] [--no-lanes]
  bench-loader DIR [--split train] [--batch-size 32] [--batches 200] [--threads 4] [--with-lanes]

A stopped build started again with the same arguments resumes where it left off.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m gpd_jax.data", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("build", help="build a dataset of samples")
    b.add_argument("--source", choices=("sumo", "nuplan", "scenarionet"), default="sumo")
    b.add_argument("--out", required=True)
    b.add_argument("--scenarios", type=int, default=1000, help="SUMO: number of scenarios")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--net", nargs="+", default=None, help="SUMO: use these networks instead of generating")
    b.add_argument("--workers", type=int, default=2, help="SUMO: processes (one SUMO each)")
    b.add_argument("--per-job", type=int, default=50, help="SUMO: scenarios per simulation run")
    b.add_argument("--split", default=None, help="put everything into this one split")
    b.add_argument("--db", help="nuPlan: a .db file or a directory of them")
    b.add_argument("--maps", help="nuPlan: maps root (nuplan-maps-v1.0.json)")
    b.add_argument("--max-per-log", type=int, default=None, help="nuPlan: at most this many windows per log")
    i = sub.add_parser("inspect", help="summary statistics of a dataset")
    i.add_argument("dir")
    i.add_argument("--json", default=None, help="also write the statistics to this JSON file")
    i.add_argument("--no-lanes", action="store_true", help="skip the (slower) vector-lane statistics")
    bl = sub.add_parser("bench-loader", help="loader throughput and memory")
    bl.add_argument("dir")
    bl.add_argument("--split", default="train")
    bl.add_argument("--batch-size", type=int, default=32)
    bl.add_argument("--batches", type=int, default=200)
    bl.add_argument("--threads", type=int, default=4)
    bl.add_argument("--with-lanes", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    from gpd_jax.data.errors import DataError

    try:
        if args.cmd == "build":
            from gpd_jax.data import build

            if args.source == "sumo":
                man = build.build_sumo(args.out, args.scenarios, args.seed, args.net, args.workers, args.split,
                                       args.per_job)
            elif args.source == "scenarionet":
                if not args.db:
                    p.error("--source scenarionet needs --db (a ScenarioNet dataset directory or .pkl files)")
                man = build.build_scenarionet(args.out, args.db, args.seed, args.split, args.max_per_log,
                                              workers=args.workers, per_job=args.per_job)
            else:
                if not args.db or not args.maps:
                    p.error("--source nuplan needs --db and --maps")
                man = build.build_nuplan(args.out, args.db, args.maps, args.seed, args.split, args.max_per_log)
            print(json.dumps({"num_samples": man["num_samples"],
                              "splits": {k: v["num_samples"] for k, v in man["splits"].items()},
                              "build_wall_s": round(man["build"]["build_wall_s"], 1)}))
        elif args.cmd == "bench-loader":
            from gpd_jax.data import loader

            print(json.dumps(loader.benchmark(args.dir, args.split, args.batch_size, args.batches,
                                              num_threads=args.threads, with_lanes=args.with_lanes,
                                              with_polylines=args.with_lanes)))
        else:
            from gpd_jax.data import inspection

            s = inspection.inspect(args.dir, with_lanes=not args.no_lanes)
            print(inspection.format_summary(s))
            if args.json:
                from gpd_jax.data.store import atomic_write_json

                atomic_write_json(args.json, s)
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
