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

from plenoxels.cameras import opengl_c2w_from_colmap_w2c
from pipeline.config import require
from plenoxels.errors import UserError
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
# A registered image is tied to the model when it observes at least this many points that images already tied to it
# observe too (the loosest PnP support we accept above). An image or group that is not tied has a pose nothing relates
# to the rest: its own few points fit it, so the reprojection error stays low while it can sit anywhere.
MIN_TIED_POINTS = 15
# A verified match lies within COLMAP's RANSAC error (4 px) of its epipolar line; a model contradicts it when its
# relative pose puts the match farther than that. Measured shares of an image's verified matches contradicted: correct
# models up to 2.2% (synthetic orbit) and 13% (fox at 480 px, some verified matches being wrong ones); the global
# mapper's wrong poses 23-58% (synthetic) and 20-63% (fox). Replacing a global model costs only a mapping run, so a
# lower share triggers it than the warning about a final model, which must not cry wolf.
EPIPOLAR_MAX_ERROR_PX = 4.0
GLOBAL_MAX_CONTRADICTED_SHARE = 0.1
MAX_CONTRADICTED_SHARE = 0.2
EXIF_MODEL_TAG = 0x0110
EXIF_IFD = 0x8769
EXIF_FOCAL_35MM = 0xA405                # FocalLengthIn35mmFilm, mm
EXIF_FOCAL = 0x920A                     # FocalLength, mm
EXIF_FOCAL_PLANE_X_RESOLUTION = 0xA20E  # sensor pixels per unit, in units of the tag below
EXIF_FOCAL_PLANE_UNIT = 0xA210
MM_PER_FOCAL_PLANE_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}
# A 35 mm equivalent focal length keeps the diagonal field of view of the 36 x 24 mm frame (CIPA DC-008), so it
# holds for any aspect ratio, not only 3:2.
FULL_FRAME_DIAGONAL_MM = float(np.hypot(36.0, 24.0))
NAMES_SHOWN = 8


@dataclass
class Settings:
    source: Literal["auto", "sfm", "colmap", "transforms", "llff"] = "auto"  # auto: import pose files found beside the photos, else SfM
    path: str = ""                      # an explicit pose file or COLMAP model folder (kind taken from source, or guessed)
    camera_model: Literal["SIMPLE_RADIAL", "OPENCV", "RADIAL", "SIMPLE_PINHOLE", "PINHOLE"] = "SIMPLE_RADIAL"
    exif_focal: bool = True             # start from the focal length in the photos' EXIF, when they carry one
    sensor_width_mm: float = 0.0        # sensor width, for EXIF with a focal length in mm but no 35 mm equivalent
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
        require(self.sensor_width_mm >= 0, "poses.sensor_width_mm must be 0 (unknown) or the sensor width in mm")
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


def _exif_focal(photo: Path, sensor_width_mm: float) -> tuple[float, str] | None:
    """Focal length in pixels of the photo as stored, from its EXIF, and which tags gave it; None without them."""
    try:
        with Image.open(photo) as im:
            exif = im.getexif().get_ifd(EXIF_IFD)
            width, height = im.size
    except (OSError, ValueError):
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


def _set_focal_priors(db: Path, records: list[dict], scene: Path, sensor_width_mm: float) -> dict | None:
    """Starts each camera in the database from the EXIF focal length of its photos (the median where photos share one,
    scaled to the ingested size), marked as a prior so verification estimates essential matrices. Without EXIF,
    COLMAP's guess of 1.2 x the longest side stays."""
    by_name = {f"{r['name']}.png": r for r in records}
    found = []
    with pycolmap.Database.open(db) as database:
        images_of: dict[int, list] = {}
        for image in database.read_all_images():
            images_of.setdefault(image.camera_id, []).append(by_name[image.name])
        for camera_id, camera_records in images_of.items():
            priors = []
            for record in camera_records:
                exif = _exif_focal(poses_import.photo_folder(scene) / record["source"], sensor_width_mm)
                if exif is not None:
                    priors.append((exif[0] * record["scale"], exif[1]))
            if not priors:
                continue
            camera = database.read_camera(camera_id)
            camera.focal_length = statistics.median(f for f, _ in priors)
            camera.has_prior_focal_length = True
            database.update_camera(camera)
            found.append((database.read_camera(camera_id).focal_length, priors[0][1], len(priors)))
    if not found:
        return None
    return {"focal_px": round(statistics.median(f for f, _, _ in found), 2), "from": found[0][1],
            "images": sum(n for _, _, n in found), "cameras": len(found)}


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


