"""OpenMVG's scene (`sfm_data.json`: the SfM_Data its incremental or global SfM made, as JSON;
`openMVG_main_ConvertSfM_DataFormat` writes it from the usual sfm_data.bin), read for the importer (`imported`).

The file is cereal's JSON. `views` and `intrinsics` are lists of {key, value}, each value an object behind a pointer
(`ptr_wrapper`'s `data`). An intrinsic's type is named (`polymorphic_name`) the first time the file holds one of it;
later ones give its number alone (`polymorphic_id`: the first carries it with its high bit set). A view gives its
photo's file name and the ids of its intrinsic and pose; `extrinsics` the poses, each a world-to-camera rotation (its
rows) and the camera's centre, in OpenCV's camera axes (x right, y down, z forward). An intrinsic is a pinhole in
pixels of a `width` x `height` photo (one focal length, its principal point) and its lens: radial terms as OpenCV's,
Brown's t1 and t2 as OpenCV's p1 and p2, a fisheye's k1-k4 as OpenCV's; a spherical camera's frames are a 360
camera's, which ingest cuts into views. A view without a pose (the listing made before SfM, `matches/sfm_data.json`,
or a photo SfM did not place) leaves its photo without one."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap

from plenoxels.core.cameras import Intrinsics, opengl_c2w_from_colmap_w2c
from plenoxels.core.errors import UserError
from stages.sfm.imported_model import (NO_LENS, CameraTable, Imported, Lens, add_image, add_view, at_ingested_size,
                                       file_stem, finite_number)

GRAVITY = None  # SfM's frame (or a GPS prior's, which the file does not name)
# OpenMVG's lenses as COLMAP models them: the model, and where each of COLMAP's coefficients is in the intrinsic's
# own list (None: a term OpenMVG's lens lacks).
LENSES = {"pinhole": (None, "OPENCV", ()),
          "pinhole_radial_k1": ("disto_k1", "OPENCV", (0, None, None, None)),
          "pinhole_radial_k3": ("disto_k3", "FULL_OPENCV", (0, 1, None, None, 2, None, None, None)),
          "pinhole_brown_t2": ("disto_t2", "FULL_OPENCV", (0, 1, 3, 4, 2, None, None, None)),
          "fisheye": ("fisheye", "OPENCV_FISHEYE", (0, 1, 2, 3))}
SPHERICAL = "spherical"
HIGH_BIT = 0x80000000


def _objects(entries, where: str) -> dict[str, tuple[str | None, dict]]:
    """A cereal list of {key, value} with its pointers: each key's type name (None: the base type) and data."""
    if not isinstance(entries, list):
        raise TypeError(where)
    names: dict[int, str] = {}
    found = {}
    for entry in entries:
        value = entry["value"]
        number = int(value.get("polymorphic_id", 0))
        if "polymorphic_name" in value:
            names[number & ~HIGH_BIT] = str(value["polymorphic_name"])
        found[str(entry["key"])] = (names.get(number & ~HIGH_BIT), value["ptr_wrapper"]["data"])
    return found


def read(path: Path) -> tuple[dict, dict, dict]:
    """An sfm_data.json's views (by key: their data), intrinsics (by key: type name and data) and poses (by key)."""
    try:
        data = json.loads(path.read_text())
        views = {key: view for key, (_, view) in _objects(data["views"], "views").items()}
        intrinsics = _objects(data.get("intrinsics", []), "intrinsics")
        poses = {str(entry["key"]): entry["value"] for entry in data.get("extrinsics", [])}
        if not all(isinstance(item, dict) for item in [*views.values(), *poses.values()]):
            raise TypeError
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError):
        raise UserError(f"{path} is not OpenMVG's SfM_Data as JSON (views, intrinsics and extrinsics); convert it "
                        "again with openMVG_main_ConvertSfM_DataFormat or set poses.source=sfm") from None
    return views, intrinsics, poses


