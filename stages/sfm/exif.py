"""What the photos' EXIF says about their cameras: the camera model (to decide whether photos share one
camera), the focal length (to start COLMAP's cameras from it), where they were taken (for up, stages/sfm/gps.py) and
how far that may be off (EXIF's horizontal positioning error, a DJI RTK drone's deviations in its XMP)."""
from __future__ import annotations

import math
import re
import statistics
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image

from stages.capture.photos import RAW_SUFFIXES, upright_size
from stages.sfm.lens import FISHEYE_DIAGONAL_FOV_DEG, fisheye_focal

EXIF_MODEL_TAG = 0x0110
EXIF_IFD = 0x8769
GPS_IFD = 0x8825
GPS_H_POSITIONING_ERROR = 0x1F          # GPSHPositioningError (EXIF 2.31), metres
# DJI's XMP on an RTK drone: its fix (50: fixed) and the deviations (metres) of its latitude, longitude and height.
DJI_RTK_FIXED = 50
DJI_RTK = {name: re.compile(rb"drone-dji:" + name.encode() + rb'\s*(?:=\s*"|>)\s*([+-]?\d+(?:\.\d*)?)')
           for name in ("RtkFlag", "RtkStdLat", "RtkStdLon", "RtkStdHgt")}
XMP_HEAD_BYTES = 1 << 17  # cameras write their XMP packet near the start
EXIF_FOCAL_35MM = 0xA405                # FocalLengthIn35mmFilm, mm
EXIF_FOCAL = 0x920A                     # FocalLength, mm
EXIF_FOCAL_PLANE_X_RESOLUTION = 0xA20E  # sensor pixels per unit, in units of the tag below
EXIF_FOCAL_PLANE_UNIT = 0xA210
EXIF_PIXEL_X, EXIF_PIXEL_Y = 0xA002, 0xA003  # the size the camera wrote the image at
EXIF_LENS_MODEL = 0xA434
LENS_TAGS = (EXIF_LENS_MODEL, EXIF_FOCAL, EXIF_FOCAL_35MM)
MM_PER_FOCAL_PLANE_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}
# A 35 mm equivalent focal length keeps the diagonal field of view of the 36 x 24 mm frame (CIPA DC-008), so it
# holds for any aspect ratio, not only 3:2.
FULL_FRAME_DIAGONAL_MM = float(np.hypot(36.0, 24.0))


def one_camera(records: list[dict], photos: Path) -> bool:
    """True when every photo (ingest records, sources in `photos`) has the same size and the same EXIF camera
    model, lens and focal length (or none): a phone's lenses, or its zoom, share a model and a size but not a focal."""
    if len({(r["width"], r["height"]) for r in records}) > 1:
        return False
    cameras = set()
    for record in records:
        try:
            with Image.open(photos / record["source"]) as im:
                exif = im.getexif()
                lens = exif.get_ifd(EXIF_IFD)
                cameras.add((exif.get(EXIF_MODEL_TAG), *(str(lens.get(tag)) for tag in LENS_TAGS)))
        except (OSError, ValueError):
            cameras.add(None)
    return len(cameras) <= 1


def recorded_size_differs(exif, size: tuple[int, int]) -> bool:
    """True when EXIF records the size the camera wrote and the file's pixels are another size: the photo was cropped,
    resized or re-saved from a screenshot, so its focal tags describe pixels that are no longer there."""
    try:
        recorded = (int(exif.get(EXIF_PIXEL_X) or 0), int(exif.get(EXIF_PIXEL_Y) or 0))
    except (TypeError, ValueError):
        return False
    return all(recorded) and sorted(recorded) != sorted(size)


def exif_focal(photo: Path, sensor_width_mm: float) -> tuple[float, str] | None:
    """Focal length in pixels of the photo as stored, from its EXIF, and which tags gave it; None without them, or
    when the photo is not the size EXIF says the camera recorded (a crop or a resize)."""
    try:
        with Image.open(photo) as im:
            exif = im.getexif().get_ifd(EXIF_IFD)
            width, height = im.size
    except (OSError, ValueError):
        return None
    if photo.suffix.lower() in RAW_SUFFIXES:  # Pillow reads a DNG's first image, often its preview: LibRaw its sensor
        width, height = upright_size(photo) or (0, 0)
    elif recorded_size_differs(exif, (width, height)):
        return None
    def positive(tag: int) -> float:
        try:
            return max(float(exif.get(tag, 0) or 0), 0.0)
        except (TypeError, ValueError, ZeroDivisionError):
            return 0.0
    focal_35mm, focal_mm = positive(EXIF_FOCAL_35MM), positive(EXIF_FOCAL)
    if focal_35mm:
        return focal_35mm / FULL_FRAME_DIAGONAL_MM * float(np.hypot(width, height)), f"EXIF {focal_35mm:g} mm (35 mm equivalent)"
    per_unit, unit = positive(EXIF_FOCAL_PLANE_X_RESOLUTION), exif.get(EXIF_FOCAL_PLANE_UNIT, 2)
    if focal_mm and per_unit and unit in MM_PER_FOCAL_PLANE_UNIT:
        return focal_mm * per_unit / MM_PER_FOCAL_PLANE_UNIT[unit], f"EXIF {focal_mm:g} mm and focal plane resolution"
    if focal_mm and sensor_width_mm:
        return focal_mm / sensor_width_mm * max(width, height), f"EXIF {focal_mm:g} mm on a {sensor_width_mm:g} mm sensor"
    return None


