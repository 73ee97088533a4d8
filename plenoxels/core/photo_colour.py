"""Each training photo's own colour: per channel, the gain that takes the field's render of its view to it.

A phone sets exposure and white balance anew as it turns: a colour correction per photo brings ball's training renders
1.2 dB closer to their photos (bench/README.md, "Real captures"). No one field reproduces photos that disagree on
colour; it fits their average, blurred, or takes the differences up as view-dependent colour. With `fit.photo_colour`
the fit measures, now and then, each photo's gain per channel against its render (over an even lattice of its pixels,
clipped pixels left out) and trains the field against the photos taken back to a common colour, photo / gain. The gains
average 1 over the photos, so the field keeps their average colour, the one a new view is rendered in.

Whether the photos differ in colour at all is decided on the fit's first DECIDING_MEASURES measures (or as many as a
short fit takes before its last level), with the photos trained as they are until then: one measure of a field that has
just begun reads its own errors as much as the photos' colours (lego's first measure at 800x800 has read 0.08 and 0.20
dB in two fits). Gains fitted to photos that agree take those errors up, and a field that can follow a photo's gain
as view-dependent colour (spherical harmonics of degree 2, for a few views) renders the photo in it, so the gains
measured against it confirm themselves measure after measure and wander: lego's `paper` fit in 30 minutes, decided on
one measure, ended with gains from 0.49 to 1.97 and held out 25.6 dB.

A photo the fit did not see (a held-out one) was taken in a colour of its own too. A phone's exposure follows its
capture: frames next to each other in a video, or photos taken one after another, share theirs. So a held-out photo is
rendered in the gain between the fitted photos nearest it in capture order (PhotoGains), from no pixel of its own.

Light differs across a frame as well as between frames: a phone video of an object on a glossy floor carries the
capturer's shadow and the ceiling lights' glow across the boards from frame to frame, which no one field reproduces
(ball's floor in front of the camera is 40% of its held-out pixels and half their error). At the fit's end each
photo's gain is measured again on a coarse lattice of cells across its frame (gain_fields, `fit.photo_colour_cells`
along its longer side), against the finished field; a held-out photo takes its neighbours' lattices where the training
photos' own, each left out in turn, lie nearer their neighbours' than what a held-out photo takes otherwise. Measured
after the fit, not during it: the field is trained against each photo's one gain, so a lattice takes up nothing the
field should learn (trained in the lattices, ball's field read no nearer its held-out photos; bench/README.md).

Where masks cut the object out, what lies outside them is the colour the masks put there, which no exposure took: the
gains are measured inside the masks and apply to the object's part of each pixel alone (`put_in`, the masks' share).
So too where normalize measured each photo's own backdrop colour: it is that photo's, as taken.
"""
from __future__ import annotations

import math
import re
from typing import Sequence

import numpy as np
import torch

# A photo's channel value this close to 0 or 1 is clipped: its true value is unknown, so it says nothing of the gain.
CLIPPED = 0.02
# The most a photo's gain may move from the common colour: beyond, the ratio measures something other than colour.
GAIN_RANGE = (0.5, 2.0)
# The measures that decide whether the photos differ in colour (their gains' mean dB against fit.photo_colour_min_db).
DECIDING_MEASURES = 2


