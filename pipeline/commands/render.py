"""`render`: the fitted scene rendered from chosen cameras (a camera file or a named path), scored where the cameras
come with photos."""
from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.commands.common import add_output_arguments, output_folder
from stages.scoring.camera_renders import render_scene, summary_line
from pipeline.report import Reporter


def add_arguments(parser: argparse.ArgumentParser, command: str) -> None:
    add_output_arguments(parser)
    parser.add_argument("--cameras", default="auto", metavar="FILE|auto|orbit|spiral",
                        help="transforms.json or nerfstudio camera_path.json, or a named path (default: auto)")
    parser.add_argument("--size", help="longest side (640) or WIDTHxHEIGHT (default: the cameras' own; paths 480)")
    parser.add_argument("--frames", type=int, help="views on a named path (default: 120)")
    parser.add_argument("--frame", choices=("input", "normalized"), default="input",
                        help="the frame a camera file is in: the poses stage's (input) or normalize's")
    parser.add_argument("--to", type=Path, help="where to write (default: OUT/render/<cameras' name>)")
    parser.add_argument("--quiet", action="store_true")


def main(args: argparse.Namespace) -> None:
    metrics, dest = render_scene(output_folder(args), args.cameras, args.to, args.size, args.frames, args.frame,
                                 Reporter(quiet=args.quiet))
    print(f"[render] {summary_line(metrics, dest)}")
