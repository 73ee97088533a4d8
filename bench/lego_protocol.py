"""The papers' protocol on lego: each preset fitted on lego's 100 training views, scored on held-out views at
full size (800x800) and at 400x400 with PSNR, SSIM and LPIPS (AlexNet, v0.1), beside the Plenoxels paper's
figures.

The held-out views are lego's `val` split (the data here has no `test` split, which the papers score on:
200 views; val is 100 views of the same kind), the first --views of them. Ground truth is each RGBA photo
composited onto the fit's background colour (white), resized with area averaging for 400x400, as the
evaluate stage does. Each preset runs in its own process (its peak memory is its own).

    .venv/bin/python -m bench.lego_protocol                               # every preset, 25 views
    .venv/bin/python -m bench.lego_protocol --presets fast --views 5 --results bench/out/lego_protocol.json
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from plenoxels.errors import UserError  # noqa: E402

RESULTS = REPO / "bench" / "results" / "lego_protocol.json"
SIZES = {"800x800": 1.0, "400x400": 0.5}
# Fridovich-Keil et al. 2022 (Plenoxels), GPU, 512^3 grid: lego's PSNR, and the 8 synthetic scenes' means.
PAPER = {"lego": {"psnr": 34.10}, "synthetic_mean": {"psnr": 31.71, "ssim": 0.958, "lpips": 0.049}}


def one_run(spec: dict) -> dict:
    """Fits lego with a preset and scores the held-out views at each size."""
    import numpy as np
    import torch

    from bench.common import fitted
    from bench.fit import load_scene, resolve
    from pipeline.images import load_frame
    from pipeline.metrics import image_scores, mean_scores

    scene, root = load_scene("lego", Path(spec["data"]), spec["views"])
    settings = resolve(spec["preset"], "object", spec["overrides"])
    summary, wall, record, model = fitted(scene, root, settings, quiet=not spec.get("verbose"))
    held_out = [f for f in scene["frames"] if f.get("split") == "test"]
    sizes = {}
    for label, scale in SIZES.items():
        views, render_started = [], time.time()
        for frame in held_out:
            truth, k = load_frame(root, frame, scale, settings.background_color)
            with torch.no_grad():
                render = model.render_camera(np.asarray(frame["transform_matrix"]), k)["rgb"].numpy()
            views.append({"name": frame["name"], **image_scores(render, truth, with_lpips=True)})
        sizes[label] = {"mean": mean_scores(views), "views": views,
                        "render_seconds_per_view": round((time.time() - render_started) / max(1, len(views)), 2)}
    return {"sizes": sizes, "held_out_views": len(held_out), "train_images": record["train_images"],
            "wall_seconds": round(wall, 1), "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
            "resolution": record["model"]["resolution"], "occupied": record["model"]["occupied"],
            "summary": summary["line"]}


def spawn(spec: dict) -> dict | None:
    from bench.common import run_child

    return run_child("bench.lego_protocol", spec, spec["preset"])


def table(results: dict) -> str:
    """Markdown: one row per preset, PSNR / SSIM / LPIPS at each size, and the paper's row."""
    head = "| preset | " + " | ".join(f"{s} PSNR / SSIM / LPIPS" for s in SIZES) + " | fit wall time | views |"
    lines = [head, "|" + "---|" * (len(SIZES) + 3)]
    for run in results.get("runs", []):
        cells = []
        for size in SIZES:
            m = run["sizes"][size]["mean"]
            cells.append(f"{m['psnr']:.2f} dB / {m['ssim']:.3f} / {m['lpips']:.3f}")
        lines.append(f"| {run['label']} | " + " | ".join(cells) + f" | {run['wall_seconds']:.0f} s | {run['held_out_views']} |")
    lego, mean = PAPER["lego"], PAPER["synthetic_mean"]
    lines.append(f"| paper (GPU, 512³) | lego {lego['psnr']:.2f} dB; 8 scenes' mean {mean['psnr']:.2f} dB / "
                 f"{mean['ssim']:.3f} / {mean['lpips']:.3f} | - | - | 200 (test) |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--presets", default="fast,balanced,default,quality", help="comma-separated presets")
    parser.add_argument("--views", type=int, default=25, help="score the first N lego val views (the papers: 200 test)")
    parser.add_argument("--set", action="append", default=[], help="key=value (a fit setting) for every run")
    parser.add_argument("--results", type=Path, default=RESULTS, help="the JSON to write (runs replace same-label runs)")
    parser.add_argument("--table", action="store_true", help="print --results as a Markdown table and exit")
    parser.add_argument("--verbose", action="store_true", help="show each fit's progress")
    args = parser.parse_args(argv)
    from bench.common import run_part

    return run_part(args, one_run, run_all)


def run_all(args) -> int:
    from bench.common import fit_overrides
    from bench.fit import load_scene, machine
    from pipeline import config
    from pipeline.lpips import read_weights

    if args.table:
        if not args.results.is_file():
            raise UserError(f"no results at {args.results}; run the benchmark first")
        print(table(json.loads(args.results.read_text())))
        return 0
    presets = [p for p in args.presets.split(",") if p]
    unknown = [p for p in presets if p not in config.preset_names()]
    if unknown:
        raise UserError(f"unknown preset {unknown[0]}; presets are {', '.join(config.preset_names())}")
    read_weights()  # missing LPIPS weights stop here, not after a fit
    load_scene("lego", args.data, args.views)
    overrides = fit_overrides(args.set)
    results = json.loads(args.results.read_text()) if args.results.is_file() else {"runs": []}
    results.update(machine=machine(), paper=PAPER, protocol={
        "held_out": f"lego val, first {args.views} views", "sizes": list(SIZES),
        "lpips": "AlexNet, v0.1 (pipeline/lpips.py)", "ssim": "pipeline/metrics.py (skimage, gaussian)"})
    failed = 0
    for preset in presets:
        label = preset + (f", {' '.join(args.set)}" if args.set else "")
        print(f"[lego protocol] {label}", flush=True)
        started = time.time()
        spec = {"preset": preset, "overrides": overrides, "views": args.views, "data": str(args.data),
                "verbose": args.verbose}
        result = spawn(spec)
        if result is None:
            failed += 1
            continue
        run = {"label": label, "preset": preset, "overrides": overrides, "threads": os.environ.get("OMP_NUM_THREADS"),
               "process_seconds": round(time.time() - started, 1), "load_average": list(os.getloadavg()),
               "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **result}
        for size, scored in result["sizes"].items():
            m = scored["mean"]
            print(f"  {size}: {m['psnr']:.2f} dB  SSIM {m['ssim']:.3f}  LPIPS {m['lpips']:.3f}", flush=True)
        results["runs"] = [r for r in results["runs"] if r["label"] != label] + [run]
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text(json.dumps(results, indent=1) + "\n")
    print(table(results))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
