"""Volume rendering of a SparseGrid: forward, fused loss+gradient, and max weights for pruning.

`backend="native"` (the product) runs the C++/OpenMP kernels in plenoxels._C and fails at once with
a one-line message when they are not built; `backend="torch"` runs the PyTorch twin in
plenoxels/reference.py (tests and benchmarks only). The math is stated in reference.py.

Rays arrive in the fit frame. Directions need not be unit length: t, `near` and depth are fit-frame
distances along the normalised direction. Density is integrated per fit-frame unit of distance while
samples are spaced `step_size` voxels apart in grid coordinates, so anisotropic boxes work.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from plenoxels.errors import UserError
from plenoxels.grid import OCCUPANCY_BLOCK, SparseGrid
from plenoxels.optim import GridGrad

_native = None


def native_core(device: torch.device | None = None):
    """The compiled kernels, or a UserError saying how to build them. For a CUDA device: the CUDA
    kernels behind the same interface (plenoxels/device.py)."""
    global _native
    if device is not None and device.type == "cuda":  # CUDA hook (owner: CUDA core, plenoxels/device.py)
        from plenoxels.device import cuda_core

        return cuda_core()
    if _native is None:
        try:
            from plenoxels import _C
        except ImportError as exc:
            raise UserError(f"native core not built: run `make install` ({exc})") from exc
        _native = _C
    return _native


def native_available() -> bool:
    try:
        native_core()
    except UserError:
        return False
    return True


@dataclass
class RenderOptions:
    step_size: float = 0.5  # sample spacing in voxels (grid-coordinate units)
    stop_transmittance: float = 1e-4  # early ray termination
    near: float = 0.0  # ray t start (fit-frame units); rays are also clipped to the grid box
    sigma_threshold: float = 0.0  # samples with density <= this are skipped
    max_samples_per_ray: int = 4096  # a finer step is widened so that no ray takes more samples

    def check(self) -> "RenderOptions":
        if not self.step_size > 0:
            raise UserError(f"step_size must be > 0 voxels, got {self.step_size}")
        if not 0 <= self.stop_transmittance <= 1:
            raise UserError(f"stop_transmittance must be in [0, 1], got {self.stop_transmittance}")
        if not self.sigma_threshold >= 0:
            raise UserError(f"sigma_threshold must be >= 0, got {self.sigma_threshold}")
        if not self.max_samples_per_ray >= 1:
            raise UserError(f"max_samples_per_ray must be >= 1, got {self.max_samples_per_ray}")
        if self.near != self.near:
            raise UserError("near must be a number")
        return self


@dataclass
class RenderResult:
    rgb: torch.Tensor  # [B, 3]
    depth: torch.Tensor  # [B] expected termination distance (fit-frame units), weights not renormalised
    opacity: torch.Tensor  # [B] 1 - final transmittance


def _rays(origins: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    origins = origins.detach().to(torch.float32).reshape(-1, 3).contiguous()
    dirs = dirs.detach().to(torch.float32).reshape(-1, 3).contiguous()
    if origins.shape != dirs.shape:
        raise ValueError(f"origins {tuple(origins.shape)} and dirs {tuple(dirs.shape)} must both be [B, 3]")
    if dirs.shape[0] and not bool((dirs.abs().amax(dim=1) > 0).all()):
        raise ValueError("ray directions must be non-zero")
    return origins, dirs


def _colours(x: torch.Tensor | None, b: int, name: str) -> torch.Tensor | None:
    if x is None:
        return None
    x = x.detach().to(torch.float32).reshape(-1, 3).contiguous()
    if x.shape[0] != b:
        raise ValueError(f"{name} must be [B, 3] with B = {b}, got {tuple(x.shape)}")
    return x


def _native_args(grid: SparseGrid) -> tuple:
    cells, blocks = grid.occupancy()
    return (grid.data, grid.links, cells, blocks, OCCUPANCY_BLOCK, list(grid.bbox_min), list(grid.bbox_max),
            grid.sh_degree)


def _march_args(opts: RenderOptions) -> tuple:
    return (float(opts.step_size), float(opts.stop_transmittance), float(opts.near), float(opts.sigma_threshold),
            int(opts.max_samples_per_ray))


def _check_backend(backend: str) -> None:
    if backend not in ("native", "torch"):
        raise ValueError(f"backend must be 'native' or 'torch', got {backend!r}")
    if backend == "native":
        native_core()


def render(grid: SparseGrid, origins, dirs, background=None, opts: RenderOptions | None = None,
           backend: str = "native") -> RenderResult:
    """rgb = sum_i T_i a_i c_i + T_final * background (None: black)."""
    opts = (opts or RenderOptions()).check()
    _check_backend(backend)
    origins, dirs = _rays(origins, dirs)
    background = _colours(background, origins.shape[0], "background")
    if backend == "torch":
        from plenoxels import reference

        with torch.no_grad():
            rgb, depth, opacity = reference.render(grid, origins, dirs, background, opts)
        return RenderResult(rgb, depth, opacity)
    rgb, depth, opacity = native_core(grid.data.device).render(*_native_args(grid), origins, dirs, background, *_march_args(opts))
    return RenderResult(rgb, depth, opacity)


def loss_and_grad(grid: SparseGrid, origins, dirs, targets, background, opts: RenderOptions | None,
                  grad: GridGrad, backend: str = "native") -> tuple[float, torch.Tensor]:
    """Mean squared error over the B*3 colour values, forward and backward in one pass.

    Adds d(mse)/d(density) and d(mse)/d(sh) into `grad` for the rows the batch touched, and returns
    (mse, d(mse)/d(background) [B, 3]).
    """
    opts = (opts or RenderOptions()).check()
    _check_backend(backend)
    origins, dirs = _rays(origins, dirs)
    b = origins.shape[0]
    targets = _colours(targets, b, "targets")
    background = _colours(background, b, "background")
    if background is None:
        background = torch.zeros(b, 3)
    if grad.data.shape != grid.data.shape:
        raise ValueError("gradient storage belongs to another grid: make a new GridGrad after prune/upsample")
    if backend == "torch":
        from plenoxels import reference

        return reference.loss_and_grad(grid, origins, dirs, targets, background, opts, grad)
    sse, grad_background, grad.num_touched = native_core(grid.data.device).loss_and_grad(
        *_native_args(grid), origins, dirs, targets, background, *_march_args(opts), grad.data, grad.touched_mask,
        grad.touched_rows, grad.num_touched, grad.thread_buffers())
    return (sse / (3 * b) if b else 0.0), grad_background


def max_weights(grid: SparseGrid, origins, dirs, opts: RenderOptions | None = None,
                backend: str = "native") -> torch.Tensor:
    """Per occupied row, the largest rendering weight of a sample that reads it over these rays."""
    opts = (opts or RenderOptions()).check()
    _check_backend(backend)
    origins, dirs = _rays(origins, dirs)
    if backend == "torch":
        from plenoxels import reference

        return reference.max_weights(grid, origins, dirs, opts)
    out = torch.zeros(grid.num_occupied, dtype=torch.float32, device=grid.data.device)
    return native_core(grid.data.device).max_weights(*_native_args(grid), origins, dirs, *_march_args(opts), out)


def sample_counts(grid: SparseGrid, origins, dirs, opts: RenderOptions | None = None) -> tuple[int, int]:
    """(lattice samples inside the box, samples that contribute) over these rays, from the native core."""
    opts = (opts or RenderOptions()).check()
    origins, dirs = _rays(origins, dirs)
    lattice, used = native_core(grid.data.device).sample_counts(*_native_args(grid), origins, dirs, *_march_args(opts))
    return int(lattice), int(used)
