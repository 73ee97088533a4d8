"""Numerical extremes of the core, each with its expected result, on the native and the PyTorch paths.

Most grids here span [0, R-1]^3 so that grid and fit-frame coordinates coincide and path lengths are
easy to state.
"""
import math

import pytest
import torch

from plenoxels.core import reference
from plenoxels.core.grid import SparseGrid
from plenoxels.core.optim import GridGrad, SparseRMSProp
from plenoxels.core.render import RenderOptions
from plenoxels.core.render import SH_C0, RenderResult, loss_and_grad, render

BACKENDS = ["native", "torch"]  # the product's native core, and the PyTorch twin it is held to


def render_with(backend, grid, origins, dirs, background=None, opts=None) -> RenderResult:
    if backend == "native":
        return render(grid, origins, dirs, background, opts)
    with torch.no_grad():
        return RenderResult(*reference.render(grid, origins, dirs, background, opts or RenderOptions()))


def loss_and_grad_with(backend, grid, origins, dirs, targets, background, opts, grad):
    if backend == "native":
        return loss_and_grad(grid, origins, dirs, targets, background, opts, grad)
    return reference.loss_and_grad(grid, origins, dirs, targets, background, opts or RenderOptions(), grad)


def step_with(backend, opt: SparseRMSProp, grad: GridGrad) -> None:
    if backend == "native":
        opt.step(grad)
    else:
        reference.rmsprop_step(opt.grid.data, opt.second_moment, grad, 1 + 3 * (opt.grid.sh_degree + 1) ** 2,
                               opt.lr_density, opt.lr_sh, opt.beta, opt.eps)


def unit_grid(res=(5, 5, 5), density=0.0, colour=(0.2, 0.6, 0.9), sh_degree=0) -> SparseGrid:
    """Uniform density and view-independent colour on the box [0, R-1]."""
    grid = SparseGrid.dense(res, (0, 0, 0), tuple(r - 1 for r in res), sh_degree, init_density=density)
    k = grid.sh.shape[1] // 3
    for ch, c in enumerate(colour):
        grid.sh[:, ch * k] = (c - 0.5) / SH_C0
    return grid


def rays(origins, dirs):
    return torch.tensor(origins, dtype=torch.float32), torch.tensor(dirs, dtype=torch.float32)


def assert_finite(*tensors):
    for t in tensors:
        assert bool(torch.isfinite(torch.as_tensor(t)).all())


