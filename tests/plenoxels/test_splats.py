"""Splats: the rasterizer against a per-pixel brute-force reference and its projection against sampled points, a
similarity that moves splats and camera together changing no pixel (SH turned with them), splats from a small grid
rendering like the grid, distillation raising their PSNR against the grid's renders, and a background model's spheres
as splats rendering like the model, a view beside the camera's plane included."""
import math

import numpy as np
import pytest
import torch

from plenoxels.core.background import MultiSphereBackground
from plenoxels.core.cameras import Intrinsics, look_at
from plenoxels.core.fit_frame import FitFrame
from plenoxels.core.grid import SparseGrid
from plenoxels.core.render import COLOUR_OFFSET, SH_C0, RenderOptions, max_weights, render as render_grid
from plenoxels.core.cameras import rays_from_camera
from plenoxels.splats.distill import RowAdam, TargetView, WindowErrors, distill, psnr
from plenoxels.splats.background_splats import splats_from_background
from plenoxels.splats.from_grid import splats_from_grid
from plenoxels.splats.model import Splats, matrix_to_quat, quat_to_matrix
from plenoxels.splats.rasterize import ALPHA_MAX, ALPHA_MIN, LOW_PASS, STOP_TRANSMITTANCE, project, render, render_window


def random_splats(n: int, degree: int, seed: int = 0, spread: float = 0.6, size=(0.04, 0.15)) -> Splats:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return Splats(means=(torch.rand(n, 3, generator=g) - 0.5) * 2 * spread,
                  log_scales=torch.log(size[0] + (size[1] - size[0]) * torch.rand(n, 3, generator=g)),
                  quats=torch.randn(n, 4, generator=g),
                  opacity_logits=torch.randn(n, generator=g) * 2,
                  sh=torch.randn(n, 3, k, generator=g) * 0.6)


def camera(eye, size: int = 24, focal: float = 30.0) -> tuple[np.ndarray, Intrinsics]:
    return look_at(np.asarray(eye, dtype=np.float64), (0.0, 0.0, 0.0)), Intrinsics(focal, focal * 1.1, size / 2 + 0.3,
                                                                                      size / 2 - 0.2, size, size - 4)


def brute_force(splats: Splats, c2w: np.ndarray, k: Intrinsics, background) -> np.ndarray:
    """Every pixel on its own, splat after splat in depth order, straight from the kernel's definition (float64)."""
    w2c = np.linalg.inv(c2w)
    out = np.zeros((k.h, k.w, 3))
    means = splats.means.double().numpy()
    cam = means @ w2c[:3, :3].T + w2c[:3, 3]
    cv = cam * [1, -1, -1]
    cov = splats.covariances().double().numpy()
    rot = np.diag([1.0, -1, -1]) @ w2c[:3, :3]
    dirs = means - c2w[:3, 3]
    colours = splats.colours(torch.as_tensor(dirs / np.linalg.norm(dirs, axis=1, keepdims=True)).float()).double().numpy()
    opac = splats.opacities().double().numpy()
    order = [i for i in np.argsort(cv[:, 2]) if cv[i, 2] > 0.01]
    kernels = []
    for i in order:
        x, y, z = cv[i]
        jac = np.array([[k.fl_x / z, 0, -k.fl_x * x / z ** 2], [0, k.fl_y / z, -k.fl_y * y / z ** 2]])
        s2 = jac @ rot @ cov[i] @ rot.T @ jac.T + LOW_PASS * np.eye(2)
        centre = np.array([k.fl_x * x / z + k.cx, k.fl_y * y / z + k.cy])
        kernels.append((centre, np.linalg.inv(s2), 3 * math.sqrt(np.linalg.eigvalsh(s2).max()), colours[i], opac[i]))
    for v in range(k.h):
        for u in range(k.w):
            p, light, colour = np.array([u + 0.5, v + 0.5]), 1.0, np.zeros(3)
            for centre, inverse, radius, c, o in kernels:
                d = p - centre
                if np.abs(d).max() > radius:  # outside the 3 sigma box
                    continue
                alpha = min(ALPHA_MAX, o * math.exp(-0.5 * d @ inverse @ d))
                if alpha < ALPHA_MIN:
                    continue
                if light * (1 - alpha) < STOP_TRANSMITTANCE:
                    break
                colour += light * alpha * c
                light *= 1 - alpha
            out[v, u] = colour + light * np.asarray(background)
    return out


