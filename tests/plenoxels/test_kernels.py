"""The native kernels against their PyTorch twin (values and gradients), and the twin against autograd."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from plenoxels.core import native
from plenoxels.core import reference
from plenoxels.core.cameras import Intrinsics, look_at
from plenoxels.core.grid import SparseGrid
from plenoxels.core.grid import OCCUPANCY_BLOCK
from plenoxels.core.optim import GridGrad, SparseRMSProp
from plenoxels.core import regularizers
from plenoxels.core.regularizers import (SAMPLE_RUN_ROWS, SPARSITY_THICKNESS, sample_rows, sparsity_loss_and_grad,
                                         tv_loss_and_grad)
from plenoxels.core.render import RenderOptions
from plenoxels.core.render import COLOUR_OFFSET, SH_C0, light_past_grid, loss_and_grad, max_weights, ray_samples, render
from plenoxels.core.render import sample_counts
from plenoxels.core.ray_set import COHERENT_EXTENT, RaySet, torch_pixel_rays
from twin_checks import assert_loss_and_grad_match_twin, assert_render_matches_twin

ATOL = 2e-5
REPO = Path(__file__).resolve().parents[2]


def random_grid(res=(9, 7, 11), sh_degree=2, holes=0.3, seed=0, box=((-1.0, -1.0, -1.0), (1.0, 1.0, 1.5))):
    """A grid with random values and a fraction of its vertices unallocated (an anisotropic box)."""
    gen = torch.Generator().manual_seed(seed)
    grid = SparseGrid.dense(res, box[0], box[1], sh_degree)
    grid.density.copy_(torch.rand(grid.num_occupied, generator=gen) * 6 - 1)
    grid.sh.copy_(torch.randn(grid.sh.shape, generator=gen) * 0.4)
    if holes > 0:
        grid, _ = grid.prune(torch.rand(grid.num_occupied, generator=gen) >= holes)
    return grid


def random_rays(n=96, seed=1, spread=3.0):
    """Rays from a shell around the box towards points near its centre; some miss."""
    gen = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=gen)
    origins = origins / origins.norm(dim=1, keepdim=True) * spread
    targets = torch.randn(n, 3, generator=gen) * 0.7
    return origins, targets - origins


def twin_render(grid, origins, dirs, background=None, opts=None):
    """The PyTorch twin's (rgb, depth, opacity), without autograd."""
    with torch.no_grad():
        return reference.render(grid, origins, dirs, background, opts or RenderOptions())


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_render_native_matches_twin(sh_degree):
    grid = random_grid(sh_degree=sh_degree, seed=sh_degree)
    assert_render_matches_twin(grid, *random_rays(seed=10 + sh_degree), seed=3)


def test_render_without_background_is_black_behind():
    grid = random_grid()
    origins, dirs = random_rays()
    black = render(grid, origins, dirs, None)
    white = render(grid, origins, dirs, torch.ones(origins.shape[0], 3))
    torch.testing.assert_close(white.rgb - black.rgb, (1 - black.opacity)[:, None].expand(-1, 3), atol=1e-6, rtol=0)


def test_a_background_past_the_grid_only_shows_nothing_behind_a_stopped_ray_which_keeps_its_opacity():
    grid = random_grid(seed=13)
    origins, dirs = random_rays(n=200, seed=14)
    stop = 0.05
    opts = RenderOptions(step_size=0.4, stop_transmittance=stop)
    black = render(grid, origins, dirs, None, opts, past_grid_only=True)
    white = render(grid, origins, dirs, torch.ones(origins.shape[0], 3), opts, past_grid_only=True)
    everywhere = render(grid, origins, dirs, torch.ones(origins.shape[0], 3), opts)
    left = 1 - black.opacity
    stopped, ramp = left < stop, (left >= stop) & (left < 2 * stop)
    assert 10 < int(stopped.sum()) < 190 and bool((left > 0.8).any()) and int(ramp.sum()) >= 3
    assert bool((left[stopped] > 0).all())                    # the opacity is what the samples took, short of 1
    assert torch.equal(white.rgb[stopped], black.rgb[stopped])
    assert torch.equal(white.opacity, everywhere.opacity) and bool((everywhere.rgb[stopped] > white.rgb[stopped]).all())
    shown = (white.rgb - black.rgb)[:, 0]
    torch.testing.assert_close(shown, light_past_grid(left, stop), atol=1e-6, rtol=0)
    assert bool((shown[ramp] < left[ramp]).all()) and bool((shown[ramp] > 0).all())  # the ramp up to the stop
    with torch.no_grad():
        rgb, _, opacity = reference.render(grid, origins, dirs, torch.ones(origins.shape[0], 3), opts,
                                           past_grid_only=True)
    torch.testing.assert_close(white.rgb, rgb, atol=ATOL, rtol=1e-5)
    torch.testing.assert_close(white.opacity, opacity, atol=ATOL, rtol=1e-5)
    gen = torch.Generator().manual_seed(15)
    targets, background = torch.rand(200, 3, generator=gen), torch.rand(200, 3, generator=gen)
    _, grad_background = loss_and_grad(grid, origins, dirs, targets, background, opts, GridGrad(grid),
                                       past_grid_only=True)
    assert not bool(grad_background[stopped].any()) and bool(grad_background[~stopped].any())
    # The density's gradient on the ramp (the background's share answering it at its own rate) against autograd.
    assert_loss_and_grad_match_twin(grid, origins[ramp], dirs[ramp], targets[ramp], background[ramp], opts,
                                    past_grid_only=True)
    assert_loss_and_grad_match_twin(grid, origins, dirs, targets, background, opts, past_grid_only=True)


