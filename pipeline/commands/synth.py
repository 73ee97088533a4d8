"""`synth`: a synthetic scene written to a folder: photos, true poses and the true mesh."""
from __future__ import annotations

import argparse
from pathlib import Path

from stages.capture import synthetic, synthetic_scenes


def add_arguments(parser: argparse.ArgumentParser, command: str) -> None:
    parser.add_argument("kind", choices=synthetic_scenes.KINDS)
    parser.add_argument("outdir", type=Path)
    parser.add_argument("--views", type=int, default=40)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--seed", type=int, default=0)


def main(args: argparse.Namespace) -> None:
    path = synthetic.write_scene(args.kind, args.outdir, n_views=args.views, width=args.width, height=args.height,
                                 seed=args.seed)
    print(f"[synth] {args.kind} scene with {args.views} views at {args.width}x{args.height} written to {path}")
