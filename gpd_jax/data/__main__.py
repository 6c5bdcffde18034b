"""Command line: `python -m gpd_jax.data {build,inspect,bench-loader,near-duplicates,mirror,sensor,pack,realnets} ...`.

  build --source sumo --out DIR --scenarios N --seed S [--net FILE.net.xml ...] [--workers W] [--split SPLIT]
        [--real-networks] [--keep-overlaps] [--allow-near-duplicates] [--against STORE ...]
        [--traffic realistic|legacy] [--parking-edge-share F] [--parking-occupancy F] [--parked-leave-share F]
        [--short-stop-share F] [--drivers heterogeneous|uniform] [--ego-rule mixed|travel]
        [--ego-stationary-share F] [--lefthand-share F] [--static-tls-share F]
  build --source nuplan --out DIR --db PATH_OR_DIR --maps DIR [--max-per-log K] [--split SPLIT] [--workers W]
  build --source scenarionet --out DIR --db DATASET_DIR_OR_PKL [--max-per-log K] [--split SPLIT] [--workers W]
  build --source interaction --out DIR --db INTERACTION_ROOT [--split SPLIT] [--sites SITE ...] [--max-per-log K]
        [--workers W]   (splits by site: gpd_jax.data.sources.interaction.SITE_SPLITS; --split S builds the sites of S)
        (--split SPLIT: train, val or test, everything into that one split; default: splits by location)
        (every build: [--executor local|ray] [--address HOST:PORT]: its jobs on Ray tasks over a cluster, the
        store identical to a local build; docs/distributed.md)
  inspect DIR [--json PATH] [--no-lanes] [--road-edges]
  bench-loader DIR [--split train] [--batch-size 32] [--batches 200] [--threads 4] [--with-lanes]
  near-duplicates --eval STORE_OR_NET ... --reference STORE_OR_NET ... [--tol METRES]
  mirror DIR --out DIR2 [--split NAME ...]     (the mirror image of every scene: gpd_jax.data.augment)
  sensor DIR --out DIR2 [--split NAME ...] [--position-sigma M] [--heading-sigma DEG] [--correlation R]
        [--range M] [--gap-rate P] [--gap-frames K] [--seed S]
                                               (the scenes as a vehicle's tracker sees the other agents: drifting
                                               errors, a range, lost tracks; gpd_jax.data.augment.SensorView)
  pack DIR [DIR ...] --out FOLDER [--splits train ...] [--frame-stride S] [--agents A] [--drop-road]
                                               (one .tar.xz per store, only what a model reads: gpd_jax.data.pack)
  realnets --cache DIR [--splits train dev] [--tiles NAME ...]
                                               (real road-network tiles for training and development, printed as
                                               JSON {split: [paths]}: gpd_jax.data.sources.realnets)

A stopped build started again with the same arguments resumes where it left off.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys

from gpd_jax import interrupt
from gpd_jax.cliargs import (ArgumentParser, UsageError, count, nonnegative, output_dir, output_file, positive,
                             program, run_command, share)
from gpd_jax.data.executors import EXECUTORS, make_executor

PROG = "python -m gpd_jax.data"
SPLITS = ("train", "val", "test")  # what `build --split` accepts


TRAFFIC_FLAGS = ("parking_edge_share", "parking_occupancy", "parked_leave_share", "short_stop_share", "drivers",
                 "ego_rule", "ego_stationary_share", "lefthand_share", "static_tls_share", "curved_share")


def traffic_options(args) -> dict:
    """The keyword arguments of `sources.sumo.build_sumo` for the traffic flags (the preset, then each flag given)."""
    from gpd_jax.data.sources import sumo, sumo_traffic

    legacy = args.traffic == "legacy"
    traffic = dict(sumo_traffic.LEGACY_TRAFFIC) if legacy else {}
    for k in ("parking_edge_share", "parking_occupancy", "parked_leave_share", "short_stop_share", "drivers"):
        v = getattr(args, k)
        if v is not None:
            traffic[k] = v
    base = sumo.LEGACY_EGO if legacy else sumo.EgoChoice()
    ego = sumo.EgoChoice(args.ego_rule or base.rule,
                         base.stationary_share if args.ego_stationary_share is None else args.ego_stationary_share)
    if ego.rule == "travel" and args.ego_stationary_share is None:
        ego = sumo.EgoChoice("travel", 0.0)
    return {"traffic": traffic or None, "ego": ego,
            "lefthand_share": args.lefthand_share if args.lefthand_share is not None else (0.0 if legacy else None),
            "static_tls_share": (args.static_tls_share if args.static_tls_share is not None
                                 else (0.0 if legacy else 0.5)),
            "curved_share": args.curved_share or 0.0}


def main(argv=None) -> int:
    p = ArgumentParser(prog=program(PROG), description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("build", help="build a dataset of samples")
    b.add_argument("--source", choices=("sumo", "nuplan", "scenarionet", "interaction"), default="sumo")
    b.add_argument("--out", type=output_dir, required=True)
    b.add_argument("--scenarios", type=count, default=1000, help="SUMO: number of scenarios")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--net", nargs="+", default=None, help="SUMO: use these networks instead of generating")
    b.add_argument("--workers", type=count, default=2,
                   help="processes of this machine (one SUMO run, log or file chunk each); with --executor ray and "
                        "no --address: the CPUs of the Ray instance started here")
    b.add_argument("--executor", choices=EXECUTORS, default="local",
                   help="where the jobs run: local processes, or Ray tasks (pip install -e '.[ray]'; "
                        "docs/distributed.md); resumable either way")
    b.add_argument("--address", default=None, metavar="HOST:PORT",
                   help="--executor ray: the cluster to join (ray start --head prints it; 'auto': the one this "
                        "machine is part of); default: a Ray instance started on this machine")
    b.add_argument("--per-job", type=count, default=50, help="SUMO: scenarios per simulation run")
    b.add_argument("--split", choices=SPLITS, default=None,
                   help="put everything into this one split (default: splits by location); INTERACTION: build the "
                        "sites of this split (or put --sites into it)")
    b.add_argument("--db", help="nuPlan: a .db file or a directory of them; ScenarioNet: a dataset directory or "
                                "scenario .pkl files; INTERACTION: the dataset root (recorded_trackfiles/, maps/)")
    b.add_argument("--sites", nargs="+", default=None, metavar="SITE",
                   help="INTERACTION: only these sites (e.g. DR_USA_Roundabout_FT); default: those of --split, or all")
    b.add_argument("--maps", help="nuPlan: maps root (nuplan-maps-v1.0.json)")
    b.add_argument("--max-per-log", type=count, default=None, help="nuPlan: at most this many windows per log")
    b.add_argument("--real-networks", nargs="*", default=None, metavar="NAME",
                   help="SUMO: build on the real (OSM-derived) networks shipped with SUMO, one location each "
                        "(gpd_jax.data.sources.sumo_networks.real_networks), or only those named "
                        "(e.g. fokr_bs_demo DRT); layout 'real'")
    b.add_argument("--net-layout", default="given", help="SUMO: layout recorded for --net networks (e.g. real)")
    b.add_argument("--keep-overlaps", action="store_true",
                   help="SUMO: keep windows in which two recorded boxes overlap (the gate drops them by default)")
    b.add_argument("--refuse-near-duplicates", action=argparse.BooleanOptionalAction, default=True,
                   help="SUMO: stop (before simulating) when a val/test network nearly matches a train network "
                        "(default); --no-refuse-near-duplicates / --allow-near-duplicates only record and warn")
    b.add_argument("--allow-near-duplicates", dest="refuse_near_duplicates", action="store_false",
                   help=argparse.SUPPRESS)
    b.add_argument("--near-duplicate-tol", type=positive, default=None,
                   help="SUMO: metres of mean lane distance below which two networks are near-duplicates (2.5)")
    b.add_argument("--against", nargs="+", default=(), metavar="STORE",
                   help="SUMO: also check this build's networks against these stores' networks")
    t = b.add_argument_group("SUMO traffic (defaults: real-traffic mix; --traffic legacy = stores built before)")
    t.add_argument("--traffic", choices=("realistic", "legacy"), default="realistic",
                   help="preset of the options below: 'legacy' turns off parking, stops, driver mix, left-hand and "
                        "fixed-cycle networks and uses the 30 m travel ego rule")
    t.add_argument("--parking-edge-share", type=share, default=None, help="share of suitable edges with road-side "
                   "parking (0.4)")
    t.add_argument("--parking-occupancy", type=share, default=None, help="share of parking spaces filled (0.6)")
    t.add_argument("--parked-leave-share", type=share, default=None,
                   help="share of parked vehicles that leave during the recording (0.1)")
    t.add_argument("--short-stop-share", type=share, default=None,
                   help="share of moving vehicles that make one pick-up / drop-off stop (0.1)")
    t.add_argument("--drivers", choices=("heterogeneous", "uniform"), default=None,
                   help="driver types: vTypeDistributions of Krauss / IDM / EIDM drivers, or one IDM per class")
    t.add_argument("--ego-rule", choices=("mixed", "travel"), default=None,
                   help="mixed: a share of egos stationary at the current frame; travel: egos that move 30 m")
    t.add_argument("--ego-stationary-share", type=share, default=None,
                   help="mixed rule: share of windows whose ego stands at the current frame (0.25)")
    t.add_argument("--lefthand-share", type=share, default=None,
                   help="share of networks with left-hand traffic, netconvert --lefthand (generated: 0.25; "
                        "--net / --real-networks: 0, else a left-hand copy of each network drawn, location <name>_lh)")
    t.add_argument("--static-tls-share", type=share, default=None,
                   help="generated networks: share whose traffic lights run fixed cycles (0.5)")
    t.add_argument("--curved-share", type=share, default=None,
                   help="generated networks: share with curved streets, bulges and S-bends (0: straight streets)")
    i = sub.add_parser("inspect", help="summary statistics of a dataset")
    i.add_argument("dir")
    i.add_argument("--json", type=output_file, default=None, help="also write the statistics to this JSON file")
    i.add_argument("--no-lanes", action="store_true", help="skip the (slower) vector-lane statistics")
    i.add_argument("--road-edges", action="store_true",
                   help="also the road edges' sources, the scenes with traffic lights and the log's own offroad rate "
                        "by the realism metric's rule (JAX; slower)")
    bl = sub.add_parser("bench-loader", help="loader throughput and memory")
    bl.add_argument("dir")
    bl.add_argument("--split", default="train")
    bl.add_argument("--batch-size", type=count, default=32)
    bl.add_argument("--batches", type=count, default=200)
    bl.add_argument("--threads", type=count, default=4)
    bl.add_argument("--with-lanes", action="store_true")
    mi = sub.add_parser("mirror", help="a new store of the mirror images of a store's scenes (y -> -y: left-hand "
                                       "traffic on mirrored roads); encode its map tokens afterwards")
    mi.add_argument("dir")
    mi.add_argument("--out", type=output_dir, required=True)
    mi.add_argument("--split", nargs="+", default=None, help="default: every split")
    se = sub.add_parser("sensor", help="a new store of the scenes as an on-board tracker sees the agents other than "
                                       "the ego: drifting position and heading errors, a range, lost tracks")
    se.add_argument("dir")
    se.add_argument("--out", type=output_dir, required=True)
    se.add_argument("--split", nargs="+", default=None, help="default: every split")
    # unset: gpd_jax.data.augment.SensorView's defaults (that module imports JAX: it is read after the checks)
    se.add_argument("--position-sigma", type=nonnegative, default=None, help="metres")
    se.add_argument("--heading-sigma", type=nonnegative, default=None, help="degrees")
    se.add_argument("--correlation", type=float, default=None, help="AR(1) per stored frame")
    se.add_argument("--range", type=positive, default=None, help="metres from the ego")
    se.add_argument("--gap-rate", type=share, default=None, help="per agent and stored frame")
    se.add_argument("--gap-frames", type=count, default=None)
    se.add_argument("--seed", type=int, default=None)
    pk = sub.add_parser("pack", help="one .tar.xz per store with only what a model reads, to carry it elsewhere "
                                     "(gpd_jax.data.pack); tar xf it there")
    pk.add_argument("dirs", nargs="+", metavar="DIR")
    pk.add_argument("--out", type=output_dir, required=True, help="folder of the archives (DIR's name + .tar.xz)")
    pk.add_argument("--splits", nargs="+", default=["train"])
    pk.add_argument("--frame-stride", type=count, default=None,
                    help="keep only the stored frames a model at this stride reads (k S and k S - 1)")
    pk.add_argument("--agents", type=count, default=None, help="keep only the first this-many agent slots")
    pk.add_argument("--drop-road", action="store_true", help="leave out the road geometry (training does not read it)")
    nd = sub.add_parser("near-duplicates", help="networks whose lane geometry nearly matches (exit 1 if any)")
    nd.add_argument("--eval", nargs="+", required=True, metavar="STORE_OR_NET",
                    help="SUMO stores (their networks outside --reference-splits) or network files")
    nd.add_argument("--reference", nargs="+", required=True, metavar="STORE_OR_NET",
                    help="SUMO stores (their networks of --reference-splits) or network files")
    nd.add_argument("--reference-splits", nargs="+", default=["train"])
    nd.add_argument("--tol", type=positive, default=None, help="metres (default 2.5)")
    rn = sub.add_parser("realnets", help="real road-network tiles for training and development, prepared offline "
                                         "(gpd_jax.data.sources.realnets); prints {split: [paths]} as JSON")
    rn.add_argument("--cache", type=output_dir, required=True, help="directory for sources, tiles and manifest.json")
    rn.add_argument("--splits", nargs="+", default=None, help="default: train dev")
    rn.add_argument("--tiles", nargs="+", default=None, help="only these tiles (names in TILES)")
    from gpd_jax.data.errors import DataError

    return run_command(PROG, lambda: _run(p, p.parse_args(argv)), (DataError,))


class _Format(logging.Formatter):
    """Progress as plain lines; warnings and errors with their level."""

    def format(self, record):
        text = super().format(record)
        return text if record.levelno <= logging.INFO else f"{record.levelname}: {text}"


def _run(p: ArgumentParser, args) -> int:
    handler = logging.StreamHandler()
    handler.setFormatter(_Format("%(message)s"))
    logging.basicConfig(level=logging.INFO, handlers=[handler])
    if args.cmd == "build":
        interrupt.keep(f"the shards of finished jobs are kept in {args.out}")
        if args.source != "sumo" and (args.real_networks is not None or args.keep_overlaps or args.against):
            p.error("--real-networks, --keep-overlaps and --against are for --source sumo")
        if args.source != "interaction" and args.sites:
            p.error("--sites is for --source interaction")
        traffic_flags = [f"--{k.replace('_', '-')}" for k in TRAFFIC_FLAGS if getattr(args, k) is not None]
        if args.source != "sumo" and (traffic_flags or args.traffic != "realistic"):
            p.error(f"the SUMO traffic options ({', '.join(traffic_flags) or '--traffic'}) are for --source sumo")
        executor = make_executor(args.executor, args.workers, args.address)
        if args.source == "sumo":
            from gpd_jax.data.sources import sumo

            nets, layout = args.net, args.net_layout
            if args.real_networks is not None:
                from gpd_jax.data.sources import sumo_networks

                if args.net:
                    p.error("--real-networks and --net exclude each other")
                nets, layout = sumo_networks.real_networks(names=args.real_networks or None), "real"
            man = sumo.build_sumo(args.out, args.scenarios, args.seed, nets, args.workers, args.split,
                                  args.per_job, net_layout=layout, keep_overlaps=args.keep_overlaps,
                                  refuse_near_duplicates=args.refuse_near_duplicates,
                                  near_duplicate_tol=args.near_duplicate_tol, against=args.against,
                                  executor=executor, **traffic_options(args))
        elif args.source == "interaction":
            if not args.db:
                p.error("--source interaction needs --db (the INTERACTION dataset root: recorded_trackfiles/, maps/)")
            from gpd_jax.data.sources import interaction

            man = interaction.build_interaction(args.out, args.db, args.seed, args.split, args.sites,
                                                args.max_per_log, workers=args.workers, executor=executor)
        elif args.source == "scenarionet":
            if not args.db:
                p.error("--source scenarionet needs --db (a ScenarioNet dataset directory or .pkl files)")
            from gpd_jax.data.sources import scenarionet

            man = scenarionet.build_scenarionet(args.out, args.db, args.seed, args.split, args.max_per_log,
                                                workers=args.workers, per_job=args.per_job, executor=executor)
        else:
            if not args.db or not args.maps:
                p.error("--source nuplan needs --db and --maps")
            from gpd_jax.data.sources import nuplan

            man = nuplan.build_nuplan(args.out, args.db, args.maps, args.seed, args.split, args.max_per_log,
                                      workers=args.workers, executor=executor)
        print(json.dumps({"num_samples": man["num_samples"],
                          "splits": {k: v["num_samples"] for k, v in man["splits"].items()},
                          "build_wall_s": round(man["build"]["build_wall_s"], 1)}))
    elif args.cmd == "realnets":
        from gpd_jax.data.sources import realnets

        splits = tuple(args.splits) if args.splits else realnets.SPLITS
        print(json.dumps(realnets.prepare_real_networks(args.cache, splits=splits, names=args.tiles), indent=1))
    elif args.cmd == "mirror":
        from gpd_jax.data.augment import mirror_store

        man = mirror_store(args.dir, args.out, args.split)
        print(json.dumps({"num_samples": man["num_samples"],
                          "splits": {k: v["num_samples"] for k, v in man["splits"].items()}}))
    elif args.cmd == "sensor":
        from gpd_jax.data.augment import SensorView, sensor_store

        given = dict(position_sigma_m=args.position_sigma, heading_sigma_deg=args.heading_sigma,
                     correlation=args.correlation, range_m=args.range, gap_rate=args.gap_rate,
                     gap_frames=args.gap_frames, seed=args.seed)
        try:
            view = SensorView(**{k: v for k, v in given.items() if v is not None})
        except ValueError as e:
            raise UsageError(str(e)) from None
        man = sensor_store(args.dir, args.out, view, args.split)
        print(json.dumps({"num_samples": man["num_samples"],
                          "splits": {k: v["num_samples"] for k, v in man["splits"].items()}}))
    elif args.cmd == "pack":
        from gpd_jax.data.pack import pack_store

        for d in args.dirs:
            pack_store(d, args.out, splits=args.splits, frame_stride=args.frame_stride, num_agents=args.agents,
                       drop_road=args.drop_road)
    elif args.cmd == "near-duplicates":
        import os

        from gpd_jax.data import netgeom

        def fps(items, in_ref):
            out = []
            for x in items:
                if os.path.isdir(x):
                    idx = netgeom.read_network_index(x)
                    want = [s for s in {r.get("split") for r in idx.values()}
                            if (s in args.reference_splits) == in_ref]
                    out += netgeom.store_fingerprints(x, want)
                else:
                    out.append(netgeom.as_fingerprint(x))
            return out

        tol = netgeom.DEFAULT_TOL if args.tol is None else args.tol
        pairs = netgeom.near_duplicates(fps(args.eval, False), fps(args.reference, True), tol)
        print(json.dumps({"near_duplicates": pairs, "tol_m": tol}, indent=1))
        return 1 if pairs else 0
    elif args.cmd == "bench-loader":
        from gpd_jax.data import loader

        print(json.dumps(loader.benchmark(args.dir, args.split, args.batch_size, args.batches,
                                          num_threads=args.threads, with_lanes=args.with_lanes,
                                          with_polylines=args.with_lanes)))
    else:
        from gpd_jax.data import inspection

        s = inspection.inspect(args.dir, with_lanes=not args.no_lanes)
        if args.road_edges:
            s["road_edges"] = inspection.road_edge_summary(args.dir)
        print(inspection.format_summary(s))
        if args.json:
            from gpd_jax.data.store import atomic_write_json

            atomic_write_json(args.json, s)
    return 0


if __name__ == "__main__":
    sys.exit(main())
