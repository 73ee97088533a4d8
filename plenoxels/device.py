"""Which device the Plenoxels core runs on: `fit.device` = auto, cpu or cuda.

CUDA needs two things: an NVIDIA GPU that torch can see, and a native extension built with the
CUDA kernels (setup.py adds them only where torch has CUDA and nvcc exists). Those kernels register
as torch operators `torch.ops.plenoxels_cuda.*` when `plenoxels._C` is imported.
"""
from __future__ import annotations

import functools
import warnings

import torch

from pipeline.errors import UserError

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

