"""How to run structure from motion: the options the poses stage's settings extend, free of pycolmap, so a
settings listing and the pipeline's cache keys read them without loading COLMAP. `check` raises a one-line UserError
for a bad value, naming the key as `section.name`."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from plenoxels.core.errors import require


@dataclass
class SfmOptions:
    """How to run SfM (the poses stage's settings, less where poses come from)."""
    camera_model: Literal["SIMPLE_RADIAL", "OPENCV", "RADIAL", "SIMPLE_PINHOLE", "PINHOLE", "OPENCV_FISHEYE",
                          "RADIAL_FISHEYE", "SIMPLE_RADIAL_FISHEYE"] = "SIMPLE_RADIAL"
    """COLMAP camera model SfM fits (distortion is removed afterwards); a fisheye lens (an action camera's wide mode)
    wants OPENCV_FISHEYE or another *_FISHEYE, whose angle from the axis, not its tangent, grows with the radius: a
    model fitted here whose lens bends like a fisheye's is made again as OPENCV_FISHEYE (with `repair`)."""
    exif_focal: bool = True
    """Start from the focal length in the photos' EXIF, when they carry one."""
    sensor_width_mm: float = 0.0
    """Sensor width in mm, for EXIF with a focal length in mm but no 35 mm equivalent; 0: unknown."""
    shared_camera: Literal["auto", "yes", "no"] = "auto"
    """One camera for all photos; auto: when their sizes, and their EXIF camera models, lenses and focal lengths agree
    (else one camera per photo)."""
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
    loop_neighbours: int = 5
    """In sequential matching, each image is also matched with this many of the most alike images outside its
    neighbours, and the first images with the last, so a walk around a scene closes its loop; 0: off."""
    gps_priors: bool = True
    """Hold the incremental mapper's cameras near where the photos' EXIF GPS says they were taken (COLMAP's position
    priors), where those positions span a survey (stages/sfm/gps.py): a drone's rows then cannot bend into a dome, and
    the model comes out in metres east, north and up."""
    mapper: Literal["incremental", "global"] = "incremental"
    """COLMAP mapper; a global model that contradicts its matches is mapped again incrementally."""
    refine_principal_point: bool = False
    """Let bundle adjustment move the principal point."""
    use_gpu: bool = True
    """Extract and match SIFT on the GPU when pycolmap was built with CUDA."""
    seed: int = 0
    """Random seed for COLMAP's RANSAC and mappers."""
    threads: int = 0
    """CPU threads COLMAP uses; 0: all cores. 1 makes the same model on every run: with more, its matching and bundle
    adjustment vary with the threads' timing, and a model near a check's limit can pass on one run and fail on the next."""
    max_contradicted_images: float = 0.1
    """Share of the images whose poses may contradict their verified matches before the model is made again with a
    safer configuration, or refused."""
    repair: bool = True
    """When a model contradicts its matches or splits in parts, try safer configurations (exhaustive matching, no EXIF
    focal prior, more features, full-size images) and keep the first that holds, and make a lens that bends like a
    fisheye's again as one; off: refuse at once, keep the lens as fitted."""

    def check(self, section: str = "poses") -> None:
        require(self.sensor_width_mm >= 0, f"{section}.sensor_width_mm must be 0 (unknown) or the sensor width in mm")
        require(self.max_features >= 64, f"{section}.max_features must be at least 64")
        require(self.feature_max_side == 0 or self.feature_max_side >= 64,
                f"{section}.feature_max_side must be 0 (the ingested size) or at least 64")
        require(self.min_features >= 0, f"{section}.min_features must be 0 or more")
        require(self.exhaustive_max_images >= 2, f"{section}.exhaustive_max_images must be at least 2")
        require(self.sequential_overlap >= 1, f"{section}.sequential_overlap must be at least 1")
        require(self.threads >= 0, f"{section}.threads must be 0 (all cores) or a number of threads")
