"""Benchmark of object captures: masks, turntables and the object box from silhouettes, on synthetic scenes with their
true poses and meshes. Each case runs the whole pipeline (a preset, `fast` by default) as a user would, in this
process, and records what each stage decided and scored. Writes bench/results/object_captures.json.

Cases:
- turntable_masks: the synthetic turntable (the object turning in front of a still, textured room; the camera
  still) with a mask per photo: SfM inside the masks against the true poses, the object's fit scored inside its
  masks, the mesh brought into the truth's frame through the cameras (how much of it lies on the object, how far its
  farthest vertex is, whether any of it reaches the floor or the room).
- turntable_no_masks: the same photos without their masks: the poses stage's refusal, and its time.
- idr_layout: the synthetic object with alpha, laid out as NeuS's DTU release (image/, mask/, cameras_sphere.npz).
- idr_light / idr_light_colour_off: the same set with each photo under a light of its own (a gain and a left-to-right
  ramp, each within ±20%, drawn at random, so no order in the capture predicts them), with each photo's colour fitted
  where the photos differ in it (the object preset) and with the photos taken as they are (fit.photo_colour=false).
- mast_hull / mast_points: the synthetic object with a thin mast, in RGBA, posed by its true cameras: the box from the
  photos' masks (visual hull) against the box of the sparse points' bulk (normalize.silhouette_box=false), and the
  held-out PSNR inside the masks that each gives.
- backdrop_varies / backdrop_varies_object: the synthetic object photographed on white and, every second photo, on
  near-black, with no masks: the scene type normalize gives, and the whole-image held-out PSNR, against the same photos
  fitted as an object (normalize.scene_type=object).

    .venv/bin/python -m bench.object_captures [--preset fast] [--cases turntable_masks,mast_hull] [--out bench/out/objects]
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from bench.fit import machine
from stages.common.json_files import read_json, write_json
from stages.scoring.metrics import mesh_scores
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from stages.sfm.compare import compare_poses, umeyama
from pipeline.stage import STAGE_ORDER
from stages.capture.synthetic import write_scene
from plenoxels.core.cameras import colmap_w2c_from_opengl_c2w
from plenoxels.core.errors import UserError

REPO = Path(__file__).resolve().parent.parent
CASES = ("turntable_masks", "turntable_no_masks", "idr_layout", "idr_light", "idr_light_colour_off", "mast_hull",
         "mast_points", "backdrop_varies", "backdrop_varies_object")
# Each photo of idr_light under a light of its own: a gain and the slope of a left-to-right ramp, drawn within these.
LIGHT_GAIN, LIGHT_SLOPE = (0.8, 1.2), (-0.2, 0.2)


def commit() -> str:
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()


def frames_by_name(transforms: dict) -> dict[str, np.ndarray]:
    return {Path(f["file_path"]).stem: np.asarray(f["transform_matrix"]) for f in transforms["frames"]}


def run_pipeline(scene: Path, out: Path, preset: str, overrides: list[str]) -> dict:
    """Runs every stage; the stages' summaries, the seconds, and the one-line error where it stopped."""
    started = time.time()
    record: dict = {"overrides": overrides, "load_average_before": os.getloadavg()[0]}
    try:
        manifests = Pipeline(scene, out, preset=preset, overrides=overrides,
                             reporter=Reporter(quiet=True)).run(list(STAGE_ORDER))
        record["summaries"] = {stage: m["summary"]["line"] for stage, m in manifests.items()}
    except UserError as e:
        record["refused"] = str(e)
    record["seconds"] = round(time.time() - started, 1)
    record["load_average_after"] = os.getloadavg()[0]
    return record


def scores(out: Path) -> dict:
    """What normalize decided, the fit's and evaluate's figures."""
    found = {}
    if (out / "normalize" / "scene.json").is_file():
        scene = read_json(out / "normalize" / "scene.json")
        found.update(scene_type=scene["type"], foreground_from=scene["measured"]["foreground_from"],
                     visual_hull=scene["measured"].get("visual_hull"))
    if (out / "fit" / "fit.json").is_file():
        fit = read_json(out / "fit" / "fit.json")
        found.update(train_psnr=fit["train_psnr"], fit_seconds=fit["seconds"], background_model=fit["model"]["background_model"],
                     background_added=fit.get("background_added"))
    if (out / "evaluate" / "metrics.json").is_file():
        found["held_out"] = read_json(out / "evaluate" / "metrics.json")["mean"]
    return found


