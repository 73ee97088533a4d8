"""Real captures at every preset: fox, cup, fern, the synthetic unbounded scene and room, and two phone captures
(ball: 127 frames of a portrait video with their own poses; apple: a 5 s clip, posed by SfM from the frames ingest
keeps), with all their photos and with a quarter of them, scored on the same held-out views.

Each scene goes through the pipeline as a user's folder would (ingest at the preset's size, poses imported from the
files beside the photos, with points triangulated when they bring none, normalize), cached under
bench/out/real_scenes/<scene>-<preset>/. Then each run fits the normalised scene with the preset (and the scene type's
overlay), in a process of its own (its peak memory is its own), on all the training photos or on every 4th of them
(`quarter`: the few-views case), and scores every held-out view (normalize's every 8th photo) with PSNR and SSIM, as
the evaluate stage does, at one size whatever the preset: the photo with its longest side --score-side pixels (the
presets ingest and fit photos of different sizes, and PSNRs at two sizes do not compare; 320, about `fast`'s fit
photos, so the comparison never favours the larger ones). The first held-out view is written beside its truth to
bench/out/real_scenes/renders/<scene>-<preset>-<views>.png (not committed: 0.3 MB each, one a run).

The synthetic scenes (stages/capture/synthetic.py) are 40 views at 320x240, written under bench/out/ with their true
poses as a transforms.json: `synthetic_unbounded`, an object on an endless textured ground inside a textured sphere;
`synthetic_room`, the object on the floor of a closed textured room, seen from inside it (what a phone video of a thing
on a floor sees); `synthetic_room_passers_by`, the same room with a person walking through 40% of its training views
(in each somewhere else; its held-out views clean), which no one scene explains. Real captures with people painted into
them the same way (`paint_passers_by`; ground_truth/passers_by/ holds each person): `fox_passers_by`, a person close by
in 20% of fox's training photos; `fox_far_passers_by`, a small one farther off in 60% of them; `ball_far_passers_by`,
small ones in 60% of ball's 111 (a capture of many photos, whose error map's blocks are coarser).

    .venv/bin/python -m bench.real_scenes                                     # every scene, preset and view count
    .venv/bin/python -m bench.real_scenes --scenes fox --presets fast --views all quarter
    .venv/bin/python -m bench.real_scenes --set tv_density=1e-9 --label tv10  # a variant, kept beside the others
    .venv/bin/python -m bench.real_scenes --table
    .venv/bin/python -m bench.real_scenes --scenes fox --presets default --views all --budgets 30s 1m 2m 5m 10m
    .venv/bin/python -m bench.real_scenes --scenes ball --presets default --views all --budgets 1m 5m --label "colour off" --set photo_colour=false
    .venv/bin/python -m bench.real_scenes --scenes ball apple --presets fast --views all --models auto contracted background

With --models each run is the fit's own choice of scene model (auto: where normalize's measures are not clear-cut, a
trial on a coarse level, plenoxels/planning/model_trial.py) or one model forced (labelled with the model's name); each run
records the model fitted and the trial's record, and the CPU seconds of the fit stage (its trial included) beside its
wall time, which on a machine other jobs share measures the cost better.

Each run records the date and the commit it measured (`recorded`) and the machine it ran on (`machine`; the
document's own `machine` is the newest run's); a sweep's runs are labelled with them unless
--label names the sweep. With --budgets each run is the preset's detail under fit.time_budget (labelled "budget 30s",
..., or "<label> budget 30s": two sweeps in one run, each a curve, such as the product as it is and with a setting
off); --table then says for each where it stands against the presets' runs labelled --front (one label or several, as
scenes benched on different days have their own; by default each scene's newest preset runs), and
bench/results/real_scenes_budget.png draws them on the axes of the presets' Pareto plot (held-out PSNR against fit
time).

    .venv/bin/python -m bench.real_scenes --table --front "2026-11-26 94122cf" "2026-11-27 78d33b1"
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from plenoxels.core.errors import UserError  # noqa: E402
from plenoxels.planning.model_trial import MODELS  # noqa: E402

RESULTS = REPO / "bench" / "results" / "real_scenes.json"
CACHE = REPO / "bench" / "out" / "real_scenes"
RENDERS = CACHE / "renders"
SCENES = ("fox", "cup", "fern", "synthetic_unbounded", "synthetic_room", "synthetic_room_passers_by", "ball", "apple",
          "fox_passers_by", "fox_far_passers_by", "ball_far_passers_by")
# The synthetic scenes: their kind, and the share of their views a person walks through (never a held-out one).
SYNTHETIC = {"synthetic_unbounded": ("unbounded", 0.0), "synthetic_room": ("room", 0.0),
             "synthetic_room_passers_by": ("room", 0.4)}
# Real scenes with people painted into them: the scene, the share of its training photos, the person's size.
PAINTED = {"fox_passers_by": ("fox", 0.2, 1.0), "fox_far_passers_by": ("fox", 0.6, 0.3),
           "ball_far_passers_by": ("ball", 0.6, 0.3)}
# Scenes given as one file (a phone's video) rather than a folder of photos.
FILES = {"apple": "apple.mp4"}
PRESETS = ("fast", "balanced", "default", "quality")
SCORE_SIDE = 320
VIEWS = {"all": 1, "quarter": 4}
# --aligned: each held-out view scored again with its colour fitted, its pose aligned, both (bench/pose_alignment.py).
ALIGNED = ("regained", "aligned", "aligned_regained")
# --models: the fit's own choice, or each scene model forced (plenoxels/planning/model_trial.py MODELS).
MODEL_FLAGS = {"auto": None, "ndc": "ndc", "contracted": "contracted", "background": "bounded + background",
               "bounded": "bounded"}


def scene_folder(name: str, data: Path) -> Path:
    """The photo folder the pipeline is pointed at (a dataset folder for the real scenes)."""
    if name in PAINTED:
        from stages.capture.synthetic import paint_passers_by

        source, share, size = PAINTED[name]
        folder = CACHE / f"{name}-photos"
        if not (folder / "ground_truth" / "passers_by").is_dir():  # painted whole, or not there
            copy = folder.with_name(folder.name + ".tmp")
            shutil.rmtree(copy, ignore_errors=True)
            shutil.copytree(scene_folder(source, data), copy)
            paint_passers_by(copy, share, size)
            shutil.rmtree(folder, ignore_errors=True)
            copy.rename(folder)
        return folder
    if not name.startswith("synthetic_"):
        folder = data / name
        if not folder.is_dir():
            raise UserError(f"no {name} scene under {data}; pass --data (the folder that holds {name}/)")
        return folder / FILES[name] if name in FILES else folder
    from stages.capture.synthetic import write_scene

    folder = CACHE / f"{name}-photos"
    if not (folder / "transforms.json").is_file():
        kind, passers_by = SYNTHETIC[name]
        write_scene(kind, folder, n_views=40, width=320, height=240, passers_by=passers_by)
    return folder


def prepared(name: str, preset: str, data: Path) -> Path:
    """The pipeline's output folder for the scene with its stages up to normalize done."""
    from pipeline.report import Reporter
    from pipeline.runner import Pipeline

    out = CACHE / f"{name}-{preset}"
    Pipeline(scene_folder(name, data), out, preset=preset, reporter=Reporter(quiet=True)).run(["normalize"])
    return out


