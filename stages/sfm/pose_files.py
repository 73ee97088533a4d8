"""Pose files beside a scene's photos: the COLMAP models, transforms*.json, poses_bounds.npy, IDR/NeuS cameras,
Metashape cameras .xml, OpenSfM reconstruction.json, NSVF's or NeRF++'s pose folders, Polycam's camera folder,
MVSNet's cams/, Record3D's metadata, RealityCapture's XMP files or CSV, Meshroom's cameras.sfm, Bundler's bundle.out,
OpenMVG's sfm_data.json and Pix4D's calibrated camera parameters the importers (pose_import.py) could read. Finding
them reads no pose, so a cache key lists them without loading COLMAP."""
from __future__ import annotations

import json
import re
from pathlib import Path

from stages.capture.photos import (DATASET_SPLITS, IMAGE_SUFFIXES, POLYCAM_CAMERAS, POSE_FOLDERS, photo_folder,
                                   split_folder, split_layout)

KINDS = ("colmap", "transforms", "llff", "idr", "metashape", "opensfm", "nsvf", "polycam", "mvsnet", "record3d",
         "realitycapture", "meshroom", "bundler", "openmvg", "pix4d")
# IDR's and NeuS's camera files: the projection of the i-th photo (sorted by name) and the sphere around the object.
IDR_FILES = ("cameras_sphere.npz", "cameras.npz")
# Bytes of a file read to tell a tool's pose file from others of its type (Metashape's XML, Record3D's JSON).
HEAD_BYTES = 4096
# Record3D's metadata, beside its rgb/ folder of frames.
RECORD3D_FILES = ("metadata.json", "metadata")
# RealityCapture's XMP file beside a photo that it aligned (its namespace, and a pose), and the columns of its camera
# CSV export that the importer reads.
REALITYCAPTURE_MARKS = (b"capturingreality.com/ns/xcr", b"Rotation", b"Position")
REALITYCAPTURE_COLUMNS = ("#name", "x", "y", "alt", "heading", "pitch", "roll", "f", "px", "py")
# Meshroom's SfMData beside the photos, or in a Meshroom project's cache there.
MESHROOM_FILES = ("*.sfm", "MeshroomCache/StructureFromMotion/*/cameras.sfm")
# Bundler's cameras (in its bundle/ folder or beside the photos), and the names its list of photos goes by.
BUNDLER_FILES = ("*.out", "bundle/*.out")
BUNDLER_LISTS = ("{name}.list.txt", "{stem}.list.txt", "{stem}_list.txt", "list.txt", "imagelist.txt")
# OpenMVG's scene as JSON, beside the photos or in an output folder there (reconstruction_sequential/, ...).
OPENMVG_FILES = ("sfm_data*.json", "*/sfm_data*.json")
OPENMVG_LISTING = "matches"  # the folder of its image listing, made before SfM: views without poses
# Pix4D's cameras: in its project's params folder (the project beside the photos, or the photos in it), or beside them.
PIX4D_FILES = tuple(f"{folder}*_calibrated_camera_parameters.txt"
                    for folder in ("", "params/", "1_initial/params/", "*/1_initial/params/"))
# Binary pose files (not read): where each tool writes them beside the photos, what it is, and the command that writes
# one that is read ({name}: the file's name).
BINARY_POSE_FILES = {
    ("sfm_data.bin", "*/sfm_data.bin"): ("openmvg", "OpenMVG's scene in its binary form",
                                         "openMVG_main_ConvertSfM_DataFormat -i {name} -o sfm_data.json"),
    ("sfm*.abc", "cameras*.abc", "MeshroomCache/StructureFromMotion/*/sfm*.abc"): (
        "meshroom", "Meshroom's SfMData as Alembic", "aliceVision_convertSfMFormat -i {name} -o cameras.sfm"),
}


def colmap_models(folder: Path) -> list[Path]:
    """COLMAP model folders under `folder`: sparse/0, sparse/1, ... or sparse/ itself."""
    sparse = folder / "sparse"
    if not sparse.is_dir():
        return []
    found = [d for d in sorted(sparse.iterdir()) if d.is_dir() and is_colmap_model(d)]
    return found or ([sparse] if is_colmap_model(sparse) else [])


def is_colmap_model(folder: Path) -> bool:
    return all((folder / f"{part}.bin").is_file() or (folder / f"{part}.txt").is_file()
               for part in ("cameras", "images"))


