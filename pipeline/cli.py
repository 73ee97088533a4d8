"""Command line: `python -m pipeline run|batch|status|settings|demo|synth|view|<stage> ...` (also installed as `voxfield`)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline import synthetic
from pipeline.batch import BatchOptions, LocalWorkers, format_table, plan_jobs, run_batch
from pipeline.batch_ray import RayCluster
from pipeline.config import describe, format_settings, preset_names
from pipeline.render_cameras import render_scene, summary_line
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from pipeline.scenes import read_scene_list, scene_name
from pipeline.stage import STAGE_ORDER, StageGraph
from pipeline.viewer import ViewOptions, Viewer
from plenoxels.errors import UserError

DEMO_SCENE = "demo"


def _common(p: argparse.ArgumentParser, needs_scene: bool = True, preset: str = "default") -> None:
    if needs_scene:
        p.add_argument("scene", type=Path, help="folder of photos, or a video file")
    p.add_argument("--out", type=Path, help="output folder (default: out/<scene-name>)")
    p.add_argument("--preset", default=preset, help=f"settings preset: {', '.join(preset_names())} (default: {preset})")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one setting, e.g. --set fit.sh_degree=1 (repeatable)")
    p.add_argument("--quiet", action="store_true", help="no progress output; summaries and warnings only")


def _program_name() -> str:
    """How the user started us: the `voxfield` console script or `python -m pipeline`."""
    return "voxfield" if Path(sys.argv[0]).name == "voxfield" else "python -m pipeline"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=_program_name(), description="Photos to a radiance field, renders and meshes.")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run every stage (or up to --until) on a folder of photos")
    _common(run)
    run.add_argument("--until", choices=STAGE_ORDER, help="stop after this stage")
    run.add_argument("--force", action="append", default=[], choices=STAGE_ORDER, help="re-run this stage even if cached")
    batch = sub.add_parser("batch", help="run the pipeline on many scenes, N at a time here or on a Ray cluster")
    batch.add_argument("scenes", type=Path, nargs="+", metavar="SCENE",
                       help="folders of photos or videos, or .txt files listing them one a line")
    _common(batch, needs_scene=False)
    batch.set_defaults(out=Path("out"))
    batch.add_argument("--until", choices=STAGE_ORDER, help="stop each scene after this stage")
    batch.add_argument("--workers", type=int, default=1, help="scenes at a time on this machine (default: 1)")
    batch.add_argument("--ray", nargs="?", const="", metavar="ADDRESS",
                       help="run on a Ray cluster at ADDRESS (auto, HOST:6379, ray://HOST:10001; put it after the scenes); "
                            "alone: the cluster `ray start` made here, else a new local one")
    batch.add_argument("--cpus-per-scene", type=float, default=1.0, help="CPUs a scene's Ray task asks for (default: 1)")
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
    render = sub.add_parser("render", help="render the fitted scene from chosen cameras (and score them where they have photos)")
    render.add_argument("out", type=Path, nargs="?", help="the scene's output folder (default: out/<scene-name>, or out/demo)")
    render.add_argument("--scene", type=Path, help="the scene's photos, to find its output folder by name")
    render.add_argument("--cameras", default="auto", metavar="FILE|auto|orbit|spiral",
                        help="transforms.json or nerfstudio camera_path.json, or a named path (default: auto)")
    render.add_argument("--size", help="longest side (640) or WIDTHxHEIGHT (default: the cameras' own; paths 480)")
    render.add_argument("--frames", type=int, help="views on a named path (default: 120)")
    render.add_argument("--frame", choices=("input", "normalized"), default="input",
                        help="the frame a camera file is in: the poses stage's (input) or normalize's")
    render.add_argument("--to", type=Path, help="where to write (default: OUT/render/<cameras' name>)")
    render.add_argument("--quiet", action="store_true")
    view = sub.add_parser("view", help="serve a web viewer of a scene's output: cameras, points, mesh, live render")
    view.add_argument("out", type=Path, nargs="?", help="the scene's output folder (default: out/<scene-name>, or out/demo)")
    view.add_argument("--scene", type=Path, help="the scene's photos, to find its output folder by name")
    view.add_argument("--host", default=ViewOptions.host, help="address to listen on (default: 127.0.0.1, this machine only)")
    view.add_argument("--port", type=int, default=ViewOptions.port, help="port (default: 8080; 0: any free one)")
    view.add_argument("--resolution", type=int, default=ViewOptions.resolution,
                      help="longest side in pixels of the refined render (default: 320)")
    settings = sub.add_parser("settings", help="every setting of every stage (or one): type, default, the preset's value, help")
    settings.add_argument("stage", nargs="?", choices=STAGE_ORDER, help="only this stage's settings")
    settings.add_argument("--preset", default="default", help=f"show this preset's values: {', '.join(preset_names())} (default: default)")
    synth = sub.add_parser("synth", help="write a synthetic scene: photos, true poses and true mesh")
    synth.add_argument("kind", choices=synthetic.KINDS)
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
    source = out_root / "demo-photos"
    if not (source / "images").is_dir():
        report.info(f"demo: generating the synthetic object scene in {source}")
        synthetic.write_scene("object", source)
    return source / "images"


def run_scene_batch(args) -> None:
    """`batch`: every scene to OUT/<scene-name>, then the results table (also OUT/batch.json and OUT/batch.csv)."""
    jobs = plan_jobs(read_scene_list(args.scenes), args.out)
    options = BatchOptions(preset=args.preset, overrides=args.overrides, until=args.until)
    options.check()
    if args.ray is not None:
        workers = RayCluster(args.ray or None, cpus_per_scene=args.cpus_per_scene)
    else:
        workers = LocalWorkers(args.workers)
    records = run_batch(jobs, options, workers, args.out, quiet=args.quiet)
    print(format_table(records))
    print(f"results in {args.out.resolve() / 'batch.json'} and batch.csv")
    if any(r["status"] != "done" for r in records):
        raise SystemExit(1)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.command == "synth":
            path = synthetic.write_scene(args.kind, args.outdir, n_views=args.views, width=args.width,
                                         height=args.height, seed=args.seed)
            print(f"[synth] {args.kind} scene with {args.views} views at {args.width}x{args.height} written to {path}")
        elif args.command == "render":
            out = args.out or (Path("out") / scene_name(args.scene) if args.scene else Path("out") / DEMO_SCENE)
            metrics, dest = render_scene(out, args.cameras, args.to, args.size, args.frames, args.frame,
                                         Reporter(quiet=args.quiet))
            print(f"[render] {summary_line(metrics, dest)}")
        elif args.command == "view":
            out = args.out or (Path("out") / scene_name(args.scene) if args.scene else Path("out") / DEMO_SCENE)
            Viewer(out, ViewOptions(host=args.host, port=args.port, resolution=args.resolution)).serve_forever()
        elif args.command == "settings":
            graph = StageGraph()
            print("\n\n".join(format_settings(name, describe(graph.load(name).Settings, name, args.preset), args.preset)
                              for name in ([args.stage] if args.stage else STAGE_ORDER)))
        elif args.command == "status":
            pipe = _pipeline(args, args.scene)
            for name in STAGE_ORDER:
                state, why = pipe.status(name)
                print(f"{name:<10} {state:<8} {why}")
        elif args.command == "batch":
            run_scene_batch(args)
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
