"""The synthetic unbounded scene's resolution ceiling: how well each preset's grid could show the scene if it knew the
true surfaces, next to what its fit scores (bench/results/real_scenes.json).

The scene (stages/capture/synthetic.py) is Lambertian with exact surfaces, so for each pixel centre the surface it sees is
known. Each preset's grid (its final resolution, in the fit's own frame: the contraction around the foreground box,
SceneModel.create) then gets one colour per vertex, chosen by least squares over every training pixel, each pixel
the trilinear blend of the eight vertices around the point its ray hits. That is the best a grid of this resolution
can do with the true geometry and a view-independent colour (which is all the scene has); held-out views are scored
with the same vertex colours (a vertex no training pixel reaches takes the training photos' mean colour), at the
preset's image scale, as PSNR per view averaged over the views, as real_scenes scores its fits.

It is a ceiling for surfaces, not for a volume: a fit can exceed it a little by spreading a surface over several
voxel layers, so each ray meets its own mix, or by giving the colour a view dependence; how far the fits sit from it
says whether the grid's resolution or the optimisation holds a scene back.

    .venv/bin/python -m bench.grid_ceiling                         # every preset
    .venv/bin/python -m bench.grid_ceiling --presets fast default
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from bench.real_scenes import PRESETS, RESULTS as FIT_RESULTS, prepared, scene_folder  # noqa: E402

RESULTS = REPO / "bench" / "results" / "grid_ceiling.json"
SCENE = "synthetic_unbounded"


def psnr(mse: float) -> float:
    return float(-10 * np.log10(max(mse, 1e-12)))


def ceiling(preset: str, data: Path, iterations: int) -> dict:
    import scipy.sparse
    import torch
    from scipy.sparse.linalg import lsqr

    from bench.fit import resolve
    from stages.common.frames import load_frame
    from stages.capture.synthetic_scenes import build_scene, surface_points
    from plenoxels.core.reference import corners
    from plenoxels.core.scene_model import SceneModel

    started = time.time()
    out = prepared(SCENE, preset, data)
    scene = json.loads((out / "normalize" / "scene.json").read_text())
    settings = resolve(preset, scene["type"], {})
    resolution = settings.resolutions[-1]
    model = SceneModel.create(scene, settings, resolution)
    shape = model.grid.resolution
    source = json.loads((scene_folder(SCENE, data) / "transforms.json").read_text())
    input_pose = {Path(f["file_path"]).stem: np.asarray(f["transform_matrix"], dtype=np.float64) for f in source["frames"]}
    world_from_input = np.asarray(scene["world_from_input"], dtype=np.float64)
    spec = build_scene("unbounded", 0)

    views = {"train": [], "test": []}
    for frame in scene["frames"]:
        truth, k = load_frame(out, frame, settings.image_scale, settings.background_color)
        points, _ = surface_points(spec, input_pose[frame["name"]], k)
        world = points @ world_from_input[:3, :3].T + world_from_input[:3, 3]
        fit = model.fit_frame.from_world(world)
        grid = model.grid.world_to_grid(torch.from_numpy(fit))
        # The grid is dense (every vertex has a row), so a corner's row names its vertex.
        rows, weights = corners(model.grid.links, grid.clamp(torch.zeros(3), torch.tensor(shape) - 1.0))
        views[frame["split"]].append((rows.numpy(), weights.numpy(), truth.reshape(-1, 3).astype(np.float64)))

    index = np.concatenate([v[0] for v in views["train"]])
    weight = np.concatenate([v[1] for v in views["train"]])
    colour = np.concatenate([v[2] for v in views["train"]])
    vertices, column = np.unique(index, return_inverse=True)
    rows = np.repeat(np.arange(len(index)), 8)
    a = scipy.sparse.csr_matrix((weight.ravel(), (rows, column.ravel())), shape=(len(index), len(vertices)))
    mean = colour.mean(axis=0)
    # Solved for the offset from the mean colour, so an unreached vertex's 0 means the mean.
    solution = np.stack([lsqr(a, colour[:, c] - mean[c], iter_lim=iterations)[0] for c in range(3)], axis=1)
    train_mse = float(((a @ solution + mean - colour) ** 2).mean())

    held_out = []
    for index, weight, truth in views["test"]:
        at = np.searchsorted(vertices, index).clip(max=len(vertices) - 1)
        known = vertices[at] == index
        values = np.where(known[..., None], solution[at], 0.0)
        estimate = (weight[..., None] * values).sum(axis=1) + mean
        held_out.append(psnr(float(((estimate - truth) ** 2).mean())))
    return {"preset": preset, "resolution": list(shape), "image_size": [k.w, k.h], "vertices_solved": int(len(vertices)),
            "train_pixels": int(len(colour)), "iterations": iterations, "train_psnr": round(psnr(train_mse), 2),
            "held_out_psnr": round(float(np.mean(held_out)), 2), "held_out_views": [round(p, 2) for p in held_out],
            "seconds": round(time.time() - started, 1)}


def latest_fits() -> dict:
    """(preset -> the last real_scenes run of the synthetic scene with all photos and no overrides)."""
    if not FIT_RESULTS.is_file():
        return {}
    runs = json.loads(FIT_RESULTS.read_text()).get("runs", [])
    return {r["preset"]: r for r in runs if r["scene"] == SCENE and r["views"] == "all" and not r["overrides"]}


def table(results: dict) -> str:
    fits = latest_fits()
    lines = ["| preset | grid | scored at | ceiling: train | ceiling: held-out | fit: held-out (run) |", "|---|---|---|---|---|---|"]
    for r in results["ceilings"]:
        fit = fits.get(r["preset"])
        scored = f"{fit['mean']['psnr']:.2f} dB ({fit['label']})" if fit and fit["image_size"] == r["image_size"] else "-"
        lines.append(f"| {r['preset']} | {'x'.join(map(str, r['resolution']))} | {r['image_size'][0]}x{r['image_size'][1]} | "
                     f"{r['train_psnr']:.2f} dB | {r['held_out_psnr']:.2f} dB | {scored} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    from stages.common.json_files import write_json
    from plenoxels.core.errors import UserError

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--presets", nargs="+", default=list(PRESETS), choices=PRESETS)
    parser.add_argument("--iterations", type=int, default=1000, help="least-squares iterations per colour channel")
    parser.add_argument("--table", action="store_true", help="print the results as a Markdown table and exit")
    args = parser.parse_args(argv)
    results = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {"ceilings": []}
    if not args.table:
        from bench.fit import machine

        try:
            for preset in args.presets:
                row = ceiling(preset, args.data, args.iterations)
                print(f"  {preset}: {row}", flush=True)
                results["ceilings"] = [r for r in results["ceilings"] if r["preset"] != preset] + [row]
        except UserError as error:
            print(f"error: {error}", file=sys.stderr)
            return 1
        results["ceilings"].sort(key=lambda r: PRESETS.index(r["preset"]))
        results["machine"] = machine()
        write_json(RESULTS, results)
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
