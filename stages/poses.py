"""Poses: camera poses and pinhole intrinsics for every ingested image, by COLMAP SfM through pycolmap
or imported from pose files the user already has (see stages/poses_import.py).

Writes poses/transforms.json (nerfstudio layout, OpenGL camera-to-world in the frame the poses came
in), poses/images/ (undistorted pinhole PNGs, the ingested names), poses/masks/ (when ingest kept
masks), poses/sparse/ (the undistorted COLMAP model, binary) and poses/points.npz (sparse points and
their observations). SfM and imports both end as a distorted COLMAP model at the ingested image size,
and one path undistorts and writes it, so later stages never know where the poses came from.
"""
from __future__ import annotations

import shutil
import statistics
import time
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Literal

import numpy as np
import pycolmap
from PIL import Image

from pipeline.cameras import opengl_c2w_from_colmap_w2c
from pipeline.config import require
from pipeline.errors import UserError
from pipeline.io import read_json, write_json, write_png
from stages import poses_import
from stages.ingest import VIDEO_SUFFIXES

NAME = "poses"
DEPENDS: tuple[str, ...] = ("ingest",)
VERSION = 1
CODE = ("stages/poses_import.py",)

# COLMAP's own detection threshold; lowered by this factor when images yield too few features.
SIFT_PEAK_THRESHOLD = 0.02 / 3
LOW_FEATURE_PEAK_DIVISOR = 3.0
# A pair counts as verified with at least this many geometric inliers (COLMAP's default).
MIN_VERIFIED_INLIERS = 15
# Looser registration thresholds for a second mapping pass when the first leaves images out.
RELAXED_ABS_POSE_MIN_INLIERS = 15
RELAXED_ABS_POSE_MIN_INLIER_RATIO = 0.15
RELAXED_INIT_MIN_INLIERS = 50
EXIF_MODEL_TAG = 0x0110
NAMES_SHOWN = 8


@dataclass
class Settings:
    source: Literal["auto", "sfm", "colmap", "transforms", "llff"] = "auto"  # auto: import pose files found beside the photos, else SfM
    path: str = ""                      # an explicit pose file or COLMAP model folder (kind taken from source, or guessed)
    camera_model: Literal["SIMPLE_RADIAL", "OPENCV", "RADIAL", "SIMPLE_PINHOLE", "PINHOLE"] = "SIMPLE_RADIAL"
    shared_camera: Literal["auto", "yes", "no"] = "auto"  # auto: one camera when sizes and EXIF camera models agree
    max_features: int = 8192            # SIFT features per image
    feature_max_side: int = 0           # extract features on images downscaled to this side (0: the ingested size)
    min_features: int = 1000            # median features per image below this: extract again with a lower threshold
    matching: Literal["auto", "exhaustive", "sequential"] = "auto"
    # auto matching: exhaustive up to this many images; above (and for video) sequential, completed by exhaustive when
    # that leaves a photo set partly registered. Sequential cannot close a loop around an object; on cup (77 photos, a
    # 336-degree orbit) the median rotation error against its model was 1.97 degrees sequential, 1.26 exhaustive.
    exhaustive_max_images: int = 100
    sequential_overlap: int = 10        # neighbours each image is matched with in sequential matching
    mapper: Literal["incremental", "global"] = "incremental"
    refine_principal_point: bool = False
    min_registered_share: float = 0.5   # fail when fewer than this share of the images register
    use_gpu: bool = True                # SIFT on the GPU when pycolmap was built with CUDA
    seed: int = 0
    colmap_log: bool = False            # show COLMAP's own log lines

    def check(self) -> None:
        require(self.max_features >= 64, "poses.max_features must be at least 64")
        require(self.feature_max_side == 0 or self.feature_max_side >= 64,
                "poses.feature_max_side must be 0 (the ingested size) or at least 64")
        require(self.min_features >= 0, "poses.min_features must be 0 or more")
        require(self.exhaustive_max_images >= 2, "poses.exhaustive_max_images must be at least 2")
        require(self.sequential_overlap >= 1, "poses.sequential_overlap must be at least 1")
        require(0.0 < self.min_registered_share <= 1.0, "poses.min_registered_share must be in (0, 1]")
        require(not (self.path and self.source == "sfm"), "poses.path names pose files to import; it cannot be used with poses.source=sfm")


