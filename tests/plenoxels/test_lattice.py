"""Grids with knots: cells fine across a foreground and coarser around it, one lattice throughout. The kernels against
their twin on rays that cross the knot planes, and every structure change (upsample, crop, prune, files) keeping the
map from the fit frame to the lattice."""
import math

import numpy as np
import pytest
import torch
import trimesh

from plenoxels.core import reference
from plenoxels.core.grid import SparseGrid
from plenoxels.core.render import RenderOptions, max_weights, ray_samples, render, sample_counts
from plenoxels.core.options import ModelOptions
from plenoxels.core.scene_model import SceneModel, lattice_extent, surroundings_knots
from plenoxels.surface.mesh import extract_surface, grid_lattice
from twin_checks import assert_loss_and_grad_match_twin, assert_render_matches_twin

ATOL = 2e-5
BOX = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.5))
# Fine cells in the middle of x and z, coarse around; y has one knot only, and its cells are finer below it.
KNOTS = (((-0.4, 0.2), (0.3, 0.8)), ((0.1, 0.7),), ((-0.5, 0.1), (0.5, 0.85)))


def warped_grid(res=(13, 9, 15), sh_degree=2, holes=0.3, seed=0, knots=KNOTS):
    gen = torch.Generator().manual_seed(seed)
    grid = SparseGrid.dense(res, BOX[0], BOX[1], sh_degree, knots=knots)
    grid.density.copy_(torch.rand(grid.num_occupied, generator=gen) * 6 - 1)
    grid.sh.copy_(torch.randn(grid.sh.shape, generator=gen) * 0.4)
    if holes > 0:
        grid, _ = grid.prune(torch.rand(grid.num_occupied, generator=gen) >= holes)
    return grid


def crossing_rays(n=160, seed=1):
    """Rays from a shell around the box through it, and some along the axes (exactly parallel to two knot planes)."""
    gen = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=gen)
    origins = origins / origins.norm(dim=1, keepdim=True) * 3.0
    dirs = torch.randn(n, 3, generator=gen) * 0.6 - origins
    axis = torch.eye(3).repeat(4, 1)
    starts = torch.rand(12, 3, generator=gen) * 1.6 - 0.8 - 2.5 * axis
    return torch.cat([origins, starts]), torch.cat([dirs, axis])


def test_knots_map_points_and_back():
    grid = warped_grid(holes=0.0)
    gen = torch.Generator().manual_seed(2)
    points = torch.rand(500, 3, generator=gen, dtype=torch.float64) * 3 - 1.2
    g = grid.world_to_grid(points)
    torch.testing.assert_close(grid.grid_to_world(g), points, atol=1e-12, rtol=0)
    # Each knot sits at its share of the lattice; the box's corners at the first and last vertex.
    for a, axis in enumerate(KNOTS):
        for x, share in axis:
            p = torch.zeros(1, 3, dtype=torch.float64)
            p[0, a] = x
            assert float(grid.world_to_grid(p)[0, a]) == pytest.approx(share * (grid.resolution[a] - 1), abs=1e-12)
    corners = grid.world_to_grid(torch.tensor(BOX, dtype=torch.float64))
    torch.testing.assert_close(corners, torch.tensor([[0.0, 0.0, 0.0], [12.0, 8.0, 14.0]], dtype=torch.float64))
    # The cells between x = -0.4 and 0.3 are (0.6 / 0.7) / (0.2 / 0.6) = 2.57 times finer than those below -0.4.
    assert grid.scale[0] == pytest.approx(0.6 * 12 / 0.7)


@pytest.mark.parametrize("sh_degree", [0, 2])
def test_render_on_knots_matches_twin(sh_degree):
    grid = warped_grid(sh_degree=sh_degree, seed=sh_degree)
    assert_render_matches_twin(grid, *crossing_rays(seed=10 + sh_degree), seed=3)


def test_loss_grad_and_weights_on_knots_match_twin():
    grid = warped_grid(seed=5)
    origins, dirs = crossing_rays(seed=20)
    gen = torch.Generator().manual_seed(4)
    targets, background = torch.rand(origins.shape[0], 3, generator=gen), torch.rand(origins.shape[0], 3, generator=gen)
    assert_loss_and_grad_match_twin(grid, origins, dirs, targets, background, RenderOptions(step_size=0.6))
    opts = RenderOptions(step_size=0.5)
    native = max_weights(grid, origins, dirs, opts)
    assert float(native.max()) > 0.1
    torch.testing.assert_close(native, reference.max_weights(grid, origins, dirs, opts), atol=ATOL, rtol=1e-5)