def test_rasterizer_matches_the_per_pixel_reference_for_every_sh_degree():
    for degree in range(4):
        splats = random_splats(40, degree, seed=degree)
        c2w, k = camera([1.2, -1.9, 0.9])
        ours = render(splats, c2w, k, background=(0.2, 0.4, 0.9))["rgb"].double().numpy()
        truth = np.clip(brute_force(splats, c2w, k, (0.2, 0.4, 0.9)), 0, 1)
        assert np.abs(ours - truth).max() < 2e-4, degree
    # Nearly opaque splats stacked up: the early stop decides which ones count.
    opaque = random_splats(40, 1, seed=9, spread=0.15)
    opaque.opacity_logits[:] = 6.0
    ours = render(opaque, c2w, k, background=(0.2, 0.4, 0.9))["rgb"].double().numpy()
    assert np.abs(ours - np.clip(brute_force(opaque, c2w, k, (0.2, 0.4, 0.9)), 0, 1)).max() < 2e-4
    # The reference can tell: the same splats seen from elsewhere differ.
    elsewhere = render(splats, camera([1.3, -1.8, 0.9])[0], k, background=(0.2, 0.4, 0.9))["rgb"].double().numpy()
    assert np.abs(elsewhere - truth).max() > 0.05


def _window_grads(splats: Splats, c2w, k: Intrinsics, window, native: bool):
    leaves = {name: t.detach().double().clone().requires_grad_(True) for name, t in splats.tensors().items()}
    rgb, opacity = render_window(project(Splats(**leaves), c2w, k), window, (0.2, 0.5, 0.9), native=native)
    weights = torch.linspace(-1.0, 1.0, rgb.numel(), dtype=rgb.dtype).reshape(rgb.shape)
    loss = (rgb * weights).sum() + (opacity ** 2).sum()
    return rgb.detach(), opacity.detach(), torch.autograd.grad(loss, list(leaves.values()), allow_unused=True)


@pytest.mark.parametrize("case", ["mixed", "opaque stack", "faint", "border window", "one splat", "nothing near"])
def test_native_compositing_matches_the_torch_pairs_in_values_and_gradients(case):
    """The native kernel (csrc/cpu_splats.cpp) against the (splat, pixel) pairs composited in torch, its reference:
    pixels and the gradient of a loss over them with respect to every splat attribute, where the clamp at ALPHA_MAX and
    the early stop decide (an opaque stack), where most pairs fall under ALPHA_MIN (faint), in a window cut by the
    image's edge, for a single splat and for none."""
    splats = random_splats(300, 2, seed=11, spread=0.5)
    c2w, k = camera([1.1, -1.7, 1.0], size=40, focal=45.0)
    window = (3, 5, 29, 23)
    if case == "opaque stack":
        splats = random_splats(200, 1, seed=12, spread=0.12)
        splats.opacity_logits[:] = 7.0
    elif case == "faint":
        splats.opacity_logits[:] = -4.0
    elif case == "border window":
        window = (k.w - 13, k.h - 9, 13, 9)
    elif case == "one splat":
        splats = random_splats(1, 3, seed=13, size=(0.2, 0.3), spread=0.05)
    elif case == "nothing near":
        splats.means[:, 2] += 40.0  # behind the camera
    ours, reference = (_window_grads(splats, c2w, k, window, native) for native in (True, False))
    assert torch.allclose(ours[0], reference[0], atol=2e-6) and torch.allclose(ours[1], reference[1], atol=2e-6)
    for mine, theirs in zip(ours[2], reference[2]):
        if theirs is None:  # nothing in front of the camera: no attribute reaches the pixels
            assert mine is None or not mine.any()
            continue
        scale = theirs.abs().max().clamp_min(1e-3)
        assert ((mine - theirs).abs().max() / scale) < 2e-4, (case, float((mine - theirs).abs().max()), float(scale))
    if case == "mixed":
        # The comparison can fail: a splat moved by a tenth of a pixel changes the gradients.
        moved = splats.detached()
        moved.means[0] += 0.003
        other = _window_grads(moved, c2w, k, window, True)
        assert max(float((a - b).abs().max()) for a, b in zip(other[2], reference[2])) > 1e-4


def test_projection_matches_the_spread_of_sampled_points():
    splats = random_splats(1, 0, seed=3, size=(0.01, 0.03))
    # A view wide enough to hold the splat: beyond 1.3 half fields of view the projection clamps its Jacobian.
    c2w, k = camera([0.9, -1.4, 0.7], size=400, focal=200.0)
    proj = project(splats, c2w, k)
    points = torch.distributions.MultivariateNormal(splats.means[0].double(), splats.covariances()[0].double()).sample((200_000,))
    w2c = np.linalg.inv(c2w)
    cv = (points.numpy() @ w2c[:3, :3].T + w2c[:3, 3]) * [1, -1, -1]
    pixels = np.stack([k.fl_x * cv[:, 0] / cv[:, 2] + k.cx - 0.5, k.fl_y * cv[:, 1] / cv[:, 2] + k.cy - 0.5], 1)
    a, b, c = proj.conics[0].double().numpy()
    cov2d = np.linalg.inv([[a, b], [b, c]]) - LOW_PASS * np.eye(2)
    assert np.allclose(pixels.mean(0), proj.means2d[0].numpy(), atol=0.02)
    assert np.allclose(np.cov(pixels.T), cov2d, rtol=0.03, atol=0.02)


