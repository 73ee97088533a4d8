"""Builds the native core `plenoxels._C` (metadata lives in pyproject.toml).

    python setup.py build_ext --inplace          # what `make install` runs
    pip install --no-build-isolation -e .

The operators are declared once (csrc/ops.cpp, torch.ops.voxfield); the C++/OpenMP kernels that
implement them for CPU tensors are always built, tuned for the machine that builds them
(-march=native; the extension is never shipped to another machine). The CUDA implementations
(csrc/*.cu and bindings_cuda.cpp) are added only when torch has CUDA, a CUDA toolkit is found and
such files exist; otherwise the build is CPU-only.
"""
import os
from pathlib import Path

from setuptools import setup
from torch.utils import cpp_extension

ROOT = Path(__file__).resolve().parent
CSRC = ROOT / "csrc"

cpp_sources = sorted(str(p.relative_to(ROOT)) for p in CSRC.glob("*.cpp"))
cuda_sources = sorted(str(p.relative_to(ROOT)) for p in CSRC.glob("*.cu"))
cxx_flags = ["-O3", "-march=native", "-fopenmp", "-std=c++20"]

import torch  # noqa: E402  (after the path set-up above, kept next to its only use)

# Machine code for A100 (sm_80) and H100/H200 (sm_90), plus sm_90 PTX that newer GPUs compile at load
# time; TORCH_CUDA_ARCH_LIST, when set, replaces this list (torch then adds the flags itself).
cuda_arch_flags = [] if os.environ.get("TORCH_CUDA_ARCH_LIST") else [
    "-gencode=arch=compute_80,code=sm_80",
    "-gencode=arch=compute_90,code=sm_90",
    "-gencode=arch=compute_90,code=compute_90",
]
use_cuda = bool(torch.version.cuda) and cpp_extension.CUDA_HOME is not None and bool(cuda_sources)
if use_cuda:
    extension = cpp_extension.CUDAExtension(
        "plenoxels._C",
        cpp_sources + cuda_sources,
        include_dirs=[str(CSRC)],
        define_macros=[("PLX_WITH_CUDA", "1")],
        extra_compile_args={"cxx": cxx_flags, "nvcc": ["-O3", "-std=c++20", *cuda_arch_flags]},
        extra_link_args=["-lgomp"],
    )
else:
    extension = cpp_extension.CppExtension(
        "plenoxels._C",
        cpp_sources,
        include_dirs=[str(CSRC)],
        extra_compile_args=cxx_flags,
        extra_link_args=["-lgomp"],
    )

setup(
    ext_modules=[extension],
    cmdclass={"build_ext": cpp_extension.BuildExtension.with_options(use_ninja=True)},
)
