"""What the photos' GPS says: where they were taken (their EXIF's latitude, longitude and altitude:
exif.exif_position) turned to metres east, north and up (WGS 84, pycolmap's GPSTransform). Across a survey it holds
SfM's model to those metres (`write_priors`: COLMAP's pose priors, which bundle adjustment keeps the cameras near, so
a survey's rows cannot bend into a dome), it says which way is up (`gravity`: the model's camera centres fitted
to them by a similarity, pycolmap's estimate_sim3d_robust, whose rotation carries the metres' up into the model), and
it moves a pose file's model, which nothing held, into those metres where its cameras fit them (`into_metres`).

GPS is metres off, more in height than across (each prior as far as its photo says, where it does: an RTK fix's
centimetres, a phone's stated error, a flight log's rounding), so it is taken only where it spans far more than that
(a drone's survey, not a phone's orbit of a thing) and not along one line (which leaves a turn about the line free),
and where the fit holds to a small angle over the span; past either, the photos' gimbal or the cameras decide."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pycolmap

from stages.capture.photos import VIDEO_SUFFIXES
from stages.sfm.exif import exif_position, position_error

# How far (metres, one standard deviation) a drone's GPS is taken to be off across and in height, for the priors.
GPS_ERROR_ACROSS_M = 2.0
GPS_ERROR_UP_M = 4.0
# The least error a position is taken at, however small its source says it is (an RTK fix's centimetres): the antenna
# sits a hand's width from the camera's centre, and its clock a few milliseconds from the shutter.
MIN_ERROR_ACROSS_M = 0.05
MIN_ERROR_UP_M = 0.10
# The share of the model's photos that must carry a position, the span (metres) they must cover across, how far
# their second extent must reach beside their first (not a line), and the angle (degrees) by which the fit's
# residuals may tilt the span.
MIN_SHARE = 0.75
MIN_SPAN_M = 20.0
MIN_WIDTH_SHARE = 0.1
MAX_TILT_DEG = 2.0
# A model held near the GPS is taken to be in its metres where the fit scales it by no more than this (its log) and
# moves it by no more than this share of the span (or a metre), turning it by no more than MAX_TILT_DEG.
MAX_GEO_SCALE_LOG = 0.02
MAX_GEO_SHIFT_SHARE = 0.01


def east_north_up(positions: np.ndarray, origin=None) -> np.ndarray:
    """Latitude, longitude and altitude [N, 3] as metres east, north and up of `origin` (the first where not given)."""
    latitude, longitude, altitude = positions[0] if origin is None else origin
    return np.asarray(pycolmap.GPSTransform().ellipsoid_to_enu(positions, latitude, longitude, altitude))


def photo_positions(records: list[dict], photos: Path) -> dict[str, tuple[float, float, float]]:
    """Where each ingested photo (by its image's name) was taken, for those whose EXIF says or a video's frames whose
    flight log did (their records' `gps`: stages/capture/flight_log.py); a 360 frame's views are cut from one photo
    and left out."""
    return {f"{r['name']}.png": where for r in records if "panorama" not in r
            and (where := tuple(r["gps"]["position"]) if "gps" in r else exif_position(photos / r["source"]))}


def position_errors(records: list[dict], photos: Path) -> dict[str, tuple[float, float]]:
    """How far (metres across and in height) each photo's position may be off, where its source says: a flight log
    rounding its degrees (GPS's own error beside the rounding's), an RTK drone's deviations or a phone's stated error
    (exif.position_error), never under MIN_ERROR_ACROSS_M and MIN_ERROR_UP_M; the rest are taken at GPS_ERROR_ACROSS_M
    and GPS_ERROR_UP_M."""
    errors = {}
    for r in records:
        if "gps" in r:  # a log written to a centimetre says nothing GPS's own error does not
            if r["gps"].get("rounding_m", 0.0) < MIN_ERROR_ACROSS_M:
                continue
            said = math.hypot(GPS_ERROR_ACROSS_M, r["gps"]["rounding_m"]), GPS_ERROR_UP_M
        elif "panorama" in r or Path(r["source"]).suffix.lower() in VIDEO_SUFFIXES:
            continue
        elif (said := position_error(photos / r["source"])) is None:
            continue
        errors[f"{r['name']}.png"] = max(said[0], MIN_ERROR_ACROSS_M), max(said[1], MIN_ERROR_UP_M)
    return errors


def above_take_off(records: list[dict]) -> bool:
    """True where the photos' heights are above where the drone took off (its barometer's), not above the sea."""
    return any(r.get("gps", {}).get("height") == "take-off" for r in records)


def spans_survey(metres: np.ndarray) -> bool:
    """True where positions (metres east, north and up [N, 3]) span MIN_SPAN_M across and do not lie along one line."""
    across = np.linalg.svd(metres[:, :2] - metres[:, :2].mean(axis=0), compute_uv=False) / math.sqrt(len(metres))
    return np.ptp(metres[:, :2], axis=0).max() >= MIN_SPAN_M and across[1] >= MIN_WIDTH_SHARE * across[0]


def survey_metres(positions: dict[str, tuple[float, float, float]], of: int) -> dict[str, np.ndarray] | None:
    """The positions as metres east, north and up, by name, where they can hold a model: at least MIN_SHARE of `of`
    photos carry one and they span a survey (`spans_survey`); else None."""
    if len(positions) < max(3, MIN_SHARE * of):
        return None
    metres = east_north_up(np.asarray(list(positions.values())))
    return dict(zip(positions, metres)) if spans_survey(metres) else None


def write_priors(db: Path, metres: dict[str, np.ndarray], errors: dict[str, tuple[float, float]] | None = None
                 ) -> int:
    """Writes each image's position (metres east, north and up) into the database as COLMAP's pose prior, replacing
    any there, each as far off as `errors` says (metres across and in height, by name; GPS_ERROR_ACROSS_M and
    GPS_ERROR_UP_M where it does not); returns how many were written."""
    errors = errors or {}
    database = pycolmap.Database.open(db)
    try:
        database.clear_pose_priors()
        written = 0
        for image in database.read_all_images():
            if image.name in metres:
                prior = pycolmap.PosePrior()
                prior.corr_data_id, prior.position = image.data_id, metres[image.name]
                across, up = errors.get(image.name, (GPS_ERROR_ACROSS_M, GPS_ERROR_UP_M))
                prior.position_covariance = np.diag([across ** 2, across ** 2, up ** 2])
                prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
                database.write_pose_prior(prior)
                written += 1
    finally:
        database.close()
    return written


def gravity(reconstruction: pycolmap.Reconstruction, positions: dict[str, tuple[float, float, float]],
            origin: tuple[float, float, float] | None = None) -> tuple[np.ndarray | None, dict]:
    """The world's up in the model's frame from where its images were taken (by image name), and what was found;
    with the `origin` of the metres SfM held the cameras near (`write_priors`), whether the model's frame is those
    metres (found["in_metres_of"]: the fit moves it by no more than GPS can tell)."""
    sim3, found = fit_model(reconstruction, positions, origin)
    if sim3 is None:
        return None, found
    turned = math.degrees(math.acos(np.clip((np.trace(sim3.rotation.matrix()) - 1) / 2, -1.0, 1.0)))
    if origin is not None and turned <= MAX_TILT_DEG and abs(math.log(sim3.scale)) <= MAX_GEO_SCALE_LOG and (
            np.linalg.norm(sim3.translation) <= max(1.0, MAX_GEO_SHIFT_SHARE * found["span_m"])):
        found["in_metres_of"] = [float(v) for v in origin]
    up = sim3.rotation.matrix().T @ [0.0, 0.0, 1.0]
    return up / np.linalg.norm(up), found


def fit_model(reconstruction: pycolmap.Reconstruction, positions: dict[str, tuple[float, float, float]],
              origin: tuple[float, float, float] | None = None) -> tuple[pycolmap.Sim3d | None, dict]:
    """The similarity that takes the model's camera centres to where their images were taken (metres east, north and
    up of `origin`, the first located where not given), where GPS can say it (a survey: `spans_survey`, the fit's
    residuals tilting its span by no more than MAX_TILT_DEG); and what was found."""
    centres, located = [], []
    for image in reconstruction.images.values():
        if image.has_pose and image.name in positions:
            centres.append(image.projection_center())
            located.append(positions[image.name])
    posed = sum(image.has_pose for image in reconstruction.images.values())
    found = {"photos": len(located), "of": posed}
    if len(located) < max(3, MIN_SHARE * posed):
        return None, found
    metres = east_north_up(np.asarray(located), origin)
    found["span_m"] = round(float(np.ptp(metres[:, :2], axis=0).max()), 1)
    if not spans_survey(metres):
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
    return sim3, found


def into_metres(reconstruction: pycolmap.Reconstruction, positions: dict[str, tuple[float, float, float]],
                up: np.ndarray | None) -> tuple[np.ndarray | None, dict, float]:
    """A model nothing held near the GPS (a pose file's) moved into the GPS's metres east, north and up of the first
    photo located, where it fits them (`fit_model`): the world's up in it (`up`, as the file or the gimbal gave it,
    turned with the model; +z where none was given), what was found (`in_metres_of`) and the scale applied (1 where
    it was not moved)."""
    origin = next(iter(positions.values()))
    sim3, found = fit_model(reconstruction, positions, origin)
    if sim3 is None:
        return up, found, 1.0
    reconstruction.transform(sim3)
    found["in_metres_of"] = [float(v) for v in origin]
    return (np.array([0.0, 0.0, 1.0]) if up is None else sim3.rotation.matrix() @ up), found, float(sim3.scale)