def _numbers(values, count: int, name: str, where: str) -> np.ndarray:
    flat = [v for row in values for v in (row if isinstance(row, list) else [row])] if isinstance(values, list) else []
    if len(flat) != count:
        raise UserError(f"{where}: {name} is not {count} numbers; fix it or set poses.source=sfm")
    return np.array([finite_number(v, name, where) for v in flat])


def camera_to_world(pose: dict, where: str) -> np.ndarray:
    """A pose's camera-to-world (ours) from its world-to-camera rotation and centre."""
    rotation = _numbers(pose.get("rotation"), 9, "rotation", where).reshape(3, 3)
    centre = _numbers(pose.get("center"), 3, "center", where)
    if abs(np.linalg.det(rotation)) < 1e-9:
        raise UserError(f"{where}: the pose's rotation is not invertible; fix it or set poses.source=sfm")
    return opengl_c2w_from_colmap_w2c(rotation, -rotation @ centre)


def camera(kind: str | None, intrinsic: dict, where: str) -> tuple[Intrinsics, Lens]:
    """An intrinsic's pinhole (for its width x height) and lens."""
    if kind not in LENSES:
        raise UserError(f"{where}: its camera is OpenMVG's {kind or 'unnamed'} intrinsic, which this tool does not "
                        f"read ({', '.join([*LENSES, SPHERICAL])}); set poses.source=sfm")
    key, model, order = LENSES[kind]
    width, height, focal = (finite_number(intrinsic.get(name), name, where, positive=True)
                            for name in ("width", "height", "focal_length"))
    cx, cy = _numbers(intrinsic.get("principal_point"), 2, "principal_point", where)
    given = _numbers(intrinsic.get(key), len(set(order) - {None}), key, where) if key else []
    coefficients = tuple(0.0 if index is None else float(given[index]) for index in order)
    lens = (model, coefficients) if any(coefficients) or model == "OPENCV_FISHEYE" else NO_LENS
    return Intrinsics(focal, focal, cx, cy, int(round(width)), int(round(height))), lens


def imported(path: Path, records: list[dict]) -> Imported:
    """Poses from OpenMVG's sfm_data.json: a photo takes the view of its file's stem, where one view alone has it and
    SfM posed it."""
    views, intrinsics, poses = read(path)
    if not poses:
        raise UserError(f"{path} holds no poses (OpenMVG's image listing, made before its SfM); give the sfm_data.json "
                        "its SfM made (openMVG_main_ConvertSfM_DataFormat writes it from sfm_data.bin) or set "
                        "poses.source=sfm")
    by_stem: dict[str, list[dict]] = {}
    for view in views.values():
        by_stem.setdefault(file_stem(str(view.get("filename", ""))), []).append(view)
    reconstruction = pycolmap.Reconstruction()
    cameras = CameraTable(reconstruction)
    missing = []
    for record in records:
        named = by_stem.get(file_stem(record["source"]), [])
        pose = poses.get(str(named[0].get("id_pose"))) if len(named) == 1 else None
        if pose is None:
            missing.append(record["name"])
            continue
        where = f"{path.name}, view {named[0].get('id_view')} ({named[0].get('filename')})"
        c2w = camera_to_world(pose, where)
        kind, intrinsic = intrinsics.get(str(named[0].get("id_intrinsic")), (None, None))
        if not isinstance(intrinsic, dict):
            raise UserError(f"{where}: its intrinsic {named[0].get('id_intrinsic')} is not in the file; convert it "
                            "again or set poses.source=sfm")
        if "panorama" in record or kind == SPHERICAL:
            add_view(reconstruction, cameras, record, f"OpenMVG's {kind}", kind == SPHERICAL, c2w, where)
            continue
        k, lens = camera(kind, intrinsic, where)
        add_image(reconstruction, len(reconstruction.images) + 1, record,
                  cameras.id_for(at_ingested_size(k, record, where), lens), c2w, where)
    return Imported(reconstruction, path, missing, gravity=GRAVITY)
