"""How much of this machine's memory a fit's grid may take, so a fit never asks for more than is there: a first level
whose every vertex would not fit stops before it starts, and later levels are held to as many voxels as fit (the
tighter of this and fit.voxel_budget)."""
from __future__ import annotations

import math
import os

from plenoxels.core.errors import UserError

# The share of physical memory a fit's grid may take at its peak; the rest is the training photos' pixels and rays,
# the per-thread gradient tables (plenoxels/core/optim.py, at most a quarter), the renders and the system.
GRID_MEMORY_SHARE = 0.5
# Copies of a voxel's row a fit holds at its peak, as measured: the parameters, RMSProp's running mean square, the
# gradient tables, and during an upsampling the old grid's rows beside the new grid's with their optimiser state
# (lego at `paper`, 7.47 M voxels at 512^3 at SH degree 2, peaked at 10.0 GiB, about 1.2 kB a voxel past its photos:
# bench/README.md, "The papers' protocol").
ROW_COPIES = 10


def physical_memory() -> int:
    """Bytes of physical memory on this machine."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def fit_bytes_per_voxel(sh_degree: int) -> int:
    """A voxel's bytes at a fit's peak: its row of density and SH coefficients (float32) in ROW_COPIES copies, and its
    index entries."""
    return (1 + 3 * (sh_degree + 1) ** 2) * 4 * ROW_COPIES + 8


def voxels_that_fit(sh_degree: int, memory: int | None = None) -> int:
    """The most voxels a fit's grid may hold on a machine with `memory` bytes (default: this one's)."""
    memory = physical_memory() if memory is None else memory
    return int(GRID_MEMORY_SHARE * memory // fit_bytes_per_voxel(sh_degree))


def check_dense_level(shape: tuple[int, ...], sh_degree: int, memory: int | None = None) -> None:
    """Stops with what to do when a first level of `shape` (every vertex allocated) would not fit in memory."""
    voxels = math.prod(shape)
    limit = voxels_that_fit(sh_degree, memory)
    if voxels > limit:
        memory = physical_memory() if memory is None else memory
        raise UserError(f"a first level of {'x'.join(map(str, shape))} vertices ({voxels / 1e6:.0f} M, every one "
                        f"allocated until the first prune) needs about {voxels * fit_bytes_per_voxel(sh_degree) / 2**30:.0f} "
                        f"GiB, more than this machine's {memory / 2**30:.0f} GiB allow; start coarser (fit.resolutions "
                        f"beginning at 128, as the presets do) and let later levels grow where the scene is")
