"""Benchmark of the normalize stage on the real scenes in ../shared/data, from the poses they come with.

Each scene's own pose files are read into the poses stage's layout (transforms dict + sparse points)
here, then `stages.framing.scene_frame.normalize_scene` decides the frame and the scene type. Writes
bench/results/normalize.json and prints one line per scene.

    .venv/bin/python -m bench.normalize [--data ../shared/data]
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image

from stages.common.json_files import write_json
from stages.framing.options import SceneOptions
from stages.framing.scene_frame import normalize_scene
from stages.framing.sightings import Points
from plenoxels.core.cameras import opengl_c2w_from_colmap_w2c, opengl_c2w_from_llff

REPO = Path(__file__).resolve().parent.parent
EXPECTED = {"lego": "object", "fern": "forward", "cup": "unbounded", "fox": "unbounded"}


def lego(folder: Path) -> tuple[dict, Points]:
    """Blender/NeRF transforms, no points. The RGBA renders stand in for ingest's masks (their alpha)."""
    meta = json.loads((folder / "transforms_train.json").read_text())
    first = folder / (meta["frames"][0]["file_path"] + ".png")
    with Image.open(first) as im:
        w, h = im.size
    focal = 0.5 * w / math.tan(0.5 * meta["camera_angle_x"])
    frames = []
    for f in meta["frames"]:
        rel = f["file_path"].removeprefix("./") + ".png"
        frames.append({"name": Path(rel).stem, "file_path": rel, "mask_path": rel, "transform_matrix": f["transform_matrix"]})
    return {"fl_x": focal, "fl_y": focal, "cx": w / 2, "cy": h / 2, "w": w, "h": h, "frames": frames}, Points.empty()


def fern(folder: Path) -> tuple[dict, Points]:
    """LLFF poses_bounds.npy (full-resolution hwf), images_4; near/far bounds per frame, no points."""
    data = np.load(folder / "poses_bounds.npy")
    names = sorted(p.name for p in (folder / "images_4").iterdir())
    with Image.open(folder / "images_4" / names[0]) as im:
        w, h = im.size
    poses = data[:, :15].reshape(-1, 3, 5)
    full_h, full_w, full_f = poses[0, :, 4]
    focal = full_f * w / full_w
    frames = [{"name": Path(n).stem, "file_path": f"images_4/{n}", "transform_matrix": opengl_c2w_from_llff(p[:, :4]).tolist(),
               "near": float(b[0]), "far": float(b[1])} for n, p, b in zip(names, poses, data[:, 15:17])]
    return {"fl_x": focal, "fl_y": focal, "cx": w / 2, "cy": h / 2, "w": w, "h": h, "frames": frames}, Points.empty()


def cup(folder: Path) -> tuple[dict, Points]:
    """The COLMAP model in sparse/0, with its points and their observations."""
    rec = pycolmap.Reconstruction(str(folder / "sparse" / "0"))
    frames, index_of = [], {}
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        cam = rec.cameras[image.camera_id]
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        f, cx, cy = (cam.params[0], cam.params[1], cam.params[2])
        index_of[image.image_id] = len(frames)
        frames.append({"name": Path(image.name).stem, "file_path": f"images/{image.name}",
                       "transform_matrix": opengl_c2w_from_colmap_w2c(pose.rotation.matrix(), pose.translation).tolist(),
                       "fl_x": f, "fl_y": f, "cx": cx, "cy": cy, "w": cam.width, "h": cam.height})
    xyz, obs_frame, obs_point = [], [], []
    for n, point in enumerate(rec.points3D.values()):
        xyz.append(point.xyz)
        for element in point.track.elements:
            obs_frame.append(index_of[element.image_id])
            obs_point.append(n)
    return {"frames": frames}, Points(np.asarray(xyz), np.asarray(obs_frame), np.asarray(obs_point))


def fox(folder: Path) -> tuple[dict, Points]:
    """instant-ngp transforms (OpenGL c2w), no points; distortion is ignored (it barely moves the geometry).
    The file lists more frames than the folder holds photos for; like an importer, keep those with a photo."""
    meta = json.loads((folder / "transforms.json").read_text())
    frames = [{"name": Path(f["file_path"]).stem, "file_path": f["file_path"], "transform_matrix": f["transform_matrix"]}
              for f in meta["frames"] if (folder / f["file_path"]).is_file()]
    shared = {k: meta[k] for k in ("fl_x", "fl_y", "cx", "cy")}
    return {**shared, "w": int(meta["w"]), "h": int(meta["h"]), "frames": frames}, Points.empty()


LOADERS = {"lego": lego, "fern": fern, "cup": cup, "fox": fox}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    args = parser.parse_args()
    results = {}
    for name, loader in LOADERS.items():
        folder = args.data / name
        started = time.time()
        transforms, points = loader(folder)
        scene = normalize_scene(transforms, points, SceneOptions(), poses_dir=folder)
        seconds = time.time() - started
        frames = scene["frames"]
        results[name] = {
            "type": scene["type"], "expected": EXPECTED[name], "agrees": scene["type"] == EXPECTED[name],
            "reasons": scene["reasons"], "measured": scene["measured"], "scale": scene["scale"],
            "foreground": scene["foreground"], "forward": scene.get("forward"),
            "near_median": float(np.median([f["near"] for f in frames])),
            "far_median": float(np.median([f["far"] for f in frames])),
            "held_out": sum(f["split"] == "test" for f in frames), "frames": len(frames),
            "camera_distance_median": float(np.median([np.linalg.norm(np.asarray(f["transform_matrix"])[:3, 3]) for f in frames])),
            "seconds": round(seconds, 2),
        }
        print(f"{name}: {scene['type']} (expected {EXPECTED[name]}) in {seconds:.1f} s; " + "; ".join(scene["reasons"]))
    out = REPO / "bench" / "results" / "normalize.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json(out, results)
    print(f"wrote {out.relative_to(REPO)}")


if __name__ == "__main__":
    main()
