"""The papers' protocol, run as a user would: the pipeline pointed at a published data set folder, every held-out
view scored at full size with PSNR, SSIM and LPIPS (AlexNet, v0.1) by the evaluate stage, beside the Plenoxels
paper's figures and a reproduction's.

- A NeRF-synthetic scene (train/, test/ beside transforms_<split>.json): fitted on train, scored on every view of
  test at 800x800 (`--split val` where a folder has no test split; the run records which split it scored).
- An LLFF scene (images_4/ beside poses_bounds.npy): its images_4 photos (1008x756 for fern) at full size, poses from
  poses_bounds.npy, every 8th photo held out (0, 8, 16, ...).

Each run is `pipeline run` up to evaluate in a process of its own (its peak memory is its own), with the preset and
an optional time budget, in bench/out/protocol/<scene>-<run>/. A new run starts from the stages before the fit
(ingest, poses, normalize) of an earlier run of its scene, this invocation's first or, where that has none yet, a
previous invocation's (a curve run one budget at a time): the pipeline's cache re-runs any whose key differs.

Ablations (the paper's Tables 3 and 4, on the scene named): `--ablation resolution` fits the preset with its levels
capped at 32, 64, 128, 256 and 512 vertices (the capped levels' steps go to the last level kept); `--ablation views`
fits a quarter of the training views (every 4th: lego's 25) with the TV weights as set (low) and with the few-views
TV the fit sets itself (high; plenoxels.core.regularizers.tv_scale_for_views).

    .venv/bin/python -m bench.protocol --scene lego=/data/nerf_synthetic/lego --presets paper
    .venv/bin/python -m bench.protocol --scene lego=../shared/data/lego --split val --presets paper --budgets 30m
    .venv/bin/python -m bench.protocol --scene fern=../shared/data/fern --presets paper,default
    .venv/bin/python -m bench.protocol --scene lego=PATH --ablation resolution --presets paper
    .venv/bin/python -m bench.protocol --table
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from plenoxels.core.errors import UserError  # noqa: E402

RESULTS = REPO / "bench" / "results" / "protocol.json"
CACHE = REPO / "bench" / "out" / "protocol"
# Run without --scene (as `make bench` does): the project's shared scenes that follow a protocol, where present.
DEFAULT_SCENES = {"lego": REPO.parent / "shared" / "data" / "lego", "fern": REPO.parent / "shared" / "data" / "fern"}
ABLATION_RESOLUTIONS = (32, 64, 128, 256, 512)
BEFORE_FIT = ("ingest", "poses", "normalize")  # the stages every run of a scene shares, unless its settings differ
FEW_VIEWS_EVERY = 4

# What others report for these scenes at this protocol. The paper: Fridovich-Keil, Yu et al., CVPR 2022 (Table 2, 4 and
# 3 averages over the 8 NeRF-synthetic scenes; lego's own figure as its text gives it). The reproduction: svox2 run by
# kakaobrain/nerf-factory (docs/performance/plenoxel.md), per scene.
PAPER = {
    "synthetic mean": {"psnr": 31.71, "ssim": 0.958, "lpips": 0.049},
    "llff mean": {"psnr": 26.29, "ssim": 0.839, "lpips": 0.210},
    "lego": {"psnr": 34.10},
    "resolution": {512: (31.71, 0.958, 0.050), 256: (30.57, 0.950, 0.065), 128: (28.46, 0.926, 0.100),
                   64: (26.11, 0.892, 0.139), 32: (23.49, 0.859, 0.174)},
    "views": {"100 views, low TV": (31.71, 0.958, 0.050), "25 views, low TV": (26.88, 0.911, 0.099),
              "25 views, high TV": (28.25, 0.932, 0.078)},
}
REPRODUCTION = {
    "chair": (34.11, 0.9769, 0.0296), "drums": (25.42, 0.9323, 0.0657), "ficus": (31.94, 0.9759, 0.0258),
    "hotdog": (36.69, 0.9805, 0.0367), "lego": (34.34, 0.9753, 0.0272), "materials": (29.26, 0.9495, 0.0553),
    "mic": (33.36, 0.9851, 0.0148), "ship": (30.10, 0.8901, 0.1313),
    "fern": (24.91, 0.8076, 0.2438), "flower": (28.17, 0.8676, 0.1733), "fortress": (31.36, 0.8902, 0.1661),
    "horns": (27.77, 0.8618, 0.2218), "leaves": (21.19, 0.7429, 0.2165), "orchids": (20.01, 0.6527, 0.2892),
    "room": (31.33, 0.9414, 0.1884), "trex": (26.54, 0.8874, 0.2523),
}


def scene_kind(folder: Path) -> str:
    """"nerf_synthetic" or "llff", from the folder's layout; anything else is a one-line error."""
    from stages.capture.photos import split_layout

    if split_layout(folder) == "blender":
        return "nerf_synthetic"
    if (folder / "poses_bounds.npy").is_file():
        return "llff"
    raise UserError(f"{folder} is neither a NeRF-synthetic folder (train/ beside transforms_train.json) nor an LLFF "
                    f"one (images_N/ beside poses_bounds.npy)")