def pose_errors(out: Path, truth: dict) -> dict:
    got, want = frames_by_name(read_json(out / "poses" / "transforms.json")), frames_by_name(truth)
    names = sorted(set(got) & set(want))
    errors = compare_poses(np.array([got[n] for n in names]), np.array([want[n] for n in names]))
    return {"registered": len(names), "of": len(want), "rotation_error_deg_max": round(errors["rotation_error_deg_max"], 4),
            "rotation_error_deg_median": round(errors["rotation_error_deg_median"], 4),
            "centre_error_share_max": round(errors["centre_error_share_max"], 5)}


def mesh_against_truth(out: Path, scene: Path) -> dict:
    """The exported mesh in the truth's frame (the camera centres' similarity): its share within 5% of the object's
    size of the true surface, its farthest vertex, and how far below the object's base its lowest vertex lies."""
    truth = trimesh.load(scene / "ground_truth" / "mesh.ply", force="mesh", process=False)
    got = frames_by_name(read_json(out / "poses" / "transforms.json"))
    want = frames_by_name(read_json(scene / "transforms.json"))
    names = sorted(got)
    scale, rotation, translation = umeyama(np.array([got[n][:3, 3] for n in names]), np.array([want[n][:3, 3] for n in names]))
    mesh = trimesh.load(out / "export" / "mesh.ply", force="mesh", process=False)
    vertices = scale * np.asarray(mesh.vertices) @ rotation.T + translation
    size = float(np.max(truth.bounds[1] - truth.bounds[0]))
    measured = mesh_scores(trimesh.Trimesh(vertices, mesh.faces, process=False), truth, 0.05 * size, samples=20_000)
    return {"faces": len(mesh.faces), "precision_at_5pct": round(measured["precision"], 4),
            "recall_at_5pct": round(measured["recall"], 4),
            "max_vertex_distance_share": round(measured["max_vertex_distance"] / size, 4),
            "lowest_vertex_below_object_share": round(float(truth.bounds[0][2] - vertices[:, 2].min()) / size, 4)}


def neus_layout(synthetic: Path, folder: Path, light_seed: int | None = None) -> None:
    """The RGBA synthetic object as NeuS's DTU release lays it out (image/, mask/, cameras_sphere.npz); with
    `light_seed`, each photo under a light of its own (LIGHT_GAIN, LIGHT_SLOPE)."""
    rng = np.random.default_rng(light_seed)
    truth = read_json(synthetic / "transforms.json")
    shutil.rmtree(folder, ignore_errors=True)
    (folder / "image").mkdir(parents=True)
    (folder / "mask").mkdir()
    k = np.array([[truth["fl_x"], 0, truth["cx"] - 0.5], [0, truth["fl_y"], truth["cy"] - 0.5], [0, 0, 1]])
    arrays = {}
    for i, frame in enumerate(truth["frames"]):
        rgba = np.asarray(Image.open(synthetic / frame["file_path"]))
        rgb = rgba[..., :3]
        if light_seed is not None:
            ramp = 1 + rng.uniform(*LIGHT_SLOPE) * np.linspace(-1, 1, rgb.shape[1])[None, :, None]
            rgb = np.clip(np.round(rgb * rng.uniform(*LIGHT_GAIN) * ramp), 0, 255).astype(np.uint8)
        Image.fromarray(rgb).save(folder / "image" / f"{i:06d}.png")
        Image.fromarray(np.where(rgba[..., 3] > 127, 255, 0).astype(np.uint8)).save(folder / "mask" / f"{i:03d}.png")
        rotation, translation = colmap_w2c_from_opengl_c2w(np.asarray(frame["transform_matrix"]))
        world = np.eye(4)
        world[:3] = k @ np.hstack([rotation, translation[:, None]])
        arrays[f"world_mat_{i}"], arrays[f"scale_mat_{i}"] = world, np.eye(4)
    np.savez(folder / "cameras_sphere.npz", **arrays)


