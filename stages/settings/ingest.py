"""The ingest stage as the pipeline plans it: its name, the stages it reads, its version, its settings and the
fingerprint of the photos it reads (its work: stages/ingest.py)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pipeline.config import require
from pipeline.photos import photo_folder, scene_files

NAME = "ingest"
DEPENDS: tuple[str, ...] = ()
VERSION = 1


@dataclass
class Settings:
    max_side: int = 960
    """Downscale so the longest side is at most this many pixels; 0 keeps the full size."""
    drop_blurry_fraction: float = 0.0
    """Share of the blurriest images to drop, in [0, 1); 0 keeps all."""
    video_motion: float = 0.05
    """From a video, keep a frame each time the view has moved this share of the frame's diagonal (the sharpest of
    the frames near that point), so neighbouring frames overlap."""
    video_fps: float = 5.0
    """From a video, keep at most this many frames per second."""
    min_images: int = 3
    """Fail when fewer usable images than this remain (at least 3)."""
    holdout_split: str = "val"
    """A NeRF synthetic dataset folder (train/, val/, test/): the split held out for scoring (val, test or none)."""

    def check(self) -> None:
        require(self.max_side == 0 or self.max_side >= 32, "ingest.max_side must be 0 (full size) or at least 32")
        require(0.0 <= self.drop_blurry_fraction < 1.0, "ingest.drop_blurry_fraction must be in [0, 1)")
        require(self.video_fps > 0, "ingest.video_fps must be positive")
        require(0 < self.video_motion < 1, "ingest.video_motion must be in (0, 1): a share of the frame's diagonal")
        require(self.min_images >= 3, "ingest.min_images must be at least 3 (fewer cannot be posed)")
        require(self.holdout_split in ("val", "test", "none"), "ingest.holdout_split must be val, test or none")


def fingerprint(scene: Path) -> list:
    return [[str(p.relative_to(photo_folder(scene))), p.stat().st_size, p.stat().st_mtime_ns] for p in scene_files(scene)]
