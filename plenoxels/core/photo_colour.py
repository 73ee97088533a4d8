"""Each training photo's own colour: per channel, the gain that takes the field's render of its view to it.

A phone sets exposure and white balance anew as it turns: a colour correction per photo brings ball's training renders
1.2 dB closer to their photos (bench/README.md, "Real captures"). No one field reproduces photos that disagree on
colour; it fits their average, blurred, or takes the differences up as view-dependent colour. With `fit.photo_colour`
the fit measures, now and then, each photo's gain per channel against its render (over an even lattice of its pixels,
clipped pixels left out) and trains the field against the photos taken back to a common colour, photo / gain. The gains
average 1 over the photos, so the field keeps their average colour, the one a new view is rendered in.
"""
from __future__ import annotations

import math

import torch

# A photo's channel value this close to 0 or 1 is clipped: its true value is unknown, so it says nothing of the gain.
CLIPPED = 0.02
# The most a photo's gain may move from the common colour: beyond, the ratio measures something other than colour.
GAIN_RANGE = (0.5, 2.0)


class PhotoColour:
    """Per photo and channel, the gain from the common colour to the photo: photo = gain * common."""

    def __init__(self, photos: int):
        self.gain = torch.ones(photos, 3, dtype=torch.float64)

    def fit(self, image: torch.Tensor, rendered: torch.Tensor, photo: torch.Tensor) -> None:
        """Fits each photo's gains to these pixels (image index [B], the render and the photo's colour [B, 3], on the
        CPU): the ratio of the photo's sum to the render's over the pixels not clipped, then set to average 1 over
        the photos. A ratio of sums, not a least-squares line: the render is itself wrong by a few percent at every
        pixel, which would pull a fitted slope towards flat."""
        rendered, photo = rendered.double().clamp(0, 1), photo.double()
        use = ((photo > CLIPPED) & (photo < 1 - CLIPPED)).double()
        sums = torch.zeros(self.gain.shape[0], 3, 3, dtype=torch.float64)
        sums.index_add_(0, image.long(), torch.stack([use, use * rendered, use * photo], 1))
        n, sr, sp = sums.unbind(1)
        fitted = (n >= 16) & (sr > 1e-3 * n)
        gain = torch.where(fitted, sp / torch.where(fitted, sr, torch.ones_like(sr)), torch.ones_like(sr))
        gain = gain.clamp(*GAIN_RANGE)
        self.gain = gain / gain.mean(dim=0, keepdim=True)

    def to_common(self, image: torch.Tensor, photo: torch.Tensor) -> torch.Tensor:
        """Photo colours [B, 3] of photos `image` [B] taken back to the common colour (on their device)."""
        return photo / self.gain.to(device=photo.device, dtype=photo.dtype)[image]

    def gain_db(self, image: torch.Tensor, rendered: torch.Tensor, photo: torch.Tensor) -> float:
        """How much closer (dB of PSNR) the renders come to these photo pixels through the gains than as they are,
        over the pixels that are not clipped."""
        rendered, photo = rendered.double().clamp(0, 1), photo.double()
        use = ((photo > CLIPPED) & (photo < 1 - CLIPPED)).double()
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
