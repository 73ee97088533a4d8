"""Benchmark of the fit: held-out quality against wall time and peak memory, per preset and per single knob.

Scenes: lego from ../shared/data (all 100 train images fitted, the first --val-limit val images held out)
and a synthetic object scene (stages/capture/synthetic.py, 48 views at 400x300, every 8th held out). Each run
is the fit stage as the pipeline runs it (preset, scene-type overlay, overrides), in its own process so
its peak memory (max RSS) is its own. Every run is scored at one size per scene, --eval-scale of the
photos (lego 400x400, the synthetic scene 200x150), whatever size it trained at, so runs of different
image scales compare; PSNR and SSIM are stages/evaluate.py's.

Runs: the presets on both scenes, and each single knob varied alone from a base preset, `fast` on both
(so the sweep stays affordable on a laptop CPU). The knobs: final grid
resolution (0.5x, 0.75x, 1.5x the base's, same total steps), SH degree (0-3), image scale (0.5x, 2x),
steps (0.5x, 2x, every level). --base picks other base presets. The knob "budget" is the time budget's sweep
(fit.time_budget 30 s to 10 min on `default`'s detail), drawn on the same axes as the presets, with a verdict on
each: on or above the presets' front, or which preset beats it in less time.

bench/results/fit.json holds one record per run, keyed by scene, preset, overrides and scoring: a new
run replaces the earlier one with its key, and records whose settings differ from what their preset
and overrides resolve to now (a preset or a default changed) are dropped. bench/results/fit.png plots
them with each scene's Pareto fronts; `--table` prints the README's table.

    .venv/bin/python -m bench.fit                                   # everything: 14 runs per scene
    .venv/bin/python -m bench.fit --scenes synthetic --knobs none   # the presets on one scene
    .venv/bin/python -m bench.fit --list                            # the runs it would do, and exit
    .venv/bin/python -m bench.fit --table                           # the results as a Markdown table (and replot)
    .venv/bin/python -m bench.fit ... --set key=value               # a fit setting for every run (and the base)
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from plenoxels.core.errors import UserError  # noqa: E402

RESULTS = REPO / "bench" / "results" / "fit.json"
CACHE = REPO / "bench" / "out"
SCENES = ("lego", "synthetic")
PRESETS = ("fast", "balanced", "default", "quality")
SWEEP_BASE = {"lego": "fast", "synthetic": "fast"}
KNOBS = ("resolution", "sh", "image_scale", "steps", "budget")
# The time budget's sweep (knob "budget"): fit.time_budget on the preset whose detail the budget plans from (its
# SH degree and image scale; the budget picks levels, resolutions and steps), beside the presets' front.
BUDGETS = ("30s", "1m", "2m", "5m", "10m")
BUDGET_BASE = "default"
SYNTHETIC = {"kind": "object", "n_views": 48, "width": 400, "height": 300, "holdout_every": 8}


def machine() -> dict:
    """The CPU (model name, and family/model numbers where the name is as vague as "AMD EPYC"), cores, memory."""
    info = {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            info.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    memory_gb = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    return {"cpu": info.get("model name", platform.processor()), "cpu_family": info.get("cpu family"),
            "cpu_model": info.get("model"), "virtual_machine": "hypervisor" in info.get("flags", "").split(),
            "cores": os.cpu_count(), "memory_gb": memory_gb, "python": platform.python_version()}


# ---- scenes ---------------------------------------------------------------------------------------
def load_scene(name: str, data: Path, val_limit: int | None) -> tuple[dict, Path]:
    """A scene.json (frames split "train"/"test") and the folder its image paths resolve against."""
    if name == "lego":
        from bench.cuda import lego_scene

        if not (data / "lego" / "transforms_train.json").is_file():
            raise UserError(f"no lego scene under {data / 'lego'}; pass --data (the folder that holds lego/)")
        scene, _ = lego_scene(data / "lego", val_limit)
        return scene, data / "lego"
    return synthetic_scene()


def synthetic_scene() -> tuple[dict, Path]:
    """The synthetic object scene, rendered once and kept under bench/out."""
    from stages.common.json_files import read_json
    from stages.capture.synthetic import write_scene
    from stages.framing.options import SceneOptions
    from stages.framing.scene_frame import normalize_scene
    from stages.framing.sightings import Points

    s = SYNTHETIC
    root = CACHE / f"synthetic_{s['kind']}_{s['n_views']}_{s['width']}x{s['height']}"
    if not (root / "transforms.json").is_file():
        write_scene(s["kind"], root, n_views=s["n_views"], width=s["width"], height=s["height"])
    scene = normalize_scene(read_json(root / "transforms.json"), Points.empty(),
                            SceneOptions(scene_type=s["kind"], holdout_every=s["holdout_every"]), poses_dir=root,
                            path_prefix="")
    return scene, root


# ---- what runs ------------------------------------------------------------------------------------
def resolve(preset: str, scene_type: str, overrides: dict):
    """The fit Settings of a run: preset, then the scene type's overlay, then the run's overrides."""
    from pipeline import config
    from stages import fit

    values = config.merge(config.load_preset(preset), config.load_scene_type_overlay(scene_type, preset),
                          {"fit": overrides}).get("fit", {})
    return config.build(fit.Settings, "fit", values)


def knob_variants(base) -> list[tuple[str, str, dict]]:
    """(knob, short label, overrides) for each single knob varied alone from the `base` Settings."""
    variants = []
    final, total = base.resolutions[-1], base.total_steps
    for factor in (0.5, 0.75, 1.5):
        res = max(8, round(final * factor))
        kept = [i for i in range(len(base.resolutions) - 1) if base.resolutions[i] < res]
        steps = [base.steps[i] for i in kept]
        variants.append(("resolution", f"res {res}", {"resolutions": [base.resolutions[i] for i in kept] + [res],
                                                      "steps": steps + [total - sum(steps)]}))
    for degree in range(4):
        if degree != base.sh_degree:
            variants.append(("sh", f"SH {degree}", {"sh_degree": degree}))
    for factor in (0.5, 2.0):
        scale = round(base.image_scale * factor, 4)
        if scale <= 1:
            variants.append(("image_scale", f"image scale {scale:g}", {"image_scale": scale}))
    for factor in (0.5, 2.0):
        steps = [max(1, round(n * factor)) for n in base.steps]
        variants.append(("steps", f"{sum(steps)} steps", {"steps": steps}))
    return variants


def run_key(scene: str, preset: str, overrides: dict, scoring: dict) -> str:
    return json.dumps([scene, preset, overrides, scoring], sort_keys=True)


def plan(args, common: dict) -> list[dict]:
    """The runs asked for, each a spec for one_run."""
    from pipeline import config

    scene_type = {"lego": "object", "synthetic": SYNTHETIC["kind"]}
    specs = []

    def add(scene, preset, knob, label, overrides):
        settings = resolve(preset, scene_type[scene], overrides)
        scoring = {"eval_scale": args.eval_scale, "val_limit": args.val_limit if scene == "lego" else None}
        specs.append({"scene": scene, "scene_type": scene_type[scene], "preset": preset, "knob": knob,
                      "label": label, "common": common, "overrides": overrides, "scoring": scoring,
                      "settings": json.loads(json.dumps(config.to_dict(settings))),
                      "key": run_key(scene, preset, overrides, scoring)})
        return settings

    for scene in args.scenes:
        for preset in args.presets:
            add(scene, preset, None, preset, dict(common))
        if args.knobs:
            base_preset = args.base[scene]
            base = resolve(base_preset, scene_type[scene], common)
            for knob, label, variant in knob_variants(base):
                if knob in args.knobs:
                    add(scene, base_preset, knob, f"{base_preset}, {label}", {**common, **variant})
        if "budget" in args.knobs:
            for budget in args.budgets:
                add(scene, BUDGET_BASE, "budget", f"{BUDGET_BASE}, budget {budget}", {**common, "time_budget": budget})
    return specs


# ---- one run, in its own process ------------------------------------------------------------------
def one_run(spec: dict) -> dict:
    """Fits the spec's scene with its settings and scores every held-out view at the scoring size."""
    import numpy as np
    import torch

    from bench.common import budget_of, fitted
    from stages.common.frames import load_frame
    from stages.scoring.metrics import image_psnr, image_ssim

    scene, root = load_scene(spec["scene"], Path(spec["data"]), spec["scoring"]["val_limit"])
    settings = resolve(spec["preset"], spec["scene_type"], spec["overrides"])
    summary, wall, record, model = fitted(scene, root, settings, quiet=not spec.get("verbose"))
    psnrs, ssims = [], []
    render_started = time.time()
    for frame in [f for f in scene["frames"] if f.get("split") == "test"]:
        truth, k = load_frame(root, frame, spec["scoring"]["eval_scale"], settings.background_color)
        with torch.no_grad():
            render = model.render_camera(frame["transform_matrix"], k, photo=frame["name"])["rgb"].numpy()
        psnrs.append(image_psnr(render, truth))
        ssims.append(image_ssim(render, truth))
    render_seconds = time.time() - render_started
    return {
        "psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims)), "held_out_views": len(psnrs),
        "eval_size": [k.w, k.h], "train_images": record["train_images"], "train_pixels": record["train_pixels"],
        "fit_seconds": record["seconds"], "wall_seconds": round(wall, 1),
        "render_seconds_per_view": round(render_seconds / max(1, len(psnrs)), 3),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "resolution": record["model"]["resolution"], "occupied": record["model"]["occupied"],
        "model_bytes": record["memory_bytes"]["total"], "history": record["history"], "levels": record["levels"],
        "summary": summary["line"],
        **budget_of(record),
    }


