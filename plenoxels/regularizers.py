"""Total-variation regulariser over a random subset of occupied vertices (see reference.tv_loss), and how strong it
needs to be for a capture: few photos far apart leave each point of the scene seen by few of them, and a fit then
memorises the photos (floaters and smears that only a held-out view shows) unless the field is held smoother."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from plenoxels import native
from plenoxels.cameras import Intrinsics, project
from plenoxels.grid import SparseGrid
from plenoxels.optim import GridGrad


def sample_rows(grid: SparseGrid, sample_fraction: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """All rows for a fraction >= 1, else round(fraction * N) rows drawn uniformly (with replacement)."""
    n = grid.num_occupied
    if sample_fraction >= 1.0:
        return torch.arange(n, dtype=torch.int64)
    if sample_fraction <= 0.0 or n == 0:
        return torch.zeros(0, dtype=torch.int64)
    m = max(1, round(sample_fraction * n))
    return torch.randint(n, (m,), generator=generator, dtype=torch.int64)


def tv_loss_and_grad(grid: SparseGrid, grad: GridGrad, weight_density: float, weight_sh: float,
                     sample_fraction: float, generator: torch.Generator | None = None) -> float:
    """TV loss of density and SH over sampled rows; its gradient is added into `grad`."""
    rows = sample_rows(grid, sample_fraction, generator)
    if rows.shape[0] == 0 or (weight_density == 0 and weight_sh == 0):
        return 0.0
    loss, grad.num_touched = native.ops.tv_loss_and_grad(
        grid.data, grid.links, grid.coords(), rows.to(grid.data.device), float(weight_density), float(weight_sh),
        grid.sh_degree, grad.data, grad.touched_mask, grad.touched_rows, grad.num_touched, *grad.scratch())
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


def tv_scale_for_views(views: float, reference_views: float, power: float, most: float) -> float:
    """The TV multiplier for a capture whose points are seen by `views` photos: (reference_views / views)^power, at
    least 1 (captures seen by more photos keep the weights as set) and at most `most`; 1 when reference_views is 0."""
    if reference_views <= 0:
        return 1.0
    return float(min(max((reference_views / max(views, 1e-6)) ** power, 1.0), most))
