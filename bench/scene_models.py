"""Benchmark of the scene models: NDC for forward scenes, the background model for unbounded ones.

For each scene the fit runs with the scene-appropriate model (fit.ndc=auto, fit.background=auto) and
with the alternative forced (NDC off for a forward scene, the background off for an unbounded one, the
background on for an object scene); a forward scene also fits in NDC at 0.75x the resolutions (the
"coarser" run), to compare the two frames at similar cost. Each run is the fit stage as the pipeline
runs it (preset, the scene-type overlay from configs/scene_types/, then this benchmark's overrides),
scored on every held-out view with stages/evaluate.py's PSNR and SSIM. For the unbounded and forward
scenes the first held-out view is rendered by both models side by side with the truth
(bench/results/scene_models/<scene>.png): the floaters a bounded grid makes without a background, the
blur of a world grid on a forward scene's near objects.

Scenes: fern (LLFF, forward, every 8th image held out), cup and fox (inward with a room behind) from
../shared/data, and the synthetic forward, unbounded and object scenes (stages/capture/synthetic.py).
Results are written to bench/results/scene_models.json after every run, so a partial benchmark keeps
what it measured.

    .venv/bin/python -m bench.scene_models                               # every scene
    .venv/bin/python -m bench.scene_models --scenes fern cup             # some
    .venv/bin/python -m bench.scene_models --set steps=[300,600]         # override fit settings in every run
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
RESULTS = REPO / "bench" / "results" / "scene_models.json"
RENDERS = REPO / "bench" / "results" / "scene_models"
CACHE = REPO / "bench" / "out"
REAL = ("fern", "cup", "fox")
SYNTHETIC = ("synthetic_forward", "synthetic_unbounded", "synthetic_object")
# Training images are resized to about this many pixels on their longer side (the CPU budget).
TRAIN_SIDE = 256
# The fit settings of every run, on top of the `fast` preset and the scene-type overlay: a CPU-sized
# fit of a few minutes. The density rate ramps up over the first 30% of the steps and the colour rate
# decays only 10x, because with few steps the preset's schedule leaves the grid opaque at its front and
# the colours barely moved. TV is left to the preset and the scene-type overlay. (Runs before the NDC
# fix set TV to 5e-6 / 5e-5 for every scene; each run's record keeps the overrides it ran with.)
BENCH_FIT = {"resolutions": [64, 128], "steps": [300, 500], "batch_size": 4096, "eval_every": 0,
             "lr_density_delay": 0.3, "lr_density_final": 1.0, "lr_sh": 0.05, "lr_sh_final": 0.005}
ALTERNATIVE = {"forward": {"ndc": "off"}, "unbounded": {"background": "off"}, "object": {"background": "on"}}
# Forward scenes also fit in NDC at this share of the resolutions: the NDC grid reaches past the reference
# image to what every camera sees, so at equal resolutions it holds more cells than the world grid; the
# coarser run shows whether NDC still wins at no more cost.
COARSER = 0.75


def machine() -> dict:
    from bench.fit import machine as fit_machine

    return fit_machine()


# ---- scenes ---------------------------------------------------------------------------------------
def real_scene(name: str, data: Path) -> tuple[dict, Path]:
    """A real scene normalised from the poses it comes with (bench/normalize.py's readers)."""
    from bench.normalize import LOADERS
    from stages.framing.options import SceneOptions
    from stages.framing.scene_frame import normalize_scene

    folder = data / name
    transforms, points = LOADERS[name](folder)
    scene = normalize_scene(transforms, points, SceneOptions(holdout_every=8), poses_dir=folder, path_prefix="")
    return scene, folder


def synthetic_scene(name: str) -> tuple[dict, Path]:
    """A synthetic scene of 40 views at 160x120 (made once under bench/out), normalised as its kind, with
    each view's true near/far depths standing in for the sparse points SfM would give."""
    from stages.common.json_files import read_json
    from stages.capture.synthetic import write_scene
    from stages.framing.options import SceneOptions
    from stages.framing.scene_frame import normalize_scene
    from stages.framing.sightings import Points

    kind = name.removeprefix("synthetic_")
    root = CACHE / name
    if not (root / "transforms.json").is_file():
        write_scene(kind, root, n_views=40, width=160, height=120)
    transforms = read_json(root / "transforms.json")
    views = read_json(root / "ground_truth" / "scene.json")["views"]
    for frame, view in zip(transforms["frames"], views):
        if view["near_depth"] is not None:
            frame["near"], frame["far"] = view["near_depth"], view["far_depth"]
    scene = normalize_scene(transforms, Points.empty(), SceneOptions(scene_type=kind, holdout_every=8),
                            poses_dir=root, path_prefix="")
    return scene, root


# ---- one run --------------------------------------------------------------------------------------
def one_run(name: str, scene: dict, root: Path, label: str, overrides: dict, preset: str) -> tuple[dict, list]:
    """Fits `scene` with the preset, its type's overlay and `overrides`; scores every held-out view.
    Returns the record and the renders of the held-out views (float RGB)."""
    import numpy as np
    import torch

    from pipeline import config
    from pipeline.report import Reporter
    from bench.common import fit_context
    from stages.common.frames import load_frame
    from plenoxels.core.scene_model import SceneModel
    from stages import fit
    from stages.scoring.metrics import image_psnr, image_ssim

    values = config.merge(config.load_preset(preset), config.load_scene_type_overlay(scene["type"], preset),
                          {"fit": overrides})["fit"]
    frames = scene["frames"]
    longest = max(max(int(f["w"]), int(f["h"])) for f in frames)
    values["image_scale"] = min(1.0, TRAIN_SIDE / longest)
    settings = config.build(fit.Settings, "fit", values)
    load = os.getloadavg()
    with fit_context(scene, root, settings, Reporter(quiet=True)) as ctx:
        started = time.time()
        summary = fit.run(ctx)
        wall = time.time() - started
        record = json.loads((ctx.work / "fit.json").read_text())
        model = SceneModel.load(ctx.work)
        psnrs, ssims, renders = [], [], []
        render_started = time.time()
        for frame in [f for f in frames if f.get("split") == "test"]:
            truth, k = load_frame(root, frame, settings.image_scale, settings.background_color)
            with torch.no_grad():
                render = model.render_camera(frame["transform_matrix"], k, photo=frame["name"])["rgb"].numpy()
            psnrs.append(image_psnr(render, truth))
            ssims.append(image_ssim(render, truth))
            renders.append((truth, render))
        render_seconds = time.time() - render_started
    described = record["model"]
    return {
        "scene": name, "type": scene["type"], "label": label, "preset": preset, "overrides": overrides,
        "threads": os.environ.get("OMP_NUM_THREADS"), "load_average_at_start": [round(x, 2) for x in load],
        "fit_frame": described["fit_frame"], "background_model": described["background_model"],
        "psnr": round(float(np.mean(psnrs)), 3), "ssim": round(float(np.mean(ssims)), 4),
        "psnr_per_view": [round(p, 3) for p in psnrs], "held_out_views": len(psnrs),
        "train_images": record["train_images"], "image_size": [k.w, k.h],
        "fit_seconds": record["seconds"], "wall_seconds": round(wall, 1),
        "render_seconds_per_view": round(render_seconds / max(1, len(psnrs)), 3),
        "resolution": described["resolution"], "occupied": described["occupied"],
        "memory_bytes": record["memory_bytes"], "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "summary": summary["line"],
    }, renders


def side_by_side(path: Path, truth, appropriate, alternative) -> None:
    """truth | appropriate model | alternative, with a 4-pixel white gap."""
    import numpy as np

    from stages.common.media import write_png
    from stages.scoring.metrics import to_uint8

    gap = np.ones((truth.shape[0], 4, 3), dtype=np.float32)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_png(path, to_uint8(np.concatenate([truth, gap, appropriate, gap, alternative], axis=1)))


def compare(runs: list[dict]) -> dict:
    """Per scene with both runs: what the scene-appropriate model gains over the alternative."""
    out = {}
    for name in dict.fromkeys(r["scene"] for r in runs):
        by_label = {r["label"]: r for r in runs if r["scene"] == name}
        if {"appropriate", "alternative"} <= by_label.keys():
            a, b = by_label["appropriate"], by_label["alternative"]
            out[name] = {"type": a["type"], "alternative": b["overrides"].get("ndc") and f"ndc={b['overrides']['ndc']}"
                         or f"background={b['overrides'].get('background')}",
                         "psnr_gain_db": round(a["psnr"] - b["psnr"], 3), "ssim_gain": round(a["ssim"] - b["ssim"], 4),
                         "fit_seconds": [a["fit_seconds"], b["fit_seconds"]],
                         "memory_mb": [round(a["memory_bytes"]["total"] / 1e6, 1), round(b["memory_bytes"]["total"] / 1e6, 1)],
                         "background_mb": round(a["memory_bytes"].get("background", 0) / 1e6, 2)}
            if "coarser" in by_label:
                c = by_label["coarser"]
                out[name]["coarser"] = {"resolutions": c["overrides"]["resolutions"],
                                        "psnr_gain_db": round(c["psnr"] - b["psnr"], 3),
                                        "ssim_gain": round(c["ssim"] - b["ssim"], 4), "fit_seconds": c["fit_seconds"],
                                        "memory_mb": round(c["memory_bytes"]["total"] / 1e6, 1)}
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--scenes", nargs="*", default=list(REAL + SYNTHETIC), choices=REAL + SYNTHETIC)
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--only", choices=("appropriate", "alternative", "coarser"), help="run one of the models")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="a fit setting for every run (as --set fit.KEY=VALUE in the CLI)")
    args = parser.parse_args(argv)
    from pipeline import config
    from stages.common.json_files import write_json

    extra = config.parse_overrides([f"fit.{kv}" for kv in args.overrides]).get("fit", {})
    results = {"machine": machine(), "bench_fit": {**BENCH_FIT, **extra}, "train_side": TRAIN_SIDE,
               "preset": args.preset, "runs": []}
    if RESULTS.is_file():
        # Keep earlier runs of scenes not run this time, so the benchmark can be run a scene at a time.
        previous = json.loads(RESULTS.read_text())
        results["runs"] = [r for r in previous.get("runs", []) if r["scene"] not in args.scenes]
    for name in args.scenes:
        scene, root = real_scene(name, args.data) if name in REAL else synthetic_scene(name)
        runs = {}
        labels = [("appropriate", {}), ("alternative", ALTERNATIVE[scene["type"]])]
        if scene["type"] == "forward":
            resolutions = {**BENCH_FIT, **extra}["resolutions"]
            labels.append(("coarser", {"resolutions": [round(COARSER * r) for r in resolutions]}))
        for label, toggles in labels:
            if args.only and label != args.only:
                continue
            record, renders = one_run(name, scene, root, label, {**BENCH_FIT, **extra, **toggles}, args.preset)
            runs[label] = (record, renders)
            results["runs"].append(record)
            results["comparison"] = compare(results["runs"])
            write_json(RESULTS, results)
            print(f"{name} ({scene['type']}) {label} {toggles or ''}: {record['psnr']:.2f} dB, SSIM {record['ssim']:.3f} "
                  f"on {record['held_out_views']} held-out views, fit {record['fit_seconds']:.0f} s, "
                  f"{record['memory_bytes']['total'] / 1e6:.1f} MB", flush=True)
        if scene["type"] in ("unbounded", "forward") and {"appropriate", "alternative"} <= runs.keys():
            truth, with_model = runs["appropriate"][1][0]
            side_by_side(RENDERS / f"{name}.png", truth, with_model, runs["alternative"][1][0][1])
    print(f"wrote {RESULTS.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
