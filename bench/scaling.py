"""How the fit's cost grows: time per optimiser step and memory against grid resolution and image count.

Each point is a short fit of lego (or the synthetic scene of bench/fit.py) in its own process, so its
peak memory (max RSS) is its own, with the `default` preset's settings: a first level at half the
resolution for --coarse-steps steps, the fit's prune and upsample to the resolution (so the grid is as
sparse as the fit makes it, not dense), then --warmup untimed steps and --steps timed ones. A point's
step time is the median of its timed steps. Memory: the model's bytes (grid and index), the training
state's (gradient and RMSProp moments, each the size of the grid's parameters), the training pixels'
and the process's peak RSS.

Two sweeps: the resolutions at every training image, and the image counts (spread evenly over the
training images) at --fixed-resolution. Writes bench/results/scaling.json and scaling.png.

    .venv/bin/python -m bench.scaling                               # lego: 64-256, 10-100 images
    .venv/bin/python -m bench.scaling --scene synthetic --resolutions 32,48 --images 10,20 --steps 10
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from bench.fit import cpu_name, load_scene, machine, resolve, synthetic_scene  # noqa: E402
from plenoxels.core.errors import UserError  # noqa: E402

RESULTS = REPO / "bench" / "results" / "scaling.json"


def training_frames(scene: dict, count: int | None) -> list[dict]:
    """`count` training frames spread evenly over the scene's (all of them for None)."""
    train = [f for f in scene["frames"] if f.get("split", "train") == "train"]
    if count is None:
        return train
    if count > len(train):
        raise UserError(f"the scene has {len(train)} training images; ask for at most that many (--images)")
    return [train[round(i * (len(train) - 1) / max(1, count - 1))] for i in range(count)]


