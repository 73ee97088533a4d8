"""Fit: the training photos of normalize/scene.json -> a Plenoxels sparse voxel grid, coarse to fine.

Reads the train split only (held-out frames are used for the live held-out PSNR, never for fitting).
Images with a mask are composited onto `background_color`. Each step renders a batch of rays (random
pixels, or random square tiles of pixels, which keep the kernel's memory reads local) and takes one
sparse RMSProp step on MSE + TV. After each level of `resolutions` but the last, vertices that no
training ray weighs (max rendering weight) or that hold no density are pruned, the survivors are
dilated and the grid is upsampled; the optimiser state follows the vertices.

Writes fit/grid.pt and fit/model.json (plenoxels.scene_model.SceneModel.save) and fit/fit.json (the
levels, occupied voxels, memory, losses and held-out PSNR over time, timings).

Interruptions:
- a checkpoint is written to the stage's scratch folder every `checkpoint_every` seconds and at each
  level change; a re-run with the same inputs and settings resumes from it (same step, same batches);
- the first Ctrl-C stops the fit after the current step and writes the model as it stands as the
  fit's output (`complete: false` in fit.json, "stopped early" in the summary), so the later stages
  run from it. That output stands for these settings: change a setting or use `--force fit` to fit
  again from the start. A second Ctrl-C aborts at once, keeping the checkpoint;
- if the loss or a parameter becomes NaN or infinite the fit stops with a message naming the setting
  to lower; the last checkpoint (always written from finite parameters) stays in the scratch folder.
"""
from __future__ import annotations

import math
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch

from plenoxels.cameras import Intrinsics
from pipeline.config import require
from plenoxels.errors import UserError
from pipeline.io import read_json, read_rgb, write_json
from plenoxels.device import resolve_device
from plenoxels.grid import SparseGrid, sh_count
from plenoxels.optim import GridGrad, SparseRMSProp
from plenoxels.regularizers import tv_loss_and_grad
from plenoxels.render import RenderOptions, loss_and_grad, max_weights
from plenoxels.scene_model import SceneModel, psnr

NAME = "fit"
DEPENDS: tuple[str, ...] = ("normalize",)
VERSION = 1
CODE = ("plenoxels", "csrc")

CHECKPOINT = "checkpoint.pt"
# The running train PSNR averages the MSE of this many recent steps.
LOSS_WINDOW = 50
# Parameters are checked for NaN/inf this often (and before every checkpoint); the loss every step.
GUARD_EVERY = 25
# Rays per call when measuring max weights for pruning and rendering held-out views.
RAY_CHUNK = 1 << 16


