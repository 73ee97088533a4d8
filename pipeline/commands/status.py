"""`status`: which stages of a scene are done, stale or missing, and why (from the cache keys; nothing runs)."""
from __future__ import annotations

import argparse

from pipeline.commands.common import add_scene_arguments, open_pipeline
from pipeline.stage import STAGE_ORDER


def add_arguments(parser: argparse.ArgumentParser, command: str) -> None:
    add_scene_arguments(parser)


def main(args: argparse.Namespace) -> None:
    pipe = open_pipeline(args, args.scene)
    for name in STAGE_ORDER:
        state, why = pipe.status(name)
        print(f"{name:<10} {state:<8} {why}")
