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

    def __init__(self, names: Sequence[str], gains: dict[str, Sequence[float]], backdrop_as_taken: bool = False):
        self.backdrop_as_taken = backdrop_as_taken
        self.order = sorted(names, key=capture_key)
        self.gains = {name: np.asarray(gain, dtype=np.float64) for name, gain in gains.items()}
        self.fitted = [i for i, name in enumerate(self.order) if name in self.gains]
        self.follows_order = self._neighbours_predict()

    def of(self, name: str) -> np.ndarray:
        """Gain per channel [3] of photo `name`; ones for a name outside the capture's order or with no fitted photo."""
        if name in self.gains:
            return self.gains[name]
        if name not in self.order or not self.follows_order:
            return np.ones(3)
        return self._between(self.order.index(name), self.fitted)

    def _between(self, at: int, fitted: list[int]) -> np.ndarray:
        before = [i for i in fitted if i < at]
        after = [i for i in fitted if i > at]
        if not before or not after:
            return self.gains[self.order[(before or after)[-1 if before else 0]]]
        lo, hi = before[-1], after[0]
        share = (at - lo) / (hi - lo)
        return (1 - share) * self.gains[self.order[lo]] + share * self.gains[self.order[hi]]

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

    def record(self) -> dict:
        """model.json's entry: the photos' names in the capture's order and each fitted photo's gains."""
        return {"order": self.order, "follows_order": self.follows_order, "backdrop_as_taken": self.backdrop_as_taken,
                "gains": {name: [round(float(g), 5) for g in gain] for name, gain in self.gains.items()}}

    @classmethod
    def from_record(cls, record: dict | None) -> "PhotoGains | None":
        return cls(record["order"], record["gains"], record.get("backdrop_as_taken", False)) if record else None
