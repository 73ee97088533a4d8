"""The lens SfM fits: how far a fitted camera bends its picture, and a fisheye's start without EXIF.

SfM starts every camera as `poses.camera_model` (SIMPLE_RADIAL: a pinhole and one radial coefficient), which holds a
phone's or a DSLR's lens. An action camera's wide mode is a fisheye: fitted as a pinhole, its corners stretch a
quarter or more, or lie past where the model's one coefficient turns back, the poses bend and mapping drags on. A
few images mapped first show it (`probe_images`), and a model whose lens bends its corners past WIDE_LENS_STRETCH is
made as OPENCV_FISHEYE (reconstruct.py)."""
from __future__ import annotations

import math
from pathlib import Path

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
# Before mapping every image as a pinhole, SfM maps this many that share the most matches, where the lens may be a
# fisheye: no focal length in EXIF (a video's frames), or one wider than this 35 mm equivalent (an ultra-wide lens's
# or a fisheye's). A fisheye mapped as a pinhole drags on (8 minutes for 60 frames at 640x480).
LENS_PROBE_IMAGES = 10
FISHEYE_EXIF_35MM_BELOW = 20.0


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


def wide_lens(reconstruction: pycolmap.Reconstruction | None) -> float | None:
    """The largest corner stretch of the model's pinhole-kind cameras, where one passes WIDE_LENS_STRETCH: the lens is
    a fisheye's; None otherwise."""
    if reconstruction is None:
        return None
    stretch = max((corner_stretch(c) for c in reconstruction.cameras.values() if c.model.name in PINHOLE_LENS_MODELS),
                  default=0.0)
    return stretch if stretch >= WIDE_LENS_STRETCH else None


def lens_words(stretch: float, model: str) -> str:
    """What a fitted lens's corner stretch says, for the summary."""
    bent = f"moves the corners {stretch:.0%} when undistorted" if math.isfinite(stretch) else \
        "turns back short of the corners"
    return f"its lens ({model}) {bent}, as a fisheye's does"


def may_be_fisheye(focal_prior: dict | None, width: int, height: int) -> bool:
    """Whether a capture's lens is worth probing (`LENS_PROBE_IMAGES`): no focal length to start from, or a start
    wider than FISHEYE_EXIF_35MM_BELOW."""
    return focal_prior is None or focal_prior["focal_px"] / math.hypot(width, height) * math.hypot(36, 24) < \
        FISHEYE_EXIF_35MM_BELOW


def probe_images(db: Path, count: int = LENS_PROBE_IMAGES) -> list[str]:
    """Up to `count` images that share many verified matches: the pair with the most, then each time the image with
    the most inliers to those already chosen."""
    with pycolmap.Database.open(db) as database:
        names = {image.image_id: image.name for image in database.read_all_images()}
        pair_ids, inliers = database.read_two_view_geometry_num_inliers()
    links: dict[int, dict[int, int]] = {}
    for pair_id, count_inliers in zip(pair_ids, inliers):
        a, b = pycolmap.pair_id_to_image_pair(pair_id)
        links.setdefault(a, {})[b] = links.setdefault(b, {})[a] = int(count_inliers)
    if not links:
        return []
    first = max(links, key=lambda a: max(links[a].values()))
    chosen = [first, max(links[first], key=links[first].get)]
    while len(chosen) < count:
        shared = {b: sum(links[b].get(a, 0) for a in chosen) for b in links if b not in chosen}
        best = max(shared, key=shared.get, default=None)
        if best is None or shared[best] == 0:
            break
        chosen.append(best)
    return [names[i] for i in chosen]
