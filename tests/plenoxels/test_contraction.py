"""The contracted grid of unbounded scenes: the contraction's math, the kernels against the twin on bent rays
(values, gradients, pruning weights, sample counts) at the extremes, and the scene model built on it."""

import numpy as np
import pytest
import torch

from plenoxels.core import reference
from plenoxels.core.cameras import Intrinsics
from plenoxels.core.fit_frame import CONTRACTED_BOX, contract, uncontract
from plenoxels.core.grid import SparseGrid
from plenoxels.core.render import RenderOptions, max_weights, render, sample_counts
from twin_checks import assert_loss_and_grad_match_twin
from plenoxels.core.scene_model import ModelOptions, SceneModel

ATOL = 2e-5


# Knots in the contracted frame: the inner cube's faces on x, fine cells inside and 4x coarser in the shell; one knot
# off centre on y; one in the shell on z.
SHELL_KNOTS = (((-1.0, 0.1), (1.0, 0.9)), ((-0.4, 0.35),), ((1.5, 0.8),))


def contracted_grid(res=9, sh_degree=1, holes=0.2, seed=0, knots=None):
    gen = torch.Generator().manual_seed(seed)
    grid = SparseGrid.dense((res, res, res), *CONTRACTED_BOX, sh_degree, contracted=True, knots=knots)
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


@pytest.mark.parametrize("knots", [None, SHELL_KNOTS], ids=["one cell size", "knots"])
@pytest.mark.parametrize("sh_degree", [0, 2])
def test_render_on_a_contracted_grid_matches_twin(sh_degree, knots):
    grid = contracted_grid(res=9 if knots is None else 13, sh_degree=sh_degree, seed=sh_degree, knots=knots)
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
    # Steps of step_size voxels of the finest cells, in the shell too.
    lattice, _ = sample_counts(grid, origins, dirs, opts)
    assert lattice == int(reference.contracted_samples(grid, origins, dirs, opts)["n"].sum())


@pytest.mark.parametrize("knots", [None, SHELL_KNOTS], ids=["one cell size", "knots"])
def test_loss_gradients_and_pruning_weights_on_a_contracted_grid_match_twin(knots):
    grid = contracted_grid(res=9 if knots is None else 13, sh_degree=1, seed=3, knots=knots)
    origins, dirs = awkward_rays()
    gen = torch.Generator().manual_seed(4)
    targets, background = torch.rand(origins.shape[0], 3, generator=gen), torch.rand(origins.shape[0], 3, generator=gen)
    opts = RenderOptions(step_size=0.6)
    assert_loss_and_grad_match_twin(grid, origins, dirs, targets, background, opts)
    torch.testing.assert_close(max_weights(grid, origins, dirs, opts), reference.max_weights(grid, origins, dirs, opts),
                               atol=ATOL, rtol=1e-5)


@pytest.mark.parametrize("knots", [None, SHELL_KNOTS], ids=["one cell size", "knots"])
def test_contracted_twin_gradcheck_float64(knots):
    grid = contracted_grid(res=5 if knots is None else 7, sh_degree=1, holes=0.0, seed=7, knots=knots)
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
    # A shell of cells twice the inner cube's across takes steps twice as long there: 16 samples out to the inner
    # cube's face at 8 voxels a unit, then 1/8 contracted units long at their start through the shell at 4 (a little
    # less at their middle, where the contraction is slower).
    shell = contracted_grid(res=25, holes=0.0, knots=(((-1.0, 1 / 6), (1.0, 5 / 6)),) * 3)
    samples = reference.contracted_samples(shell, origins[:1], dirs[:1], opts)
    c, delta = samples["c"][0], samples["delta"][0]
    assert int((c[:, 0] < 1).sum()) == 16 and float(delta[c[:, 0] < 1].max()) == pytest.approx(1 / 16)
    near_face = delta[(c[:, 0] > 1) & (c[:, 0] < 1.5)]
    assert len(near_face) == 5 and 1.5 / 16 < float(near_face.min()) and float(near_face.max()) < 1 / 8
    assert sample_counts(shell, origins, dirs, opts)[0] == int(reference.contracted_samples(shell, origins, dirs, opts)["n"].sum())
    capped = RenderOptions(step_size=0.5, max_samples_per_ray=5)
    lattice, _ = sample_counts(grid, origins, dirs, capped)
    assert lattice == int(reference.contracted_samples(grid, origins, dirs, capped)["n"].sum())
    assert lattice <= 5 * origins.shape[0]


def unbounded_scene(beyond=0.3):
    """An unbounded scene as normalize writes it, `beyond` of its sparse points far beyond the foreground."""
    return {"type": "unbounded", "foreground": {"min": [-0.5, -0.4, -0.2], "max": [0.9, 0.6, 0.3]},
            "measured": {"beyond_fraction": beyond}, "thresholds": {"unbounded_min_beyond_fraction": 0.1}}


