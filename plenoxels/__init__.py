"""The Plenoxels model: sparse voxel grid, volume rendering, sparse RMSProp and TV.

The native C++/OpenMP kernels (plenoxels._C, built by `make install`) do the work; reference.py is
their PyTorch twin.
"""
from plenoxels.grid import SparseGrid
from plenoxels.optim import GridGrad, SparseRMSProp
from plenoxels.regularizers import tv_loss_and_grad
from plenoxels.render import RenderOptions, RenderResult, loss_and_grad, max_weights, native_available

# `render` stays in plenoxels.render only: re-exporting it here would shadow the submodule.
__all__ = ["SparseGrid", "GridGrad", "SparseRMSProp", "RenderOptions", "RenderResult", "loss_and_grad",
           "max_weights", "tv_loss_and_grad", "native_available"]