@pytest.mark.parametrize("sh_degree", [0, 2, 3])
def test_loss_and_grad_native_matches_twin(sh_degree):
    grid = random_grid(sh_degree=sh_degree, seed=5 + sh_degree)
    origins, dirs = random_rays(seed=20 + sh_degree)
    gen = torch.Generator().manual_seed(4)
    targets = torch.rand(origins.shape[0], 3, generator=gen)
    background = torch.rand(origins.shape[0], 3, generator=gen)
    opts = RenderOptions(step_size=0.6)
    native, twin = assert_loss_and_grad_match_twin(grid, origins, dirs, targets, background, opts)
    scale = float(twin.data.abs().max())
    # Gradients accumulate across calls; the touched set is the union.
    origins2, dirs2 = random_rays(n=32, seed=99)
    loss_and_grad(grid, origins2, dirs2, targets[:32], background[:32], opts, native)
    reference.loss_and_grad(grid, origins2, dirs2, targets[:32], background[:32], opts, twin)
    assert set(native.touched().tolist()) == set(twin.touched().tolist())
    torch.testing.assert_close(native.data, twin.data, atol=1e-5 * scale, rtol=1e-4)
    untouched = native.touched_mask == 0
    assert bool((native.data[untouched] == 0).all())


@pytest.mark.parametrize("sh_degree", [0, 2])
def test_a_floor_target_is_wrong_only_below_it_natively_as_in_the_twin(sh_degree):
    grid = random_grid(sh_degree=sh_degree, seed=60 + sh_degree, holes=0.1)
    origins, dirs = random_rays(n=200, seed=61)
    gen = torch.Generator().manual_seed(62)
    background = torch.rand(origins.shape[0], 3, generator=gen)
    opts = RenderOptions(step_size=0.6)
    rgb = render(grid, origins, dirs, background, opts).rgb
    floors = torch.rand(origins.shape[0], 3, generator=gen) < 0.4
    plain = torch.rand(origins.shape[0], 3, generator=gen)
    below, above = (rgb - 0.05).clamp(min=1e-3), rgb + 0.05
    assert bool(((rgb > 0.06) & floors).any())
    # Floors the render passes cost nothing: the loss and gradient of the other values alone.
    passed = torch.where(floors, -below, plain)
    native, _ = assert_loss_and_grad_match_twin(grid, origins, dirs, passed, background, opts)
    alone, _ = assert_loss_and_grad_match_twin(grid, origins, dirs, torch.where(floors, rgb, plain), background, opts)
    torch.testing.assert_close(native.data, alone.data, atol=1e-6 * float(alone.data.abs().max()), rtol=1e-5)
    # Floors above the render are targets at their value.
    short = torch.where(floors, -above, plain)
    native, _ = assert_loss_and_grad_match_twin(grid, origins, dirs, short, background, opts)
    target, _ = assert_loss_and_grad_match_twin(grid, origins, dirs, torch.where(floors, above, plain), background,
                                                opts)
    torch.testing.assert_close(native.data, target.data, atol=1e-6 * float(target.data.abs().max()), rtol=1e-5)
    mse_short = loss_and_grad(grid, origins, dirs, short, background, opts, GridGrad(grid))[0]
    mse_passed = loss_and_grad(grid, origins, dirs, passed, background, opts, GridGrad(grid))[0]
    assert mse_short == pytest.approx(float(((rgb - torch.where(floors, above, plain)) ** 2).mean()), rel=1e-4)
    assert mse_passed == pytest.approx(float(((rgb - plain) ** 2 * ~floors).mean()), rel=1e-4)


@pytest.mark.parametrize("sh_degree", [0, 2])
def test_near_gradient_scaling_matches_twin(sh_degree):
    # Rays start inside the box, so samples lie on both sides of the distance that scaling ends at.
    grid = random_grid(sh_degree=sh_degree, seed=40 + sh_degree, holes=0.1)
    origins, dirs = random_rays(seed=41, spread=0.9)
    gen = torch.Generator().manual_seed(42)
    targets, background = torch.rand(origins.shape[0], 3, generator=gen), torch.rand(origins.shape[0], 3, generator=gen)
    opts = RenderOptions(step_size=0.6)
    whole, _ = assert_loss_and_grad_match_twin(grid, origins, dirs, targets, background, opts)
    near, _ = assert_loss_and_grad_match_twin(grid, origins, dirs, targets, background, opts, near_gradient=1.2)
    far, _ = assert_loss_and_grad_match_twin(grid, origins, dirs, targets, background, opts, near_gradient=1e-6)
    # A distance shorter than every sample's scales nothing (up to the threads' sums, added in another order), and one
    # past the rays' first stretch takes most of the gradient of the rows there.
    torch.testing.assert_close(far.data, whole.data, atol=1e-6 * float(whole.data.abs().max()), rtol=1e-5)
    near_start = torch.zeros(grid.num_occupied, dtype=torch.bool)
    unit = dirs / dirs.norm(dim=1, keepdim=True)
    points = origins[:, None, :] + torch.linspace(0.0, 0.3, 7)[None, :, None] * unit[:, None, :]
    g = grid.world_to_grid(points.reshape(-1, 3).double()).round().long()
    inside = ((g >= 0) & (g < torch.tensor(grid.resolution))).all(dim=1)
    rows = grid.links[g[inside, 0], g[inside, 1], g[inside, 2]].long()
    near_start[rows[rows >= 0]] = True
    touched = whole.touched_mask.bool() & near_start
    assert int(touched.sum()) > 0
    assert float(near.data[touched].abs().sum()) < 0.5 * float(whole.data[touched].abs().sum())


