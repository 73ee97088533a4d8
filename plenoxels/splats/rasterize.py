"""A differentiable splat rasterizer for the CPU: the projection in PyTorch (autograd gives its gradients), the
compositing by the native core (csrc/cpu_splats.cpp, forward and backward) or, as its reference, by (splat, pixel)
pairs in PyTorch.

It follows the ellipse kernel of glTF's KHR_gaussian_splatting and the original 3D Gaussian Splatting renderer:
1. Each splat's mean goes into the camera (OpenCV axes: x right, y down, z forward); splats closer than `near` drop.
2. EWA: its covariance projects to the image as J W S W^T J^T (W the world-to-camera rotation, J the Jacobian of the
   perspective divide at the mean), plus 0.3 px^2 on the diagonal (the low-pass filter every 3DGS renderer adds).
   J is taken at the mean's direction clamped to 1.3 times the half field of view, as the original renderer does:
   beside the camera and just in front of it J grows without bound, and one such splat would cover the whole view.
3. Its footprint is the box 3 sigma around the projected mean; every (splat, pixel) pair inside is kept.
4. At each pixel centre alpha = min(0.99, opacity exp(-d^T S'^-1 d / 2)); pairs under 1/255 are skipped.
5. Per pixel the splats composite front to back in order of camera depth: C = sum c_i a_i prod_{j<i} (1 - a_j), then
   the background times what light remains; a splat that would leave less than 1e-4 of the light, and all behind it,
   are left out (the original renderer's early stop).
Pixel (i, j) has its centre at (i + 0.5, j + 0.5) in the intrinsics' convention (plenoxels/core/cameras.py).
"""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch

from plenoxels.core.cameras import Intrinsics
from plenoxels.core.native import ops
from plenoxels.splats.model import Splats, quat_to_matrix

LOW_PASS = 0.3
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
STOP_TRANSMITTANCE = 1e-4
NEAR = 0.01
FOV_CLAMP = 1.3
# Pairs made at once while rendering without gradients: bounds the memory of a full-size view.
PAIRS_PER_PASS = 1 << 21


@contextmanager
def one_thread():
    """Torch on one thread for the duration: a window's tensors hold 1e4-1e5 rows, where OpenMP's fork, join and
    spin-waiting cost more than the work, and on a busy machine far more (bench/README.md, "Splats")."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


@dataclass
class Projected:
    means2d: torch.Tensor  # [M, 2] pixel-index coordinates (centres at integers)
    conics: torch.Tensor  # [M, 3] the inverse 2D covariance's (a, b, c)
    radii: torch.Tensor  # [M] 3 sigma, in pixels
    depth: torch.Tensor  # [M] camera z
    colours: torch.Tensor  # [M, 3]
    opacities: torch.Tensor  # [M]


def project(splats: Splats, c2w, k: Intrinsics, near: float = NEAR) -> Projected:
    """Steps 1-2 for the splats in front of the camera (c2w: OpenGL camera-to-world, as the poses keep it). The 2x3
    and 3x3 products are written out per entry: batched matrix products of that size cost torch more than the
    arithmetic, forward and backward."""
    c2w = torch.as_tensor(np.asarray(c2w), dtype=splats.means.dtype)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=c2w.dtype))
    rot = flip @ c2w[:3, :3].T  # world -> OpenCV camera
    centre = c2w[:3, 3]
    p = (splats.means - centre) @ rot.T
    front = p[:, 2] > near
    if not bool(front.all()):
        splats, p = splats.subset(front), p[front]
    x, y, z = p.unbind(-1)
    lim_x, lim_y = FOV_CLAMP * max(k.cx, k.w - k.cx) / k.fl_x, FOV_CLAMP * max(k.cy, k.h - k.cy) / k.fl_y
    tx, ty = (x / z).clamp(-lim_x, lim_x) * z, (y / z).clamp(-lim_y, lim_y) * z
    # Rows of J W (J the Jacobian of the perspective divide, W the rotation into the camera), then of J W R S.
    jw0 = (k.fl_x / z)[:, None] * rot[0] - (k.fl_x * tx / (z * z))[:, None] * rot[2]
    jw1 = (k.fl_y / z)[:, None] * rot[1] - (k.fl_y * ty / (z * z))[:, None] * rot[2]
    shape = quat_to_matrix(splats.quats) * torch.exp(splats.log_scales)[:, None, :]
    t0 = (jw0[:, :, None] * shape).sum(1)
    t1 = (jw1[:, :, None] * shape).sum(1)
    a, b, c = (t0 * t0).sum(1) + LOW_PASS, (t0 * t1).sum(1), (t1 * t1).sum(1) + LOW_PASS
    det = (a * c - b * b).clamp_min(1e-12)
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)
    mid = (a + c) / 2
    largest = mid + torch.sqrt((mid * mid - det).clamp_min(0.0))
    means2d = torch.stack([k.fl_x * x / z + k.cx - 0.5, k.fl_y * y / z + k.cy - 0.5], dim=-1)
    dirs = splats.means - centre
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return Projected(means2d, conics, 3.0 * torch.sqrt(largest), z, splats.colours(dirs), splats.opacities())


@dataclass
class Footprints:
    """Where each splat lands in a view, bounded by its largest scale (a sphere): centre (u, v) in pixel-index
    coordinates, 3 sigma reach in pixels plus one, and whether it lies in front of the camera."""
    u: torch.Tensor
    v: torch.Tensor
    reach: torch.Tensor
    front: torch.Tensor

    def in_window(self, window: tuple[int, int, int, int]) -> torch.Tensor:
        """Indices of the splats that may touch the window (x0, y0, w, h)."""
        x0, y0, w, h = window
        touch = (self.front & (self.u + self.reach >= x0) & (self.u - self.reach <= x0 + w - 1)
                 & (self.v + self.reach >= y0) & (self.v - self.reach <= y0 + h - 1))
        return torch.nonzero(touch).squeeze(1)


def footprints(splats: Splats, c2w, k: Intrinsics, near: float = NEAR) -> Footprints:
    """Every splat's footprint in the view, found without projecting its covariance."""
    with torch.no_grad():
        c2w = torch.as_tensor(np.asarray(c2w), dtype=splats.means.dtype)
        flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=c2w.dtype))
        p = (splats.means - c2w[:3, 3]) @ (flip @ c2w[:3, :3].T).T
        z = p[:, 2].clamp_min(near)
        scales = splats.log_scales
        largest = torch.maximum(torch.maximum(scales[:, 0], scales[:, 1]), scales[:, 2])  # max(dim=1) is slower
        reach = 3.0 * torch.exp(largest) * max(k.fl_x, k.fl_y) / z + 1.0
        return Footprints(k.fl_x * p[:, 0] / z + k.cx - 0.5, k.fl_y * p[:, 1] / z + k.cy - 0.5, reach, p[:, 2] > near)