def spawn(spec: dict) -> dict | None:
    """Runs one_run in a child process; None (after saying so) if it failed."""
    load_before = os.getloadavg()
    started = time.time()
    from bench.common import recorded, run_child

    result = run_child("bench.fit", spec, f"{spec['scene']} {spec['label']}")
    if result is None:
        return None
    keep = ("key", "scene", "scene_type", "preset", "knob", "label", "common", "overrides", "scoring", "settings")
    return {**{k: spec[k] for k in keep}, "recorded": recorded(), **result,
            "process_seconds": round(time.time() - started, 1),
            "threads": os.environ.get("OMP_NUM_THREADS"),
            "load_average": {"before": [round(x, 2) for x in load_before],
                             "after": [round(x, 2) for x in os.getloadavg()]},
            "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")}


# ---- results --------------------------------------------------------------------------------------
# The background model's settings: they change nothing in a fit without one.
BACKGROUND_SETTINGS = ("background_spheres", "background_width", "background_texel_px", "lr_background", "tv_background")


def still_valid(run: dict) -> bool:
    """Whether a stored run's settings are what its preset and overrides give today. A setting added since the run
    counts as the same when it sits at its default, and the background model's settings do not count for a fit
    without one. (Most new settings' defaults keep the behaviour of the runs recorded without them;
    fit.prune_rays_per_cell's does not, and each run's `recorded` says the date and commit it was measured at.)"""
    from pipeline import config
    from stages import fit

    if not all(k in run for k in ("key", "scene_type", "settings")):
        return False
    try:
        settings = resolve(run["preset"], run["scene_type"], run["overrides"])
    except UserError:
        return False
    now = json.loads(json.dumps(config.to_dict(settings)))
    defaults = json.loads(json.dumps(config.to_dict(fit.Settings())))
    stored = run["settings"]
    has_background = settings.background == "on" or (settings.background == "auto" and run["scene_type"] == "unbounded")
    return all(stored.get(k, defaults[k]) == v for k, v in now.items()
               if has_background or k not in BACKGROUND_SETTINGS) and set(stored) <= set(now)


