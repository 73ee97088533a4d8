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
    """The model's options and the trainer's (plenoxels.core.options: ModelOptions, TrainOptions)
    and what only this stage decides: the device, the images, the live held-out PSNR, checkpoints."""

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
    chosen for it by a cost model measured on this machine (fit.resolutions and fit.steps are then ignored)."""

    @property
    def budget_seconds(self) -> float:
        return parse_duration(self.time_budget, "fit.time_budget")

    def check(self) -> None:
        require(len(self.resolutions) >= 1 and all(r >= 8 for r in self.resolutions),
                "fit.resolutions must be a list of at least one resolution, each >= 8 (for example [128, 256])")
        require(all(b >= a for a, b in zip(self.resolutions, self.resolutions[1:])),
                "fit.resolutions must not decrease from level to level (for example [128, 128, 256]: a repeated "
                "resolution prunes the grid without upsampling it)")
        require(0 < self.first_level_scale <= 1, "fit.first_level_scale must be in (0, 1] (1: the first level as set)")
        require(len(self.steps) == len(self.resolutions) and all(s >= 1 for s in self.steps),
                f"fit.steps must list one positive step count per resolution ({len(self.resolutions)} here)")
        require(self.batch_size >= 1, "fit.batch_size must be at least 1")
        require(self.tile_size >= 1, "fit.tile_size must be at least 1")
        require(0 < self.image_scale <= 1, "fit.image_scale must be in (0, 1]")
        require(0 <= self.sh_degree <= 3, "fit.sh_degree must be 0, 1, 2 or 3")
        require(self.lr_density > 0 and self.lr_density_final > 0 and self.lr_sh > 0 and self.lr_sh_final > 0,
                "fit.lr_density, fit.lr_density_final, fit.lr_sh and fit.lr_sh_final must be positive")
        require(0 <= self.lr_density_delay < 1, "fit.lr_density_delay must be in [0, 1)")
        require(0 <= self.rmsprop_beta < 1, "fit.rmsprop_beta must be in [0, 1)")
        require(self.tv_density >= 0 and self.tv_sh >= 0, "fit.tv_density and fit.tv_sh must be >= 0")
        require(0 < self.tv_sample_fraction <= 1, "fit.tv_sample_fraction must be in (0, 1]")
        require(self.tv_reference_resolution >= 0,
                "fit.tv_reference_resolution must be >= 0 (0: the TV weights as set on every level)")
        require(self.sparsity >= 0, "fit.sparsity must be >= 0 (0: off)")
        require(self.step_size > 0, "fit.step_size must be positive (voxels)")
        require(0 <= self.stop_transmittance < 1, "fit.stop_transmittance must be in [0, 1)")
        require(self.prune_weight >= 0 and self.prune_dilation >= 0, "fit.prune_weight and fit.prune_dilation must be >= 0")
        require(0 < self.prune_ray_scale <= 1, "fit.prune_ray_scale must be in (0, 1]")
        require(self.prune_rays_per_cell >= 0, "fit.prune_rays_per_cell must be >= 0 (0: every pixel at fit.prune_ray_scale)")
        require(self.voxel_budget >= 1000, "fit.voxel_budget must be at least 1000")
        require(len(self.background_color) == 3 and all(0 <= c <= 1 for c in self.background_color),
                "fit.background_color must be three numbers in [0, 1] (for example [1, 1, 1])")
        require(self.box_padding >= 0, "fit.box_padding must be >= 0")
        require(0 <= self.near_share < 1, "fit.near_share must be in [0, 1)")
        require(self.background_spheres >= 1 and (self.background_width == 0 or self.background_width >= 4),
                "fit.background_spheres must be >= 1 and fit.background_width 0 (from the photos) or >= 4")
        require(self.background_texel_px > 0, "fit.background_texel_px must be positive")
        require(self.lr_background > 0 and self.tv_background >= 0, "fit.lr_background must be > 0, fit.tv_background >= 0")
        require(self.eval_every >= 0 and self.eval_views >= 0, "fit.eval_every and fit.eval_views must be >= 0")
        require(0 < self.eval_scale <= 1, "fit.eval_scale must be in (0, 1]")
        require(self.checkpoint_every > 0, "fit.checkpoint_every must be positive (seconds)")
        parse_duration(self.time_budget, "fit.time_budget")
