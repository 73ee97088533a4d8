"""Sparse gradients and the sparse RMSProp optimiser of the grid.

Gradients are kept in one persistent table shaped like the grid's packed parameters, with a record of
the rows touched since the last optimiser step. A step updates and clears only those rows, so no step
ever zeroes or scans the whole grid.
"""
from __future__ import annotations

import math

import torch

from plenoxels.core import native
from plenoxels.core.grid import OCCUPANCY_BLOCK, SparseGrid, large_rows, large_zeros, sh_count
from plenoxels.core.memory import usable_memory


# The share of usable memory (plenoxels/core/memory.py) the per-thread gradient tables may take together. Each thread past the first adds a
# table the size of the grid's (random rays touch every page of it within a few batches), so on many cores a fine
# grid would otherwise take a table per core: 15 x 1.5 GB for 12 M voxels on 16 cores.
SCRATCH_MEMORY_SHARE = 0.25


def scratch_slots(table_bytes: int, memory: int | None = None) -> int:
    """How many per-thread copies of a gradient table of `table_bytes` (with its mask) fit in SCRATCH_MEMORY_SHARE
    of `memory` (default: what this process may use); the kernels that add gradient use one thread per copy, plus one."""
    memory = usable_memory() if memory is None else memory
    return int(SCRATCH_MEMORY_SHARE * memory // max(table_bytes, 1))


class GridGrad:
    """d(loss)/d(parameters) of one grid, plus which rows were touched since the last clear."""

    def __init__(self, grid: SparseGrid):
        n = grid.num_occupied
        self.sh_degree = grid.sh_degree
        self.data = large_zeros(grid.data)
        self.touched_mask = torch.zeros(n, dtype=torch.uint8, device=grid.data.device)
        self.touched_rows = torch.zeros(n, dtype=torch.int32, device=grid.data.device)
        self.num_touched = 0
        self._scratch = None

    @property
    def density(self) -> torch.Tensor:
        return self.data[:, 0]

    @property
    def sh(self) -> torch.Tensor:
        return self.data[:, 1 : 1 + 3 * sh_count(self.sh_degree)]

    def touched(self) -> torch.Tensor:
        """int64 rows touched since the last clear, in first-touch order."""
        return self.touched_rows[: self.num_touched].long()

    def scratch(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The CPU kernels' per-thread gradient buffers and touched masks (allocated once, pages mapped on first
        touch; the masks are clear between calls, and a kernel zeroes a buffer row when its thread first touches it),
        as many as scratch_slots allows; empty on a GPU."""
        if self._scratch is None:
            table = self.data.numel() * self.data.element_size() + self.touched_mask.numel()
            self._scratch = tuple(native.ops.grad_scratch(self.data, scratch_slots(table)))
        return self._scratch

    def threads(self) -> tuple[int, int]:
        """(threads the CPU kernels add this table's gradients on: its scratch slots plus one, threads they have)."""
        return min(self.scratch()[0].shape[0] + 1, native.ops.num_threads()), native.ops.num_threads()

    def accumulate(self, rows: torch.Tensor, density: torch.Tensor, sh: torch.Tensor) -> None:
        """Adds gradients for distinct rows (the PyTorch path) and records them as touched."""
        rows = rows.long()
        self.data[rows, 0] += density
        self.data[rows, 1 : 1 + sh.shape[1]] += sh
        new = rows[self.touched_mask[rows] == 0]
        self.touched_mask[new] = 1
        self.touched_rows[self.num_touched : self.num_touched + new.shape[0]] = new.to(torch.int32)
        self.num_touched += new.shape[0]

    def clear(self) -> None:
        rows = self.touched()
        self.data.index_fill_(0, rows, 0.0)
        self.touched_mask.index_fill_(0, rows, 0)
        self.num_touched = 0


class SparseRMSProp:
    """RMSProp on touched rows only: v = beta v + (1 - beta) g^2; p -= lr g / (sqrt(v) + eps).

    A row's second moment decays only when the row is touched. Density and SH have their own rates.
    """

    def __init__(self, grid: SparseGrid, lr_density: float, lr_sh: float, beta: float = 0.95, eps: float = 1e-8):
        if not 0.0 <= beta < 1.0:
            raise ValueError(f"beta must be in [0, 1), got {beta}")
        if eps <= 0.0:
            raise ValueError(f"eps must be > 0, got {eps}")
        self.grid = grid
        self.lr_density, self.lr_sh = float(lr_density), float(lr_sh)
        self.beta, self.eps = float(beta), float(eps)
        self.second_moment = large_zeros(grid.data)

    def set_lr(self, lr_density: float | None = None, lr_sh: float | None = None) -> None:
        if lr_density is not None:
            self.lr_density = float(lr_density)
        if lr_sh is not None:
            self.lr_sh = float(lr_sh)

    def step(self, grad: GridGrad) -> None:
        """Updates the rows `grad` touched, then clears them from `grad`."""
        if grad.data.shape != self.grid.data.shape:
            raise ValueError("gradient storage belongs to another grid: make a new GridGrad after prune/upsample")
        columns = 1 + 3 * sh_count(self.grid.sh_degree)
        live = (None, OCCUPANCY_BLOCK, None, None)
        if self.grid.live_blocks_current():
            counts, blocks = self.grid.live_blocks()
            live = (self.grid.coords(), OCCUPANCY_BLOCK, counts, blocks)
        native.ops.rmsprop_step(
            self.grid.data, self.second_moment, grad.data, grad.touched_mask, grad.touched_rows, grad.num_touched,
            columns, self.lr_density, self.lr_sh, self.beta, self.eps, *live)
        grad.num_touched = 0

    def remap(self, new_grid: SparseGrid, old_rows: torch.Tensor) -> None:
        """Carries the state to a grid from prune/upsample: new row i takes old row old_rows[i]
        (-1: fresh state)."""
        old_rows = old_rows.long()
        if old_rows.shape[0] != new_grid.num_occupied:
            raise ValueError("old_rows must have one entry per row of the new grid")
        if self.second_moment.shape[0] == 0:
            state = large_zeros(new_grid.data)
        else:  # gathered straight into its table, with no second table beside it
            state = large_rows(self.second_moment, old_rows.clamp_min(0))
            state[old_rows < 0] = 0.0
        self.second_moment = state
        self.grid = new_grid

    def state_dict(self) -> dict:
        return {"lr_density": self.lr_density, "lr_sh": self.lr_sh, "beta": self.beta, "eps": self.eps,
                "second_moment": self.second_moment}

    def load_state_dict(self, state: dict) -> None:
        if state["second_moment"].shape != self.grid.data.shape:
            raise ValueError("optimiser state does not match the grid it is loaded for")
        self.lr_density, self.lr_sh = state["lr_density"], state["lr_sh"]
        self.beta, self.eps = state["beta"], state["eps"]
        self.second_moment = state["second_moment"].to(self.grid.data.device).clone()


def decayed_lr(initial: float, final: float, progress: float, delay: float = 0.0) -> float:
    """Exponential (log-linear) decay from `initial` to `final` as progress goes 0 -> 1; with a delay,
    the rate first ramps up from 1% along a quarter sine (as svox2 does)."""
    progress = min(max(progress, 0.0), 1.0)
    rate = math.exp(math.log(initial) * (1 - progress) + math.log(final) * progress)
    if delay > 0:
        rate *= 0.01 + 0.99 * math.sin(0.5 * math.pi * min(progress / delay, 1.0))
    return rate


def density_rate_scale(resolution: int, reference: int) -> float:
    """What a level at `resolution` multiplies the density's rates by: resolution / reference above the reference
    resolution, else 1 (and always 1 when reference is 0). The density that makes a cell opaque in one step through
    it grows as the cell shrinks (optical depth is density times distance), while RMSProp steps it by about its rate."""
    return resolution / reference if 0 < reference < resolution else 1.0