def fingerprint(scene: Path) -> list:
    """Pose files beside the photos decide what this stage does, so they are part of its key."""
    return [[str(p), p.stat().st_size, p.stat().st_mtime_ns] for p in poses_import.pose_files(scene)]


@contextmanager
def _colmap_logging(verbose: bool) -> Iterator[None]:
    """COLMAP logs every step through glog; by default only its errors get through."""
    previous = (pycolmap.logging.minloglevel, pycolmap.logging.stderrthreshold)
    if not verbose:
        pycolmap.logging.minloglevel = 2
        pycolmap.logging.stderrthreshold = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel, pycolmap.logging.stderrthreshold = previous


def _names(names: list[str]) -> str:
    shown = ", ".join(names[:NAMES_SHOWN])
    return shown + (f" and {len(names) - NAMES_SHOWN} more" if len(names) > NAMES_SHOWN else "")


def _pycolmap_device(use_gpu: bool) -> pycolmap.Device:
    return pycolmap.Device.cuda if use_gpu and pycolmap.has_cuda else pycolmap.Device.cpu


# ---- SfM --------------------------------------------------------------------------------------------------

def _one_camera(records: list[dict], scene: Path) -> bool:
    """True when every photo has the same size and the same EXIF camera model (or none)."""
    if len({(r["width"], r["height"]) for r in records}) > 1:
        return False
    models = set()
    for record in records:
        try:
            with Image.open(poses_import.photo_folder(scene) / record["source"]) as im:
                models.add(im.getexif().get(EXIF_MODEL_TAG))
        except (OSError, ValueError):
            models.add(None)
    return len(models) <= 1


def _extract(db: Path, image_dir: Path, names: list[str], s: Settings, single_camera: bool,
             peak_threshold: float) -> None:
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = s.camera_model
    options = pycolmap.FeatureExtractionOptions()
    options.sift.max_num_features = s.max_features
    options.sift.peak_threshold = peak_threshold
    options.max_image_size = s.feature_max_side or -1
    options.use_gpu = s.use_gpu and pycolmap.has_cuda
    db.unlink(missing_ok=True)
    pycolmap.extract_features(db, image_dir, image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.PER_IMAGE,
                              reader_options=reader, extraction_options=options, device=_pycolmap_device(s.use_gpu))


def _median_features(db: Path) -> float:
    with pycolmap.Database.open(db) as database:
        return statistics.median(database.num_keypoints_for_image(image.image_id) for image in database.read_all_images())


def _match(db: Path, mode: str, s: Settings) -> None:
    options = pycolmap.FeatureMatchingOptions()
    options.use_gpu = s.use_gpu and pycolmap.has_cuda
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = s.seed
    device = _pycolmap_device(s.use_gpu)
    if mode == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = s.sequential_overlap
        pycolmap.match_sequential(db, matching_options=options, pairing_options=pairing,
                                  verification_options=verification, device=device)
    else:
        pycolmap.match_exhaustive(db, matching_options=options, verification_options=verification, device=device)


def _matching_summary(db: Path) -> dict:
    """Pairs matched and verified, and the images with fewer than two verified partners."""
    with pycolmap.Database.open(db) as database:
        names = {image.image_id: image.name for image in database.read_all_images()}
        pair_ids, inliers = database.read_two_view_geometry_num_inliers()
        matched = database.num_matched_image_pairs()
    partners: Counter = Counter()
    verified = 0
    for pair_id, count in zip(pair_ids, inliers):
        if count >= MIN_VERIFIED_INLIERS:
            verified += 1
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            partners[a] += 1
            partners[b] += 1
    poorly = sorted(Path(names[i]).stem for i in names if partners[i] < 2)
    return {"pairs_matched": matched, "pairs_verified": verified, "poorly_matched": poorly,
            "inlier_matches": int(sum(c for c in inliers if c >= MIN_VERIFIED_INLIERS))}


