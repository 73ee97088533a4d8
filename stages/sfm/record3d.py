"""Record3D's export (an iPhone's LiDAR capture app, as nerfstudio and svox2 read it): its frames in rgb/, named by
their number (0.jpg, 1.jpg, ...), beside metadata.json, read for the importer (`imported`).

The metadata holds `K`, the pinhole's 3x3 matrix column by column, for frames of `w` x `h` pixels, and `poses`, one a
frame: camera-to-world as a unit quaternion (x, y, z, w) and a translation, in ARKit's axes (x right, y up, z back:
ours), the world gravity-aligned. Newer exports add `perFrameIntrinsicCoeffs`, each frame's fx, fy, cx, cy (the
focal length follows the lens's focus), which are read where there is one a frame."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pycolmap

from plenoxels.core.cameras import Intrinsics
from plenoxels.core.errors import UserError
from stages.sfm.imported_model import CameraTable, Imported, add_image, at_ingested_size, file_stem
from stages.sfm.pose_files import RECORD3D_FILES as METADATA_FILES

GRAVITY = (0.0, 1.0, 0.0)  # ARKit's world: y up


def read(path: Path) -> tuple[list[Intrinsics], np.ndarray]:
    """Each frame's pinhole (at the metadata's w x h) and their poses [N, 7]."""
    try:
        data = json.loads(path.read_text())
        k = np.asarray(data["K"], dtype=np.float64).reshape(3, 3).T
        w, h = float(data["w"]), float(data["h"])
        poses = np.asarray(data["poses"], dtype=np.float64)
        per_frame = np.asarray(data.get("perFrameIntrinsicCoeffs") or np.zeros((0, 4)), dtype=np.float64)
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError):
        raise UserError(f"{path} is not Record3D's metadata (K as 9 numbers, w, h and poses as rows of 7); fix it or "
                        "set poses.source=sfm") from None
    if poses.ndim != 2 or poses.shape[1] != 7:
        raise UserError(f"{path}: its poses are {poses.shape}, not rows of 7 (a quaternion and a translation); fix it "
                        "or set poses.source=sfm")
    if not np.isfinite(k).all() or min(k[0, 0], k[1, 1], w, h) <= 0 or not (math.isfinite(w) and math.isfinite(h)):
        raise UserError(f"{path}: its K, w and h are not a camera (positive, finite focal lengths and size); fix it or "
                        "set poses.source=sfm")
    if per_frame.shape != (len(poses), 4):  # the shared K for all
        per_frame = np.tile([k[0, 0], k[1, 1], k[0, 2], k[1, 2]], (len(poses), 1))
    if not np.isfinite(per_frame).all() or per_frame[:, :2].min(initial=1.0) <= 0:
        raise UserError(f"{path}: its perFrameIntrinsicCoeffs are not positive, finite focal lengths and finite "
                        "principal points; fix it or set poses.source=sfm")
    return [Intrinsics(*row, int(round(w)), int(round(h))) for row in per_frame], poses


def camera_to_world(pose: np.ndarray, where: str) -> np.ndarray:
    """A frame's camera-to-world (ours) from its quaternion (x, y, z, w) and translation."""
    if not np.isfinite(pose).all() or abs(np.linalg.norm(pose[:4]) - 1.0) > 1e-3:
        raise UserError(f"{where}: its pose is not a unit quaternion and a translation of finite numbers; fix it or "
                        "set poses.source=sfm")
    c2w = np.eye(4)
    c2w[:3, :3] = pycolmap.Rotation3d(pose[:4]).matrix()
    c2w[:3, 3] = pose[4:]
    return c2w


def imported(path: Path, records: list[dict]) -> Imported:
    """Poses from Record3D's metadata: a frame named by its number takes that row."""
    pinholes, poses = read(path)
    reconstruction = pycolmap.Reconstruction()
    cameras = CameraTable(reconstruction)
    missing = []
    for record in records:
        number = file_stem(record["source"])
        if not number.isdigit() or int(number) >= len(poses):
            missing.append(record["name"])
            continue
        where = f"{path.name}, pose {int(number)}"
        add_image(reconstruction, len(reconstruction.images) + 1, record,
                  cameras.id_for(at_ingested_size(pinholes[int(number)], record, str(path))),
                  camera_to_world(poses[int(number)], where), where)
    return Imported(reconstruction, path, missing, gravity=GRAVITY)