# ---- one point, in its own process ----------------------------------------------------------------
def one_point(spec: dict) -> dict:
    import numpy as np

    from stages.common.frames import load_frame
    from plenoxels.core.scene_model import SceneModel
    from plenoxels.core.train import Fitter
    from plenoxels.core.ray_set import RaySet

    scene, root = load_scene(spec["scene"], Path(spec["data"]), 0)
    resolution, coarse = spec["resolution"], spec["coarse_steps"]
    timed_steps = spec["warmup"] + spec["steps"]
    levels = {"resolutions": [resolution // 2, resolution], "steps": [coarse, timed_steps]} if coarse else \
        {"resolutions": [resolution], "steps": [timed_steps]}
    s = resolve(spec["preset"], scene.get("type", "object"), {**spec["overrides"], **levels, "eval_every": 0})
    frames = training_frames(scene, spec["images"])
    loading = time.perf_counter()
    images, c2ws, ks = [], [], []
    for frame in frames:
        image, k = load_frame(root, frame, s.image_scale, s.background_color)
        images.append(image)
        c2ws.append(np.asarray(frame["transform_matrix"], dtype=np.float64))
        ks.append(k)
    train = RaySet(images, c2ws, ks)
    del images
    loading = time.perf_counter() - loading

    fitter = Fitter(SceneModel.create(scene, s, s.resolutions[0]), s, train)
    started = time.perf_counter()
    for _ in range(coarse):
        fitter.train_step()
    coarse_seconds = time.perf_counter() - started
    started = time.perf_counter()
    if coarse:
        fitter.next_level()
    level_seconds = time.perf_counter() - started
    times = []
    for _ in range(timed_steps):
        started = time.perf_counter()
        fitter.train_step()
        times.append(time.perf_counter() - started)
    timed = sorted(times[spec["warmup"]:])
    grid = fitter.model.grid
    return {
        "resolution": resolution, "grid": list(grid.resolution), "images": len(frames),
        "image_size": [ks[0].w, ks[0].h], "batch_size": s.batch_size, "sh_degree": s.sh_degree,
        "step_ms": {"median": round(1e3 * statistics.median(timed), 2),
                    "p10": round(1e3 * timed[len(timed) // 10], 2), "p90": round(1e3 * timed[(9 * len(timed)) // 10], 2)},
        "occupied": grid.num_occupied, "model_bytes": fitter.model.memory_bytes()["total"],
        "training_state_bytes": fitter.optim.second_moment.nbytes + fitter.grad.data.nbytes,
        "pixel_bytes": train.pixels.nbytes,
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "loading_seconds": round(loading, 2), "coarse_seconds": round(coarse_seconds, 2),
        "level_change_seconds": round(level_seconds, 2), "train_psnr": round(fitter.train_psnr(), 2),
    }


def spawn(spec: dict) -> dict | None:
    load_before = os.getloadavg()
    from bench.common import run_child

    result = run_child("bench.scaling", spec, f"resolution {spec['resolution']}, {spec['images'] or 'all'} images")
    if result is None:
        return None
    return {**result, "threads": os.environ.get("OMP_NUM_THREADS"),
            "load_average": {"before": [round(x, 2) for x in load_before],
                             "after": [round(x, 2) for x in os.getloadavg()]}}


# ---- plot -----------------------------------------------------------------------------------------
def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(12, 9))
    sweeps = (("resolution", "resolution", "grid resolution (vertices on the longest axis)"),
              ("images", "images", "training images"))
    setup = results["setup"]
    for col, (sweep, x_key, x_label) in enumerate(sweeps):
        points = sorted(results[sweep], key=lambda p: p[x_key])
        if not points:
            continue
        xs = [p[x_key] for p in points]
        ax = axes[0, col]
        median = [p["step_ms"]["median"] for p in points]
        ax.errorbar(xs, median, yerr=[[m - p["step_ms"]["p10"] for m, p in zip(median, points)],
                                      [p["step_ms"]["p90"] - m for m, p in zip(median, points)]],
                    marker="o", capsize=3, label="median step (bars: 10th-90th percentile)")
        for p, y in zip(points, median):
            ax.annotate(f"{p['occupied'] / 1e6:.2f}M voxels", (p[x_key], y), fontsize=7, xytext=(4, 4),
                        textcoords="offset points")
        ax.set_ylabel("time per optimiser step (ms)")
        ax.set_ylim(bottom=0)
        ax = axes[1, col]
        ax.plot(xs, [p["peak_rss_mb"] for p in points], marker="o", label="peak RSS of the process")
        ax.plot(xs, [(p["model_bytes"] + p["training_state_bytes"]) / 2**20 for p in points], marker="s",
                label="model + gradient + RMSProp state")
        ax.plot(xs, [p["model_bytes"] / 2**20 for p in points], marker="^", label="model (grid and index)")
        ax.plot(xs, [p["pixel_bytes"] / 2**20 for p in points], marker="v", label="training pixels")
        ax.set_ylabel("memory (MiB)")
        ax.set_ylim(bottom=0)
        for row in (0, 1):
            axes[row, col].set_xlabel(x_label)
            axes[row, col].set_xticks(xs)
            axes[row, col].grid(alpha=0.3)
            axes[row, col].legend(fontsize=7)
    res, img = results["resolution"], results["images"]
    titles = (f"at all {res[0]['images']} training images" if res else "",
              f"at resolution {setup['fixed_resolution']}" if img else "")
    axes[0, 0].set_title(titles[0], fontsize=9)
    axes[0, 1].set_title(titles[1], fontsize=9)
    m = results["machine"]
    loads = [x for p in res + img for x in (p["load_average"]["before"][0], p["load_average"]["after"][0])]
    fig.suptitle(f"fit cost scaling on {setup['scene']} ({setup['preset']} preset, {setup['batch_size']} rays per step, "
                 f"SH degree {setup['sh_degree']}, a {setup['coarse_steps']}-step first level at half resolution)\n"
                 f"{cpu_name(m)}, {m['cores']} cores, OMP_NUM_THREADS {setup['threads']}, "
                 f"1-min load average {min(loads):.1f}-{max(loads):.1f} around the runs", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ---- main -----------------------------------------------------------------------------------------
def int_list(text: str) -> list[int]:
    try:
        values = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise UserError(f"'{text}' must be comma-separated whole numbers (for example 64,128)") from None
    if any(v < 1 for v in values):
        raise UserError(f"'{text}' must be positive numbers")
    return values


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--scene", choices=("lego", "synthetic"), default="lego")
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--preset", default="default")
    parser.add_argument("--resolutions", default="64,96,128,192,256")
    parser.add_argument("--images", default="10,25,50,100")
    parser.add_argument("--fixed-resolution", type=int, default=128, help="the resolution of the image-count sweep")
    parser.add_argument("--coarse-steps", type=int, default=300, help="steps of the first level (0: start dense)")
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--steps", type=int, default=40, help="timed steps per point")
    parser.add_argument("--set", action="append", default=[], help="key=value (a fit setting) for every point")
    parser.add_argument("--results", type=Path, default=RESULTS, help="the JSON to write (the PNG goes beside it)")
    args = parser.parse_args(argv)
    from bench.common import run_part

    return run_part(args, one_point, measure)


def measure(args) -> int:
    if args.steps < 1 or args.warmup < 0 or args.coarse_steps < 0:
        raise UserError("--steps must be at least 1, --warmup and --coarse-steps at least 0")
    from bench.common import fit_overrides

    overrides = fit_overrides(args.set)
    settings = resolve(args.preset, "object", overrides)
    scene, _ = load_scene(args.scene, args.data, 0) if args.scene == "lego" else synthetic_scene()
    counts = int_list(args.images)
    training_frames(scene, max(counts, default=1))  # too many asked for stops here, before any run
    every_image = len(training_frames(scene, None))
    setup = {"scene": args.scene, "preset": args.preset, "overrides": overrides, "batch_size": settings.batch_size,
             "sh_degree": settings.sh_degree, "image_scale": settings.image_scale, "coarse_steps": args.coarse_steps,
             "warmup": args.warmup, "steps": args.steps, "fixed_resolution": args.fixed_resolution,
             "threads": os.environ.get("OMP_NUM_THREADS")}
    base = {"scene": args.scene, "data": str(args.data), "preset": args.preset, "overrides": overrides,
            "coarse_steps": args.coarse_steps, "warmup": args.warmup, "steps": args.steps}
    plan = [("resolution", {**base, "resolution": r, "images": None}) for r in int_list(args.resolutions)]
    # every training image is None in both sweeps, so that point is measured once and appears in both
    plan += [("images", {**base, "resolution": args.fixed_resolution, "images": None if n == every_image else n})
             for n in counts]
    results = {"machine": machine(), "setup": setup, "resolution": [], "images": []}
    measured = {}
    failed = 0
    for n, (sweep, spec) in enumerate(plan, 1):
        key = json.dumps(spec, sort_keys=True)
        if key in measured:
            results[sweep].append(measured[key])
            args.results.write_text(json.dumps(results, indent=1) + "\n")
            continue
        print(f"[{n}/{len(plan)}] resolution {spec['resolution']}, {spec['images'] or 'all'} images", flush=True)
        point = spawn(spec)
        if point is None:
            failed += 1
            continue
        print(f"  step {point['step_ms']['median']:.1f} ms (median of {args.steps}), {point['occupied'] / 1e6:.2f}M voxels, "
              f"model {point['model_bytes'] / 2**20:.0f} MiB, peak RSS {point['peak_rss_mb']:.0f} MiB, "
              f"level change {point['level_change_seconds']:.1f} s", flush=True)
        results[sweep].append(point)
        measured[key] = point
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text(json.dumps(results, indent=1) + "\n")
    if results["resolution"] or results["images"]:
        plot(results, args.results.with_suffix(".png"))
        print(f"wrote {args.results} and {args.results.with_suffix('.png')}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
