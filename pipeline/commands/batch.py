"""`batch`: the pipeline on many scenes, N at a time on this machine or as tasks on a Ray cluster, then a table of
the results (also OUT/batch.json and OUT/batch.csv)."""
from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.batch import BatchOptions, LocalWorkers, format_table, plan_jobs, run_batch
from pipeline.batch_ray import RayCluster
from pipeline.commands.common import add_scene_arguments
from pipeline.scenes import read_scene_list
from pipeline.stage import STAGE_ORDER


def add_arguments(parser: argparse.ArgumentParser, command: str) -> None:
    parser.add_argument("scenes", type=Path, nargs="+", metavar="SCENE",
                        help="folders of photos or videos, or .txt files listing them one a line")
    add_scene_arguments(parser, needs_scene=False)
    parser.set_defaults(out=Path("out"))
    parser.add_argument("--until", choices=STAGE_ORDER, help="stop each scene after this stage")
    parser.add_argument("--workers", type=int, default=1, help="scenes at a time on this machine (default: 1)")
    parser.add_argument("--ray", nargs="?", const="", metavar="ADDRESS",
                        help="run on a Ray cluster at ADDRESS (auto, HOST:6379, ray://HOST:10001; put it after the "
                             "scenes); alone: the cluster `ray start` made here, else a new local one")
    parser.add_argument("--cpus-per-scene", type=float, default=1.0,
                        help="CPUs a scene's Ray task asks for (default: 1)")


def main(args: argparse.Namespace) -> None:
    jobs = plan_jobs(read_scene_list(args.scenes), args.out)
    options = BatchOptions(preset=args.preset, overrides=args.overrides, until=args.until)
    options.check()
    if args.ray is not None:
        workers = RayCluster(args.ray or None, cpus_per_scene=args.cpus_per_scene)
    else:
        workers = LocalWorkers(args.workers)
    records = run_batch(jobs, options, workers, args.out, quiet=args.quiet)
    print(format_table(records))
    print(f"results in {args.out.resolve() / 'batch.json'} and batch.csv")
    if any(r["status"] != "done" for r in records):
        raise SystemExit(1)
