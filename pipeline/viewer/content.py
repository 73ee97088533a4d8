"""What a scene's output folder holds for the viewer, all in the normalised world (scene.json's frame):
cameras with thumbnails of their photos, sparse points, the exported mesh, point cloud and splats, the
foreground box, the scale and the up direction. Each part is None where its stage has not run."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from stages.common.json_files import read_json
from stages.interchange.splat_files import read_splat_ply
from plenoxels.core.cameras import Intrinsics
from plenoxels.core.errors import UserError
from plenoxels.splats.model import Splats
from stages.common.layout import EXPORT_JSON, MESH_PLY, POINTS_NPZ, scene_json, stage_file

# Longest side of the photo thumbnails drawn inside the camera frustums.
THUMBNAIL_SIDE = 160
# The normalised world is z up (normalize's convention).
UP = (0.0, 0.0, 1.0)


@dataclass
class ViewCamera:
    name: str
    split: str
    c2w: np.ndarray
    """Camera-to-world 4x4, OpenGL convention (looks along -z, y up)."""
    intrinsics: Intrinsics
    thumbnail: np.ndarray | None
    """uint8 RGB photo, longest side THUMBNAIL_SIDE, or None when the file is missing."""


@dataclass
class SceneContent:
    out: Path
    cameras: list[ViewCamera] = field(default_factory=list)
    foreground: tuple[np.ndarray, np.ndarray] | None = None
    scale: float | None = None
    sparse_points: tuple[np.ndarray, np.ndarray] | None = None
    """(xyz [N,3], rgb uint8 [N,3])."""
    mesh: trimesh.Trimesh | None = None
    points: tuple[np.ndarray, np.ndarray] | None = None
    """The exported point cloud (xyz [N,3], rgb uint8 [N,3])."""
    splats: Splats | None = None
    """The exported Gaussian splats."""

    @property
    def radius(self) -> float:
        """How far the cameras stand from the origin (median), the size things are drawn at."""
        if self.cameras:
            return float(np.median([np.linalg.norm(c.c2w[:3, 3]) for c in self.cameras])) or 1.0
        return 1.0


def load_content(out: Path) -> SceneContent:
    """Reads what exists under `out`; the normalize stage's scene.json is required."""
    scene_path = scene_json(out)
    if not scene_path.is_file():
        raise UserError(f"{out} has no normalize/scene.json: run the pipeline up to normalize first "
                        f"(make normalize scene=PATH), or give the scene's output folder")
    scene = read_json(scene_path)
    world_from_input = np.asarray(scene.get("world_from_input", np.eye(4)), dtype=np.float64)
    content = SceneContent(out=out, scale=scene.get("scale"))
    fg = scene.get("foreground")
    if fg:
        content.foreground = (np.asarray(fg["min"], dtype=np.float64), np.asarray(fg["max"], dtype=np.float64))
    for frame in scene.get("frames", []):
        content.cameras.append(ViewCamera(
            name=frame.get("name", ""), split=frame.get("split", "train"),
            c2w=np.asarray(frame["transform_matrix"], dtype=np.float64), intrinsics=Intrinsics.from_frame(frame),
            thumbnail=_thumbnail(out / frame["file_path"]) if frame.get("file_path") else None))
    content.sparse_points = _sparse_points(stage_file(out, "poses", POINTS_NPZ), world_from_input)
    export = out / "export"
    if (export / EXPORT_JSON).is_file():
        to_world = world_from_input if read_json(export / EXPORT_JSON).get("frame", "input") == "input" else np.eye(4)
        if (export / MESH_PLY).is_file():
            content.mesh = trimesh.load(export / MESH_PLY, force="mesh", process=False)
            content.mesh.apply_transform(to_world)
        if (export / "points.ply").is_file():
            cloud = trimesh.load(export / "points.ply")
            xyz = trimesh.transform_points(np.asarray(cloud.vertices, dtype=np.float64), to_world)
            content.points = (xyz, _colours(cloud.colors if hasattr(cloud, "colors") else None, len(xyz)))
        if (export / "splats.ply").is_file():
            content.splats = read_splat_ply(export / "splats.ply").transformed(to_world)
    return content


def _thumbnail(path: Path) -> np.ndarray | None:
    if not path.is_file():
        return None
    with Image.open(path) as image:
        image = image.convert("RGB")
        image.thumbnail((THUMBNAIL_SIDE, THUMBNAIL_SIDE))
        return np.asarray(image)


def _sparse_points(path: Path, world_from_input: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    if not path.is_file():
        return None
    with np.load(path) as data:
        xyz = np.asarray(data["xyz"], dtype=np.float64).reshape(-1, 3)
        rgb = np.asarray(data["rgb"], dtype=np.uint8).reshape(-1, 3) if "rgb" in data else None
    if len(xyz) == 0:
        return None
    return trimesh.transform_points(xyz, world_from_input), _colours(rgb, len(xyz))


def _colours(colours, n: int) -> np.ndarray:
    if colours is None or len(colours) != n:
        return np.full((n, 3), 200, dtype=np.uint8)
    return np.asarray(colours, dtype=np.uint8)[:, :3]