def test_near_gradient_twin_is_the_scaled_chain_rule():
    # The twin's scaling against its definition: the gradient each sample's density and coefficients receive, times
    # min(1, (t / near_gradient)^2), carried back through the (linear) interpolation; the values themselves unscaled.
    grid = random_grid(res=(5, 5, 5), sh_degree=1, seed=50, holes=0.0)
    origins, dirs = random_rays(n=12, seed=51, spread=0.8)
    gen = torch.Generator().manual_seed(52)
    targets, background = torch.rand(12, 3, generator=gen).double(), torch.rand(12, 3, generator=gen).double()
    opts = RenderOptions(step_size=0.7)

    def loss(near_gradient):
        density = grid.density.detach().double().requires_grad_(True)
        sh = grid.sh.detach().double().requires_grad_(True)
        m = reference.march(grid, origins.double(), dirs.double(), opts, density, sh, near_gradient)
        m["density_samples"].retain_grad()
        m["sh_samples"].retain_grad()
        rgb = (m["weight"][..., None] * m["colour"]).sum(dim=1) + m["t_final"][:, None] * background
        value = ((rgb - targets) ** 2).mean()
        value.backward(retain_graph=True)
        return value, density, sh, m

    scaled_loss, density, sh, _ = loss(1.0)
    plain_loss, plain_density, plain_sh, m = loss(0.0)
    assert float(scaled_loss.detach()) == float(plain_loss.detach())
    share = (m["t"][m["ray"], m["idx"]] / 1.0).clamp_max(1) ** 2
    assert 0 < float(share.min()) < 0.5 and float(share.max()) == 1.0  # samples on both sides of the distance
    want_density, want_sh = torch.autograd.grad(
        [m["density_samples"], m["sh_samples"]], [plain_density, plain_sh],
        [share * m["density_samples"].grad, share[:, None, None] * m["sh_samples"].grad])
    torch.testing.assert_close(density.grad, want_density, atol=1e-12, rtol=1e-9)
    torch.testing.assert_close(sh.grad, want_sh, atol=1e-12, rtol=1e-9)
    assert not torch.allclose(density.grad, plain_density.grad)


def gradients_on_threads(grid, threads: int, seeds, seed: int) -> tuple[GridGrad, GridGrad]:
    """The native and twin gradients of the MSE over one batch of random rays per seed, summed, the native ones added
    on `threads` threads (its per-thread tables made there too)."""
    gen = torch.Generator().manual_seed(seed)
    opts = RenderOptions(step_size=0.6)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        native, twin = GridGrad(grid), GridGrad(grid)
        native.scratch()
        for ray_seed in seeds:
            origins, dirs = random_rays(n=256, seed=ray_seed)
            targets, background = torch.rand(256, 3, generator=gen), torch.rand(256, 3, generator=gen)
            loss_and_grad(grid, origins, dirs, targets, background, opts, native)
            reference.loss_and_grad(grid, origins, dirs, targets, background, opts, twin)
    finally:
        torch.set_num_threads(before)
    return native, twin


@pytest.mark.parametrize("threads", [2, 3])
def test_gradients_of_every_thread_sum_across_calls(threads):
    # Each thread adds into its own table, which keeps the last call's values: a row it has not touched yet in this
    # call must start from zero, or a second call counts the first one's gradients again.
    native, twin = gradients_on_threads(random_grid(seed=31), threads, (33, 34, 35), seed=32)
    touched = native.touched().tolist()
    assert set(touched) == set(twin.touched().tolist()) and len(touched) == len(set(touched))  # each row once
    torch.testing.assert_close(native.data, twin.data, atol=1e-5 * float(twin.data.abs().max()), rtol=1e-4)
    assert not bool(native.scratch()[1].any())  # the per-thread masks are left clear


def test_per_thread_tables_stop_at_their_memory_share_and_the_gradients_still_sum(monkeypatch):
    # Memory for one table beside the caller's: three threads ask, two add gradients, and nothing is lost.
    import plenoxels.core.optim as optim

    grid = random_grid(seed=51)
    table = grid.data.numel() * 4 + grid.num_occupied
    monkeypatch.setattr(optim, "usable_memory", lambda: int(1.5 * table / optim.SCRATCH_MEMORY_SHARE))
    assert optim.scratch_slots(table) == 1 and optim.scratch_slots(table, memory=8 * table) == 2
    native, twin = gradients_on_threads(grid, 3, (53, 54), seed=52)
    before = torch.get_num_threads()
    torch.set_num_threads(3)
    try:
        assert native.threads() == (2, 3)
    finally:
        torch.set_num_threads(before)
    torch.testing.assert_close(native.data, twin.data, atol=1e-5 * float(twin.data.abs().max()), rtol=1e-4)


