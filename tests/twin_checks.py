"""Checks of the native kernels against their PyTorch twin that more than one test file makes."""
import pytest
import torch

from plenoxels.core import reference
from plenoxels.core.optim import GridGrad
from plenoxels.core.render import RenderOptions, loss_and_grad, render


def assert_loss_and_grad_match_twin(grid, origins, dirs, targets, background, opts, near_gradient: float = 0.0,
                                    past_grid_only: bool = False) -> tuple[GridGrad, GridGrad]:
    """One batch's fused loss and gradient, native against the twin: the mse, d(mse)/d(background), the touched rows
    and the gradient rows. Returns both gradient stores (native, twin), to add more batches to."""
    native, twin = GridGrad(grid), GridGrad(grid)
    mse_n, gbg_n = loss_and_grad(grid, origins, dirs, targets, background, opts, native, near_gradient, past_grid_only)
    mse_t, gbg_t = reference.loss_and_grad(grid, origins, dirs, targets, background, opts, twin, near_gradient,
                                           past_grid_only)
    assert mse_n == pytest.approx(mse_t, rel=1e-5)
    torch.testing.assert_close(gbg_n, gbg_t, atol=1e-8, rtol=1e-4)
    assert native.num_touched > 0
    assert set(native.touched().tolist()) == set(twin.touched().tolist())
    scale = float(twin.data.abs().max())
    torch.testing.assert_close(native.data, twin.data, atol=1e-5 * scale, rtol=1e-4)
    return native, twin


def assert_render_matches_twin(grid, origins, dirs, seed: int) -> None:
    """rgb, depth and opacity of one batch before a random background, native against the twin, on rays that composite
    for real (neither all clear nor all opaque)."""
    background = torch.rand(origins.shape[0], 3, generator=torch.Generator().manual_seed(seed))
    opts = RenderOptions(step_size=0.4, sigma_threshold=0.05)
    native = render(grid, origins, dirs, background, opts)
    with torch.no_grad():
        rgb, depth, opacity = reference.render(grid, origins, dirs, background, opts)
    assert 0.05 < float(native.opacity.mean()) < 0.999
    torch.testing.assert_close(native.rgb, rgb, atol=2e-5, rtol=1e-5)
    torch.testing.assert_close(native.depth, depth, atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(native.opacity, opacity, atol=2e-5, rtol=1e-5)
