"""Benchmark of the fit: held-out quality against wall time and peak memory, per preset and per knob.

Scenes: lego from ../shared/data (train images fitted at --lego-scale of 800x800, i.e. 400x400 by
default; its val images are the held-out views, scored at the same size on white) and a synthetic
object scene (pipeline/synthetic.py, every 8th view held out). Each run is the fit stage exactly as
the pipeline runs it, in its own process so its peak memory (max RSS) is its own; PSNR and SSIM come
from stages/evaluate.py's functions. Writes bench/results/fit.json and bench/results/fit.png (PSNR
and SSIM against time and against peak memory, the Pareto front of each scene marked).

    .venv/bin/python -m bench.fit                                  # presets fast/default/quality on both scenes
    .venv/bin/python -m bench.fit --scenes lego --presets fast     # one run
    .venv/bin/python -m bench.fit --sweep                          # also the single knobs on the synthetic scene
    .venv/bin/python -m bench.fit ... --set fit_key=value          # override fit settings in every run
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
RESULTS = REPO / "bench" / "results" / "fit.json"
PLOT = REPO / "bench" / "results" / "fit.png"
CACHE = REPO / "bench" / "out"

# The single knobs of the sweep, each varied alone from the default preset.
SWEEP = {
    "final resolution": [{"resolutions": [64, 128], "steps": [1000, 2000]}, {"resolutions": [128, 192]}],
    "sh degree": [{"sh_degree": d} for d in (0, 1, 3)],
    "image scale": [{"image_scale": 0.25}, {"image_scale": 1.0}],
    "steps": [{"steps": [750, 1500]}, {"steps": [3000, 6000]}],
}


def machine() -> dict:
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "omp_threads": os.environ.get("OMP_NUM_THREADS"),
            "load_average_at_start": os.getloadavg()}


# ---- scenes ---------------------------------------------------------------------------------------
def lego(data: Path, val_limit: int | None) -> tuple[dict, Path]:
    from bench.cuda import lego_scene

    scene, _ = lego_scene(data / "lego", val_limit)
    return scene, data / "lego"


def synthetic() -> tuple[dict, Path]:
    """An object scene of 48 views at 200x150, made once and kept under bench/out."""
    from pipeline.io import read_json
    from pipeline.synthetic import write_scene
    from stages.normalize import Points, Settings, normalize_scene

    root = CACHE / "synthetic_object"
    if not (root / "transforms.json").is_file():
        write_scene("object", root, n_views=48, width=200, height=150)
    scene = normalize_scene(read_json(root / "transforms.json"), Points.empty(),
                            Settings(scene_type="object", holdout_every=8), poses_dir=root, path_prefix="")
    return scene, root


# ---- one run, in its own process ------------------------------------------------------------------
def one_run(spec: dict) -> dict:
    """Fits `spec['scene']` with the preset plus overrides and scores every held-out view."""
    import numpy as np
    import torch

    from pipeline import config
    from pipeline.report import Reporter
    from bench.common import fit_context
    from plenoxels.scene_model import SceneModel
    from stages import fit
    from stages.evaluate import image_psnr, image_ssim

    scene, root = lego(Path(spec["data"]), spec.get("val_limit")) if spec["scene"] == "lego" else synthetic()
    values = config.merge(config.load_preset(spec["preset"]), {"fit": spec["overrides"]})["fit"]
    settings = config.build(fit.Settings, "fit", values)
    with fit_context(scene, root, settings, Reporter(quiet=not spec.get("verbose"))) as ctx:
        started = time.time()
        summary = fit.run(ctx)
        wall = time.time() - started
        record = json.loads((ctx.work / "fit.json").read_text())
        model = SceneModel.load(ctx.work)
        psnrs, ssims = [], []
        render_started = time.time()
        for frame in [f for f in scene["frames"] if f.get("split") == "test"]:
            truth, k = fit.load_frame(root, frame, settings.image_scale, settings.background_color)
            with torch.no_grad():
                render = model.render_camera(frame["transform_matrix"], k)["rgb"].numpy()
            psnrs.append(image_psnr(render, truth))
            ssims.append(image_ssim(render, truth))
        render_seconds = time.time() - render_started
    return {
        "scene": spec["scene"], "preset": spec["preset"], "overrides": spec["overrides"], "label": spec["label"],
        "psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims)), "held_out_views": len(psnrs),
        "image_size": [k.w, k.h], "fit_seconds": record["seconds"], "wall_seconds": round(wall, 1),
        "render_seconds_per_view": round(render_seconds / max(1, len(psnrs)), 3),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "occupied": record["model"]["occupied"], "model_bytes": record["memory_bytes"]["total"],
        "history": record["history"], "levels": record["levels"], "summary": summary["line"],
        "settings": config.to_dict(settings),
    }


def spawn(spec: dict) -> dict | None:
    proc = subprocess.run([sys.executable, "-m", "bench.fit", "--one", json.dumps(spec)], cwd=REPO,
                          stdout=subprocess.PIPE, text=True)
    if proc.returncode != 0:
        print(f"  {spec['scene']} {spec['label']}: failed (exit {proc.returncode})", flush=True)
        return None
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ---- plot -----------------------------------------------------------------------------------------
def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats on both cost (lower) and quality (higher), by cost."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], float("-inf")
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


def plot(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(12, 9))
    for row, metric in enumerate(("psnr", "ssim")):
        for col, (cost, label) in enumerate((("fit_seconds", "fit time (s)"), ("peak_rss_mb", "peak memory (MB)"))):
            ax = axes[row, col]
            for scene in sorted({r["scene"] for r in runs}):
                mine = [r for r in runs if r["scene"] == scene]
                xy = [(r[cost], r[metric]) for r in mine]
                dots = ax.scatter(*zip(*xy), label=scene)
                front = pareto(xy)
                ax.plot([xy[i][0] for i in front], [xy[i][1] for i in front], "--", color=dots.get_facecolor()[0])
                for r, (x, y) in zip(mine, xy):
                    ax.annotate(r["label"], (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
            ax.set_xlabel(label)
            ax.set_ylabel("held-out " + metric.upper() + (" (dB)" if metric == "psnr" else ""))
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
    fig.suptitle("fit: held-out quality against cost (dashed: Pareto front)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


# ---- main -----------------------------------------------------------------------------------------
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--one", help=argparse.SUPPRESS)
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--scenes", default="lego,synthetic")
    parser.add_argument("--presets", default="fast,default,quality")
    parser.add_argument("--sweep", action="store_true", help="also vary single knobs from the default preset")
    parser.add_argument("--sweep-scene", default="synthetic")
    parser.add_argument("--lego-scale", type=float, default=0.5, help="fit and score lego at this share of 800x800")
    parser.add_argument("--val-limit", type=int, default=None, help="score only the first N lego val views")
    parser.add_argument("--set", action="append", default=[], help="fit_key=value for every run")
    parser.add_argument("--verbose", action="store_true")
    args = parser.parse_args(argv)
    if args.one:
        print(json.dumps(one_run(json.loads(args.one))))
        return 0

    import yaml

    common = {k: yaml.safe_load(v) for k, v in (item.partition("=")[::2] for item in args.set)}
    specs = []
    for scene in args.scenes.split(","):
        extra = {"image_scale": args.lego_scale} if scene == "lego" else {}
        for preset in args.presets.split(","):
            specs.append({"scene": scene, "preset": preset, "label": preset, "overrides": {**extra, **common}})
    if args.sweep:
        extra = {"image_scale": args.lego_scale} if args.sweep_scene == "lego" else {}
        for knob, variants in SWEEP.items():
            for variant in variants:
                label = knob + ": " + ", ".join(f"{k}={v}" for k, v in variant.items())
                specs.append({"scene": args.sweep_scene, "preset": "default", "label": label,
                              "overrides": {**extra, **variant, **common}})
    results = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
    results["machine"] = machine()
    runs = results.get("runs", [])
    for spec in specs:
        spec.update(data=str(args.data), val_limit=args.val_limit, verbose=args.verbose)
        result = spawn(spec)
        if result is None:
            continue
        print(f"  {result['scene']:<9} {result['label']:<40} {result['psnr']:6.2f} dB  SSIM {result['ssim']:.3f}  "
              f"fit {result['fit_seconds']:7.1f} s  peak {result['peak_rss_mb']:7.0f} MB  ({result['summary']})", flush=True)
        runs = [r for r in runs if (r["scene"], r["label"]) != (result["scene"], result["label"])] + [result]
        results["runs"] = runs
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps(results, indent=1) + "\n")
    if runs:
        plot(runs, PLOT)
        print(f"wrote {RESULTS.relative_to(REPO)} and {PLOT.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
