"""A multi-sphere-image background for unbounded scenes, composited behind the foreground grid.

In the spirit of the Plenoxels paper's background model: concentric spheres around the foreground,
from just outside the foreground box to a large radius, spaced uniformly in inverse radius (so the
near background, where parallax is visible, gets most of the layers). Each sphere carries an
equirectangular texture of density and colour. A ray's background colour is the front-to-back
composite of the spheres it meets; whatever transmittance is left sees a constant colour.

The renderer adds this colour behind the foreground (rgb = foreground + T_final * background), so the
module is plain torch: the fit computes `rgb = bg(o, d)`, the kernel returns d(loss)/d(rgb), and
`rgb.backward(grad)` trains the textures.

Where a ray meets a sphere: from its origin o and unit direction d, the sphere |p - centre| = r is met
at t = -b + sqrt(b^2 - c), b = (o - centre).d, c = |o - centre|^2 - r^2: the exit point. From inside a
sphere that is its only crossing; from outside (a camera beyond the inner spheres) it is the far side,
behind whatever the ray passes in the middle, which keeps every sphere behind the foreground. Spheres a
ray misses (b^2 < c), or whose exit lies behind the origin, add nothing.

Opacity of a layer is alpha = 1 - exp(-relu(sigma)), colour is sigmoid(logit): a layer is a thin shell,
so its density is already integrated across it.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import torch
import torch.nn.functional as F

from plenoxels.errors import UserError

# Far spheres are placed at most this far (in foreground-box half-diagonals); beyond it parallax is nil.
DEFAULT_FAR_RATIO = 1000.0


class MultiSphereBackground(torch.nn.Module):
    """Concentric textured spheres; forward(o, d) -> background colour [B, 3] per ray."""

    def __init__(self, centre: Sequence[float] = (0.0, 0.0, 0.0), r_min: float = math.sqrt(3) * 1.05,
                 r_max: float = math.sqrt(3) * 1.05 * DEFAULT_FAR_RATIO, n_spheres: int = 16,
                 height: int = 32, width: int = 64, far_colour: Sequence[float] = (0.0, 0.0, 0.0),
                 init_density: float = 0.1, tv_density: float = 1e-3, tv_colour: float = 1e-3):
        super().__init__()
        if not (0 < r_min < r_max and math.isfinite(r_max)):
            raise UserError(f"background spheres need 0 < r_min < r_max < inf, got r_min={r_min}, r_max={r_max}")
        if n_spheres < 1 or height < 2 or width < 3:
            raise UserError(f"the background needs at least 1 sphere and a 2x3 texture, got {n_spheres} spheres "
                            f"of {height}x{width}")
        if len(far_colour) != 3:
            raise UserError(f"background far_colour must be three numbers (RGB in [0, 1]), got {list(far_colour)}")
        self.r_min, self.r_max = float(r_min), float(r_max)
        self.tv_density, self.tv_colour = float(tv_density), float(tv_colour)
        inverse = torch.linspace(1.0 / r_min, 1.0 / r_max, n_spheres, dtype=torch.float64)
        self.register_buffer("centre", torch.tensor(list(centre), dtype=torch.float32))
        self.register_buffer("radii", (1.0 / inverse).float())
        self.register_buffer("far_colour", torch.tensor(list(far_colour), dtype=torch.float32))
        # One texture per sphere, spheres on the batch axis so a single grid_sample reads them all.
        self.density = torch.nn.Parameter(torch.full((n_spheres, 1, height, width), float(init_density)))
        self.colour = torch.nn.Parameter(torch.zeros(n_spheres, 3, height, width))

    @classmethod
    def around_box(cls, bbox_min: Sequence[float], bbox_max: Sequence[float], margin: float = 1.05,
                   far_ratio: float = DEFAULT_FAR_RATIO, **kwargs) -> "MultiSphereBackground":
        """Spheres centred on the foreground box, the first just outside its corners."""
        lo, hi = torch.tensor(list(bbox_min), dtype=torch.float64), torch.tensor(list(bbox_max), dtype=torch.float64)
        if not bool((hi > lo).all()):
            raise UserError(f"the foreground box must have max > min on every axis, got {list(bbox_min)}, {list(bbox_max)}")
        r_min = float((hi - lo).norm() / 2) * margin
        return cls(centre=((lo + hi) / 2).tolist(), r_min=r_min, r_max=r_min * far_ratio, **kwargs)

    # ---- description --------------------------------------------------------------------------
    @property
    def n_spheres(self) -> int:
        return self.density.shape[0]

    def config(self) -> dict[str, Any]:
        """What rebuilds an empty model of this shape (the textures come from state_dict)."""
        return {"centre": self.centre.tolist(), "r_min": self.r_min, "r_max": self.r_max,
                "n_spheres": self.n_spheres, "height": self.density.shape[2], "width": self.density.shape[3],
                "far_colour": self.far_colour.tolist(), "tv_density": self.tv_density, "tv_colour": self.tv_colour}

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> "MultiSphereBackground":
        return cls(**config)

    def parameter_count(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def memory_bytes(self) -> int:
        """Bytes held by the parameters and buffers (the optimiser's state comes on top)."""
        return sum(t.numel() * t.element_size() for t in [*self.parameters(), *self.buffers()])

    # ---- rendering ----------------------------------------------------------------------------
    def _texture_coordinates(self, o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """grid_sample coordinates [K, B, 1, 2] of each ray's exit point on each sphere, and which hits count [K, B]."""
        rel = o - self.centre.to(o.dtype)
        unit = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        b = (rel * unit).sum(-1)                                                  # [B]
        c = (rel * rel).sum(-1)
        radii = self.radii.to(o.dtype)[:, None]                                  # [K, 1]
        disc = b * b - c + radii * radii                                          # [K, B]
        t = -b + disc.clamp_min(0).sqrt()
        valid = (disc >= 0) & (t > 0)
        # Direction of the exit point from the centre.
        p = (rel[None] + t[..., None] * unit[None]) / radii[..., None]
        p = p / p.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        azimuth = torch.atan2(p[..., 1], p[..., 0])                               # [-pi, pi]
        elevation = torch.asin(p[..., 2].clamp(-1.0, 1.0))                       # [-pi/2, pi/2], z up
        width = self.density.shape[3]
        # The texture is padded with one wrapped column on each side, so the seam at azimuth +-pi
        # interpolates across it; map [-1, 1] over the W real columns into the W + 2 padded ones.
        x = (azimuth / math.pi) * width / (width + 2)
        y = -elevation / (math.pi / 2)
        return torch.stack([x, y], dim=-1)[:, :, None, :], valid

    def forward(self, o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Background colour [B, 3] of rays with origins o [B, 3] and directions d [B, 3] (any length)."""
        if o.shape != d.shape or o.dim() != 2 or o.shape[-1] != 3:
            raise ValueError(f"background rays must be [B, 3] origins and directions, got {tuple(o.shape)}, {tuple(d.shape)}")
        dtype = self.density.dtype
        grid, valid = self._texture_coordinates(o.to(dtype), d.to(dtype))
        texture = torch.cat([self.density, self.colour], dim=1)
        texture = torch.cat([texture[..., -1:], texture, texture[..., :1]], dim=-1)
        samples = F.grid_sample(texture, grid, mode="bilinear", padding_mode="border", align_corners=False)
        samples = samples[..., 0]                                                  # [K, 4, B]
        alpha = (1 - torch.exp(-F.relu(samples[:, 0]))) * valid.to(dtype)        # [K, B]
        rgb = torch.sigmoid(samples[:, 1:])                                       # [K, 3, B]
        # Transmittance before each sphere, front (small radius) to back.
        transmittance = torch.cumprod(torch.cat([torch.ones_like(alpha[:1]), 1 - alpha], dim=0), dim=0)
        weights = alpha * transmittance[:-1]                                      # [K, B]
        colour = (weights[:, None] * rgb).sum(0).T                                # [B, 3]
        return colour + transmittance[-1][:, None] * self.far_colour.to(dtype)

    # ---- regulariser --------------------------------------------------------------------------
    def regularizer(self) -> torch.Tensor:
        """Total variation (mean squared neighbour difference) over each sphere's texture, wrapping in
        azimuth, weighted by tv_density and tv_colour."""
        def tv(x: torch.Tensor) -> torch.Tensor:
            across = x - torch.roll(x, shifts=1, dims=-1)
            down = x[..., 1:, :] - x[..., :-1, :]
            return across.pow(2).mean() + down.pow(2).mean()
        return self.tv_density * tv(self.density) + self.tv_colour * tv(self.colour)
