"""Poses: camera poses and pinhole intrinsics for every ingested image, by COLMAP SfM through pycolmap
(pipeline/sfm/reconstruct.py) or imported from pose files the user already has (pipeline/sfm/pose_import.py).

Writes poses/transforms.json (nerfstudio layout, OpenGL camera-to-world in the frame the poses came
in), poses/images/ (undistorted pinhole PNGs, the ingested names), poses/masks/ (when ingest kept
masks), poses/sparse/ (the undistorted COLMAP model, binary) and poses/points.npz (sparse points and
their observations). SfM and imports both end as a distorted COLMAP model at the ingested image size,
and one path (pipeline/sfm/outputs.py) undistorts and writes it, so later stages never know where the
poses came from.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import pycolmap

from pipeline.config import require
from pipeline.io import read_json
from pipeline.photos import is_video, photo_folder
from pipeline.sfm import pose_import
from pipeline.sfm.outputs import write_poses
from pipeline.report import short_list
from pipeline.sfm.reconstruct import SfmOptions, colmap_logging, reconstruct
from plenoxels.errors import UserError

NAME = "poses"
DEPENDS: tuple[str, ...] = ("ingest",)
VERSION = 1


@dataclass
class Settings(SfmOptions):
    """SfM's options (pipeline.sfm.reconstruct.SfmOptions), and where poses come from."""
    source: Literal["auto", "sfm", "colmap", "transforms", "llff", "idr"] = "auto"
    """Where poses come from: auto imports pose files found beside the photos (a COLMAP model, a transforms.json,
    LLFF's poses_bounds.npy, IDR/NeuS's cameras_sphere.npz), else runs SfM."""
    path: str = ""
    """An explicit pose file or COLMAP model folder to import (kind taken from source, or guessed)."""
    min_registered_share: float = 0.5
    """Fail when fewer than this share of the images get a pose, in (0, 1]."""
    colmap_log: bool = False
    """Show COLMAP's own log lines."""

    def check(self) -> None:
        require(self.max_features >= 64, "poses.max_features must be at least 64")
        require(self.feature_max_side == 0 or self.feature_max_side >= 64,
                "poses.feature_max_side must be 0 (the ingested size) or at least 64")
        require(self.min_features >= 0, "poses.min_features must be 0 or more")
        require(self.sensor_width_mm >= 0, "poses.sensor_width_mm must be 0 (unknown) or the sensor width in mm")
        require(self.exhaustive_max_images >= 2, "poses.exhaustive_max_images must be at least 2")
        require(self.sequential_overlap >= 1, "poses.sequential_overlap must be at least 1")
        require(self.threads >= 0, "poses.threads must be 0 (all cores) or a number of threads")
        require(0.0 < self.min_registered_share <= 1.0, "poses.min_registered_share must be in (0, 1]")
        require(not (self.path and self.source == "sfm"), "poses.path names pose files to import; it cannot be used with poses.source=sfm")


def fingerprint(scene: Path) -> list:
    """Pose files beside the photos decide what this stage does, so they are part of its key."""
    return [[str(p), p.stat().st_size, p.stat().st_mtime_ns] for p in pose_import.pose_files(scene)]


def _check_registered(reconstruction: pycolmap.Reconstruction, records: list[dict], share: float, how: str) -> list[str]:
    posed = {Path(im.name).stem for im in reconstruction.images.values() if im.has_pose}
    left_out = [r["name"] for r in records if r["name"] not in posed]
    if len(posed) < share * len(records):
        raise UserError(f"{how} posed only {len(posed)}/{len(records)} images (below poses.min_registered_share="
                        f"{share:g}); left out: {short_list(left_out)}. Take more overlapping photos or lower the share")
    return left_out


def run(ctx) -> dict:
    s: Settings = ctx.settings
    ingest = ctx.upstream["ingest"]
    records = read_json(ingest / "images.json")["images"]
    started = time.perf_counter()
    with colmap_logging(s.colmap_log):
        pycolmap.set_random_seed(s.seed)
        found = pose_import.find(s.source, s.path, records, ctx.scene)
        if found is None:
            reconstruction, info = reconstruct(records, ingest / "images", photo_folder(ctx.scene), is_video(ctx.scene),
                                               ctx.scratch, s, ctx.report)
            source, source_path, bounds = "sfm", None, {}
            left_out = _check_registered(reconstruction, records, s.min_registered_share, "SfM")
        else:
            source, imported = found
            reconstruction, info = imported.reconstruction, {"seconds": {}}
            source_path, bounds = imported.path, imported.bounds
            ctx.report.info(f"importing {source} poses from {imported.path}")
            left_out = _check_registered(reconstruction, records, s.min_registered_share, f"{imported.path}")
        step = time.perf_counter()
        written = write_poses(ctx.work, ctx.scratch, ingest, reconstruction, records, source, source_path, bounds,
                              ctx.report)
        info["seconds"]["undistort"] = time.perf_counter() - step

    registered = written["frames"]
    points = reconstruction.num_points3D()
    error = reconstruction.compute_mean_reprojection_error() if points else None
    track = reconstruction.compute_mean_track_length() if points else None
    if left_out:
        ctx.report.warn(f"{len(left_out)} image(s) have no pose and are left out: {short_list(left_out)}")
    how = "registered" if source == "sfm" else f"imported ({source}) for"
    line = f"{how} {registered}/{len(records)} images at {written['width']}x{written['height']}"
    if points:
        line += f", {points} points, mean reprojection error {error:.2f} px, mean track length {track:.1f}"
    elif written.get("triangulated"):
        points = written["triangulated"]["points"]
        line += f", {points} points triangulated from {written['triangulated']['pairs']} pairs of nearby photos"
    if source == "sfm":
        line += f" ({info['matching']} matching: {info['pairs_verified']}/{info['pairs_matched']} pairs verified)"
        if info.get("masked_images"):
            line += f", features only inside the masks of {info['masked_images']} images"
    if info.get("attempt_why"):
        line += f"; as set, {info['attempt_why']}, so these poses come from the attempt with {info['attempt']}"
    if info.get("mapper_fallback"):
        line += f"; {info['mapper_fallback']}, so the incremental mapper made these poses"
    info["seconds"] = {k: round(v, 2) for k, v in info["seconds"].items()}
    return {"line": line, "source": source, "registered": registered, "images": len(records), "left_out": left_out,
            "points": points, "mean_reprojection_error": error, "mean_track_length": track,
            "seconds_total": round(time.perf_counter() - started, 2), **info}