@dataclass
class Settings:
    device: Literal["auto", "cpu", "cuda"] = "auto"
    resolutions: list[int] = field(default_factory=lambda: [128, 256])  # vertices along the longest axis, per level
    steps: list[int] = field(default_factory=lambda: [1000, 1500])     # optimiser steps per level
    batch_size: int = 8192             # rays per step (lego 400 px, 2 cores: 31.2 dB held-out in 3.7 min; 16384
    #                                    rays and [1500, 3000] steps ran at 5 steps/s on the first level alone)
    batch_mode: Literal["tiles", "rays"] = "rays"  # rays: random pixels; tiles: square pixel tiles (faster kernel,
    #                                                but 2-3 dB worse per step on lego at equal steps)
    tile_size: int = 32                # tile side in pixels (batch_mode tiles)
    image_scale: float = 0.5           # training images are resized by this factor
    sh_degree: int = 2                 # spherical-harmonic degree of the colour, 0-3
    init_density: float = 0.1          # raw density of every vertex at the start
    lr_density: float = 30.0           # RMSProp rate of the density, decayed exponentially to lr_density_final
    lr_density_final: float = 3.0      # (lego 200 px, 64^3 -> 128^3: 3 -> 30 gave +0.8 dB and 35% less time)
    lr_density_delay: float = 0.1      # share of the steps over which the density rate ramps up from 1% (0: none)
    lr_sh: float = 0.05                # RMSProp rate of the SH coefficients, decayed to lr_sh_final
    lr_sh_final: float = 5e-3          # both rates fall 10x over the whole fit: lego 200 px held-out 29.2 dB,
    #                                    against 27.8 falling 100x/1000x (the finer level barely trained), 27.6 flat
    rmsprop_beta: float = 0.95
    tv_density: float = 1e-10          # TV weight per sampled vertex of the density; with the MSE a mean over the
    tv_sh: float = 1e-8                # batch. A vertex's TV gradient does not shrink with the cell size while its
    #                                    MSE gradient does, so TV bites harder on finer grids: at 1e-8 / 1e-6 lego's
    #                                    256^3 level stalled at train PSNR 28.3 (held-out 27.9 dB); at these, 31.2 dB
    #                                    in 224 s of fitting (no TV at all: 31.0 on 10 views). Forward scenes pin
    #                                    their own (configs/scene_types/forward.yaml).
    tv_sample_fraction: float = 0.01   # share of the occupied vertices the TV term looks at each step
    step_size: float = 0.5             # ray sample spacing in voxels
    stop_transmittance: float = 1e-4   # a ray stops once this little light gets through
    prune_weight: float = 0.002        # keep vertices some training ray weighs by more than this...
    prune_density: float = 0.0         # ...whose raw density is above this (fit-frame units)
    prune_dilation: int = 2            # then grow what is kept by this many voxels
    prune_ray_scale: float = 0.5       # the training rays used to measure weights: images at this share of their size
    prune_final: bool = True           # prune the same way after the last level (smaller file, fewer floaters)
    voxel_budget: int = 16_000_000     # most occupied vertices after an upsample
    ndc: Literal["auto", "on", "off"] = "auto"          # auto: NDC for forward scenes
    background: Literal["auto", "on", "off"] = "auto"   # auto: a background model for unbounded scenes
    background_color: list[float] = field(default_factory=lambda: [1.0, 1.0, 1.0])  # behind the grid and under masks
    box_padding: float = 0.05          # the grid box is the foreground box grown by this share on each side
    background_spheres: int = 32       # background model: spheres
    background_width: int = 128        # background model: texture width (height is half)
    lr_background: float = 0.01        # background model: Adam rate
    tv_background: float = 1e-3        # background model: TV weight
    eval_every: int = 500              # held-out PSNR every this many steps (0: only at the end)
    eval_views: int = 3                # held-out views used for it
    eval_scale: float = 0.25           # ...rendered at this share of their size
    checkpoint_every: float = 180.0    # seconds between checkpoints
    seed: int = 0

    def check(self) -> None:
        require(len(self.resolutions) >= 1 and all(r >= 8 for r in self.resolutions),
                "fit.resolutions must be a list of at least one resolution, each >= 8 (for example [128, 256])")
        require(all(b > a for a, b in zip(self.resolutions, self.resolutions[1:])),
                "fit.resolutions must increase from level to level (for example [128, 256])")
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
        require(self.step_size > 0, "fit.step_size must be positive (voxels)")
        require(0 <= self.stop_transmittance < 1, "fit.stop_transmittance must be in [0, 1)")
        require(self.prune_weight >= 0 and self.prune_dilation >= 0, "fit.prune_weight and fit.prune_dilation must be >= 0")
        require(0 < self.prune_ray_scale <= 1, "fit.prune_ray_scale must be in (0, 1]")
        require(self.voxel_budget >= 1000, "fit.voxel_budget must be at least 1000")
        require(len(self.background_color) == 3 and all(0 <= c <= 1 for c in self.background_color),
                "fit.background_color must be three numbers in [0, 1] (for example [1, 1, 1])")
        require(self.box_padding >= 0, "fit.box_padding must be >= 0")
        require(self.background_spheres >= 1 and self.background_width >= 4,
                "fit.background_spheres must be >= 1 and fit.background_width >= 4")
        require(self.lr_background > 0 and self.tv_background >= 0, "fit.lr_background must be > 0, fit.tv_background >= 0")
        require(self.eval_every >= 0 and self.eval_views >= 0, "fit.eval_every and fit.eval_views must be >= 0")
        require(0 < self.eval_scale <= 1, "fit.eval_scale must be in (0, 1]")
        require(self.checkpoint_every > 0, "fit.checkpoint_every must be positive (seconds)")

    @property
    def total_steps(self) -> int:
        return sum(self.steps)