def with_views(scene: dict, every: int) -> dict:
    """The scene with every `every`-th training frame kept (held-out frames unchanged)."""
    train = [f for f in scene["frames"] if f["split"] == "train"]
    kept = {id(f) for f in train[::every]}
    return {**scene, "frames": [f for f in scene["frames"] if f["split"] != "train" or id(f) in kept]}


def one_run(spec: dict) -> dict:
    import numpy as np
    import torch

    from bench.common import budget_of, fitted
    from bench.fit import resolve
    from bench.pose_alignment import aligned_scores
    from stages.common.frames import load_frame
    from stages.common.media import write_png
    from stages.scoring.metrics import image_scores, mean_scores, to_uint8

    out = Path(spec["out"])
    scene = with_views(json.loads((out / "normalize" / "scene.json").read_text()), VIEWS[spec["views"]])
    settings = resolve(spec["preset"], scene["type"], spec["overrides"])
    load_before = os.getloadavg()[0]
    cpu_before = _cpu_seconds()
    summary, wall, record, model = fitted(scene, out, settings, quiet=not spec.get("verbose"))
    cpu = _cpu_seconds() - cpu_before
    views, first, fit_size = [], None, None
    for frame in [f for f in scene["frames"] if f["split"] == "test"]:
        fit_size = [round(frame["w"] * settings.image_scale), round(frame["h"] * settings.image_scale)]
        scale = spec["score_side"] / max(frame["w"], frame["h"]) if spec.get("score_side") else settings.image_scale
        truth, k = load_frame(out, frame, scale, settings.background_color)
        with torch.no_grad():
            render = model.render_camera(np.asarray(frame["transform_matrix"]), k, backdrop=frame.get("backdrop"),
                                       photo=frame["name"])["rgb"].numpy()
        views.append({"name": frame["name"], **image_scores(render, truth, with_lpips=False)})
        if spec.get("aligned"):
            views[-1].update(aligned_scores(model, frame, k, truth, render))
        first = first if first is not None else (truth, render)
    RENDERS.mkdir(parents=True, exist_ok=True)
    gap = np.ones((first[0].shape[0], 4, 3), dtype=np.float32)
    write_png(RENDERS / f"{spec['scene']}-{spec['preset']}-{spec['views']}{spec['label_suffix']}.png",
              to_uint8(np.concatenate([first[0], gap, first[1]], axis=1)))
    return {"scene": spec["scene"], "preset": spec["preset"], "views": spec["views"], "label": spec["label"],
            "recorded": spec["recorded"], "overrides": spec["overrides"], "type": scene["type"],
            "mean": mean_scores(views), "held_out": views,
            **{f"mean_{key}": mean_scores([v[key] for v in views]) for key in ALIGNED if spec.get("aligned")},
            "train_images": record["train_images"], "image_size": fit_size, "score_size": [k.w, k.h],
            "fit_seconds": record["seconds"], "wall_seconds": round(wall, 1), "cpu_seconds": round(cpu, 1),
            "scene_model": record.get("scene_model"), "model_choice": record.get("model_choice"),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
            "load_average": [round(load_before, 2), round(os.getloadavg()[0], 2)],
            "threads": os.environ.get("OMP_NUM_THREADS"), "regularisation": record.get("regularisation"),
            "background_cost": record.get("background_cost"), "resolution": record["model"]["resolution"],
            "occupied": record["model"]["occupied"], "summary": summary["line"], **budget_of(record)}