def test_a_similarity_moving_splats_and_camera_together_changes_no_pixel():
    splats = random_splats(60, 3, seed=7)
    c2w, k = camera([1.0, -2.0, 0.8])
    rotation = torch.linalg.matrix_exp(torch.tensor([[0, -0.7, 0.4], [0.7, 0, -1.1], [-0.4, 1.1, 0]])).double().numpy()
    similarity = np.eye(4)
    similarity[:3, :3], similarity[:3, 3] = 1.7 * rotation, [0.3, -2.0, 5.0]
    moved = splats.transformed(similarity)
    moved_c2w = similarity @ c2w
    moved_c2w[:3, :3] /= 1.7
    before = render(splats, c2w, k)["rgb"]
    after = render(moved, moved_c2w, k)["rgb"]
    assert (after - before).abs().max() < 2e-3
    # Without turning the SH the colours change: the test can tell.
    unturned = Splats(moved.means, moved.log_scales, moved.quats, moved.opacity_logits, splats.sh)
    assert (render(unturned, moved_c2w, k)["rgb"] - before).abs().max() > 0.05
    q = matrix_to_quat(quat_to_matrix(splats.quats).double().numpy())
    assert np.allclose(quat_to_matrix(torch.as_tensor(q)).numpy(), quat_to_matrix(splats.quats).double().numpy(),
                       atol=1e-6)


def ball_grid(res: int = 20) -> SparseGrid:
    """A dense grid holding a soft ball, red on one side and blue on the other, with a view-dependent term."""
    axis = torch.linspace(-1, 1, res)
    p = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    density = 40.0 * torch.sigmoid((0.5 - p.norm(dim=1)) / 0.05)
    target = torch.where(p[:, :1] > 0, torch.tensor([0.9, 0.2, 0.1]), torch.tensor([0.1, 0.3, 0.9]))
    sh = torch.zeros(len(p), 3, 4)
    sh[:, :, 0] = (target - COLOUR_OFFSET) / SH_C0
    sh[:, :, 1:] = 0.15
    links = torch.arange(len(p), dtype=torch.int32).reshape(res, res, res)
    return SparseGrid.from_values(links, density, sh.reshape(len(p), 12), (-1, -1, -1), (1, 1, 1), 1)


# The hand-made grids below are rendered as splats are, to the same last light: a fitted grid stops its rays where it
# was fitted to (fit.stop_transmittance), which these grids never were.
AS_SPLATS = RenderOptions(stop_transmittance=STOP_TRANSMITTANCE)


def grid_views(grid: SparseGrid, n: int, size: int = 32) -> list[TargetView]:
    views = []
    for i in range(n):
        angle = 2 * math.pi * i / n
        c2w = look_at(np.array([2.2 * math.cos(angle), 2.2 * math.sin(angle), 0.8]), (0.0, 0.0, 0.0))
        k = Intrinsics(size * 1.2, size * 1.2, size / 2, size / 2, size, size)
        o, d = rays_from_camera(c2w, k)
        out = render_grid(grid, o.reshape(-1, 3), d.reshape(-1, 3), torch.ones(size * size, 3), AS_SPLATS)
        views.append(TargetView(c2w, k, out.rgb.reshape(size, size, 3)))
    return views


