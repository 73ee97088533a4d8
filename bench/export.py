"""Benchmark of the export stage against true surfaces, on the project's synthetic scenes, and in Blender.

Scenes (`--scenes kind:seed,...`; other seeds vary the layout, sizes and textures):
- `object`: a still life on a slab, photographed with alpha (an object on a backdrop); the truth is all of it;
- `room`: the still life standing on the floor of a closed, textured room; the truth is the objects alone, so the
  floor and walls count against the mesh wherever the export keeps them.
Each runs the whole pipeline (ingest, imported true poses, normalize, fit, export) at the preset, then scores:
- the mesh (input frame) against the true surface: F-score, precision, recall and Chamfer distance at 1% of the
  objects' size, recall on the surface some training camera sees (VISIBLE_DEFINITION), precision over the whole
  mesh, and the share of the mesh's area farther than 5% of the objects' size from the truth (GOAL_*);
- the colours: the textured mesh (OBJ + MTL + PNG, as written) and the PLY's vertex colours rendered unlit from every
  held-out camera (plenoxels.surface.texture.render_mesh), against the photo on the pixels the true objects cover, beside the
  radiance field's own render of the same pixels: the goal is the texture within GOAL_TEXTURE_DB of the field;
- Blender 5.0.1 (bench/blender.py, when its `bpy` environment is installed): the GLB, OBJ and PLY imported, their
  frame, scale, materials and a render from a training camera against render_mesh's.
Writes bench/results/export.json (or export-<label>.json with --label).

    .venv/bin/python -m bench.export [--scenes object:0,room:0] [--preset default] [--set export.texture=off]
                                     [--label NAME] [--real lego|fox|none] [--real-preset fast]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

from bench import blender
from bench.fit import machine
from stages.capture import synthetic, synthetic_scenes
from stages.common.json_files import read_json, write_json
from stages.scoring.metrics import mesh_scores, surface_distance
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from plenoxels.core.cameras import Intrinsics, project
from plenoxels.core.scene_model import SceneModel
from plenoxels.surface.texture import render_mesh

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "bench" / "results"
TOLERANCE_SHARE = 0.01
FAR_SHARE = 0.05
VISIBLE_DEFINITION = ("the true-mesh sample points that at least one training camera sees: inside its image and "
                      "not hidden, by more than the tolerance, behind another surface along the ray from the camera "
                      "(rays cast against the generator's exact shapes, floor and walls included)")
GOAL_F_SCORE = 0.93
GOAL_FAR_AREA = 0.01
GOAL_TEXTURE_DB = 2.0
# Views, size and alpha of each kind's photos.
SCENES = {"object": {"views": 48, "size": (320, 240), "alpha": True},
          "room": {"views": 60, "size": (400, 300), "alpha": False}}
# The real scenes' photo folders (../shared/data/<scene>/...), whose poses files sit beside them.
REAL_PHOTOS = {"lego": "train", "fox": "images"}


def training_cameras(transforms: dict, scene: dict, split: str = "train") -> list[tuple[np.ndarray, Intrinsics]]:
    """The generator-frame cameras of normalize's `split` ("train": the views the fit trained on; "test": held out)."""
    k = Intrinsics(transforms["fl_x"], transforms["fl_y"], transforms["cx"], transforms["cy"], transforms["w"], transforms["h"])
    names = {f["name"] for f in scene["frames"] if f.get("split", "train") == split}
    return [(np.asarray(f["transform_matrix"]), k) for f in transforms["frames"] if Path(f["file_path"]).stem in names]


def visible_from(cameras: list[tuple[np.ndarray, Intrinsics]], spec: synthetic_scenes.SceneSpec, tolerance: float):
    """A mask function: which points (generator frame) some camera sees, inside its image and not
    hidden behind another surface by more than `tolerance`."""

    def mask(points: np.ndarray) -> np.ndarray:
        seen = np.zeros(len(points), dtype=bool)
        for c2w, k in cameras:
            uv, depth = project(points, c2w, k)
            in_view = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < k.w) & (uv[:, 1] >= 0) & (uv[:, 1] < k.h)
            candidates = np.flatnonzero(in_view & ~seen)
            if len(candidates) == 0:
                continue
            centre = c2w[:3, 3]
            offsets = points[candidates] - centre
            t_hit, _ = synthetic_scenes.trace(spec, centre, offsets)
            distance = np.linalg.norm(offsets, axis=1)
            seen[candidates] = t_hit * distance >= distance - tolerance
        return seen

    return mask


