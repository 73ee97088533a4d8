"""Where the render still disagrees with the photos: a map of squared error per block of each training photo, from
which a share of every batch is drawn, and of what moved between the photos, which the fit leaves out.

Every pixel of a capture is not equally hard. An object on a backdrop fills a fraction of its photos, and once the
backdrop renders right its pixels teach the grid nothing; an edge, a print or a thin part stays wrong for most of a
fit. Drawing rays by the error their block still holds spends the steps where the photos still have something to
say (as instant-ngp's error map does). The rest of each batch stays uniform, so no pixel is ever left out and what
renders right stays right. Measured, it buys objects at `default` 0.3-0.4 dB with a third fewer last-level steps,
lego at `fast` about 0.2 dB at equal time and fox and ball nothing, so `fit.error_share` is 0 but for objects at
`default` (configs/scene_types/object.yaml; bench/README.md, "Fit: quality against cost").

The map is measured, not learned from the batches: the fit renders every `stride`-th row and column of each photo
with the model as it stands (Fitter.measure_photos). Where it draws rays, the squared error is averaged over blocks of
`2 * stride` pixels (four measured pixels a block); where it only finds what moved, each measured pixel is its block
(where that is MIN_BLOCK pixels across), so a patch's edge is found to a stride, and a person a few strides across is
found at all (a small person in 60% of fox's training photos: 70% of their pixels left out against 12% on blocks of
four; bench/README.md, "Real captures"). It is deterministic (no draw from the batches' generator), so a resumed fit
measures the same map.

What moved between the photos (a person walking through, a car, a pet) is in some photos and not in the others, so no
one scene explains it: a grid fitted to it draws ghosts and floaters in every view (a room with a person in 14 of its 35
training photos: 1.7 dB lower held out, 0.3 with them left out; bench/README.md, "Real captures"). Where the render
disagrees with a photo only in detail it blurs, the photo is as often above it as below, and the difference averages out
over a few blocks; where something stood in front of the scene, the photo's colour is shifted the same way over the
whole patch. So each block also keeps its mean difference (render less photo), and `find_transients` leaves out of the
fit the patches where that difference, averaged over each block's neighbours, stays far off over a connected patch of
blocks: rays are then never drawn there (RaySet.batch) and the photos' colours are measured without them. A patch of
exposure over most of a photo is its light, which the photos' colours take (plenoxels/core/photo_colour.py), and is
kept. The patches are found anew at each measurement, so a photo that the fit comes to explain is trained whole again.
"""
from __future__ import annotations

import math

import numpy as np
import scipy.ndimage
import skimage.measure
import torch

# Measured pixels along each side of a block where the map draws rays: the block is this many strides across.
PIXELS_PER_BLOCK_SIDE = 2
# The blocks are at least this many pixels across (a map finer than the photos' own grain measures noise), so the
# measured pixels at least MIN_STRIDE apart.
MIN_BLOCK = 4
MIN_STRIDE = MIN_BLOCK // PIXELS_PER_BLOCK_SIDE
# What moved between photos: the mean difference (render less photo, RGB in [0, 1]) over a block's neighbours (this
# many blocks across) at least TRANSIENT_MIN_DIFFERENCE long, and TRANSIENT_RATIO times the capture's median and
# TRANSIENT_SPREADS robust spreads above it, over a patch of at least TRANSIENT_MIN_BLOCKS blocks and
# TRANSIENT_MIN_SHARE of its photo, but under TRANSIENT_MAX_SHARE of it. The least difference: fox's and ball's photos,
# whose light and detail differ from view to view, lie under it in over 99.9% of their blocks. The least patch: at 8
# blocks of one measured pixel, fox without passers-by leaves out 0.3% of its pixels (bench/README.md, "Real captures").
TRANSIENT_NEIGHBOURS = 3
TRANSIENT_MIN_DIFFERENCE = 0.15
TRANSIENT_RATIO = 2.5
TRANSIENT_SPREADS = 4.0
TRANSIENT_MIN_BLOCKS = 12
TRANSIENT_MIN_SHARE = 0.005
TRANSIENT_MAX_SHARE = 0.5


def measure_stride(sizes: torch.Tensor, rays: int) -> int:
    """The pixel stride at which a measurement of photos of these [N, 2] sizes renders about `rays` rays."""
    pixels = float((sizes[:, 0].double() * sizes[:, 1].double()).sum())
    return max(MIN_STRIDE, math.floor(math.sqrt(pixels / max(rays, 1))))


