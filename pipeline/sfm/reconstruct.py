"""COLMAP structure from motion through pycolmap: SIFT extraction (with EXIF focal priors), exhaustive or sequential
matching, incremental or global mapping, and the fallbacks that keep a wrong or partial model from being used:
a global model that contradicts its matches is mapped again incrementally, sequential matching that leaves photos
out is completed by exhaustive matching, and images left out are retried with looser registration thresholds."""
from __future__ import annotations

import shutil
import statistics
import time
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Literal

import pycolmap

from pipeline.sfm.exif import one_camera, set_focal_priors
from pipeline.sfm.model_checks import (GLOBAL_MAX_CONTRADICTED_SHARE, MAX_CONTRADICTED_SHARE, MIN_VERIFIED_INLIERS,
                                       contradicted_images, detached_images, drop_images)
from plenoxels.errors import UserError

# COLMAP's own detection threshold; lowered by this factor when images yield too few features.
SIFT_PEAK_THRESHOLD = 0.02 / 3
LOW_FEATURE_PEAK_DIVISOR = 3.0
# Looser registration thresholds for a second mapping pass when the first leaves images out.
RELAXED_ABS_POSE_MIN_INLIERS = 15
RELAXED_ABS_POSE_MIN_INLIER_RATIO = 0.15
RELAXED_INIT_MIN_INLIERS = 50
NAMES_SHOWN = 8


@dataclass
class SfmOptions:
    """How to run SfM (the poses stage's settings, less where poses come from)."""
    camera_model: Literal["SIMPLE_RADIAL", "OPENCV", "RADIAL", "SIMPLE_PINHOLE", "PINHOLE"] = "SIMPLE_RADIAL"
    """COLMAP camera model SfM fits (distortion is removed afterwards)."""
    exif_focal: bool = True
    """Start from the focal length in the photos' EXIF, when they carry one."""
    sensor_width_mm: float = 0.0
    """Sensor width in mm, for EXIF with a focal length in mm but no 35 mm equivalent; 0: unknown."""
    shared_camera: Literal["auto", "yes", "no"] = "auto"
    """One camera for all photos; auto: when sizes and EXIF camera models agree."""
    max_features: int = 8192
    """SIFT features per image (at least 64)."""
    feature_max_side: int = 0
    """Extract features on images downscaled to this side in pixels; 0: the ingested size."""
    min_features: int = 1000
    """Median features per image below this: extract again with a lower detection threshold."""
    matching: Literal["auto", "exhaustive", "sequential"] = "auto"
    """Image pairs to match; auto: exhaustive up to exhaustive_max_images photos, else (and for video) sequential."""
    exhaustive_max_images: int = 100
    """Auto matching is exhaustive up to this many images; above, sequential completed by exhaustive when needed."""
    sequential_overlap: int = 10
    """Neighbours each image is matched with in sequential matching."""
    mapper: Literal["incremental", "global"] = "incremental"
    """COLMAP mapper; a global model that contradicts its matches is mapped again incrementally."""
    refine_principal_point: bool = False
    """Let bundle adjustment move the principal point."""
    use_gpu: bool = True
    """Extract and match SIFT on the GPU when pycolmap was built with CUDA."""
    seed: int = 0
    """Random seed for COLMAP's RANSAC and mappers."""


@contextmanager
def colmap_logging(verbose: bool) -> Iterator[None]:
    """COLMAP logs every step through glog; by default only its errors get through."""
    previous = (pycolmap.logging.minloglevel, pycolmap.logging.stderrthreshold)
    if not verbose:
        pycolmap.logging.minloglevel = 2
        pycolmap.logging.stderrthreshold = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel, pycolmap.logging.stderrthreshold = previous


def short_list(names: list[str]) -> str:
    shown = ", ".join(names[:NAMES_SHOWN])
    return shown + (f" and {len(names) - NAMES_SHOWN} more" if len(names) > NAMES_SHOWN else "")


def pycolmap_device(use_gpu: bool) -> pycolmap.Device:
    return pycolmap.Device.cuda if use_gpu and pycolmap.has_cuda else pycolmap.Device.cpu


