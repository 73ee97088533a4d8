"""The export's files opened in Blender itself: the `bpy` module (Blender 5.0.1 as a Python module), in its own
environment beside the project's (`make install extras=blender` puts it in .venv/blender: bpy 5.0.1 is built against
NumPy 1.x, which the project's OpenCV rules out, so the two cannot share one site-packages). bench/blender_session.py
runs there, in a child process; this side compares what it reports with the files as written.

`check_export` opens mesh.glb, mesh.obj and mesh.ply with Blender's own importers and their defaults, and checks:
- frame and scale: every sampled vertex Blender places lies on a vertex of the PLY (input frame), within
  FRAME_TOLERANCE of the mesh's size, and the bounds agree;
- the material shows the colours with no manual step: GLB and OBJ arrive with the Principled BSDF's Base Color fed by
  an Image Texture holding mesh.png (matte: metallic 0); the PLY (which holds no material), and all three without a
  texture, with the file's vertex colours as the mesh's render colour attribute, equal within COLOUR_TOLERANCE (in
  sRGB: the glTF's COLOR_0 is linear light);
- a Cycles render from a training camera of what each material's Base Color shows against
  plenoxels.surface.texture.render_mesh's render of the same file: on the pixels both cover (one pixel in from either's
  silhouette) the mean absolute difference is below RENDER_MEAN_TOLERANCE, and the covered pixels agree (IoU at least
  RENDER_MIN_IOU).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import trimesh
from scipy.ndimage import binary_erosion
from scipy.spatial import cKDTree

from stages.common.media import GLTF_FROM_ZUP
from stages.interchange.mesh_files import linear_to_srgb, srgb_to_linear
from plenoxels.core.cameras import Intrinsics
from plenoxels.surface.texture import render_mesh

REPO = Path(__file__).resolve().parent.parent
ENVIRONMENT = REPO / ".venv" / "blender"
SESSION = Path(__file__).with_name("blender_session.py")
INSTALL = "Blender's bpy module is not installed: make install extras=blender (puts bpy 5.0.1 in .venv/blender)"
FRAME_TOLERANCE = 1e-5
COLOUR_TOLERANCE = 1.5 / 255
RENDER_MEAN_TOLERANCE = 2.0 / 255
RENDER_MIN_IOU = 0.98


def missing() -> str | None:
    """Why Blender cannot run here (None when it can)."""
    if not (ENVIRONMENT / "bpy").is_dir():
        return INSTALL
    return None


def run_session(files: dict[str, Path], camera: dict | None, out: Path, timeout: float = 600) -> dict:
    """Blender imports `files` ({kind: path}) and, with `camera`, renders each (bench/blender_session.py)."""
    spec = {"files": {k: str(p) for k, p in files.items()}, "camera": camera, "out": str(out)}
    (out / "spec.json").write_text(json.dumps(spec))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ENVIRONMENT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, str(SESSION), str(out / "spec.json")], cwd=out, env=env,
                          capture_output=True, text=True, timeout=timeout)
    if not (out / "report.json").is_file():
        raise RuntimeError(f"Blender wrote no report (exit {proc.returncode}): {(proc.stdout + proc.stderr)[-3000:]}")
    return json.loads((out / "report.json").read_text())


def camera_spec(c2w: np.ndarray, k: Intrinsics, samples: int = 4) -> dict:
    return {"c2w": np.asarray(c2w, dtype=np.float64).tolist(), "fl_x": k.fl_x, "fl_y": k.fl_y, "cx": k.cx, "cy": k.cy,
            "w": k.w, "h": k.h, "samples": samples}


def as_written(path: Path) -> tuple[trimesh.Trimesh, np.ndarray | None, np.ndarray | None]:
    """A mesh file as trimesh reads it, in the frame's own axes (OBJ and GLB are y-up: GLTF_FROM_ZUP undone), with
    its UVs and texture image [H, W, 3] in [0, 1] (None, None for vertex colours)."""
    mesh = trimesh.load(path, force="mesh", process=False)
    if path.suffix in (".obj", ".glb"):
        mesh.apply_transform(np.linalg.inv(GLTF_FROM_ZUP))
    visual = mesh.visual
    if path.suffix == ".glb" and visual.kind == "vertex":
        # glTF's COLOR_0 is linear light (trimesh writes it so, and reads it back as stored); Blender shows sRGB.
        linear = visual.vertex_colors[:, :3] / 255.0
        visual.vertex_colors[:, :3] = np.round(linear_to_srgb(linear) * 255.0).astype(np.uint8)
    if visual.kind == "texture" and getattr(visual, "uv", None) is not None:
        material = visual.material
        image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
        if image is not None:
            return mesh, np.asarray(visual.uv), np.asarray(image.convert("RGB"), dtype=np.float64) / 255.0
    return mesh, None, None


def compare_render(blender_png: Path, path: Path, c2w: np.ndarray, k: Intrinsics) -> dict:
    """Blender's render against render_mesh's of the same file (module docstring)."""
    rgba = iio.imread(blender_png).astype(np.float64) / 255.0
    mesh, uv, image = as_written(path)
    if uv is not None:
        ours, covered = render_mesh(mesh.vertices, mesh.faces, c2w, k, uv=uv, image=image)
    else:  # Blender blends vertex colours in linear light
        linear, covered = render_mesh(mesh.vertices, mesh.faces, c2w, k,
                                      vertex_colours=srgb_to_linear(mesh.visual.vertex_colors[:, :3] / 255.0))
        ours = linear_to_srgb(linear)
    theirs = rgba[..., 3] > 0.5
    both = binary_erosion(covered & theirs, iterations=1)
    difference = np.abs(rgba[..., :3] - ours)[both]
    union = (covered | theirs).sum()
    return {"pixels": int(both.sum()), "iou": float((covered & theirs).sum() / max(union, 1)),
            "mean_abs_difference": float(difference.mean()) if len(difference) else None,
            "p99_abs_difference": float(np.quantile(difference, 0.99)) if len(difference) else None}


def check_export(export_dir: Path, camera: tuple[np.ndarray, Intrinsics] | None, work: Path | None = None) -> dict:
    """Blender opens the export's GLB, OBJ and PLY (module docstring); `camera`: a training camera (input frame) to
    render from; `work`: a folder to keep Blender's report and renders in (<kind>.png). Returns what it found, the
    comparisons and `ok`; {"ran": False, "why": ...} without Blender."""
    why = missing()
    if why:
        return {"ran": False, "why": why}
    export_dir = Path(export_dir)
    files = {kind: export_dir / f"mesh.{kind}" for kind in ("glb", "obj", "ply")}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(work) if work is not None else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        started = time.time()
        report = run_session(files, camera_spec(*camera) if camera else None, folder)
        seconds = time.time() - started
        ply = trimesh.load(files["ply"], force="mesh", process=False)
        size = float(np.max(ply.bounds[1] - ply.bounds[0]))
        tree = cKDTree(ply.vertices)
        png = export_dir / "mesh.png"
        texture_size = list(iio.imread(png).shape[1::-1]) if png.is_file() else None
        result = {"ran": True, "blender": report["blender"], "seconds": round(seconds, 1), "files": {}}
        for kind, seen in report["files"].items():
            gap, nearest = tree.query(np.asarray(seen["positions"]))
            entry = {"objects": seen["objects"], "vertices": seen["vertices"], "faces": seen["faces"],
                     "bounds": seen.get("bounds"),
                     "ply_faces": len(ply.faces), "largest_offset_share": float(gap.max() / size),
                     "bounds_offset_share": float(np.abs(np.asarray(seen["bounds"]) - ply.bounds).max() / size),
                     "materials": seen["materials"], "colour_attributes": [
                         {k: v for k, v in a.items() if k != "sample_srgb"} for a in seen["colour_attributes"]]}
            checks = {"one_object": seen["objects"] == 1, "faces": seen["faces"] == len(ply.faces),
                      "frame": entry["largest_offset_share"] < FRAME_TOLERANCE
                      and entry["bounds_offset_share"] < FRAME_TOLERANCE}
            if kind == "ply" or texture_size is None:
                active = [a for a in seen["colour_attributes"] if a.get("render_active") and "sample_srgb" in a]
                if active:
                    written = as_written(files[kind])[0]
                    _, at = cKDTree(written.vertices).query(np.asarray(seen["positions"]))
                    error = np.abs(np.asarray(active[0]["sample_srgb"]) - written.visual.vertex_colors[at, :3] / 255.0)
                    entry["colour_max_error"] = float(error.max())
                checks["colours"] = bool(active) and entry.get("colour_max_error", 1.0) <= COLOUR_TOLERANCE
            else:
                materials = seen["materials"]
                checks["texture"] = bool(materials) and all(
                    m["base_color_from"] == "TEX_IMAGE" and m["image"] is not None and m["image"]["size"] == texture_size
                    and (m["metallic"] or 0.0) == 0.0 for m in materials)
            if "render" in seen:
                entry["render"] = compare_render(Path(seen["render"]), files[kind], *camera)
                checks["render"] = (entry["render"]["mean_abs_difference"] is not None
                                    and entry["render"]["mean_abs_difference"] < RENDER_MEAN_TOLERANCE
                                    and entry["render"]["iou"] >= RENDER_MIN_IOU)
            entry["checks"] = checks
            entry["ok"] = all(checks.values())
            result["files"][kind] = entry
    result["ok"] = all(entry["ok"] for entry in result["files"].values())
    return result
