"""SparseGrid: construction, interpolation, prune/upsample/dilate, persistence, optimiser remap."""
import pytest
import torch

from plenoxels.core.errors import UserError
from plenoxels.core.grid import SparseGrid
from plenoxels.core.optim import GridGrad, SparseRMSProp
from plenoxels.core.render import RenderOptions
from plenoxels.core.render import loss_and_grad, render


def linear_grid(res, sh_degree=1, box=((-1.0, -0.5, 0.0), (1.0, 0.5, 2.0))):
    """Values that are affine in position, which trilinear interpolation reproduces exactly."""
    grid = SparseGrid.dense(res, box[0], box[1], sh_degree)
    p = grid.coords().float() / (torch.tensor(res, dtype=torch.float32) - 1)  # in [0,1]^3
    grid.density.copy_(2.0 + 3.0 * p[:, 0] - 1.0 * p[:, 1] + 0.5 * p[:, 2])
    k = torch.arange(grid.sh.shape[1], dtype=torch.float32)
    grid.sh.copy_(0.1 * torch.sin(k) + p[:, :1] * 0.2 * torch.cos(k) - p[:, 2:] * 0.1)
    return grid


def test_dense_layout_and_views():
    grid = SparseGrid.dense((3, 4, 5), (0, 0, 0), (1, 2, 3), 2, init_density=0.25, init_sh=-0.5)
    assert grid.resolution == (3, 4, 5) and grid.num_occupied == 60
    assert grid.links.dtype == torch.int32 and int(grid.links[2, 3, 4]) == 59
    assert grid.density.shape == (60,) and grid.sh.shape == (60, 27)
    assert bool((grid.density == 0.25).all()) and bool((grid.sh == -0.5).all())
    grid.density[7] = 3.0  # views write through to the packed table the kernels read
    assert float(grid.data[7, 0]) == 3.0
    assert grid.memory_bytes() >= grid.data.numel() * 4 + grid.links.numel() * 4
    corners = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    torch.testing.assert_close(grid.world_to_grid(corners), torch.tensor([[0.0, 0.0, 0.0], [2.0, 3.0, 4.0]]))


@pytest.mark.parametrize("bad", [(1, 4, 4), (4, 4)])
def test_bad_resolution_is_a_user_error(bad):
    with pytest.raises(UserError, match="resolution"):
        SparseGrid.dense(bad, (0, 0, 0), (1, 1, 1), 0)


def test_bad_box_and_degree_are_user_errors():
    with pytest.raises(UserError, match="bbox_min < bbox_max"):
        SparseGrid.dense((4, 4, 4), (0, 0, 0), (1, 0, 1), 0)
    with pytest.raises(UserError, match="sh_degree"):
        SparseGrid.dense((4, 4, 4), (0, 0, 0), (1, 1, 1), 4)


def test_sample_is_exact_at_vertices_linear_between_and_zero_outside():
    grid = linear_grid((4, 3, 5))
    vertices = grid.coords()[[0, 5, 17, 59]].float()
    lo, hi = torch.tensor(grid.bbox_min), torch.tensor(grid.bbox_max)
    points = lo + vertices / (torch.tensor(grid.resolution, dtype=torch.float32) - 1) * (hi - lo)
    density, sh = grid.sample(points)
    rows = grid.links[vertices[:, 0].long(), vertices[:, 1].long(), vertices[:, 2].long()].long()
    torch.testing.assert_close(density, grid.density[rows], atol=1e-5, rtol=1e-6)
    torch.testing.assert_close(sh, grid.sh[rows], atol=1e-5, rtol=1e-6)
    mid = (points[0] + points[1]) / 2  # affine field: the mean of the two ends (any path in the grid)
    d_mid, _ = grid.sample(mid[None])
    assert float(d_mid) == pytest.approx(float(density[:2].mean()), abs=1e-5)
    outside = torch.tensor([[5.0, 0.0, 1.0], [0.0, 0.0, -0.01]])
    d_out, sh_out = grid.sample(outside)
    assert bool((d_out == 0).all()) and bool((sh_out == 0).all())


