"""The poses stage as the pipeline plans it: its name, the stages it reads, its version, its settings and the
fingerprint of the pose files beside the photos (its work: stages/poses.py)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from plenoxels.core.errors import require
from stages.sfm.options import SfmOptions
from stages.sfm.pose_files import pose_files

NAME = "poses"
DEPENDS: tuple[str, ...] = ("ingest",)
VERSION = 1


@dataclass
class Settings(SfmOptions):
    """SfM's options (stages.sfm.options.SfmOptions, which checks its own), and where poses come from."""
    source: Literal["auto", "sfm", "colmap", "transforms", "llff", "idr", "metashape", "opensfm", "nsvf",
                    "polycam", "mvsnet", "record3d", "realitycapture", "meshroom", "bundler",
                    "openmvg", "pix4d"] = "auto"
    """Where poses come from: auto imports pose files found beside the photos (a COLMAP model, a transforms.json,
    LLFF's poses_bounds.npy, IDR/NeuS's cameras_sphere.npz, Metashape's exported cameras .xml, OpenSfM's or
    OpenDroneMap's opensfm/reconstruction.json, NSVF's or NeRF++'s pose/ folders, Polycam's keyframes/cameras/,
    MVSNet's cams/, Record3D's metadata.json, RealityCapture's XMP files beside the photos or its camera CSV,
    Meshroom's cameras.sfm, Bundler's bundle.out with its list.txt, OpenMVG's sfm_data.json,
    Pix4D's calibrated camera parameters), else runs SfM."""
    path: str = ""
    """An explicit pose file or COLMAP model folder to import (kind taken from source, or guessed)."""
    min_registered_share: float = 0.5
    """Fail when fewer than this share of the images get a pose, in (0, 1]."""
    colmap_log: bool = False
    """Show COLMAP's own log lines."""

    def check(self) -> None:
        SfmOptions.check(self, NAME)
        require(0.0 < self.min_registered_share <= 1.0, "poses.min_registered_share must be in (0, 1]")
        require(not (self.path and self.source == "sfm"),
                "poses.path names pose files to import; it cannot be used with poses.source=sfm")


def fingerprint(scene: Path) -> list:
    """Pose files beside the photos decide what this stage does, so they are part of its key."""
    return [[str(p), p.stat().st_size, p.stat().st_mtime_ns] for p in pose_files(scene)]
