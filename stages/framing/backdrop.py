"""How much of the photos show nothing: transparent pixels, one flat backdrop colour behind the whole capture or each
photo's own, the colours outside the masks, and a still textured background behind a turning object."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from stages.framing.sightings import Cameras


# Sampled images and their size when measuring how much of the photos show an empty backdrop.
BACKDROP_SAMPLES = 12
BACKDROP_SIDE = 96
BACKDROP_TOLERANCE = 6  # 8-bit levels from the backdrop colour that still count as backdrop
# A still background behind a turning object: textured pixels (a local contrast of STILL_TEXTURE_LEVELS) that look the
# same in every sampled photo, on this share of the pixels: a turntable's room shows far more than that, a handheld
# capture's moving view next to none (bench/README.md, "Normalize").
STILL_TEXTURE_LEVELS = 24
STILL_TEXTURED_SHARE = 0.1
# One backdrop behind the whole capture: at least BACKDROP_MIN_PHOTOS of the sampled photos show its colour on at least
# BACKDROP_BORDER_SHARE of their borders (an object in front of a flat backdrop leaves most of every border to it).
BACKDROP_BORDER_SHARE = 0.5
BACKDROP_MIN_PHOTOS = 0.8



def _thumbnail(path: Path, mode: str) -> np.ndarray:
    """A small copy of an image; for masks ("L") an image with an alpha channel gives its alpha."""
    with Image.open(path) as im:
        im = im.getchannel("A") if mode == "L" and "A" in im.getbands() else im.convert(mode)
        im.thumbnail((BACKDROP_SIDE, BACKDROP_SIDE), Image.Resampling.BOX)
        return np.asarray(im)



@dataclass
class Backdrop:
    """How much of the photos shows nothing: from masks (transparent or masked-out pixels), or from one flat colour."""
    empty_fraction: float               # share of sampled pixels that show the empty backdrop
    from_masks: bool
    colour: np.ndarray | None           # the flat backdrop's RGB (0-255) where no masks say it
    photos_showing: float               # share of the sampled photos whose borders mostly show that colour
    still_textured: float = 0.0         # share of pixels with texture that is the same in every sampled photo



def measure_backdrop(cams: Cameras, poses_dir: Path) -> Backdrop | None:
    """The empty backdrop of a few evenly spread photos (small copies): where every one has a mask, its masked-out
    pixels; otherwise the one flat colour that dominates the image borders, and how many of the photos show it around
    their own borders (a white table in some photos and a dark room in others is no one colour). None when the
    images cannot be read."""
    picks = np.unique(np.linspace(0, len(cams.frames) - 1, min(BACKDROP_SAMPLES, len(cams.frames))).round().astype(int))
    frames = [cams.frames[i] for i in picks]
    try:
        if all(f.get("mask_path") for f in frames):
            empty = [_thumbnail(poses_dir / f["mask_path"], "L") < 128 for f in frames]
            return Backdrop(float(np.mean(np.concatenate([e.ravel() for e in empty]))), True, None, 1.0)
        images = [_thumbnail(poses_dir / f["file_path"], "RGB").astype(np.int32) for f in frames]
    except (OSError, ValueError):
        return None
    borders = [_border(im) for im in images]
    colour = _flat_colour(np.concatenate(borders))
    empty = [np.abs(im - colour).max(axis=-1) <= BACKDROP_TOLERANCE for im in images]
    showing = [np.mean(np.abs(b - colour).max(axis=-1) <= BACKDROP_TOLERANCE) >= BACKDROP_BORDER_SHARE for b in borders]
    return Backdrop(float(np.mean(np.concatenate([e.ravel() for e in empty]))), False, colour, float(np.mean(showing)),
                    still_textured_share(images))



def _border(image: np.ndarray) -> np.ndarray:
    """[M,3] the pixels of an image's outer two rows and columns."""
    return np.concatenate([image[:2].reshape(-1, 3), image[-2:].reshape(-1, 3), image[:, :2].reshape(-1, 3),
                           image[:, -2:].reshape(-1, 3)])



