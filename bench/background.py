"""What the background model costs a fit step: the same grid, the same batches, with the multi-sphere background
on and off, timed through Fitter.train_step (rendering, loss, gradients, TV, optimiser steps), medians of
interleaved repeats.

The grid is bench/kernels.py's synthetic object at 128^3, sparse (its occupied region only, as after pruning) and
dense (every vertex, as a fit's first level starts); the training rays are random pixels of 40 cameras around it at
400x300, as for an unbounded scene; the background as unbounded scenes get it (configs/scene_types/unbounded.yaml:
16 spheres of 32x64 texels) and at the fit's own defaults (32 spheres of 64x128).

    python -m bench.background [--steps 20] [--repeats 5] [--results bench/results/background.json]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from bench.kernels import make_grid  # noqa: E402
from plenoxels.core.background import MultiSphereBackground  # noqa: E402
from plenoxels.core.cameras import Intrinsics, look_at  # noqa: E402
from plenoxels.core.render import RenderOptions  # noqa: E402
from plenoxels.core.scene_model import ModelOptions, SceneModel, background_width_for  # noqa: E402
from plenoxels.core.train import Fitter, TrainOptions  # noqa: E402
from plenoxels.core.ray_set import RaySet  # noqa: E402

RESULTS = REPO / "bench" / "results" / "background.json"


def training_rays(views: int = 40, width: int = 400, height: int = 300, seed: int = 0) -> RaySet:
    rng = np.random.default_rng(seed)
    images, c2ws, ks = [], [], []
    for i in range(views):
        angle = 2 * np.pi * i / views
        eye = np.array([2.5 * np.cos(angle), 2.5 * np.sin(angle), 0.6 + 0.3 * np.sin(3 * angle)])
        c2ws.append(look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0])))
        ks.append(Intrinsics(0.8 * width, 0.8 * width, width / 2, height / 2, width, height))
        images.append(rng.random((height, width, 3), dtype=np.float32))
    return RaySet(images, c2ws, ks)


# (spheres, texture width) of the background: what unbounded scenes get, and the fit's defaults (whose width 0 means
# texels sized from the photos: these rays' focal length of 0.8 x 400 pixels).
SIZES = {"unbounded overlay": (16, 64),
         "fit defaults": (ModelOptions().background_spheres,
                          ModelOptions().background_width or background_width_for(0.8 * 400, ModelOptions().background_texel_px))}


def model(sparse: bool, background_size: tuple[int, int] | None) -> SceneModel:
    grid = make_grid(128, sparse=sparse)
    background = None
    if background_size is not None:
        spheres, width = background_size
        background = MultiSphereBackground.around_box(grid.bbox_min, grid.bbox_max, n_spheres=spheres,
                                                      height=width // 2, width=width)
    return SceneModel(grid, "unbounded" if background is not None else "object", background=background,
                      render_options=RenderOptions(step_size=0.5))


def time_steps(fitter: Fitter, steps: int) -> float:
    started = time.perf_counter()
    for _ in range(steps):
        fitter.train_step()
    return (time.perf_counter() - started) / steps


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20, help="steps per timed repeat")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--label", default="", help="a name for this code version in the results (e.g. its commit)")
    args = parser.parse_args(argv)
    rays = training_rays()
    # Rates of ~0: every variant keeps the same grid from step to step, so the timings compare the same work (with
    # real rates the grids drift apart, and a grid fitting noise without a background slows down as it fills).
    still = 1e-12
    options = TrainOptions(batch_size=8192, lr_density=still, lr_density_final=still, lr_sh=still, lr_sh_final=still,
                           lr_background=still)
    runs = {}
    for grid_kind in ("sparse", "dense"):
        variants = {"off": None, **SIZES}
        fitters = {name: Fitter(model(grid_kind == "sparse", size), options, rays) for name, size in variants.items()}
        for fitter in fitters.values():
            time_steps(fitter, 3)  # warm-up: page in the tables, settle the optimisers
        seconds = {name: [] for name in variants}
        for _ in range(args.repeats):  # interleaved, so load changes hit every variant alike
            for name, fitter in fitters.items():
                seconds[name].append(time_steps(fitter, args.steps))
        off = statistics.median(seconds["off"])
        runs[grid_kind] = {"occupied": fitters["off"].model.grid.num_occupied,
                           "step_seconds_off": round(off, 4), "all_off": seconds["off"]}
        for name, size in SIZES.items():
            on = statistics.median(seconds[name])
            background = fitters[name].model.background
            runs[grid_kind][name] = {"spheres": size[0], "width": size[1], "step_seconds_on": round(on, 4),
                                     "ratio": round(on / off, 3), "all_on": seconds[name],
                                     "background_bytes": background.memory_bytes()}
            print(f"{grid_kind:>6} 128^3, {name} background: step {off * 1000:.1f} ms without, {on * 1000:.1f} ms "
                  f"with it ({on / off:.2f}x)", flush=True)
    results = json.loads(args.results.read_text()) if args.results.is_file() else {}
    results[args.label or "latest"] = {"runs": runs, "threads": torch.get_num_threads(), "batch": options.batch_size,
                                       "load_average": list(os.getloadavg()),
                                       "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
