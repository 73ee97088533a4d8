"""The contracted grid of unbounded scenes: the contraction's math, the kernels against the twin on bent rays
(values, gradients, pruning weights, sample counts) at the extremes."""

import numpy as np
import pytest
import torch

from plenoxels import reference
from plenoxels.fit_frame import CONTRACTED_BOX, contract, uncontract
from plenoxels.grid import SparseGrid
from plenoxels.optim import GridGrad
from plenoxels.render import RenderOptions, loss_and_grad, max_weights, render, sample_counts

ATOL = 2e-5


def contracted_grid(res=9, sh_degree=1, holes=0.2, seed=0):
    gen = torch.Generator().manual_seed(seed)
    grid = SparseGrid.dense((res, res, res), *CONTRACTED_BOX, sh_degree, contracted=True)
    grid.density.copy_(torch.rand(grid.num_occupied, generator=gen) * 4 - 0.5)
    grid.sh.copy_(torch.randn(grid.sh.shape, generator=gen) * 0.4)
    if holes > 0:
        grid, _ = grid.prune(torch.rand(grid.num_occupied, generator=gen) >= holes)
    return grid


def awkward_rays():
    """Rays from inside the inner cube, from the contracted shell and from very far away; along axes (zero
    direction components), along diagonals (the max norm's ties), grazing the inner cube's faces, away from
    everything."""
    origins = [[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [3.0, 0.5, -0.4], [-2.5, -2.5, 1.0], [0.0, 0.0, 5.0],
               [1.0, 1.0, 1.0], [1.0, -0.5, 0.2], [1e6, 0.0, 0.0], [40.0, -30.0, 8.0], [0.5, 0.5, 0.5],
               [-1.5, 0.2, 0.9], [2.0, 2.0, 2.0], [-1e6, 5.0, 0.0]]
    dirs = [[1.0, 0.0, 0.0], [0.3, 0.9, -0.2], [-1.0, -0.1, 0.1], [1.0, 1.0, 0.0], [0.0, 0.0, -1.0],
            [1.0, 1.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [-0.8, 0.6, -0.1], [-1.0, -1.0, -1.0],
            [0.0, 0.0, 1.0], [1.0, 1.0, 1.0], [-1.0, 0.0, 0.0]]
    gen = torch.Generator().manual_seed(5)
    random_o = torch.randn(52, 3, generator=gen) * 2.0
    random_d = torch.randn(52, 3, generator=gen)
    return torch.cat([torch.tensor(origins), random_o]), torch.cat([torch.tensor(dirs), random_d])


def test_contraction_is_identity_inside_continuous_at_the_cube_and_inverts():
    rng = np.random.default_rng(0)
    inside = rng.uniform(-1, 1, (500, 3))
    np.testing.assert_array_equal(contract(inside), inside)
    q = rng.normal(size=(2000, 3)) * np.exp(rng.uniform(-1, 8, (2000, 1)))
    c = contract(q)
    assert np.abs(c).max() < 2.0
    np.testing.assert_allclose(uncontract(c), q, rtol=1e-9, atol=1e-12)
    # Just outside the cube's face the contraction barely moves a point: continuous at |q|_inf = 1.
    face = np.array([[1.0 + 1e-9, 0.3, -0.7]])
    np.testing.assert_allclose(contract(face), face, atol=1e-8)
    # Far away goes to the cube's faces, order kept along a ray.
    ray = np.outer(np.geomspace(1, 1e9, 50), [0.6, -0.8, 0.1])
    size = np.abs(contract(ray)).max(axis=1)
    assert np.all(np.diff(size) > 0) and size[-1] > 2 - 1e-8


def test_the_twins_speed_is_the_contractions_derivative():
    """|J u| from the closed form against central differences of contract() (the kernels' step length)."""
    gen = torch.Generator().manual_seed(1)
    q = torch.randn(400, 3, generator=gen, dtype=torch.float64) * 4
    u = torch.randn(400, 3, generator=gen, dtype=torch.float64)
    u = u / u.norm(dim=1, keepdim=True)
    # Keep away from the max norm's ties, where the contraction has a kink.
    a = q.abs().sort(dim=1).values
    q, u = q[(a[:, 2] - a[:, 1]) > 1e-3], u[(a[:, 2] - a[:, 1]) > 1e-3]
    h = 1e-6
    numeric = (contract(q + h * u) - contract(q - h * u)).norm(dim=1) / (2 * h)
    torch.testing.assert_close(reference._contracted_speed(q, u), numeric, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("sh_degree", [0, 2])
def test_render_on_a_contracted_grid_matches_twin(sh_degree):
    grid = contracted_grid(sh_degree=sh_degree, seed=sh_degree)
    origins, dirs = awkward_rays()
    background = torch.rand(origins.shape[0], 3, generator=torch.Generator().manual_seed(2))
    opts = RenderOptions(step_size=0.5, sigma_threshold=0.05)
    native = render(grid, origins, dirs, background, opts)
    rgb, depth, opacity = reference.render(grid, origins, dirs, background, opts)
    assert 0.05 < float(native.opacity.mean()) < 0.999
    # From a million units away: coming in, the ray crosses the whole grid; going out, it is at infinity already.
    assert float(native.opacity[7]) > 0.5 and float(native.opacity[12]) == 0.0
    torch.testing.assert_close(native.rgb, rgb, atol=ATOL, rtol=1e-5)
    torch.testing.assert_close(native.depth, depth, atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(native.opacity, opacity, atol=ATOL, rtol=1e-5)


def test_loss_gradients_and_pruning_weights_on_a_contracted_grid_match_twin():
    grid = contracted_grid(sh_degree=1, seed=3)
    origins, dirs = awkward_rays()
    gen = torch.Generator().manual_seed(4)
    targets, background = torch.rand(origins.shape[0], 3, generator=gen), torch.rand(origins.shape[0], 3, generator=gen)
    opts = RenderOptions(step_size=0.6)
    native, twin = GridGrad(grid), GridGrad(grid)
    mse_n, gbg_n = loss_and_grad(grid, origins, dirs, targets, background, opts, native)
    mse_t, gbg_t = reference.loss_and_grad(grid, origins, dirs, targets, background, opts, twin)
    assert mse_n == pytest.approx(mse_t, rel=1e-5)
    torch.testing.assert_close(gbg_n, gbg_t, atol=1e-8, rtol=1e-4)
    assert set(native.touched().tolist()) == set(twin.touched().tolist())
    scale = float(twin.data.abs().max())
    torch.testing.assert_close(native.data, twin.data, atol=1e-5 * scale, rtol=1e-4)
    torch.testing.assert_close(max_weights(grid, origins, dirs, opts), reference.max_weights(grid, origins, dirs, opts),
                               atol=ATOL, rtol=1e-5)


def test_contracted_twin_gradcheck_float64():
    grid = contracted_grid(res=5, sh_degree=1, holes=0.0, seed=7)
    density = (grid.density.double().abs() * 0.3 + 0.2).requires_grad_(True)
    sh = (grid.sh.double() * 0.2).requires_grad_(True)
    origins = torch.tensor([[0.2, 0.1, 0.0], [3.0, -1.0, 0.5], [-0.5, 0.4, -0.3]])
    dirs = torch.tensor([[1.0, 0.2, 0.1], [-1.0, 0.3, 0.0], [0.2, -1.0, 0.6]])
    background = torch.rand(3, 3, dtype=torch.float64, requires_grad=True)
    opts = RenderOptions(step_size=0.5, stop_transmittance=0.0)

    def f(d, s, bg):
        return reference.render(grid, origins, dirs, bg, opts, density=d, sh=s)

    assert float(f(density, sh, background)[2].detach().min()) > 0.05
    assert torch.autograd.gradcheck(f, (density, sh, background), eps=1e-6, atol=1e-6, fast_mode=True)


def test_a_contracted_ray_takes_the_twins_steps_out_to_infinity_and_no_more_than_asked():
    grid = contracted_grid(res=17, holes=0.0)
    origins, dirs = awkward_rays()
    opts = RenderOptions(step_size=0.5)
    lattice, _ = sample_counts(grid, origins, dirs, opts)
    counted = reference.contracted_samples(grid, origins, dirs, opts)["n"]
    assert lattice == int(counted.sum())
    # From the centre along +x: steps of step_size voxels (1/8 contracted unit at 17 vertices over [-2, 2]), 8 of
    # them in the inner cube, none longer outside, and together they cover the way to the cube's face.
    samples = reference.contracted_samples(grid, origins[:1], dirs[:1], opts)
    step = 0.5 * 4 / 16
    c, delta = samples["c"][0], samples["delta"][0]
    assert int((c[:, 0] < 1).sum()) == 8
    assert float(delta.max()) <= step * 1.01
    assert float(delta.sum()) == pytest.approx(2 - step / 2, rel=0.03)
    # From 50 units away towards the centre no step is much longer in the contracted frame than asked, though the
    # contraction is 2500 times slower out there than at the centre.
    inward = reference.contracted_samples(grid, torch.tensor([[50.0, 0.0, 0.0]]), torch.tensor([[-1.0, 0.0, 0.0]]), opts)
    assert float(inward["delta"][0].max()) < 2 * step
    assert int((inward["c"][0, :, 0].abs() < 1).sum()) == 16
    capped = RenderOptions(step_size=0.5, max_samples_per_ray=5)
    lattice, _ = sample_counts(grid, origins, dirs, capped)
    assert lattice == int(reference.contracted_samples(grid, origins, dirs, capped)["n"].sum())
    assert lattice <= 5 * origins.shape[0]
