"""`demo`: the built-in synthetic object scene, made once, and every stage (or up to --until) on it."""
from __future__ import annotations

import argparse
from pathlib import Path

from stages.capture import synthetic
from pipeline.commands.common import DEMO_SCENE, add_scene_arguments, open_pipeline
from pipeline.commands.run import run_until
from pipeline.report import Reporter
from pipeline.stage import STAGE_ORDER


def add_arguments(parser: argparse.ArgumentParser, command: str) -> None:
    add_scene_arguments(parser, needs_scene=False, preset="fast")  # the demo is a quick tour, not a benchmark
    parser.add_argument("--until", choices=STAGE_ORDER)
    parser.add_argument("--force", action="append", default=[], choices=STAGE_ORDER)


def demo_scene(out_root: Path, report: Reporter) -> Path:
    """The demo's photos: a synthetic object scene, generated once (it is deterministic)."""
    source = out_root / "demo-photos"
    if not (source / "images").is_dir():
        report.info(f"demo: generating the synthetic object scene in {source}")
        synthetic.write_scene("object", source)
    return source / "images"


def main(args: argparse.Namespace) -> None:
    args.out = args.out or Path("out") / DEMO_SCENE
    run_until(open_pipeline(args, demo_scene(args.out, Reporter(args.quiet))), args.until, args.force)
