"""Where the render still disagrees with the photos: a map of squared error per block of each training photo, from
which a share of every batch is drawn.

Every pixel of a capture is not equally hard. An object on a backdrop fills a fraction of its photos, and once the
backdrop renders right its pixels teach the grid nothing; an edge, a print or a thin part stays wrong for most of a
fit. Drawing rays by the error their block still holds spends the steps where the photos still have something to
say (as instant-ngp's error map does). The rest of each batch stays uniform, so no pixel is ever left out and what
renders right stays right. Measured, it buys objects at `default` 0.3-0.4 dB with a third fewer last-level steps,
lego at `fast` about 0.2 dB at equal time and fox and ball nothing, so `fit.error_share` is 0 but for objects at
`default` (configs/scene_types/object.yaml; bench/README.md, "Fit: quality against cost").

The map is measured, not learned from the batches: the fit renders every `stride`-th row and column of each photo
with the model as it stands (Fitter.measure_photos), and the squared error is averaged over blocks of `2 * stride`
pixels (four measured pixels a block). It is deterministic (no draw from the batches' generator), so a resumed fit
measures the same map.
"""
from __future__ import annotations

import math

import torch

# Measured pixels along each side of a block: the block is this many strides across.
PIXELS_PER_BLOCK_SIDE = 2
# The blocks are at least this many pixels across (a map finer than the photos' own grain measures noise).
MIN_BLOCK = 4


def measure_stride(sizes: torch.Tensor, rays: int) -> int:
    """The pixel stride at which a measurement of photos of these [N, 2] sizes renders about `rays` rays."""
    pixels = float((sizes[:, 0].double() * sizes[:, 1].double()).sum())
    return max(MIN_BLOCK // PIXELS_PER_BLOCK_SIDE, math.floor(math.sqrt(pixels / max(rays, 1))))


class ErrorMap:
    """Per block of each photo, the mean squared error of the render at its measured pixels (0 until measured)."""

    def __init__(self, sizes: torch.Tensor, stride: int):
        self.stride = stride
        self.block = stride * PIXELS_PER_BLOCK_SIDE
        sizes = sizes.cpu().long()
        image, top, left, height, width = [], [], [], [], []
        for i, (h, w) in enumerate(sizes.tolist()):
            rows, cols = torch.arange(0, h, self.block), torch.arange(0, w, self.block)
            t, l = (g.reshape(-1) for g in torch.meshgrid(rows, cols, indexing="ij"))
            image.append(torch.full_like(t, i))
            top.append(t)
            left.append(l)
            height.append((h - t).clamp(max=self.block))
            width.append((w - l).clamp(max=self.block))
        self.image, self.top, self.left = torch.cat(image), torch.cat(top), torch.cat(left)
        self.height, self.width = torch.cat(height), torch.cat(width)
        self.error = torch.zeros(self.image.shape[0], dtype=torch.float64)
        self.widths = sizes[:, 1]

    @property
    def measured(self) -> bool:
        return bool(self.error.sum() > 0)

    def block_of(self, image: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> torch.Tensor:
        """The block index of each pixel."""
        first = torch.zeros(int(self.widths.shape[0]) + 1, dtype=torch.long)
        first[1:] = torch.bincount(self.image, minlength=int(self.widths.shape[0])).cumsum(0)
        across = (self.widths + self.block - 1) // self.block
        return first[image] + (row // self.block) * across[image] + col // self.block

    def measure(self, image: torch.Tensor, row: torch.Tensor, col: torch.Tensor, errors: torch.Tensor) -> None:
        """Measures the map anew from the render's squared errors [P] (mean over the colour channels) at these pixels
        (the photos' lattice at this map's stride, on the CPU)."""
        block = self.block_of(image, row, col)
        errors = errors.double().cpu()
        total = torch.zeros_like(self.error).index_add_(0, block, errors)
        count = torch.zeros_like(self.error).index_add_(0, block, torch.ones_like(errors))
        self.error = total / count.clamp_min(1)

    def draw(self, n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """`n` pixels (image, row, column), each block drawn in proportion to its pixels times the square root of their
        mean squared error (their RMS error: in proportion to the error itself, a few blocks that no grid of the fit's
        cells can match take most of the rays; bench/README.md, "Fit: quality against cost"), the pixel uniform within
        it."""
        weights = self.error.sqrt() * (self.height * self.width).double()
        blocks = torch.multinomial(weights, n, replacement=True, generator=generator)
        row = self.top[blocks] + (torch.rand(n, generator=generator) * self.height[blocks]).long()
        col = self.left[blocks] + (torch.rand(n, generator=generator) * self.width[blocks]).long()
        return self.image[blocks], row, col

    def state_dict(self) -> dict:
        return {"stride": self.stride, "error": self.error.clone()}

    def load_state_dict(self, state: dict) -> None:
        if state["stride"] != self.stride or state["error"].shape != self.error.shape:
            raise ValueError("the error map was measured on photos of other sizes")
        self.error = state["error"].clone()