def _cpu_seconds() -> float:
    """CPU seconds this process has used (its threads together): a fit's cost on a machine other jobs share."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def spawn(spec: dict) -> dict | None:
    from bench.common import run_child

    return run_child("bench.real_scenes", spec, f"{spec['scene']} {spec['preset']} {spec['views']}")


def is_budget(run: dict) -> bool:
    return "time_budget" in run["overrides"]


def budget_label(budget: str, sweep: str = "") -> str:
    """The label of a budget sweep's run: "budget 2m", or "<sweep> budget 2m" for a sweep --label names (its runs are
    drawn as a curve of their own, beside the others in the same run)."""
    return f"{sweep} budget {budget}".strip()


def sweep_of(run: dict) -> str | None:
    """The name of the budget sweep a run belongs to ("" for the unnamed one; None for a run under no budget, or a
    probe under one whose label is its own)."""
    if not is_budget(run):
        return None
    suffix = budget_label(run["overrides"]["time_budget"])
    return run["label"][:-len(suffix)].strip() if run["label"].endswith(suffix) else None


def newest_front(runs: list[dict]) -> list[str]:
    """The labels of each scene's newest sweep of the presets as set (labelled by its date and commit alone, no
    overrides; a run replaces its same-labelled one at the end of the file): what a budget is compared with when
    --front names none."""
    newest = {(r["scene"], r["views"]): r["label"] for r in runs
              if not r["overrides"] and r["label"] == r.get("recorded")}
    return sorted(set(newest.values()))


def front_runs(run: dict, runs: list[dict], front: list[str]) -> list[dict]:
    """The preset runs a budget run is compared with: its scene, photos and scoring size (PSNRs at two sizes do not
    compare; runs before --score-side were scored at their fit's size), labelled one of `front`, no overrides."""
    return [r for r in runs if (r["scene"], r["views"]) == (run["scene"], run["views"]) and r["label"] in front
            and scored_size(r) == scored_size(run) and not r["overrides"]]


def scored_size(run: dict) -> list[int]:
    return run.get("score_size", run["image_size"])


def budget_verdict(run: dict, runs: list[dict], front: list[str]) -> str:
    """On or above the presets' front when no preset run reached a higher PSNR in as little fitting time."""
    presets = front_runs(run, runs, front)
    if not presets:
        return f"no preset run labelled {' or '.join(repr(f) for f in front)} to compare with"
    faster = [r for r in presets if r["fit_seconds"] <= run["fit_seconds"] and r["mean"]["psnr"] > run["mean"]["psnr"]]
    if not faster:
        return "on or above the presets' front"
    best = max(faster, key=lambda r: r["mean"]["psnr"])
    return f"below {best['preset']} ({best['mean']['psnr']:.2f} dB in {best['fit_seconds']:.0f} s)"


def table(results: dict, front: list[str]) -> str:
    lines = ["| scene | preset | photos | run | held-out PSNR | SSIM | fit time | peak memory | background's share |",
             "|---|---|---|---|---|---|---|---|---|"]
    runs = results.get("runs", [])
    for r in runs:
        share = (r.get("background_cost") or {}).get("share_of_fitting")
        label = f"{r['label']}: {budget_verdict(r, runs, front)}" if is_budget(r) else r["label"]
        lines.append(f"| {r['scene']} | {r['preset']} | {r['views']} ({r['train_images']} train) | {label} | "
                     f"{r['mean']['psnr']:.2f} dB | {r['mean']['ssim']:.3f} | {r['fit_seconds']:.0f} s | "
                     f"{r['peak_rss_mb'] / 1024:.1f} GiB | {'-' if share is None else f'{share:.0%}'} |")
    return "\n".join(lines)


def plot_budgets(results: dict, front: list[str], path: Path, sweeps: tuple[str, ...] = ()) -> None:
    """Held-out PSNR against fit time: each scene's preset runs with their Pareto front, and its budget sweep (the runs
    labelled "budget ..."), with the sweeps named in `sweeps` ("<sweep> budget ..."); the other sweeps and probes of
    other settings under a budget stay in the table."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bench.fit import pareto

    runs = results.get("runs", [])
    budgets = [r for r in runs if sweep_of(r) is not None and sweep_of(r) in ("", *sweeps)]
    groups = sorted({(r["scene"], r["views"], sweep_of(r)) for r in budgets})
    if not groups:
        return
    fig, ax = plt.subplots(figsize=(8, 6))
    for scene, views, sweep in groups:
        mine = sorted((r for r in budgets if (r["scene"], r["views"], sweep_of(r)) == (scene, views, sweep)),
                      key=lambda r: r["fit_seconds"])
        presets = sorted(front_runs(mine[0], runs, front), key=lambda r: r["fit_seconds"])
        line, = ax.plot([r["fit_seconds"] for r in mine], [r["mean"]["psnr"] for r in mine], "-^", markersize=8,
                        label=f"{scene} ({views} photos): {sweep or 'time budgets'} on {mine[0]['preset']}")
        for r in mine:
            ax.annotate(r["overrides"]["time_budget"], (r["fit_seconds"], r["mean"]["psnr"]), fontsize=7,
                        xytext=(4, -10), textcoords="offset points")
        if presets and not any(g[:2] == (scene, views) for g in groups[:groups.index((scene, views, sweep))]):
            points = [(r["fit_seconds"], r["mean"]["psnr"]) for r in presets]
            on_front = [presets[i] for i in pareto(points)]
            ax.scatter(*zip(*points), marker="s", s=50, color=line.get_color(), label=f"{scene}: presets")
            ax.plot([r["fit_seconds"] for r in on_front], [r["mean"]["psnr"] for r in on_front], "--",
                    color=line.get_color(), linewidth=1)
            for r in presets:
                ax.annotate(r["preset"], (r["fit_seconds"], r["mean"]["psnr"]), fontsize=7, xytext=(4, 3),
                            textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("fit time (s), log scale")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title("real captures: the time budget against the presets (dashed: the presets' Pareto front)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    parser.add_argument("--presets", nargs="+", default=list(PRESETS), choices=PRESETS)
    parser.add_argument("--views", nargs="+", default=list(VIEWS), choices=list(VIEWS))
    parser.add_argument("--set", action="append", default=[], help="key=value (a fit setting) for every run")
    parser.add_argument("--label", help="names the runs (a run replaces the same-labelled one; default: the date and "
                                         "the commit they measure)")
    parser.add_argument("--models", nargs="+", default=[], choices=list(MODEL_FLAGS),
                        help="one run each: auto (the fit's choice, with its trial) or a scene model forced (its label "
                             "then names it)")
    parser.add_argument("--budgets", nargs="+", default=[], help="fit.time_budget values: one run each (30s 1m ...)")
    parser.add_argument("--score-side", type=int, default=SCORE_SIDE,
                        help="score held-out views with their longest side this many pixels (0: at the fit's size)")
    parser.add_argument("--front", nargs="+",
                        help="the labels of the preset runs budget runs are compared with (a scene's runs under any; "
                             "default: each scene's newest)")
    parser.add_argument("--table", action="store_true", help="print the results as a Markdown table and exit")
    parser.add_argument("--plot-sweeps", nargs="+", default=[], metavar="LABEL",
                        help="budget sweeps (their --label) to draw beside each scene's plain one")
    parser.add_argument("--verbose", action="store_true", help="show each fit's progress")
    parser.add_argument("--aligned", action="store_true",
                        help="score each held-out view again with its pose aligned to the field (bench/pose_alignment.py)")
    args = parser.parse_args(argv)
    from bench.common import run_part

    return run_part(args, one_run, run_all)


def run_all(args) -> int:
    from bench.common import fit_overrides, recorded, write_runs
    from bench.fit import machine

    results = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {"runs": []}
    budget_plot = RESULTS.with_name("real_scenes_budget.png")
    if args.table:
        front = args.front or newest_front(results["runs"])
        print(table(results, front))
        plot_budgets(results, front, budget_plot, tuple(args.plot_sweeps))
        return 0
    overrides = fit_overrides(args.set)
    when = recorded()
    variants = ([(budget_label(b, args.label or ""), {**overrides, "time_budget": b}) for b in args.budgets] if args.budgets
                else [(args.label or when, overrides)])
    if args.models:
        variants = [(label if flag == "auto" else f"{label} {MODEL_FLAGS[flag]}",
                     {**run_overrides, **(MODELS[MODEL_FLAGS[flag]] if flag != "auto" else {})})
                    for label, run_overrides in variants for flag in args.models]
    results["machine"] = machine()
    for name in args.scenes:
        for preset in args.presets:
            out = prepared(name, preset, args.data)
            for views in args.views:
                for label, run_overrides in variants:
                    spec = {"scene": name, "preset": preset, "views": views, "label": label, "recorded": when,
                            "overrides": run_overrides, "out": str(out), "verbose": args.verbose,
                            "score_side": args.score_side, "aligned": args.aligned,
                            "label_suffix": "" if label == "as set" else "-" + re.sub(r"[^A-Za-z0-9._-]+", "_", label)}
                    record = spawn(spec)
                    if record is None:
                        continue
                    record["machine"] = results["machine"]
                    key = (name, preset, views, label)
                    results["runs"] = [r for r in results["runs"]
                                       if (r["scene"], r["preset"], r["views"], r["label"]) != key] + [record]
                    write_runs(RESULTS, results)
                    print(f"{name} {preset} {views} ({label}): {record['mean']['psnr']:.2f} dB, SSIM "
                          f"{record['mean']['ssim']:.3f}, fit {record['fit_seconds']:.0f} s, {record['summary']}",
                          flush=True)
                    for key in ALIGNED if args.aligned else ():
                        print(f"  {key}: {record[f'mean_{key}']['psnr']:.2f} dB, SSIM {record[f'mean_{key}']['ssim']:.3f}")
    front = args.front or newest_front(results["runs"])
    print(table(results, front))
    plot_budgets(results, front, budget_plot, tuple(args.plot_sweeps))
    return 0


if __name__ == "__main__":
    sys.exit(main())
