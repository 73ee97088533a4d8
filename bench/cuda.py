"""Benchmark of the CUDA core against the C++ CPU core. Needs an NVIDIA GPU and a CUDA build
of plenoxels._C; elsewhere it says so in one line and exits 0.

Two parts, results in bench/results/cuda.json:
- throughput: samples per second of the fused forward+backward (loss_and_grad, the training step's
  kernel) and of the forward render, SH degree 2, on bench/kernels.py's synthetic grids (128^3 dense,
  256^3 occupied region) and batches (32x32 tiles, random pixels), CUDA against the CPU core run with
  --cpu-threads OpenMP threads (2: the CPU machines' cores). Samples counts the samples that
  contribute (sample_counts), as bench/kernels.py does; marching empty space is part of the time.
- lego: the fit stage (stages/fit.py, exactly as the pipeline runs it, fit.device=cuda) on the NeRF
  synthetic lego train images at 800x800, then PSNR over the val images at 800x800 on a white
  background; held-out PSNR against wall time comes from the fit's own history (val views).
  The val images present on disk are used (a GPU machine may carry only some of them).

    python -m bench.cuda [--part throughput|lego|all] [--data ../shared/data] [--cpu-threads 2]
        [--gpu-rays 262144] [--cpu-rays 8192] [--val-limit N] [--set fit_key=value ...] [--lego-key lego]

--lego-key names the entry of cuda.json the lego part writes (another key keeps the first run's beside it, e.g.
`--set time_budget=60s --lego-key lego_budget_60s`).

The throughput part needs only torch; the lego part also the fit stage's packages (numpy, PIL,
OpenCV, imageio, PyYAML, tqdm). A GPU machine without ../shared/data can take lego/train, the
transforms JSONs and part of lego/val (under 64 MiB) and point --data at their parent.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
RESULTS = REPO / "bench" / "results" / "cuda.json"
NEEDS_GPU = ("bench.cuda: skipped: needs an NVIDIA GPU and plenoxels._C built with its CUDA kernels "
             "(`make install` on a machine with nvcc and a CUDA build of torch)")

# Lego fit defaults: coarse to fine to 512^3 at full resolution. Any fit setting can be changed with --set.
LEGO_FIT = {"device": "cuda", "image_scale": 1.0, "resolutions": [128, 256, 512], "steps": [1000, 2000, 5000],
            "batch_size": 32768, "eval_every": 1000, "eval_views": 8, "eval_scale": 1.0, "checkpoint_every": 1e9}


def parse_args(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("throughput", "lego", "all"), default="all")
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--cpu-threads", type=int, default=2, help="OpenMP threads of the CPU baseline")
    parser.add_argument("--resolutions", default="128,256", help="throughput grids (vertices per side)")
    parser.add_argument("--gpu-rays", type=int, default=1 << 18, help="rays per CUDA batch")
    parser.add_argument("--cpu-rays", type=int, default=8192, help="rays per CPU batch")
    parser.add_argument("--val-limit", type=int, default=None, help="score at most this many val images")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a fit setting for the lego part, e.g. steps=[1000,2000,4000]")
    parser.add_argument("--lego-key", default="lego", help="the entry of cuda.json the lego part writes")
    parser.add_argument("--preset", default=None, help="fit lego with this preset's settings (default: LEGO_FIT)")
    # Internal: the CPU baseline runs in a child process so its thread count is set before OpenMP starts.
    parser.add_argument("--cpu-baseline", default=None, help=argparse.SUPPRESS)
    return parser.parse_args(argv)


# ---- throughput -----------------------------------------------------------------------------------
def measure(torch, resolution: int, device, rays: int, reps: int, kind: str) -> dict:
    """Median samples/s of loss_and_grad and of render over `reps` batches (after a warm-up batch), on
    bench/kernels.py's grid and batches, so the CPU figures compare with that benchmark's."""
    from bench.kernels import make_grid, random_batch, tile_batch
    from plenoxels.core.optim import GridGrad
    from plenoxels.core.render import RenderOptions, loss_and_grad, render, sample_counts

    opts = RenderOptions(step_size=0.5)
    grid = make_grid(resolution, sparse=resolution > 128).to(device)
    gen = torch.Generator().manual_seed(resolution)
    make = tile_batch if kind == "tiles" else random_batch
    batches = []
    for _ in range(reps + 1):
        origins, dirs = make(rays, gen)
        targets = torch.rand(origins.shape[0], 3, generator=gen)
        batches.append(tuple(x.to(device) for x in (origins, dirs, targets, torch.ones(origins.shape[0], 3))))
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    grad = GridGrad(grid)

    def seconds(run) -> list[float]:
        times = []
        for batch in batches:
            sync()
            started = time.perf_counter()
            run(batch)
            sync()
            times.append(time.perf_counter() - started)
            grad.clear()
        return times[1:]

    fused = seconds(lambda b: loss_and_grad(grid, *b, opts, grad))
    forward = seconds(lambda b: render(grid, b[0], b[1], b[3], opts))
    samples = [sample_counts(grid, b[0], b[1], opts)[1] for b in batches[1:]]
    return {"device": str(device), "resolution": resolution, "batch": kind, "occupied": grid.num_occupied,
            "rays_per_batch": int(batches[1][0].shape[0]), "samples_per_batch": int(statistics.median(samples)),
            "loss_and_grad_samples_per_s": statistics.median(n / t for n, t in zip(samples, fused)),
            "render_samples_per_s": statistics.median(n / t for n, t in zip(samples, forward))}


def cpu_baseline(resolution: int, kind: str, args) -> dict:
    """The CPU measurement in a child process with OMP_NUM_THREADS set before torch starts."""
    env = dict(os.environ, OMP_NUM_THREADS=str(args.cpu_threads))
    cmd = [sys.executable, "-m", "bench.cuda", "--cpu-baseline", f"{resolution},{kind}",
           "--cpu-rays", str(args.cpu_rays)]
    out = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def throughput(torch, args) -> list[dict]:
    rows = []
    for resolution in (int(r) for r in args.resolutions.split(",")):
        for kind in ("tiles", "random"):
            gpu = measure(torch, resolution, torch.device("cuda"), args.gpu_rays, 10, kind)
            torch.cuda.empty_cache()
            cpu = cpu_baseline(resolution, kind, args)
            row = {"resolution": resolution, "batch": kind, "cuda": gpu, "cpu": cpu, "cpu_threads": args.cpu_threads,
                   "speedup_loss_and_grad": gpu["loss_and_grad_samples_per_s"] / cpu["loss_and_grad_samples_per_s"],
                   "speedup_render": gpu["render_samples_per_s"] / cpu["render_samples_per_s"]}
            rows.append(row)
            print(f"{resolution}^3 SH2 {kind:>6} batches, forward+backward: CUDA "
                  f"{gpu['loss_and_grad_samples_per_s'] / 1e6:.1f} M samples/s, CPU ({args.cpu_threads} threads) "
                  f"{cpu['loss_and_grad_samples_per_s'] / 1e6:.2f} M samples/s: {row['speedup_loss_and_grad']:.0f}x; "
                  f"forward only {row['speedup_render']:.0f}x", flush=True)
    return rows


# ---- lego -----------------------------------------------------------------------------------------
LEGO_SIZE = 800  # every NeRF-synthetic render is 800x800


def blender_frames(folder: Path, split: str) -> list[dict]:
    """The frames of transforms_<split>.json whose image is on disk, in the poses stage's layout
    (OpenGL camera-to-world, pinhole intrinsics, the RGBA image as its own mask). Read here rather
    than through bench/normalize.py, which needs pycolmap (not on every GPU machine)."""
    meta = json.loads((folder / f"transforms_{split}.json").read_text())
    focal = 0.5 * LEGO_SIZE / math.tan(0.5 * meta["camera_angle_x"])
    frames = []
    for f in meta["frames"]:
        stem = f["file_path"].removeprefix("./")
        rel = next((stem + suffix for suffix in (".png", ".webp") if (folder / (stem + suffix)).is_file()), None)
        if rel is not None:
            frames.append({"name": f"{split}_{Path(rel).stem}", "file_path": rel, "mask_path": rel,
                           "transform_matrix": f["transform_matrix"], "fl_x": focal, "fl_y": focal,
                           "cx": LEGO_SIZE / 2, "cy": LEGO_SIZE / 2, "w": LEGO_SIZE, "h": LEGO_SIZE})
    if not frames:
        raise SystemExit(f"bench.cuda: no lego {split} images under {folder / split}; pass --data")
    return frames


def lego_scene(folder: Path, val_limit: int | None = None):
    """scene.json for lego as the normalize stage writes it (every train image for training), plus
    the val frames mapped into the same frame with split "test"."""
    import numpy as np

    from stages.framing.options import SceneOptions

    from stages.framing.scene_frame import normalize_scene

    from stages.framing.sightings import Points

    transforms = {"frames": blender_frames(folder, "train")}  # intrinsics are per frame
    scene = normalize_scene(transforms, Points.empty(), SceneOptions(holdout_every=0), poses_dir=folder, path_prefix="")
    world_from_input = np.asarray(scene["world_from_input"])
    val = blender_frames(folder, "val")[:val_limit]
    for frame in val:
        c2w = world_from_input @ np.asarray(frame["transform_matrix"], dtype=np.float64)
        c2w[:3, :3] /= scene["scale"]  # as normalize does: rotation and translation, no scale
        frame.update(transform_matrix=c2w.tolist(), split="test")
    scene["frames"] = scene["frames"] + val
    return scene, val


def fit_settings(overrides: list[str], preset: str | None = None):
    """The lego fit's settings: bench.cuda's own schedule (LEGO_FIT), or a preset's as the pipeline resolves it for an
    object scene (the GPU's live held-out PSNR as LEGO_FIT's), then the --set overrides."""
    import dataclasses

    import yaml

    from pipeline import config
    from stages.settings.fit import Settings

    if preset is None:
        values = dict(LEGO_FIT)
    else:
        values = config.merge(config.load_preset(preset),
                              config.load_scene_type_overlay("object", preset)).get("fit", {})
        values.update({k: LEGO_FIT[k] for k in ("device", "eval_every", "eval_views", "eval_scale", "checkpoint_every")})
    names = {f.name for f in dataclasses.fields(Settings)}
    for item in overrides:
        key, sep, raw = item.partition("=")
        if not sep or key not in names:
            raise SystemExit(f"bench.cuda: --set needs KEY=VALUE with KEY a fit setting; got {item!r}")
        values[key] = yaml.safe_load(raw)
    return config.build(Settings, "fit", values)


def lego(torch, args) -> dict:
    import dataclasses

    from pipeline.report import Reporter
    from bench.common import fit_context
    from plenoxels.core.native import resolve_device
    from plenoxels.core.scene_model import SceneModel, psnr
    from stages import fit
    from stages.common.frames import load_frame

    folder = args.data / "lego"
    settings = fit_settings(args.set, args.preset)
    scene, val = lego_scene(folder, args.val_limit)
    device = resolve_device(settings.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    with fit_context(scene, folder, settings, Reporter()) as ctx:
        started = time.time()
        summary = fit.run(ctx)
        total = time.time() - started
        record = json.loads((ctx.work / "fit.json").read_text()) if (ctx.work / "fit.json").is_file() else {}
        model = SceneModel.load(ctx.work).to(device)
        scores, render_seconds = [], 0.0
        for frame in val:
            image, k = load_frame(folder, frame, 1.0, settings.background_color)
            sync()
            t0 = time.time()
            rgb = model.render_camera(frame["transform_matrix"], k, photo=frame["name"])["rgb"]
            sync()
            render_seconds += time.time() - t0
            scores.append(psnr(float(((rgb.cpu() - torch.from_numpy(image)) ** 2).mean())))
    train_images = sum(1 for f in scene["frames"] if f.get("split") != "test")
    result = {"train_images": train_images, "val_images": len(scores), "val_psnr": statistics.mean(scores),
              "fit_seconds": record.get("seconds"),
              "fit_and_load_seconds": total, "render_seconds_per_image": render_seconds / len(scores),
              "settings": dataclasses.asdict(settings),
              "history": record.get("history"), "levels": record.get("levels"), "budget": record.get("budget"),
              "summary": summary.get("line")}
    print(f"lego 800x800 on {device}, {train_images} train images: {result['val_psnr']:.2f} dB over {len(scores)} "
          f"val images after {result['fit_seconds']} s of fitting ({total:.0f} s with image loading); "
          f"{1 / result['render_seconds_per_image']:.1f} val images/s rendered", flush=True)
    return result


def main(argv=None) -> int:
    args = parse_args(argv)
    import torch

    from plenoxels.core.native import cuda_ready

    if args.cpu_baseline is not None:
        resolution, kind = args.cpu_baseline.split(",")
        print(json.dumps(measure(torch, int(resolution), torch.device("cpu"), args.cpu_rays, 3, kind)))
        return 0
    if not cuda_ready():
        print(NEEDS_GPU)
        return 0
    results = {"gpu": torch.cuda.get_device_name(), "torch": torch.__version__, "cuda": torch.version.cuda}
    if RESULTS.is_file():
        results = {**json.loads(RESULTS.read_text()), **results}
    if args.part in ("throughput", "all"):
        results["throughput"] = throughput(torch, args)
    if args.part in ("lego", "all"):
        results[args.lego_key] = lego(torch, args)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=1) + "\n")
    print(f"wrote {RESULTS.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