def backdrop_photos(synthetic: Path, folder: Path) -> None:
    """The RGBA synthetic object as plain photos with true poses, on white from one half of the orbit and on near-black
    from the other (a white table seen from one side, a dark room from the other): a backdrop that differs between
    photos the way a place's surroundings do, by where the camera stands."""
    truth = read_json(synthetic / "transforms.json")
    shutil.rmtree(folder, ignore_errors=True)
    (folder / "images").mkdir(parents=True)
    centres = np.array([np.asarray(f["transform_matrix"])[:3, 3] for f in truth["frames"]])
    side = centres[:, 0] - centres[:, 0].mean()
    for i, frame in enumerate(truth["frames"]):
        rgba = np.asarray(Image.open(synthetic / frame["file_path"])).astype(float) / 255
        backdrop = 0.05 if side[i] < 0 else 1.0
        rgb = rgba[..., :3] * rgba[..., 3:] + backdrop * (1 - rgba[..., 3:])
        Image.fromarray(np.round(rgb * 255).astype(np.uint8)).save(folder / frame["file_path"])
    write_json(folder / "transforms.json", truth)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "out" / "objects")
    args = parser.parse_args()
    cases = [c for c in args.cases.split(",") if c]
    unknown = set(cases) - set(CASES)
    if unknown:
        raise SystemExit(f"unknown case(s) {', '.join(sorted(unknown))}; choose from {', '.join(CASES)}")
    results_path = REPO / "bench" / "results" / "object_captures.json"
    results = read_json(results_path) if results_path.is_file() else {}
    results.update(machine=machine(), commit=commit(), date=time.strftime("%Y-%m-%d"), preset=args.preset)
    results.setdefault("cases", {})
    data = args.out / "scenes"
    turntable = data / "turntable"
    if {"turntable_masks", "turntable_no_masks"} & set(cases) and not turntable.is_dir():
        write_scene("turntable", turntable, n_views=36, width=480, height=360, seed=0, masks=True)
    for case in cases:
        out = args.out / case
        shutil.rmtree(out, ignore_errors=True)
        print(f"{case}: running", flush=True)
        if case.startswith("turntable"):
            overrides = ["poses.source=sfm"] + (["ingest.masks=false"] if case == "turntable_no_masks" else [])
            record = run_pipeline(turntable, out, args.preset, overrides)
            if "refused" not in record:
                record.update(poses=pose_errors(out, read_json(turntable / "transforms.json")),
                              mesh=mesh_against_truth(out, turntable), **scores(out))
        elif case.startswith("idr"):
            synthetic = data / "object_rgba"
            if not synthetic.is_dir():
                write_scene("object", synthetic, n_views=40, width=400, height=300, seed=2, alpha=True)
            lit = case.startswith("idr_light")
            neus_layout(synthetic, data / case, light_seed=7 if lit else None)
            record = run_pipeline(data / case, out, args.preset,
                                  ["fit.photo_colour=false"] if case == "idr_light_colour_off" else [])
            record.update(scores(out))
        elif case.startswith("mast"):
            mast = data / "mast"
            if not mast.is_dir():
                write_scene("object", mast, n_views=40, width=400, height=300, seed=1, alpha=True, mast=True)
            record = run_pipeline(mast, out, args.preset,
                                  [] if case == "mast_hull" else ["normalize.silhouette_box=false"])
            record.update(scores(out))
        else:
            photos = data / "backdrop"
            if not photos.is_dir():
                synthetic = write_scene("object", data / "object_rgba_small", n_views=40, width=320, height=240,
                                        seed=0, alpha=True)
                backdrop_photos(synthetic, photos)
            record = run_pipeline(photos, out, args.preset,
                                  [] if case == "backdrop_varies" else ["normalize.scene_type=object"])
            record.update(scores(out))
        results["cases"][case] = {**record, "commit": results["commit"], "date": results["date"],
                                  "machine": results["machine"]}
        write_json(results_path, results)
        print(f"{case}: {record.get('refused') or record.get('summaries', {}).get('evaluate')} "
              f"({record['seconds']} s)", flush=True)
    print(f"wrote {results_path.relative_to(REPO)}")


if __name__ == "__main__":
    main()