def block_side(stride: int, draws: bool) -> int:
    """Measured pixels along each side of a map's blocks at this stride: PIXELS_PER_BLOCK_SIDE where the map draws rays
    (their error wants an average), else one, each measured pixel its own block, where that is MIN_BLOCK across."""
    return PIXELS_PER_BLOCK_SIDE if draws else max(1, -(-MIN_BLOCK // stride))


def kept_inside(error_map: ErrorMap | None, image: torch.Tensor, row: torch.Tensor, col: torch.Tensor,
                inside: torch.Tensor | None) -> torch.Tensor | None:
    """`inside` (a mask of these pixels [P]; None: every pixel) less the pixels `error_map` leaves out: what moved
    between the photos says nothing of a photo's colour."""
    if error_map is None or not error_map.leaves_out:
        return inside
    kept = error_map.kept(image, row, col)
    return kept if inside is None else inside & kept


class ErrorMap:
    """Per block of each photo, the mean squared error of the render at its measured pixels (0 until measured), its
    mean difference, and whether the fit leaves it out. A block is `side` measured pixels across (the module's
    docstring)."""

    def __init__(self, sizes: torch.Tensor, stride: int, side: int = PIXELS_PER_BLOCK_SIDE):
        self.stride = stride
        self.block = stride * side
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
        self.difference = torch.zeros(self.image.shape[0], 3, dtype=torch.float64)
        self.left_out = torch.zeros(self.image.shape[0], dtype=torch.bool)
        # Each photo's blocks as a lattice (rows, columns), stored one photo after the other, row by row.
        self.lattices = [(-(-h // self.block), -(-w // self.block)) for h, w in sizes.tolist()]
        self.across = torch.tensor([cols for _, cols in self.lattices], dtype=torch.long)
        self.first = torch.tensor([0] + [rows * cols for rows, cols in self.lattices], dtype=torch.long).cumsum(0)

    @property
    def measured(self) -> bool:
        return bool(self.error.sum() > 0)

    @property
    def leaves_out(self) -> bool:
        return bool(self.left_out.any())

    def block_of(self, image: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> torch.Tensor:
        """The block index of each pixel."""
        return self.first[image] + (row // self.block) * self.across[image] + col // self.block

    def kept(self, image: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> torch.Tensor:
        """Whether the fit trains on each of these pixels [P] (bool): not left out by find_transients."""
        return ~self.left_out[self.block_of(image, row, col)]

    def measure(self, image: torch.Tensor, row: torch.Tensor, col: torch.Tensor, difference: torch.Tensor) -> None:
        """Measures the map anew from the render's differences from the photos [P, 3] (render.colour_error) at these
        pixels (the photos' lattice at this map's stride, on the CPU)."""
        block = self.block_of(image, row, col)
        difference = difference.double().cpu()
        count = torch.zeros_like(self.error).index_add_(0, block, torch.ones_like(difference[:, 0])).clamp_min(1)
        self.error = torch.zeros_like(self.error).index_add_(0, block, (difference ** 2).mean(dim=1)) / count
        self.difference = torch.zeros_like(self.difference).index_add_(0, block, difference) / count[:, None]

    def find_transients(self) -> None:
        """Leaves out of the fit the patches of each photo whose colour the render, fitted to all of them, says moved
        (TRANSIENT_*: the module's docstring), each with a block's margin round it; keeps every other block."""
        offsets, start = [], 0
        for rows, cols in self.lattices:
            difference = self.difference[start:start + rows * cols].reshape(rows, cols, 3).numpy()
            around = scipy.ndimage.uniform_filter(difference, (TRANSIENT_NEIGHBOURS, TRANSIENT_NEIGHBOURS, 1),
                                                  mode="nearest")
            offsets.append(np.linalg.norm(around, axis=-1))
            start += rows * cols
        every = np.concatenate([o.reshape(-1) for o in offsets])
        middle = float(np.median(every))
        spread = 1.4826 * float(np.median(np.abs(every - middle)))
        least = max(TRANSIENT_MIN_DIFFERENCE, TRANSIENT_RATIO * middle, middle + TRANSIENT_SPREADS * spread)
        left_out = []
        for offset in offsets:
            patches = skimage.measure.label(offset > least, connectivity=2)
            blocks = np.bincount(patches.reshape(-1))
            blocks[0] = 0  # the blocks outside every patch
            moved = blocks[patches] >= max(TRANSIENT_MIN_BLOCKS, TRANSIENT_MIN_SHARE * offset.size)
            if moved.any():
                moved = scipy.ndimage.binary_dilation(moved, np.ones((3, 3), bool))
            left_out.append(torch.from_numpy(moved.reshape(-1) & (moved.mean() <= TRANSIENT_MAX_SHARE)))
        self.left_out = torch.cat(left_out)

    def transients_record(self) -> dict:
        """What find_transients leaves out: the share of the photos' pixels and the photos it is in."""
        pixels = (self.height * self.width).double()
        photos = torch.zeros(len(self.lattices), dtype=torch.bool).index_fill_(0, self.image[self.left_out], True)
        return {"share": round(float(pixels[self.left_out].sum() / pixels.sum()), 4), "photos": int(photos.sum())}

    def draw(self, n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """`n` pixels (image, row, column), each block drawn in proportion to its pixels times the square root of their
        mean squared error (their RMS error: in proportion to the error itself, a few blocks that no grid of the fit's
        cells can match take most of the rays; bench/README.md, "Fit: quality against cost"), the pixel uniform within
        it."""
        weights = self.error.sqrt() * (self.height * self.width).double() * (~self.left_out).double()
        blocks = torch.multinomial(weights, n, replacement=True, generator=generator)
        row = self.top[blocks] + (torch.rand(n, generator=generator) * self.height[blocks]).long()
        col = self.left[blocks] + (torch.rand(n, generator=generator) * self.width[blocks]).long()
        return self.image[blocks], row, col

    def state_dict(self) -> dict:
        return {"stride": self.stride, "error": self.error.clone(), "left_out": self.left_out.clone()}

    def load_state_dict(self, state: dict) -> None:
        if state["stride"] != self.stride or state["error"].shape != self.error.shape:
            raise ValueError("the error map was measured on photos of other sizes")
        self.error = state["error"].clone()
        self.left_out = state.get("left_out", torch.zeros_like(self.left_out)).clone()