class PhotoColour:
    """Per photo and channel, the gain from the common colour to the photo: photo = gain * common."""

    def __init__(self, photos: int):
        self.gain = torch.ones(photos, 3, dtype=torch.float64)

    def fit(self, image: torch.Tensor, rendered: torch.Tensor, photo: torch.Tensor,
            inside: torch.Tensor | None = None) -> None:
        """Fits each photo's gains to these pixels (image index [B], the render and the photo's colour [B, 3], on the
        CPU; `inside` [B] bool, the pixels wholly inside their photo's mask where the photos have masks): the ratio of
        the photo's sum to the render's over the pixels not clipped, then set to average 1 over the photos. A ratio of
        sums, not a least-squares line: the render is itself wrong by a few percent at every pixel, which would pull a
        fitted slope towards flat."""
        rendered, photo = rendered.double().clamp(0, 1), photo.double()
        use = _measured(photo, inside)
        sums = torch.zeros(self.gain.shape[0], 3, 3, dtype=torch.float64)
        sums.index_add_(0, image.long(), torch.stack([use, use * rendered, use * photo], 1))
        n, sr, sp = sums.unbind(1)
        fitted = (n >= 16) & (sr > 1e-3 * n)
        gain = torch.where(fitted, sp / torch.where(fitted, sr, torch.ones_like(sr)), torch.ones_like(sr))
        gain = gain.clamp(*GAIN_RANGE)
        self.gain = gain / gain.mean(dim=0, keepdim=True)

    def to_common(self, image: torch.Tensor, photo: torch.Tensor, put_in: torch.Tensor | None = None) -> torch.Tensor:
        """Photo colours [B, 3] of photos `image` [B] taken back to the common colour (on their device); `put_in`
        [B, 3], the part of each colour the masks put there (their backdrop times one less their coverage), stays."""
        gain = self.gain.to(device=photo.device, dtype=photo.dtype)[image]
        return photo / gain if put_in is None else (photo - put_in) / gain + put_in

    def gain_db(self, image: torch.Tensor, rendered: torch.Tensor, photo: torch.Tensor,
                inside: torch.Tensor | None = None) -> float:
        """How much closer (dB of PSNR) the renders come to these photo pixels through the gains than as they are,
        over the pixels that are not clipped (and inside their masks, `inside`, where the photos have masks)."""
        rendered, photo = rendered.double().clamp(0, 1), photo.double()
        use = _measured(photo, inside)
        through = self.gain[image] * rendered
        before = float((use * (rendered - photo) ** 2).sum() / use.sum().clamp_min(1))
        after = float((use * (through.clamp(0, 1) - photo) ** 2).sum() / use.sum().clamp_min(1))
        return 10.0 * math.log10(max(before, 1e-12) / max(after, 1e-12))

    def describe(self) -> dict:
        """The gains' range over the photos, per channel."""
        return {"gain_min": self.gain.min(dim=0).values.round(decimals=3).tolist(),
                "gain_max": self.gain.max(dim=0).values.round(decimals=3).tolist()}

    def state_dict(self) -> dict:
        return {"gain": self.gain.clone()}

    def load_state_dict(self, state: dict) -> None:
        if state["gain"].shape != self.gain.shape:
            raise ValueError("the photos' colours were measured on another set of photos")
        self.gain = state["gain"].clone()


def lattice_shape(sizes: torch.Tensor, cells: int) -> tuple[int, int]:
    """Cells (rows, columns) of a photo's gain lattice: `cells` along the longer side of the capture's median photo,
    the shorter side in proportion (at least one)."""
    h, w = (float(v) for v in sizes.double().median(dim=0).values)
    short = max(1, round(cells * min(h, w) / max(h, w)))
    return (cells, short) if h >= w else (short, cells)


def gain_field_lattice(sizes: torch.Tensor, cells: int) -> tuple[tuple[int, int], int]:
    """The cells of the photos' gain lattices (lattice_shape) and the stride of the pixels they are measured on:
    about CELL_PIXELS a cell of the median photo."""
    shape = lattice_shape(sizes, cells)
    pixels = float(sizes.double().prod(dim=1).median())
    return shape, max(1, int(math.sqrt(pixels / (CELL_PIXELS * shape[0] * shape[1]))))


