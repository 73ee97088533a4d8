"""The multi-sphere background against a per-ray reference, at extreme radii, and its gradients."""
import math

import pytest
import torch

from plenoxels.background import MultiSphereBackground
from plenoxels.errors import UserError


def _random_rays(n: int, seed: int, spread: float = 0.9, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    o = (torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1) * spread
    d = torch.randn(n, 3, generator=g, dtype=dtype) * torch.rand(n, 1, generator=g, dtype=dtype).add(0.2)
    return o, d


def _textured(model: MultiSphereBackground, seed: int) -> MultiSphereBackground:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        model.density.copy_(torch.rand(model.density.shape, generator=g, dtype=model.density.dtype) * 1.5 - 0.3)
        model.colour.copy_(torch.randn(model.colour.shape, generator=g, dtype=model.colour.dtype) * 2)
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
            rel = oi - centre
            b, c = float(rel @ di), float(rel @ rel - r * r)
            if b * b - c < 0:
                continue
            t = -b + math.sqrt(b * b - c)
            if t <= 0:
                continue
            p = rel + t * di
            assert abs(float(p.norm()) - float(r)) < 1e-6 * float(r)
            tex = torch.cat([model.density[k], model.colour[k]], 0).detach().double()
            sample = _bilinear_equirect(tex, p / p.norm())
            alpha = 1 - math.exp(-max(float(sample[0]), 0.0))
            colour = colour + transmittance * alpha * torch.sigmoid(sample[1:])
            transmittance *= 1 - alpha
        out.append(colour + transmittance * model.far_colour.double())
    return torch.stack(out)


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


def test_textured_spheres_match_per_ray_reference_inside_and_outside():
    model = _textured(MultiSphereBackground(r_min=1.5, r_max=40.0, n_spheres=4, height=5, width=8,
                                            far_colour=(0.1, 0.0, 0.3)), seed=1).double()
    o_in, d_in = _random_rays(40, 2)
    # Origins outside the inner spheres (cameras around a 360 scene): some spheres are seen from outside
    # or missed, and the exit point is the one that counts.
    o_out, d_out = _random_rays(40, 3, spread=6.0)
    for o, d in ((o_in, d_in), (o_out, d_out)):
        torch.testing.assert_close(model(o, d), _reference(model, o, d), atol=1e-9, rtol=1e-9)


def test_rays_from_inside_hit_every_sphere_once_at_its_radius():
    model = MultiSphereBackground.around_box((-1, -1, -1), (1, 1, 1), n_spheres=16).double()
    o, d = _random_rays(500, 4)
    grid, valid = model._texture_coordinates(o, d)
    assert bool(valid.all())
    assert grid.shape == (16, 500, 1, 2) and bool((grid.abs() <= 1).all())
    # Inverse radii are evenly spaced from just outside the box corner.
    inverse = 1 / model.radii.double()
    torch.testing.assert_close(inverse.diff(), torch.full((15,), float(inverse.diff()[0]), dtype=torch.float64))
    assert float(model.radii[0]) == pytest.approx(math.sqrt(3) * 1.05, rel=1e-6)


def test_huge_radii_stay_finite_and_see_the_ray_direction():
    model = _textured(MultiSphereBackground(r_min=2.0, r_max=1e9, n_spheres=3, height=6, width=12), seed=5)
    o, d = _random_rays(300, 6, dtype=torch.float32)
    rgb = model(o, d)
    assert torch.isfinite(rgb).all()
    rgb.square().sum().backward()
    assert torch.isfinite(model.density.grad).all() and torch.isfinite(model.colour.grad).all()
    assert model.colour.grad.abs().sum() > 0
    # On the farthest sphere the texture is looked up in the ray's own direction, wherever it starts.
    grid, _ = model._texture_coordinates(o, d)
    unit = d / d.norm(dim=-1, keepdim=True)
    width = model.density.shape[3]
    expected_x = torch.atan2(unit[:, 1], unit[:, 0]) / math.pi * width / (width + 2)
    expected_y = -torch.asin(unit[:, 2]) / (math.pi / 2)
    torch.testing.assert_close(grid[-1, :, 0, 0], expected_x, atol=1e-5, rtol=0)
    torch.testing.assert_close(grid[-1, :, 0, 1], expected_y, atol=1e-5, rtol=0)


def test_gradcheck_float64():
    model = _textured(MultiSphereBackground(r_min=1.5, r_max=30.0, n_spheres=3, height=3, width=4), seed=7).double()
    o, d = _random_rays(6, 8)

    def render(density, colour):
        return torch.func.functional_call(model, {"density": density, "colour": colour}, (o, d))

    density = model.density.detach().clone().requires_grad_(True)
    colour = model.colour.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(render, (density, colour), eps=1e-6, atol=1e-6)


def test_regularizer_penalises_variation_across_the_seam():
    model = MultiSphereBackground(n_spheres=2, height=4, width=6, tv_density=1.0, tv_colour=1.0)
    assert model.regularizer().item() == 0.0
    with torch.no_grad():
        model.colour[:, :, :, 0] = 1.0                       # one column differs from both neighbours, one across the seam
    expected = 2 * (2 * 3 * 4 * 1.0) / model.colour.numel()  # two unit differences per row, channel and sphere
    assert model.regularizer().item() == pytest.approx(expected)
    model.regularizer().backward()
    assert model.colour.grad[:, :, :, 0].sum() > 0 and model.colour.grad[:, :, :, -1].sum() < 0


def test_state_round_trip_memory_and_bad_settings():
    model = _textured(MultiSphereBackground(n_spheres=4, height=8, width=16), seed=9)
    copy = MultiSphereBackground.from_config(model.config())
    copy.load_state_dict(model.state_dict())
    o, d = _random_rays(32, 10, dtype=torch.float32)
    torch.testing.assert_close(copy(o, d), model(o, d))
    assert model.parameter_count() == 4 * 4 * 8 * 16
    assert model.memory_bytes() == 4 * (4 * 4 * 8 * 16 + 3 + 4 + 3)
    with pytest.raises(UserError):
        MultiSphereBackground(r_min=5.0, r_max=2.0)
    with pytest.raises(UserError):
        MultiSphereBackground.around_box((0, 0, 0), (1, -1, 1))
