"""`view`: a web viewer of a scene's output (cameras, points, mesh, the fit rendered live)."""
from __future__ import annotations

import argparse

from pipeline.commands.common import add_output_arguments, output_folder
from pipeline.viewer import ViewOptions, Viewer


def add_arguments(parser: argparse.ArgumentParser, command: str) -> None:
    add_output_arguments(parser)
    parser.add_argument("--host", default=ViewOptions.host,
                        help="address to listen on (default: 127.0.0.1, this machine only)")
    parser.add_argument("--port", type=int, default=ViewOptions.port, help="port (default: 8080; 0: any free one)")
    parser.add_argument("--resolution", type=int, default=ViewOptions.resolution,
                        help="longest side in pixels of the refined render (default: 320)")


def main(args: argparse.Namespace) -> None:
    Viewer(output_folder(args), ViewOptions(host=args.host, port=args.port, resolution=args.resolution)).serve_forever()
