"""NSVF's and NeRF++'s camera files, one text file a photo (the format svox2 reads Tanks and Temples and its own
captures in), read for the importer (pose_import.from_camera_files).

A photo's pose is a text file named as the photo in a pose folder beside the photos' folder: NSVF keeps rgb/ and
pose/ side by side, NeRF++ rgb/, pose/ and intrinsics/ in each of train/, validation/ and test/. A pose is
camera-to-world, 16 or 12 numbers (a 4x4 or 3x4 matrix, row by row), in OpenCV's camera axes (x right, y down,
z forward); NSVF's extrinsic/ holds world-to-camera ones instead. The intrinsics are a pinhole's K, 4x4 or 3x3, for
the photo as stored (its pixel centres at +0.5, as COLMAP's): NeRF++ one file a photo in intrinsics/, NSVF one
intrinsics.txt for all (or intrinsic/, a file a photo), or NSVF's older form whose first line is `f cx cy 0`. A line
of two numbers before or after the matrix (an image size some of NSVF's files add) is not part of it."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from plenoxels.core.cameras import Intrinsics, OPENCV_TO_OPENGL_AXES, opengl_c2w_from_colmap_w2c
from plenoxels.core.errors import UserError
from stages.sfm.imported_model import NO_LENS, Lens
from stages.capture.photos import POSE_FOLDERS

GRAVITY = None  # the world is whatever frame the poses were made in
INTRINSICS_FOLDERS = ("intrinsics", "intrinsic")
INTRINSICS_FILES = ("intrinsics.txt", "intrinsic.txt")


def own_folders(photos: Path) -> list[Path]:
    """The pose folders beside a folder of photos."""
    return [photos.parent / name for name in POSE_FOLDERS if (photos.parent / name).is_dir()]


def camera(pose_file: Path, width: int, height: int, where: str) -> tuple[Intrinsics, np.ndarray, Lens]:
    """The pinhole (for its photo, stored at width x height), camera-to-world (ours) and lens (none) of a pose
    file."""
    k_file = intrinsics_file(pose_file)
    if k_file is None:
        raise UserError(f"{where} has no intrinsics beside it (intrinsics.txt, or intrinsics/{pose_file.name}); add "
                        "them or set poses.source=sfm")
    return intrinsics(k_file, width, height, where), camera_to_world(pose_file, where), NO_LENS


def intrinsics_file(pose_file: Path) -> Path | None:
    """The intrinsics of the photo whose pose is `pose_file`: its own file, else the one its folder shares."""
    root = pose_file.parent.parent
    own = [root / folder / pose_file.name for folder in INTRINSICS_FOLDERS]
    return next((path for path in own + [root / name for name in INTRINSICS_FILES] if path.is_file()), None)


def _rows(path: Path, where: str) -> list[list[float]]:
    try:
        rows = [[float(word) for word in line.split()] for line in path.read_text().splitlines() if line.strip()]
    except (OSError, UnicodeDecodeError, ValueError):
        raise UserError(f"{where}: {path.name} is not a text file of numbers; fix it or set poses.source=sfm") from None
    if rows and len(rows[0]) == 2:
        rows = rows[1:]
    if rows and len(rows[-1]) == 2:
        rows = rows[:-1]
    if not rows or not all(math.isfinite(v) for row in rows for v in row):
        raise UserError(f"{where}: {path.name} holds no finite numbers; fix it or set poses.source=sfm")
    return rows


def camera_to_world(path: Path, where: str) -> np.ndarray:
    """A pose file's camera-to-world, in our (OpenGL) camera axes; 3x4 or 4x4 as written (pose_import checks it)."""
    numbers = [v for row in _rows(path, where) for v in row]
    if len(numbers) not in (12, 16):
        raise UserError(f"{where}: {path.name} holds {len(numbers)} numbers, not a 4x4 or 3x4 pose; fix it or set "
                        "poses.source=sfm")
    matrix = np.eye(4)
    matrix[:len(numbers) // 4] = np.reshape(numbers, (-1, 4))
    if path.parent.name == "extrinsic":  # NSVF's world-to-camera
        if abs(np.linalg.det(matrix[:3, :3])) < 1e-9:
            raise UserError(f"{where}: {path.name} is not an invertible pose; fix it or set poses.source=sfm")
        return opengl_c2w_from_colmap_w2c(matrix[:3, :3], matrix[:3, 3])
    return matrix @ OPENCV_TO_OPENGL_AXES


def intrinsics(path: Path, width: int, height: int, where: str) -> Intrinsics:
    """The pinhole an intrinsics file describes, for a photo stored at width x height."""
    rows = _rows(path, where)
    if all(len(row) == len(rows[0]) for row in rows) and len(rows) * len(rows[0]) in (9, 16):
        k = np.reshape([v for row in rows for v in row], (3, 3) if len(rows) * len(rows[0]) == 9 else (4, 4))
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    elif len(rows[0]) == 4:  # NSVF's older form: f cx cy 0 on the first line
        fx = fy = rows[0][0]
        cx, cy = rows[0][1], rows[0][2]
    else:
        raise UserError(f"{where}: {path.name} is neither a 3x3 or 4x4 camera matrix nor NSVF's `f cx cy 0` line; fix "
                        "it or set poses.source=sfm")
    if min(fx, fy) <= 0:
        raise UserError(f"{where}: {path.name} gives a focal length of {min(fx, fy):g}, not a positive one; fix it or "
                        "set poses.source=sfm")
    return Intrinsics(float(fx), float(fy), float(cx), float(cy), width, height)
