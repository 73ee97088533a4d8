"""Meshroom's (AliceVision's) cameras: the SfMData file its StructureFromMotion node writes (`cameras.sfm`, JSON),
read for the importer (`imported`).

Every value is written as a string. `views` give each photo's path, its pose's and camera's ids; `poses` a rotation
(world-to-camera, in OpenCV's camera axes: x right, y down, z forward; its nine numbers column by column) and the
camera's centre (a camera of a rig posed as one: its rig's pose, and its sub-pose in `rigs`); `intrinsics` a camera for photos of `width` x `height`: its focal length and principal point, whose
units changed with the file's `version` (`focal_lengths`), and its lens (`distortionType`, and its
`distortionParams`). A photo SfM did not place has a view and no pose."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from plenoxels.core.cameras import Intrinsics, opengl_c2w_from_colmap_w2c
from plenoxels.core.errors import UserError
from stages.sfm.imported_model import (NO_LENS, CameraTable, Imported, Lens, add_image, at_ingested_size, file_stem,
                                       finite_number)

GRAVITY = None  # SfM's frame, wherever its first pair put it
# AliceVision's lenses as COLMAP models them: the model and the coefficients' order (their names in AliceVision's
# distortionParams, 0 where COLMAP has a term AliceVision lacks). The files before version 1.2.8 name the lens in
# the camera's `type`.
LENSES = {"none": ("OPENCV", ()), "radialk1": ("OPENCV", ("k1", 0, 0, 0)),
          "radialk3": ("FULL_OPENCV", ("k1", "k2", 0, 0, "k3", 0, 0, 0)),
          "brown": ("FULL_OPENCV", ("k1", "k2", "t1", "t2", "k3", 0, 0, 0)),
          "fisheye4": ("OPENCV_FISHEYE", ("k1", "k2", "k3", "k4"))}
PARAMETERS = {"none": (), "radialk1": ("k1",), "radialk3": ("k1", "k2", "k3"), "brown": ("k1", "k2", "k3", "t1", "t2"),
              "fisheye4": ("k1", "k2", "k3", "k4")}
OLDER_TYPES = {"pinhole": "none", "radial1": "radialk1", "radial3": "radialk3", "brown": "brown",
               "fisheye4": "fisheye4"}


@dataclass
class SfmData:
    version: tuple[int, ...]
    views: list[dict]
    intrinsics: dict[str, dict]       # by intrinsicId
    poses: dict[str, dict]            # by poseId
    rigs: dict[str, list[dict]]       # by rigId: its sub-poses, by subPoseId


def read(path: Path) -> SfmData:
    try:
        data = json.loads(path.read_text())
        found = SfmData(tuple(int(v) for v in data.get("version", ["1", "0", "0"])),
                        [view for view in data["views"] if isinstance(view, dict)],
                        {str(i["intrinsicId"]): i for i in data.get("intrinsics", []) if isinstance(i, dict)},
                        {str(p["poseId"]): p["pose"] for p in data.get("poses", []) if isinstance(p, dict)},
                        {str(r["rigId"]): list(r.get("subPoses", [])) for r in data.get("rigs", [])
                         if isinstance(r, dict)})
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError):
        raise UserError(f"{path} is not Meshroom's SfMData (a JSON object with views, intrinsics and poses); export "
                        "it again from the StructureFromMotion node or set poses.source=sfm") from None
    return found


def _numbers(values, count: int, name: str, where: str) -> np.ndarray:
    if not isinstance(values, list) or len(values) != count:
        raise UserError(f"{where}: {name} is not {count} numbers; fix it or set poses.source=sfm")
    return np.array([finite_number(v, name, where) for v in values])


def _world_to_camera(transform, where: str) -> np.ndarray:
    """A transform's 4x4 world-to-camera (OpenCV's axes)."""
    if not isinstance(transform, dict):
        raise UserError(f"{where}: the pose has no transform; fix it or set poses.source=sfm")
    rotation = _numbers(transform.get("rotation"), 9, "rotation", where).reshape(3, 3).T  # written column by column
    centre = _numbers(transform.get("center"), 3, "center", where)
    if abs(np.linalg.det(rotation)) < 1e-9:
        raise UserError(f"{where}: the pose's rotation is not invertible; fix it or set poses.source=sfm")
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = rotation, -rotation @ centre
    return w2c


def camera_to_world(view: dict, sfm: SfmData, where: str) -> np.ndarray | None:
    """A view's camera-to-world (ours); None where SfM did not place it. A camera of a rig posed as one (not
    `isPoseIndependant`) is its rig's pose moved by its sub-pose."""
    pose = sfm.poses.get(str(view.get("poseId")))
    if pose is None:
        return None
    w2c = _world_to_camera(pose.get("transform") if isinstance(pose, dict) else None, where)
    if "rigId" in view and str(view.get("isPoseIndependant", "true")).lower() in ("false", "0"):
        sub_poses, index = sfm.rigs.get(str(view["rigId"]), []), view.get("subPoseId")
        if not str(index).isdigit() or int(index) >= len(sub_poses) or not isinstance(sub_poses[int(index)], dict):
            raise UserError(f"{where}: its rig {view['rigId']} has no sub-pose {index}; export it again or set "
                            "poses.source=sfm")
        w2c = _world_to_camera(sub_poses[int(index)].get("pose"), where) @ w2c
    return opengl_c2w_from_colmap_w2c(w2c[:3, :3], w2c[:3, 3])


