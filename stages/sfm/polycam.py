"""Polycam's raw data export (its developer mode's `keyframes/`, a LiDAR phone's capture with the poses it
optimised), read for the importer (pose_import.from_camera_files).

Each photo of keyframes/images/ has a JSON file of the same name in keyframes/cameras/, and each of
keyframes/corrected_images/ (the photos undistorted, which ingest prefers) one in keyframes/corrected_cameras/: fx,
fy, cx, cy in pixels of its width x height, and t_00 ... t_23, the camera-to-world matrix's three rows in ARKit's
axes (x right, y up, z back: ours), the world gravity-aligned."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from plenoxels.core.cameras import Intrinsics
from plenoxels.core.errors import UserError
from stages.sfm.imported_model import NO_LENS, Lens
from stages.capture.photos import POLYCAM_CAMERAS as CAMERA_FOLDERS
GRAVITY = (0.0, 1.0, 0.0)  # ARKit's world: y up
POSE_KEYS = tuple(f"t_{row}{column}" for row in range(3) for column in range(4))


def own_folders(photos: Path) -> list[Path]:
    """The camera folder beside a folder of Polycam's photos."""
    folder = photos.parent / CAMERA_FOLDERS.get(photos.name, "")
    return [folder] if photos.name in CAMERA_FOLDERS and folder.is_dir() else []


def camera(path: Path, width: int, height: int, where: str) -> tuple[Intrinsics, np.ndarray, Lens]:
    """The pinhole (at the camera file's own width x height), camera-to-world (ours) and lens (none: the photos are
    undistorted) of a camera file."""
    try:
        data = json.loads(path.read_text())
        values = [float(data[key]) for key in ("fx", "fy", "cx", "cy", "width", "height", *POSE_KEYS)]
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError):
        raise UserError(f"{where} is not a Polycam camera (fx, fy, cx, cy, width, height and t_00 ... t_23 as "
                        "numbers); fix it or set poses.source=sfm") from None
    if not all(math.isfinite(v) for v in values) or min(values[:2] + values[4:6]) <= 0:
        raise UserError(f"{where}: its focal lengths and size are not all positive, finite numbers; fix it or set "
                        "poses.source=sfm")
    fx, fy, cx, cy, w, h = values[:6]
    c2w = np.eye(4)
    c2w[:3] = np.reshape(values[6:], (3, 4))
    return Intrinsics(fx, fy, cx, cy, int(round(w)), int(round(h))), c2w, NO_LENS
