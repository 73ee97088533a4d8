"""The normalize stage as the pipeline plans it: its name, the stages it reads, its version and its settings (its
work: stages/normalize.py)."""
from __future__ import annotations

from dataclasses import dataclass

from plenoxels.core.errors import require
from stages.framing.options import SceneOptions

NAME = "normalize"
DEPENDS: tuple[str, ...] = ("poses",)
VERSION = 1


@dataclass
class Settings(SceneOptions):
    """The scene frame's options (stages.framing.options.SceneOptions), checked."""

    def check(self) -> None:
        require(self.holdout_every == 0 or self.holdout_every >= 2,
                "normalize.holdout_every must be 0 (hold none out) or at least 2")
        require(self.train_every >= 1, "normalize.train_every must be at least 1 (1: every training photo)")
        require(0.0 <= self.margin <= 1.0, "normalize.margin must be in [0, 1]")
        require(0.0 < self.forward_max_cone_deg < 90.0, "normalize.forward_max_cone_deg must be in (0, 90)")
        require(self.beyond_factor > 1.0, "normalize.beyond_factor must be greater than 1")
        require(0.0 < self.unbounded_min_beyond_fraction < 1.0, "normalize.unbounded_min_beyond_fraction must be in (0, 1)")
        require(0.0 < self.object_min_empty_fraction < 1.0, "normalize.object_min_empty_fraction must be in (0, 1)")
        require(0.0 <= self.borderline_deg < self.forward_max_cone_deg,
                "normalize.borderline_deg must be >= 0 and below normalize.forward_max_cone_deg")