def focal_lengths(intrinsic: dict, version: tuple[int, ...], width: float, height: float,
                  where: str) -> tuple[float, float]:
    """fx, fy in pixels. From 1.2.2 the file gives millimetres on a sensor `sensorWidth` wide and a ratio of the two,
    which was fx / fy until 1.2.5, fy / fx since; since 1.2.11 the millimetres are fy's, across the longer side."""
    if version < (1, 2, 2):
        focal = intrinsic.get("pxFocalLength")
        fx, fy = (focal, focal) if version < (1, 2, 0) or not isinstance(focal, list) else (focal + [None, None])[:2]
        return finite_number(fx, "pxFocalLength", where), finite_number(fy, "pxFocalLength", where)
    millimetres = finite_number(intrinsic.get("focalLength"), "focalLength", where)
    sensor = finite_number(intrinsic.get("sensorWidth", 36.0), "sensorWidth", where)
    ratio = finite_number(intrinsic.get("pixelRatio", 1.0), "pixelRatio", where)
    if min(sensor, ratio) <= 0:
        raise UserError(f"{where}: sensorWidth and pixelRatio must be positive; fix it or set poses.source=sfm")
    if version >= (1, 2, 11):
        fy = millimetres * max(width, height) / sensor
        return fy / ratio, fy
    fx = millimetres * width / sensor
    return fx, (fx / ratio if version < (1, 2, 5) else fx * ratio)


def camera(intrinsic: dict, version: tuple[int, ...], where: str) -> tuple[Intrinsics, Lens]:
    """An intrinsic's pinhole (for its width x height) and lens."""
    width, height = (finite_number(intrinsic.get(key), key, where) for key in ("width", "height"))
    kind = str(intrinsic.get("type", "")).lower()
    lens_name = OLDER_TYPES.get(kind) if version < (1, 2, 8) else \
        str(intrinsic.get("distortionType", "none")).lower() if kind == "pinhole" else None
    undistortion = str(intrinsic.get("undistortionType", "none")).lower()
    if lens_name not in LENSES or undistortion != "none":
        raise UserError(f"{where}: its camera is AliceVision's {kind} ({intrinsic.get('distortionType', kind)} lens"
                        f"{', ' + undistortion + ' undistortion' if undistortion != 'none' else ''}), which this tool "
                        f"does not read; reconstruct with a pinhole camera ({', '.join(LENSES)} lens) or set "
                        "poses.source=sfm")
    fx, fy = focal_lengths(intrinsic, version, width, height, where)
    offset = _numbers(intrinsic.get("principalPoint"), 2, "principalPoint", where)
    if version >= (1, 2, 1):  # from the photo's centre
        offset = offset + [width / 2, height / 2]
    if min(fx, fy, width, height) <= 0:
        raise UserError(f"{where}: its focal lengths and size are not positive; fix it or set poses.source=sfm")
    given = intrinsic.get("distortionParams", []) if lens_name != "none" else []  # AliceVision ignores those, too
    values = dict(zip(PARAMETERS[lens_name], _numbers(given, len(PARAMETERS[lens_name]), "distortionParams", where)))
    model, order = LENSES[lens_name]
    coefficients = tuple(values[term] if isinstance(term, str) else 0.0 for term in order)
    lens = (model, coefficients) if any(coefficients) or model == "OPENCV_FISHEYE" else NO_LENS
    return Intrinsics(fx, fy, offset[0], offset[1], int(round(width)), int(round(height))), lens


def imported(path: Path, records: list[dict]) -> Imported:
    """Poses from Meshroom's SfMData: a photo takes the view of its file's stem, where one view alone has it and SfM
    placed it."""
    sfm = read(path)
    by_stem: dict[str, list[dict]] = {}
    for view in sfm.views:
        by_stem.setdefault(file_stem(str(view.get("path", ""))), []).append(view)
    reconstruction = pycolmap.Reconstruction()
    cameras = CameraTable(reconstruction)
    missing = []
    for record in records:
        named = by_stem.get(file_stem(record["source"]), [])
        where = f"{path.name}, view {named[0].get('viewId')} ({Path(str(named[0].get('path'))).name})" if named else ""
        c2w = camera_to_world(named[0], sfm, where) if len(named) == 1 else None
        if c2w is None:
            missing.append(record["name"])
            continue
        intrinsic = sfm.intrinsics.get(str(named[0].get("intrinsicId")))
        if intrinsic is None:
            raise UserError(f"{where}: its intrinsic {named[0].get('intrinsicId')} is not in the file; export it "
                            "again or set poses.source=sfm")
        k, lens = camera(intrinsic, sfm.version, where)
        add_image(reconstruction, len(reconstruction.images) + 1, record,
                  cameras.id_for(at_ingested_size(k, record, where), lens), c2w, where)
    return Imported(reconstruction, path, missing, gravity=GRAVITY)