def test_ray_pieces_are_the_kernels_lattice():
    """The twin's pieces lay out exactly the samples the kernels count, with a sample cap that runs out mid-ray and a
    near plane inside the box."""
    grid = warped_grid(seed=3)
    origins, dirs = crossing_rays(n=300, seed=4)
    for opts in (RenderOptions(step_size=0.37), RenderOptions(step_size=0.05, max_samples_per_ray=30, near=2.5)):
        lattice = ray_samples(grid, origins, dirs, opts)
        assert lattice["n"].shape[1] == 6  # up to 5 knot planes crossed
        assert int(lattice["n"].sum()) == sample_counts(grid, origins, dirs, opts)[0]
        assert int((lattice["n"].sum(dim=1) == 0).sum()) > 0 and int((lattice["n"] > 0).sum(dim=1).max()) >= 3


def test_twin_gradcheck_on_knots_float64():
    grid = warped_grid(res=(4, 3, 4), sh_degree=1, holes=0.0, seed=7)
    density = (grid.density.double().abs() + 0.5).requires_grad_(True)
    sh = (grid.sh.double() * 0.2).requires_grad_(True)
    origins, dirs = crossing_rays(n=4, seed=3)
    background = torch.rand(origins.shape[0], 3, dtype=torch.float64, requires_grad=True)
    opts = RenderOptions(step_size=0.7, stop_transmittance=0.0)

    def f(d, s, bg):
        return reference.render(grid, origins[:4], dirs[:4], bg[:4], opts, density=d, sh=s)

    assert torch.autograd.gradcheck(f, (density, sh, background), eps=1e-6, atol=1e-6, fast_mode=True)


def test_density_is_per_unit_of_distance_on_every_cell_size():
    """A uniform fog renders the same through fine and coarse cells: each sample integrates over its own length."""
    sigma, length = 0.8, 2.5
    plain = SparseGrid.dense((30, 30, 30), BOX[0], BOX[1], 0, init_density=sigma)
    warped = SparseGrid.dense((30, 30, 30), BOX[0], BOX[1], 0, init_density=sigma, knots=KNOTS)
    origins = torch.tensor([[-0.9, -0.9, -1.0], [0.95, 0.0, -1.0], [-0.3, 0.2, -1.0]])
    dirs = torch.tensor([[0.0, 0.0, 1.0]]).expand(3, 3)
    expected = 1 - math.exp(-sigma * length)
    for grid in (plain, warped):
        opacity = render(grid, origins, dirs, None, RenderOptions(step_size=0.5)).opacity
        torch.testing.assert_close(opacity, torch.full((3,), expected), atol=0.02, rtol=0)


def test_upsample_crop_prune_and_files_keep_the_map(tmp_path):
    """A field linear in grid coordinates survives an upsample exactly (the knots are shares of the lattice, not
    vertices); a crop, a prune and a file read back give the same values at the same fit-frame points."""
    grid = warped_grid(res=(9, 7, 11), sh_degree=0, holes=0.0)
    g = grid.coords().double()
    grid.density.copy_((1.0 + 0.5 * g[:, 0] - 0.25 * g[:, 1] + 0.3 * g[:, 2]).float())
    gen = torch.Generator().manual_seed(6)
    points = torch.rand(400, 3, generator=gen) * 1.8 - 0.9
    before = grid.sample(points)[0]
    finer, _ = grid.upsample((17, 13, 21))
    assert finer.knots == grid.knots
    # Linear in the old grid's coordinates is linear in the new one's: (R' - 1) / (R - 1) per axis.
    torch.testing.assert_close(finer.sample(points)[0], before, atol=1e-4, rtol=1e-5)
    crop = grid.crop((1, 1, 2), (7, 5, 9))
    inside = ((points >= torch.tensor(crop.bbox_min)) & (points <= torch.tensor(crop.bbox_max))).all(dim=1)
    assert int(inside.sum()) > 50
    torch.testing.assert_close(crop.sample(points[inside])[0], before[inside], atol=1e-5, rtol=1e-5)
    pruned, _ = grid.prune(torch.ones(grid.num_occupied, dtype=torch.bool))
    path = tmp_path / "grid.pt"
    pruned.save(path)
    loaded, _ = SparseGrid.load(path)
    assert loaded.knots == grid.knots
    torch.testing.assert_close(loaded.sample(points)[0], before, atol=0, rtol=0)
    state = SparseGrid.from_state_dict(grid.state_dict())
    torch.testing.assert_close(state.sample(points)[0], before, atol=0, rtol=0)