def protocol_settings(kind: str, split: str) -> list[str]:
    """The settings that make a pipeline run follow the protocol of a `kind` of scene: photos at full size, every
    held-out view scored at full size, no video (its time is not the protocol's)."""
    common = ["ingest.max_side=0", "evaluate.scale=1", "evaluate.max_views=0", "evaluate.video_frames=0"]
    if kind == "nerf_synthetic":
        return common + [f"ingest.holdout_split={split}"]
    return common + ["normalize.holdout_every=8"]


def capped_levels(resolutions: list[int], steps: list[int], cap: int) -> tuple[list[int], list[int]]:
    """The levels of a schedule at most `cap` vertices across; the steps of the levels past it go to the last kept
    (a level at the cap itself where none is at most the cap)."""
    kept = [(r, s) for r, s in zip(resolutions, steps) if r <= cap] or [(cap, 0)]
    dropped = sum(steps) - sum(s for _, s in kept)
    levels, counts = [r for r, _ in kept], [s for _, s in kept]
    counts[-1] += dropped
    return levels, counts


def one_run(spec: dict) -> dict:
    """One pipeline run up to evaluate (or, for a few-views run, the fit and the evaluation of a reduced scene),
    and what it measured."""
    from stages.common.json_files import read_json
    from pipeline.report import Reporter
    from pipeline.runner import Pipeline

    out = Path(spec["out"])
    started = time.time()
    Pipeline(Path(spec["folder"]), out, preset=spec["preset"], overrides=spec["settings"],
             reporter=Reporter(quiet=not spec.get("verbose"))).run(["ingest", "poses", "normalize", "fit", "evaluate"])
    wall = time.time() - started
    fit = read_json(out / "fit" / "fit.json")
    metrics = read_json(out / "evaluate" / "metrics.json")
    held_out = [f for f in read_json(out / "normalize" / "scene.json")["frames"] if f["split"] == "test"]
    eval_size = [round(held_out[0]["w"] * metrics["scale"]), round(held_out[0]["h"] * metrics["scale"])]
    stage_seconds = {stage: read_json(out / stage / "manifest.json").get("seconds")
                     for stage in ("ingest", "poses", "normalize", "fit", "evaluate")
                     if (out / stage / "manifest.json").is_file()}
    return {"mean": metrics["mean"], "held_out_views": metrics["count"], "eval_size": eval_size,
            "fit_seconds": fit["seconds"], "stage_seconds": stage_seconds,
            "wall_seconds": round(wall, 1), "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
            "train_images": fit["train_images"], "train_pixels": fit["train_pixels"],
            "resolution": fit["model"]["resolution"], "occupied": fit["model"]["occupied"],
            "levels": fit["resolutions"], "steps": fit["steps_per_level"], "budget": fit.get("budget", {}).get("plan"),
            "regularisation": fit.get("regularisation")}