def test_far_content_gets_a_contracted_grid_and_no_background_model(tmp_path):
    model = SceneModel.create(unbounded_scene(), ModelOptions(), 16)
    assert model.grid.contracted and model.background is None
    assert model.grid.resolution == (16, 16, 16)
    assert (model.grid.bbox_min, model.grid.bbox_max) == CONTRACTED_BOX
    contraction = model.fit_frame.contraction
    # The inner cube holds the padded foreground box.
    lo, hi = model.region_box()
    fg = unbounded_scene()["foreground"]
    assert np.all(np.asarray(lo) <= fg["min"]) and np.all(np.asarray(hi) >= fg["max"])
    # Off, or content that all lies near (a room around an object): the bounded grid and the multi-sphere background.
    for plain in (SceneModel.create(unbounded_scene(), ModelOptions(contract="off"), 16),
                  SceneModel.create(unbounded_scene(beyond=0.02), ModelOptions(), 16)):
        assert not plain.grid.contracted and plain.background is not None
    assert SceneModel.create(unbounded_scene(beyond=0.02), ModelOptions(contract="on"), 16).grid.contracted
    assert not SceneModel.create({**unbounded_scene(), "type": "object"}, ModelOptions(), 16).grid.contracted
    # Past infinity a contracted grid's rays see the photos' mean colour (unless masks say what lies behind), and its
    # rays start half the nearest sparse point's depth from their camera.
    frames = [{"near": 0.4, "far": 3.0}, {"near": 0.3, "far": 2.0}]
    grey = SceneModel.create({**unbounded_scene(), "frames": frames}, ModelOptions(), 16, mean_colour=(0.3, 0.4, 0.5))
    assert grey.background_color == (0.3, 0.4, 0.5)
    assert grey.render_options.near == pytest.approx(0.5 * 0.3 / grey.fit_frame.contraction.half_size)
    masked = [{**f, "mask_path": "masks/a.png"} for f in frames]
    assert SceneModel.create({**unbounded_scene(), "frames": masked}, ModelOptions(), 16,
                             mean_colour=(0.3, 0.4, 0.5)).background_color == (1.0, 1.0, 1.0)
    bounded = SceneModel.create({**unbounded_scene(0.0), "frames": frames}, ModelOptions(), 16, mean_colour=(0.3, 0.4, 0.5))
    assert bounded.background_color == (1.0, 1.0, 1.0) and bounded.render_options.near == 0.0
    # A room's bounded grid with its background model off shows the photos' mean colour past it too, an object's the
    # colour set (its backdrop).
    alone = dict(mean_colour=(0.3, 0.4, 0.5))
    assert SceneModel.create({**unbounded_scene(0.0), "frames": frames}, ModelOptions(background="off"), 16,
                             **alone).background_color == (0.3, 0.4, 0.5)
    assert SceneModel.create({**unbounded_scene(0.0), "type": "object", "frames": frames},
                             ModelOptions(background="off"), 16, **alone).background_color == (1.0, 1.0, 1.0)
    # Saved and loaded, it renders the same; world depth is in world units.
    gen = torch.Generator().manual_seed(0)
    model.grid.density.copy_(torch.rand(model.grid.num_occupied, generator=gen) * 3)
    model.save(tmp_path)
    again = SceneModel.load(tmp_path)
    assert again.grid.contracted and again.fit_frame.contraction == contraction
    c2w = np.eye(4)
    c2w[:3, 3] = [0.2, 0.1, 3.0]
    k = Intrinsics(fl_x=6.0, fl_y=6.0, cx=4.0, cy=3.0, w=8, h=6)
    a, b = model.render_camera(c2w, k), again.render_camera(c2w, k)
    torch.testing.assert_close(a["rgb"], b["rgb"])
    # Depth: the kernels' t is in inner-frame units; the model reports world distance.
    o = torch.tensor([[0.2, 0.1, 3.0]])
    d = torch.tensor([[0.0, 0.0, -1.0]])
    result = model.render_rays(o, d)
    expected = result.depth / result.opacity * contraction.half_size
    assert float(model.world_depth(o, d, result)) == pytest.approx(float(expected), rel=1e-6)