def test_a_surface_across_cell_sizes_has_no_crack():
    """What the mesh reads of a grid with knots: its density as the renderer interpolates it, at its finest cells'
    spacing, so a ball that straddles fine and coarse cells comes out closed, the size it is."""
    grid = SparseGrid.dense((25, 25, 25), BOX[0], BOX[1], 0, knots=KNOTS)
    centre, radius = torch.tensor([0.3, 0.1, 0.45], dtype=torch.float64), 0.45  # across x = 0.3, y = 0.1, z = 0.5
    distance = (grid.grid_to_world(grid.coords().double()) - centre).norm(dim=1)
    grid.density.copy_((20.0 * (radius - distance)).float())
    lattice = grid_lattice(grid)
    np.testing.assert_allclose(lattice.spacing, 1.0 / np.asarray(grid.scale), rtol=0.05)
    vertices, faces = extract_surface(lattice, 0.0)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.volume > 0
    spread = np.linalg.norm(vertices - centre.numpy(), axis=1)
    assert abs(float(np.median(spread)) - radius) < 0.03 and float(spread.max()) < radius + 0.1


def test_surroundings_take_coarser_cells():
    inner = ((-0.5, -0.4, -1.0), (0.5, 0.4, 0.2))
    outer = ((-1.5, -1.0, -1.0), (1.5, 1.0, 0.8))
    knots = surroundings_knots(inner, outer, 3.0)
    assert knots[2] == ((0.2, pytest.approx(1.2 / (1.2 + 0.6 / 3))),)  # the floor: no knot where the boxes meet
    extent = lattice_extent(outer[0], outer[1], knots)
    np.testing.assert_allclose(extent, [1.0 + 2.0 / 3, 0.8 + 1.2 / 3, 1.2 + 0.2])
    grid = SparseGrid.dense((41, 25, 35), outer[0], outer[1], 0, knots=knots)
    cell = [1.0 / s for s in grid.scale]
    coarse = grid.grid_to_world(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], dtype=torch.float64))
    np.testing.assert_allclose((coarse[1] - coarse[0]).numpy()[:2], 3.0 * np.asarray(cell[:2]), rtol=1e-9)
    assert surroundings_knots(inner, outer, 1.0) is None


def test_a_rooms_grid_keeps_fine_cells_on_its_foreground(tmp_path):
    """An unbounded scene's bounded grid over its surroundings: with coarser cells there, the foreground gets finer
    ones at the same resolution, and the model's file keeps them."""
    scene = {"type": "unbounded", "frames": [], "foreground": {"min": [-0.5, -0.5, -0.5], "max": [0.5, 0.5, 0.5]},
             "surroundings": {"min": [-1.5, -1.5, -0.5], "max": [1.5, 1.5, 1.0]}}
    plain = SceneModel.create(scene, ModelOptions(sh_degree=0, background="off", surroundings_cells=1.0), 32)
    warped = SceneModel.create(scene, ModelOptions(sh_degree=0, background="off", surroundings_cells=3.0), 32)
    assert not plain.grid.warped and warped.grid.warped
    assert max(warped.grid.resolution) == 32 and warped.grid.bbox_min == plain.grid.bbox_min
    # x and y: a foreground of 1.1 in a box of 3.3; with the other 2.2 three times coarser, the box counts as 1.83
    # foreground cells across, so those cells are 3.3 / 1.83 = 1.8 times finer.
    assert warped.grid.scale[0] == pytest.approx(1.8 * plain.grid.scale[0])
    assert warped.resolution_for(32) == warped.grid.resolution  # the levels after the first are shaped alike
    warped.save(tmp_path)
    assert SceneModel.load(tmp_path).grid.knots == warped.grid.knots
