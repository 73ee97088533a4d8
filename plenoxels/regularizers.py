"""Total-variation regulariser over a random subset of occupied vertices (see reference.tv_loss)."""
from __future__ import annotations

import torch

from plenoxels import native
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