def _match_and_summarise(db: Path, mode: str, s: Settings, n_images: int, report, seconds: dict) -> dict:
    started = time.perf_counter()
    report.info(f"matching features ({mode})")
    _match(db, "exhaustive" if mode.startswith("exhaustive") else mode, s)
    seconds["match"] += time.perf_counter() - started
    matching = _matching_summary(db)
    report.info(f"matching: {matching['pairs_verified']} of {matching['pairs_matched']} image pairs verified, "
                f"{matching['inlier_matches']} inlier matches")
    poorly = matching.pop("poorly_matched")
    if poorly:
        report.warn(f"{len(poorly)} image(s) verified with fewer than 2 others, so they may not register: {_names(poorly)}")
    if matching["pairs_verified"] < n_images - 1:
        report.warn(f"only {matching['pairs_verified']} image pairs verified for {n_images} images; the photos "
                    "may overlap too little (take more, closer together)")
    return matching


def _incremental(db: Path, image_dir: Path, out: Path, s: Settings, relaxed: bool = False) -> list[pycolmap.Reconstruction]:
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = s.seed
    options.mapper.random_seed = s.seed
    options.triangulation.random_seed = s.seed
    options.min_model_size = 3
    options.ba_refine_principal_point = s.refine_principal_point
    if relaxed:
        options.mapper.abs_pose_min_num_inliers = RELAXED_ABS_POSE_MIN_INLIERS
        options.mapper.abs_pose_min_inlier_ratio = RELAXED_ABS_POSE_MIN_INLIER_RATIO
        options.mapper.init_min_num_inliers = RELAXED_INIT_MIN_INLIERS
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    return list(pycolmap.incremental_mapping(db, image_dir, out, options).values())


def _global(db: Path, image_dir: Path, out: Path, s: Settings) -> list[pycolmap.Reconstruction]:
    options = pycolmap.GlobalPipelineOptions()
    options.random_seed = s.seed
    options.mapper.random_seed = s.seed
    options.mapper.bundle_adjustment.refine_principal_point = s.refine_principal_point
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    return list(pycolmap.global_mapping(db, image_dir, out, options).values())


def _largest(models: list[pycolmap.Reconstruction]) -> pycolmap.Reconstruction | None:
    """COLMAP may return several models, and model 0 is not always the biggest: take the most registered."""
    return max(models, key=lambda m: (m.num_reg_images(), m.num_points3D()), default=None)


