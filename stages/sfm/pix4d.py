"""Pix4D's cameras (`<project>_calibrated_camera_parameters.txt`, which Pix4Dmapper writes to its project's
`1_initial/params/`), read for the importer (`imported`).

After a header that names its fields (seven lines, the last `camera model m = K [R|-Rt] X`), each calibrated photo
has a block: its file name, width and height on a line, then its camera matrix K (three rows), three radial and two
tangential lens coefficients, the camera's position t and its world-to-camera rotation R (three rows). A point X is
seen at K [R | -R t] X, so the camera's axes are OpenCV's (x right, y down, z forward); the lens is OpenCV's
(tangential T1, T2 its p1, p2), and the world is Pix4D's (x east, y north, z up). A photo Pix4D did not calibrate has
no block."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from plenoxels.core.cameras import Intrinsics, opengl_c2w_from_colmap_w2c
from plenoxels.core.errors import UserError
from stages.sfm.imported_model import (NO_LENS, CameraTable, Imported, add_image, at_ingested_size, file_stem,
                                       finite_number)

GRAVITY = (0.0, 0.0, 1.0)  # Pix4D's world: z up
BLOCK_NUMBERS = 9 + 3 + 2 + 3 + 9  # K, radial, tangential, position, rotation


def read(path: Path) -> dict[str, tuple[int, int, np.ndarray, int]]:
    """Each block by its photo's file name: width, height, its numbers (BLOCK_NUMBERS) and its line in the file."""
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        raise UserError(f"cannot read {path}; fix it or set poses.source=sfm") from None
    blocks, start = {}, next((n + 1 for n, line in enumerate(lines) if line.lower().startswith("camera model")), 0)
    name, numbers, at = None, [], 0
    for number, line in enumerate(lines[start:], start=start + 1):
        if not line.strip():
            continue
        if name is None:
            parts = line.rsplit(maxsplit=2)
            if len(parts) != 3 or not (parts[1].isdigit() and parts[2].isdigit()):
                raise UserError(f"{path.name}, line {number}: {line.strip()[:60]!r} is not a photo's name, width "
                                "and height; export the calibrated camera parameters again or set poses.source=sfm")
            name, size, numbers, at = parts[0], (int(parts[1]), int(parts[2])), [], number
            continue
        numbers += [finite_number(value, f"{name}'s value", f"{path.name}, line {number}") for value in line.split()]
        if len(numbers) >= BLOCK_NUMBERS:
            if len(numbers) > BLOCK_NUMBERS:
                raise UserError(f"{path.name}, line {number}: {name}'s block holds more than {BLOCK_NUMBERS} numbers; "
                                "export the calibrated camera parameters again or set poses.source=sfm")
            blocks[name] = (*size, np.array(numbers), at)
            name = None
    if name is not None:
        raise UserError(f"{path.name}, line {at}: {name}'s block ends after {len(numbers)} of its {BLOCK_NUMBERS} "
                        "numbers; export the calibrated camera parameters again or set poses.source=sfm")
    return blocks


def camera(width: int, height: int, numbers: np.ndarray, where: str) -> tuple[Intrinsics, tuple, np.ndarray]:
    """A block's pinhole (for its width x height), lens and camera-to-world (ours)."""
    k, radial, tangential = numbers[:9].reshape(3, 3), numbers[9:12], numbers[12:14]
    position, rotation = numbers[14:17], numbers[17:26].reshape(3, 3)
    if min(k[0, 0], k[1, 1], width, height) <= 0 or abs(k[0, 1]) > 1e-9 * k[0, 0]:
        raise UserError(f"{where}: its camera matrix has no positive focal lengths (or a skew); export it again or "
                        "set poses.source=sfm")
    if abs(np.linalg.det(rotation)) < 1e-9:
        raise UserError(f"{where}: its rotation is not invertible; export it again or set poses.source=sfm")
    coefficients = (radial[0], radial[1], tangential[0], tangential[1], radial[2], 0.0, 0.0, 0.0)
    lens = ("FULL_OPENCV", tuple(float(c) for c in coefficients)) if any(coefficients) else NO_LENS
    pinhole = Intrinsics(k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height)
    return pinhole, lens, opengl_c2w_from_colmap_w2c(rotation, -rotation @ position)


def imported(path: Path, records: list[dict]) -> Imported:
    """Poses from Pix4D's calibrated camera parameters: a photo takes the block of its file's stem, where one block
    alone has it."""
    by_stem: dict[str, list[str]] = {}
    blocks = read(path)
    for name in blocks:
        by_stem.setdefault(file_stem(name), []).append(name)
    reconstruction = pycolmap.Reconstruction()
    cameras = CameraTable(reconstruction)
    missing = []
    for record in records:
        named = by_stem.get(file_stem(record["source"]), [])
        if len(named) != 1:
            missing.append(record["name"])
            continue
        width, height, numbers, line = blocks[named[0]]
        where = f"{path.name}, line {line} ({named[0]})"
        k, lens, c2w = camera(width, height, numbers, where)
        add_image(reconstruction, len(reconstruction.images) + 1, record,
                  cameras.id_for(at_ingested_size(k, record, where), lens), c2w, where)
    return Imported(reconstruction, path, missing, gravity=GRAVITY)
