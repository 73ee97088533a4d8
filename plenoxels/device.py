"""Which device the Plenoxels core runs on: `fit.device` = auto, cpu or cuda.

CUDA needs two things: an NVIDIA GPU that torch can see, and a native extension built with the
CUDA kernels (setup.py adds them only where torch has CUDA and nvcc exists). Those kernels register
as torch operators `torch.ops.plenoxels_cuda.*` when `plenoxels._C` is imported.
"""
from __future__ import annotations

import functools
import warnings

import torch

from plenoxels.errors import UserError

CHOICES = ("auto", "cpu", "cuda")
CUDA_MISSING = "fit.device=cuda but no CUDA GPU/CUDA build is available; use fit.device=cpu or auto"


@functools.lru_cache(maxsize=1)
def cuda_kernels_built() -> bool:
    """True when plenoxels._C was built with the CUDA kernels."""
    try:
        import plenoxels._C  # noqa: F401  (importing registers the torch operators)
    except ImportError:
        return False
    try:
        torch.ops.plenoxels_cuda.render
    except (AttributeError, RuntimeError):
        return False
    return True


def cuda_ready() -> bool:
    """True when the CUDA core can run here: a visible GPU and the CUDA kernels built."""
    return torch.cuda.is_available() and cuda_kernels_built()


def resolve_device(choice: str) -> torch.device:
    """The torch device for a `fit.device` setting; `cuda` without a GPU or CUDA build is a UserError."""
    if choice not in CHOICES:
        raise UserError(f"fit.device must be one of {', '.join(CHOICES)}; got {choice!r}")
    if choice == "cpu":
        return torch.device("cpu")
    if cuda_ready():
        return torch.device("cuda", torch.cuda.current_device())
    if choice == "cuda":
        raise UserError(CUDA_MISSING)
    if torch.cuda.is_available():
        warnings.warn(
            "an NVIDIA GPU is present but plenoxels._C was built without CUDA kernels (nvcc not found when it "
            "was built?); fitting on the CPU. Rebuild with `python setup.py build_ext --inplace` to use the GPU",
            stacklevel=2,
        )
    return torch.device("cpu")


class CudaCore:
    """The interface of plenoxels._C, served by the CUDA kernels, for grids whose tensors are on a GPU.

    Arguments are those of the CPU functions. Read-only per-ray inputs (origins, dirs, targets,
    background, TV sample rows) may come from the CPU and are moved to the grid's device; tensors
    the kernels write (gradients, touched rows, outputs) must already be there. The CPU's per-thread
    scratch argument is accepted and ignored: the GPU kernels accumulate with atomics.
    """

    # Per kernel: positions of the inputs that may be moved, and the position of the CPU's scratch
    # argument (None: it has none).
    KERNELS = {
        "render": ((8, 9, 10), None),
        "loss_and_grad": ((8, 9, 10, 11), 21),
        "max_weights": ((8, 9), None),
        "sample_counts": ((8, 9), None),
        "tv_loss_and_grad": ((2, 3), 11),
        "build_occupancy": ((), None),
        "count_live_blocks": ((), None),
        "row_coords": ((), None),
        "rmsprop_step": ((), None),  # a method below: its `live` argument is unpacked
    }
    # Device-free helpers of plenoxels._C, served by it (advise_huge_pages acts on host memory only).
    CPU_HELPERS = ("padded_stride", "num_threads", "advise_huge_pages")

    def __init__(self):
        if not cuda_kernels_built():
            raise UserError(CUDA_MISSING)
        import plenoxels._C as cpu_core

        self._cpu_core = cpu_core
        self._ops = torch.ops.plenoxels_cuda

    @staticmethod
    def ThreadGrads(rows: int, stride: int) -> None:  # noqa: N802  (mirrors the CPU class name)
        """No per-thread buffers on the GPU."""
        return None

    def rmsprop_step(self, *args, live=None):
        """As the CPU's: `live` = (coords, block, counts, blocks) keeps the live-block counts in step."""
        if len(args) == 12:
            *args, live = args
        coords, block, counts, blocks = live if live is not None else (None, 0, None, None)
        return self._ops.rmsprop_step(*args, coords, block, counts, blocks)

    def __getattr__(self, name):
        if name.startswith("_"):
            raise AttributeError(name)
        if name in self.CPU_HELPERS:
            return getattr(self._cpu_core, name)
        if name not in self.KERNELS:
            raise AttributeError(f"the CUDA core has no kernel {name!r}: add it to csrc/kernels_cuda.cu and CudaCore")
        movable, scratch = self.KERNELS[name]
        op = getattr(self._ops, name)

        def call(*args):
            args = list(args[:scratch] if scratch is not None else args)
            device = args[0].device
            for i in movable:
                if isinstance(args[i], torch.Tensor) and args[i].device != device:
                    args[i] = args[i].to(device, non_blocking=True)
            return op(*args)

        call.__name__ = name
        return call


@functools.lru_cache(maxsize=1)
def cuda_core() -> CudaCore:
    """The CUDA kernels behind plenoxels._C's interface; a UserError when they are not built."""
    return CudaCore()