def _detached(model: pycolmap.Reconstruction) -> list[str]:
    """Stems of the registered images not tied to the model's main block, grown from the image with the most points
    by adding every image that observes MIN_TIED_POINTS points the block observes."""
    registered = [im for im in model.images.values() if im.has_pose]
    if not registered:
        return []
    column = {im.image_id: n for n, im in enumerate(registered)}
    observer, point = [], []
    for n, point3d in enumerate(model.points3D.values()):
        for element in point3d.track.elements:
            if element.image_id in column:
                observer.append(column[element.image_id])
                point.append(n)
    observer, point = np.asarray(observer, dtype=np.int64), np.asarray(point, dtype=np.int64)
    tied = np.zeros(len(registered), dtype=bool)
    tied[np.argmax([im.num_points3D for im in registered])] = True
    while True:
        seen_by_block = np.bincount(point, weights=tied[observer], minlength=model.num_points3D()) > 0
        support = np.bincount(observer, weights=seen_by_block[point], minlength=len(registered))
        joining = ~tied & (support >= MIN_TIED_POINTS)
        if not joining.any():
            return sorted(Path(im.name).stem for im, ok in zip(registered, tied) if not ok)
        tied |= joining


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _contradicted(db: Path, model: pycolmap.Reconstruction, above: float) -> dict[str, float]:
    """Registered images whose poses in the model contradict more than `above` of their verified matches, and the share."""
    posed = {im.name: im for im in model.images.values() if im.has_pose}
    with pycolmap.Database.open(db) as database:
        names = {image.image_id: image.name for image in database.read_all_images()}
        pair_ids, geometries = database.read_two_view_geometries()
        keypoints = {i: database.read_keypoints(i)[:, :2].astype(np.float64) for i in names if names[i] in posed}
    matches, contradicted = Counter(), Counter()
    for pair_id, geometry in zip(pair_ids, geometries):
        a, b = pycolmap.pair_id_to_image_pair(pair_id)
        inliers = geometry.inlier_matches
        if len(inliers) < MIN_VERIFIED_INLIERS or names[a] not in posed or names[b] not in posed:
            continue
        image_a, image_b = posed[names[a]], posed[names[b]]
        camera_a, camera_b = model.cameras[image_a.camera_id], model.cameras[image_b.camera_id]
        b_from_a = image_b.cam_from_world() * image_a.cam_from_world().inverse()
        baseline = np.linalg.norm(b_from_a.translation)
        if baseline == 0:  # two views from one centre have no epipolar geometry to contradict
            continue
        essential = _skew(b_from_a.translation / baseline) @ b_from_a.rotation.matrix()
        rays_a = np.c_[camera_a.cam_from_img(keypoints[a][inliers[:, 0]]), np.ones(len(inliers))]
        rays_b = np.c_[camera_b.cam_from_img(keypoints[b][inliers[:, 1]]), np.ones(len(inliers))]
        line_b, line_a = rays_a @ essential.T, rays_b @ essential
        # Sampson distance on the normalised image plane, in pixels of image a
        sampson = np.abs((rays_b * line_b).sum(1)) / np.sqrt(line_b[:, 0] ** 2 + line_b[:, 1] ** 2 + line_a[:, 0] ** 2 + line_a[:, 1] ** 2)
        wrong = int((sampson * camera_a.mean_focal_length() > EPIPOLAR_MAX_ERROR_PX).sum())
        for name in (names[a], names[b]):
            matches[name] += len(inliers)
            contradicted[name] += wrong
    shares = {Path(name).stem: contradicted[name] / matches[name] for name in matches}
    return {stem: round(share, 3) for stem, share in sorted(shares.items()) if share > above}


def _drop(model: pycolmap.Reconstruction, stems: list[str]) -> None:
    for image in model.images.values():
        if image.has_pose and Path(image.name).stem in stems:
            model.deregister_frame(image.frame_id)


def _largest(models: list[pycolmap.Reconstruction]) -> pycolmap.Reconstruction | None:
    """COLMAP may return several models, and model 0 is not always the biggest: take the most registered."""
    return max(models, key=lambda m: (m.num_reg_images(), m.num_points3D()), default=None)