def load_results(path: Path, fresh: bool) -> dict:
    results = json.loads(path.read_text()) if path.is_file() and not fresh else {}
    runs = results.get("runs", [])
    valid = [r for r in runs if still_valid(r)]
    if len(valid) < len(runs):
        print(f"  dropped {len(runs) - len(valid)} earlier run(s) of {path.name} whose settings or format are "
              "out of date", flush=True)
    results["runs"] = valid
    return results


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats on both cost (lower) and quality (higher), by cost."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], float("-inf")
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


COSTS = (("wall_seconds", "fit wall time (s)"), ("peak_rss_mb", "peak memory, max RSS (MiB)"))
METRICS = ("psnr", "ssim")


def series(run: dict) -> str:
    """The runs that can share a front: one scene scored at one size (PSNR at 200 px and at 400 px don't compare)."""
    w, h = run["eval_size"]
    return f"{run['scene']} {w}x{h}"


def fronts(runs: list[dict]) -> dict[tuple[str, str, str], set[str]]:
    """(series, metric, cost) -> keys of the runs on that Pareto front."""
    out = {}
    for name in {series(r) for r in runs}:
        mine = [r for r in runs if series(r) == name]
        for metric in METRICS:
            for cost, _ in COSTS:
                front = pareto([(r[cost], r[metric]) for r in mine])
                out[name, metric, cost] = {mine[i]["key"] for i in front}
    return out


