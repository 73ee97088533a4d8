"""Regularisers over a random subset of occupied vertices: total variation (see reference.tv_loss) and a sparsity
prior on density; and how strong TV needs to be for a capture: few photos far apart leave each point of the scene
seen by few of them, and a fit then memorises the photos (floaters and smears that only a held-out view shows) unless
the field is held smoother."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from plenoxels.core import native
from plenoxels.core.cameras import Intrinsics, project
from plenoxels.core.grid import SparseGrid
from plenoxels.core.optim import GridGrad


# Rows a regulariser's sample takes in runs of this many consecutive rows, on grids of at least SAMPLE_RUNS_FROM rows.
# A grid's rows lie in raster order, so a run's rows, their +z neighbours and their +x and +y neighbours each sit
# together in the tables: a run costs a few streams of memory, where as many rows drawn one by one cost a miss each in
# tables of hundreds of MB (bench/README.md, "A train step's parts"). A smaller grid's tables stay in cache: its rows
# are drawn one by one.
SAMPLE_RUN_ROWS = 32
SAMPLE_RUNS_FROM = 1 << 20


def sample_rows(grid: SparseGrid, sample_fraction: float, generator: torch.Generator | None = None,
                in_runs: bool = True) -> torch.Tensor:
    """All rows for a fraction >= 1, else round(fraction * N) rows drawn with replacement, every row as likely: in runs
    of SAMPLE_RUN_ROWS consecutive rows (wrapping past the last) from starts drawn uniformly where the grid has
    SAMPLE_RUNS_FROM rows or more and `in_runs` allows, else one by one."""
    n = grid.num_occupied
    if sample_fraction >= 1.0:
        return torch.arange(n, dtype=torch.int64)
    if sample_fraction <= 0.0 or n == 0:
        return torch.zeros(0, dtype=torch.int64)
    m = max(1, round(sample_fraction * n))
    run = min(SAMPLE_RUN_ROWS if in_runs and n >= SAMPLE_RUNS_FROM else 1, m)
    starts = torch.randint(n, (-(-m // run),), generator=generator, dtype=torch.int64)
    return ((starts[:, None] + torch.arange(run, dtype=torch.int64)) % n).reshape(-1)[:m]


def tv_loss_and_grad(grid: SparseGrid, grad: GridGrad, weight_density: float, weight_sh: float,
                     sample_fraction: float, generator: torch.Generator | None = None) -> float:
    """TV loss of density and SH over sampled rows; its gradient is added into `grad`."""
    rows = sample_rows(grid, sample_fraction, generator)
    if rows.shape[0] == 0 or (weight_density == 0 and weight_sh == 0):
        return 0.0
    # In row order, each row's neighbours and gradients are read in the order the tables are laid out (sorted where
    # the grid is: on a GPU a launch, on the CPU as before).
    rows = rows.to(grid.data.device).sort().values
    loss, grad.num_touched = native.ops.tv_loss_and_grad(
        grid.data, grid.links, grid.coords(), rows, float(weight_density), float(weight_sh),
        grid.sh_degree, grad.data, grad.touched_mask, grad.touched_rows, grad.num_touched, *grad.scratch())
    return float(loss)


# The sparsity prior's scale: the optical thickness of one voxel (density times the voxel's length) at which the
# Cauchy penalty turns from quadratic to logarithmic. A vertex that stops less than about this share of the light
# (faint haze, which pruning would otherwise keep wherever some ray sees it) is pulled to zero; surfaces, far above
# it, feel almost nothing.
SPARSITY_THICKNESS = 0.01


def sparsity_loss_and_grad(grid: SparseGrid, grad: GridGrad, weight: float, sample_fraction: float,
                           generator: torch.Generator | None = None) -> float:
    """weight * sum over sampled vertices of log(1 + (relu(density) * voxel / SPARSITY_THICKNESS)^2), a Cauchy prior
    that density is zero (svox2's lambda_sparsity, here on grid vertices rather than ray samples); its gradient is
    added into `grad`. The voxel length makes it the same prior on every level."""
    if weight == 0:
        return 0.0  # before drawing rows: a fit without the prior draws the batches it always drew
    # One by one on any grid: runs of rows pulled to zero together left a toy's first level a worse start (held-out 19.4
    # against 20.9 dB, tests/stages/test_fit.py's sparsity test with every draw in runs).
    rows = torch.unique(sample_rows(grid, sample_fraction, generator, in_runs=False).to(grid.data.device))
    if rows.shape[0] == 0:
        return 0.0
    voxel = 1.0 / min(grid.scale)  # the longest vertex spacing, in fit-frame units
    thickness = grid.data[rows, 0].clamp_min(0.0) * (voxel / SPARSITY_THICKNESS)
    live = thickness > 0
    if not bool(live.any()):
        return 0.0
    thickness, rows = thickness[live], rows[live]
    loss = weight * torch.log1p(thickness * thickness).sum()
    d_density = weight * 2.0 * thickness / (1.0 + thickness * thickness) * (voxel / SPARSITY_THICKNESS)
    grad.accumulate(rows, d_density, d_density.new_zeros(d_density.shape[0], 0))
    return float(loss)


def views_per_point(c2w: Sequence[np.ndarray], intrinsics: Sequence[Intrinsics], box_min, box_max,
                    samples: int = 4096, seed: int = 0) -> float:
    """How many of the cameras see a point of the box, on average over points drawn uniformly in it (in front of a
    camera and inside its image)."""
    lo, hi = np.asarray(box_min, dtype=np.float64), np.asarray(box_max, dtype=np.float64)
    points = lo + (hi - lo) * np.random.default_rng(seed).random((samples, 3))
    seen = np.zeros(samples)
    for pose, k in zip(c2w, intrinsics):
        uv, depth = project(points, np.asarray(pose, dtype=np.float64), k)
        seen += (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= k.w) & (uv[:, 1] >= 0) & (uv[:, 1] <= k.h)
    return float(seen.mean())


def tv_scale_for_resolution(resolution: int, reference: int) -> float:
    """The TV multiplier of a level at `resolution`: (reference / resolution)^2 above the reference resolution, else
    1 (and always 1 when reference is 0)."""
    if reference <= 0 or resolution <= reference:
        return 1.0
    return (reference / resolution) ** 2


def tv_scale_for_views(views: float, reference_views: float, power: float, most: float) -> float:
    """The TV multiplier for a capture whose points are seen by `views` photos: (reference_views / views)^power, at
    least 1 (captures seen by more photos keep the weights as set) and at most `most`; 1 when reference_views is 0."""
    if reference_views <= 0:
        return 1.0
    return float(min(max((reference_views / max(views, 1e-6)) ** power, 1.0), most))
