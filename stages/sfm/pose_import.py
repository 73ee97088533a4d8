"""Poses a user already has: a COLMAP sparse model, a NeRF / instant-ngp / nerfstudio / Blender transforms.json, LLFF
poses_bounds.npy, IDR/NeuS cameras_sphere.npz (DTU-style sets), Metashape's exported cameras.xml, OpenSfM's
(OpenDroneMap's) reconstruction.json, NSVF's and NeRF++'s pose folders (svox2's), MVSNet's cams/, Polycam's raw export,
RealityCapture's XMP files, turned into the same distorted COLMAP model that SfM makes; the single-file formats whose
reader holds its own import (Record3D's metadata, RealityCapture's CSV, Meshroom's cameras.sfm, Bundler's bundle.out,
OpenMVG's sfm_data.json, Pix4D's calibrated camera parameters) dispatched to it.

Every importer returns an `Imported`: a `pycolmap.Reconstruction` whose image names are the ingested PNGs
(`<name>.png`) and whose cameras are scaled to the ingested image size, so it is undistorted and written exactly as an
SfM result is (stages/sfm/outputs.py). Pose files describe images by their own names and sizes; images are matched to
pose entries by path first, then by file stem (LLFF, which has no names, and IDR/NeuS, which number them, by sorted
file order), and the ones without a pose are listed."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pycolmap

from stages.capture.photos import (DATASET_SPLITS, POSE_FOLDERS, frame_photo, lexical_path, photo_folder,
                                   split_layout)
from stages.sfm import (bundler, meshroom, metashape, mvsnet, nsvf, openmvg, opensfm, pix4d, polycam,
                        realitycapture, record3d)
from stages.sfm.imported_model import (CameraTable, Imported, Lens, add_image, add_view, at_ingested_size,
                                       camera_within_bars, file_stem, finite_number, ingested_size, pixels_within_bars,
                                       scale_factor)
from stages.sfm.pose_files import (KINDS, candidates, colmap_models, holds_realitycapture_xmp, is_bundler,
                                   is_colmap_model, is_meshroom, is_openmvg, is_pix4d,
                                   is_realitycapture_csv)
from plenoxels.core.cameras import Intrinsics, opengl_c2w_from_llff, opengl_c2w_from_projection
from plenoxels.core.errors import UserError

# The single-file formats whose reader holds its own import (RealityCapture's CSV: its XMP files are camera files).
SINGLE_FILE_IMPORTS = {"record3d": record3d.imported, "realitycapture": realitycapture.imported_csv,
                       "meshroom": meshroom.imported, "bundler": bundler.imported, "openmvg": openmvg.imported,
                       "pix4d": pix4d.imported}
# nerfstudio's perspective camera models: their k1, k2, p1, p2 (k3) are OpenCV's radial-tangential distortion.
PERSPECTIVE_MODELS = {"OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"}


def kind_of(path: Path) -> str:
    if path.is_dir():
        if is_colmap_model(path) or colmap_models(path) or colmap_models(path.parent):
            return "colmap"
        if path.name in POSE_FOLDERS:
            return "nsvf"
        if path.name in polycam.CAMERA_FOLDERS.values():
            return "polycam"
        if path.name == mvsnet.CAMERA_FOLDER:
            return "mvsnet"
        if holds_realitycapture_xmp(path):
            return "realitycapture"
    elif path.name == "reconstruction.json":
        return "opensfm"
    elif path.name in record3d.METADATA_FILES:
        return "record3d"
    elif path.suffix.lower() == ".sfm" or is_meshroom(path):  # Meshroom's SfMData, as .sfm or .json
        return "meshroom"
    elif path.suffix.lower() == ".out" or is_bundler(path):
        return "bundler"
    elif is_openmvg(path):
        return "openmvg"
    elif is_pix4d(path):
        return "pix4d"
    elif path.suffix == ".json":
        return "transforms"
    elif path.suffix == ".npy":
        return "llff"
    elif path.suffix == ".npz":
        return "idr"
    elif path.suffix.lower() == ".xml":
        return "metashape"
    elif is_realitycapture_csv(path):
        return "realitycapture"
    raise UserError(f"poses.path {path} is not a COLMAP model folder, a transforms*.json, a poses_bounds.npy, an "
                    "IDR/NeuS cameras*.npz, a Metashape cameras .xml, an OpenSfM reconstruction.json, an NSVF pose/ "
                    "folder, Polycam's keyframes/cameras/, MVSNet's cams/, Record3D's metadata.json, or "
                    "RealityCapture's camera CSV or a folder of its XMP files, Meshroom's cameras.sfm, Bundler's "
                    "bundle.out, OpenMVG's sfm_data.json or Pix4D's *_calibrated_camera_parameters.txt")


def load(kind: str, path: Path, records: list[dict], scene: Path) -> Imported:
    if kind == "colmap":
        if not is_colmap_model(path):
            models = (colmap_models(path) or colmap_models(path.parent)) if path.is_dir() else []
            if not models:
                raise UserError(f"{path} holds no COLMAP model (cameras and images .bin/.txt, or sparse/0 with them); "
                                "point poses.path at the model folder")
            path = max(models, key=lambda m: pycolmap.Reconstruction(m).num_reg_images())
        return from_colmap(path, records)
    if kind == "transforms":
        return from_transforms(path, records, scene)
    if kind == "idr":
        return from_idr(path, records, scene)
    if kind == "metashape":
        return from_metashape(path, records)
    if kind == "opensfm":
        return from_opensfm(path, records)
    if kind in CAMERA_FILES and path.is_dir():
        return from_camera_files(kind, [path], records, scene)
    if kind in SINGLE_FILE_IMPORTS:
        return SINGLE_FILE_IMPORTS[kind](path, records)
    return from_llff(path, records)


def choose(kind: str, paths: list[Path], records: list[dict], scene: Path) -> Imported:
    """Of several pose files of one kind, the one that poses the most images (paths that match beat stems)."""
    best, best_score = None, None
    for path in paths:
        imported = load(kind, path, records, scene)
        score = (imported.path_matches, len(records) - len(imported.missing))
        if best_score is None or score > best_score:
            best, best_score = imported, score
    return best


def find(source: str, path: str, records: list[dict], scene: Path) -> tuple[str, Imported] | None:
    """The poses to import for a scene and their kind, or None when SfM should make them: `path` names a pose file
    or model folder (relative to the photos when not found as given), else the pose files beside the photos are
    searched; `source` is "auto", "sfm" or one of KINDS."""
    if source == "sfm":
        return None
    if path:
        given = Path(path).expanduser()
        if not given.is_absolute() and not given.exists():
            given = photo_folder(scene) / given
        if not given.exists():
            raise UserError(f"poses.path {path} does not exist; give a COLMAP model folder, a transforms*.json or a poses_bounds.npy")
        kind = source if source != "auto" else kind_of(given)
        return kind, load(kind, given, records, scene)
    found = candidates(scene)
    if split_layout(scene) == "blender" and source in ("auto", "transforms"):
        # One dataset in several files: the photos of every split the ingest kept are posed together.
        splits = [scene / f"transforms_{split}.json" for split in DATASET_SPLITS]
        present = [p for p in splits if p.is_file()]
        return "transforms", from_transforms(present[0], records, scene, tuple(present[1:]))
    for kind in [source] if source != "auto" else list(KINDS):
        folders = [p for p in found[kind] if p.is_dir()] if kind in CAMERA_FILES else []
        if folders:  # one dataset's camera folders (a split each: NeRF++), together
            return kind, from_camera_files(kind, folders, records, scene)
        if found[kind]:
            return kind, choose(kind, found[kind], records, scene)
    if source != "auto":
        raise UserError(f"poses.source={source} but no such pose file is beside the photos in "
                        f"{photo_folder(scene)}; set poses.path to it or use poses.source=auto")
    return None


# ---- COLMAP -----------------------------------------------------------------------------------------------

def from_colmap(model_dir: Path, records: list[dict]) -> Imported:
    try:
        source = pycolmap.Reconstruction(model_dir)
    except Exception as e:  # pycolmap raises plain RuntimeErrors for unreadable or truncated models
        raise UserError(f"cannot read the COLMAP model in {model_dir} ({str(e).splitlines()[0][:80]}); "
                        "fix it or set poses.source=sfm") from None
    by_stem: dict[str, pycolmap.Image] = {}
    for image in source.images.values():
        if image.has_pose:
            by_stem.setdefault(file_stem(image.name), image)
    out = pycolmap.Reconstruction()
    camera_ids: dict[tuple[int, int, int], int] = {}   # (source camera, w, h) -> new camera
    kept: dict[int, int] = {}                           # source image id -> new image id
    missing = []
    for record in records:
        image = by_stem.get(file_stem(record["source"])) or by_stem.get(record["name"])
        if image is None:
            missing.append(record["name"])
            continue
        cam, what = source.cameras[image.camera_id], f"the COLMAP model in {model_dir}"
        cropped = "frame_size" in record  # the model's camera sees the whole frame whose black bars ingest cropped
        if not cropped:
            scale_factor(record, cam.width, cam.height, what)
        width, height = ingested_size(record, cam.width, cam.height)  # as stored, where COLMAP read it so
        key = (image.camera_id, width, height)
        if key not in camera_ids:
            scaled = pycolmap.Camera(model=cam.model_name, width=cam.width, height=cam.height,
                                     params=list(cam.params), camera_id=len(camera_ids) + 1)
            scaled = camera_within_bars(scaled, record, what) if cropped else scaled
            scaled.rescale(width, height)
            camera_ids[key] = scaled.camera_id
            out.add_camera_with_trivial_rig(scaled)
        new_id = len(kept) + 1
        keypoints = np.array([p.xy for p in image.points2D], dtype=np.float64).reshape(-1, 2)
        keypoints = pixels_within_bars(keypoints, cam.width, cam.height, record) if cropped else \
            keypoints * [width / cam.width, height / cam.height]
        new_image = pycolmap.Image(name=f"{record['name']}.png", keypoints=keypoints, camera_id=camera_ids[key],
                                   image_id=new_id)
        out.add_image_with_trivial_frame(new_image, image.cam_from_world())
        kept[image.image_id] = new_id
    for point in source.points3D.values():
        elements = [pycolmap.TrackElement(kept[e.image_id], e.point2D_idx)
                    for e in point.track.elements if e.image_id in kept]
        if len(elements) >= 2:
            out.add_point3D(point.xyz, pycolmap.Track(elements), point.color)
    out.update_point_3d_errors()
    return Imported(out, model_dir, missing)


# ---- transforms.json (NeRF, instant-ngp, nerfstudio, Blender) --------------------------------------------

def _intrinsics_from(meta: dict, fallback: dict, record: dict, where: str) -> tuple[Intrinsics, Lens]:
    """A frame's camera from its own keys, else the file's: fl_x/fl_y/cx/cy/w/h or camera_angle_x/y, and its lens
    (`_lens`)."""
    def get(key, positive=False, default=None):
        value = meta.get(key, fallback.get(key))
        return default if value is None else finite_number(value, key, where, positive)

    w = get("w", positive=True, default=record["original_width"])
    h = get("h", positive=True, default=record["original_height"])
    fl_x = get("fl_x", positive=True)
    if fl_x is None and (angle_x := get("camera_angle_x", positive=True)) is not None:
        fl_x = 0.5 * w / math.tan(0.5 * angle_x)
    if fl_x is None:
        raise UserError(f"{where}: no focal length (fl_x or camera_angle_x); add one or set poses.source=sfm")
    fl_y = get("fl_y", positive=True)
    if fl_y is None:
        angle_y = get("camera_angle_y", positive=True)
        fl_y = 0.5 * h / math.tan(0.5 * angle_y) if angle_y is not None else fl_x
    cx, cy = get("cx", default=w / 2), get("cy", default=h / 2)
    return Intrinsics(fl_x, fl_y, cx, cy, int(round(w)), int(round(h))), _lens(meta, fallback, where, get)


def _lens(meta: dict, fallback: dict, where: str, get) -> Lens:
    """The COLMAP camera model and distortion coefficients a frame's `camera_model` (nerfstudio's names) and k1-k4,
    p1, p2 describe: OpenCV's radial-tangential model for a perspective camera (with k3 where it is given), its
    equidistant model for a fisheye (a 360 camera's frames are cut into views, `add_view`); another model stops with
    what to do."""
    model = _model_of(meta, fallback)
    if model in PERSPECTIVE_MODELS:
        k1, k2, p1, p2, k3 = (get(key, default=0.0) for key in ("k1", "k2", "p1", "p2", "k3"))
        return ("FULL_OPENCV", (k1, k2, p1, p2, k3, 0.0, 0.0, 0.0)) if k3 else ("OPENCV", (k1, k2, p1, p2))
    if model == "OPENCV_FISHEYE":
        return "OPENCV_FISHEYE", tuple(get(key, default=0.0) for key in ("k1", "k2", "k3", "k4"))
    raise UserError(f"{where}: camera_model {model} is not one this tool reads ({', '.join(sorted(PERSPECTIVE_MODELS))}"
                    ", OPENCV_FISHEYE); undistort the photos to pinholes, or set poses.source=sfm")


def _model_of(meta: dict, fallback: dict) -> str:
    return str(meta.get("camera_model", fallback.get("camera_model", "OPENCV"))).upper()


def _read_transforms(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
        if not isinstance(data["frames"], list):
            raise TypeError
    except (json.JSONDecodeError, KeyError, TypeError):
        raise UserError(f"{path} is not a transforms.json with a 'frames' list; fix it or set poses.source=sfm") from None
    return data


def from_transforms(path: Path, records: list[dict], scene: Path, more: tuple[Path, ...] = ()) -> Imported:
    """Poses from a transforms.json, and from the `more` files beside it (a split dataset's transforms_<split>.json
    files, read as one); a frame's own camera keys override its file's.

    A photo takes the frame whose file_path names it: both paths compared as written, made absolute without
    following links (stages.capture.photos.lexical_path), then, where that finds none, both with their links followed,
    where only one frame leads to the photo's file. A pose file written elsewhere (other folders, another machine)
    matches by file stem, where only one frame has that stem; a stem several frames share (r_0 in train/, val/ and
    test/) is refused, never guessed."""
    folder = photo_folder(scene)
    frames: list[tuple[dict, dict]] = []
    by_path: dict[Path, int] = {}
    by_target: dict[Path, list[int]] = {}
    by_stem: dict[str, list[int]] = {}
    for file in (path, *more):
        data = _read_transforms(file)
        for frame in data["frames"]:
            index = len(frames)
            frames.append((frame, data))
            file_path = str(frame.get("file_path", ""))
            written = lexical_path(file.parent / file_path)
            by_path.setdefault(written, index)
            by_path.setdefault(written.with_suffix(""), index)
            photo = frame_photo(file.parent, file_path)
            if photo is not None:
                by_target.setdefault(photo.resolve(), []).append(index)
            by_stem.setdefault(file_stem(file_path), []).append(index)
    reconstruction = pycolmap.Reconstruction()
    cameras = CameraTable(reconstruction)
    missing, ambiguous, path_matches = [], [], 0
    for record in records:
        photo = folder / record["source"]
        index = by_path.get(lexical_path(photo))
        if index is None:
            index = by_path.get(lexical_path(photo).with_suffix(""))
        if index is None and len(by_target.get(photo.resolve(), [])) == 1:
            index = by_target[photo.resolve()][0]
        path_matches += index is not None
        if index is None:
            same_stem = by_stem.get(file_stem(record["source"]), [])
            if len(same_stem) > 1:
                ambiguous.append(record["source"])
                continue
            index = same_stem[0] if same_stem else None
        if index is None:
            missing.append(record["name"])
            continue
        frame, data = frames[index]
        where = f"{path.name if not more else 'the transforms files'}, the frame of {record['source']}"
        if not isinstance(frame, dict) or "transform_matrix" not in frame:
            raise UserError(f"{where} has no transform_matrix; add it or set poses.source=sfm")
        if "panorama" in record or _model_of(frame, data) == "EQUIRECTANGULAR":
            model = _model_of(frame, data)
            add_view(reconstruction, cameras, record, f"camera_model {model}", model == "EQUIRECTANGULAR",
                     frame["transform_matrix"], where)
            continue
        k, lens = _intrinsics_from(frame, data, record, where)
        scaled = at_ingested_size(k, record, str(path))
        add_image(reconstruction, len(reconstruction.images) + 1, record, cameras.id_for(scaled, lens),
                  frame["transform_matrix"], where)
    if ambiguous:
        raise UserError(f"{len(ambiguous)} photo(s) match no frame of {path.name if not more else 'the transforms files'}"
                        f" by path, and several frames by name ({', '.join(ambiguous[:3])}"
                        f"{', ...' if len(ambiguous) > 3 else ''}); make each frame's file_path name its photo, relative "
                        f"to the pose file")
    return Imported(reconstruction, path.parent if more else path, missing, path_matches=path_matches)


# ---- LLFF poses_bounds.npy --------------------------------------------------------------------------------

def from_llff(path: Path, records: list[dict]) -> Imported:
    """poses_bounds.npy rows follow the sorted photo file names; each is a 3x5 [down, right, back, centre, hwf]
    plus near and far. The focal is for the full-size photos, so it is scaled by the width ratio."""
    try:
        table = np.load(path)
    except (ValueError, OSError):
        raise UserError(f"cannot read {path} as an LLFF poses_bounds.npy; fix it or set poses.source=sfm") from None
    if table.ndim != 2 or table.shape[1] != 17:
        raise UserError(f"{path} has shape {table.shape}; LLFF poses_bounds.npy is [N, 17]")
    ordered = sorted(records, key=lambda r: r["source"])
    if len(ordered) != len(table):
        raise UserError(f"{path} has {len(table)} poses but the folder has {len(ordered)} photos; LLFF poses "
                        "follow the photos' sorted order, so the counts must match (or set poses.source=sfm)")
    reconstruction = pycolmap.Reconstruction()
    cameras = CameraTable(reconstruction)
    bounds = {}
    for number, (row, record) in enumerate(zip(table, ordered)):
        where = f"{path.name}, row {number} ({record['source']})"
        if not np.isfinite(row).all():
            raise UserError(f"{where} holds NaN or infinite numbers; fix the pose file or set poses.source=sfm")
        pose = row[:15].reshape(3, 5)
        h, w, focal = (finite_number(value, key, where, positive=True)
                       for value, key in zip(pose[:, 4], ("h", "w", "focal")))
        k = at_ingested_size(Intrinsics(focal, focal, w / 2, h / 2, int(round(w)), int(round(h))), record, str(path),
                             w, h)
        add_image(reconstruction, len(reconstruction.images) + 1, record, cameras.id_for(k),
                  opengl_c2w_from_llff(pose[:, :4]), where)
        bounds[record["name"]] = (float(row[15]), float(row[16]))
    return Imported(reconstruction, path, [], bounds)


# ---- IDR / NeuS cameras_sphere.npz ------------------------------------------------------------------------

def from_idr(path: Path, records: list[dict], scene: Path) -> Imported:
    """IDR's and NeuS's cameras (their DTU and BlendedMVS releases): `world_mat_i`, the projection K [R | t] of the
    i-th photo in sorted file order (the number in its name, where every name is one), and `scale_mat_i`, which takes the unit sphere around the object to the world;
    the poses are kept in the sphere's frame (world_mat @ scale_mat), as those methods use them. Their K puts pixel
    centres at whole numbers, ours at +0.5."""
    try:
        with np.load(path) as data:
            projections = {int(key[len("world_mat_"):]): data[key] @ data.get(f"scale_mat_{key[len('world_mat_'):]}",
                                                                                 np.eye(4))
                           for key in data.files if key.startswith("world_mat_") and key[len("world_mat_"):].isdigit()}
    except (ValueError, OSError, KeyError, TypeError):
        raise UserError(f"cannot read {path} as IDR/NeuS cameras (world_mat_N, scale_mat_N); fix it or set "
                        "poses.source=sfm") from None
    if not projections:
        raise UserError(f"{path} holds no world_mat_N projections; it is not an IDR/NeuS camera file (set poses.source)")
    # Photos numbered by their names (000000.png) take those numbers, so a photo ingest skipped shifts no other.
    numbered = all(file_stem(r["source"]).isdigit() for r in records)
    ordered = sorted(records, key=lambda r: r["source"])
    if not numbered and len(ordered) != len(projections):
        raise UserError(f"{path} has {len(projections)} cameras but the folder has {len(ordered)} photos; its cameras "
                        "follow the photos' sorted order, so the counts must match (or set poses.source=sfm)")
    reconstruction = pycolmap.Reconstruction()
    cameras = CameraTable(reconstruction)
    missing = []
    for position, record in enumerate(ordered):
        index = int(file_stem(record["source"])) if numbered else position
        if index not in projections:
            missing.append(record["name"])
            continue
        matrix, c2w = opengl_c2w_from_projection(projections[index])
        w, h = record["original_width"], record["original_height"]
        k = at_ingested_size(Intrinsics(matrix[0, 0], matrix[1, 1], matrix[0, 2] + 0.5, matrix[1, 2] + 0.5, w, h),
                             record, str(path))
        add_image(reconstruction, len(reconstruction.images) + 1, record, cameras.id_for(k), c2w,
                  f"{path.name}, world_mat_{index} ({record['source']})")
    return Imported(reconstruction, path, missing)


# ---- Metashape cameras.xml ----------------------------------------------------------------------------------

def from_metashape(path: Path, records: list[dict]) -> Imported:
    """Poses from Metashape's exported cameras (stages/sfm/metashape.py): a photo takes the aligned camera labelled
    with its file name, with or without its suffix; a label several cameras share is refused, never guessed."""
    chunk, sensors, components, found = metashape.read(path)
    by_label: dict[str, list[int]] = {}
    for index, (label, *_) in enumerate(found):
        by_label.setdefault(label, []).append(index)
    reconstruction = pycolmap.Reconstruction()
    cameras = CameraTable(reconstruction)
    missing = []
    for record in records:
        source = Path(record["source"])
        hits = by_label.get(source.name) or by_label.get(source.stem) or []
        if len(hits) > 1:
            raise UserError(f"{path}: {len(hits)} aligned cameras are labelled {source.stem}; label each photo's "
                            "camera once (or set poses.source=sfm)")
        if not hits:
            missing.append(record["name"])
            continue
        label, sensor_id, component_id, transform = found[hits[0]]
        where = f"{path.name}, camera {label}"
        kind, calibration = sensors.get(sensor_id, (None, None))
        c2w = metashape.camera_to_world(transform, components.get(component_id), where)
        if "panorama" in record or kind == "spherical":
            add_view(reconstruction, cameras, record, f"a {kind} sensor", kind == "spherical", c2w, where)
            continue
        if calibration is None:
            raise UserError(f"{where}: its sensor {sensor_id} has no calibration; export the cameras of an aligned "
                            "chunk, or set poses.source=sfm")
        k, model, coefficients = metashape.camera_and_lens(kind, calibration, where)
        camera_id = cameras.id_for(at_ingested_size(k, record, str(path)), (model, coefficients))
        add_image(reconstruction, len(reconstruction.images) + 1, record, camera_id, c2w, where)
    return Imported(reconstruction, path, missing, gravity=metashape.gravity(chunk, path))


# ---- OpenSfM / OpenDroneMap reconstruction.json ------------------------------------------------------------

def from_opensfm(path: Path, records: list[dict]) -> Imported:
    """Poses from an OpenSfM reconstruction.json (stages/sfm/opensfm.py), of its reconstructions the one that poses
    the most photos: a photo takes the shot named as its file, or its stem where one shot alone has it."""
    def shot_names(shots: dict) -> dict[str, str]:
        by_stem: dict[str, list[str]] = {}
        for key in shots:
            by_stem.setdefault(Path(key).stem, []).append(key)
        names = {}
        for record in records:
            source = Path(record["source"])
            named = [key for key in (source.as_posix(), source.name) if key in shots]
            stems = by_stem.get(source.stem, [])
            if named or len(stems) == 1:
                names[record["name"]] = named[0] if named else stems[0]
        return names

    chosen = max(opensfm.read(path), key=lambda r: len(shot_names(r["shots"])))
    names, cameras_of = shot_names(chosen["shots"]), chosen.get("cameras") or {}
    reconstruction = pycolmap.Reconstruction()
    cameras = CameraTable(reconstruction)
    missing = []
    for record in records:
        if record["name"] not in names:
            missing.append(record["name"])
            continue
        shot = chosen["shots"][names[record["name"]]]
        where = f"{path.name}, shot {names[record['name']]}"
        camera = cameras_of.get(shot.get("camera")) if isinstance(shot, dict) else None
        if not isinstance(camera, dict):
            raise UserError(f"{where}: its camera is not among the reconstruction's cameras; fix the reconstruction or "
                            "set poses.source=sfm")
        c2w = opensfm.camera_to_world(shot, where)
        projection = str(camera.get("projection_type", "perspective"))
        if "panorama" in record or projection in opensfm.PANORAMA_PROJECTIONS:
            add_view(reconstruction, cameras, record, f"a {projection} camera",
                     projection in opensfm.PANORAMA_PROJECTIONS, c2w, where)
            continue
        k, model, coefficients = opensfm.camera_and_lens(camera, where)
        camera_id = cameras.id_for(at_ingested_size(k, record, str(path)), (model, coefficients))
        add_image(reconstruction, len(reconstruction.images) + 1, record, camera_id, c2w, where)
    return Imported(reconstruction, path, missing, gravity=opensfm.GRAVITY)


# ---- a camera file a photo: NSVF's, NeRF++'s, Polycam's, MVSNet's, RealityCapture's -------------------------

CAMERA_FILES = {"nsvf": (".txt", nsvf), "polycam": (".json", polycam), "mvsnet": (mvsnet.SUFFIX, mvsnet),
                "realitycapture": (realitycapture.SUFFIX, realitycapture)}


def from_camera_files(kind: str, folders: list[Path], records: list[dict], scene: Path) -> Imported:
    """Poses from folders of a camera file a photo (stages/sfm/nsvf.py, polycam.py, mvsnet.py, realitycapture.py):
    a photo takes the file named as it in its own camera folder (beside its photos' folder, or its own folder), where
    that is among `folders`; a photo with no camera folder of its own, the one file of its name in `folders`
    (NeRF++'s splits repeat names, so a file is never taken from another split)."""
    suffix, reader = CAMERA_FILES[kind]
    photos, named_folders = photo_folder(scene), {lexical_path(f) for f in folders}
    by_name: dict[str, list[Path]] = {}
    for folder in folders:
        for file in sorted(folder.glob(f"*{suffix}")):
            by_name.setdefault(file.name[:-len(suffix)], []).append(file)
    reconstruction = pycolmap.Reconstruction()
    cameras = CameraTable(reconstruction)
    missing = []
    for record in records:
        photo = photos / record["source"]
        own = reader.own_folders(photo.parent)
        named = [folder / f"{photo.stem}{suffix}" for folder in own if lexical_path(folder) in named_folders
                 and (folder / f"{photo.stem}{suffix}").is_file()] if own else by_name.get(photo.stem, [])
        if len(named) != 1:
            missing.append(record["name"])
            continue
        where = f"{named[0].parent.name}/{named[0].name}"
        found = reader.camera(named[0], record["original_width"], record["original_height"], where)
        if found is None:  # a file that does not pose its photo (RealityCapture's, for a photo it did not align)
            missing.append(record["name"])
            continue
        k, c2w, lens = found
        add_image(reconstruction, len(reconstruction.images) + 1, record,
                  cameras.id_for(at_ingested_size(k, record, where), lens), c2w, where)
    return Imported(reconstruction, folders[0] if len(folders) == 1 else scene, missing,
                    gravity=reader.GRAVITY)