def test_march_refuses_an_occupancy_block_that_is_not_a_power_of_two():
    # The march finds a cell's block with a shift; any other block size would index the wrong block. In a
    # child process: on one GPU machine's toolchain (g++ 13.3, torch 2.11) an integer streamed into the
    # message crashed the process, and a crash must fail this test, not end the whole run.
    script = (
        "import torch\n"
        "from plenoxels.core import native\n"
        "from plenoxels.core.grid import SparseGrid\n"
        "from plenoxels.core.render import RenderOptions, _grid_args, _march_args\n"
        "grid = SparseGrid.dense((5, 5, 5), (-1, -1, -1), (1, 1, 1), 1)\n"
        "args = list(_grid_args(grid))\n"
        "args[4] = 3\n"
        "rays = torch.tensor([[0.0, 0.0, -3.0]]), torch.tensor([[0.0, 0.0, 1.0]])\n"
        "try:\n"
        "    native.ops.sample_counts(*args, *rays, *_march_args(RenderOptions(), grid))\n"
        "except RuntimeError as exc:\n"
        "    print(str(exc).splitlines()[0])\n"
    )
    child = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert child.returncode == 0, f"the child ended with {child.returncode}: {child.stderr[-2000:]}"
    assert "the occupancy block must be a power of two, got 3" in child.stdout


def test_twin_gradcheck_float64():
    grid = random_grid(res=(2, 3, 3), sh_degree=1, holes=0.0, seed=7)
    # Densities well above 0 and colours well inside the relu keep gradcheck away from kinks.
    density = (grid.density.double().abs() + 0.5).requires_grad_(True)
    sh = (grid.sh.double() * 0.2).requires_grad_(True)
    origins, dirs = random_rays(n=4, seed=3, spread=2.5)
    background = torch.rand(4, 3, dtype=torch.float64, requires_grad=True)
    opts = RenderOptions(step_size=0.7, stop_transmittance=0.0)

    def f(d, s, bg):
        rgb, depth, opacity = reference.render(grid, origins, dirs, bg, opts, density=d, sh=s)
        return rgb, depth, opacity

    assert float(f(density, sh, background)[2].detach().min()) > 0.05  # every ray crosses the grid
    assert torch.autograd.gradcheck(f, (density, sh, background), eps=1e-6, atol=1e-6, fast_mode=True)


def test_max_weights_native_matches_twin():
    grid = random_grid(seed=11)
    origins, dirs = random_rays(seed=12)
    opts = RenderOptions(step_size=0.5)
    native = max_weights(grid, origins, dirs, opts)
    twin = reference.max_weights(grid, origins, dirs, opts)
    assert float(native.max()) > 0.1
    assert bool((native == 0).any())  # some rows are never seen
    torch.testing.assert_close(native, twin, atol=ATOL, rtol=1e-5)


@pytest.mark.parametrize("fraction", [1.0, 0.3])
def test_tv_native_matches_twin(fraction):
    grid = random_grid(seed=13, holes=0.2)
    native, twin = GridGrad(grid), GridGrad(grid)
    loss_n = tv_loss_and_grad(grid, native, 0.7, 0.05, fraction, torch.Generator().manual_seed(1))
    rows = sample_rows(grid, fraction, torch.Generator().manual_seed(1))
    loss_t = reference.tv_loss_and_grad(grid, twin, rows, 0.7, 0.05)
    assert loss_n == pytest.approx(loss_t, rel=1e-5)
    assert set(native.touched().tolist()) == set(twin.touched().tolist())
    torch.testing.assert_close(native.data, twin.data, atol=1e-7, rtol=1e-4)


def test_regularisers_draw_runs_of_neighbouring_rows_and_every_row_as_often(monkeypatch):
    grid = random_grid(seed=16, holes=0.2)
    n = grid.num_occupied
    def share_in_runs(rows: torch.Tensor) -> float:
        return float((((rows[1:] - rows[:-1]) % n) == 1).float().mean())

    # Below SAMPLE_RUNS_FROM rows rows are drawn one by one; so are the sparsity prior's (in_runs=False) on any grid.
    assert share_in_runs(sample_rows(grid, 0.5, torch.Generator().manual_seed(4))) < 0.05
    monkeypatch.setattr(regularizers, "SAMPLE_RUNS_FROM", n)
    assert share_in_runs(sample_rows(grid, 0.5, torch.Generator().manual_seed(4), in_runs=False)) < 0.05
    m = round(0.1 * n)
    generator, counts, draws = torch.Generator().manual_seed(4), torch.zeros(n), 3000
    for _ in range(draws):
        rows = sample_rows(grid, 0.1, generator)
        assert rows.shape == (m,) and int(rows.min()) >= 0 and int(rows.max()) < n
        counts += torch.bincount(rows, minlength=n)
    # Each row about draws * m / n times, the last rows (where runs wrap to the first) as often as any.
    expected = draws * m / n
    assert float(counts.min()) > 0.7 * expected and float(counts.max()) < 1.3 * expected
    assert abs(float(counts[-SAMPLE_RUN_ROWS:].mean()) / expected - 1) < 0.1
    # Runs of consecutive rows: within a run, each row is the one after the row before it.
    assert share_in_runs(rows) > 1 - 2 / SAMPLE_RUN_ROWS
    assert sample_rows(grid, 1.0).tolist() == list(range(n))


