"""COLMAP's mappers through pycolmap: incremental (of some images alone where asked), global, and the choice between
them that a global model failing the checks leaves (`map_images`)."""
from __future__ import annotations

import shutil
from pathlib import Path

import pycolmap

from stages.common.text import short_list
from stages.sfm.model_checks import GLOBAL_MAX_CONTRADICTED_SHARE, contradicted_images, detached_images
from stages.sfm.options import SfmOptions

# Looser registration thresholds for a second mapping pass when the first leaves images out.
RELAXED_ABS_POSE_MIN_INLIERS = 15
RELAXED_ABS_POSE_MIN_INLIER_RATIO = 0.15
RELAXED_INIT_MIN_INLIERS = 50


def colmap_threads(s: SfmOptions) -> int:
    return s.threads or -1


def incremental_mapping(db: Path, image_dir: Path, out: Path, s: SfmOptions, relaxed: bool = False,
                        fixed_cameras: bool = False, image_names: list[str] | None = None, priors: bool = False
                        ) -> list[pycolmap.Reconstruction]:
    """COLMAP's incremental mapper, of `image_names` alone where given; `fixed_cameras`: the cameras' focal lengths and
    distortion are known (a 360 frame's views), and bundle adjustment keeps them; `priors`: the database holds
    positions (gps.write_priors) that bundle adjustment keeps the cameras near, a robust loss letting a bad fix go."""
    options = pycolmap.IncrementalPipelineOptions()
    options.image_names = image_names or []
    options.num_threads = colmap_threads(s)
    options.random_seed = s.seed
    options.mapper.random_seed = s.seed
    options.triangulation.random_seed = s.seed
    options.min_model_size = 3
    options.ba_refine_principal_point = s.refine_principal_point
    if fixed_cameras:
        options.ba_refine_focal_length = options.ba_refine_extra_params = False
    options.use_prior_position = options.use_robust_loss_on_prior_position = priors
    if relaxed:
        options.mapper.abs_pose_min_num_inliers = RELAXED_ABS_POSE_MIN_INLIERS
        options.mapper.abs_pose_min_inlier_ratio = RELAXED_ABS_POSE_MIN_INLIER_RATIO
        options.mapper.init_min_num_inliers = RELAXED_INIT_MIN_INLIERS
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    return list(pycolmap.incremental_mapping(db, image_dir, out, options).values())


def global_mapping(db: Path, image_dir: Path, out: Path, s: SfmOptions,
                   fixed_cameras: bool = False) -> list[pycolmap.Reconstruction]:
    options = pycolmap.GlobalPipelineOptions()
    options.num_threads = colmap_threads(s)
    options.random_seed = s.seed
    options.mapper.random_seed = s.seed
    options.mapper.bundle_adjustment.refine_principal_point = s.refine_principal_point
    if fixed_cameras:
        options.mapper.bundle_adjustment.refine_focal_length = False
        options.mapper.bundle_adjustment.refine_extra_params = False
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    return list(pycolmap.global_mapping(db, image_dir, out, options).values())


def largest_model(models: list[pycolmap.Reconstruction]) -> pycolmap.Reconstruction | None:
    """COLMAP may return several models, and model 0 is not always the biggest: take the most registered."""
    return max(models, key=lambda m: (m.num_reg_images(), m.num_points3D()), default=None)


def map_images(db: Path, image_dir: Path, scratch: Path, s: SfmOptions, report,
               fixed_cameras: bool = False, priors: bool = False) -> tuple[list, pycolmap.Reconstruction | None, str]:
    """Maps with the chosen mapper; returns the models, the largest, and why the global mapper was replaced, if it was.

    Global mapping (rotation averaging, then positions) has no loop to correct a bad relative pose where the view graph
    is a chain, as sequential matching leaves the start of an orbit, and its wrong poses can still reproject their own
    points to a fraction of a pixel: such images come back tied to nothing, or contradicting their verified matches
    (bench/README.md, "Poses"). The incremental mapper, which registers each image against points it already has,
    poses those captures correctly, so a global model that fails the checks is mapped again with it. `priors`: the
    database holds the photos' positions, which the incremental mapper keeps the cameras near (the global one here
    does not read them)."""
    if s.mapper == "global":
        report.info("global mapping")
        models = global_mapping(db, image_dir, scratch / "models", s, fixed_cameras)
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
    models = incremental_mapping(db, image_dir, scratch / "models", s, fixed_cameras=fixed_cameras, priors=priors)
    return models, largest_model(models), fallback
