"""`run` and each stage by name: the pipeline on a scene, every stage up to one, or one stage and what it needs."""
from __future__ import annotations

import argparse

from pipeline.commands.common import add_scene_arguments, open_pipeline
from pipeline.runner import Pipeline
from pipeline.stage import STAGE_ORDER


def add_arguments(parser: argparse.ArgumentParser, command: str) -> None:
    add_scene_arguments(parser)
    if command == "run":
        parser.add_argument("--until", choices=STAGE_ORDER, help="stop after this stage")
        parser.add_argument("--force", action="append", default=[], choices=STAGE_ORDER,
                            help="re-run this stage even if cached")
    else:
        parser.add_argument("--force", action="store_true", help=f"re-run {command} even if cached")


def run_until(pipe: Pipeline, until: str | None, force: list[str]) -> None:
    """Every stage up to `until` (all of them when None), re-running those in `force` even if cached."""
    last = until or STAGE_ORDER[-1]
    pipe.run(list(STAGE_ORDER[: STAGE_ORDER.index(last) + 1]), force=set(force))
    print(f"outputs in {pipe.out}")


def main(args: argparse.Namespace) -> None:
    pipe = open_pipeline(args, args.scene)
    if args.command == "run":
        run_until(pipe, args.until, args.force)
    else:
        pipe.run([args.command], force={args.command} if args.force else set())