def _map(db: Path, image_dir: Path, scratch: Path, s: Settings, report) -> tuple[list, pycolmap.Reconstruction | None, str]:
    """Maps with the chosen mapper; returns the models, the largest, and why the global mapper was replaced, if it was.

    Global mapping (rotation averaging, then positions) has no loop to correct a bad relative pose where the view graph
    is a chain, as sequential matching leaves the start of an orbit. On a 24-view synthetic orbit it turned the first
    two views about 65 and 35 degrees (against the other 22, which were right); depending on small run-to-run
    differences in the matches, the two came back either tied to nothing (their 10 points seen only by each other) or
    tied by 25 points while contradicting a quarter of their verified matches. Both times 24/24 registered at 0.15 px
    reprojection error, centres off by 128% of the spread. On fox at 480 px it went wrong even with exhaustive matching
    (rotations off by 90 degrees; 14 images detached, 30 contradicting over 10% of their matches). The incremental
    mapper, which registers each image against points it already has, posed both correctly."""
    if s.mapper == "global":
        report.info("global mapping")
        models = _global(db, image_dir, scratch / "models", s)
        best = _largest(models)
        if best is None:
            fallback = "global mapping formed no model"
        else:
            misplaced = sorted(set(_detached(best)) | set(_contradicted(db, best, GLOBAL_MAX_CONTRADICTED_SHARE)))
            if not misplaced:
                return models, best, ""
            fallback = (f"global mapping gave {len(misplaced)} image(s) poses that contradict their matches or tie them "
                        f"to nothing ({_names(misplaced)})")
        report.warn(f"{fallback}; mapping again with the incremental mapper")
    else:
        fallback = ""
    report.info("incremental mapping")
    models = _incremental(db, image_dir, scratch / "models", s)
    return models, _largest(models), fallback


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
    info["focal_prior"] = _set_focal_priors(db, records, ctx.scene, s.sensor_width_mm) if s.exif_focal else None
    if info["focal_prior"]:
        prior = info["focal_prior"]
        report.info(f"initial focal length {prior['focal_px']:.1f} px from {prior['from']} ({prior['images']} photos)")
    seconds["extract"] = time.perf_counter() - started

    from_video = ctx.scene.is_file() and ctx.scene.suffix.lower() in VIDEO_SUFFIXES
    mode = s.matching
    if mode == "auto":
        mode = "sequential" if from_video or len(names) > s.exhaustive_max_images else "exhaustive"
    seconds["match"], seconds["map"] = 0.0, 0.0
    while True:
        matching = _match_and_summarise(db, mode, s, len(names), report, seconds)
        started = time.perf_counter()
        models, best, fallback = _map(db, image_dir, ctx.scratch, s, report)
        seconds["map"] += time.perf_counter() - started
        complete = best is not None and best.num_reg_images() == len(names) and not _detached(best)
        # Photos that are not an ordered sequence lose pairs under sequential matching: when auto chose it for a
        # photo set and it leaves images out, match the remaining pairs too (matched pairs are not redone) and map again.
        if complete or mode != "sequential" or s.matching != "auto" or from_video:
            break
        report.info(f"{best.num_reg_images() if best else 0}/{len(names)} registered after sequential matching; "
                    "matching all remaining pairs")
        mode = "exhaustive after sequential"
    info["mapper"] = "incremental" if fallback else s.mapper
    if fallback:
        info["mapper_fallback"] = fallback
    info.update(matching, matching=mode, models=len(models))
    if (s.mapper == "incremental" or fallback) and not complete:
        started = time.perf_counter()
        before = best.num_reg_images() - len(_detached(best)) if best else 0
        report.info(f"{before}/{len(names)} registered; mapping again with looser registration thresholds")
        relaxed = _largest(_incremental(db, image_dir, ctx.scratch / "models_relaxed", s, relaxed=True))
        if relaxed is not None and relaxed.num_reg_images() - len(_detached(relaxed)) > before:
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
    detached = _detached(best)
    if detached:
        _drop(best, detached)
        info["detached"] = detached
        report.warn(f"{len(detached)} registered image(s) share too few points with the rest of the model to place "
                    f"them, so they are left out: {_names(detached)}")
    info["contradicted"] = _contradicted(db, best, MAX_CONTRADICTED_SHARE)
    if info["contradicted"]:
        report.warn(f"the poses of {len(info['contradicted'])} image(s) contradict over {MAX_CONTRADICTED_SHARE:.0%} of "
                    f"their verified matches, so they may be wrong: {_names(list(info['contradicted']))}")
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
    if info.get("mapper_fallback"):
        line += f"; {info['mapper_fallback']}, so the incremental mapper made these poses"
    info["seconds"] = {k: round(v, 2) for k, v in info["seconds"].items()}
    return {"line": line, "source": source, "registered": registered, "images": len(records), "left_out": left_out,
            "points": points, "mean_reprojection_error": error, "mean_track_length": track,
            "seconds_total": round(time.perf_counter() - started, 2), **info}
