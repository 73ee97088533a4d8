"""The export stage as the pipeline plans it: its name, the stages it reads, its version and its settings (its
work: stages/export.py)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from pipeline.config import require

NAME = "export"
DEPENDS: tuple[str, ...] = ("normalize", "fit")
VERSION = 1


@dataclass
class Settings:
    frame: Literal["input", "normalized"] = "input"
    """Input: the poses' (COLMAP) frame; normalized: the fit's world."""
    resolution: int | Literal["auto"] = "auto"
    """Marching-cubes cells along the grid's longest axis; auto: the fit's own."""
    level: float | Literal["auto"] = "auto"
    """Density iso-level; auto: see level_share."""
    level_share: float = 0.5
    """Auto level: this share of the peak density the opaque training rays meet (auto_level)."""
    level_opacity: float = 0.5
    """Auto level without such points: the density at which one voxel is this opaque."""
    crop_margin: float = 0.05
    """The foreground box is grown by this share of its size before cropping."""
    crop: list[float] = field(default_factory=list)
    """Box [xmin, ymin, zmin, xmax, ymax, zmax] (normalised frame, e.g. from the viewer) instead of the foreground box."""
    min_piece_fraction: float = 0.01
    """Pieces with fewer faces than this share of the largest piece are dropped."""
    max_gap: float = 0.05
    """Pieces farther than this share of the foreground diagonal from the largest are dropped."""
    target_faces: int = 0
    """Decimate to this many faces; 0 keeps every face."""
    points: int = 200_000
    """Points kept in points.ply (a random, seeded subset)."""
    point_scale: float = 0.5
    """Training views are rendered at this share of their size (points, seen faces)."""
    point_views: int = 0
    """Training views rendered for the points; 0: all."""
    point_opacity: float = 0.5
    """A pixel gives a point only where its ray is at least this opaque."""
    unseen: Literal["drop", "keep"] = "drop"
    """Faces no training view sees (insides of the fit's shells, undersides)."""
    seen_tolerance: float = 1.0
    """A vertex this many voxels behind what a view's pixel sees is still seen."""
    seed: int = 0
    """Seed of the random point subsets."""

    def check(self) -> None:
        require(self.resolution == "auto" or 8 <= self.resolution <= 2048,
                "export.resolution must be auto or between 8 and 2048 cells")
        require(self.level == "auto" or self.level > 0, "export.level must be auto or a positive density")
        require(0.0 < self.level_share < 1.0, "export.level_share must be in (0, 1)")
        require(0.0 < self.level_opacity < 1.0, "export.level_opacity must be in (0, 1)")
        require(self.crop_margin >= 0.0, "export.crop_margin must be 0 or more")
        require(not self.crop or (len(self.crop) == 6 and all(lo < hi for lo, hi in zip(self.crop[:3], self.crop[3:]))),
                "export.crop must be empty or [xmin, ymin, zmin, xmax, ymax, zmax] with each min below its max")
        require(0.0 <= self.min_piece_fraction <= 1.0, "export.min_piece_fraction must be in [0, 1]")
        require(self.max_gap > 0.0, "export.max_gap must be positive")
        require(self.target_faces == 0 or self.target_faces >= 4, "export.target_faces must be 0 (keep all) or at least 4")
        require(self.points >= 0, "export.points must be 0 (no point cloud) or more")
        require(0.0 < self.point_scale <= 1.0, "export.point_scale must be in (0, 1]")
        require(self.point_views >= 0, "export.point_views must be 0 (all training views) or more")
        require(0.0 < self.point_opacity < 1.0, "export.point_opacity must be in (0, 1)")
        require(self.seen_tolerance >= 0.0, "export.seen_tolerance must be 0 or more voxels")
