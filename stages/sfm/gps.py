"""Which way is up from the photos' GPS: where they were taken (their EXIF's latitude, longitude and altitude:
exif.exif_position) turned to metres east, north and up (WGS 84, pycolmap's GPSTransform), and the model's camera
centres fitted to them by a similarity (pycolmap's estimate_sim3d_robust). The fit carries the up of those metres
into the model's frame.

GPS is metres off, more in height than across, so it is taken only where it spans far more than that (a drone's
survey, not a phone's orbit of a thing) and not along one line (which leaves a turn about the line free), and where
the fit holds to a small angle over the span; past either, the photos' gimbal or the cameras decide."""
from __future__ import annotations

import math

import numpy as np
import pycolmap

# The share of the model's photos that must carry a position, the span (metres) they must cover across, how far
# their second extent must reach beside their first (not a line), and the angle (degrees) by which the fit's
# residuals may tilt the span.
MIN_SHARE = 0.75
MIN_SPAN_M = 20.0
MIN_WIDTH_SHARE = 0.1
MAX_TILT_DEG = 2.0


def east_north_up(positions: np.ndarray) -> np.ndarray:
    """Latitude, longitude and altitude [N, 3] as metres east, north and up of the first."""
    latitude, longitude, altitude = positions[0]
    return np.asarray(pycolmap.GPSTransform().ellipsoid_to_enu(positions, latitude, longitude, altitude))


def gravity(reconstruction: pycolmap.Reconstruction, positions: dict[str, tuple[float, float, float]],
            ) -> tuple[np.ndarray | None, dict]:
    """The world's up in the model's frame from where its images were taken (by image name), and what was found."""
    centres, located = [], []
    for image in reconstruction.images.values():
        if image.has_pose and image.name in positions:
            centres.append(image.projection_center())
            located.append(positions[image.name])
    posed = sum(image.has_pose for image in reconstruction.images.values())
    found = {"photos": len(located), "of": posed}
    if len(located) < max(3, MIN_SHARE * posed):
        return None, found
    metres = east_north_up(np.asarray(located))
    across = np.linalg.svd(metres[:, :2] - metres[:, :2].mean(axis=0), compute_uv=False) / math.sqrt(len(metres))
    found["span_m"] = round(float(np.ptp(metres[:, :2], axis=0).max()), 1)
    if found["span_m"] < MIN_SPAN_M or across[1] < MIN_WIDTH_SHARE * across[0]:
        return None, found
    options = pycolmap.RANSACOptions()
    options.max_error, options.random_seed = max(1.0, 0.02 * found["span_m"]), 0
    fitted = pycolmap.estimate_sim3d_robust(np.asarray(centres), metres, options)
    if fitted is None or fitted["num_inliers"] < MIN_SHARE * len(located):
        return None, found
    sim3, inliers = fitted["tgt_from_src"], np.asarray(fitted["inlier_mask"], dtype=bool)
    residual = np.linalg.norm(np.asarray([sim3 * c for c in np.asarray(centres)[inliers]]) - metres[inliers], axis=1)
    found["fit_m"] = round(float(np.sqrt(np.mean(residual ** 2))), 2)
    if math.degrees(math.atan2(found["fit_m"], found["span_m"])) > MAX_TILT_DEG:
        return None, found
    up = sim3.rotation.matrix().T @ [0.0, 0.0, 1.0]
    return up / np.linalg.norm(up), found
