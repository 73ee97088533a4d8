"""Checks of the native kernels against their PyTorch twin that more than one test file makes."""
import pytest
import torch

from plenoxels.core import reference
from plenoxels.core.optim import GridGrad
from plenoxels.core.render import loss_and_grad


def assert_loss_and_grad_match_twin(grid, origins, dirs, targets, background, opts) -> tuple[GridGrad, GridGrad]:
    """One batch's fused loss and gradient, native against the twin: the mse, d(mse)/d(background), the touched rows
    and the gradient rows. Returns both gradient stores (native, twin), to add more batches to."""
    native, twin = GridGrad(grid), GridGrad(grid)
    mse_n, gbg_n = loss_and_grad(grid, origins, dirs, targets, background, opts, native)
    mse_t, gbg_t = reference.loss_and_grad(grid, origins, dirs, targets, background, opts, twin)
    assert mse_n == pytest.approx(mse_t, rel=1e-5)
    torch.testing.assert_close(gbg_n, gbg_t, atol=1e-8, rtol=1e-4)
    assert native.num_touched > 0
    assert set(native.touched().tolist()) == set(twin.touched().tolist())
    scale = float(twin.data.abs().max())
    torch.testing.assert_close(native.data, twin.data, atol=1e-5 * scale, rtol=1e-4)
    return native, twin
