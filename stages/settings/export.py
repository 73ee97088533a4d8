"""The export stage as the pipeline plans it: its name, the stages it reads, its version and its settings (its
work: stages/export.py)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from plenoxels.core.errors import require
from plenoxels.core.options import MeshOptions

NAME = "export"
DEPENDS: tuple[str, ...] = ("normalize", "fit")
VERSION = 3


@dataclass
class Settings(MeshOptions):
    """The mesh's options (plenoxels.core.options.MeshOptions, which checks its own), and the frame, box, texture,
    points and splats."""
    frame: Literal["input", "normalized"] = "input"
    """Input: the poses' (COLMAP) frame; normalized: the fit's world."""
    crop: list[float] = field(default_factory=list)
    """Box [xmin, ymin, zmin, xmax, ymax, zmax] (normalised frame, e.g. from the viewer) instead of the foreground box."""
    texture: bool = True
    """Unwrap the mesh (xatlas) and bake the field's colour into mesh.png for the OBJ and GLB; off: vertex colours."""
    texture_size: int = 2048
    """The texture's side, about (xatlas packs the atlas to it), in texels."""
    texture_colour: Literal["view", "normal", "mean"] = "view"
    """view: the colour the field renders from the training views that face the surface most squarely (texture_views);
    normal: looking straight at the surface; mean: its view-independent SH degree-0 term (plenoxels/surface/texture.py says
    why view)."""
    texture_views: int = 8
    """With texture_colour view: each texel takes the mean of what up to this many of the training views that see it
    most squarely saw, weighted by their squared cosine with the surface; 1: the one facing it most squarely."""
    points: int = 200_000
    """Points kept in points.ply (a random, seeded subset)."""
    point_scale: float = 0.5
    """Training views are rendered at this share of their size (points, seen faces)."""
    point_views: int = 0
    """Training views rendered for the points; 0: all."""
    splats: bool = True
    """Write splats.ply and splats.glb: Gaussian splats of the field, started from the grid and distilled against its
    renders of the training views (plenoxels/splats/)."""
    max_splats: int = 500_000
    """At most this many splats from the grid: the cells the training views weigh most (a background model's texels
    come on top)."""
    splat_min_weight: float = 0.01
    """A grid vertex becomes a splat where some training ray's rendering weight at it reaches this."""
    splat_seconds: float = 300.0
    """How long the distillation runs, in seconds; 0: the splats as they start from the grid."""
    splat_scale: float = 0.5
    """The training views are rendered for the distillation at this share of their size."""
    splat_views: int = 0
    """Training views rendered for the distillation; 0: all."""
    splat_window: int = 48
    """Each distillation step renders a window of a training view this many pixels a side (small windows: more steps
    in the same time, each over the splats near one part of the scene; bench/README.md, "Splats")."""
    splat_score_views: int = 8
    """Held-out views the splats are rendered from and scored on (export.json); 0: none."""

    def check(self) -> None:
        MeshOptions.check(self, NAME)
        require(not self.crop or (len(self.crop) == 6 and all(lo < hi for lo, hi in zip(self.crop[:3], self.crop[3:]))),
                "export.crop must be empty or [xmin, ymin, zmin, xmax, ymax, zmax] with each min below its max")
        require(64 <= self.texture_size <= 16384, "export.texture_size must be between 64 and 16384 texels")
        require(self.texture_views >= 1, "export.texture_views must be 1 or more")
        require(self.points >= 0, "export.points must be 0 (no point cloud) or more")
        require(0.0 < self.point_scale <= 1.0, "export.point_scale must be in (0, 1]")
        require(self.point_views >= 0, "export.point_views must be 0 (all training views) or more")
        require(self.max_splats >= 1, "export.max_splats must be 1 or more (export.splats: false writes none)")
        require(0.0 < self.splat_min_weight < 1.0, "export.splat_min_weight must be in (0, 1)")
        require(self.splat_seconds >= 0, "export.splat_seconds must be 0 (no distillation) or more")
        require(0.0 < self.splat_scale <= 1.0, "export.splat_scale must be in (0, 1]")
        require(self.splat_views >= 0, "export.splat_views must be 0 (all training views) or more")
        require(self.splat_window >= 8, "export.splat_window must be 8 pixels or more")
        require(self.splat_score_views >= 0, "export.splat_score_views must be 0 (no scoring) or more")