def _pairs(proj: Projected, window: tuple[int, int, int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Step 3 inside window (x0, y0, w, h): splat index and window pixel index of every pair."""
    x0, y0, w, h = window
    with torch.no_grad():
        m, r = proj.means2d.detach(), proj.radii.detach()
        lo_x = torch.clamp(torch.ceil(m[:, 0] - r), min=x0).long()
        hi_x = torch.clamp(torch.floor(m[:, 0] + r), max=x0 + w - 1).long()
        lo_y = torch.clamp(torch.ceil(m[:, 1] - r), min=y0).long()
        hi_y = torch.clamp(torch.floor(m[:, 1] + r), max=y0 + h - 1).long()
        nx, ny = (hi_x - lo_x + 1).clamp_min(0), (hi_y - lo_y + 1).clamp_min(0)
        counts = nx * ny
        splat = torch.repeat_interleave(torch.arange(len(counts)), counts)
        first = torch.cumsum(counts, 0) - counts
        local = torch.arange(len(splat)) - first[splat]
        px = lo_x[splat] + local % nx[splat]
        py = lo_y[splat] + local // nx[splat]
    return splat, (py - y0) * w + (px - x0)


def _alphas(proj: Projected, splat: torch.Tensor, pixel: torch.Tensor, window_xy: torch.Tensor) -> torch.Tensor:
    d = window_xy[pixel] - proj.means2d[splat]
    conic = proj.conics[splat]
    power = -0.5 * (conic[:, 0] * d[:, 0] ** 2 + 2 * conic[:, 1] * d[:, 0] * d[:, 1] + conic[:, 2] * d[:, 1] ** 2)
    return torch.clamp_max(proj.opacities[splat] * torch.exp(power.clamp_max(0.0)), ALPHA_MAX)


def _transmittance(alpha: torch.Tensor, pixel: torch.Tensor) -> torch.Tensor:
    """Per pair (sorted by pixel, then front to back), the light left in front of it: prod (1 - a) over the pixel's
    earlier pairs (a cumulative sum of logs, restarted at each pixel)."""
    log_clear = torch.log1p(-alpha).double()
    before = torch.cumsum(log_clear, 0) - log_clear
    with torch.no_grad():
        starts = torch.ones_like(pixel, dtype=torch.bool)
        starts[1:] = pixel[1:] != pixel[:-1]
        first = torch.nonzero(starts).squeeze(1)[torch.cumsum(starts.long(), 0) - 1]
    return torch.exp(before - before[first]).to(alpha.dtype)


def composite(proj: Projected, splat: torch.Tensor, pixel: torch.Tensor, n_pixels: int, window_xy: torch.Tensor,
              background: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Steps 4-5 over the given pairs: rgb [n_pixels, 3] and opacity [n_pixels]. window_xy [n_pixels, 2]: the pixels'
    index coordinates. Which pairs count is settled without gradients first (those under ALPHA_MIN and those behind
    the point where a pixel's light falls under STOP_TRANSMITTANCE drop), so the graph holds only the pairs seen."""
    with torch.no_grad():
        alpha = _alphas(proj, splat, pixel, window_xy)
        keep = alpha >= ALPHA_MIN
        splat, pixel, alpha = splat[keep], pixel[keep], alpha[keep]
        rank = torch.empty(len(proj.depth), dtype=torch.long)
        rank[torch.argsort(proj.depth.detach())] = torch.arange(len(proj.depth))
        order = torch.argsort(pixel * len(proj.depth) + rank[splat])
        splat, pixel, alpha = splat[order], pixel[order], alpha[order]
        seen = _transmittance(alpha, pixel) * (1 - alpha) >= STOP_TRANSMITTANCE
        splat, pixel = splat[seen], pixel[seen]
    alpha = _alphas(proj, splat, pixel, window_xy)
    weight = alpha * _transmittance(alpha, pixel)
    rgb = torch.zeros(n_pixels, 3, dtype=alpha.dtype).index_add(0, pixel, weight[:, None] * proj.colours[splat])
    opacity = torch.zeros(n_pixels, dtype=alpha.dtype).index_add(0, pixel, weight)
    return rgb + (1 - opacity)[:, None] * background, opacity


class _NativeComposite(torch.autograd.Function):
    """Steps 4-5 by the native core (csrc/cpu_splats.cpp), the gradients by its backward kernel."""

    @staticmethod
    def forward(ctx, means2d, conics, colours, opacities, radii, order, window, background):
        inputs = [t.detach().float().contiguous() for t in (means2d, conics, colours, opacities, radii)]
        rgb, opacity, ends, light = ops.splat_composite(*inputs, order, *window, background)
        ctx.save_for_backward(*inputs, order, background, ends, light)
        ctx.window = window
        return rgb, opacity

    @staticmethod
    def backward(ctx, grad_rgb, grad_opacity):
        *inputs, order, background, ends, light = ctx.saved_tensors
        grads = ops.splat_composite_backward(*inputs, order, *ctx.window, background, ends, light,
                                             grad_rgb.float().contiguous(), grad_opacity.float().contiguous())
        return (*grads, None, None, None, None)


def render_window(proj: Projected, window: tuple[int, int, int, int], background,
                  native: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """rgb [h, w, 3] and opacity [h, w] of the window (x0, y0, w, h) of the image: by the native core, or with
    native=False by the (splat, pixel) pairs in torch, its reference."""
    x0, y0, w, h = window
    background = torch.as_tensor(background, dtype=proj.means2d.dtype).reshape(3)
    if native:
        order = torch.argsort(proj.depth.detach())
        rgb, opacity = _NativeComposite.apply(proj.means2d, proj.conics, proj.colours, proj.opacities,
                                              proj.radii.detach(), order, window, background.float().contiguous())
        return rgb.reshape(h, w, 3).to(proj.means2d.dtype), opacity.reshape(h, w).to(proj.means2d.dtype)
    j, i = torch.meshgrid(torch.arange(y0, y0 + h), torch.arange(x0, x0 + w), indexing="ij")
    window_xy = torch.stack([i, j], dim=-1).reshape(-1, 2).to(proj.means2d.dtype)
    splat, pixel = _pairs(proj, window)
    rgb, opacity = composite(proj, splat, pixel, w * h, window_xy, background)
    return rgb.reshape(h, w, 3), opacity.reshape(h, w)


def render(splats: Splats, c2w, k: Intrinsics, background=(1.0, 1.0, 1.0)) -> dict[str, torch.Tensor]:
    """A whole view without gradients: {"rgb" [h, w, 3], "opacity" [h, w]}, rendered in bands of rows so that no pass
    holds more than PAIRS_PER_PASS pairs."""
    with torch.no_grad(), one_thread():
        proj = project(splats, c2w, k)
        area = ((2 * proj.radii + 1) ** 2).sum().item()
        rows = max(1, min(k.h, int(k.h * PAIRS_PER_PASS / max(area, 1.0))))
        bands = [render_window(proj, (0, y, k.w, min(rows, k.h - y)), background) for y in range(0, k.h, rows)]
    return {"rgb": torch.cat([b[0] for b in bands]).clamp(0.0, 1.0), "opacity": torch.cat([b[1] for b in bands])}