def colour_error(mesh: trimesh.Trimesh, spec: synthetic_scenes.SceneSpec) -> dict:
    """Mean absolute RGB error of the mesh's vertex colours against the true (view-independent, shaded)
    colour of the nearest foreground shape at each vertex, with two baselines for scale."""
    shapes = spec.foreground()
    vertices = np.asarray(mesh.vertices)
    rng = np.random.default_rng(0)
    nearest = np.stack([surface_distance(shape.mesh(), vertices, rng) for shape in shapes], axis=1).argmin(axis=1)
    truth = np.zeros((len(vertices), 3))
    for index, shape in enumerate(shapes):
        truth[nearest == index] = synthetic_scenes.surface_colour(spec, shape, vertices[nearest == index])
    got = mesh.visual.vertex_colors[:, :3] / 255.0
    return {"median_abs_error": float(np.median(np.abs(got - truth).mean(axis=1))),
            "baseline_mid_grey": float(np.median(np.abs(0.5 - truth).mean(axis=1))),
            "baseline_mean_colour": float(np.median(np.abs(truth.mean(axis=0) - truth).mean(axis=1)))}


def load_textured(obj: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Vertices (the frame's own axes), faces, UV and the texture image [H, W, 3] in [0, 1] of a textured OBJ (None
    without a texture)."""
    mesh, uv, image = blender.as_written(obj)
    return None if uv is None else (np.asarray(mesh.vertices), np.asarray(mesh.faces), uv, image)


def colour_renders(export_dir: Path, run_dir: Path, transforms: dict, scene: dict, spec: synthetic_scenes.SceneSpec) -> dict:
    """PSNR against the held-out photos, on the pixels the true objects wholly cover: the textured OBJ and the PLY's
    vertex colours rendered unlit (render_mesh; black where the mesh is missing), and the radiance field's own render
    of the same pixels; and the same on the part of those pixels the mesh covers (the colours apart from the holes)."""
    model = SceneModel.load(run_dir / "fit")
    textured = load_textured(export_dir / "mesh.obj")
    ply = trimesh.load(export_dir / "mesh.ply", force="mesh", process=False)
    held_out = {f["name"]: f for f in scene["frames"] if f.get("split") == "test"}
    keys = ("field", "texture", "vertex_colours")
    squared = {key: 0.0 for key in keys}
    squared_covered = {key: 0.0 for key in keys}
    pixels = pixels_covered = 0
    for frame in transforms["frames"]:
        record = held_out.get(Path(frame["file_path"]).stem)
        if record is None:
            continue
        c2w, k = np.asarray(frame["transform_matrix"]), Intrinsics.from_frame(record)
        photo, _, coverage = synthetic_scenes.render_view(spec, c2w, k)
        photo = photo / 255.0
        mask = coverage >= 1.0
        vertex_render, covered = render_mesh(ply.vertices, ply.faces, c2w, k,
                                             vertex_colours=ply.visual.vertex_colors[:, :3] / 255.0)
        renders = {"field": model.render_camera(np.asarray(record["transform_matrix"]), k)["rgb"].numpy(),
                   "vertex_colours": vertex_render}
        if textured is not None:
            renders["texture"] = render_mesh(textured[0], textured[1], c2w, k, uv=textured[2], image=textured[3])[0]
        for key, image in renders.items():
            squared[key] += float(((image - photo)[mask] ** 2).sum())
            squared_covered[key] += float(((image - photo)[mask & covered] ** 2).sum())
        pixels += int(mask.sum())
        pixels_covered += int((mask & covered).sum())

    def psnr(errors: dict, count: int) -> dict:
        return {key: (-10 * np.log10(max(value / max(3 * count, 1), 1e-12)) if count and (key != "texture" or textured)
                      else None) for key, value in errors.items()}

    result, on_mesh = psnr(squared, pixels), psnr(squared_covered, pixels_covered)
    return {"psnr": result, "views": len(held_out), "pixels": pixels,
            "texture_below_field_db": result["field"] - result["texture"] if result["texture"] is not None else None,
            "psnr_where_the_mesh_covers": on_mesh, "mesh_covers_share": pixels_covered / max(pixels, 1)}


def topology(mesh: trimesh.Trimesh) -> dict:
    """Boundary edges (one face), non-manifold edges (more than two), connected pieces and the Euler number."""
    _, counts = np.unique(np.sort(mesh.edges, axis=1), axis=0, return_counts=True)
    pieces = trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(len(mesh.faces)))
    return {"boundary_edges": int((counts == 1).sum()), "non_manifold_edges": int((counts > 2).sum()),
            "pieces": len(pieces), "euler": int(mesh.euler_number)}


def scene_paths(out: Path, kind: str, seed: int, run: str = "run") -> tuple[Path, Path]:
    """The synthetic scene's folder and the pipeline's output folder (`run`) for one kind and seed."""
    spec = SCENES[kind]
    width, height = spec["size"]
    base = out / f"{kind}-{spec['views']}-{width}x{height}-seed{seed}"
    return base / "photos", base / run


def score_scene(kind: str, seed: int, preset: str, overrides: list[str], out: Path, run: str = "run",
                score_only: bool = False) -> dict:
    """The whole pipeline on one synthetic scene (or, with `score_only`, what an earlier run left in its folder),
    and its export scored against the truth (module docstring)."""
    spec_of_kind = SCENES[kind]
    width, height = spec_of_kind["size"]
    scene_dir, run_dir = scene_paths(out, kind, seed, run)
    if not (scene_dir / "images").is_dir():
        synthetic.write_scene(kind, scene_dir, n_views=spec_of_kind["views"], width=width, height=height, seed=seed,
                              alpha=spec_of_kind["alpha"])
    started = time.time()
    if score_only:
        manifests = {name: read_json(run_dir / name / "manifest.json") for name in ("normalize", "fit", "export")}
    else:
        manifests = Pipeline(scene_dir / "images", run_dir, preset=preset, overrides=overrides,
                             reporter=Reporter(quiet=True)).run(["export"])
    pipeline_seconds = time.time() - started
    export_dir = run_dir / "export"
    record = read_json(export_dir / "export.json")
    if record["frame"] != "input":
        raise SystemExit("the benchmark scores the input frame; drop export.frame from --set")

    truth = trimesh.load(scene_dir / "ground_truth" / "mesh.ply", force="mesh", process=False)
    size = float(np.max(truth.bounds[1] - truth.bounds[0]))
    tolerance = TOLERANCE_SHARE * size
    transforms = read_json(scene_dir / "transforms.json")
    scene = read_json(run_dir / "normalize" / "scene.json")
    cameras = training_cameras(transforms, scene)
    spec = synthetic_scenes.build_scene(kind, seed)
    mesh = trimesh.load(export_dir / "mesh.ply", force="mesh", process=False)
    scores = mesh_scores(mesh, truth, tolerance, reference_visible=visible_from(cameras, spec, tolerance),
                         far=FAR_SHARE * size)
    all_surface = mesh_scores(mesh, truth, tolerance)
    points = np.asarray(trimesh.load(export_dir / "points.ply").vertices)
    point_distance = surface_distance(truth, points, np.random.default_rng(0)) if len(points) else np.zeros(0)
    colours = colour_renders(export_dir, run_dir, transforms, scene, spec)
    texture_gap = colours["texture_below_field_db"]
    return {
        "scene": {"kind": kind, "seed": seed, "views": spec_of_kind["views"], "size": [width, height],
                  "object_size": size, "tolerance": tolerance},
        "stage_summaries": {name: m["summary"]["line"] for name, m in manifests.items()},
        "fit_held_out_psnr": read_json(run_dir / "fit" / "fit.json").get("held_out_psnr"),
        "pipeline_seconds": None if score_only else round(pipeline_seconds, 1),
        "export_code": manifests["export"]["code"],
        "export_seconds": read_json(export_dir / "manifest.json")["seconds"],
        "export": {k: record.get(k) for k in ("level", "level_source", "resolution", "lattice", "cleaning", "mesh",
                                               "points", "file_bytes", "object_only", "aligned", "decimation", "texture")},
        "training_cameras": len(cameras),
        "visible_share_of_true_surface": scores["reference_samples_used"] / all_surface["reference_samples_used"],
        "mesh_vs_truth": scores,
        "mesh_vs_all_true_surface": all_surface,
        "topology": topology(mesh),
        "vertex_colours": colour_error(mesh, spec),
        "colour_renders": colours,
        "goal": {"f_score": scores["f_score"] >= GOAL_F_SCORE, "far_area": scores["far_share"] <= GOAL_FAR_AREA,
                 "texture": texture_gap is not None and texture_gap <= GOAL_TEXTURE_DB},
        "points_vs_truth": {"count": len(points),
                            "within_tolerance": float((point_distance < tolerance).mean()) if len(points) else None,
                            "median_distance": float(np.median(point_distance)) if len(points) else None},
        "blender": blender.check_export(export_dir, cameras[0]),
    }


def real_scene(name: str, data: Path, preset: str, out: Path) -> dict:
    """The whole pipeline on a real scene's photos (imported poses), and Blender's import of its files."""
    if name == "none":
        return {"ran": False, "why": "--real none"}
    photos = data / name / REAL_PHOTOS[name]
    if not photos.is_dir():
        return {"ran": False, "why": f"no photos at {photos}"}
    started = time.time()
    manifests = Pipeline(photos, out / f"real-{name}", preset=preset, reporter=Reporter(quiet=True)).run(["export"])
    export_dir = out / f"real-{name}" / "export"
    record = read_json(export_dir / "export.json")
    return {"ran": True, "scene": name, "preset": preset, "pipeline_seconds": round(time.time() - started, 1),
            "export": manifests["export"]["summary"]["line"], "level_source": record["level_source"],
            "blender": blender.check_export(export_dir, None)}


def commit() -> str:
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True)
    return head.stdout.strip() + ("+uncommitted changes" if dirty.stdout.strip() else "")


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="object:0,room:0", help="kind:seed, comma-separated")
    parser.add_argument("--preset", default="default")
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--label", default="", help="write bench/results/export-LABEL.json")
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "out" / "export")
    parser.add_argument("--run", default="run", help="the pipeline's output folder in each scene's folder")
    parser.add_argument("--score-only", action="store_true",
                        help="score the export an earlier run left in --run, without running the pipeline")
    parser.add_argument("--real", choices=sorted(REAL_PHOTOS) + ["none"], default="lego",
                        help="a real scene whose files Blender must import (skipped when its data is absent)")
    parser.add_argument("--real-preset", default="fast")
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    args = parser.parse_args(argv)
    load_before = os.getloadavg()
    started = time.strftime("%Y-%m-%d %H:%M")
    results = []
    for item in args.scenes.split(","):
        kind, seed = item.split(":")
        result = score_scene(kind, int(seed), args.preset, args.overrides, args.out, args.run, args.score_only)
        results.append(result)
        s, c = result["mesh_vs_truth"], result["colour_renders"]["psnr"]
        print(f"[bench export] {kind} seed {seed}: F-score@1% {s['f_score']:.3f} (precision {s['precision']:.3f}, "
              f"recall {s['recall']:.3f}), Chamfer {s['chamfer'] / result['scene']['object_size']:.2%} of the objects' "
              f"size, {s['far_share']:.1%} of the mesh farther than 5%; PSNR on the objects: field {c['field']:.2f}, "
              f"texture {c['texture'] if c['texture'] is None else round(c['texture'], 2)}, vertex colours "
              f"{c['vertex_colours']:.2f} dB; goal {result['goal']}; blender: "
              f"{'ok' if result['blender'].get('ok') else result['blender'].get('why', 'check failed')}", flush=True)
    real = real_scene(args.real, args.data, args.real_preset, args.out)
    document = {"machine": machine(), "commit": commit(), "started": started,
                "load_average": {"before": [round(x, 2) for x in load_before],
                                 "after": [round(x, 2) for x in os.getloadavg()]},
                "preset": args.preset, "overrides": args.overrides, "visible_definition": VISIBLE_DEFINITION,
                "goal": {"f_score_at_1_percent": GOAL_F_SCORE, "far_area_share_at_5_percent": GOAL_FAR_AREA,
                         "texture_within_db_of_field": GOAL_TEXTURE_DB},
                "scenes": results, "real_scene": real}
    RESULTS.mkdir(parents=True, exist_ok=True)
    write_json(RESULTS / (f"export-{args.label}.json" if args.label else "export.json"), document)
    if real.get("ran"):
        print(f"[bench export] {real['scene']} ({real['preset']}): {real['export']}; blender: "
              f"{'ok' if real['blender'].get('ok') else real['blender'].get('why', 'check failed')}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