def resized_since_capture(records: list[dict], photos: Path) -> list[str]:
    """Names of the photos whose pixels are not the size their EXIF says the camera recorded."""
    changed = []
    for record in records:
        if Path(record["source"]).suffix.lower() in RAW_SUFFIXES:  # a RAW file is the sensor's, never resized
            continue
        try:
            with Image.open(photos / record["source"]) as im:
                if recorded_size_differs(im.getexif().get_ifd(EXIF_IFD), im.size):
                    changed.append(record["name"])
        except (OSError, ValueError):
            continue
    return changed


def set_focal_priors(db: Path, records: list[dict], photos: Path, sensor_width_mm: float,
                     from_exif: bool = True) -> dict | None:
    """Starts each camera in the database from the EXIF focal length of its photos (the median where photos share one,
    scaled to the ingested size), marked as a prior so verification estimates essential matrices; from the focal
    length a record gives (a 360 frame's view, `focal`) where it gives one, EXIF or not. Without either (or with
    `from_exif` off), a fisheye camera starts from `fisheye_focal`, and others from COLMAP's guess of 1.2 x the
    longest side."""
    by_name = {f"{r['name']}.png": r for r in records}
    found = []
    with pycolmap.Database.open(db) as database:
        images_of: dict[int, list] = {}
        for image in database.read_all_images():
            images_of.setdefault(image.camera_id, []).append(by_name[image.name])
        for camera_id, camera_records in images_of.items():
            priors = []
            for record in camera_records:
                if "focal" in record:
                    priors.append((record["focal"], "the 360 views' field of view"))
                    continue
                exif = exif_focal(photos / record["source"], sensor_width_mm) if from_exif else None
                if exif is not None:
                    priors.append((exif[0] * record["scale"], exif[1]))
            camera = database.read_camera(camera_id)
            if not priors and "FISHEYE" in camera.model.name:
                priors.append((fisheye_focal(camera.width, camera.height), "a fisheye's usual field of view "
                               f"({FISHEYE_DIAGONAL_FOV_DEG:.0f} degrees across the diagonal)"))
            if not priors:
                continue
            camera.focal_length = statistics.median(f for f, _ in priors)
            camera.has_prior_focal_length = True
            database.update_camera(camera)
            found.append((database.read_camera(camera_id).mean_focal_length(), priors[0][1], len(priors)))
    if not found:
        return None
    return {"focal_px": round(statistics.median(f for f, _, _ in found), 2), "from": found[0][1],
            "images": sum(n for _, _, n in found), "cameras": len(found)}


def _degrees(value, ref: str, negative: str) -> float:
    degrees, minutes, seconds = (float(v) for v in value)
    return (-1.0 if str(ref).strip().upper() == negative else 1.0) * (degrees + minutes / 60.0 + seconds / 3600.0)


def exif_position(photo: Path) -> tuple[float, float, float] | None:
    """A photo's latitude, longitude (degrees) and altitude (metres) from its EXIF; None without all three."""
    try:
        with Image.open(photo) as image:
            gps = image.getexif().get_ifd(GPS_IFD)
        latitude, longitude = _degrees(gps[2], gps.get(1, "N"), "S"), _degrees(gps[4], gps.get(3, "E"), "W")
        below = gps.get(5, 0) in (1, b"\x01")
        altitude = (-1.0 if below else 1.0) * float(gps[6])
    except Exception:  # any photo or tag a reader cannot take means the same thing here: no position
        return None
    found = (latitude, longitude, altitude)
    return found if all(math.isfinite(v) for v in found) and abs(latitude) <= 90 and abs(longitude) <= 180 else None


def position_error(photo: Path) -> tuple[float, float] | None:
    """How far (metres, one standard deviation, across and in height) a photo says its position may be off: a DJI RTK
    drone's deviations where its fix is fixed (XMP), else the horizontal error a phone writes (EXIF), twice that in
    height; None where it says neither."""
    try:
        with open(photo, "rb") as f:
            head = f.read(XMP_HEAD_BYTES)
        rtk = {name: float(found.group(1)) for name, pattern in DJI_RTK.items() if (found := pattern.search(head))}
        if rtk.get("RtkFlag") == DJI_RTK_FIXED and {"RtkStdLat", "RtkStdLon", "RtkStdHgt"} <= set(rtk):
            return math.hypot(rtk["RtkStdLat"], rtk["RtkStdLon"]) / math.sqrt(2.0), rtk["RtkStdHgt"]
        with Image.open(photo) as image:
            across = float(image.getexif().get_ifd(GPS_IFD)[GPS_H_POSITIONING_ERROR])
    except Exception:  # any photo or tag a reader cannot take means the same thing here: nothing said
        return None
    return (across, 2.0 * across) if math.isfinite(across) and across > 0.0 else None
