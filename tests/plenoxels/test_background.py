"""The multi-sphere background: the native kernels against the PyTorch twin (reference.background_colour) and a
per-ray loop, at extreme radii and grazing rays, values and texel gradients, and its sparse optimiser."""
import math

import pytest
import torch

from plenoxels.core import background as background_module
from plenoxels.core import reference
from plenoxels.core.background import BACKGROUND_STOP_TRANSMITTANCE, BackgroundOptimiser, MultiSphereBackground
from plenoxels.core.errors import UserError
from plenoxels.core.grid import SparseGrid
from plenoxels.core.optim import GridGrad
from plenoxels.core.render import RenderOptions, loss_and_grad, loss_and_grad_before_spheres, render


def _random_rays(n: int, seed: int, spread: float = 0.9, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    o = (torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1) * spread
    d = torch.randn(n, 3, generator=g, dtype=dtype) * torch.rand(n, 1, generator=g, dtype=dtype).add(0.2)
    return o, d


def _textured(model: MultiSphereBackground, seed: int) -> MultiSphereBackground:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        model.density.copy_(torch.rand(model.density.shape, generator=g) * 1.5 - 0.3)
        model.colour.copy_(torch.randn(model.colour.shape, generator=g) * 2)
    return model


def _bilinear_equirect(tex: torch.Tensor, direction: torch.Tensor) -> torch.Tensor:
    """Texture [C, H, W] at a unit direction: texel centres at (i + 0.5) / W of 2 pi azimuth from -pi,
    (j + 0.5) / H of pi elevation from the top; azimuth wraps, elevation clamps."""
    _, h, w = tex.shape
    azimuth = math.atan2(float(direction[1]), float(direction[0]))
    elevation = math.asin(max(-1.0, min(1.0, float(direction[2]))))
    u = (azimuth + math.pi) / (2 * math.pi) * w - 0.5
    v = min(max((math.pi / 2 - elevation) / math.pi * h - 0.5, 0.0), h - 1.0)
    i0, j0 = math.floor(u), math.floor(v)
    fu, fv = u - i0, v - j0
    j1 = min(j0 + 1, h - 1)
    c0, c1 = i0 % w, (i0 + 1) % w
    top = tex[:, j0, c0] * (1 - fu) + tex[:, j0, c1] * fu
    bottom = tex[:, j1, c0] * (1 - fu) + tex[:, j1, c1] * fu
    return top * (1 - fv) + bottom * fv


def _reference(model: MultiSphereBackground, o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """One ray at a time: intersect each sphere, look up its texture, composite front to back."""
    out = []
    centre = model.centre.double()
    for oi, di in zip(o.double(), d.double()):
        di = di / di.norm()
        colour, transmittance = torch.zeros(3, dtype=torch.float64), 1.0
        for k, r in enumerate(model.radii.double()):
            if transmittance < BACKGROUND_STOP_TRANSMITTANCE:
                break
            rel = oi - centre
            b, c = float(rel @ di), float(rel @ rel - r * r)
            if b * b - c < 0:
                continue
            t = -b + math.sqrt(b * b - c)
            if t <= 0:
                continue
            p = rel + t * di
            assert abs(float(p.norm()) - float(r)) < 1e-6 * float(r)
            tex = model.texture[k].permute(2, 0, 1).detach().double()
            sample = _bilinear_equirect(tex, p / p.norm())
            alpha = 1 - math.exp(-max(float(sample[0]), 0.0))
            colour = colour + transmittance * alpha * torch.sigmoid(sample[1:])
            transmittance *= 1 - alpha
        out.append(colour + transmittance * model.far_colour.double())
    return torch.stack(out)


def twin(model: MultiSphereBackground, o, d, texture=None) -> torch.Tensor:
    texture = model.texture.detach().double() if texture is None else texture
    return reference.background_colour(o.double(), d.double(), model.centre, model.radii, texture, model.far_colour)


def native_texel_grad(model: MultiSphereBackground, o, d, grad_rgb) -> torch.Tensor:
    """The native backward's d(loss)/d(texture) as a dense [K, H, W, 4] table, and it checks the touched list."""
    optimiser = BackgroundOptimiser(model, lr=0.0)
    optimiser.backward(o.float(), d.float(), model(o.float(), d.float()), grad_rgb.float())
    rows = optimiser.touched_rows[: optimiser.num_touched].long()
    assert len(set(rows.tolist())) == len(rows)                     # each touched texel listed once
    untouched = torch.ones(optimiser.grad.shape[0], dtype=torch.bool)
    untouched[rows] = False
    assert not bool(optimiser.grad[untouched].any())                 # gradient only where listed
    return optimiser.grad.view_as(model.texture).double()


def twin_texel_grad(model: MultiSphereBackground, o, d, grad_rgb) -> torch.Tensor:
    texture = model.texture.detach().double().requires_grad_(True)
    (twin(model, o, d, texture) * grad_rgb.double()).sum().backward()
    return texture.grad


def test_constant_spheres_match_closed_form():
    model = MultiSphereBackground(n_spheres=5, height=4, width=6, far_colour=(0.2, 0.4, 0.6))
    sigmas = torch.tensor([0.3, 0.0, 1.2, 0.05, 0.7])
    logits = torch.tensor([[0.5, -1.0, 2.0], [3.0, 3.0, 3.0], [-2.0, 0.0, 1.0], [0.1, 0.2, 0.3], [1.0, -1.0, 0.0]])
    with torch.no_grad():
        model.density.copy_(sigmas[:, None, None, None].expand_as(model.density))
        model.colour.copy_(logits[:, :, None, None].expand_as(model.colour))
    alpha = 1 - torch.exp(-sigmas)
    before = torch.cumprod(torch.cat([torch.ones(1), 1 - alpha]), 0)
    expected = (alpha[:, None] * before[:-1, None] * torch.sigmoid(logits)).sum(0) + before[-1] * model.far_colour
    o, d = _random_rays(64, 0, dtype=torch.float32)
    torch.testing.assert_close(model(o, d), expected.expand(64, 3), atol=1e-5, rtol=1e-5)


def test_rays_stop_at_an_opaque_sphere_and_the_spheres_behind_it_get_no_gradient():
    model = _textured(MultiSphereBackground(r_min=1.5, r_max=40.0, n_spheres=4, height=5, width=8), seed=3)
    with torch.no_grad():
        model.density[1] = 12.0  # the second sphere lets exp(-12) ~ 6e-6 of the light through: below the threshold
    o, d = _random_rays(60, 4, spread=0.9)
    rgb = model(o.float(), d.float())
    torch.testing.assert_close(rgb.double(), twin(model, o, d), atol=2e-6, rtol=0)
    torch.testing.assert_close(rgb.double(), _reference(model, o, d), atol=2e-6, rtol=0)
    optimiser = BackgroundOptimiser(model, lr=0.0)
    optimiser.backward(o.float(), d.float(), rgb, torch.ones_like(rgb))
    touched = optimiser.touched_rows[: optimiser.num_touched].long()
    sphere = touched // (5 * 8)
    assert set(sphere.tolist()) == {0, 1}  # the two spheres behind it are neither read nor trained
    torch.testing.assert_close(native_texel_grad(model, o, d, torch.ones_like(rgb)), twin_texel_grad(model, o, d, torch.ones_like(rgb)),
                               atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("spread", [0.9, 6.0, 60.0])
def test_native_and_twin_match_the_per_ray_loop_inside_and_outside(spread):
    # spread 0.9: cameras inside every sphere; 6 and 60: outside the inner ones, so some spheres are seen from
    # outside (their exit point counts) or missed altogether.
    model = _textured(MultiSphereBackground(r_min=1.5, r_max=40.0, n_spheres=4, height=5, width=8,
                                            far_colour=(0.1, 0.0, 0.3)), seed=1)
    o, d = _random_rays(60, 2, spread=spread)
    expected = _reference(model, o, d)
    torch.testing.assert_close(twin(model, o, d), expected, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(model(o.float(), d.float()).double(), expected, atol=2e-6, rtol=0)


@pytest.mark.parametrize("case", ["inside", "outside", "grazing", "huge_radii", "poles_and_seam"])
def test_native_texel_gradients_match_the_twin(case):
    kwargs = {"r_min": 1.5, "r_max": 40.0, "n_spheres": 4, "height": 5, "width": 8}
    o, d = _random_rays(80, 11, spread=0.9)
    if case == "outside":
        o, d = _random_rays(80, 12, spread=8.0)
    if case == "huge_radii":
        kwargs.update(r_min=2.0, r_max=2e6)
        o, d = _random_rays(80, 13, spread=5.0)
    model = _textured(MultiSphereBackground(**kwargs), seed=3)
    if case == "grazing":
        # Rays from outside aimed to pass the second sphere at its radius (to 1e-6): the discriminant is ~0.
        r = float(model.radii[1])
        g = torch.Generator().manual_seed(14)
        side = torch.nn.functional.normalize(torch.randn(80, 3, generator=g, dtype=torch.float64), dim=1)
        along = torch.nn.functional.normalize(torch.linalg.cross(side, torch.randn(80, 3, generator=g, dtype=torch.float64)), dim=1)
        o = side * r * (1 - 1e-6) - along * 3 * r
        d = along
    if case == "poles_and_seam":
        d = torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [-1, 1e-7, 0.1], [-1, -1e-7, 0.1], [-1, 0, 0], [1e-9, 0, 1]] * 10,
                         dtype=torch.float64)
        o = torch.zeros_like(d)
    # Both sides get the same float32 rays: a grazing ray's exit moves a long way for a rounding of its origin.
    o, d = o.float().double(), d.float().double()
    grad_rgb = torch.randn(o.shape[0], 3, generator=torch.Generator().manual_seed(15), dtype=torch.float64)
    torch.testing.assert_close(model(o.float(), d.float()).double(), twin(model, o, d), atol=2e-6, rtol=0)
    native, expected = native_texel_grad(model, o, d, grad_rgb), twin_texel_grad(model, o, d, grad_rgb)
    assert expected.abs().sum() > 0
    torch.testing.assert_close(native, expected, atol=2e-5 * float(expected.abs().max()), rtol=0)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_texels_shared_by_every_thread_sum_their_gradients_across_calls(threads):
    # A tiny texture under thousands of rays: every texel is read by rays of every thread (each adds into its own
    # table, merged after), and a second call adds to the first, as a step's several batches would.
    model = _textured(MultiSphereBackground(r_min=1.5, r_max=40.0, n_spheres=2, height=3, width=4), seed=21)
    o, d = _random_rays(3000, 22, spread=0.9)
    o, d = o.float().double(), d.float().double()
    grad_rgb = torch.randn(o.shape[0], 3, generator=torch.Generator().manual_seed(23), dtype=torch.float64)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        optimiser = BackgroundOptimiser(model, lr=0.0)
        for half in (slice(0, 1500), slice(1500, 3000)):
            oh, dh = o[half].float().contiguous(), d[half].float().contiguous()
            optimiser.backward(oh, dh, model(oh, dh), grad_rgb[half].float().contiguous())
    finally:
        torch.set_num_threads(before)
    rows = optimiser.touched_rows[: optimiser.num_touched].long()
    assert sorted(rows.tolist()) == list(range(model.rows.shape[0]))  # every texel listed, once
    assert bool((optimiser.touched_mask == 1).all())
    assert not bool(optimiser.scratch[1].any())                     # the per-thread masks are left clear
    expected = twin_texel_grad(model, o, d, grad_rgb)
    torch.testing.assert_close(optimiser.grad.view_as(model.texture).double(), expected,
                               atol=1e-5 * float(expected.abs().max()), rtol=0)


@pytest.mark.parametrize("spread", [0.9, 8.0])
def test_the_forward_record_of_layers_gives_the_backward_the_same_texels_and_gradients(spread):
    # Cameras inside every sphere and outside the inner ones (some spheres missed); an opaque second sphere stops some
    # rays early, so their record ends there as their compositing does.
    model = _textured(MultiSphereBackground(r_min=1.5, r_max=40.0, n_spheres=4, height=5, width=8), seed=31)
    with torch.no_grad():
        model.texture[1, :3, :, 0] = 20.0
    o, d = _random_rays(400, 32, spread=spread)
    o, d = o.float(), d.float()
    grad_rgb = torch.randn(o.shape[0], 3, generator=torch.Generator().manual_seed(33))
    recorded = BackgroundOptimiser(model, lr=0.0)
    rgb = recorded.forward(o, d)
    assert recorded.record is not None and bool((recorded.record[2] < 0).any())  # missed or behind an opaque one
    torch.testing.assert_close(rgb, model(o, d), atol=0, rtol=0)
    recorded.backward(o, d, rgb, grad_rgb)
    assert recorded.record is None                                   # a record serves the one backward
    again = BackgroundOptimiser(model, lr=0.0)
    again.backward(o, d, model(o, d), grad_rgb)                      # no record: the spheres intersected again
    torch.testing.assert_close(recorded.grad, again.grad, atol=0, rtol=0)
    assert sorted(recorded.touched_rows[: recorded.num_touched].tolist()) == \
        sorted(again.touched_rows[: again.num_touched].tolist())
    expected = twin_texel_grad(model, o.double(), d.double(), grad_rgb.double())
    torch.testing.assert_close(recorded.grad.view_as(model.texture).double(), expected,
                               atol=2e-5 * float(expected.abs().max()), rtol=0)
    # The backward reads the record, not the spheres: a record with every layer blanked out passes no gradient.
    blanked = BackgroundOptimiser(model, lr=0.0)
    rgb = blanked.forward(o, d)
    blanked.record[2].fill_(-1)
    blanked.backward(o, d, rgb, grad_rgb)
    assert blanked.num_touched == 0 and not bool(blanked.grad.any())


def test_the_grids_loss_draws_the_spheres_only_on_rays_it_lets_light_past():
    gen = torch.Generator().manual_seed(51)
    grid = SparseGrid.dense((9, 8, 10), (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), 1)
    grid.density.copy_(torch.rand(grid.num_occupied, generator=gen) * 8 - 2)
    grid.sh.copy_(torch.randn(grid.sh.shape, generator=gen) * 0.4)
    model = _textured(MultiSphereBackground.around_box((-1, -1, -1), (1, 1, 1), n_spheres=4, height=5, width=8), 52)
    o = torch.randn(300, 3, generator=gen)
    o = o / o.norm(dim=1, keepdim=True) * 2.5
    d = torch.randn(300, 3, generator=gen) * 0.8 - o
    targets = torch.rand(300, 3, generator=gen)
    opts = RenderOptions(step_size=0.5, stop_transmittance=0.01)
    stopped = render(grid, o, d, None, opts).opacity > 0.99
    assert torch.equal(stopped, render(grid, o, d, None, opts, past_grid_only=True).opacity > 0.99)
    assert 30 < int(stopped.sum()) < 270
    fused, plain = BackgroundOptimiser(model, lr=0.0), BackgroundOptimiser(model, lr=0.0)
    fused_grad, plain_grad = GridGrad(grid), GridGrad(grid)
    mse, grad_background, drawn = loss_and_grad_before_spheres(grid, o, d, targets, fused.on_rays(o, d), opts,
                                                               fused_grad)
    assert bool((fused.record[2][stopped][..., 0] < 0).all()) and bool((fused.record[2][~stopped][..., 0] >= 0).any())
    behind = model(o, d)
    plain_mse, plain_grad_background = loss_and_grad(grid, o, d, targets, behind, opts, plain_grad,
                                                     past_grid_only=True)
    assert mse == pytest.approx(plain_mse, rel=1e-6)
    assert not bool(drawn[stopped].any()) and torch.equal(drawn[~stopped], behind[~stopped])
    torch.testing.assert_close(grad_background, plain_grad_background, atol=1e-9, rtol=1e-6)
    assert not bool(grad_background[stopped].any())
    assert torch.equal(fused_grad.touched_mask, plain_grad.touched_mask)
    torch.testing.assert_close(fused_grad.data, plain_grad.data, atol=1e-9, rtol=1e-5)
    # The texels: the record of the drawn rays' layers against the twin's chain rule through the grid's loss.
    fused.backward(o, d, drawn, grad_background)
    twin_grad = GridGrad(grid)
    _, twin_grad_background = reference.loss_and_grad(grid, o, d, targets, twin(model, o, d).float(), opts, twin_grad,
                                                      past_grid_only=True)
    expected = twin_texel_grad(model, o.double(), d.double(), twin_grad_background.double())
    torch.testing.assert_close(fused.grad.view_as(model.texture).double(), expected,
                               atol=2e-5 * float(expected.abs().max()), rtol=0)


def test_a_backward_of_other_rays_than_the_recorded_ones_intersects_them_itself():
    model = _textured(MultiSphereBackground(r_min=1.5, r_max=40.0, n_spheres=3, height=4, width=6), seed=41)
    o, d = (t.float() for t in _random_rays(50, 42))
    other_o, other_d = (t.float() for t in _random_rays(50, 43))
    grad_rgb = torch.randn(50, 3, generator=torch.Generator().manual_seed(44))
    optimiser = BackgroundOptimiser(model, lr=0.0)
    optimiser.forward(o, d)
    optimiser.backward(other_o, other_d, model(other_o, other_d), grad_rgb)
    expected = twin_texel_grad(model, other_o.double(), other_d.double(), grad_rgb.double())
    torch.testing.assert_close(optimiser.grad.view_as(model.texture).double(), expected,
                               atol=2e-5 * float(expected.abs().max()), rtol=0)


def test_inverse_radii_are_evenly_spaced_from_just_outside_the_box():
    model = MultiSphereBackground.around_box((-1, -1, -1), (1, 1, 1), n_spheres=16)
    inverse = 1 / model.radii.double()
    torch.testing.assert_close(inverse.diff(), torch.full((15,), float(inverse.diff()[0]), dtype=torch.float64),
                               atol=1e-9, rtol=1e-5)
    assert float(model.radii[0]) == pytest.approx(math.sqrt(3) * 1.05, rel=1e-6)


def test_huge_radii_stay_finite_and_see_the_ray_direction():
    # One sphere a billion units out: wherever a ray starts, it reads the texture in its own direction, which a
    # texture with one bright texel per direction shows.
    model = _textured(MultiSphereBackground(r_min=2.0, r_max=1e9, n_spheres=2, height=6, width=12), seed=5)
    with torch.no_grad():
        model.texture[0, ..., 0] = -5.0  # the inner sphere clear, so only the far one colours the rays
    o, d = _random_rays(300, 6, spread=50.0, dtype=torch.float32)
    rgb = model(o, d)
    assert torch.isfinite(rgb).all()
    at_origin = model(torch.zeros_like(o), d)
    torch.testing.assert_close(rgb, at_origin, atol=1e-4, rtol=0)
    grad = native_texel_grad(model, o, d, torch.ones_like(o))
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_gradcheck_float64():
    # The twin's gradients are what the native kernels are held to: here they are checked against finite differences.
    model = _textured(MultiSphereBackground(r_min=1.5, r_max=30.0, n_spheres=3, height=3, width=4), seed=7)
    o, d = _random_rays(6, 8)
    texture = model.texture.detach().double().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: twin(model, o, d, t), (texture,), eps=1e-6, atol=1e-6)


def test_sparse_tv_gradient_matches_the_dense_regulariser():
    model = _textured(MultiSphereBackground(n_spheres=2, height=4, width=6, tv_density=0.7, tv_colour=1.3), seed=9)
    texture = model.texture.detach().double().requires_grad_(True)

    def tv(x):  # [K, C, H, W]: neighbours across (wrapping) and down
        across = x - torch.roll(x, shifts=1, dims=-1)
        down = x[..., 1:, :] - x[..., :-1, :]
        return across.pow(2).mean() + down.pow(2).mean()

    channels = texture.permute(0, 3, 1, 2)
    (model.tv_density * tv(channels[:, :1]) + model.tv_colour * tv(channels[:, 1:])).backward()
    rows = torch.tensor([0, 5, 6, 11, 23, 24, 47])                 # corners, the seam, first and last rows
    torch.testing.assert_close(model.tv_grad(rows).double(), texture.grad.view(-1, 4)[rows], atol=1e-6, rtol=1e-4)
    torch.testing.assert_close(model.tv_grad_all().double(), texture.grad.view(-1, 4), atol=1e-6, rtol=1e-4)


def test_optimiser_steps_only_the_touched_texels_and_lowers_the_loss():
    model = _textured(MultiSphereBackground(r_min=1.5, r_max=40.0, n_spheres=3, height=8, width=16, tv_density=0.0,
                                            tv_colour=0.0), seed=2)
    o, d = _random_rays(40, 16, dtype=torch.float32)
    target = torch.full((40, 3), 0.8)
    optimiser = BackgroundOptimiser(model, lr=0.05)
    before = model.texture.detach().clone()
    losses, reached = [], torch.zeros(model.rows.shape[0], dtype=torch.bool)
    for _ in range(30):
        rgb = model(o, d)
        losses.append(float((rgb - target).square().mean()))
        optimiser.backward(o, d, rgb, 2 * (rgb - target) / rgb.numel())
        reached[optimiser.touched_rows[: optimiser.num_touched].long()] = True
        optimiser.step()
    changed = (model.texture.detach() != before).any(-1).view(-1)
    assert losses[-1] < 0.5 * losses[0]
    assert bool(changed.any()) and not bool((changed & ~reached).any())


def test_a_large_texture_samples_its_tv_and_the_samples_average_to_the_whole(monkeypatch):
    # With more touched texels than it samples, a step's TV gradient is a random share of the touched texels' scaled
    # up: on average over steps, the TV gradient of every touched texel.
    monkeypatch.setattr(background_module, "TV_SAMPLE_ROWS", 64)
    model = _textured(MultiSphereBackground(r_min=1.5, r_max=40.0, n_spheres=4, height=16, width=32), seed=5)
    o, d = _random_rays(400, 17, dtype=torch.float32)
    optimiser = BackgroundOptimiser(model, lr=0.0)
    optimiser.backward(o, d, model(o, d), torch.zeros(400, 3))    # marks the touched texels, adds no data gradient
    rows = optimiser.touched_rows[: optimiser.num_touched].long().clone()
    assert len(rows) > 4 * 64 and model.rows.shape[0] > 8 * 64
    mask = optimiser.touched_mask.clone()
    total = torch.zeros_like(optimiser.grad)
    steps = []

    class Recorder:  # stands in for the native optimiser step: keeps the gradient it was handed
        class ops:
            @staticmethod
            def rmsprop_step(rows_table, second_moment, grad, *rest):
                steps.append(grad.clone())
                grad.zero_()

    monkeypatch.setattr(background_module, "native", Recorder)
    draws = 2000
    for _ in range(draws):
        optimiser.touched_mask.copy_(mask)
        optimiser.num_touched = len(rows)
        optimiser.step()
        total += steps[-1]
    exact = torch.zeros_like(total)
    exact[rows] = model.tv_grad(rows)
    assert not bool(total[~mask.bool()].any())
    # Each touched texel is drawn about 2000 * 64 / len(rows) times, so the average holds to about a tenth.
    assert float((total / draws - exact).norm() / exact.norm()) < 0.15
    assert float(steps[0].norm()) > 0 and int((steps[0] != 0).any(1).sum()) <= 64


def test_legacy_state_and_round_trip_memory_and_bad_settings():
    model = _textured(MultiSphereBackground(n_spheres=4, height=8, width=16), seed=9)
    copy = MultiSphereBackground.from_config(model.config())
    copy.load_state_dict(model.state_dict())
    o, d = _random_rays(32, 10, dtype=torch.float32)
    torch.testing.assert_close(copy(o, d), model(o, d))
    # Models saved before the texture table held separate density and colour textures.
    legacy = {"centre": model.centre, "radii": model.radii, "far_colour": model.far_colour,
              "density": model.density.detach().clone(), "colour": model.colour.detach().clone()}
    old = MultiSphereBackground.from_config(model.config())
    old.load_state_dict(legacy)
    torch.testing.assert_close(old(o, d), model(o, d))
    assert model.parameter_count() == 4 * 4 * 8 * 16
    assert model.memory_bytes() == 4 * (4 * 4 * 8 * 16 + 3 + 4 + 3)
    with pytest.raises(UserError):
        MultiSphereBackground(r_min=5.0, r_max=2.0)
    with pytest.raises(UserError):
        MultiSphereBackground.around_box((0, 0, 0), (1, -1, 1))