def _sfm(ctx, records: list[dict], image_dir: Path) -> tuple[pycolmap.Reconstruction, dict]:
    s: Settings = ctx.settings
    report = ctx.report
    db = ctx.scratch / "database.db"
    names = [f"{r['name']}.png" for r in records]
    seconds: dict[str, float] = {}
    info: dict = {}

    single = {"yes": True, "no": False}.get(s.shared_camera) if s.shared_camera != "auto" else _one_camera(records, ctx.scene)
    info["shared_camera"] = single
    started = time.perf_counter()
    device = "GPU" if _pycolmap_device(s.use_gpu) == pycolmap.Device.cuda else "CPU"
    report.info(f"extracting SIFT features from {len(names)} images ({device}, {'one shared camera' if single else 'one camera per image'}, {s.camera_model})")
    _extract(db, image_dir, names, s, single, SIFT_PEAK_THRESHOLD)
    median = _median_features(db)
    if median < s.min_features:
        report.info(f"only {median:.0f} features per image (median); extracting again with a lower detection threshold")
        _extract(db, image_dir, names, s, single, SIFT_PEAK_THRESHOLD / LOW_FEATURE_PEAK_DIVISOR)
        median = _median_features(db)
    info["median_features"] = median
    seconds["extract"] = time.perf_counter() - started

    from_video = ctx.scene.is_file() and ctx.scene.suffix.lower() in VIDEO_SUFFIXES
    mode = s.matching
    if mode == "auto":
        mode = "sequential" if from_video or len(names) > s.exhaustive_max_images else "exhaustive"
    seconds["match"], seconds["map"] = 0.0, 0.0
    while True:
        matching = _match_and_summarise(db, mode, s, len(names), report, seconds)
        started = time.perf_counter()
        report.info(f"{s.mapper} mapping")
        mapper = _global if s.mapper == "global" else _incremental
        models = mapper(db, image_dir, ctx.scratch / "models", s)
        best = _largest(models)
        seconds["map"] += time.perf_counter() - started
        complete = best is not None and best.num_reg_images() == len(names)
        # Photos that are not an ordered sequence lose pairs under sequential matching: when auto chose it for a
        # photo set and it leaves images out, match the remaining pairs too (matched pairs are not redone) and map again.
        if complete or mode != "sequential" or s.matching != "auto" or from_video:
            break
        report.info(f"{best.num_reg_images() if best else 0}/{len(names)} registered after sequential matching; "
                    "matching all remaining pairs")
        mode = "exhaustive after sequential"
    info.update(matching, matching=mode, models=len(models))
    if s.mapper == "incremental" and not complete:
        started = time.perf_counter()
        before = best.num_reg_images() if best else 0
        report.info(f"{before}/{len(names)} registered; mapping again with looser registration thresholds")
        relaxed = _largest(_incremental(db, image_dir, ctx.scratch / "models_relaxed", s, relaxed=True))
        if relaxed is not None and relaxed.num_reg_images() > before:
            strict = {im.name for im in best.images.values() if im.has_pose} if best else set()
            info["relaxed_only"] = sorted(Path(im.name).stem for im in relaxed.images.values()
                                          if im.has_pose and im.name not in strict)
            best = relaxed
            report.warn(f"{len(info['relaxed_only'])} image(s) registered only with looser thresholds, so their poses "
                        f"are less certain: {_names(info['relaxed_only'])}")
        seconds["map"] += time.perf_counter() - started
    info["seconds"] = seconds
    if len(models) > 1:
        sizes = sorted((m.num_reg_images() for m in models), reverse=True)
        report.warn(f"COLMAP made {len(models)} separate models ({', '.join(map(str, sizes))} images); using the largest")
    if best is None:
        raise UserError(f"SfM formed no model from {len(names)} images ({matching['pairs_verified']} verified pairs); "
                        "the photos need more overlap and texture, or give poses with poses.source/poses.path")
    return best, info


# ---- writing ----------------------------------------------------------------------------------------------

def _check_registered(reconstruction: pycolmap.Reconstruction, records: list[dict], share: float, how: str) -> list[str]:
    posed = {Path(im.name).stem for im in reconstruction.images.values() if im.has_pose}
    left_out = [r["name"] for r in records if r["name"] not in posed]
    if len(posed) < share * len(records):
        raise UserError(f"{how} posed only {len(posed)}/{len(records)} images (below poses.min_registered_share="
                        f"{share:g}); left out: {_names(left_out)}. Take more overlapping photos or lower the share")
    return left_out


def _camera_dict(camera: pycolmap.Camera) -> dict:
    return {"model": camera.model_name, "width": camera.width, "height": camera.height,
            "params": [float(v) for v in camera.params], "param_names": camera.params_info.split(", ")}


def _pinhole(camera: pycolmap.Camera) -> dict:
    return {"fl_x": float(camera.focal_length_x), "fl_y": float(camera.focal_length_y),
            "cx": float(camera.principal_point_x), "cy": float(camera.principal_point_y),
            "w": camera.width, "h": camera.height}


