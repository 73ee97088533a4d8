"""OpenSfM's reconstruction.json, as OpenDroneMap writes it beside a drone survey's photos (`opensfm/`), turned into
the distorted COLMAP model the other importers make (pose_import.py).

OpenSfM's cameras (its documentation's geometric models) measure pixels in normalised image coordinates: from the
image's centre, in units of its longer side, the top-left pixel's centre at half a pixel in. A point (X, Y, Z) in
the camera's axes (x right, y down, z forward: OpenCV's) is seen at x = X/Z, y = Y/Z:
- perspective: focal * (1 + k1 r^2 + k2 r^4) * (x, y), COLMAP's RADIAL (as OPENCV, its p1 = p2 = 0);
- brown: radial k1-k3 and tangential p1, p2 as OpenCV's, focal_x, focal_y and c_x, c_y off the centre: FULL_OPENCV;
- fisheye: the angle from the axis bent by k1, k2 (fisheye_opencv: k1-k4, with c_x, c_y): OPENCV_FISHEYE;
- spherical and equirectangular: a 360 camera's frames, which ingest cuts into views (imported_model.add_view).
A shot's rotation is world-to-camera as an axis times its angle, its translation t such that a point's camera
coordinates are R X + t. The poses stay in the reconstruction's frame (ODM's: metres, east-north-up around the
survey)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np

from plenoxels.core.cameras import Intrinsics, opengl_c2w_from_colmap_w2c
from plenoxels.core.errors import UserError

PANORAMA_PROJECTIONS = ("spherical", "equirectangular")
# OpenSfM's world is east-north-up around the survey where its photos have GPS, and z up by its orientation prior
# where they have none.
GRAVITY = (0.0, 0.0, 1.0)


def read(path: Path) -> list[dict]:
    """The reconstructions of an OpenSfM reconstruction.json: each a dict with `cameras` and `shots`."""
    try:
        data = json.loads(path.read_text())
        if isinstance(data, dict):
            data = [data]
        if not all(isinstance(r, dict) and isinstance(r.get("shots"), dict) for r in data):
            raise TypeError
    except (OSError, ValueError, TypeError):
        raise UserError(f"{path} is not an OpenSfM reconstruction.json (a list of reconstructions with shots); fix "
                        "it or set poses.source=sfm") from None
    return data


def _numbers(camera: dict, keys: tuple[str, ...], where: str) -> list[float]:
    try:
        values = [float(camera.get(key, 0.0)) for key in keys]
    except (TypeError, ValueError):
        values = [math.nan]
    if not all(math.isfinite(v) for v in values):
        raise UserError(f"{where}: its camera's {', '.join(keys)} are not all finite numbers; fix the reconstruction "
                        "or set poses.source=sfm")
    return values


def camera_and_lens(camera: dict, where: str) -> tuple[Intrinsics, str, tuple[float, ...]]:
    """The pinhole intrinsics (at the camera's own width x height) and COLMAP lens of an OpenSfM camera."""
    projection = str(camera.get("projection_type", "perspective"))
    w, h = _numbers(camera, ("width", "height"), where)
    if min(w, h) <= 0:
        raise UserError(f"{where}: its camera has no positive width and height; fix the reconstruction or set "
                        "poses.source=sfm")
    size = max(w, h)
    if projection in ("perspective", "fisheye"):
        focal, k1, k2 = _numbers(camera, ("focal", "k1", "k2"), where)
        k = Intrinsics(focal * size, focal * size, w / 2, h / 2, int(round(w)), int(round(h)))
        return k, "OPENCV_FISHEYE" if projection == "fisheye" else "OPENCV", (k1, k2, 0.0, 0.0)
    if projection in ("brown", "fisheye_opencv", "radial"):
        if projection == "fisheye_opencv":
            focal, aspect = _numbers(camera, ("focal", "aspect_ratio"), where)
            fx, fy = focal, focal * (aspect or 1.0)
        else:
            fx, fy = _numbers(camera, ("focal_x", "focal_y"), where)
        cx, cy = _numbers(camera, ("c_x", "c_y"), where)
        k = Intrinsics(fx * size, fy * size, w / 2 + cx * size, h / 2 + cy * size, int(round(w)), int(round(h)))
        if projection == "fisheye_opencv":
            return k, "OPENCV_FISHEYE", tuple(_numbers(camera, ("k1", "k2", "k3", "k4"), where))
        k1, k2, k3, p1, p2 = _numbers(camera, ("k1", "k2", "k3", "p1", "p2"), where)
        return k, "FULL_OPENCV", (k1, k2, p1, p2, k3, 0.0, 0.0, 0.0)
    raise UserError(f"{where}: a {projection} camera, which this tool does not import (perspective, brown, radial, "
                    "fisheye, fisheye_opencv, spherical); set poses.source=sfm")


def camera_to_world(shot: dict, where: str) -> np.ndarray:
    """Our camera-to-world (OpenGL axes) from a shot's rotation (axis-angle, world to camera) and translation."""
    try:
        rotation = np.asarray(shot["rotation"], dtype=np.float64).reshape(3)
        translation = np.asarray(shot["translation"], dtype=np.float64).reshape(3)
    except (KeyError, TypeError, ValueError):
        raise UserError(f"{where}: its rotation and translation are not three numbers each; fix the reconstruction or "
                        "set poses.source=sfm") from None
    if not (np.isfinite(rotation).all() and np.isfinite(translation).all()):
        raise UserError(f"{where}: its rotation or translation is not finite; fix the reconstruction or set "
                        "poses.source=sfm")
    return opengl_c2w_from_colmap_w2c(cv2.Rodrigues(rotation)[0], translation)
