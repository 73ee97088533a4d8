"""The evaluate stage as the pipeline plans it: its name, the stages it reads, its version and its settings (its
work: stages/evaluate.py)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from plenoxels.core.errors import require

NAME = "evaluate"
DEPENDS: tuple[str, ...] = ("normalize", "fit")
VERSION = 1


@dataclass
class Settings:
    scale: float | Literal["fit"] = "fit"
    """Share of their size the held-out views are rendered at, in (0, 1]; fit: the fit's image_scale."""
    max_views: int = 0
    """Held-out views evaluated at most, spread evenly; 0: all."""
    video_frames: int = 60
    """Frames of the novel-view video; 0: no video."""
    video_side: int = 240
    """Longest side of the video frames, pixels."""
    video_fps: int = 24
    """Video frames per second."""
    sheet_rows: int = 8
    """Held-out views on the contact sheet, spread evenly."""
    sheet_side: int = 200
    """Longest side of each contact-sheet tile, pixels."""

    def check(self) -> None:
        require(self.scale == "fit" or 0 < float(self.scale) <= 1, "evaluate.scale must be 'fit' or a number in (0, 1]")
        require(self.max_views >= 0, "evaluate.max_views must be >= 0 (0: all held-out views)")
        require(self.video_frames >= 0 and self.video_fps >= 1, "evaluate.video_frames must be >= 0, video_fps >= 1")
        require(self.video_side >= 16, "evaluate.video_side must be at least 16 pixels")
        require(self.sheet_rows >= 1 and self.sheet_side >= 16, "evaluate.sheet_rows must be >= 1, sheet_side >= 16")
