"""`settings`: every setting of every stage (or one), with its type, default, a preset's value and its help."""
from __future__ import annotations

import argparse

from pipeline.config import describe, format_settings, preset_names
from pipeline.stage import STAGE_ORDER, StageGraph


def add_arguments(parser: argparse.ArgumentParser, command: str) -> None:
    parser.add_argument("stage", nargs="?", choices=STAGE_ORDER, help="only this stage's settings")
    parser.add_argument("--preset", default="default",
                        help=f"show this preset's values: {', '.join(preset_names())} (default: default)")


def main(args: argparse.Namespace) -> None:
    graph = StageGraph()
    print("\n\n".join(format_settings(name, describe(graph.declaration(name).Settings, name, args.preset), args.preset)
                      for name in ([args.stage] if args.stage else STAGE_ORDER)))
