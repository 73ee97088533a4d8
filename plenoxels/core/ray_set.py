"""The training photos' pixels as rays: a RaySet holds every photo's pixels with its camera, makes the world ray of
any pixel, and draws the fit's batches (random pixels, square tiles, a share from an error map), ordered so that rays
passing near each other sit together. On the CPU a batch's rays, colours and order are made in one native pass
(torch.ops.voxfield.pixel_rays); on a GPU by torch's operators on the set's tables (`torch_pixel_rays`, the same rays)."""
from __future__ import annotations

import copy

import numpy as np
import torch

from plenoxels.core import native
from plenoxels.core.cameras import Intrinsics
from plenoxels.core.error_map import ErrorMap
from plenoxels.core.photo_colour import PhotoColour
from plenoxels.core.render import floor_targets

# A photo's channel at or above this byte is clipped: what the sensor took there is a floor, not a value.
CLIPPED_BYTE = 254


def as_bytes(image: np.ndarray) -> np.ndarray:
    """An image's pixels as uint8, from floats in [0, 1] or as they are."""
    return image if image.dtype == np.uint8 else np.round(image * 255).astype(np.uint8)


class RaySet:
    """Pixels of a set of images with their cameras; makes world rays for any (image, row, column).

    Pixels are stored flat (uint8 [P, 3]) so images of different sizes sit side by side.
    """

    def __init__(self, images: list[np.ndarray], c2ws: list[np.ndarray], intrinsics: list[Intrinsics],
                 backdrops: list | None = None, masks: list[np.ndarray] | None = None, behind: list | None = None,
                 cover: list[np.ndarray] | None = None, clipped: list[np.ndarray] | None = None):
        # Each photo's own backdrop colour (RGB in [0, 1]) where the photos of an object show it on backdrops of
        # different colours: what a ray of that photo sees past the grid. None: the model's one colour or background.
        self.backdrops = torch.tensor(np.asarray(backdrops, dtype=np.float32).reshape(-1, 3)) if backdrops else None
        # Where the fit needs to know what its photos' masks put in (their colours measured inside the masks alone):
        # each pixel's coverage by its mask (uint8 [P]) and the colour composited behind each photo [N, 3].
        self.coverage = torch.cat([torch.from_numpy(as_bytes(m).reshape(-1)) for m in masks]) if masks else None
        self.behind = torch.tensor(np.asarray(behind, dtype=np.float32).reshape(-1, 3)) if masks else None
        # Each pixel's coverage by its mask (uint8 [P]) where the fit trains rays past the object toward random
        # backdrops (random_backdrops): those no mask covers, and a share of those it covers whole.
        self.cover = torch.cat([torch.from_numpy(as_bytes(c).reshape(-1)) for c in cover]) if cover else None
        # The pixels with a clipped channel, as sorted flat indices [C] and their channels' bits (bit c: channel c;
        # uint8 [C]; clipped_bits), which a batch trains as floors; None where no photo has one. Kept sparse: a few
        # percent of lego's pixels are clipped, a fifth of a DTU skull's.
        self.clipped = None
        if clipped and any(c is not None and c.any() for c in clipped):
            at, bits, start = [], [], 0
            for c, im in zip(clipped, images):
                if c is not None:
                    flat = torch.from_numpy(c.reshape(-1))
                    where = flat.nonzero().squeeze(1)
                    at.append(where + start)
                    bits.append(flat[where])
                start += im.shape[0] * im.shape[1]
            index_type = torch.int32 if start < 2 ** 31 else torch.int64
            self.clipped = (torch.cat(at).to(index_type), torch.cat(bits))
        self.sizes = torch.tensor([[k.h, k.w] for k in intrinsics], dtype=torch.int64)
        counts = self.sizes[:, 0] * self.sizes[:, 1]
        self.offsets = torch.cat([torch.zeros(1, dtype=torch.int64), counts.cumsum(0)])
        self.pixels = torch.cat([torch.from_numpy(as_bytes(im).reshape(-1, 3)) for im in images])
        self.c2w = torch.tensor(np.stack(c2ws), dtype=torch.float32)
        self.k = torch.tensor([[k.fl_x, k.fl_y, k.cx, k.cy] for k in intrinsics], dtype=torch.float32)
        self.intrinsics = intrinsics
        self.num_pixels = int(self.offsets[-1])
        self.image_pixels = counts.double()  # the tiles' draw weights, on the CPU with the generator

    def to(self, device: torch.device) -> RaySet:
        """The same rays with their tables on `device`, where a batch's rays and colours are then made: on a GPU a
        few launches instead of milliseconds of small CPU operations. The random draws stay on the CPU generator
        (a few thousand integers), so a fit draws the same batches on every device."""
        moved = copy.copy(self)
        for name in ("sizes", "offsets", "pixels", "c2w", "k"):  # not image_pixels
            setattr(moved, name, getattr(self, name).to(device))
        for name in ("backdrops", "coverage", "behind", "cover"):
            if getattr(self, name) is not None:
                setattr(moved, name, getattr(self, name).to(device))
        if self.clipped is not None:
            moved.clipped = tuple(t.to(device) for t in self.clipped)
        return moved

    @property
    def device(self) -> torch.device:
        return self.pixels.device

    def mean_colour(self) -> list[float]:
        """The mean RGB in [0, 1] of every pixel, summed a slice at a time (no float copy of the whole set)."""
        total = sum(chunk.sum(dim=0, dtype=torch.float64) for chunk in self.pixels.split(1 << 20))
        return (total / (255.0 * max(self.num_pixels, 1))).tolist()

    def __len__(self) -> int:
        return self.sizes.shape[0]

    def image(self, index: int) -> torch.Tensor:
        """Image `index` as float RGB [h, w, 3] in [0, 1], on this set's device."""
        h, w = self.sizes[index].tolist()
        start = int(self.offsets[index])
        return self.pixels[start:start + h * w].reshape(h, w, 3).float() / 255.0

    def subset(self, indices: list[int]) -> RaySet:
        """The images at `indices` (in that order) as a RaySet of their own, on the CPU."""
        masks = None
        if self.coverage is not None:
            masks = [self.coverage[self.offsets[i]:self.offsets[i + 1]].cpu().numpy() for i in indices]
        cover = clipped = None
        if self.cover is not None:
            cover = [self.cover[self.offsets[i]:self.offsets[i + 1]].cpu().numpy() for i in indices]
        if self.clipped is not None:
            clipped = [self.clipped_channels(torch.arange(int(self.offsets[i]), int(self.offsets[i + 1]),
                                                     device=self.device)).cpu().numpy() for i in indices]
        return RaySet([self.image(i).cpu().numpy() for i in indices], [self.c2w[i].double().cpu().numpy() for i in indices],
                      [self.intrinsics[i] for i in indices],
                      None if self.backdrops is None else self.backdrops[indices].cpu().tolist(),
                      masks, None if masks is None else self.behind[indices].cpu().tolist(), cover, clipped)

    def backdrop(self, index: int) -> list[float] | None:
        """Photo `index`'s own backdrop colour (None where the photos have none of their own)."""
        return None if self.backdrops is None else self.backdrops[index].tolist()

    def rays(self, image: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World origins and unit directions [B, 3] through pixel centres (plenoxels.core.cameras convention)."""
        _, _, o, d, _ = self.pixel_rays(self.flat(image, row, col))
        return o, d

    def flat(self, image: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> torch.Tensor:
        """The flat indices [B] of these pixels into the set's table of pixels."""
        return self.offsets[image] + row * self.sizes[image, 1] + col

    def unflat(self, pixel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The (image, row, column) [B] of the pixels at flat indices `pixel` (flat's inverse)."""
        image = torch.searchsorted(self.offsets, pixel, right=True) - 1
        local = pixel - self.offsets[image]
        width = self.sizes[image, 1]
        return image, local // width, local % width

    def pixel_rays(self, pixel: torch.Tensor, coherent: bool = False) -> tuple[torch.Tensor, ...]:
        """(order [B], image [B], world origins, unit directions [B, 3], colours [B, 3] in [0, 1]) of the pixels at
        flat indices `pixel`, output i being pixel order[i]: the pixels' own order, or with `coherent` coherent_order's
        (ties in the pixels' order)."""
        if self.device.type == "cpu":
            return tuple(native.ops.pixel_rays(pixel.long().contiguous(), self.k, self.c2w, self.pixels, self.offsets,
                                               self.sizes, coherent, COHERENT_EXTENT))
        return torch_pixel_rays(self, pixel, coherent)

    def batch(self, size: int, mode: str, tile: int, generator: torch.Generator, coherent: bool = False,
              with_backdrops: bool = False, error_map: ErrorMap | None = None, error_share: float = 0.0,
              colour: PhotoColour | None = None, with_cover: bool = False):
        """A training batch: world origins, directions [B, 3] and target colours [B, 3] in [0, 1], and with
        `with_backdrops` each ray's photo's backdrop colour [B, 3] after them, with `with_cover` each ray's pixel's
        coverage by its mask (uint8 [B]; None where the set keeps no such record) last; with `coherent`, random rays
        come ordered by coherent_order. Random rays: `error_share` of them drawn from `error_map` once it is measured. With `colour`
        the target colours are the photos' taken back to their common colour. A clipped channel's target is a floor
        (render.floor_targets). `generator` is a CPU generator; the batch is on this set's device."""
        device = self.device
        if mode == "rays":
            by_error = round(size * error_share) if error_map is not None and error_map.measured else 0
            pixel = torch.randint(self.num_pixels, (size - by_error,), generator=generator).to(device)
            if error_map is not None and error_map.leaves_out:  # what moved between the photos is never drawn
                pixel = pixel[error_map.kept(*(t.cpu() for t in self.unflat(pixel))).to(device)]
            if by_error:
                pixel = torch.cat([pixel, self.flat(*(t.to(device) for t in error_map.draw(by_error, generator)))])
        else:
            n_tiles = max(1, size // (tile * tile))
            image = torch.multinomial(self.image_pixels, n_tiles, replacement=True, generator=generator).to(device)
            h, w = self.sizes[image, 0], self.sizes[image, 1]
            th, tw = torch.clamp(h, max=tile), torch.clamp(w, max=tile)
            top = (torch.rand(n_tiles, generator=generator).to(device) * (h - th + 1)).long()
            left = (torch.rand(n_tiles, generator=generator).to(device) * (w - tw + 1)).long()
            dy, dx = torch.meshgrid(torch.arange(tile, device=device), torch.arange(tile, device=device), indexing="ij")
            dy, dx = dy.reshape(1, -1), dx.reshape(1, -1)
            inside = (dy < th[:, None]) & (dx < tw[:, None])
            pixel = (self.offsets[image][:, None] + (top[:, None] + dy) * w[:, None] + left[:, None] + dx)[inside]
        order, image, o, d, target = self.pixel_rays(pixel, coherent and mode == "rays")
        if colour is not None:
            target = colour.to_common(image, target, self.put_in_at(image, pixel[order]))
        if self.clipped is not None:
            target = floor_targets(target, self.floors_at(pixel[order]))
        drawn = [o, d, target]
        if with_backdrops:  # as the photos' colours are: in their common colour where `colour` takes them there
            drawn.append(self.backdrops[image] if colour is None else colour.to_common(image, self.backdrops[image]))
        if with_cover:
            drawn.append(None if self.cover is None else self.cover[pixel[order]])
        return tuple(drawn)

    def lattice(self, stride: int, images: range | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A regular subset of every image's pixels (or of `images`'), every stride-th row and column from
        stride // 2: (image, row, column) [P], on the CPU."""
        image, row, col = [], [], []
        for i in images if images is not None else range(len(self.sizes)):
            h, w = self.sizes[i].tolist()
            r, c = torch.meshgrid(torch.arange(stride // 2, h, stride), torch.arange(stride // 2, w, stride),
                                  indexing="ij")
            image.append(torch.full((r.numel(),), i))
            row.append(r.reshape(-1))
            col.append(c.reshape(-1))
        return torch.cat(image), torch.cat(row), torch.cat(col)

    def put_in(self, image: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> torch.Tensor | None:
        """The part of the photos' colours [B, 3] at these pixels that their masks put there (the colour behind the
        photo times one less the mask's coverage); None where the set keeps no masks."""
        return self.put_in_at(image, self.flat(image, row, col))

    def put_in_at(self, image: torch.Tensor, pixel: torch.Tensor) -> torch.Tensor | None:
        """put_in of the pixels at flat indices `pixel` of these images."""
        if self.coverage is None:
            return None
        return (1.0 - self.coverage[pixel].float() / 255.0)[:, None] * self.behind[image]

    def clipped_share(self) -> float:
        """The share of the pixels with a clipped channel (0 where the set keeps none)."""
        return 0.0 if self.clipped is None else self.clipped[0].numel() / max(self.num_pixels, 1)

    def clipped_channels(self, pixel: torch.Tensor) -> torch.Tensor:
        """The clipped channels as bits [B] (uint8; clipped_bits) of the pixels at flat indices `pixel`."""
        if self.clipped is None:
            return torch.zeros(pixel.shape[0], dtype=torch.uint8, device=pixel.device)
        at, bits = self.clipped
        place = torch.searchsorted(at, pixel.to(at.dtype)).clamp(max=at.numel() - 1)
        return torch.where(at[place] == pixel, bits[place], torch.zeros_like(bits[place]))

    def floors_at(self, pixel: torch.Tensor) -> torch.Tensor:
        """Whether each channel of the pixels at flat indices `pixel` is clipped [B, 3] (bool; all False where the set
        keeps no clipped pixels)."""
        return ((self.clipped_channels(pixel).long()[:, None] >> torch.arange(3, device=pixel.device)) & 1).bool()

    def inside(self, image: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> torch.Tensor | None:
        """Whether each of these pixels lies wholly inside its photo's mask [B] (None where the set keeps no masks)."""
        if self.coverage is None:
            return None
        return self.coverage[self.flat(image, row, col)] == 255

    def strided_rays(self, stride: int, images: range | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through a regular subset of every image's pixels (or of `images`'; every stride-th row and column)."""
        image, row, col = (t.to(self.device) for t in self.lattice(stride, images))
        return self.rays(image, row, col)

    def strided_ray_chunks(self, stride: int, rays: int):
        """strided_rays' rays, a run of whole images at a time of at least `rays` rays (the last run fewer): a pass
        over many large photos never holds all their rays at once."""
        first, count = 0, 0
        for i, (h, w) in enumerate(self.sizes.tolist()):
            count += lattice_pixels(h, w, stride)
            if count >= rays or i == len(self.sizes) - 1:
                yield self.strided_rays(stride, range(first, i + 1))
                first, count = i + 1, 0


def clipped_bits(image: np.ndarray, coverage: np.ndarray | None = None) -> np.ndarray:
    """A photo's clipped channels as bits (bit c: channel c) [h, w] uint8, from its bytes [h, w, 3] and its mask's
    coverage (bytes [h, w]; None: no mask): a channel within a byte of the top, where the photo's own light fills the
    pixel. The light there reached at least that value, maybe much more (a highlight, a window). Held to the value,
    a clipped white taken back to the common colour is 1 / gain per channel, tinted differently by each photo's gains
    (a DTU skull's blown-out cranium rendered blue-grey; bench/README.md, "Object captures"). A colour the mask put
    in (a composited backdrop) is not light the photo took, so it stays a target."""
    clipped = image >= CLIPPED_BYTE
    if coverage is not None:
        clipped &= (coverage == 255)[..., None]
    return (clipped[..., 0] | (clipped[..., 1] << 1) | (clipped[..., 2] << 2)).astype(np.uint8)


def lattice_pixels(h: int, w: int, stride: int) -> int:
    """How many of an h x w photo's pixels RaySet.lattice takes at this stride."""
    return -(-(h - stride // 2) // stride) * -(-(w - stride // 2) // stride)


# The coherent order's cube: rays' closest points beyond it share its faces (the normalised frame puts the foreground
# inside [-1, 1]^3).
COHERENT_EXTENT = 2.0


def torch_pixel_rays(rays: RaySet, pixel: torch.Tensor, coherent: bool = False) -> tuple[torch.Tensor, ...]:
    """RaySet.pixel_rays made of torch's operators, on any device: what the native pass computes on the CPU."""
    image, row, col = rays.unflat(pixel)
    k = rays.k[image]
    d_cam = torch.stack([(col.float() + 0.5 - k[:, 2]) / k[:, 0],
                         -((row.float() + 0.5 - k[:, 3]) / k[:, 1]), -torch.ones_like(k[:, 0])], dim=-1)
    c2w = rays.c2w[image]
    d = (c2w[:, :3, :3] * d_cam[:, None, :]).sum(-1)
    o, d = c2w[:, :3, 3].contiguous(), (d / d.norm(dim=-1, keepdim=True)).contiguous()
    colours = rays.pixels[pixel].float() / 255.0
    order = coherent_order(o, d) if coherent else torch.arange(pixel.shape[0], device=pixel.device)
    return order, image[order], o[order], d[order], colours[order]


def coherent_order(origins: torch.Tensor, dirs: torch.Tensor, extent: float = COHERENT_EXTENT) -> torch.Tensor:
    """A permutation that puts rays passing near each other next to each other: by the Morton code (a space-filling
    curve, 10 bits per axis) of each ray's point closest to the scene's centre, which the normalised frame puts at the
    origin with the foreground inside [-1, 1]^3 (points beyond `extent` share the faces of the curve's cube); a stable
    sort, so that rays of one code keep their order."""
    unit = dirs / dirs.norm(dim=1, keepdim=True)
    closest = origins - unit * (origins * unit).sum(1, keepdim=True)
    cell = ((closest.clamp(-extent, extent) + extent) / (2 * extent) * 1023).long()
    spread = _every_third_bit(cell)
    return torch.argsort(spread[:, 0] | (spread[:, 1] << 1) | (spread[:, 2] << 2), stable=True)


def _every_third_bit(v: torch.Tensor) -> torch.Tensor:
    """Bit i of each 10-bit value moved to bit 3i, in four shifts and masks (not thirty single-bit steps)."""
    v = (v | (v << 16)) & 0x030000FF
    v = (v | (v << 8)) & 0x0300F00F
    v = (v | (v << 4)) & 0x030C30C3
    return (v | (v << 2)) & 0x09249249


def random_backdrops(cover: torch.Tensor, background: torch.Tensor, target: torch.Tensor, covered_share: float,
                     generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """The backdrops [B, 3] and targets [B, 3] of a batch whose rays through pixels no mask covers (`cover` [B] 0)
    see a random colour past the grid and are trained toward it, and `covered_share` of those through pixels a mask
    covers whole (255) see one behind their photo's colour: the first are right only where the field leaves them
    empty, the second only where it is opaque, whatever colour the photos' backdrop is (an object as pale as its
    backdrop is otherwise fitted half see-through). A pixel a mask covers in part keeps its backdrop: its photo's
    colour holds that backdrop's share."""
    empty = cover == 0
    covered = (cover == 255) & (torch.rand(cover.shape, generator=generator).to(cover.device) < covered_share)
    if not bool(empty.any()) and not bool(covered.any()):
        return background, target
    background, target = background.expand_as(target).clone(), target.clone()
    colours = torch.rand(len(cover), 3, generator=generator).to(target.device)
    background[empty], target[empty] = colours[empty], colours[empty]
    background[covered] = colours[covered]
    return background, target