def _undistort_mask(mask: np.ndarray, camera: pycolmap.Camera) -> np.ndarray:
    """The same warp `undistort_images` applies to the photo, so mask and image stay aligned."""
    bitmap, _ = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), pycolmap.Bitmap.from_array(mask), camera)
    return np.asarray(bitmap.to_array()).reshape(bitmap.height, bitmap.width)


def _write_outputs(ctx, distorted: pycolmap.Reconstruction, records: list[dict], source: str,
                   source_path: Path | None, bounds: dict) -> dict:
    ingest = ctx.upstream["ingest"]
    model_dir, undistorted_dir = ctx.scratch / "distorted", ctx.scratch / "undistorted"
    for folder in (model_dir, undistorted_dir):
        shutil.rmtree(folder, ignore_errors=True)
    model_dir.mkdir(parents=True)
    distorted.write_binary(model_dir)
    posed = {Path(im.name).stem: im for im in distorted.images.values() if im.has_pose}
    ctx.report.info(f"undistorting {len(posed)} images to pinhole")
    pycolmap.undistort_images(undistorted_dir, model_dir, ingest / "images", output_type="COLMAP")
    shutil.move(undistorted_dir / "images", ctx.work / "images")
    undistorted = pycolmap.Reconstruction(undistorted_dir / "sparse")
    (ctx.work / "sparse").mkdir()
    undistorted.write_binary(ctx.work / "sparse")

    by_name = {Path(im.name).stem: im for im in undistorted.images.values()}
    frames, frame_index, cameras = [], {}, []
    for record in records:
        image = by_name.get(record["name"])
        if image is None or record["name"] not in posed:
            continue
        pose = image.cam_from_world()
        frame = {"name": record["name"], "file_path": f"images/{record['name']}.png",
                 "transform_matrix": opengl_c2w_from_colmap_w2c(pose.rotation.matrix(), pose.translation).tolist()}
        if record.get("mask"):
            mask = np.asarray(Image.open(ingest / record["mask"]).convert("L"))
            (ctx.work / "masks").mkdir(exist_ok=True)
            write_png(ctx.work / "masks" / f"{record['name']}.png",
                      _undistort_mask(mask, distorted.cameras[posed[record["name"]].camera_id]))
            frame["mask_path"] = f"masks/{record['name']}.png"
        if record["name"] in bounds:
            frame["near"], frame["far"] = bounds[record["name"]]
        frame_index[image.image_id] = len(frames)
        frames.append(frame)
        cameras.append((undistorted.cameras[image.camera_id], distorted.cameras[posed[record["name"]].camera_id]))

    shared = _pinhole(cameras[0][0])
    per_frame = any(_pinhole(c) != shared for c, _ in cameras)
    originals = [_camera_dict(o) for _, o in cameras]
    for frame, (camera, _), original in zip(frames, cameras, originals):
        if per_frame:
            frame.update(_pinhole(camera))
        if originals.count(original) != len(originals):
            frame["original_camera"] = original
    write_json(ctx.work / "transforms.json", {
        "camera_model": "PINHOLE", **shared, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "original_camera": originals[0], "source": source,
        "source_path": str(source_path) if source_path else None, "frames": frames})
    _write_points(ctx.work / "points.npz", undistorted, frame_index)
    return {"frames": len(frames), "width": shared["w"], "height": shared["h"]}