# ------------------------------------------------------------------------------------------------
# Images and rays


def load_frame(root: Path, frame: dict, scale: float, background_color) -> tuple[np.ndarray, Intrinsics]:
    """A frame's image as float32 RGB [h,w,3] in [0,1], resized by `scale`, its mask (if any) composited
    onto `background_color`; and the intrinsics of the resized image."""
    path = root / frame["file_path"]
    if not path.is_file():
        raise UserError(f"image {path} listed in scene.json is missing; re-run the stages before fit")
    rgb = read_rgb(path).astype(np.float32) / 255.0
    k = Intrinsics.from_frame(frame)
    if (rgb.shape[1], rgb.shape[0]) != (k.w, k.h):
        raise UserError(f"{path} is {rgb.shape[1]}x{rgb.shape[0]} but scene.json says {k.w}x{k.h}; re-run normalize")
    if frame.get("mask_path"):
        alpha = read_alpha(root / frame["mask_path"])
        if alpha.shape != rgb.shape[:2]:
            raise UserError(f"mask {frame['mask_path']} is not the size of its image; re-run ingest")
        rgb = rgb * alpha[..., None] + np.asarray(background_color, dtype=np.float32) * (1 - alpha[..., None])
    k = k.scaled(scale) if scale != 1 else k
    if (k.w, k.h) != (rgb.shape[1], rgb.shape[0]):
        rgb = cv2.resize(rgb, (k.w, k.h), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(rgb), k


def read_alpha(path: Path) -> np.ndarray:
    """A mask as float32 [h,w] in [0,1]: a grey image, or the alpha channel of an RGBA one."""
    import imageio.v3 as iio

    image = iio.imread(path)
    if image.ndim == 3:
        image = image[..., 3] if image.shape[2] == 4 else image[..., 0]
    scale = 65535.0 if image.dtype == np.uint16 else 255.0
    return image.astype(np.float32) / scale


class RaySet:
    """Pixels of a set of images with their cameras; makes world rays for any (image, row, column).

    Pixels are stored flat (uint8 [P, 3]) so images of different sizes sit side by side.
    """

    def __init__(self, images: list[np.ndarray], c2ws: list[np.ndarray], intrinsics: list[Intrinsics]):
        self.sizes = torch.tensor([[k.h, k.w] for k in intrinsics], dtype=torch.int64)
        counts = self.sizes[:, 0] * self.sizes[:, 1]
        self.offsets = torch.cat([torch.zeros(1, dtype=torch.int64), counts.cumsum(0)])
        self.pixels = torch.cat([torch.from_numpy(np.round(im * 255).astype(np.uint8).reshape(-1, 3)) for im in images])
        self.c2w = torch.tensor(np.stack(c2ws), dtype=torch.float32)
        self.k = torch.tensor([[k.fl_x, k.fl_y, k.cx, k.cy] for k in intrinsics], dtype=torch.float32)
        self.intrinsics = intrinsics

    @property
    def num_pixels(self) -> int:
        return int(self.offsets[-1])

    def __len__(self) -> int:
        return self.sizes.shape[0]

    def rays(self, image: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World origins and unit directions [B, 3] through pixel centres (plenoxels.cameras convention)."""
        k = self.k[image]
        d_cam = torch.stack([(col.float() + 0.5 - k[:, 2]) / k[:, 0], -(row.float() + 0.5 - k[:, 3]) / k[:, 1],
                             -torch.ones_like(k[:, 0])], dim=-1)
        c2w = self.c2w[image]
        d = torch.einsum("bij,bj->bi", c2w[:, :3, :3], d_cam)
        return c2w[:, :3, 3].contiguous(), (d / d.norm(dim=-1, keepdim=True)).contiguous()

    def batch(self, size: int, mode: str, tile: int, generator: torch.Generator):
        """A training batch: world origins, directions [B, 3] and target colours [B, 3] in [0, 1]."""
        if mode == "rays":
            flat = torch.randint(self.num_pixels, (size,), generator=generator)
            image = torch.searchsorted(self.offsets, flat, right=True) - 1
            local = flat - self.offsets[image]
            w = self.sizes[image, 1]
            row, col = local // w, local % w
        else:
            n_tiles = max(1, size // (tile * tile))
            counts = (self.offsets[1:] - self.offsets[:-1]).double()
            image = torch.multinomial(counts, n_tiles, replacement=True, generator=generator)
            h, w = self.sizes[image, 0], self.sizes[image, 1]
            th, tw = torch.clamp(h, max=tile), torch.clamp(w, max=tile)
            top = (torch.rand(n_tiles, generator=generator) * (h - th + 1)).long()
            left = (torch.rand(n_tiles, generator=generator) * (w - tw + 1)).long()
            dy, dx = torch.meshgrid(torch.arange(tile), torch.arange(tile), indexing="ij")
            dy, dx = dy.reshape(1, -1), dx.reshape(1, -1)
            inside = (dy < th[:, None]) & (dx < tw[:, None])
            image = image[:, None].expand(-1, tile * tile)[inside]
            row = (top[:, None] + dy)[inside]
            col = (left[:, None] + dx)[inside]
            w = self.sizes[image, 1]
            flat = self.offsets[image] + row * w + col
        o, d = self.rays(image, row, col)
        return o, d, self.pixels[flat].float() / 255.0

    def subsampled_rays(self, scale: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through a regular subset of every image's pixels (every 1/scale-th row and column)."""
        stride = max(1, round(1 / scale))
        origins, dirs = [], []
        for i in range(len(self)):
            h, w = int(self.sizes[i, 0]), int(self.sizes[i, 1])
            row, col = torch.meshgrid(torch.arange(stride // 2, h, stride), torch.arange(stride // 2, w, stride),
                                      indexing="ij")
            o, d = self.rays(torch.full((row.numel(),), i), row.reshape(-1), col.reshape(-1))
            origins.append(o)
            dirs.append(d)
        return torch.cat(origins), torch.cat(dirs)


# ------------------------------------------------------------------------------------------------
# Schedules, pruning


def decayed_lr(initial: float, final: float, progress: float, delay: float = 0.0) -> float:
    """Exponential (log-linear) decay from `initial` to `final` as progress goes 0 -> 1; with a delay,
    the rate first ramps up from 1% along a quarter sine (as svox2 does)."""
    progress = min(max(progress, 0.0), 1.0)
    rate = math.exp(math.log(initial) * (1 - progress) + math.log(final) * progress)
    if delay > 0:
        rate *= 0.01 + 0.99 * math.sin(0.5 * math.pi * min(progress / delay, 1.0))
    return rate


def prune_mask(grid: SparseGrid, weights: torch.Tensor, s: Settings) -> torch.Tensor:
    """Rows to keep: weighed by some training ray and holding density, grown by the dilation."""
    keep = (weights > s.prune_weight) & (grid.density > s.prune_density)
    return grid.dilate(keep, s.prune_dilation)


def budget_mask(grid: SparseGrid, keep: torch.Tensor, weights: torch.Tensor, budget_rows: int) -> torch.Tensor:
    """Narrows `keep` to the `budget_rows` rows with the largest weights when it holds more."""
    if int(keep.sum()) <= budget_rows:
        return keep
    score = torch.where(keep, weights, torch.full_like(weights, -1.0))
    top = torch.topk(score, budget_rows).indices
    narrowed = torch.zeros_like(keep)
    narrowed[top] = True
    return narrowed


# ------------------------------------------------------------------------------------------------
# The fit


class Diverged(Exception):
    """The loss or the parameters stopped being finite."""


class StopRequest:
    """The first Ctrl-C asks the fit to stop after the current step; the second raises KeyboardInterrupt.
    Only the main thread can take signals; elsewhere Ctrl-C simply raises."""

    def __init__(self):
        self.requested = False
        self._previous = None

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def _handle(self, signum, frame):
        self.requested = True
        signal.signal(signal.SIGINT, signal.default_int_handler)

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
        return False


class Fitter:
    """The state of one fit: the model, its optimisers, the step counter and the history."""

    def __init__(self, scene: dict, s: Settings, train: RaySet, report, device: torch.device = torch.device("cpu"),
                 backend: str = "native"):
        self.s, self.train, self.report, self.device, self.backend = s, train, report, device, backend
        self.opts = RenderOptions(step_size=s.step_size, stop_transmittance=s.stop_transmittance)
        self.model = SceneModel.create(scene, s, s.resolutions[0], self.opts, backend)
        self.model.to(device)
        self.generator = torch.Generator().manual_seed(s.seed)
        self.step = 0
        self.level = 0
        self.elapsed = 0.0
        self.history: list[dict] = []      # held-out PSNR over time
        self.levels: list[dict] = []       # what happened at each level change
        self.recent_mse: list[float] = []
        self.checkpoint_step: int | None = None
        self._new_optimiser()

    # ---- optimiser state ------------------------------------------------------------------------
    def _new_optimiser(self) -> None:
        self.grad = GridGrad(self.model.grid)
        self.optim = SparseRMSProp(self.model.grid, self.s.lr_density, self.s.lr_sh, self.s.rmsprop_beta,
                                   backend=self.backend)
        self.bg_optim = (torch.optim.Adam(self.model.background.parameters(), lr=self.s.lr_background)
                         if self.model.background is not None else None)

    def _replace_grid(self, grid: SparseGrid, old_rows: torch.Tensor) -> None:
        self.optim.remap(grid, old_rows)
        self.model.grid = grid
        self.grad = GridGrad(grid)

    # ---- one step ------------------------------------------------------------------------------
    def level_end(self, level: int) -> int:
        return sum(self.s.steps[:level + 1])

    def train_step(self) -> float:
        s = self.s
        progress = self.step / max(1, s.total_steps)
        self.optim.set_lr(decayed_lr(s.lr_density, s.lr_density_final, progress, s.lr_density_delay),
                          decayed_lr(s.lr_sh, s.lr_sh_final, progress))
        o_w, d_w, target = (t.to(self.device) for t in self.train.batch(s.batch_size, s.batch_mode, s.tile_size,
                                                                          self.generator))
        o, d = self.model.to_grid_frame(o_w, d_w)
        background = self.model.background_rgb(o_w, d_w)
        mse, grad_background = loss_and_grad(self.model.grid, o, d, target, background.detach(), self.opts,
                                             self.grad, backend=self.backend)
        if not math.isfinite(mse):
            raise Diverged(f"the loss became {mse}")
        tv_rows = max(1, round(s.tv_sample_fraction * self.model.grid.num_occupied))
        tv_loss_and_grad(self.model.grid, self.grad, s.tv_density * tv_rows, s.tv_sh * tv_rows, s.tv_sample_fraction,
                         self.generator, backend=self.backend)
        self.optim.step(self.grad)
        if self.bg_optim is not None:
            self.bg_optim.zero_grad()
            ((background * grad_background).sum() + self.model.background.regularizer()).backward()
            self.bg_optim.step()
        self.step += 1
        self.recent_mse = (self.recent_mse + [mse])[-LOSS_WINDOW:]
        if self.step % GUARD_EVERY == 0:
            self.check_finite()
        return mse

    def check_finite(self) -> None:
        columns = 1 + 3 * sh_count(self.model.grid.sh_degree)
        if not bool(torch.isfinite(self.model.grid.data[:, :columns]).all()):
            raise Diverged("a grid parameter became NaN or infinite")
        if self.model.background is not None and not all(bool(torch.isfinite(p).all())
                                                         for p in self.model.background.parameters()):
            raise Diverged("a background parameter became NaN or infinite")

    def train_psnr(self) -> float:
        return psnr(sum(self.recent_mse) / len(self.recent_mse)) if self.recent_mse else float("nan")

    # ---- structure changes ----------------------------------------------------------------------
    def measure_weights(self) -> torch.Tensor:
        origins, dirs = self.train.subsampled_rays(self.s.prune_ray_scale)
        weights = torch.zeros(self.model.grid.num_occupied, device=self.device)
        for start in range(0, origins.shape[0], RAY_CHUNK):
            o, d = self.model.to_grid_frame(origins[start:start + RAY_CHUNK].to(self.device),
                                            dirs[start:start + RAY_CHUNK].to(self.device))
            weights = torch.maximum(weights, max_weights(self.model.grid, o, d, self.opts, backend=self.backend))
        return weights

    def prune(self, budget_rows: int | None = None) -> dict:
        before = self.model.grid.num_occupied
        weights = self.measure_weights()
        keep = prune_mask(self.model.grid, weights, self.s)
        if budget_rows is not None:
            keep = budget_mask(self.model.grid, keep, weights, budget_rows)
        if int(keep.sum()) == 0:
            raise UserError("pruning would remove every voxel (no training ray hits any density); check the poses, "
                            "or lower fit.prune_weight / fit.prune_density")
        grid, old_rows = self.model.grid.prune(keep)
        self._replace_grid(grid, old_rows)
        return {"before": before, "after": grid.num_occupied}

    def next_level(self) -> None:
        """Prune, upsample to the next resolution within the voxel budget, carry the optimiser state."""
        old_res = max(self.model.grid.resolution)
        self.level += 1
        new_shape = self.model.resolution_for(self.s.resolutions[self.level])
        growth = (max(new_shape) / old_res) ** 3
        pruned = self.prune(budget_rows=max(1, int(self.s.voxel_budget / growth)))
        grid, old_rows = self.model.grid.upsample(new_shape)
        if grid.num_occupied > self.s.voxel_budget:
            # The estimate of the growth was short: drop the emptiest new vertices.
            keep = torch.zeros(grid.num_occupied, dtype=torch.bool, device=grid.data.device)
            keep[torch.topk(grid.density, self.s.voxel_budget).indices] = True
            grid, rows = grid.prune(keep)
            old_rows = old_rows[rows]
        self._replace_grid(grid, old_rows)
        self.levels.append({"step": self.step, "pruned_from": pruned["before"], "kept": pruned["after"],
                            "resolution": list(grid.resolution), "occupied": grid.num_occupied,
                            "memory_bytes": grid.memory_bytes()})

    # ---- checkpoints ----------------------------------------------------------------------------
    def state(self) -> dict:
        grid = self.model.grid
        return {
            "step": self.step, "level": self.level, "elapsed": self.elapsed, "history": self.history,
            "levels": self.levels, "recent_mse": self.recent_mse, "generator": self.generator.get_state(),
            "grid": {"links": grid.links, "data": grid.data, "bbox_min": grid.bbox_min, "bbox_max": grid.bbox_max,
                     "sh_degree": grid.sh_degree},
            "optim": self.optim.state_dict(),
            "background": self.model.background.state_dict() if self.model.background is not None else None,
            "bg_optim": self.bg_optim.state_dict() if self.bg_optim is not None else None,
        }

    def save_checkpoint(self, path: Path) -> None:
        self.check_finite()
        tmp = path.with_name(path.name + ".tmp")
        torch.save(self.state(), tmp)
        tmp.replace(path)
        self.checkpoint_step = self.step

    def load_checkpoint(self, path: Path) -> None:
        state = torch.load(path, map_location="cpu", weights_only=False)
        g = state["grid"]
        self.model.grid = SparseGrid(g["links"], g["data"], g["bbox_min"], g["bbox_max"], g["sh_degree"])
        self.model.to(self.device)
        self.checkpoint_step = state["step"]
        self.step, self.level, self.elapsed = state["step"], state["level"], state["elapsed"]
        self.history, self.levels, self.recent_mse = state["history"], state["levels"], state["recent_mse"]
        self.generator.set_state(state["generator"])
        self._new_optimiser()
        self.optim.load_state_dict(state["optim"])
        self.optim.second_moment = self.optim.second_moment.to(self.device)
        if self.model.background is not None:
            self.model.background.load_state_dict(state["background"])
            self.bg_optim.load_state_dict(state["bg_optim"])


class HeldOut:
    """A few held-out views, small, to report held-out PSNR while fitting."""

    def __init__(self, root: Path, frames: list[dict], s: Settings):
        pick = frames if len(frames) <= s.eval_views else [frames[i] for i in
                                                             np.linspace(0, len(frames) - 1, s.eval_views).round().astype(int)]
        self.views = []
        for frame in pick if s.eval_views else []:
            image, k = load_frame(root, frame, s.eval_scale, s.background_color)
            self.views.append((np.asarray(frame["transform_matrix"], dtype=np.float64), k, torch.from_numpy(image)))

    def __bool__(self) -> bool:
        return bool(self.views)

    def psnr(self, model: SceneModel) -> float:
        errors = []
        for c2w, k, image in self.views:
            rgb = model.render_camera(c2w, k, chunk=RAY_CHUNK)["rgb"].cpu()
            errors.append(float(((rgb.cpu() - image) ** 2).mean()))
        return float(np.mean([psnr(e) for e in errors]))


def _load_training(ctx, scene: dict, s: Settings) -> tuple[RaySet, list[dict]]:
    frames = scene.get("frames") or []
    train = [f for f in frames if f.get("split", "train") == "train"]
    held_out = [f for f in frames if f.get("split") == "test"]
    if not train:
        raise UserError("scene.json has no training frames; re-run normalize with fewer held out (normalize.holdout_every)")
    images, c2ws, ks = [], [], []
    for frame in ctx.report.track(train, desc="loading training images"):
        image, k = load_frame(ctx.out, frame, s.image_scale, s.background_color)
        images.append(image)
        c2ws.append(np.asarray(frame["transform_matrix"], dtype=np.float64))
        ks.append(k)
    return RaySet(images, c2ws, ks), held_out


def _duration(seconds: float) -> str:
    minutes, sec = divmod(int(round(seconds)), 60)
    return f"{minutes}m{sec:02d}s" if minutes else f"{sec}s"


def _megabytes(n: int) -> str:
    return f"{n / 1e6:.0f} MB" if n >= 1e6 else f"{n / 1e3:.0f} kB"


def _voxels(n: int) -> str:
    return f"{n / 1e6:.2f}M" if n >= 1e6 else f"{n / 1e3:.1f}k"


def run(ctx) -> dict:
    s: Settings = ctx.settings
    device = resolve_device(s.device)
    if device.type != "cpu":
        ctx.report.info(f"fitting on {device}")
    scene = read_json(ctx.upstream["normalize"] / "scene.json")
    train, held_out_frames = _load_training(ctx, scene, s)
    fitter = Fitter(scene, s, train, ctx.report, device)
    held_out = HeldOut(ctx.out, held_out_frames, s)

    checkpoint = ctx.scratch / CHECKPOINT
    if checkpoint.is_file():
        fitter.load_checkpoint(checkpoint)
        ctx.report.info(f"resuming from the checkpoint at step {fitter.step}/{s.total_steps}")
    resumed_from = fitter.step
    stopped_early = False
    last_save = time.time()
    started = time.time() - fitter.elapsed

    try:
        with StopRequest() as stop, ctx.report.bar(total=s.total_steps, desc="fitting") as bar:
            bar.update(fitter.step)
            while fitter.step < s.total_steps:
                if fitter.step == fitter.level_end(fitter.level):
                    fitter.next_level()
                    fitter.elapsed = time.time() - started
                    fitter.save_checkpoint(checkpoint)
                    last_save = time.time()
                    grid = fitter.model.grid
                    ctx.report.info(f"level {fitter.level + 1}: {'x'.join(map(str, grid.resolution))} grid, "
                                    f"{_voxels(grid.num_occupied)} voxels ({_megabytes(grid.memory_bytes())})")
                mse = fitter.train_step()
                bar.update(1)
                if s.eval_every and held_out and fitter.step % s.eval_every == 0:
                    fitter.history.append({"step": fitter.step, "seconds": round(time.time() - started, 1),
                                           "train_psnr": round(fitter.train_psnr(), 3),
                                           "held_out_psnr": round(held_out.psnr(fitter.model), 3)})
                    ctx.report.info(f"step {fitter.step}: held-out PSNR {fitter.history[-1]['held_out_psnr']:.2f} dB")
                bar.set_postfix(loss=f"{mse:.4f}", psnr=f"{fitter.train_psnr():.2f}", refresh=False)
                if time.time() - last_save > s.checkpoint_every:
                    fitter.elapsed = time.time() - started
                    fitter.save_checkpoint(checkpoint)
                    last_save = time.time()
                if stop.requested:
                    stopped_early = True
                    break
    except Diverged as exc:
        kept = (f"the last good checkpoint (step {fitter.checkpoint_step}) is kept"
                if fitter.checkpoint_step is not None else "no checkpoint was written yet")
        raise UserError(f"the fit diverged at step {fitter.step} ({exc}); lower fit.lr_density (now {s.lr_density:g}) "
                        f"or fit.lr_sh (now {s.lr_sh:g}) and run again; {kept}") from None
    except KeyboardInterrupt:
        fitter.elapsed = time.time() - started
        try:
            fitter.save_checkpoint(checkpoint)
        except Diverged:
            pass  # keep the earlier, finite checkpoint
        raise

    fitter.elapsed = time.time() - started
    if stopped_early:
        fitter.save_checkpoint(checkpoint)
        ctx.report.warn(f"stopped early at step {fitter.step}/{s.total_steps} (Ctrl-C); writing the model as it stands")
    elif s.prune_final:
        fitter.prune()
    return finish(ctx, fitter, held_out, resumed_from, stopped_early, device)


def finish(ctx, fitter: Fitter, held_out: HeldOut, resumed_from: int, stopped_early: bool, device) -> dict:
    s = fitter.s
    model = fitter.model
    final_psnr = held_out.psnr(model) if held_out else None
    memory = model.memory_bytes()
    model.save(ctx.work, extra={"fit_settings": {k: getattr(s, k) for k in ("resolutions", "steps", "sh_degree",
                                                                            "image_scale", "step_size")}})
    grid = model.grid
    record = {
        "complete": not stopped_early,
        "resolutions": s.resolutions, "steps_per_level": s.steps,
        "steps": fitter.step, "total_steps": s.total_steps, "resumed_from_step": resumed_from,
        "seconds": round(fitter.elapsed, 1), "device": str(device),
        "train_images": len(fitter.train), "train_pixels": fitter.train.num_pixels,
        "train_psnr": round(fitter.train_psnr(), 3),
        "held_out_psnr": round(final_psnr, 3) if final_psnr is not None else None,
        "held_out_views": len(held_out.views), "held_out_scale": s.eval_scale,
        "history": fitter.history, "levels": fitter.levels,
        "model": model.describe(),
        "memory_bytes": memory,
    }
    write_json(ctx.work / "fit.json", record)
    res = grid.resolution
    shape = f"{res[0]}^3" if len(set(res)) == 1 else "x".join(map(str, res))
    line = (f"{shape} grid, {_voxels(grid.num_occupied)} voxels ({_megabytes(memory['total'])}), "
            f"train PSNR {record['train_psnr']:.1f} dB")
    if final_psnr is not None:
        # A quick estimate (a few views, downscaled); the evaluate stage gives the full figure.
        line += f", held-out ~{final_psnr:.1f} dB ({len(held_out.views)} views at {s.eval_scale:g}x)"
    line += f", {_duration(fitter.elapsed)}"
    if model.background is not None:
        line += f", background model {_megabytes(memory['background'])}"
    if model.ndc is not None:
        line += ", in NDC"
    if stopped_early:
        line += f"; stopped early at step {fitter.step}/{s.total_steps} (Ctrl-C)"
    return {"line": line, "complete": not stopped_early, "steps": fitter.step, "occupied": grid.num_occupied,
            "train_psnr": record["train_psnr"], "held_out_psnr": record["held_out_psnr"],
            "seconds": record["seconds"], "memory_bytes": memory["total"]}