def extract_features(db: Path, image_dir: Path, names: list[str], s: SfmOptions, single_camera: bool,
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
                              reader_options=reader, extraction_options=options, device=pycolmap_device(s.use_gpu))


def median_features(db: Path) -> float:
    with pycolmap.Database.open(db) as database:
        return statistics.median(database.num_keypoints_for_image(image.image_id) for image in database.read_all_images())


def match_features(db: Path, mode: str, s: SfmOptions) -> None:
    options = pycolmap.FeatureMatchingOptions()
    options.use_gpu = s.use_gpu and pycolmap.has_cuda
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = s.seed
    device = pycolmap_device(s.use_gpu)
    if mode == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = s.sequential_overlap
        pycolmap.match_sequential(db, matching_options=options, pairing_options=pairing,
                                  verification_options=verification, device=device)
    else:
        pycolmap.match_exhaustive(db, matching_options=options, verification_options=verification, device=device)


def matching_summary(db: Path) -> dict:
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


def _match_and_summarise(db: Path, mode: str, s: SfmOptions, n_images: int, report, seconds: dict) -> dict:
    started = time.perf_counter()
    report.info(f"matching features ({mode})")
    match_features(db, "exhaustive" if mode.startswith("exhaustive") else mode, s)
    seconds["match"] += time.perf_counter() - started
    matching = matching_summary(db)
    report.info(f"matching: {matching['pairs_verified']} of {matching['pairs_matched']} image pairs verified, "
                f"{matching['inlier_matches']} inlier matches")
    poorly = matching.pop("poorly_matched")
    if poorly:
        report.warn(f"{len(poorly)} image(s) verified with fewer than 2 others, so they may not register: {short_list(poorly)}")
    if matching["pairs_verified"] < n_images - 1:
        report.warn(f"only {matching['pairs_verified']} image pairs verified for {n_images} images; the photos "
                    "may overlap too little (take more, closer together)")
    return matching


def incremental_mapping(db: Path, image_dir: Path, out: Path, s: SfmOptions, relaxed: bool = False) -> list[pycolmap.Reconstruction]:
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


def global_mapping(db: Path, image_dir: Path, out: Path, s: SfmOptions) -> list[pycolmap.Reconstruction]:
    options = pycolmap.GlobalPipelineOptions()
    options.random_seed = s.seed
    options.mapper.random_seed = s.seed
    options.mapper.bundle_adjustment.refine_principal_point = s.refine_principal_point
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    return list(pycolmap.global_mapping(db, image_dir, out, options).values())


def largest_model(models: list[pycolmap.Reconstruction]) -> pycolmap.Reconstruction | None:
    """COLMAP may return several models, and model 0 is not always the biggest: take the most registered."""
    return max(models, key=lambda m: (m.num_reg_images(), m.num_points3D()), default=None)


def map_images(db: Path, image_dir: Path, scratch: Path, s: SfmOptions, report) -> tuple[list, pycolmap.Reconstruction | None, str]:
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
        models = global_mapping(db, image_dir, scratch / "models", s)
        best = largest_model(models)
        if best is None:
            fallback = "global mapping formed no model"
        else:
            misplaced = sorted(set(detached_images(best)) | set(contradicted_images(db, best, GLOBAL_MAX_CONTRADICTED_SHARE)))
            if not misplaced:
                return models, best, ""
            fallback = (f"global mapping gave {len(misplaced)} image(s) poses that contradict their matches or tie them "
                        f"to nothing ({short_list(misplaced)})")
        report.warn(f"{fallback}; mapping again with the incremental mapper")
    else:
        fallback = ""
    report.info("incremental mapping")
    models = incremental_mapping(db, image_dir, scratch / "models", s)
    return models, largest_model(models), fallback