def test_the_sparsity_prior_matches_autograd_and_spares_what_has_no_density():
    grid = random_grid(seed=15, holes=0.2)
    grid.density[:5] = torch.tensor([-2.0, 0.0, 1e-6, 50.0, 1e4])  # none, the kink, haze, a surface, far beyond
    grad = GridGrad(grid)
    loss = sparsity_loss_and_grad(grid, grad, 0.3, 1.0)
    voxel = max((hi - lo) / (r - 1) for lo, hi, r in zip(grid.bbox_min, grid.bbox_max, grid.resolution))
    density = grid.density.double().requires_grad_(True)
    reference_loss = 0.3 * torch.log1p((density.clamp_min(0) * voxel / SPARSITY_THICKNESS) ** 2).sum()
    reference_loss.backward()
    reference_loss = reference_loss.detach()
    assert loss == pytest.approx(reference_loss.item(), rel=1e-5)
    torch.testing.assert_close(grad.density.double(), density.grad, atol=1e-9, rtol=1e-4)
    assert grad.sh.abs().max() == 0  # colour is not its business
    touched = set(grad.touched().tolist())
    assert touched == set(torch.nonzero(grid.density > 0).flatten().tolist()) and 0 not in touched and 1 not in touched
    # Haze is pulled far harder, relative to its density, than a surface is; the surface's pull is all but gone.
    assert grad.density[2] / grid.density[2] > 1e3 * grad.density[3] / grid.density[3]
    assert 0 < grad.density[4] < 1e-3 * float(grad.density.max())
    # Sampled rows only, each once, and nothing at all at weight 0.
    partial = GridGrad(grid)
    sparsity_loss_and_grad(grid, partial, 0.3, 0.2, torch.Generator().manual_seed(3))
    assert 0 < partial.num_touched < grad.num_touched
    assert sparsity_loss_and_grad(grid, GridGrad(grid), 0.0, 1.0) == 0.0


def test_tv_twin_gradcheck_and_known_value():
    grid = random_grid(res=(3, 4, 3), sh_degree=0, holes=0.25, seed=14)
    rows = sample_rows(grid, 1.0)
    density = grid.density.double().requires_grad_(True)
    sh = grid.sh.double().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda d, s: reference.tv_loss(grid, rows, 0.3, 0.2, d, s), (density, sh))
    # Two allocated vertices along x with values 0 and 3 and nothing else: TV = |3 - 0| at the first.
    links = torch.full((2, 2, 2), -1, dtype=torch.int32)
    links[0, 0, 0], links[1, 0, 0] = 0, 1
    pair = SparseGrid.from_values(links, torch.tensor([0.0, 3.0]), torch.zeros(2, 3), (0, 0, 0), (1, 1, 1), 0)
    grad = GridGrad(pair)
    loss = tv_loss_and_grad(pair, grad, 1.0, 0.0, 1.0)
    assert loss == pytest.approx(3.0 / 2, rel=1e-6)  # mean over the 2 sampled rows, one of them has no neighbour
    torch.testing.assert_close(grad.density, torch.tensor([-0.5, 0.5]))


def bundle_of_rays(wide: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays along +x into random_grid's box: a thin bundle (a few rows touched, which the native step updates in the
    touched list's order) or a lattice across the whole box (most rows touched, which it walks in memory order)."""
    if not wide:
        origins = torch.tensor([[-3.0, 0.05, 0.1]]).repeat(4, 1)
        return origins, torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.01, 0.0], [1.0, 0.0, 0.01], [1.0, 0.01, 0.01]])
    side = torch.linspace(-0.95, 0.95, 24)
    y, z = torch.meshgrid(side, side, indexing="ij")
    origins = torch.stack([torch.full_like(y, -3.0), y, z], dim=-1).reshape(-1, 3)
    return origins, torch.tensor([[1.0, 0.003, -0.002]]).expand_as(origins).contiguous()