def lattice_weights(v: torch.Tensor, u: torch.Tensor, shape: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear weights of pixels at normalised positions v, u [B] in [0, 1] (row, column) on a lattice of cell centres
    `shape`, clamped at its borders: (flat cell index [B, 4],
    weight [B, 4])."""
    rows, cols = shape
    y = (v * rows - 0.5).clamp(0, rows - 1)
    x = (u * cols - 0.5).clamp(0, cols - 1)
    y0, x0 = y.floor().long(), x.floor().long()
    y1, x1 = (y0 + 1).clamp(max=rows - 1), (x0 + 1).clamp(max=cols - 1)
    fy, fx = y - y0, x - x0
    index = torch.stack([y0 * cols + x0, y0 * cols + x1, y1 * cols + x0, y1 * cols + x1], 1)
    weight = torch.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], 1)
    return index, weight


# Pixels a cell of a photo's gain lattice is measured on, about: the lattice of pixels rendered for gain_fields is as
# fine as this asks (ball's 111 photos at 8x4 cells, 0.4 M rays: a second or two of rendering on a CPU).
CELL_PIXELS = 128
# Pixels' worth of weight that hold a cell's gain at its photo's own: a cell seen by fewer unclipped pixels than this
# leans toward the photo's gain in proportion.
CELL_PRIOR = 4.0


def gain_fields(image: torch.Tensor, row: torch.Tensor, col: torch.Tensor, sizes: torch.Tensor,
                rendered: torch.Tensor, photo: torch.Tensor, gains: torch.Tensor, shape: tuple[int, int],
                inside: torch.Tensor | None = None) -> torch.Tensor:
    """Each photo's gain per channel on a lattice of `shape` cells across its frame [P, rows, cols, 3], from these
    pixels (image, row, column [B]; `sizes` [P, 2] each photo's height and width) of the render in the common colour
    and the photo [B, 3]: the lattice whose bilinear spread (field_image) times the render comes nearest the photo,
    each pixel's squared error weighed by one over its render. That weighing makes one cell's gain the ratio of sums
    PhotoColour.fit takes, which the render's own errors do not pull toward flat as they would a plain least-squares
    slope. Each cell leans toward the photo's own gain (`gains` [P, 3]) by CELL_PRIOR pixels' worth, so a cell that
    few pixels say anything of keeps it; within GAIN_RANGE."""
    rendered, photo = rendered.double().clamp(0, 1), photo.double()
    use = _measured(photo, inside)
    size = sizes[image.long()].double()
    index, weight = lattice_weights((row.double() + 0.5) / size[:, 0], (col.double() + 0.5) / size[:, 1], shape)
    photos, cells = gains.shape[0], shape[0] * shape[1]
    # Normal equations per photo and channel: A[c, d] = sum of w_c w_d r, b[c] = sum of w_c p over the used pixels.
    pair = (image.long()[:, None, None] * cells + index[:, :, None]) * cells + index[:, None, :]
    outer = weight[:, :, None] * weight[:, None, :]
    a = torch.zeros(photos * cells * cells, 3, dtype=torch.float64)
    a.index_add_(0, pair.reshape(-1), (outer[..., None] * (use * rendered)[:, None, None, :]).reshape(-1, 3))
    b = torch.zeros(photos * cells, 3, dtype=torch.float64)
    b.index_add_(0, (image.long()[:, None] * cells + index).reshape(-1),
                 (weight[..., None] * (use * photo)[:, None, :]).reshape(-1, 3))
    a = a.reshape(photos, cells, cells, 3).permute(0, 3, 1, 2)
    b = b.reshape(photos, cells, 3).permute(0, 2, 1)
    # The prior: CELL_PRIOR pixels of the photo's mean render a cell, at the photo's own gain.
    counts = torch.zeros(photos, 3, dtype=torch.float64).index_add_(0, image.long(), use)
    sums = torch.zeros(photos, 3, dtype=torch.float64).index_add_(0, image.long(), use * rendered)
    mean = torch.where(counts > 0, sums / counts.clamp_min(1), torch.full_like(sums, 0.5)).clamp_min(1e-3)
    prior = CELL_PRIOR * mean[..., None]
    a = a + torch.diag_embed(prior.expand(photos, 3, cells))
    b = b + prior * gains.double()[..., None]
    field = torch.linalg.solve(a, b[..., None])[..., 0].clamp(*GAIN_RANGE)
    return field.permute(0, 2, 1).reshape(photos, shape[0], shape[1], 3)


def field_image(field: np.ndarray, h: int, w: int) -> torch.Tensor:
    """A gain lattice [rows, cols, 3] spread over an image of h x w pixels [h * w, 3], with the bilinear weights
    gain_fields measures it by."""
    field = torch.as_tensor(np.asarray(field), dtype=torch.float64)
    v, u = torch.meshgrid((torch.arange(h, dtype=torch.float64) + 0.5) / h,
                          (torch.arange(w, dtype=torch.float64) + 0.5) / w, indexing="ij")
    index, weight = lattice_weights(v.reshape(-1), u.reshape(-1), tuple(field.shape[:2]))
    return (weight[..., None] * field.reshape(-1, 3)[index]).sum(dim=1)


def _measured(photo: torch.Tensor, inside: torch.Tensor | None) -> torch.Tensor:
    """1.0 where a photo's channel value says something of its gain: not clipped, and inside its mask where it has
    one; else 0.0 [B, 3]."""
    use = (photo > CLIPPED) & (photo < 1 - CLIPPED)
    return (use if inside is None else use & inside.to(use.device)[:, None]).double()


# Rays a measurement of the photos' colours alone renders (the error map's take fit.measure_rays): a photo's gains are
# three ratios of sums, which a few hundred of its pixels fix to a fraction of a percent.
COLOUR_RAYS = 1 << 15
# The share of the gains' spread that the capture's order must explain (1 - the squared error of each fitted photo's
# gain predicted from its neighbours over that of the common colour) before a held-out photo takes its neighbours'.
# Phone videos: ball 0.81, apple 0.87; photo sets whose gains scatter: fox 0.45, cup 0.18, whose held-out views the
# neighbours' gains brought +0.19 dB and -0.07 / +0.09 (two fits) nearer their photos: little either way, so the bar
# stands at half (bench/README.md, "Real captures").
ORDER_EXPLAINS = 0.5


def capture_key(name: str) -> list:
    """A photo's place in the capture's order, read from its name as cameras and video frames number them: runs of
    digits compare as numbers, so 9 comes before 10 with or without leading zeros."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


class PhotoGains:
    """Each fitted photo's gain by name, and the gain of any photo of the capture from them: its own where it was
    fitted; else, by position in the capture's order (capture_key), the straight line between the nearest fitted photos
    before and after it (the nearest one's where it has a neighbour on one side only). Only where the order says
    something of the colour (ORDER_EXPLAINS): photos named in no order of their taking, or whose gains scatter from one
    to the next, leave a held-out photo in the common colour. `backdrop_as_taken`: the colour past the object is
    given with the photos as they were taken (their masks', or each photo's own backdrop), which the gains leave."""

    def __init__(self, names: Sequence[str], gains: dict[str, Sequence[float]], backdrop_as_taken: bool = False,
                 fields: dict[str, Sequence] | None = None):
        self.backdrop_as_taken = backdrop_as_taken
        self.order = sorted(names, key=capture_key)
        self.gains = {name: np.asarray(gain, dtype=np.float64) for name, gain in gains.items()}
        self.fields = {name: np.asarray(field, dtype=np.float64) for name, field in (fields or {}).items()}
        self.fitted = [i for i, name in enumerate(self.order) if name in self.gains]
        self.follows_order = self._neighbours_predict()
        self.fields_follow_order = self._neighbours_predict_fields()

    def of(self, name: str) -> np.ndarray:
        """Gain per channel [3] of photo `name`; ones for a name outside the capture's order or with no fitted photo."""
        if name in self.gains:
            return self.gains[name]
        if name not in self.order or not self.follows_order:
            return np.ones(3)
        return self._between(self.order.index(name), self.fitted)

    def field_of(self, name: str) -> np.ndarray | None:
        """Gain lattice [rows, cols, 3] of photo `name` across its frame (gain_fields): its own where it was measured;
        else its capture neighbours', as `of` takes their gains, where their lattices follow the capture's order; None
        where there is none to give (its gain, `of`, stands)."""
        if name in self.fields:
            return self.fields[name]
        if not self.fields or name not in self.order or not self.fields_follow_order:
            return None
        return self._between(self.order.index(name), self.fitted, self.fields)

    def _between(self, at: int, fitted: list[int], table: dict[str, np.ndarray] | None = None) -> np.ndarray:
        table = self.gains if table is None else table
        before = [i for i in fitted if i < at]
        after = [i for i in fitted if i > at]
        if not before or not after:
            return table[self.order[(before or after)[-1 if before else 0]]]
        lo, hi = before[-1], after[0]
        share = (at - lo) / (hi - lo)
        return (1 - share) * table[self.order[lo]] + share * table[self.order[hi]]

    def _neighbours_predict(self) -> bool:
        """Whether the fitted photos' gains follow the capture's order: each one's log gains predicted from the others
        by position explain at least ORDER_EXPLAINS of their squared spread about the common colour (0)."""
        if len(self.fitted) < 3:
            return False
        by_order = by_common = 0.0
        for i in self.fitted:
            own = np.log(self.gains[self.order[i]])
            by_order += float(((np.log(self._between(i, [j for j in self.fitted if j != i])) - own) ** 2).sum())
            by_common += float((own ** 2).sum())
        return by_order < (1.0 - ORDER_EXPLAINS) * by_common

    def _neighbours_predict_fields(self) -> bool:
        """Whether the light across the frames follows the capture's order too: each measured photo's lattice (log)
        is nearer the lattice its neighbours' give it by position than what a held-out photo takes without them (the
        gain its neighbours' give it, where the gains follow the order; else the common colour), summed over the
        photos. Frames a step apart in a video share their shadows and highlights; photos taken from one side of a
        room and then the other need not."""
        measured = [i for i in self.fitted if self.order[i] in self.fields]
        if len(measured) < 3:
            return False
        by_fields = by_gains = 0.0
        for i in measured:
            others = [j for j in measured if j != i]
            own = np.log(self.fields[self.order[i]])
            by_fields += float(((np.log(self._between(i, others, self.fields)) - own) ** 2).sum())
            without = np.log(self._between(i, others)) if self.follows_order else np.zeros(3)
            by_gains += float(((without - own) ** 2).sum())
        return by_fields < by_gains

    def record(self) -> dict:
        """model.json's entry: the photos' names in the capture's order, each fitted photo's gains and, where measured,
        its gain lattice."""
        record = {"order": self.order, "follows_order": self.follows_order, "backdrop_as_taken": self.backdrop_as_taken,
                  "gains": {name: [round(float(g), 5) for g in gain] for name, gain in self.gains.items()}}
        if self.fields:
            record["fields_follow_order"] = self.fields_follow_order
            record["fields"] = {name: np.round(field, 4).tolist() for name, field in self.fields.items()}
        return record

    @classmethod
    def from_record(cls, record: dict | None) -> "PhotoGains | None":
        if not record:
            return None
        return cls(record["order"], record["gains"], record.get("backdrop_as_taken", False), record.get("fields"))