def short_label(run: dict) -> str:
    """The plot's label: the knob's variant alone (its base preset is the scene's sweep base)."""
    return run["label"].split(", ", 1)[1] if run["knob"] else run["label"]


def plot(runs: list[dict], path: Path, machine_line: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    on_front = fronts(runs)
    fig, axes = plt.subplots(2, 2, figsize=(13, 10))
    for row, metric in enumerate(METRICS):
        for col, (cost, cost_label) in enumerate(COSTS):
            ax = axes[row, col]
            for scene in sorted({series(r) for r in runs}):
                mine = sorted((r for r in runs if series(r) == scene), key=lambda r: r[cost])
                presets = [r for r in mine if not r["knob"]]
                knobs = [r for r in mine if r["knob"] and r["knob"] != "budget"]
                budgets = [r for r in mine if r["knob"] == "budget"]
                dots = ax.scatter([r[cost] for r in presets], [r[metric] for r in presets], marker="s", s=50,
                                  label=f"{scene}: presets")
                colour = dots.get_facecolor()[0]
                if knobs:
                    bases = "/".join(sorted({r["preset"] for r in knobs}))
                    ax.scatter([r[cost] for r in knobs], [r[metric] for r in knobs], marker="o", s=22,
                               color=colour, alpha=0.6, label=f"{scene}: one knob from {bases}")
                if budgets:
                    ax.plot([r[cost] for r in budgets], [r[metric] for r in budgets], "-^", color=colour,
                            markersize=8, linewidth=1.5, label=f"{scene}: time budgets on {BUDGET_BASE}")
                front = [r for r in mine if r["key"] in on_front[scene, metric, cost]]
                ax.plot([r[cost] for r in front], [r[metric] for r in front], "--", color=colour, linewidth=1)
                ax.scatter([r[cost] for r in front], [r[metric] for r in front], s=140, facecolors="none",
                           edgecolors=colour, linewidths=1.2)
                for r in mine:
                    ax.annotate(short_label(r), (r[cost], r[metric]), fontsize=7, xytext=(4, 3),
                                textcoords="offset points")
            if cost == "wall_seconds":
                ax.set_xscale("log")
                plain = matplotlib.ticker.FuncFormatter(lambda x, _: f"{x:g}")
                ax.xaxis.set_major_formatter(plain)
                ax.xaxis.set_minor_formatter(plain)
                cost_label += ", log scale"
            ax.set_xlabel(cost_label)
            ax.set_ylabel("held-out " + ("PSNR (dB)" if metric == "psnr" else "SSIM"))
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=7)
    fig.suptitle("fit: held-out quality against cost, one point per run (circled and dashed: Pareto front)\n"
                 + machine_line, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def budget_verdict(run: dict, runs: list[dict]) -> str:
    """Where a time budget's run stands against the presets' runs of its series (PSNR against fit wall time): on
    or above their front when no preset reached a higher PSNR in as little time."""
    presets = [r for r in runs if not r["knob"] and series(r) == series(run) and r["common"] == run["common"]]
    if not presets:
        return "no preset run to compare with"
    faster = [r for r in presets if r["wall_seconds"] <= run["wall_seconds"] and r["psnr"] > run["psnr"]]
    if not faster:
        return "on or above the presets' front"
    best = max(faster, key=lambda r: r["psnr"])
    return f"below {best['label']} ({best['psnr']:.2f} dB in {best['wall_seconds']:.0f} s)"


def cpu_name(m: dict) -> str:
    family = f" (family {m['cpu_family']} model {m['cpu_model']})" if m.get("cpu_family") else ""
    return f"{m.get('cpu', '?')}{family}{', virtual machine' if m.get('virtual_machine') else ''}"


def machine_line(results: dict) -> str:
    m = results.get("machine", {})
    runs = results.get("runs", [])
    loads = [x for r in runs for x in (r["load_average"]["before"][0], r["load_average"]["after"][0])]
    threads = sorted({str(r.get("threads")) for r in runs})
    line = f"{cpu_name(m)}, {m.get('cores', '?')} cores, OMP_NUM_THREADS {'/'.join(threads)}"
    if loads:
        line += f", 1-min load average {min(loads):.1f}-{max(loads):.1f} around the runs"
    settings = {json.dumps(r.get("common") or {}) for r in runs}
    common = sorted(settings - {"{}"})
    if common:
        line += ("; some runs also set " if "{}" in settings else "; every run also set ") + " or ".join(common)
    return line


def table(results: dict) -> str:
    """The runs as a Markdown table, scene by scene, presets first."""
    runs = results.get("runs", [])
    on_front = fronts(runs)
    lines = [f"Machine: {machine_line(results)}.", "",
             "| scene | run | held-out PSNR | SSIM | fit wall time | peak memory | model | final grid | "
             "Pareto (PSNR vs time / memory) |",
             "|---|---|---|---|---|---|---|---|---|"]
    order = {name: i for i, name in enumerate(SCENES)}
    for r in sorted(runs, key=lambda r: (order.get(r["scene"], 9), r["knob"] is not None, r["knob"] or "",
                                         r["wall_seconds"])):
        marks = ["yes" if r["key"] in on_front[series(r), "psnr", cost] else "-" for cost, _ in COSTS]
        if r["knob"] == "budget":
            marks[0] += f" ({budget_verdict(r, runs)})"
        w, h = r["eval_size"]
        seconds = f"{r['wall_seconds']:.{0 if r['wall_seconds'] >= 10 else 1}f}"
        lines.append(f"| {r['scene']} ({w}x{h}, {r['held_out_views']} views) | {r['label']} | {r['psnr']:.2f} dB | "
                     f"{r['ssim']:.3f} | {seconds} s | {r['peak_rss_mb']:.0f} MiB | {r['model_bytes'] / 2**20:.0f} MiB | "
                     f"{max(r['resolution'])}³, {r['occupied'] / 1e6:.2f}M voxels | {' / '.join(marks)} |")
    return "\n".join(lines)


# ---- main -----------------------------------------------------------------------------------------
def parse_list(text: str, allowed: tuple[str, ...], what: str) -> list[str]:
    if text in ("", "none"):
        return []
    if text == "all":
        return list(allowed)
    items = [t.strip() for t in text.split(",") if t.strip()]
    for item in items:
        if item not in allowed:
            raise UserError(f"unknown {what} '{item}'; choose from {', '.join(allowed)} (comma-separated), all or none")
    return items


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--scenes", default="lego,synthetic", help=f"comma-separated: {', '.join(SCENES)}")
    parser.add_argument("--presets", default="fast,balanced,default,quality", help="comma-separated presets, or none")
    parser.add_argument("--knobs", default="all", help=f"knobs to sweep: {', '.join(KNOBS)}, all or none")
    parser.add_argument("--base", default=",".join(f"{k}={v}" for k, v in SWEEP_BASE.items()),
                        help="the preset each scene's knobs are varied from, as scene=preset,...")
    parser.add_argument("--budgets", default=",".join(BUDGETS), help="the knob budget's time budgets, comma-separated")
    parser.add_argument("--eval-scale", type=float, default=0.5, help="score held-out views at this share of the photos")
    parser.add_argument("--val-limit", type=int, default=25, help="score the first N lego val views")
    parser.add_argument("--set", action="append", default=[], help="key=value (a fit setting) for every run")
    parser.add_argument("--results", type=Path, default=RESULTS, help="the JSON to update (the PNG goes beside it)")
    parser.add_argument("--fresh", action="store_true", help="drop the earlier runs in --results")
    parser.add_argument("--list", action="store_true", help="print the runs and exit")
    parser.add_argument("--table", action="store_true",
                        help="print --results as a Markdown table, redraw its plot, and exit")
    parser.add_argument("--verbose", action="store_true", help="show each fit's progress")
    args = parser.parse_args(argv)
    from bench.common import run_part

    return run_part(args, one_run, sweep)


def sweep(args) -> int:
    from pipeline import config

    if args.table:
        if not args.results.is_file():
            raise UserError(f"no results at {args.results}; run the benchmark first")
        results = json.loads(args.results.read_text())
        print(table(results))
        if results.get("runs"):
            plot(results["runs"], args.results.with_suffix(".png"), machine_line(results))
        return 0
    if not 0 < args.eval_scale <= 1:
        raise UserError("--eval-scale must be in (0, 1]")
    args.scenes = parse_list(args.scenes, SCENES, "scene")
    args.presets = parse_list(args.presets, tuple(config.preset_names()), "preset")
    args.knobs = parse_list(args.knobs, KNOBS, "knob")
    args.budgets = [b.strip() for b in args.budgets.split(",") if b.strip()]
    from stages.common.text import parse_duration

    for budget in args.budgets:
        parse_duration(budget, "--budgets")  # a bad one stops here, not in a child
    bases = dict(SWEEP_BASE)
    for item in args.base.split(","):
        scene, _, preset = item.partition("=")
        if scene not in SCENES or preset not in config.preset_names():
            raise UserError(f"--base '{item}' must be scene=preset with a scene of {', '.join(SCENES)} "
                            f"and a preset of {', '.join(config.preset_names())}")
        bases[scene] = preset
    args.base = bases
    from bench.common import fit_overrides

    common = fit_overrides(args.set)
    specs = plan(args, common)
    if args.list:
        for spec in specs:
            print(f"  {spec['scene']:<9} {spec['label']:<40} {json.dumps(spec['overrides'])}")
        print(f"{len(specs)} runs")
        return 0
    if "lego" in args.scenes:
        load_scene("lego", args.data, args.val_limit)  # a missing folder stops here, not in every child
    if "synthetic" in args.scenes:
        synthetic_scene()  # rendered once, before the children need it

    results = load_results(args.results, args.fresh)
    results["machine"] = machine()
    plot_path = args.results.with_suffix(".png")
    failed = 0
    for n, spec in enumerate(specs, 1):
        print(f"[{n}/{len(specs)}] {spec['scene']} {spec['label']}", flush=True)
        result = spawn({**spec, "data": str(args.data), "verbose": args.verbose})
        if result is None:
            failed += 1
            continue
        print(f"  {result['psnr']:6.2f} dB  SSIM {result['ssim']:.3f}  wall {result['wall_seconds']:7.1f} s  "
              f"peak {result['peak_rss_mb']:6.0f} MiB  ({result['summary']})", flush=True)
        results["runs"] = [r for r in results["runs"] if r["key"] != result["key"]] + [result]
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text(json.dumps(results, indent=1) + "\n")
        plot(results["runs"], plot_path, machine_line(results))
    if results["runs"]:
        print(table(results))
        print(f"wrote {args.results} and {plot_path}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
