"""RealityCapture's (RealityScan's) cameras: the XMP file it writes beside each photo it aligned (`<stem>.xmp`, read
for pose_import.from_camera_files), and its "Internal/External camera parameters" CSV export (one row a photo, as
nerfstudio's `ns-process-data realitycapture` reads it: `imported_csv`).

An XMP's `xcr:Rotation` is world-to-camera, row by row, in OpenCV's camera axes (x right, y down, z forward), and
`xcr:Position` the camera's centre; each is an element or an attribute. `xcr:FocalLength35mm` is the focal length of
a 36 mm wide frame across the photo's longer side, `xcr:PrincipalPointU`/`V` the principal point's offset from the
photo's centre in units of that side. The lens is Brown's (`xcr:DistortionModel` brown3, brown4, brown3t2, brown4t2):
`xcr:DistortionCoeficients` (sic) k1-k4 radial, then two tangential, which AliceVision's importer of these files
(importKnownPoses) takes as OpenCV's p2, p1. A photo RealityCapture did not align has no pose in its file.

The CSV gives each photo's position (x, y, alt) and its heading, pitch and roll in degrees (pitch 0 looking straight
down, 90 level; heading clockwise from +y), the same 35 mm focal length, principal point and lens in its columns.
Exported in a geographic system (WGS 84), x and y are longitude and latitude in degrees beside an altitude in metres:
those are taken to metres east, north and up of the first camera (`in_metres`), and z is up."""
from __future__ import annotations

import csv
import math
import re
from pathlib import Path

import numpy as np
import pycolmap
from scipy.spatial.transform import Rotation

from plenoxels.core.cameras import Intrinsics, opengl_c2w_from_colmap_w2c
from plenoxels.core.errors import UserError
from stages.sfm.gps import east_north_up
from stages.sfm.imported_model import (NO_LENS, CameraTable, Imported, Lens, add_image, at_ingested_size, file_stem,
                                       finite_number)
from stages.sfm.pose_files import REALITYCAPTURE_COLUMNS as CSV_COLUMNS
from stages.sfm.pose_files import aligned_by_realitycapture

GRAVITY = None  # a component's frame is geographic only where it was georeferenced, which neither file says
SUFFIX = ".xmp"
FRAME_MM = 36.0  # the 35 mm film frame's width, which the focal length is given against
BROWN_MODELS = ("brown3", "brown4", "brown3t2", "brown4t2")
CSV_LENS_COLUMNS = ("k1", "k2", "k3", "k4", "t1", "t2")
# A CSV's x and y are degrees of longitude and latitude where the cameras spread over fewer of them than this share of
# their metres of altitude, or than DEGREES_SPREAD away from the origin: a degree is some 100 km, and no capture in
# metres spreads a hundred times higher than wide, or stays within a centimetre across.
DEGREES_SPREAD_SHARE = 0.01
DEGREES_SPREAD = 0.01


def own_folders(photos: Path) -> list[Path]:
    """The folder of a photo's XMP file: its own, where RealityCapture wrote them beside the photos; else none (they
    were exported to a folder of their own, which poses.path names)."""
    return [photos] if aligned_by_realitycapture(photos) else []


def _field(text: str, name: str) -> str | None:
    """An xcr field's text, written as an attribute or as an element."""
    found = re.search(rf'xcr:{name}\s*=\s*"([^"]*)"', text) or re.search(rf"<xcr:{name}>([^<]*)</xcr:{name}>", text)
    return found.group(1) if found else None


def _numbers(text: str | None, count: int, name: str, where: str) -> np.ndarray:
    try:
        values = np.array([float(v) for v in (text or "").split()], dtype=np.float64)
    except ValueError:
        values = np.zeros(0)
    if len(values) != count or not np.isfinite(values).all():
        raise UserError(f"{where}: xcr:{name} is not {count} finite numbers; fix it or set poses.source=sfm")
    return values


def pinhole(focal_35mm: float, u: float, v: float, aspect: float, width: int, height: int) -> Intrinsics:
    """The pinhole of a photo of width x height from RealityCapture's focal length and principal point."""
    side = max(width, height)
    focal = focal_35mm * side / FRAME_MM
    return Intrinsics(focal, focal * aspect, width / 2 + u * side, height / 2 + v * side, width, height)


def lens(model: str, coefficients: list[float], k: Intrinsics, where: str) -> Lens:
    """COLMAP's lens for RealityCapture's model and its six coefficients (k1-k4, t1, t2). A fourth radial term, which
    COLMAP's OpenCV model lacks, is folded into the first three by least squares over the photo's radii."""
    k1, k2, k3, k4, t1, t2 = (list(coefficients) + [0.0] * 6)[:6]
    if not any(coefficients):
        return NO_LENS
    if model.lower() not in BROWN_MODELS:
        raise UserError(f"{where}: its lens is RealityCapture's {model or 'unnamed'} model, which this tool does not "
                        f"read; align with a Brown model ({', '.join(BROWN_MODELS)}) or set poses.source=sfm")
    if k4:
        corner = math.hypot(k.w / 2, k.h / 2) / min(k.fl_x, k.fl_y)
        r2 = np.linspace(0.0, corner, 64) ** 2
        folded = np.linalg.lstsq(np.stack([r2, r2 ** 2, r2 ** 3], axis=1), k4 * r2 ** 4, rcond=None)[0]
        k1, k2, k3 = k1 + folded[0], k2 + folded[1], k3 + folded[2]
    p1, p2 = t2, t1
    return ("FULL_OPENCV", (k1, k2, p1, p2, k3, 0.0, 0.0, 0.0)) if k3 else ("OPENCV", (k1, k2, p1, p2))