def test_empty_vertex_counts_as_zero():
    grid = SparseGrid.dense((2, 2, 2), (0, 0, 0), (1, 1, 1), 0, init_density=4.0)
    pruned, _ = grid.prune(torch.tensor([True] * 7 + [False]))
    d, _ = pruned.sample(torch.tensor([[0.5, 0.5, 0.5], [1.0, 1.0, 1.0]]))
    torch.testing.assert_close(d, torch.tensor([4.0 * 7 / 8, 0.0]))


def test_prune_keeps_rows_and_render_of_zero_valued_rows():
    grid = linear_grid((6, 5, 7), sh_degree=2)
    gen = torch.Generator().manual_seed(0)
    zero = torch.rand(grid.num_occupied, generator=gen) < 0.4
    grid.data[zero] = 0.0  # rows that are all zeros render exactly as empty vertices
    pruned, old_rows = grid.prune(~zero)
    assert pruned.num_occupied == int((~zero).sum())
    torch.testing.assert_close(pruned.data, grid.data[old_rows])
    assert int((pruned.links >= 0).sum()) == pruned.num_occupied
    origins = torch.randn(64, 3, generator=gen) * 3
    dirs = torch.randn(64, 3, generator=gen) * 0.3 - origins + torch.tensor([0.0, 0.0, 1.0])
    opts = RenderOptions(step_size=0.3)
    before = render(grid, origins, dirs, None, opts)
    after = render(pruned, origins, dirs, None, opts)
    assert float(before.opacity.max()) > 0.5
    torch.testing.assert_close(after.rgb, before.rgb, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(after.depth, before.depth, atol=1e-5, rtol=1e-6)


def test_upsample_reproduces_an_affine_field():
    grid = linear_grid((5, 4, 6))
    fine, old_rows = grid.upsample((9, 7, 11))
    assert fine.resolution == (9, 7, 11) and fine.num_occupied == 9 * 7 * 11
    gen = torch.Generator().manual_seed(1)
    lo, hi = torch.tensor(grid.bbox_min), torch.tensor(grid.bbox_max)
    points = lo + torch.rand(200, 3, generator=gen) * (hi - lo)
    for a, b in zip(grid.sample(points), fine.sample(points)):
        torch.testing.assert_close(b, a, atol=1e-5, rtol=1e-5)
    # Every new vertex carries the state of the nearest old vertex.
    nearest = (fine.coords().double() * (torch.tensor([4.0, 3.0, 5.0], dtype=torch.float64)
                                        / torch.tensor([8.0, 6.0, 10.0], dtype=torch.float64))).round().long()
    expected = grid.links[nearest[:, 0], nearest[:, 1], nearest[:, 2]].long()
    assert torch.equal(old_rows, expected)
    # The same world-space samples (step doubled with the resolution) render the same image.
    origins = torch.randn(32, 3, generator=gen) * 4
    dirs = lo + (hi - lo) * torch.rand(32, 3, generator=gen) - origins
    grid.density.mul_(0.3)
    fine.density.mul_(0.3)
    coarse_img = render(grid, origins, dirs, None, RenderOptions(step_size=0.5))
    fine_img = render(fine, origins, dirs, None, RenderOptions(step_size=1.0))
    torch.testing.assert_close(fine_img.rgb, coarse_img.rgb, atol=1e-5, rtol=1e-5)


def test_upsample_allocates_only_near_occupied_vertices():
    grid = SparseGrid.dense((9, 9, 9), (0, 0, 0), (1, 1, 1), 0, init_density=1.0)
    keep = torch.zeros(grid.num_occupied, dtype=torch.bool)
    keep[int(grid.links[2, 2, 2])] = True
    single, _ = grid.prune(keep)
    fine, old_rows = single.upsample((17, 17, 17))
    xyz = fine.coords()
    # Old vertex 2 sits at new 4. The old cells with it as a corner (1 and 2) hold new vertices
    # 2..5 (new 6 lies on old 3, the first vertex of cell 3); one new voxel of dilation makes 1..6.
    assert int(xyz.min()) == 1 and int(xyz.max()) == 6
    assert fine.num_occupied == 6 ** 3
    assert int((old_rows >= 0).sum()) >= 1  # the vertex on the old one carries its state
    assert int((old_rows == -1).sum()) > 0  # fresh vertices around it start from zero state


def test_dilate_grows_by_one_voxel():
    grid = SparseGrid.dense((6, 6, 6), (0, 0, 0), (1, 1, 1), 0)
    keep = torch.zeros(grid.num_occupied, dtype=torch.bool)
    keep[int(grid.links[3, 3, 3])] = True
    keep[int(grid.links[0, 0, 0])] = True
    grown = grid.dilate(keep, radius=1)
    assert int(grown.sum()) == 27 + 8
    assert torch.equal(grid.dilate(keep, radius=0), keep)


def test_dilate_reaches_every_allocated_vertex_within_the_radius():
    """Against the Chebyshev distance itself, on a sparse grid whose empty vertices must stay out of the mask."""
    generator = torch.Generator().manual_seed(3)
    grid = SparseGrid.dense((9, 7, 8), (0, 0, 0), (1, 1, 1), 0)
    grid, _ = grid.prune(torch.rand(grid.num_occupied, generator=generator) < 0.7)
    xyz = grid.coords().long()
    for radius in (1, 2, 3):
        keep = torch.rand(grid.num_occupied, generator=generator) < 0.02
        distance = (xyz[:, None, :] - xyz[None, keep, :]).abs().amax(dim=2)
        expected = (distance <= radius).any(dim=1) if bool(keep.any()) else keep
        assert torch.equal(grid.dilate(keep, radius), expected)


def test_save_load_round_trip(tmp_path):
    grid = linear_grid((4, 5, 3), sh_degree=3)
    grid, _ = grid.prune(grid.density > 2.5)
    path = tmp_path / "grid.pt"
    grid.save(path, {"scene_transform": [[1, 0], [0, 1]], "step": 12})
    loaded, extra = SparseGrid.load(path)
    assert extra == {"scene_transform": [[1, 0], [0, 1]], "step": 12}
    assert torch.equal(loaded.links, grid.links) and torch.equal(loaded.data, grid.data)
    assert loaded.bbox_min == grid.bbox_min and loaded.bbox_max == grid.bbox_max and loaded.sh_degree == 3


def test_load_errors_are_user_errors(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        SparseGrid.load(tmp_path / "missing.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a grid")
    with pytest.raises(UserError, match="not a readable grid file"):
        SparseGrid.load(junk)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(2)}, other)
    with pytest.raises(UserError, match="not a voxfield Plenoxels grid"):
        SparseGrid.load(other)


