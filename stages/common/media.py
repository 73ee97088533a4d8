"""Media files shared by the stages: 8-bit RGB images in and out, point clouds (PLY). Meshes: stages/interchange/mesh_files.py;
the pipeline's own JSON records: stages/common/json_files.py."""
from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import trimesh
from trimesh.exchange.ply import export_ply


def read_rgb(path: Path) -> np.ndarray:
    """An 8-bit RGB image [h, w, 3] (the ingest stage has already normalised every image to this)."""
    return rgb_of(iio.imread(path))


def rgb_of(image: np.ndarray) -> np.ndarray:
    """The RGB channels [h, w, 3] of a decoded image: grey repeated, alpha dropped."""
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    return np.ascontiguousarray(image[..., :3])


def write_png(path: Path, image: np.ndarray) -> None:
    iio.imwrite(path, np.ascontiguousarray(image), extension=".png")


# glTF is y-up; these axes make a z-up frame stand upright in glTF viewers, and importers that convert
# glTF to z-up (Blender) get the frame's own coordinates back.
GLTF_FROM_ZUP = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])


def write_points(path: Path, points: np.ndarray, colours: np.ndarray, normals: np.ndarray) -> None:
    """A binary PLY of vertices with normals and 8-bit colours (no faces)."""
    cloud = trimesh.Trimesh(vertices=points, faces=np.zeros((0, 3), dtype=np.int64), vertex_normals=normals,
                            vertex_colors=rgba8(colours), process=False)
    path.write_bytes(export_ply(cloud, encoding="binary", vertex_normal=True))


def rgba8(colours: np.ndarray) -> np.ndarray:
    """Float RGB [N, 3] in [0, 1] -> opaque 8-bit RGBA [N, 4]."""
    rgb = np.round(np.clip(colours, 0.0, 1.0) * 255).astype(np.uint8)
    return np.concatenate([rgb, np.full((len(rgb), 1), 255, dtype=np.uint8)], axis=1)
