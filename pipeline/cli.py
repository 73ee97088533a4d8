"""Command line: `python -m pipeline run|status|demo|synth|<stage> ...`."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.config import preset_names
from plenoxels.errors import UserError
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from pipeline.stage import STAGE_ORDER

GENERIC_FOLDER_NAMES = {"images", "photos", "frames", "input", "rgb"}
DEMO_SCENE = "demo"


def scene_name(scene: Path) -> str:
    """fox/images -> 'fox', fern/images_4 -> 'fern', my_trip.mp4 -> 'my_trip'."""
    scene = scene.resolve()
    name = scene.stem if scene.is_file() else scene.name
    if name.lower() in GENERIC_FOLDER_NAMES or name.lower().startswith("images_"):
        name = scene.parent.name
    return name or "scene"


def _common(p: argparse.ArgumentParser, needs_scene: bool = True, preset: str = "default") -> None:
    if needs_scene:
        p.add_argument("scene", type=Path, help="folder of photos, or a video file")
    p.add_argument("--out", type=Path, help="output folder (default: out/<scene-name>)")
    p.add_argument("--preset", default=preset, help=f"settings preset: {', '.join(preset_names())} (default: {preset})")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one setting, e.g. --set fit.sh_degree=1 (repeatable)")
    p.add_argument("--quiet", action="store_true", help="no progress output; summaries and warnings only")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m pipeline", description="Photos to a radiance field, renders and meshes.")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run every stage (or up to --until) on a folder of photos")
    _common(run)
    run.add_argument("--until", choices=STAGE_ORDER, help="stop after this stage")
    run.add_argument("--force", action="append", default=[], choices=STAGE_ORDER, help="re-run this stage even if cached")
    demo = sub.add_parser("demo", help="make the built-in synthetic scene and run every stage on it")
    _common(demo, needs_scene=False, preset="fast")  # the demo is a quick tour, not a benchmark
    demo.add_argument("--until", choices=STAGE_ORDER)
    demo.add_argument("--force", action="append", default=[], choices=STAGE_ORDER)
    status = sub.add_parser("status", help="which stages are done, stale or missing, and why")
    _common(status)
    for name in STAGE_ORDER:
        one = sub.add_parser(name, help=f"run the {name} stage (and anything it needs that is not done)")
        _common(one)
        one.add_argument("--force", action="store_true", help=f"re-run {name} even if cached")
    synth = sub.add_parser("synth", help="write a synthetic scene: photos, true poses and true mesh")
    synth.add_argument("kind", choices=("object", "forward", "unbounded"))
    synth.add_argument("outdir", type=Path)
    synth.add_argument("--views", type=int, default=40)
    synth.add_argument("--width", type=int, default=320)
    synth.add_argument("--height", type=int, default=240)
    synth.add_argument("--seed", type=int, default=0)
    return parser


def _pipeline(args, scene: Path) -> Pipeline:
    if not scene.exists():
        raise UserError(f"{scene} does not exist; give a folder of photos or a video file")
    out = args.out or Path("out") / scene_name(scene)
    return Pipeline(scene, out, preset=args.preset, overrides=args.overrides, reporter=Reporter(quiet=args.quiet))


def _demo_scene(out_root: Path, report: Reporter) -> Path:
    """The built-in demo: a synthetic object scene, generated once (it is deterministic)."""
    from pipeline import synthetic

    source = out_root / "demo-photos"
    if not (source / "images").is_dir():
        report.info(f"demo: generating the synthetic object scene in {source}")
        synthetic.write_scene("object", source)
    return source / "images"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.command == "synth":
            from pipeline import synthetic

            path = synthetic.write_scene(args.kind, args.outdir, n_views=args.views, width=args.width,
                                         height=args.height, seed=args.seed)
            print(f"[synth] {args.kind} scene with {args.views} views at {args.width}x{args.height} written to {path}")
        elif args.command == "status":
            pipe = _pipeline(args, args.scene)
            for name in STAGE_ORDER:
                state, why = pipe.status(name)
                print(f"{name:<10} {state:<8} {why}")
        elif args.command in ("run", "demo"):
            if args.command == "demo":
                args.out = args.out or Path("out") / DEMO_SCENE
                scene = _demo_scene(args.out, Reporter(args.quiet))
            else:
                scene = args.scene
            pipe = _pipeline(args, scene)
            last = args.until or STAGE_ORDER[-1]
            pipe.run([s for s in STAGE_ORDER[: STAGE_ORDER.index(last) + 1]], force=set(args.force))
            print(f"outputs in {pipe.out}")
        else:
            pipe = _pipeline(args, args.scene)
            pipe.run([args.command], force={args.command} if args.force else set())
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: completed stages are kept; run the same command again to resume", file=sys.stderr)
        return 130
    return 0
