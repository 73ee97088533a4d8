"""The lens SfM fits: how far a fitted camera bends its picture, and a fisheye's start without EXIF.

SfM starts every camera as `poses.camera_model` (SIMPLE_RADIAL: a pinhole and one radial coefficient), which holds a
phone's or a DSLR's lens. An action camera's wide mode is a fisheye: fitted as a pinhole, its corners stretch a
quarter or more, or lie past where the model's one coefficient turns back, the poses bend and mapping drags on. A
model whose lens bends its corners past WIDE_LENS_STRETCH is made again as OPENCV_FISHEYE (reconstruct.py)."""
from __future__ import annotations

import math

import numpy as np
import pycolmap

# Without EXIF (a video's frames), a fisheye camera starts from this field of view, an action camera's wide mode
# (120-170 degrees): a pair is verified by an essential matrix only from a focal length, and bundle adjustment
# refines it. A fisheye's curved lines obey no fundamental matrix on the pixels, COLMAP's check without one.
FISHEYE_DIAGONAL_FOV_DEG = 150.0
# A fitted lens that moves its image's corners this share of their distance from the centre, or more, when undistorted
# to a pinhole. Phones' and DSLRs' lenses, and 120-degree fisheyes fitted as pinholes, in bench/README.md ("Poses").
WIDE_LENS_STRETCH = 0.1
PINHOLE_LENS_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


def fisheye_focal(width: int, height: int) -> float:
    """The focal length in pixels of an equidistant fisheye (the angle from the axis grows as the radius) that sees
    FISHEYE_DIAGONAL_FOV_DEG across the diagonal of a width x height image."""
    return math.hypot(width, height) / 2 / math.radians(FISHEYE_DIAGONAL_FOV_DEG / 2)


def corner_stretch(camera: pycolmap.Camera) -> float:
    """How much farther from the principal point the image's corners lie once undistorted to a pinhole, as a share of
    how far they lie in the photo (negative where the lens pinches); infinite where the fitted distortion turns back
    short of a corner (no pinhole ray reaches it: the lens is wider than the model holds)."""
    w, h = camera.width, camera.height
    corners = np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]])
    rays = camera.cam_from_img(corners)
    if not np.all(np.isfinite(rays)):
        return math.inf
    centre = np.array([camera.principal_point_x, camera.principal_point_y])
    pinhole = np.linalg.norm(rays * [camera.focal_length_x, camera.focal_length_y], axis=1)
    return float(np.max(pinhole / np.linalg.norm(corners - centre, axis=1)) - 1)


def wide_lens(reconstruction: pycolmap.Reconstruction, camera_model: str) -> float | None:
    """The largest corner stretch of the model's cameras, where `camera_model` is a pinhole's and some camera's passes
    WIDE_LENS_STRETCH: the lens is a fisheye's; None otherwise."""
    if camera_model not in PINHOLE_LENS_MODELS or reconstruction is None:
        return None
    stretch = max((corner_stretch(c) for c in reconstruction.cameras.values()), default=0.0)
    return stretch if stretch >= WIDE_LENS_STRETCH else None