def test_splats_from_a_small_grid_render_like_it_and_distillation_raises_their_psnr():
    grid = ball_grid()
    views = grid_views(grid, 8)
    o, d = zip(*(rays_from_camera(v.c2w, v.k) for v in views))
    weights = max_weights(grid, torch.cat(o).reshape(-1, 3), torch.cat(d).reshape(-1, 3))
    splats = splats_from_grid(grid, FitFrame(), weights, max_splats=100_000, min_weight=0.01)
    assert 200 < splats.count < (weights > 0).sum()  # the seen shell, not every vertex with density
    radii = splats.means.norm(dim=1)
    # The shell the views see, through the ball's soft edge; its faint outskirts count for little.
    assert radii.min() > 0.2 and radii.max() < 0.9
    heavy = splats.opacities() > 0.5
    assert heavy.sum() > 100 and radii[heavy].max() < 0.6
    red = splats.means[:, 0] > 0.15
    colours = splats.colours(torch.nn.functional.normalize(splats.means, dim=1))
    assert (colours[red, 0] > colours[red, 2]).all() and (colours[splats.means[:, 0] < -0.15, 2] > 0.6).all()

    held = grid_views(grid, 3)  # views between the training ones
    for v, a in zip(held, (0.4, 1.3, 2.9)):
        v.c2w = look_at(np.array([2.2 * math.cos(a), 2.2 * math.sin(a), 0.5]), (0.0, 0.0, 0.0))
        o, d = rays_from_camera(v.c2w, v.k)
        v.rgb = render_grid(grid, o.reshape(-1, 3), d.reshape(-1, 3), torch.ones(o.numel() // 3, 3),
                           AS_SPLATS).rgb.reshape(v.rgb.shape)
    score = lambda s: np.mean([psnr(render(s, v.c2w, v.k)["rgb"], v.rgb) for v in held])  # noqa: E731
    start = score(splats)
    assert start > 18
    refined, record = distill(splats, views, (1.0, 1.0, 1.0), seconds=0, window=32, max_steps=150)
    assert record["steps"] == 150 and record["window_psnr_last"] > record["window_psnr_first"]
    assert score(refined) > start + 1.0, (start, score(refined))
    assert refined.count == splats.count and not torch.equal(refined.means, splats.means)


def test_native_row_adam_matches_its_torch_reference_over_steps_on_overlapping_rows():
    """Rows visited unevenly (each with its own step count), a per-row factor on some columns, gradients from tiny to
    huge: the native step (float32) and the torch one (its reference, here in float64) agree after every step, and a
    row not stepped never moves."""
    g = torch.Generator().manual_seed(5)
    data = torch.randn(50, 7, generator=g)
    rates, factor = torch.tensor([0.1, 0.2, 0.05, 0.01, 0.3, 0.02, 0.5]), torch.rand(50, generator=g) + 0.1
    twins = [RowAdam(data.clone(), rates, factor, slice(1, 3)), RowAdam(data.double(), rates, factor, slice(1, 3))]
    twins[1].rates, twins[1].row_factor = rates.double(), factor.double()
    twins[1].steps = twins[1].steps.double()
    for step in range(12):
        rows = torch.randperm(49, generator=g)[: 5 + step * 3]  # row 49 is never stepped
        grad = torch.randn(len(rows), 7, generator=g) * torch.tensor([1e-8, 1e-3, 1.0, 1e3, 1e6, 0.0, 1.0])
        for twin, native in zip(twins, (True, False)):
            twin.step(rows, grad.to(twin.data.dtype), native=native)
        assert torch.allclose(twins[0].data.double(), twins[1].data, rtol=0, atol=1e-6), step
        assert torch.equal(twins[0].steps.double(), twins[1].steps)
    assert torch.equal(twins[0].data[49], data[49]) and not torch.allclose(twins[0].data[:49], data[:49])


def test_error_drawn_windows_go_where_the_splats_differ_from_the_field():
    """Two views, one flat and one with detail in a corner: before any measure the detailed tiles are drawn most;
    once measured, a tile with error is drawn in proportion to it and a perfect one only by the uniform share."""
    flat = torch.full((64, 64, 3), 0.5)
    detailed = flat.clone()
    detailed[:32, :32] = torch.rand(32, 32, 3, generator=torch.Generator().manual_seed(1))
    views = [TargetView(np.eye(4), Intrinsics(64, 64, 32, 32, 64, 64), rgb) for rgb in (flat, detailed)]
    errors = WindowErrors(views, 32, share=0.8, power=1.0)
    rng = np.random.default_rng(0)
    draws = [errors.draw_view(rng) for _ in range(2000)]
    assert 0.85 < np.mean(draws) < 0.95  # 0.8 by error (all to view 1) + 0.2 uniform (half of it)
    tiles = [errors.draw_tile(1, rng) for _ in range(2000)]
    assert 0.8 < np.mean([t == (0, 0) for t in tiles]) < 0.9
    for row, col in [(0, 0), (0, 1), (1, 0), (1, 1)]:
        errors.measured(1, row, col, 0.0)
    errors.measured(1, 1, 1, 0.01)
    tiles = [errors.draw_tile(1, rng) for _ in range(2000)]
    assert 0.8 < np.mean([t == (1, 1) for t in tiles]) < 0.9


@pytest.mark.parametrize("n", [0])
def test_no_splats_render_the_background(n):
    splats = random_splats(n, 1)
    c2w, k = camera([1, 1, 1])
    out = render(splats, c2w, k, background=(0.3, 0.6, 0.9))
    assert torch.allclose(out["rgb"], torch.tensor([0.3, 0.6, 0.9]).expand(k.h, k.w, 3)) and out["opacity"].sum() == 0


def test_a_background_model_s_spheres_as_splats_render_like_the_model_and_mirrored_ones_do_not():
    """Two opaque spheres around an off-centre camera, their colour varying over azimuth and polar angle: the splats
    (one per texel) render what the model's rays see; the same splats mirrored in z do not. The camera stands inside
    the spheres, so splats lie beside and behind it too: their footprints must stay bounded."""
    bg = MultiSphereBackground(centre=(0.1, -0.2, 0.05), r_min=2.0, r_max=20.0, n_spheres=2, height=16, width=32,
                               far_colour=(1.0, 1.0, 1.0))
    j, i = torch.meshgrid(torch.arange(16), torch.arange(32), indexing="ij")
    tex = bg.texture.data
    tex[..., 0] = 5.0
    tex[0, ..., 1], tex[0, ..., 2] = torch.sin(i * 2 * math.pi / 32) * 2, torch.cos(j * math.pi / 16) * 2
    tex[0, ..., 3] = torch.sin(i * 4 * math.pi / 32 + j * 0.5)
    splats = splats_from_background(bg, 4)
    assert splats.count == 2 * 16 * 32 and splats.sh_degree == 1
    mirrored = splats.detached()
    mirrored.means[:, 2] = 2 * 0.05 - mirrored.means[:, 2]
    k = Intrinsics(w=64, h=48, fl_x=40.0, fl_y=40.0, cx=32.0, cy=24.0)
    for target in [(1.0, 0.3, 0.6), (-0.5, 1.0, -0.2), (0.2, 0.1, 1.0)]:
        c2w = look_at((0.3, 0.0, 0.1), target)
        o, d = rays_from_camera(c2w, k)
        truth = bg(o.reshape(-1, 3), d.reshape(-1, 3)).reshape(k.h, k.w, 3)
        assert psnr(render(splats, c2w, k)["rgb"], truth) > 25
        assert psnr(render(mirrored, c2w, k)["rgb"], truth) < 18


def test_a_camera_outside_an_inner_sphere_sees_its_splats_behind_the_scene_as_the_model_does():
    """Cameras circling at 3 units around an opaque sphere of radius 1.2, red on its +x half and blue on its -x half:
    the model reads a sphere only where a ray leaves it, so a camera on the +x side sees blue at the middle of its view.
    The sphere's splats, pushed out beyond the cameras, show that too; left at radius 1.2 they would show the near
    side's red, a veil between the camera and what it looks at."""
    bg = MultiSphereBackground(centre=(0.0, 0.0, 0.0), r_min=1.2, r_max=30.0, n_spheres=2, height=16, width=32,
                               far_colour=(1.0, 1.0, 1.0))
    j, i = torch.meshgrid(torch.arange(16), torch.arange(32), indexing="ij")
    azimuth = -math.pi + (i + 0.5) * 2 * math.pi / 32
    tex = bg.texture.data
    tex[..., 0] = 5.0
    red = torch.cos(azimuth) > 0
    tex[0, ..., 1], tex[0, ..., 2], tex[0, ..., 3] = torch.where(red, 4.0, -4.0), -4.0, torch.where(red, -4.0, 4.0)
    k = Intrinsics(w=48, h=36, fl_x=30.0, fl_y=30.0, cx=24.0, cy=18.0)
    reach = 3.0
    pushed, left = splats_from_background(bg, 1, camera_reach=reach), splats_from_background(bg, 1)
    assert pushed.means.norm(dim=1).min() >= reach and left.means.norm(dim=1).min() < 1.3
    for angle in (-0.4, 0.0, 0.5):
        c2w = look_at((reach * math.cos(angle), reach * math.sin(angle), 0.3), (0.0, 0.0, 0.0))
        o, d = rays_from_camera(c2w, k)
        middle = lambda image: image.reshape(k.h, k.w, 3)[14:22, 20:28].reshape(-1, 3).mean(0)  # noqa: E731
        truth = middle(bg(o.reshape(-1, 3), d.reshape(-1, 3)))
        assert truth[2] > 0.9 and truth[0] < 0.1  # the far side: blue
        assert (middle(render(pushed, c2w, k)["rgb"]) - truth).abs().max() < 0.1
        assert (middle(render(left, c2w, k)["rgb"]) - truth).abs().max() > 0.5
