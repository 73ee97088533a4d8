"""MVSNet's camera files (its Tanks and Temples and DTU releases, and the multi-view stereo sets laid out as they are):
`cams/<name>_cam.txt` beside `images/<name>.jpg`, read for the importer (pose_import.from_camera_files).

A camera file holds the word `extrinsic` and the 4x4 world-to-camera matrix (OpenCV's camera axes: x right, y down,
z forward) row by row, the word `intrinsic` and the pinhole's 3x3 K for the photo as stored, then the depth range the
stereo searches (not read)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from plenoxels.core.cameras import Intrinsics, opengl_c2w_from_colmap_w2c
from plenoxels.core.errors import UserError
from stages.sfm.imported_model import NO_LENS, Lens

GRAVITY = None  # the world is whatever frame the poses were made in
CAMERA_FOLDER = "cams"
SUFFIX = "_cam.txt"


def own_folders(photos: Path) -> list[Path]:
    """The camera folder beside a folder of photos."""
    return [photos.parent / CAMERA_FOLDER] if (photos.parent / CAMERA_FOLDER).is_dir() else []


def _matrix(lines: list[str], word: str, size: int, path: Path, where: str) -> np.ndarray:
    """The size x size matrix on the lines after the one that reads `word`."""
    try:
        start = next(i for i, line in enumerate(lines) if line.strip().lower() == word) + 1
        rows = [[float(v) for v in line.split()] for line in lines[start:start + size]]
        matrix = np.array(rows, dtype=np.float64)
    except (StopIteration, ValueError):
        matrix = np.zeros(0)
    if matrix.shape != (size, size) or not all(math.isfinite(v) for v in matrix.ravel()):
        raise UserError(f"{where}: {path.name} has no {size}x{size} {word} matrix of finite numbers after the word "
                        f"{word}; fix it or set poses.source=sfm")
    return matrix


def camera(path: Path, width: int, height: int, where: str) -> tuple[Intrinsics, np.ndarray, Lens]:
    """The pinhole (for its photo, stored at width x height), camera-to-world (ours) and lens (none) of a camera
    file."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError):
        raise UserError(f"{where}: {path.name} is not a text file; fix it or set poses.source=sfm") from None
    w2c, k = _matrix(lines, "extrinsic", 4, path, where), _matrix(lines, "intrinsic", 3, path, where)
    if abs(np.linalg.det(w2c[:3, :3])) < 1e-9:
        raise UserError(f"{where}: {path.name}'s extrinsic matrix is not an invertible pose; fix it or set "
                        "poses.source=sfm")
    if min(k[0, 0], k[1, 1]) <= 0:
        raise UserError(f"{where}: {path.name} gives a focal length of {min(k[0, 0], k[1, 1]):g}, not a positive one; "
                        "fix it or set poses.source=sfm")
    pinhole = Intrinsics(k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height)
    return pinhole, opengl_c2w_from_colmap_w2c(w2c[:3, :3], w2c[:3, 3]), NO_LENS
