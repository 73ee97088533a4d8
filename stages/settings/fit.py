"""The fit stage as the pipeline plans it: its name, the stages it reads, its version and its settings (its work:
stages/fit.py)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from stages.common.text import parse_duration
from plenoxels.core.errors import require
from plenoxels.core.options import ModelOptions, TrainOptions

NAME = "fit"
DEPENDS: tuple[str, ...] = ("normalize",)
VERSION = 1


@dataclass
class Settings(TrainOptions, ModelOptions):
    """The model's options and the trainer's (plenoxels.core.options: ModelOptions, TrainOptions; each checks its
    own) and what only this stage decides: the device, the images, the live held-out PSNR, checkpoints."""

    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Where to fit: auto (a CUDA GPU when one is ready, else the CPU), cpu or cuda."""
    image_scale: float = 0.5
    """Training images are resized by this factor."""
    eval_every: int = 500
    """Held-out PSNR every this many steps (0: only at the end)."""
    eval_views: int = 3
    """Held-out views used for the live held-out PSNR."""
    eval_scale: float = 0.25
    """Share of their size the held-out views are rendered at."""
    checkpoint_every: float = 180.0
    """Seconds between checkpoints."""
    time_budget: float | str = 0.0
    """Finish the fit within this time (90s, 5m, 2m30s or seconds; 0: off), with levels, resolutions and steps
    chosen for it by a cost model measured on this machine (in place of fit.resolutions and fit.steps), and the
    photos taken at image_scale or more, up to whole, where image_scale would leave them coarser than fit.resolutions'
    finest level (plenoxels/planning/fit_plan.py, photo_scale)."""

    @property
    def budget_seconds(self) -> float:
        return parse_duration(self.time_budget, "fit.time_budget")

    def check(self) -> None:
        ModelOptions.check(self, NAME)
        TrainOptions.check(self, NAME)
        require(0 < self.image_scale <= 1, "fit.image_scale must be in (0, 1]")
        require(self.eval_every >= 0 and self.eval_views >= 0, "fit.eval_every and fit.eval_views must be >= 0")
        require(0 < self.eval_scale <= 1, "fit.eval_scale must be in (0, 1]")
        require(self.checkpoint_every > 0, "fit.checkpoint_every must be positive (seconds)")
        parse_duration(self.time_budget, "fit.time_budget")