def test_the_foreground_model_is_the_inner_cube_and_renders_it_as_the_full_model_does():
    model = SceneModel.create(unbounded_scene(), ModelOptions(), 17)
    grid = model.grid
    gen = torch.Generator().manual_seed(2)
    grid.density.copy_(torch.rand(grid.num_occupied, generator=gen) * 3)
    grid.sh.copy_(torch.randn(grid.sh.shape, generator=gen) * 0.3)
    # Nothing outside the inner cube, so both models see the same matter.
    g = grid.coords().double() / 16 * 4 - 2
    grid.density[(g.abs().amax(dim=1) > 1.0 - 1e-9)] = 0.0
    inner = model.foreground_model()
    assert not inner.grid.contracted and inner.grid.resolution == (9, 9, 9)
    assert inner.grid.bbox_min == (-1.0, -1.0, -1.0) and inner.grid.bbox_max == (1.0, 1.0, 1.0)
    # The inner frame's points map to the world as the contracted frame's do inside the cube.
    points = np.random.default_rng(0).uniform(-0.9, 0.9, (50, 3))
    np.testing.assert_allclose(inner.fit_frame.to_world(points), model.fit_frame.to_world(points))
    lo, hi = model.region_box()
    centre = (np.asarray(lo) + np.asarray(hi)) / 2
    origins = torch.tensor(centre + np.random.default_rng(1).normal(size=(40, 3)) * 3, dtype=torch.float32)
    dirs = torch.tensor(centre, dtype=torch.float32) - origins
    full, crop = model.render_rays(origins, dirs), inner.render_rays(origins, dirs)
    torch.testing.assert_close(full.opacity, crop.opacity, atol=0.02, rtol=0)
    assert float(full.opacity.mean()) > 0.3


def test_a_contracted_grid_has_no_lattice_and_the_photos_mean_colour_is_their_pixels_mean():
    from plenoxels.core.render import ray_samples
    from plenoxels.core.ray_set import RaySet

    with pytest.raises(ValueError, match="no lattice"):
        ray_samples(contracted_grid(), *awkward_rays(), RenderOptions())
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (5, 7, 3)) / 255.0, rng.integers(0, 256, (3, 4, 3)) / 255.0]
    k = Intrinsics(fl_x=5.0, fl_y=5.0, cx=3.5, cy=2.5, w=7, h=5)
    rays = RaySet(images, [np.eye(4)] * 2, [k, Intrinsics(fl_x=3.0, fl_y=3.0, cx=2.0, cy=1.5, w=4, h=3)])
    every = np.concatenate([im.reshape(-1, 3) for im in images])
    np.testing.assert_allclose(rays.mean_colour(), every.mean(axis=0), atol=1e-12)


def test_a_coarser_shell_gives_the_inner_cube_finer_cells_and_its_foreground_model_keeps_them(tmp_path):
    plain = SceneModel.create(unbounded_scene(), ModelOptions(), 25)
    shell = SceneModel.create(unbounded_scene(), ModelOptions(shell_cells=2.0), 25)
    assert plain.grid.knots == ((), (), ()) and shell.grid.contracted and shell.grid.resolution == (25, 25, 25)
    # Per axis the inner cube's faces are knots; the cube takes 2 of the 3 fine-cell units of the box.
    for a in range(3):
        xs, gs = shell.grid.axis_knots(a)
        assert xs == [-2.0, -1.0, 1.0, 2.0] and gs == pytest.approx([0, 4, 20, 24])
        assert shell.grid.axis_slopes(a) == pytest.approx([4, 8, 4])
    assert shell.grid.coarsening() == pytest.approx(2.0) and plain.grid.scale == (6.0, 6.0, 6.0)
    # The same content in both: a blob inside the inner cube.
    for model in (plain, shell):
        c = model.grid.grid_to_world(model.grid.coords().double())
        model.grid.density.copy_((8.0 * torch.exp(-((c - 0.1) ** 2).sum(dim=1) / 0.1)).float())
        model.grid.sh[:, 0] = 1.0
    # Its foreground model is the inner cube alone, at the shell's finer cells, and renders it as the full model does.
    inner = shell.foreground_model()
    assert not inner.grid.contracted and inner.grid.resolution == (17, 17, 17) and not inner.grid.warped
    assert inner.grid.bbox_min == pytest.approx((-1.0,) * 3) and inner.grid.bbox_max == pytest.approx((1.0,) * 3)
    lo, hi = shell.region_box()
    centre = (np.asarray(lo) + np.asarray(hi)) / 2
    origins = torch.tensor(centre + np.random.default_rng(3).normal(size=(60, 3)) * 3, dtype=torch.float32)
    dirs = torch.tensor(centre, dtype=torch.float32) - origins
    full, crop, coarse = shell.render_rays(origins, dirs), inner.render_rays(origins, dirs), plain.render_rays(origins, dirs)
    assert float(full.opacity.mean()) > 0.3
    torch.testing.assert_close(full.opacity, crop.opacity, atol=0.02, rtol=0)
    torch.testing.assert_close(full.opacity, coarse.opacity, atol=0.05, rtol=0)
    # Saved and loaded, the knots and the renders stay.
    shell.save(tmp_path)
    again = SceneModel.load(tmp_path)
    assert again.grid.knots == shell.grid.knots
    torch.testing.assert_close(again.render_rays(origins, dirs).rgb, full.rgb)
