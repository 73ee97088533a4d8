"""Command line: `python -m pipeline COMMAND ...` (also installed as `voxfield`).

The commands are a table of module names (pipeline/commands/), as git's and nerfstudio's are: `--help` lists them
from the table alone, and a command imports its module, and so what it needs (torch, COLMAP, viser, Ray), only when
it runs. `voxfield --help`, `status` and `settings` therefore load neither torch nor COLMAP.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

from pipeline.disk import describe_os_error
from pipeline.stage import STAGE_ORDER
from plenoxels.core.errors import UserError


@dataclass(frozen=True)
class Command:
    module: str
    """The module that defines the command's `add_arguments(parser, command)` and `main(args)`."""
    help: str


COMMANDS: dict[str, Command] = {
    "run": Command("pipeline.commands.run", "run every stage (or up to --until) on a folder of photos"),
    "batch": Command("pipeline.commands.batch",
                     "run the pipeline on many scenes, N at a time here or on a Ray cluster"),
    "demo": Command("pipeline.commands.demo", "make the built-in synthetic scene and run every stage on it"),
    "status": Command("pipeline.commands.status", "which stages are done, stale or missing, and why"),
    **{name: Command("pipeline.commands.run", f"run the {name} stage (and anything it needs that is not done)")
       for name in STAGE_ORDER},
    "render": Command("pipeline.commands.render",
                      "render the fitted scene from chosen cameras (and score them where they have photos)"),
    "view": Command("pipeline.commands.view",
                    "serve a web viewer of a scene's output: cameras, points, mesh, live render"),
    "settings": Command("pipeline.commands.settings",
                        "every setting of every stage (or one): type, default, the preset's value, help"),
    "synth": Command("pipeline.commands.synth", "write a synthetic scene: photos, true poses and true mesh"),
}


def _program_name() -> str:
    """How the user started us: the `voxfield` console script or `python -m pipeline`."""
    return "voxfield" if Path(sys.argv[0]).name == "voxfield" else "python -m pipeline"


def build_parser() -> argparse.ArgumentParser:
    """The commands and what each does; each command's own arguments are its module's."""
    parser = argparse.ArgumentParser(prog=_program_name(),
                                     description="Photos to a radiance field, renders and meshes.",
                                     epilog=f"`{_program_name()} COMMAND --help` shows a command's options.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, command in COMMANDS.items():
        sub.add_parser(name, help=command.help, add_help=False)
    return parser


def command_parser(name: str) -> tuple[argparse.ArgumentParser, ModuleType]:
    """The parser of one command's arguments, and its module (imported here)."""
    command = COMMANDS[name]
    module = importlib.import_module(command.module)
    parser = argparse.ArgumentParser(prog=f"{_program_name()} {name}", description=command.help)
    module.add_arguments(parser, name)
    return parser, module


def main(argv: list[str] | None = None) -> int:
    chosen, rest = build_parser().parse_known_args(sys.argv[1:] if argv is None else argv)
    parser, module = command_parser(chosen.command)
    args = parser.parse_args(rest, argparse.Namespace(command=chosen.command))
    try:
        module.main(args)
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"error: {describe_os_error(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: completed stages are kept; run the same command again to resume", file=sys.stderr)
        return 130
    return 0
