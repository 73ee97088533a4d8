"""The compiled Plenoxels core, loaded in this one place, and the device it runs on.

`plenoxels._C` (built from csrc/ by `make install`) registers the operators torch.ops.voxfield.*: one
schema (csrc/ops.cpp) with a C++/OpenMP implementation and, in a CUDA build, a CUDA one; torch's
dispatcher picks the implementation from the device of the tensors passed in. Importing this module
never fails: without a build, the first use of `ops` raises a UserError saying how to build it.
"""
from __future__ import annotations

import functools
import warnings

import torch

from plenoxels.core.errors import UserError

try:
    from .. import _C  # noqa: F401  (loading the library registers torch.ops.voxfield)
except ImportError as exc:
    _LOAD_ERROR: ImportError | None = exc
else:
    _LOAD_ERROR = None

DEVICE_CHOICES = ("auto", "cpu", "cuda")
CUDA_MISSING = "fit.device=cuda but no CUDA GPU/CUDA build is available; use fit.device=cpu or auto"


class _Ops:
    """torch.ops.voxfield, or a UserError at first use when the core is not built."""

    def __getattr__(self, name: str):
        if _LOAD_ERROR is not None:
            raise UserError(f"native core not built: run `make install` ({_LOAD_ERROR})")
        return getattr(torch.ops.voxfield, name)


ops = _Ops()


@functools.lru_cache(maxsize=4)
def row_stride(sh_degree: int) -> int:
    """Floats per packed grid row for an SH degree: 1 + 3K rounded as csrc/plenoxels_math.h defines."""
    return int(ops.padded_stride(1 + 3 * (sh_degree + 1) ** 2))


def num_threads() -> int:
    """OpenMP threads the CPU kernels use."""
    return int(ops.num_threads())


@functools.lru_cache(maxsize=1)
def cuda_kernels_built() -> bool:
    """True when plenoxels._C was built with the CUDA kernels."""
    if _LOAD_ERROR is not None:
        return False
    return torch._C._dispatch_has_kernel_for_dispatch_key("voxfield::render", "CUDA")


def cuda_ready() -> bool:
    """True when the CUDA core can run here: a visible GPU and the CUDA kernels built."""
    return torch.cuda.is_available() and cuda_kernels_built()


def check_device(device: torch.device) -> None:
    """A UserError when tensors on `device` have no kernels to run them."""
    if device.type == "cuda" and not cuda_kernels_built():
        raise UserError(CUDA_MISSING)
    if device.type not in ("cpu", "cuda"):
        raise UserError(f"the Plenoxels core runs on cpu or cuda, not {device.type}")


def resolve_device(choice: str) -> torch.device:
    """The torch device for a `fit.device` setting; `cuda` without a GPU or CUDA build is a UserError."""
    if choice not in DEVICE_CHOICES:
        raise UserError(f"fit.device must be one of {', '.join(DEVICE_CHOICES)}; got {choice!r}")
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