def _write_points(path: Path, reconstruction: pycolmap.Reconstruction, frame_index: dict[int, int]) -> None:
    xyz, rgb, error, track_length, obs_frame, obs_point = [], [], [], [], [], []
    for point in reconstruction.points3D.values():
        elements = [e for e in point.track.elements if e.image_id in frame_index]
        if not elements:
            continue
        for element in elements:
            obs_frame.append(frame_index[element.image_id])
            obs_point.append(len(xyz))
        xyz.append(point.xyz)
        rgb.append(point.color)
        error.append(point.error)
        track_length.append(len(elements))
    np.savez(path, xyz=np.asarray(xyz, dtype=np.float64).reshape(-1, 3), rgb=np.asarray(rgb, dtype=np.uint8).reshape(-1, 3),
             error=np.asarray(error, dtype=np.float64), track_length=np.asarray(track_length, dtype=np.int32),
             obs_frame=np.asarray(obs_frame, dtype=np.int32), obs_point=np.asarray(obs_point, dtype=np.int32))


# ---- the stage --------------------------------------------------------------------------------------------

def _find_import(ctx, records: list[dict]) -> tuple[str, poses_import.Imported] | None:
    s: Settings = ctx.settings
    if s.source == "sfm":
        return None
    if s.path:
        path = Path(s.path).expanduser()
        if not path.is_absolute() and not path.exists():
            path = poses_import.photo_folder(ctx.scene) / path
        if not path.exists():
            raise UserError(f"poses.path {s.path} does not exist; give a COLMAP model folder, a transforms*.json or a poses_bounds.npy")
        kind = s.source if s.source != "auto" else poses_import.kind_of(path)
        return kind, poses_import.load(kind, path, records, ctx.scene)
    found = poses_import.candidates(ctx.scene)
    kinds = [s.source] if s.source != "auto" else list(poses_import.KINDS)
    for kind in kinds:
        if found[kind]:
            return kind, poses_import.choose(kind, found[kind], records, ctx.scene)
    if s.source != "auto":
        raise UserError(f"poses.source={s.source} but no such pose file is beside the photos in "
                        f"{poses_import.photo_folder(ctx.scene)}; set poses.path to it or use poses.source=auto")
    return None


def run(ctx) -> dict:
    s: Settings = ctx.settings
    ingest = ctx.upstream["ingest"]
    records = read_json(ingest / "images.json")["images"]
    started = time.perf_counter()
    with _colmap_logging(s.colmap_log):
        pycolmap.set_random_seed(s.seed)
        found = _find_import(ctx, records)
        if found is None:
            reconstruction, info = _sfm(ctx, records, ingest / "images")
            source, source_path, bounds = "sfm", None, {}
            left_out = _check_registered(reconstruction, records, s.min_registered_share, "SfM")
        else:
            source, imported = found
            reconstruction, info = imported.reconstruction, {"seconds": {}}
            source_path, bounds = imported.path, imported.bounds
            ctx.report.info(f"importing {source} poses from {imported.path}")
            left_out = _check_registered(reconstruction, records, s.min_registered_share, f"{imported.path}")
        step = time.perf_counter()
        written = _write_outputs(ctx, reconstruction, records, source, source_path, bounds)
        info["seconds"]["undistort"] = time.perf_counter() - step

    registered = written["frames"]
    points = reconstruction.num_points3D()
    error = reconstruction.compute_mean_reprojection_error() if points else None
    track = reconstruction.compute_mean_track_length() if points else None
    if left_out:
        ctx.report.warn(f"{len(left_out)} image(s) have no pose and are left out: {_names(left_out)}")
    how = "registered" if source == "sfm" else f"imported ({source}) for"
    line = f"{how} {registered}/{len(records)} images at {written['width']}x{written['height']}"
    if points:
        line += f", {points} points, mean reprojection error {error:.2f} px, mean track length {track:.1f}"
    if source == "sfm":
        line += f" ({info['matching']} matching: {info['pairs_verified']}/{info['pairs_matched']} pairs verified)"
    info["seconds"] = {k: round(v, 2) for k, v in info["seconds"].items()}
    return {"line": line, "source": source, "registered": registered, "images": len(records), "left_out": left_out,
            "points": points, "mean_reprojection_error": error, "mean_track_length": track,
            "seconds_total": round(time.perf_counter() - started, 2), **info}