def _flat_colour(pixels: np.ndarray) -> np.ndarray:
    """The colour that dominates these pixels: the median of the most common 32-level bin."""
    bins = pixels // 32
    keys, counts = np.unique(bins, axis=0, return_counts=True)
    return np.median(pixels[(bins == keys[counts.argmax()]).all(axis=1)], axis=0)



def own_backdrops(cams: Cameras, poses_dir: Path) -> tuple[np.ndarray, float] | None:
    """([N,3] RGB in [0, 1], share): each photo's own backdrop colour, the flat colour that dominates its border, and
    the share of the photos whose border shows it on at least BACKDROP_BORDER_SHARE of its pixels: an object
    photographed on a white table from one side and before a dark room from the other, each photo on one flat colour
    of its own. None when the images cannot be read."""
    colours, flat = [], []
    try:
        for frame in cams.frames:
            border = _border(_thumbnail(poses_dir / frame["file_path"], "RGB").astype(np.int32))
            colour = _flat_colour(border)
            colours.append(colour / 255.0)
            flat.append(np.mean(np.abs(border - colour).max(axis=-1) <= BACKDROP_TOLERANCE) >= BACKDROP_BORDER_SHARE)
    except (OSError, ValueError):
        return None
    return np.asarray(colours), float(np.mean(flat))



def shows_backdrop_outside_mask(frame: dict) -> bool:
    """Whether a frame's photo shows a backdrop outside its mask: it has a mask, and was not cut out by an alpha of its
    own (ingest took that alpha as its mask, or the RGBA photo is its own mask), which leaves whatever the cut left."""
    return bool(frame.get("mask_path")) and not frame.get("cutout") and frame["mask_path"] != frame["file_path"]


def masked_out_colours(cams: Cameras, poses_dir: Path) -> np.ndarray | None:
    """[N,3] RGB in [0, 1]: each masked photo's median colour outside its mask (small copies; where a mask leaves no
    pixel out, its border's median). None when an image or mask cannot be read."""
    colours = []
    try:
        for frame in cams.frames:
            image = _thumbnail(poses_dir / frame["file_path"], "RGB").astype(np.float64)
            mask = _thumbnail(poses_dir / frame["mask_path"], "L")
            if mask.shape != image.shape[:2]:
                mask = np.asarray(Image.fromarray(mask).resize((image.shape[1], image.shape[0]), Image.Resampling.BOX))
            outside = image[mask < 128]
            colours.append(np.median(outside if len(outside) else _border(image), axis=0) / 255.0)
    except (OSError, ValueError):
        return None
    return np.asarray(colours)


def from_nearest_cameras(colours: np.ndarray, centres: np.ndarray, held_out: set[int], count: int = 2) -> np.ndarray:
    """`colours` ([N,3]) with each held-out photo's replaced by its `count` nearest training cameras' (by centre,
    weighted by inverse distance): a held-out view is a new view, so it takes nothing from its own photo, and cameras
    standing near one another see the same backdrop behind the object."""
    train = np.array([i for i in range(len(colours)) if i not in held_out])
    if not len(train):
        return colours
    colours = colours.copy()
    for i in held_out:
        distance = np.linalg.norm(centres[train] - centres[i], axis=1)
        nearest = np.argsort(distance)[:count]
        weight = 1.0 / np.maximum(distance[nearest], 1e-9)
        colours[i] = weight @ colours[train[nearest]] / weight.sum()
    return colours



def still_textured_share(images: list[np.ndarray]) -> float:
    """The share of pixels that show texture (a local contrast of STILL_TEXTURE_LEVELS or more) and look the same
    (within BACKDROP_TOLERANCE) in every one of these photos, taken from around the scene: a still background behind
    an object that turned, not the scene the cameras moved around. 0 where the photos differ in size."""
    if len(images) < 3 or len({im.shape for im in images}) > 1:
        return 0.0
    stack = np.stack(images).astype(np.int16)
    still = (stack.max(axis=0) - stack.min(axis=0)).max(axis=-1) <= BACKDROP_TOLERANCE
    grey = np.median(stack, axis=0).mean(axis=-1).astype(np.float32)
    contrast = cv2.dilate(grey, np.ones((3, 3), np.uint8)) - cv2.erode(grey, np.ones((3, 3), np.uint8))
    return float(np.mean(still & (contrast >= STILL_TEXTURE_LEVELS)))
