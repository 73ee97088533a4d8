"""`run`, `demo` and each stage by name: the pipeline on a scene, every stage up to one, or one stage and what it
needs."""
from __future__ import annotations

import argparse
from pathlib import Path

from pipeline import synthetic
from pipeline.commands.common import DEMO_SCENE, add_scene_arguments, open_pipeline
from pipeline.report import Reporter
from pipeline.stage import STAGE_ORDER


def add_arguments(parser: argparse.ArgumentParser, command: str) -> None:
    if command == "run":
        add_scene_arguments(parser)
        parser.add_argument("--until", choices=STAGE_ORDER, help="stop after this stage")
        parser.add_argument("--force", action="append", default=[], choices=STAGE_ORDER,
                            help="re-run this stage even if cached")
    elif command == "demo":
        add_scene_arguments(parser, needs_scene=False, preset="fast")  # the demo is a quick tour, not a benchmark
        parser.add_argument("--until", choices=STAGE_ORDER)
        parser.add_argument("--force", action="append", default=[], choices=STAGE_ORDER)
    else:
        add_scene_arguments(parser)
        parser.add_argument("--force", action="store_true", help=f"re-run {command} even if cached")


def demo_scene(out_root: Path, report: Reporter) -> Path:
    """The built-in demo: a synthetic object scene, generated once (it is deterministic)."""
    source = out_root / "demo-photos"
    if not (source / "images").is_dir():
        report.info(f"demo: generating the synthetic object scene in {source}")
        synthetic.write_scene("object", source)
    return source / "images"


def main(args: argparse.Namespace) -> None:
    if args.command not in ("run", "demo"):
        pipe = open_pipeline(args, args.scene)
        pipe.run([args.command], force={args.command} if args.force else set())
        return
    if args.command == "demo":
        args.out = args.out or Path("out") / DEMO_SCENE
        scene = demo_scene(args.out, Reporter(args.quiet))
    else:
        scene = args.scene
    pipe = open_pipeline(args, scene)
    last = args.until or STAGE_ORDER[-1]
    pipe.run(list(STAGE_ORDER[: STAGE_ORDER.index(last) + 1]), force=set(args.force))
    print(f"outputs in {pipe.out}")