def candidates(scene: Path) -> dict[str, list[Path]]:
    """Pose files beside the photos (the photo folder first, then its parent), by kind."""
    found: dict[str, list[Path]] = {kind: [] for kind in KINDS}
    folder = photo_folder(scene)
    for place in (folder, folder.parent) if not scene.is_file() else (folder,):
        found["colmap"] += colmap_models(place)
        found["transforms"] += sorted(p for p in place.glob("transforms*.json") if p.is_file())
        if (place / "poses_bounds.npy").is_file():
            found["llff"].append(place / "poses_bounds.npy")
        found["idr"] += [place / name for name in IDR_FILES if (place / name).is_file()]
        found["metashape"] += [p for p in sorted(place.glob("*.xml")) if is_metashape(p)]
        found["opensfm"] += [p for p in (place / "opensfm" / "reconstruction.json", place / "reconstruction.json")
                             if p.is_file()]
        found["nsvf"] += pose_folders(place, folder)
        found["record3d"] += [place / name for name in RECORD3D_FILES if is_record3d(place / name)]
        found["mvsnet"] += [place / "cams"] if names_a_photo(place / "cams", "_cam.txt", folder) else []
        found["realitycapture"] += [p for p in sorted(place.glob("*.csv")) if is_realitycapture_csv(p)]
        found["meshroom"] += [p for pattern in MESHROOM_FILES for p in sorted(place.glob(pattern)) if is_meshroom(p)]
        found["bundler"] += [p for pattern in BUNDLER_FILES for p in sorted(place.glob(pattern)) if is_bundler(p)]
        found["openmvg"] += [p for pattern in OPENMVG_FILES for p in sorted(place.glob(pattern))
                             if is_openmvg(p) and p.parent.name != OPENMVG_LISTING]
        found["pix4d"] += [p for pattern in PIX4D_FILES for p in sorted(place.glob(pattern)) if is_pix4d(p)]
    for kind in ("openmvg", "pix4d"):  # the photo folder's, found from its parent too
        found[kind] = list(dict.fromkeys(found[kind]))
    if aligned_by_realitycapture(folder):  # its XMP files before its CSV
        found["realitycapture"].insert(0, folder)
    found["polycam"] += [camera_folder for camera_folder in [folder.parent / POLYCAM_CAMERAS.get(folder.name, "")]
                         if folder.name in POLYCAM_CAMERAS and camera_folder.is_dir()]
    if split_layout(scene) == "nerfpp":
        found["nsvf"] += [pose for split in DATASET_SPLITS if (photos := split_folder(scene, split)) is not None
                          for pose in pose_folders(photos.parent, photos)]
    return found


def unread(scene: Path) -> list[tuple[Path, str, str]]:
    """Binary pose files beside the photos (BINARY_POSE_FILES) of a tool none of whose readable files is there: each
    with what it is and the command that writes one that is read."""
    folder = photo_folder(scene)
    if scene.is_file():
        return []
    found = candidates(scene)
    listed = {p: (what, command.format(name=p.name)) for patterns, (kind, what, command) in BINARY_POSE_FILES.items()
              if not found[kind] for place in (folder, folder.parent) for pattern in patterns
              for p in sorted(place.glob(pattern)) if p.is_file()}
    return [(path, what, command) for path, (what, command) in listed.items()]


def numbered_frames(scene: Path) -> bool:
    """Whether the scene's poses are Record3D's alone: a video's frames, posed by their numbers, so that ingest may
    read one in N of a long capture as it reads a video (every other pose file fixes the photos it poses)."""
    found = candidates(scene)
    return bool(found["record3d"]) and not any(paths for kind, paths in found.items() if kind != "record3d")


def pose_folders(place: Path, photos: Path) -> list[Path]:
    """NSVF's and NeRF++'s pose folders in `place` (pose/, poses/, extrinsic/) that pose a photo in `photos`."""
    return [place / name for name in POSE_FOLDERS if names_a_photo(place / name, ".txt", photos)]


def names_a_photo(folder: Path, suffix: str, photos: Path) -> bool:
    """Whether `folder` holds a file named as a photo in `photos` (its stem and `suffix`): a folder of a camera file
    a photo, not of notes that share its name."""
    if not folder.is_dir() or not photos.is_dir():
        return False
    return any((folder / f"{photo.stem}{suffix}").is_file() for photo in photos.iterdir()
               if photo.suffix.lower() in IMAGE_SUFFIXES)


def _head(path: Path) -> bytes:
    """A file's first HEAD_BYTES (none where it cannot be read: the importer names it)."""
    try:
        with open(path, "rb") as f:
            return f.read(HEAD_BYTES)
    except OSError:
        return b""