def test_optimizer_state_follows_prune_and_upsample():
    grid = linear_grid((5, 5, 5), sh_degree=0)
    opt = SparseRMSProp(grid, lr_density=0.1, lr_sh=0.01)
    grad = GridGrad(grid)
    origins = torch.tensor([[-3.0, 0.0, 1.0], [0.0, -3.0, 1.2]])
    dirs = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    grid.density.mul_(0.2)
    loss_and_grad(grid, origins, dirs, torch.zeros(2, 3), torch.zeros(2, 3), RenderOptions(), grad)
    opt.step(grad)
    state = opt.second_moment.clone()
    assert int((state != 0).any(dim=1).sum()) > 0
    keep = torch.rand(grid.num_occupied, generator=torch.Generator().manual_seed(2)) < 0.7
    pruned, old_rows = grid.prune(keep)
    opt.remap(pruned, old_rows)
    assert opt.grid is pruned
    torch.testing.assert_close(opt.second_moment, state[old_rows])
    fine, nearest = pruned.upsample((9, 9, 9))
    before = opt.second_moment.clone()
    opt.remap(fine, nearest)
    has = nearest >= 0
    torch.testing.assert_close(opt.second_moment[has], before[nearest[has]])
    assert bool((opt.second_moment[~has] == 0).all())
    new_grad = GridGrad(fine)
    loss_and_grad(fine, origins, dirs, torch.zeros(2, 3), torch.zeros(2, 3), RenderOptions(), new_grad)
    opt.step(new_grad)
    assert bool(torch.isfinite(fine.data).all())
    with pytest.raises(ValueError, match="another grid"):
        opt.step(grad)