@pytest.mark.parametrize("wide", [False, True], ids=["few rows", "most rows"])
def test_rmsprop_updates_only_touched_rows_and_matches_twin(wide):
    grid = random_grid(res=(12,) * 3 if wide else (24,) * 3, sh_degree=1, holes=0.2 if wide else 0.0, seed=15)
    origins, dirs = bundle_of_rays(wide)
    targets = torch.zeros(origins.shape[0], 3)
    # A moment from earlier steps: an untouched row's must not decay.
    moment = torch.rand(grid.data.shape, generator=torch.Generator().manual_seed(3)) * 0.1
    results = {}
    for backend in ("native", "torch"):
        g = SparseGrid(grid.links.clone(), grid.data.clone(), grid.bbox_min, grid.bbox_max, grid.sh_degree)
        opt = SparseRMSProp(g, lr_density=0.5, lr_sh=0.1)
        opt.second_moment.copy_(moment)
        grad = GridGrad(g)
        # One kernel's gradients for both steps: a fresh RMSProp moment turns a gradient of 1e-8 into a full step,
        # so the twins' last-bit differences in a tiny gradient would show here as a different update.
        loss_and_grad(g, origins, dirs, targets, targets, RenderOptions(), grad)
        touched = grad.touched().clone()
        if wide:
            assert grid.num_occupied // 4 < touched.shape[0] < grid.num_occupied  # some rows left untouched
        else:
            assert 0 < touched.shape[0] < grid.num_occupied // 64  # below the native step's share for memory order
        if backend == "native":
            opt.step(grad)
        else:
            twin_step(opt, grad)
        assert grad.num_touched == 0 and bool((grad.data == 0).all()) and bool((grad.touched_mask == 0).all())
        changed = (g.data != grid.data).any(dim=1) | (opt.second_moment != moment).any(dim=1)
        assert set(torch.nonzero(changed).squeeze(1).tolist()) <= set(touched.tolist())
        assert bool(changed.any())
        results[backend] = (g.data, opt.second_moment)
    torch.testing.assert_close(results["native"][0], results["torch"][0], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(results["native"][1], results["torch"][1], atol=1e-9, rtol=1e-4)


def twin_step(opt: SparseRMSProp, grad: GridGrad) -> None:
    """The twin's RMSProp step on an optimiser's grid and state."""
    reference.rmsprop_step(opt.grid.data, opt.second_moment, grad, 1 + 3 * (opt.grid.sh_degree + 1) ** 2,
                           opt.lr_density, opt.lr_sh, opt.beta, opt.eps)


@pytest.mark.parametrize("backend", ["native", "torch"])
def test_rmsprop_step_formula(backend):
    grid = SparseGrid.dense((2, 2, 2), (0, 0, 0), (1, 1, 1), 0, init_density=1.0, init_sh=0.0)
    opt = SparseRMSProp(grid, lr_density=0.1, lr_sh=0.01, beta=0.9, eps=1e-8)
    opt.second_moment[3, 0] = 4.0
    grad = GridGrad(grid)
    grad.accumulate(torch.tensor([3, 5]), torch.tensor([2.0, -1.0]), torch.tensor([[0.5, 0.0, 0.0], [0.0, 0.0, 0.0]]))
    opt.step(grad) if backend == "native" else twin_step(opt, grad)
    v3 = 0.9 * 4.0 + 0.1 * 4.0
    assert float(grid.density[3]) == pytest.approx(1.0 - 0.1 * 2.0 / (v3 ** 0.5 + 1e-8), rel=1e-6)
    assert float(grid.density[5]) == pytest.approx(1.0 + 0.1 * 1.0 / (0.1 ** 0.5 + 1e-8), rel=1e-6)
    assert float(grid.sh[3, 0]) == pytest.approx(-0.01 * 0.5 / ((0.1 * 0.25) ** 0.5 + 1e-8), rel=1e-6)
    assert float(grid.sh[5, 0]) == 0.0 and float(opt.second_moment[5, 1]) == 0.0  # zero gradient, zero moment
    assert bool((grid.density[[0, 1, 2, 4, 6, 7]] == 1.0).all())


def test_native_path_fails_early_when_not_built():
    """Without plenoxels._C, importing the model works and the first kernel call says how to build it."""
    script = (
        "import sys, torch\n"
        "sys.modules['plenoxels._C'] = None\n"  # makes the import fail
        "from plenoxels.core.grid import SparseGrid\n"
        "from plenoxels.core.errors import UserError\n"
        "try:\n"
        "    SparseGrid.dense((3, 3, 3), (0, 0, 0), (1, 1, 1), 0)\n"
        "except UserError as exc:\n"
        "    print(exc)\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout
    assert "native core not built: run `make install`" in out


def test_ray_samples_are_the_kernels_lattice():
    """render.ray_samples (what export samples along rays, and the twin marches) lays out exactly the
    samples the kernels count."""
    grid = random_grid(seed=3)
    origins, dirs = random_rays(n=200, seed=4)
    for opts in (RenderOptions(step_size=0.37), RenderOptions(step_size=0.05, max_samples_per_ray=30, near=2.5)):
        lattice = ray_samples(grid, origins, dirs, opts)
        assert int(lattice["n"].sum()) == sample_counts(grid, origins, dirs, opts)[0]
        assert int((lattice["n"] == 0).sum()) > 0 and int(lattice["n"].max()) > 0


def test_sample_matches_twin_interpolation():
    grid = random_grid(sh_degree=3, seed=9)
    gen = torch.Generator().manual_seed(9)
    points = torch.rand(2000, 3, generator=gen) * 2.6 - 1.3  # about a third outside the box
    density, sh = grid.sample(points)
    g = grid.world_to_grid(points.double())
    inside = ((g >= 0) & (g <= torch.tensor(grid.resolution, dtype=torch.float64) - 1)).all(dim=1)
    assert 0 < int(inside.sum()) < points.shape[0]
    twin = reference.interpolate(grid.links, grid.data, g.to(torch.float32)) * inside[:, None]
    torch.testing.assert_close(density, twin[:, 0], atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(sh, twin[:, 1 : 1 + sh.shape[1]], atol=1e-6, rtol=1e-6)
    # Vertices read back their own values exactly; padding columns stay zero.
    corners = torch.tensor([[0.0, 0.0, 0.0], [8.0, 6.0, 10.0], [3.0, 2.0, 5.0]])
    values = native.ops.sample(grid.data, grid.links, corners)
    rows = grid.links[corners[:, 0].long(), corners[:, 1].long(), corners[:, 2].long()].long()
    expected = torch.where((rows >= 0)[:, None], grid.data[rows.clamp_min(0)], torch.zeros_like(grid.data[:3]))
    torch.testing.assert_close(values, expected, atol=0, rtol=0)


def test_sh_constants_are_the_kernels():
    """The Python SH constants (used by export and the twin) give the kernels' colour: a grid whose
    degree-0 coefficient is (c - offset) / SH_C0 renders colour c where opaque."""
    grid = SparseGrid.dense((4, 4, 4), (0, 0, 0), (1, 1, 1), 0, init_density=1e4)
    colour = torch.tensor([0.2, 0.45, 0.9])
    grid.sh.copy_(((colour - COLOUR_OFFSET) / SH_C0).expand_as(grid.sh))
    out = render(grid, torch.tensor([[0.5, 0.5, -1.0]]), torch.tensor([[0.0, 0.0, 1.0]]), None)
    torch.testing.assert_close(out.rgb[0], colour, atol=1e-6, rtol=0)


def test_empty_space_skipping_is_exact():
    """A small blob in a large, mostly unallocated grid: skipping must not change any value."""
    grid = SparseGrid.dense((40, 40, 40), (-1, -1, -1), (1, 1, 1), 1)
    coords = grid.coords().float()
    blob = ((coords - torch.tensor([25.0, 14.0, 20.0])).norm(dim=1) < 5) | ((coords - 30).norm(dim=1) < 2)
    gen = torch.Generator().manual_seed(2)
    grid.density.copy_(torch.rand(grid.num_occupied, generator=gen) * 40)
    grid.sh.copy_(torch.randn(grid.sh.shape, generator=gen) * 0.3)
    grid, _ = grid.prune(blob)
    cells, blocks = grid.occupancy()
    assert float(blocks.float().mean()) < 0.5
    origins, dirs = random_rays(n=200, seed=8, spread=2.5)
    dirs = dirs + torch.tensor([0.25, -0.3, 0.0])  # aim at the blob
    opts = RenderOptions(step_size=0.5)
    native = render(grid, origins, dirs, None, opts)
    rgb, _, opacity = twin_render(grid, origins, dirs, None, opts)
    assert int((native.opacity > 0.01).sum()) > 10
    torch.testing.assert_close(native.rgb, rgb, atol=ATOL, rtol=1e-5)
    torch.testing.assert_close(native.opacity, opacity, atol=ATOL, rtol=1e-5)


def test_live_blocks_stay_exact_through_optimizer_steps():
    """Densities cross zero during native steps; the incrementally kept live-block counts must equal a
    recount, and rendering (which skips dead blocks) must still match the twin (which skips nothing)."""
    grid = random_grid(res=(17, 17, 17), sh_degree=0, holes=0.0, seed=21)
    grid.density.copy_(torch.randn(grid.num_occupied, generator=torch.Generator().manual_seed(5)) * 0.3 - 0.4)
    opt = SparseRMSProp(grid, lr_density=0.4, lr_sh=0.05)
    grad = GridGrad(grid)
    origins, dirs = random_rays(n=128, seed=31)
    targets = torch.rand(128, 3, generator=torch.Generator().manual_seed(6))
    opts = RenderOptions(step_size=0.5)
    live_before = int(grid.live_blocks()[0].sum())
    for _ in range(4):
        loss_and_grad(grid, origins, dirs, targets, targets, opts, grad)
        opt.step(grad)
    assert grid.live_blocks_current()  # kept current by the native step, not recounted
    counts = grid.live_blocks()[0].clone()
    assert int(counts.sum()) != live_before
    fresh = SparseGrid(grid.links, grid.data.clone(), grid.bbox_min, grid.bbox_max, grid.sh_degree)
    assert torch.equal(counts, fresh.live_blocks()[0])
    native = render(grid, origins, dirs, None, opts)
    torch.testing.assert_close(native.rgb, twin_render(grid, origins, dirs, None, opts)[0], atol=ATOL, rtol=1e-5)


def test_live_block_flags_stay_exact_when_threads_share_blocks():
    """Every occupancy block holds two interior vertices, one live and one dead, and each step swaps
    them: the first half of the touched rows (one OpenMP thread) turns its vertex live while the second
    half (another thread) turns the same block's other vertex dead, in the same block order. A block's
    count stays 1 throughout, so after every step every flag must still say live; a flag written from a
    thread's own momentary count could leave a block marked empty (found in 631 of 2000 such steps
    before the flags were rewritten from the final counts)."""
    grid = SparseGrid.dense((65, 65, 65), (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), 0)
    coords = grid.coords().long()
    interior = torch.nonzero((coords % OCCUPANCY_BLOCK != 0).all(dim=1)).squeeze(1)
    block_of = coords[interior] // OCCUPANCY_BLOCK
    block_id = (block_of[:, 0] * 64 + block_of[:, 1]) * 64 + block_of[:, 2]
    interior = interior[torch.argsort(block_id, stable=True)]
    block_id = block_id.sort(stable=True).values
    first = torch.ones_like(block_id, dtype=torch.bool)
    first[1:] = block_id[1:] != block_id[:-1]
    second = torch.zeros_like(first)
    second[1:] = first[:-1]
    rows_a, rows_b = interior[first], interior[second]
    grid.density.fill_(-1.0)
    grid.density[rows_a] = -0.5
    grid.density[rows_b] = 0.5
    counts, blocks = grid.live_blocks()
    assert bool(blocks.all()) and int(counts.max()) == 1
    touched = torch.cat([rows_a, rows_b]).int()
    # beta = 0 and eps = 0 make every step move a density by exactly lr * sign(gradient) = +-1.
    grads = []
    for sign in (1.0, -1.0):
        g = torch.zeros_like(grid.data)
        g[rows_a, 0], g[rows_b, 0] = -sign, sign
        grads.append(g)
    grad, mask, second_moment = torch.zeros_like(grid.data), torch.zeros(grid.num_occupied, dtype=torch.uint8), torch.zeros_like(grid.data)
    live = (grid.coords(), OCCUPANCY_BLOCK, counts, blocks)
    stale_steps = 0
    for step in range(100):
        grad.copy_(grads[step % 2])
        native.ops.rmsprop_step(grid.data, second_moment, grad, mask, touched, touched.numel(), 1, 1.0, 0.0, 0.0, 0.0,
                                *live)
        stale_steps += int(not bool(blocks.all()))
    assert bool((grid.density[rows_a] > 0).all()) == (step % 2 == 0)
    assert int(counts.min()) == 1 and int(counts.max()) == 1
    assert stale_steps == 0, f"{stale_steps} of 100 steps left a live block flagged empty"
    fresh = SparseGrid(grid.links, grid.data.clone(), grid.bbox_min, grid.bbox_max, grid.sh_degree)
    assert torch.equal(blocks, fresh.live_blocks()[1])


def photos_of_four_sizes(seed: int = 0) -> RaySet:
    """Four photos of random pixels and sizes (one of 5x7), random cameras looking near the centre from 1 to 7 units."""
    rng = np.random.default_rng(seed)
    sizes = [(37, 53), (64, 48), (5, 7), (120, 90)]
    images = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for h, w in sizes]
    c2ws = [look_at(rng.normal(size=3) * 3, rng.normal(size=3) * 0.3) for _ in sizes]
    ks = [Intrinsics(float(rng.uniform(20, 200)), float(rng.uniform(20, 200)), w * rng.uniform(0.3, 0.7),
                     h * rng.uniform(0.3, 0.7), w, h) for h, w in sizes]
    return RaySet(images, c2ws, ks)


def morton_cells(o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Each ray's closest point to the origin in the coherent order's cells (clamped to its cube), in float64: the
    cell's integer part, before the truncation that makes it one."""
    unit = torch.nn.functional.normalize(d.double(), dim=1)
    closest = o.double() - unit * (o.double() * unit).sum(1, keepdim=True)
    return (closest.clamp(-COHERENT_EXTENT, COHERENT_EXTENT) + COHERENT_EXTENT) / (2 * COHERENT_EXTENT) * 1023


@pytest.mark.parametrize("coherent", [False, True])
def test_a_batchs_rays_in_one_native_pass_are_the_twins(coherent):
    # Random pixels of every photo and the first and last of each (where one photo's run of pixels meets the next):
    # the photos, rays and colours the torch operators (the twin, and the GPU's path) make, in the coherent order.
    photos = photos_of_four_sizes()
    ends = torch.cat([photos.offsets[:-1], photos.offsets[1:] - 1])
    pixel = torch.cat([torch.randint(photos.num_pixels, (20000,), generator=torch.Generator().manual_seed(1)), ends])
    order, image, o, d, rgb = photos.pixel_rays(pixel, coherent)
    _, want_image, want_o, want_d, want_rgb = torch_pixel_rays(photos, pixel)
    assert torch.equal(order.sort().values, torch.arange(len(pixel)))
    assert torch.equal(image, want_image[order])
    torch.testing.assert_close(o, want_o[order], atol=0, rtol=0)
    torch.testing.assert_close(d, want_d[order], atol=3e-7, rtol=0)
    torch.testing.assert_close(rgb, want_rgb[order], atol=0, rtol=0)
    # Each output is its pixel's ray: through the pixel's centre from the camera, and the pixel's colour.
    for n in range(len(photos)):
        mine = image == n
        local = pixel[order][mine] - photos.offsets[n]
        w, k, c2w = photos.intrinsics[n].w, photos.k[n].double(), photos.c2w[n].double()
        cam = torch.stack([((local % w).double() + 0.5 - k[2]) / k[0], -((local // w).double() + 0.5 - k[3]) / k[1],
                           -torch.ones(len(local), dtype=torch.float64)], dim=1)
        world = torch.nn.functional.normalize(cam @ c2w[:3, :3].T, dim=1)
        torch.testing.assert_close(d[mine].double(), world, atol=1e-6, rtol=0)
        assert torch.equal(o[mine], photos.c2w[n, :3, 3].expand(int(mine.sum()), 3))
        assert torch.equal(rgb[mine], photos.image(n).reshape(-1, 3)[local])
    if not coherent:
        assert torch.equal(order, torch.arange(len(pixel)))
        return
    # By the Morton code of each ray's closest point (bit b of axis a at bit 3b + a), ties in the pixels' order. A ray
    # within a rounding of a cell's edge may fall on either side of it (float32 here, in the twin, on other CPUs); one
    # beyond the cube is on its face.
    cells = morton_cells(o, d)
    clear = (((cells - cells.round()).abs() > 1e-3) | (cells == 0) | (cells == 1023)).all(dim=1)
    code = torch.zeros(len(pixel), dtype=torch.int64)
    for bit in range(10):
        for axis in range(3):
            code |= ((cells[:, axis].long() >> bit) & 1) << (3 * bit + axis)
    both = clear[1:] & clear[:-1]
    assert bool(both.float().mean() > 0.99)
    assert bool((code[1:] >= code[:-1])[both].all())
    tied = both & (code[1:] == code[:-1])
    assert bool(tied.any()) and bool((order[1:] > order[:-1])[tied].all())
    assert not torch.equal(order, torch.arange(len(pixel)))


def test_a_batchs_native_rays_refuse_a_pixel_outside_the_photos_and_take_an_empty_batch():
    photos = photos_of_four_sizes()
    for outside in (-1, photos.num_pixels):
        with pytest.raises(RuntimeError, match="outside the photos"):
            photos.pixel_rays(torch.tensor([0, outside]))
    order, image, o, d, rgb = photos.pixel_rays(torch.zeros(0, dtype=torch.int64), coherent=True)
    assert order.shape == image.shape == (0,) and o.shape == d.shape == rgb.shape == (0, 3)
