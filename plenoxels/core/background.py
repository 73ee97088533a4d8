"""A multi-sphere-image background for unbounded scenes, composited behind the foreground grid.

In the spirit of the Plenoxels paper's background model: concentric spheres around the foreground,
from just outside the foreground box to a large radius, spaced uniformly in inverse radius (so the
near background, where parallax is visible, gets most of the layers). Each sphere carries an
equirectangular texture of density and colour. A ray's background colour is the front-to-back
composite of the spheres it meets; whatever transmittance is left sees a constant colour.

The renderer adds this colour behind the foreground (rgb = foreground + T_final * background): the fit
asks the native core for each ray's background colour, the grid's kernel returns d(loss)/d(colour), and
the native background_backward turns that into gradients of the texels the batch read, which a sparse
RMSProp step (BackgroundOptimiser) updates, as the grid's rows are. The math is stated once more in
reference.background_colour, the PyTorch twin the tests hold the kernels to. The textures are one table
[K, H, W, 4] (raw density, colour logits R, G, B), a row per texel.

Where a ray meets a sphere: from its origin o and unit direction d, the sphere |p - centre| = r is met
at t = -b + sqrt(b^2 - c), b = (o - centre).d, c = |o - centre|^2 - r^2: the exit point. From inside a
sphere that is its only crossing; from outside (a camera beyond the inner spheres) it is the far side,
behind whatever the ray passes in the middle, which keeps every sphere behind the foreground. Spheres a
ray misses (b^2 < c), or whose exit lies behind the origin, add nothing.

Opacity of a layer is alpha = 1 - exp(-relu(sigma)), colour is sigmoid(logit): a layer is a thin shell,
so its density is already integrated across it. A ray stops once less than BACKGROUND_STOP_TRANSMITTANCE of its
light gets through; what is left sees the far colour.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import torch

from plenoxels.core import native
from plenoxels.core.errors import UserError
from plenoxels.core.optim import scratch_slots

# A ray stops compositing spheres once this little of its light gets through (the grid's rays stop the same way), so
# the spheres behind an opaque one cost nothing; PLX_BG_STOP_TRANSMITTANCE in csrc/plenoxels_math.h.
BACKGROUND_STOP_TRANSMITTANCE = 1e-4
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
        texture = torch.zeros(n_spheres, height, width, 4)
        texture[..., 0] = float(init_density)
        self.texture = torch.nn.Parameter(texture, requires_grad=False)

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
        return self.texture.shape[0]

    @property
    def density(self) -> torch.Tensor:
        """Raw density [K, 1, H, W], a view of the texture table."""
        return self.texture[..., :1].permute(0, 3, 1, 2)

    @property
    def colour(self) -> torch.Tensor:
        """Colour logits [K, 3, H, W], a view of the texture table."""
        return self.texture[..., 1:].permute(0, 3, 1, 2)

    @property
    def rows(self) -> torch.Tensor:
        """The texture as a table of texel rows [K*H*W, 4] (a view)."""
        return self.texture.data.view(-1, 4)

    def config(self) -> dict[str, Any]:
        """What rebuilds an empty model of this shape (the textures come from state_dict)."""
        return {"centre": self.centre.tolist(), "r_min": self.r_min, "r_max": self.r_max,
                "n_spheres": self.n_spheres, "height": self.texture.shape[1], "width": self.texture.shape[2],
                "far_colour": self.far_colour.tolist(), "tv_density": self.tv_density, "tv_colour": self.tv_colour}

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> "MultiSphereBackground":
        return cls(**config)

    def load_state_dict(self, state: dict, strict: bool = True):
        """Also reads models saved with separate density [K, 1, H, W] and colour [K, 3, H, W] textures."""
        if "density" in state and "texture" not in state:
            state = dict(state)
            density, colour = state.pop("density"), state.pop("colour")
            state["texture"] = torch.cat([density, colour], 1).permute(0, 2, 3, 1).contiguous()
        return super().load_state_dict(state, strict)

    def parameter_count(self) -> int:
        return self.texture.numel()

    def memory_bytes(self) -> int:
        """Bytes held by the parameters and buffers (the optimiser's state comes on top)."""
        return sum(t.numel() * t.element_size() for t in [*self.parameters(), *self.buffers()])

    # ---- rendering ----------------------------------------------------------------------------
    def forward(self, o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Background colour [B, 3] of rays with origins o [B, 3] and directions d [B, 3] (any length)."""
        if o.shape != d.shape or o.dim() != 2 or o.shape[-1] != 3:
            raise ValueError(f"background rays must be [B, 3] origins and directions, got {tuple(o.shape)}, {tuple(d.shape)}")
        device = self.texture.device
        o = o.detach().to(device=device, dtype=torch.float32).contiguous()
        d = d.detach().to(device=device, dtype=torch.float32).contiguous()
        return native.ops.background_render(o, d, self.centre, self.radii, self.texture.data, self.far_colour)

    # ---- regulariser --------------------------------------------------------------------------
    def tv_grad(self, rows: torch.Tensor) -> torch.Tensor:
        """d/d(texel rows [R, 4]) of the textures' total variation, the mean squared difference between
        neighbours across (wrapping in azimuth) and down each sphere's texture, weighted by tv_density
        (channel 0) and tv_colour (channels 1-3); only at `rows`, so a step pays for the texels it touched."""
        k, h, w, _ = self.texture.shape
        table = self.rows
        x = rows % w
        y = (rows // w) % h
        base = rows - x - y * w
        left, right = base + y * w + (x - 1) % w, base + y * w + (x + 1) % w
        here = table[rows]
        grad = 2 * (2 * here - table[left] - table[right]) / (k * h * w)
        up_diff = torch.where((y > 0)[:, None], here - table[(rows - w).clamp_min(0)], torch.zeros_like(here))
        down_diff = torch.where((y < h - 1)[:, None], table[(rows + w).clamp_max(table.shape[0] - 1)] - here,
                                torch.zeros_like(here))
        grad = grad + 2 * (up_diff - down_diff) / (k * (h - 1) * w)
        return grad * self._tv_weights(grad)

    def tv_grad_all(self) -> torch.Tensor:
        """tv_grad at every texel row [K*H*W, 4], by whole-table shifts."""
        k, h, w, _ = self.texture.shape
        x = self.texture.data
        grad = 2 * (2 * x - torch.roll(x, 1, dims=2) - torch.roll(x, -1, dims=2)) / (k * h * w)
        down = torch.zeros_like(x)
        down[:, 1:] += x[:, 1:] - x[:, :-1]
        down[:, :-1] -= x[:, 1:] - x[:, :-1]
        return (grad + 2 * down / (k * (h - 1) * w)).view(-1, 4) * self._tv_weights(x)

    def _tv_weights(self, like: torch.Tensor) -> torch.Tensor:
        # The mean over a texture's elements: the colour's three channels share tv_colour.
        return torch.tensor([self.tv_density] + [self.tv_colour / 3] * 3, dtype=like.dtype, device=like.device)


# Above this share of the texels touched in a step, the TV gradient of a small table is taken over all of it.
DENSE_TV_SHARE = 0.25
# Below it, TV looks at most this many of the touched texels a step (drawn at random, the gradient scaled up to stand
# for all of them), as the grid's TV samples its vertices: a large texture's TV then costs what a small one's does.
TV_SAMPLE_ROWS = 16384


class BackgroundOptimiser:
    """Sparse RMSProp over the background's texels: gradients land in a table shaped like the texture's rows with
    a record of the rows touched, and a step updates (and clears) only those, with their TV gradient added."""

    def __init__(self, background: MultiSphereBackground, lr: float, beta: float = 0.95, eps: float = 1e-8, seed: int = 0):
        self.background, self.lr, self.beta, self.eps = background, float(lr), float(beta), float(eps)
        rows = background.rows
        self.grad = torch.zeros_like(rows)
        self.touched_mask = torch.zeros(rows.shape[0], dtype=torch.uint8, device=rows.device)
        self.touched_rows = torch.zeros(rows.shape[0], dtype=torch.int32, device=rows.device)
        self.num_touched = 0
        # The CPU kernel's per-thread gradient tables (pages mapped on first touch; empty on a GPU).
        table = self.grad.numel() * self.grad.element_size() + rows.shape[0]
        self.scratch = tuple(native.ops.grad_scratch(self.grad, scratch_slots(table)))
        self.record = None  # (origins, dirs, layer texels, layer weights) of the last forward's batch
        self.second_moment = torch.zeros_like(rows)
        self.generator = torch.Generator(device=rows.device).manual_seed(seed)

    def forward(self, o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """The background colours [B, 3] of a training batch (as the model's forward), keeping on a CPU where each ray
        met each sphere, so that the backward of this batch reads the texels back instead of intersecting again."""
        bg = self.background
        if bg.texture.device.type != "cpu":
            self.record = None
            return bg(o, d)
        shape = (o.shape[0], bg.n_spheres, 4)
        self.record = (o, d, torch.empty(shape, dtype=torch.int32), torch.empty(shape, dtype=torch.float32))
        o, d = (t.detach().to(dtype=torch.float32).contiguous() for t in (o, d))
        return native.ops.background_render(o, d, bg.centre, bg.radii, bg.texture.data, bg.far_colour, *self.record[2:])

    def on_rays(self, o: torch.Tensor, d: torch.Tensor) -> tuple | None:
        """The background's arguments on a training batch's rays with a fresh layer record, for a grid's loss that
        draws the spheres in its own pass only where light gets past the grid (render.loss_and_grad_before_spheres),
        after which this optimiser's backward reads the record; None on a GPU, which draws every ray beforehand."""
        bg = self.background
        if bg.texture.device.type != "cpu":
            return None
        shape = (o.shape[0], bg.n_spheres, 4)
        self.record = (o, d, torch.empty(shape, dtype=torch.int32), torch.empty(shape, dtype=torch.float32))
        o_f, d_f = (t.detach().to(dtype=torch.float32).contiguous() for t in (o, d))
        return (o_f, d_f, bg.centre, bg.radii, bg.texture.data, bg.far_colour, *self.record[2:])

    def backward(self, o: torch.Tensor, d: torch.Tensor, rgb: torch.Tensor, grad_rgb: torch.Tensor) -> None:
        """Adds d(loss)/d(texels) for rays o, d [B, 3] whose background colours were rgb [B, 3] (the model's
        forward, or this optimiser's, whose record of the layers it then uses), given d(loss)/d(those colours) [B, 3]."""
        bg = self.background
        device = bg.texture.device
        record = self.record if self.record is not None and self.record[0] is o and self.record[1] is d else None
        self.record = None
        o, d, rgb, g = (t.detach().to(device=device, dtype=torch.float32).contiguous() for t in (o, d, rgb, grad_rgb))
        layers = record[2:] if record is not None else (None, None)
        self.num_touched = native.ops.background_backward(
            o, d, bg.centre, bg.radii, bg.texture.data, bg.far_colour, rgb, g, *layers, self.grad, self.touched_mask,
            self.touched_rows, self.num_touched, *self.scratch)

    def step(self) -> None:
        if self.num_touched > DENSE_TV_SHARE * self.grad.shape[0] and self.grad.shape[0] <= 8 * TV_SAMPLE_ROWS:
            # Most texels touched (small textures, big batches): one pass over the whole table beats gathering.
            self.grad += self.background.tv_grad_all() * (self.touched_mask != 0)[:, None]
        else:
            rows = self.touched_rows[: self.num_touched].long()
            if len(rows) > TV_SAMPLE_ROWS:
                picked = rows[torch.randint(len(rows), (TV_SAMPLE_ROWS,), generator=self.generator, device=rows.device)]
                self.grad.index_add_(0, picked, self.background.tv_grad(picked) * (len(rows) / TV_SAMPLE_ROWS))
            else:
                self.grad[rows] += self.background.tv_grad(rows)
        native.ops.rmsprop_step(self.background.rows, self.second_moment, self.grad, self.touched_mask,
                                self.touched_rows, self.num_touched, 4, self.lr, self.lr, self.beta, self.eps,
                                None, 1, None, None)
        self.num_touched = 0

    def state_dict(self) -> dict:
        return {"lr": self.lr, "beta": self.beta, "eps": self.eps, "second_moment": self.second_moment,
                "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        if state["second_moment"].shape != self.second_moment.shape:
            raise ValueError("background optimiser state does not match the background it is loaded for")
        self.lr, self.beta, self.eps = state["lr"], state["beta"], state["eps"]
        self.second_moment = state["second_moment"].to(self.second_moment.device).clone()
        if "generator" in state:
            self.generator.set_state(state["generator"])
