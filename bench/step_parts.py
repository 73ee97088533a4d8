"""Where a train step's time goes: milliseconds per step of each part at each level of a scene's `default` fit
(lego, or a real capture of bench/real_scenes.py), shortened to a few hundred steps a level (the levels, grids and
batches of the full fit), on the CPU unless `--set device=cuda` names the GPU.

The parts: the render's loss and gradient (the native kernel with its per-thread gradient merge), total variation,
the optimiser step, the background model (its render, gradient and step, in scenes that have one; on a CPU the grid's
pass draws the spheres, so there they count in the render), drawing the batch, the guard that checks the parameters
are finite, and the rest of the step. Each is timed around its call inside a train step, so the times add up to the
step's. On a GPU each part waits for the device before and after it (the kernels are asynchronous), so a part's time
is its own, and the step loses what the parts would have overlapped.

    python -m bench.step_parts [--scene lego] [--steps 200,300,300] [--label NAME] [--data ../shared/data]
        [--set key=value ...]   # a fit setting, e.g. device=cuda or batch_size=32768

Adds the run to bench/results/step_parts.json (replacing one of the same scene and label) and prints a table. To
compare two versions of the code back to back, run the same file from a worktree of the other (`git worktree add`,
build its core, copy this file into its bench/) with `--out` pointing here and another label.
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

RESULTS = REPO / "bench" / "results" / "step_parts.json"
PARTS = ("render", "tv", "optimiser", "background", "batch", "guard")


def scene_of(name: str, data: Path) -> tuple[dict, Path, str]:
    """(scene.json, the folder its paths resolve against, its scene type): lego as bench/fit.py loads it, a real
    capture through the pipeline up to normalize as bench/real_scenes.py prepares it."""
    if name == "lego":
        from bench.fit import load_scene

        scene, root = load_scene("lego", data, 25)
        return scene, root, "object"
    from bench.real_scenes import prepared

    root = prepared(name, "default", data)
    scene = json.loads((root / "normalize" / "scene.json").read_text())
    return scene, root, scene["type"]


def timed_fit(name: str, data: Path, steps: list[int], overrides: dict) -> dict:
    """Runs the shortened fit with each part's calls timed; per level: steps, grid rows, rows a step touched and
    milliseconds per step of each part and of the whole step."""
    import torch

    from bench.common import fitted
    from bench.fit import resolve
    from plenoxels.core import background
    from plenoxels.core import optim
    from plenoxels.core import train

    scene, root, scene_type = scene_of(name, data)
    settings = resolve("default", scene_type, {**overrides, "steps": steps, "eval_every": 0})
    on_gpu = settings.device == "cuda" or (settings.device == "auto" and torch.cuda.is_available())
    wait = torch.cuda.synchronize if on_gpu else (lambda: None)

    seconds = collections.defaultdict(float)
    touched = collections.defaultdict(float)
    rows = collections.defaultdict(float)
    counts = collections.Counter()
    level = [0]
    in_step = [False]  # parts count only inside a train step (the guard also runs at each checkpoint)

    def wrap(owner, name: str, part: str) -> None:
        original = getattr(owner, name)

        def timed(*args, **kwargs):
            if in_step[0]:
                wait()
            started = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                if in_step[0]:
                    wait()
                    seconds[(level[0], part)] += time.perf_counter() - started

        setattr(owner, name, timed)

    wrap(train, "loss_and_grad", "render")
    # On a CPU a scene with background spheres renders them in the grid's pass: that call is the render too.
    wrap(train, "loss_and_grad_before_spheres", "render")
    wrap(train, "tv_loss_and_grad", "tv")
    wrap(train.RaySet, "batch", "batch")
    wrap(train.Fitter, "check_finite", "guard")
    wrap(optim.SparseRMSProp, "step", "optimiser")
    for method in ("forward", "backward", "step"):
        wrap(background.BackgroundOptimiser, method, "background")
    optimiser_step = optim.SparseRMSProp.step

    def counted_step(self, grad):
        touched[level[0]] += grad.num_touched
        rows[level[0]] += self.grid.num_occupied
        return optimiser_step(self, grad)

    optim.SparseRMSProp.step = counted_step
    train_step = train.Fitter.train_step

    def step(self):
        level[0] = self.level
        counts[self.level] += 1
        wait()
        in_step[0] = True
        started = time.perf_counter()
        try:
            return train_step(self)
        finally:
            wait()
            seconds[(self.level, "step")] += time.perf_counter() - started
            in_step[0] = False

    train.Fitter.train_step = step
    started = time.time()
    summary, wall, record, _ = fitted(scene, root, settings)
    levels = []
    for index, resolution in enumerate(settings.resolutions):
        ms = {part: round(seconds[(index, part)] / max(1, counts[index]) * 1e3, 2) for part in (*PARTS, "step")}
        ms["rest"] = round(ms["step"] - sum(ms[p] for p in PARTS), 2)
        levels.append({"resolution": resolution, "steps": counts[index],
                       "grid_rows": round(rows[index] / max(1, counts[index])),
                       "rows_touched": round(touched[index] / max(1, counts[index])), "ms_per_step": ms})
    return {"levels": levels, "fit_seconds": record["seconds"], "wall_seconds": round(time.time() - started, 1),
            "device": torch.cuda.get_device_name() if on_gpu else "cpu", "overrides": overrides,
            "batch_size": settings.batch_size, "summary": summary["line"]}


def print_run(run: dict) -> None:
    print(f"{run.get('scene', 'lego')}, {run['label']} ({run.get('device', 'cpu')}, batch {run.get('batch_size')}): "
          f"{run['fit_seconds']} s fitting; ms per step")
    columns = (*PARTS, "rest", "step")
    print(f"{'level':>5} {'res':>4} {'rows':>9} {'touched':>8} " + " ".join(f"{p:>9}" for p in columns))
    for i, lv in enumerate(run["levels"]):
        ms = {"background": 0.0, **lv["ms_per_step"]}
        print(f"{i:>5} {lv['resolution']:>4} {lv['grid_rows']:>9} {lv['rows_touched']:>8} "
              + " ".join(f"{ms[p]:>9.1f}" for p in columns))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default="lego", help="lego or a scene of bench/real_scenes.py (fox, cup, ...)")
    parser.add_argument("--steps", default="200,300,300", help="steps of default's three levels, comma-separated")
    parser.add_argument("--label", default="as is", help="names the run (a run replaces the same-labelled one)")
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a fit setting")
    args = parser.parse_args(argv)
    import torch

    from bench.common import fit_overrides
    from plenoxels.planning.fit_cost import processor_name

    load_before = os.getloadavg()[0]
    run = {"scene": args.scene, "label": args.label,
           "commit": os.popen(f"git -C {REPO} rev-parse --short HEAD").read().strip(),
           **timed_fit(args.scene, args.data, [int(s) for s in args.steps.split(",")], fit_overrides(args.set)),
           "machine": {"cpu": processor_name(), "threads": torch.get_num_threads()},
           "load_average": [round(load_before, 2), round(os.getloadavg()[0], 2)],
           "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    results = json.loads(args.out.read_text()) if args.out.is_file() else {"runs": []}
    results["runs"] = [r for r in results["runs"]
                       if (r.get("scene", "lego"), r["label"]) != (args.scene, args.label)] + [run]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    print_run(run)
    return 0


if __name__ == "__main__":
    sys.exit(main())