def runs_to_do(args, kind: str, name: str, folder: Path) -> list[dict]:
    """(label, preset, settings) of every run the arguments ask for on one scene."""
    from pipeline import config

    split = "every 8th"
    if kind == "nerf_synthetic":
        split = args.split
        if split == "test" and not (folder / "transforms_test.json").is_file():
            split = "val"  # a copy without the release's test split is scored on val, and its results say so
            print(f"[protocol] {name}: no test split in {folder}; scoring its val split", flush=True)
    base = protocol_settings(kind, split) + [f"fit.{s.removeprefix('fit.')}" for s in args.set]
    runs = []
    for preset in args.presets:
        if args.ablation == "resolution":
            fit = config.load_preset(preset).get("fit", {})
            resolutions, steps = fit.get("resolutions"), fit.get("steps")
            if not resolutions:
                raise UserError(f"preset {preset} sets no fit.resolutions to cap")
            for cap in ABLATION_RESOLUTIONS:
                levels, counts = capped_levels(resolutions, steps, cap)
                runs.append({"label": f"{preset}, up to {cap}^3", "preset": preset, "ablation": "resolution",
                             "cap": cap, "settings": base + [f"fit.resolutions={levels}", f"fit.steps={counts}"]})
        elif args.ablation == "views":
            few = [f"normalize.train_every={FEW_VIEWS_EVERY}"]
            runs.append({"label": f"{preset}, all views", "preset": preset, "ablation": "views", "settings": base})
            runs.append({"label": f"{preset}, 1/{FEW_VIEWS_EVERY} views, low TV (as set)", "preset": preset,
                         "ablation": "views", "settings": base + few + ["fit.tv_views=0"]})
            runs.append({"label": f"{preset}, 1/{FEW_VIEWS_EVERY} views, high TV (few-views TV)", "preset": preset,
                         "ablation": "views", "settings": base + few})
        else:
            for budget in args.budgets or [None]:
                label = preset + (f", budget {budget}" if budget else "") + (f", {' '.join(args.set)}" if args.set else "")
                runs.append({"label": label, "preset": preset, "budget": budget,
                             "settings": base + ([f"fit.time_budget={budget}"] if budget else [])})
    for run in runs:
        run.update(scene=name, kind=kind, split=split)
    return runs


def earlier_run(scene: str, out: Path, first: Path) -> Path | None:
    """The folder of an earlier run of `scene` whose stages before the fit a run in `out` can start from: `first`
    (this invocation's first run) where it has them, else the latest finished one of the scene's other runs."""
    def finished(folder: Path) -> bool:
        return folder != out and all((folder / stage / "manifest.json").is_file() for stage in BEFORE_FIT)

    if finished(first):
        return first
    others = [folder for folder in CACHE.glob(f"{glob.escape(scene)}-*") if finished(folder)]
    return max(others, key=lambda folder: (folder / "normalize" / "manifest.json").stat().st_mtime, default=None)


def slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", text.lower()).strip("_")


def commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def table(results: dict) -> str:
    """Markdown, one table per scene: each run, then the paper's and the reproduction's figures."""
    from bench.fit import cpu_name

    lines = []
    for name in dict.fromkeys(r["scene"] for r in results.get("runs", [])):
        runs = [r for r in results["runs"] if r["scene"] == name]
        first = runs[0]
        size = "x".join(map(str, first.get("eval_size") or [])) or "full size"
        lines += [f"**{name}** ({first['held_out_views']} held-out views, {first['split']}, at {size})", "",
                  "| run | PSNR | SSIM | LPIPS | fit | whole run | peak memory | final grid | machine, date, commit |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in runs:
            m = r["mean"]
            grid = f"{'x'.join(str(n) for n in r['resolution'])}, {r['occupied'] / 1e6:.2f} M voxels"
            lines.append(f"| {r['label']} | {m['psnr']:.2f} | {m['ssim']:.3f} | {m.get('lpips', float('nan')):.3f} | "
                         f"{r['fit_seconds']:.0f} s | {r['wall_seconds']:.0f} s | {r['peak_rss_mb'] / 1024:.1f} GiB | "
                         f"{grid} | {cpu_name(r['machine'])}, {r['machine']['cores']} cores, {r['finished'][:10]}, "
                         f"{r['commit']} |")
        if name in REPRODUCTION:
            psnr, ssim, lpips = REPRODUCTION[name]
            lines.append(f"| svox2 reproduced (nerf-factory, GPU) | {psnr:.2f} | {ssim:.3f} | {lpips:.3f} | | | | | |")
        if name in PAPER:
            lines.append(f"| Plenoxels paper (GPU, 512^3, 10.8 min) | {PAPER[name]['psnr']:.2f} | | | | | | | |")
        kind_mean = "synthetic mean" if first["kind"] == "nerf_synthetic" else "llff mean"
        mean = PAPER[kind_mean]
        lines += [f"| Plenoxels paper, {kind_mean} | {mean['psnr']:.2f} | {mean['ssim']:.3f} | {mean['lpips']:.3f} "
                  f"| | | | | |", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--scene", action="append", default=[], metavar="NAME=FOLDER",
                        help="a published data set folder to run, with the name its results go under")
    parser.add_argument("--split", default="test", choices=("test", "val"),
                        help="NeRF-synthetic: the split scored (the papers': test, all 200 views)")
    parser.add_argument("--presets", default="paper", type=lambda s: [p for p in s.split(",") if p])
    parser.add_argument("--budgets", nargs="*", default=[], help="time budgets to run each preset under (30m, ...)")
    parser.add_argument("--ablation", choices=("resolution", "views"), default=None)
    parser.add_argument("--set", action="append", default=[], help="fit.key=value for every run")
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--table", action="store_true", help="print --results as Markdown tables and exit")
    parser.add_argument("--verbose", action="store_true", help="show each run's stages")
    args = parser.parse_args(argv)
    from bench.common import run_part

    return run_part(args, one_run, run_all)


def run_all(args) -> int:
    from bench.common import run_child
    from bench.fit import machine
    from pipeline import config
    from stages.scoring.lpips import read_weights

    if args.table:
        if not args.results.is_file():
            raise UserError(f"no results at {args.results}; run the benchmark first")
        print(table(json.loads(args.results.read_text())))
        return 0
    scenes = args.scene or [f"{name}={folder}" for name, folder in DEFAULT_SCENES.items() if folder.is_dir()]
    if not scenes:
        raise UserError("name a scene: --scene lego=FOLDER (a NeRF-synthetic folder) or --scene fern=FOLDER (LLFF)")
    unknown = [p for p in args.presets if p not in config.preset_names()]
    if unknown:
        raise UserError(f"unknown preset {unknown[0]}; presets are {', '.join(config.preset_names())}")
    read_weights()  # missing LPIPS weights stop here, not after a fit
    todo = []
    for item in scenes:
        name, sep, folder = item.partition("=")
        if not sep or not Path(folder).is_dir():
            raise UserError(f"--scene {item}: give NAME=FOLDER with an existing folder")
        todo += [{**run, "folder": str(Path(folder).resolve())}
                 for run in runs_to_do(args, scene_kind(Path(folder)), name, Path(folder))]
    results = json.loads(args.results.read_text()) if args.results.is_file() else {"runs": []}
    failed = 0
    for run in todo:
        out = CACHE / f"{run['scene']}-{slug(run['label'])}"
        earlier = earlier_run(run["scene"], out, first=CACHE / f"{run['scene']}-{slug(todo[0]['label'])}")
        if not out.exists() and earlier is not None:
            for stage in BEFORE_FIT:
                shutil.copytree(earlier / stage, out / stage)
        print(f"[protocol] {run['scene']}: {run['label']}", flush=True)
        load_before, measured_at = os.getloadavg(), commit()  # the code the run measures, whatever HEAD is by its end
        result = run_child("bench.protocol", {**run, "out": str(out), "verbose": args.verbose}, run["label"])
        if result is None:
            failed += 1
            continue
        record = {**run, **result, "machine": machine(), "commit": measured_at,
                  "threads": os.environ.get("OMP_NUM_THREADS"), "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                  "load_average": {"before": list(load_before), "after": list(os.getloadavg())}}
        m = result["mean"]
        print(f"  {m['psnr']:.2f} dB  SSIM {m['ssim']:.3f}  LPIPS {m.get('lpips', float('nan')):.3f}  "
              f"fit {result['fit_seconds']:.0f} s, whole run {result['wall_seconds']:.0f} s", flush=True)
        key = (run["scene"], run["label"])
        results["runs"] = [r for r in results["runs"] if (r["scene"], r["label"]) != key] + [record]
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text(json.dumps(results, indent=1) + "\n")
    print(table(results))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