def reconstruct(records: list[dict], image_dir: Path, photos: Path, from_video: bool, scratch: Path,
                s: SfmOptions, report) -> tuple[pycolmap.Reconstruction, dict]:
    """The largest model COLMAP makes of the ingested images (`records`, PNGs in `image_dir`, original photos in
    `photos` for their EXIF), with detached images dropped, and what happened on the way (counts, fallbacks,
    timings). `scratch` holds the database and the mapper's models."""
    db = scratch / "database.db"
    names = [f"{r['name']}.png" for r in records]
    seconds: dict[str, float] = {}
    info: dict = {}

    single = {"yes": True, "no": False}.get(s.shared_camera) if s.shared_camera != "auto" else one_camera(records, photos)
    info["shared_camera"] = single
    started = time.perf_counter()
    device = "GPU" if pycolmap_device(s.use_gpu) == pycolmap.Device.cuda else "CPU"
    report.info(f"extracting SIFT features from {len(names)} images ({device}, {'one shared camera' if single else 'one camera per image'}, {s.camera_model})")
    extract_features(db, image_dir, names, s, single, SIFT_PEAK_THRESHOLD)
    median = median_features(db)
    if median < s.min_features:
        report.info(f"only {median:.0f} features per image (median); extracting again with a lower detection threshold")
        extract_features(db, image_dir, names, s, single, SIFT_PEAK_THRESHOLD / LOW_FEATURE_PEAK_DIVISOR)
        median = median_features(db)
    info["median_features"] = median
    info["focal_prior"] = set_focal_priors(db, records, photos, s.sensor_width_mm) if s.exif_focal else None
    if info["focal_prior"]:
        prior = info["focal_prior"]
        report.info(f"initial focal length {prior['focal_px']:.1f} px from {prior['from']} ({prior['images']} photos)")
    seconds["extract"] = time.perf_counter() - started

    mode = s.matching
    if mode == "auto":
        mode = "sequential" if from_video or len(names) > s.exhaustive_max_images else "exhaustive"
    seconds["match"], seconds["map"] = 0.0, 0.0
    while True:
        matching = _match_and_summarise(db, mode, s, len(names), report, seconds)
        started = time.perf_counter()
        models, best, fallback = map_images(db, image_dir, scratch, s, report)
        seconds["map"] += time.perf_counter() - started
        complete = best is not None and best.num_reg_images() == len(names) and not detached_images(best)
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
        before = best.num_reg_images() - len(detached_images(best)) if best else 0
        report.info(f"{before}/{len(names)} registered; mapping again with looser registration thresholds")
        relaxed = largest_model(incremental_mapping(db, image_dir, scratch / "models_relaxed", s, relaxed=True))
        if relaxed is not None and relaxed.num_reg_images() - len(detached_images(relaxed)) > before:
            strict = {im.name for im in best.images.values() if im.has_pose} if best else set()
            info["relaxed_only"] = sorted(Path(im.name).stem for im in relaxed.images.values()
                                          if im.has_pose and im.name not in strict)
            best = relaxed
            report.warn(f"{len(info['relaxed_only'])} image(s) registered only with looser thresholds, so their poses "
                        f"are less certain: {short_list(info['relaxed_only'])}")
        seconds["map"] += time.perf_counter() - started
    info["seconds"] = seconds
    if len(models) > 1:
        sizes = sorted((m.num_reg_images() for m in models), reverse=True)
        report.warn(f"COLMAP made {len(models)} separate models ({', '.join(map(str, sizes))} images); using the largest")
    if best is None:
        raise UserError(f"SfM formed no model from {len(names)} images ({matching['pairs_verified']} verified pairs); "
                        "the photos need more overlap and texture, or give poses with poses.source/poses.path")
    unplaced = detached_images(best)
    if unplaced:
        drop_images(best, unplaced)
        info["detached"] = unplaced
        report.warn(f"{len(unplaced)} registered image(s) share too few points with the rest of the model to place "
                    f"them, so they are left out: {short_list(unplaced)}")
    info["contradicted"] = contradicted_images(db, best, MAX_CONTRADICTED_SHARE)
    if info["contradicted"]:
        report.warn(f"the poses of {len(info['contradicted'])} image(s) contradict over {MAX_CONTRADICTED_SHARE:.0%} of "
                    f"their verified matches, so they may be wrong: {short_list(list(info['contradicted']))}")
    return best, info