def is_record3d(path: Path) -> bool:
    """Whether a file is Record3D's metadata (a JSON object whose head holds its camera matrix, K, and its poses)."""
    head = _head(path)
    return head.lstrip().startswith(b"{") and b'"K"' in head and b'"poses"' in head


def aligned_by_realitycapture(photos: Path) -> bool:
    """Whether a photo in `photos` has RealityCapture's XMP file beside it, with a pose (REALITYCAPTURE_MARKS): not
    a photo editor's sidecar of the same name."""
    return photos.is_dir() and any(all(mark in _head(photo.with_suffix(".xmp")) for mark in REALITYCAPTURE_MARKS)
                                   for photo in photos.iterdir() if photo.suffix.lower() in IMAGE_SUFFIXES)


def holds_realitycapture_xmp(folder: Path) -> bool:
    """Whether a folder holds RealityCapture's XMP files with a pose (the folder they were exported to)."""
    return folder.is_dir() and any(all(mark in _head(xmp) for mark in REALITYCAPTURE_MARKS)
                                   for xmp in folder.iterdir() if xmp.suffix.lower() == ".xmp")


def is_realitycapture_csv(path: Path) -> bool:
    """Whether a .csv file is RealityCapture's camera export (its header names the columns the importer reads)."""
    first_line = _head(path).decode("utf-8-sig", errors="replace").splitlines()[:1]
    header = [column.strip().lower() for column in first_line[0].split(",")] if first_line else []
    return all(column in header for column in REALITYCAPTURE_COLUMNS)


def is_meshroom(path: Path) -> bool:
    """Whether a file is Meshroom's SfMData as JSON (its head holds AliceVision's version and views; an .sfm may be
    Alembic, which is not read)."""
    head = _head(path)
    return head.lstrip().startswith(b"{") and b'"version"' in head and b'"views"' in head


def is_bundler(path: Path) -> bool:
    """Whether a file is Bundler's cameras (its header says so)."""
    return _head(path).lstrip().lower().startswith(b"# bundle file")


def is_openmvg(path: Path) -> bool:
    """Whether a file is OpenMVG's SfM_Data as JSON (its head names the format's version)."""
    head = _head(path)
    return head.lstrip().startswith(b"{") and b'"sfm_data_version"' in head


def is_pix4d(path: Path) -> bool:
    """Whether a file is Pix4D's calibrated camera parameters (its header names the fields)."""
    head = _head(path)
    return head.lstrip().startswith(b"fileName imageWidth imageHeight") and b"camera rotation R" in head


def is_metashape(path: Path) -> bool:
    """Whether an .xml file is Metashape's cameras (a <document> whose head opens a <chunk>)."""
    head = _head(path)
    return b"<document" in head and b"<chunk" in head


def pose_files(scene: Path) -> list[Path]:
    """Every file the importers could read for this scene (for a cache key)."""
    files: list[Path] = []
    for kind, paths in candidates(scene).items():
        for path in paths:
            suffix = ".xmp" if kind == "realitycapture" else ""  # the photo folder: its XMP files
            files += sorted(p for p in path.iterdir() if p.is_file() and p.name.lower().endswith(suffix)) \
                if path.is_dir() else [path]
    return files


def poses_equirect(scene: Path) -> bool:
    """Whether a pose file beside the photos poses 360 frames: a transforms.json's camera_model EQUIRECTANGULAR
    (nerfstudio's, for the file or any of its frames), a Metashape spherical sensor, an OpenSfM or OpenMVG spherical
    camera.
    Ingest then cuts the frames into views, and the import poses each view from its frame's pose."""
    found = candidates(scene)
    marks = [(path, rb"\"projection_type\"\s*:\s*\"(spherical|equirectangular)\"") for path in found["opensfm"]]
    marks += [(path, rb"<sensor\b[^>]*\btype=\"spherical\"") for path in found["metashape"]]
    marks += [(path, rb"\"polymorphic_name\"\s*:\s*\"spherical\"") for path in found["openmvg"]]
    for path, mark in marks:
        try:
            if re.search(mark, path.read_bytes()):
                return True
        except OSError:  # named where the import reads it
            continue
    for path in found["transforms"]:
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):  # a damaged pose file is named where the import reads it
            continue
        frames = data.get("frames") if isinstance(data, dict) else None
        models = [data.get("camera_model")] if isinstance(data, dict) else []
        models += [f.get("camera_model") for f in frames if isinstance(f, dict)] if isinstance(frames, list) else []
        if any(str(model).upper() == "EQUIRECTANGULAR" for model in models):
            return True
    return False