def camera(path: Path, width: int, height: int, where: str) -> tuple[Intrinsics, np.ndarray, Lens] | None:
    """The pinhole (for its photo, width x height), camera-to-world (ours) and lens of an XMP file; None where it
    holds no pose (RealityCapture did not align the photo)."""
    try:
        text = path.read_text(errors="replace")
    except OSError:
        raise UserError(f"{where} cannot be read; fix it or set poses.source=sfm") from None
    if not re.search(r"</(\w+:)?(xmpmeta|RDF)>", text):  # cut short: a field may end early, or be missing
        raise UserError(f"{where} is not a whole XMP file (it does not close); export it again or set "
                        "poses.source=sfm")
    rotation, position = _field(text, "Rotation"), _field(text, "Position")
    if rotation is None or position is None:
        return None
    rotation = _numbers(rotation, 9, "Rotation", where).reshape(3, 3)
    centre = _numbers(position, 3, "Position", where)
    if abs(np.linalg.det(rotation)) < 1e-9:
        raise UserError(f"{where}: xcr:Rotation is not an invertible rotation; fix it or set poses.source=sfm")

    def number(name: str, default: float | None, positive: bool = False) -> float:
        value = _field(text, name)
        if value is None and default is None:
            raise UserError(f"{where}: no xcr:{name}; fix it or set poses.source=sfm")
        return default if value is None else finite_number(value, f"xcr:{name}", where, positive)

    k = pinhole(number("FocalLength35mm", None, positive=True), number("PrincipalPointU", 0.0),
                number("PrincipalPointV", 0.0), number("AspectRatio", 1.0, positive=True), width, height)
    coefficients = _field(text, "DistortionCoeficients")
    coefficients = list(_numbers(coefficients, len(coefficients.split()), "DistortionCoeficients", where)) \
        if coefficients and coefficients.split() else []
    return (k, opengl_c2w_from_colmap_w2c(rotation, -rotation @ centre),
            lens(_field(text, "DistortionModel") or "", coefficients, k, where))


def csv_rows(path: Path) -> dict[str, dict[str, str]]:
    """The CSV's rows by the photo's stem."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as file:
            rows = [{key.strip().lower(): (value or "").strip() for key, value in row.items() if key}
                    for row in csv.DictReader(file)]
    except (OSError, UnicodeDecodeError, csv.Error):
        raise UserError(f"{path} cannot be read as RealityCapture's camera CSV; fix it or set poses.source=sfm") \
            from None
    return {Path(row["#name"].replace("\\", "/")).stem: row for row in rows if row.get("#name")}


def csv_camera(row: dict[str, str], width: int, height: int, where: str) -> tuple[Intrinsics, np.ndarray, Lens]:
    """The pinhole, camera-to-world (ours) and lens of a CSV row, for its photo as stored (width x height)."""
    value = {key: finite_number(row.get(key), key, where, positive=key == "f") for key in CSV_COLUMNS[1:]}
    c2w = np.eye(4)
    # OpenGL's camera turned about z by -heading, then about its x by pitch and its y by roll (nerfstudio's reading)
    angles = [-value["heading"], value["pitch"], value["roll"]]
    c2w[:3, :3] = Rotation.from_euler("ZXY", angles, degrees=True).as_matrix()
    c2w[:3, 3] = value["x"], value["y"], value["alt"]
    k = pinhole(value["f"], value["px"], value["py"], 1.0, width, height)
    coefficients = [finite_number(row.get(key) or 0, key, where) for key in CSV_LENS_COLUMNS]
    return k, c2w, lens("brown4t2", coefficients, k, where)


def in_metres(rows: dict[str, dict[str, str]], where: str) -> bool:
    """Whether the rows' x and y are longitude and latitude (DEGREES_SPREAD_SHARE, DEGREES_SPREAD), which are then set
    to metres east, north and up of the first row, in place."""
    position = np.array([[finite_number(row.get(key), key, f"{where}, {row['#name']}") for key in ("x", "y", "alt")]
                         for row in rows.values()]).reshape(-1, 3)
    spread = np.ptp(position, axis=0) if len(position) else np.zeros(3)
    across, away = max(spread[:2]), np.abs(position[:, :2].mean(axis=0)).min() if len(position) else 0.0
    degrees = (len(position) > 1 and (np.abs(position[:, 0]) <= 180).all() and (np.abs(position[:, 1]) <= 90).all()
               and 0 < across and (across < DEGREES_SPREAD_SHARE * spread[2] or across < DEGREES_SPREAD < away))
    if degrees:
        for row, metres in zip(rows.values(), east_north_up(position[:, [1, 0, 2]])):
            row["x"], row["y"], row["alt"] = (repr(float(v)) for v in metres)
    return degrees


def imported_csv(path: Path, records: list[dict]) -> Imported:
    """Poses from RealityCapture's camera CSV: a photo takes the row of its stem."""
    rows = csv_rows(path)
    geographic = in_metres(rows, path.name)
    reconstruction = pycolmap.Reconstruction()
    cameras = CameraTable(reconstruction)
    missing = []
    for record in records:
        row = rows.get(file_stem(record["source"]))
        if row is None:
            missing.append(record["name"])
            continue
        where = f"{path.name}, {row['#name']}"
        k, c2w, lens = csv_camera(row, record["original_width"], record["original_height"], where)
        add_image(reconstruction, len(reconstruction.images) + 1, record,
                  cameras.id_for(at_ingested_size(k, record, where), lens), c2w, where)
    return Imported(reconstruction, path, missing, gravity=(0.0, 0.0, 1.0) if geographic else GRAVITY)
