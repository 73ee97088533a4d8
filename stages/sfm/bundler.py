"""Bundler's cameras (`bundle.out`, v0.3: Bundler's and VisualSFM's own, and the export RealityCapture, Metashape and
Meshroom offer), with the list of the photos they pose in order (`list.txt`), read for the importer
(`imported`).

After a header line, the file gives the counts of cameras and points, then for each camera its focal length in
pixels and two radial coefficients (on a line), its world-to-camera rotation (three lines) and translation (a line),
in OpenGL's camera axes (ours: x right, y up, z back); the principal point is the photo's centre. A camera the
reconstruction left out has a focal length of 0. The list gives a photo's path a line, with more words after it."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from plenoxels.core.cameras import Intrinsics
from plenoxels.core.errors import UserError
from stages.sfm.imported_model import CameraTable, Imported, Lens, add_image, at_ingested_size, file_stem
from stages.sfm.pose_files import BUNDLER_LISTS as LISTS

GRAVITY = None  # the reconstruction's frame


def list_names(path: Path) -> list[str]:
    return [pattern.format(name=path.name, stem=path.stem) for pattern in LISTS]


def image_list(path: Path) -> Path | None:
    """The list of photos beside a bundle file (LISTS; in its folder or the one above)."""
    return next((folder / name for name in list_names(path) for folder in (path.parent, path.parent.parent)
                 if (folder / name).is_file()), None)


def read(path: Path) -> tuple[list[str], list[tuple[float, float, float, np.ndarray] | None]]:
    """The photos the list names, in order, and each one's camera: focal length, k1, k2 and world-to-camera 4x4, or
    None where the reconstruction left it out."""
    listing = image_list(path)
    if listing is None:
        raise UserError(f"{path} has no list of its photos beside it ({', '.join(list_names(path))}); export it "
                        "again with the list, or set poses.source=sfm")
    try:
        names = [line.split()[0] for line in listing.read_text(errors="replace").splitlines() if line.strip()]
        lines = [line for line in path.read_text(errors="replace").splitlines() if line.strip()]
        header = 1 if lines and lines[0].lstrip().startswith("#") else 0
        count = int(lines[header].split()[0])
        rows = [[float(v) for v in line.split()] for line in lines[header + 1: header + 1 + 5 * count]]
    except (OSError, ValueError, IndexError):
        raise UserError(f"{path} is not a Bundler file (a count of cameras, then five lines of numbers a camera); "
                        "export it again or set poses.source=sfm") from None
    if count != len(names) or len(rows) != 5 * count or any(len(row) != 3 for row in rows):
        raise UserError(f"{path} gives {count} cameras of {min(len(rows), 5 * count) // 5} whole ones, and "
                        f"{listing.name} names {len(names)} photos; export them again together or set "
                        "poses.source=sfm")
    cameras = []
    for i in range(count):
        block = np.array(rows[5 * i: 5 * i + 5])
        where = f"{path.name}, camera {i} ({Path(names[i]).name})"
        if not np.isfinite(block).all():
            raise UserError(f"{where}: not all its numbers are finite; fix it or set poses.source=sfm")
        if block[0, 0] == 0:  # left out of the reconstruction
            cameras.append(None)
            continue
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = block[1:4], block[4]
        if block[0, 0] < 0 or abs(np.linalg.det(w2c[:3, :3])) < 1e-9:
            raise UserError(f"{where}: its focal length is negative or its rotation is not invertible; fix it or set "
                            "poses.source=sfm")
        cameras.append((float(block[0, 0]), float(block[0, 1]), float(block[0, 2]), w2c))
    return names, cameras


def camera(focal: float, k1: float, k2: float, width: int, height: int) -> tuple[Intrinsics, Lens]:
    """The pinhole (for its photo, width x height, the principal point at its centre) and lens of a camera."""
    lens: Lens = ("OPENCV", (k1, k2, 0.0, 0.0))  # radial in the same normalised coordinates as OpenCV's
    return Intrinsics(focal, focal, width / 2, height / 2, width, height), lens


def camera_to_world(w2c: np.ndarray) -> np.ndarray:
    return np.linalg.inv(w2c)  # OpenGL's axes are ours


def imported(path: Path, records: list[dict]) -> Imported:
    """Poses from Bundler's cameras and their list of photos: a photo takes the camera of the line that names its
    stem, where one line alone does and the reconstruction kept it."""
    names, cameras_of = read(path)
    by_stem: dict[str, list[int]] = {}
    for i, name in enumerate(names):
        by_stem.setdefault(file_stem(name), []).append(i)
    reconstruction = pycolmap.Reconstruction()
    cameras = CameraTable(reconstruction)
    missing = []
    for record in records:
        index = by_stem.get(file_stem(record["source"]), [])
        found = cameras_of[index[0]] if len(index) == 1 else None
        if found is None:
            missing.append(record["name"])
            continue
        focal, k1, k2, w2c = found
        k, lens = camera(focal, k1, k2, record["original_width"], record["original_height"])
        where = f"{path.name}, camera {index[0]} ({Path(names[index[0]]).name})"
        add_image(reconstruction, len(reconstruction.images) + 1, record,
                  cameras.id_for(at_ingested_size(k, record, where), lens), camera_to_world(w2c), where)
    return Imported(reconstruction, path, missing, gravity=GRAVITY)