def check_loss_grad_finite(grid, origins, dirs, backend, opts=None):
    grad = GridGrad(grid)
    b = origins.shape[0]
    mse, gbg = loss_and_grad_with(backend, grid, origins, dirs, torch.rand(b, 3), torch.rand(b, 3), opts, grad)
    assert_finite(mse, gbg, grad.data)
    return grad


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_density_renders_the_background_exactly(backend):
    grid = unit_grid(density=0.0)
    grid.sh.normal_(0, 1)
    gen = torch.Generator().manual_seed(0)
    origins = torch.randn(40, 3, generator=gen) * 6 + 2
    dirs = torch.rand(40, 3, generator=gen) * 4 - origins
    background = torch.rand(40, 3, generator=gen)
    out = render_with(backend, grid, origins, dirs, background)
    assert torch.equal(out.rgb, background)
    assert bool((out.opacity == 0).all()) and bool((out.depth == 0).all())
    targets = torch.rand(40, 3, generator=gen)
    grad = GridGrad(grid)
    mse, gbg = loss_and_grad_with(backend, grid, origins, dirs, targets, background, None, grad)
    assert mse == pytest.approx(float(((background - targets) ** 2).mean()), rel=1e-5)
    torch.testing.assert_close(gbg, 2 * (background - targets) / (3 * 40))
    assert grad.num_touched == 0 and bool((grad.data == 0).all())


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("step, first_x", [(2.0, 1.0), (1e-4, 0.0)])
def test_huge_density_shows_the_colour_at_the_first_sample(backend, step, first_x):
    grid = unit_grid(density=1e6)
    x = grid.coords()[:, 0].float()
    grid.sh[:, 0] = (0.1 + 0.2 * x - 0.5) / SH_C0  # red grows with x: 0.1 at x=0, 0.3 at x=1, ...
    origins, dirs = rays([[-1.0, 1.0, 2.0], [-3.0, 3.0, 0.0]], [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    opts = RenderOptions(step_size=step)
    out = render_with(backend, grid, origins, dirs, torch.ones(2, 3), opts)
    assert bool((out.opacity == 1).all())
    # step 2: first sample 1 voxel in; step 1e-4 is capped at max_samples_per_ray -> 4/4096/2 voxel in.
    expected_x = first_x if step > 1 else 4.0 / opts.max_samples_per_ray / 2
    torch.testing.assert_close(out.rgb[:, 0], torch.full((2,), 0.1 + 0.2 * expected_x), atol=1e-5, rtol=0)
    torch.testing.assert_close(out.rgb[:, 1:], torch.tensor([[0.6, 0.9]]).expand(2, 2), atol=1e-5, rtol=0)
    torch.testing.assert_close(out.depth, torch.tensor([1.0 + expected_x, 3.0 + expected_x]), atol=1e-4, rtol=0)
    check_loss_grad_finite(grid, origins, dirs, backend, opts)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("step", [1e-4, 0.5, 2.0])
@pytest.mark.parametrize("sh_degree", [0, 3])
def test_uniform_medium_matches_beer_lambert(backend, step, sh_degree):
    sigma, colour, bg = 0.5, torch.tensor([0.2, 0.6, 0.9]), torch.tensor([1.0, 0.5, 0.0])
    grid = unit_grid(density=sigma, sh_degree=sh_degree)
    # Along x through cell centres, and along the y axis through a line of vertices: 4 units of medium.
    origins, dirs = rays([[-2.0, 1.5, 2.5], [3.0, 9.0, 1.0]], [[3.0, 0.0, 0.0], [0.0, -0.5, 0.0]])
    out = render_with(backend, grid, origins, dirs, bg.expand(2, 3), RenderOptions(step_size=step))
    t = math.exp(-sigma * 4)
    torch.testing.assert_close(out.opacity, torch.full((2,), 1 - t), atol=2e-5, rtol=0)
    torch.testing.assert_close(out.rgb, (colour * (1 - t) + bg * t).expand(2, 3), atol=2e-5, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_rays_that_miss_or_only_touch_the_grid(backend):
    grid = unit_grid(density=5.0)
    origins, dirs = rays(
        [[-1.0, 5.0, 2.0],   # parallel to x, above the box
         [6.0, 2.0, 2.0],    # points away from the box
         [-1.0, 1.0, 0.0],   # in the face z=0, touches only the corner (0,0,0)
         [-1.0, 1.0, 2.0],   # touches only the edge x=0, y=0 (at z=2)
         [-1.0, -1e-3, 2.0]],  # parallel to x, just below the face y=0
        [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
    background = torch.rand(5, 3)
    out = render_with(backend, grid, origins, dirs, background)
    assert torch.equal(out.rgb, background) and bool((out.opacity == 0).all())
    grad = check_loss_grad_finite(grid, origins, dirs, backend)
    assert grad.num_touched == 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_rays_along_a_face_and_an_edge_see_the_medium(backend):
    sigma = 0.25
    grid = unit_grid(density=sigma)
    origins, dirs = rays([[-1.0, 0.0, 2.0], [-1.0, 0.0, 0.0], [2.0, 4.0, -3.0]],
                         [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # face y=0, edge y=z=0, face y=4
    out = render_with(backend, grid, origins, dirs, None)
    torch.testing.assert_close(out.opacity, torch.full((3,), 1 - math.exp(-sigma * 4)), atol=2e-5, rtol=0)
    check_loss_grad_finite(grid, origins, dirs, backend)


def test_axis_and_plane_aligned_rays_native_matches_twin():
    gen = torch.Generator().manual_seed(3)
    grid = unit_grid(res=(6, 5, 7), sh_degree=2)
    grid.density.copy_(torch.rand(grid.num_occupied, generator=gen) * 2)
    grid.sh.copy_(torch.randn(grid.sh.shape, generator=gen) * 0.3)
    o, d = [], []
    for y in range(5):  # along x through vertex lines, in grid planes, and between them
        for z in (0.0, 1.0, 2.5, 6.0):
            o.append([-1.0, float(y), z])
            d.append([1.0, 0.0, 0.0])
    o += [[2.0, -1.0, 3.0], [2.5, 1.0, -1.0], [5.0, 4.0, 10.0], [1.0, 1.0, 1.0]]
    d += [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 1.0, 1.0]]  # last: the main diagonal
    origins, dirs = rays(o, d)
    opts = RenderOptions(step_size=0.5)
    native = render(grid, origins, dirs, None, opts)
    twin = render_with("torch", grid, origins, dirs, None, opts)
    assert float(native.opacity.min()) > 0.3
    torch.testing.assert_close(native.rgb, twin.rgb, atol=2e-5, rtol=1e-5)
    torch.testing.assert_close(native.opacity, twin.opacity, atol=2e-5, rtol=1e-5)
    targets = torch.rand(origins.shape[0], 3, generator=gen)
    gn, gt = GridGrad(grid), GridGrad(grid)
    loss_and_grad(grid, origins, dirs, targets, targets, opts, gn)
    loss_and_grad_with("torch", grid, origins, dirs, targets, targets, opts, gt)
    torch.testing.assert_close(gn.data, gt.data, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("backend", BACKENDS)
def test_origins_inside_the_grid_and_near_plane(backend):
    sigma = 0.3
    grid = unit_grid(density=sigma)
    origins, dirs = rays([[2.0, 1.5, 2.5], [2.0, 1.5, 2.5]], [[1.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])
    out = render_with(backend, grid, origins, dirs, None)
    torch.testing.assert_close(out.opacity, torch.full((2,), 1 - math.exp(-sigma * 2)), atol=2e-5, rtol=0)
    near = render_with(backend, grid, origins, dirs, None, RenderOptions(near=1.0))
    torch.testing.assert_close(near.opacity, torch.full((2,), 1 - math.exp(-sigma * 1)), atol=2e-5, rtol=0)
    behind = render_with(backend, grid, origins, dirs, None, RenderOptions(near=20.0))
    assert bool((behind.opacity == 0).all())
    check_loss_grad_finite(grid, origins, dirs, backend)
    # Along the main diagonal from (1,1,1): 3*sqrt(3) of medium, a whole number of steps.
    diag_o, diag_d = rays([[1.0, 1.0, 1.0]], [[1.0, 1.0, 1.0]])
    diag = render_with(backend, grid, diag_o, diag_d, None, RenderOptions(step_size=math.sqrt(3) / 4))
    assert float(diag.opacity) == pytest.approx(1 - math.exp(-sigma * 3 * math.sqrt(3)), abs=2e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_single_cell_grid(backend):
    sigma = 2.0
    grid = unit_grid(res=(2, 2, 2), density=sigma)
    origins, dirs = rays([[-1.0, 0.5, 0.5], [0.5, 0.5, 3.0]], [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    out = render_with(backend, grid, origins, dirs, None, RenderOptions(step_size=0.1))
    torch.testing.assert_close(out.opacity, torch.full((2,), 1 - math.exp(-sigma)), atol=2e-5, rtol=0)
    check_loss_grad_finite(grid, origins, dirs, backend)


def test_single_cell_grid_native_matches_twin():
    grid = unit_grid(res=(2, 2, 2), sh_degree=3)
    gen = torch.Generator().manual_seed(4)
    grid.data.copy_(torch.rand(grid.data.shape, generator=gen) * 3)
    origins = torch.randn(32, 3, generator=gen) * 3
    dirs = torch.rand(32, 3, generator=gen) - origins
    a = render(grid, origins, dirs, None, RenderOptions(step_size=0.05))
    b = render_with("torch", grid, origins, dirs, None, RenderOptions(step_size=0.05))
    assert float(a.opacity.max()) > 0.5
    torch.testing.assert_close(a.rgb, b.rgb, atol=2e-5, rtol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("target", [0.0, 1.0])
def test_black_and_white_targets_pull_colour_the_right_way(backend, target):
    grid = unit_grid(density=0.6, colour=(0.5, 0.5, 0.5), sh_degree=1)
    gen = torch.Generator().manual_seed(5)
    origins = torch.cat([torch.full((64, 1), -1.0), torch.rand(64, 2, generator=gen) * 4], dim=1)
    dirs = torch.tensor([[1.0, 0.0, 0.0]]).expand(64, 3) + torch.randn(64, 3, generator=gen) * 0.05
    targets = torch.full((64, 3), target)
    background = torch.full((64, 3), target)
    opt = SparseRMSProp(grid, lr_density=0.05, lr_sh=0.05)
    grad = GridGrad(grid)
    first, _ = loss_and_grad_with(backend, grid, origins, dirs, targets, background, None, grad)
    rows = grad.touched()
    dc0 = grad.sh[rows][:, [0, 4, 8]]  # the constant coefficient of R, G and B
    sign = 1.0 if target == 0.0 else -1.0
    assert bool((sign * dc0 >= 0).all()) and bool((sign * dc0 > 0).any())
    step_with(backend, opt, grad)
    for _ in range(15):
        mse, _ = loss_and_grad_with(backend, grid, origins, dirs, targets, background, None, grad)
        step_with(backend, opt, grad)
    assert_finite(grid.data, opt.second_moment)
    assert mse < 0.5 * first


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("density", [1e6, 1e30])
def test_underflowing_transmittance_stays_finite(backend, density):
    grid = unit_grid(res=(6, 6, 6), density=density, sh_degree=2)
    grid.sh.normal_(0, 0.5)
    gen = torch.Generator().manual_seed(6)
    origins = torch.randn(16, 3, generator=gen) * 8
    dirs = torch.rand(16, 3, generator=gen) * 5 - origins
    opts = RenderOptions(step_size=0.05, stop_transmittance=0.0)  # no early stop: T runs down to 0
    out = render_with(backend, grid, origins, dirs, torch.ones(16, 3), opts)
    assert_finite(out.rgb, out.depth, out.opacity)
    hit = out.opacity > 0
    assert bool(hit.any()) and bool((out.opacity[hit] == 1).all())
    check_loss_grad_finite(grid, origins, dirs, backend, opts)


@pytest.mark.parametrize("backend", BACKENDS)
def test_rmsprop_with_zero_second_moment_and_zero_gradient(backend):
    grid = unit_grid(density=0.5, sh_degree=1)
    before = grid.data.clone()
    opt = SparseRMSProp(grid, lr_density=10.0, lr_sh=10.0, eps=1e-8)
    grad = GridGrad(grid)
    rows = torch.tensor([0, 7, 63])
    grad.accumulate(rows, torch.zeros(3), torch.zeros(3, grid.sh.shape[1]))
    step_with(backend, opt, grad)
    assert torch.equal(grid.data, before)
    assert bool((opt.second_moment == 0).all())
    tiny = torch.full((3,), 1e-30)
    grad.accumulate(rows, tiny, torch.zeros(3, grid.sh.shape[1]))
    step_with(backend, opt, grad)
    assert_finite(grid.data, opt.second_moment)
    changed = torch.nonzero((grid.data != before).any(dim=1)).squeeze(1)
    assert set(changed.tolist()) <= set(rows.tolist())


def slab_in_512_grid(sigma, colour, x_range, yz_range):
    """The 512^3 budget: a 512^3 index (512 MiB of links, every vertex addressable) on [0, 511]^3 with
    only a slab x_range x yz_range x yz_range of vertices allocated (~150k rows), uniform density and
    view-independent colour. A dense 512^3 grid would be 134M rows: 2.1 GB of parameters even at SH
    degree 0."""
    res = (512, 512, 512)
    links = torch.full(res, -1, dtype=torch.int32)
    (x0, x1), (a0, a1) = x_range, yz_range
    shape = (x1 - x0 + 1, a1 - a0 + 1, a1 - a0 + 1)
    n = shape[0] * shape[1] * shape[2]
    links[x0 : x1 + 1, a0 : a1 + 1, a0 : a1 + 1] = torch.arange(n, dtype=torch.int32).reshape(shape)
    density = torch.full((n,), sigma)
    sh = torch.zeros(n, 12)
    for ch, c in enumerate(colour):
        sh[:, ch * 4] = (c - 0.5) / SH_C0
    return SparseGrid.from_values(links, density, sh, (0, 0, 0), (511, 511, 511), 1)


def test_512_cubed_budget_with_a_thin_slab():
    sigma, bg = 0.01, torch.tensor([1.0, 0.5, 0.0])
    grid = slab_in_512_grid(sigma, (0.2, 0.6, 0.9), x_range=(252, 260), yz_range=(192, 319))
    assert grid.resolution == (512, 512, 512) and grid.num_occupied == 9 * 128 * 128
    # Outside the slab the unallocated corners count as 0, so density ramps linearly to 0 over the one
    # cell on either side: each ramp adds half a cell of medium. Step 0.5 from a whole-voxel entry
    # puts sample intervals between whole voxels, where the midpoint rule is exact for the ramps.
    origins, dirs = rays(
        [[-1.0, 250.5, 260.25],  # along x across the slab: 8 cells + 2 half ramps
         [256.5, 230.5, -1.0],   # along z inside the slab: 127 cells + 2 half ramps
         [100.5, -1.0, 300.5],   # along y through 512 voxels of empty space
         [-3.0, 256.0, 700.0]],  # misses the box
        [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    tau = torch.tensor([9 * sigma, 128 * sigma, 0.0, 0.0])
    opts = RenderOptions(step_size=0.5)
    for backend in BACKENDS:
        out = render_with(backend, grid, origins, dirs, bg.expand(4, 3), opts)
        torch.testing.assert_close(out.opacity, 1 - torch.exp(-tau), atol=2e-5, rtol=0)
        # The colour coefficients ramp to 0 with the density, so only the empty rays have a closed form.
        assert torch.equal(out.rgb[2:], bg.expand(2, 3))
    # Varied values and oblique rays (the main diagonal crosses the slab at its centre): native and
    # twin agree on colour and on the gradient of every row.
    gen = torch.Generator().manual_seed(12)
    grid.density.copy_(torch.rand(grid.num_occupied, generator=gen) * 0.05)
    grid.sh.normal_(0, 0.3, generator=gen)
    centre = torch.tensor([256.0, 255.5, 255.5])
    far = torch.randn(6, 3, generator=gen)
    origins = torch.cat([torch.tensor([[-1.0, -1.0, -1.0]]), centre + far / far.norm(dim=1, keepdim=True) * 400])
    dirs = centre + torch.randn(7, 3, generator=gen) * 20 - origins
    native = render(grid, origins, dirs, None, opts)
    twin = render_with("torch", grid, origins, dirs, None, opts)
    assert float(native.opacity.min()) > 0.05
    torch.testing.assert_close(native.rgb, twin.rgb, atol=2e-5, rtol=1e-5)
    torch.testing.assert_close(native.opacity, twin.opacity, atol=2e-5, rtol=1e-5)
    targets = torch.rand(7, 3, generator=gen)
    gn, gt = GridGrad(grid), GridGrad(grid)
    loss_and_grad(grid, origins, dirs, targets, targets, opts, gn)
    loss_and_grad_with("torch", grid, origins, dirs, targets, targets, opts, gt)
    assert gn.num_touched > 0 and sorted(gn.touched().tolist()) == sorted(gt.touched().tolist())
    assert_finite(gn.data)
    torch.testing.assert_close(gn.data, gt.data, atol=1e-6, rtol=1e-4)
