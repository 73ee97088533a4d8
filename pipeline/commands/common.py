"""What several commands share: a scene's arguments (--out, --preset, --set, --quiet), its pipeline, and the output
folder a command on a finished scene reads."""
from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.config import preset_names
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from pipeline.scenes import scene_name
from plenoxels.core.errors import UserError

DEMO_SCENE = "demo"


def add_scene_arguments(parser: argparse.ArgumentParser, needs_scene: bool = True, preset: str = "default") -> None:
    if needs_scene:
        parser.add_argument("scene", type=Path, help="folder of photos, or a video file")
    parser.add_argument("--out", type=Path, help="output folder (default: out/<scene-name>)")
    parser.add_argument("--preset", default=preset,
                        help=f"settings preset: {', '.join(preset_names())} (default: {preset})")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="override one setting, e.g. --set fit.sh_degree=1 (repeatable)")
    parser.add_argument("--quiet", action="store_true", help="no progress output; summaries and warnings only")


def open_pipeline(args: argparse.Namespace, scene: Path) -> Pipeline:
    if not scene.exists():
        raise UserError(f"{scene} does not exist; give a folder of photos or a video file")
    out = args.out or Path("out") / scene_name(scene)
    return Pipeline(scene, out, preset=args.preset, overrides=args.overrides, reporter=Reporter(quiet=args.quiet))


def add_output_arguments(parser: argparse.ArgumentParser) -> None:
    """The finished scene a command reads: its output folder, or its photos to find the folder by name."""
    parser.add_argument("out", type=Path, nargs="?",
                        help="the scene's output folder (default: out/<scene-name>, or out/demo)")
    parser.add_argument("--scene", type=Path, help="the scene's photos, to find its output folder by name")


def output_folder(args: argparse.Namespace) -> Path:
    return args.out or (Path("out") / scene_name(args.scene) if args.scene else Path("out") / DEMO_SCENE)
