"""Masks the user gives beside the photos: a `masks/` or `mask/` folder holding one image per photo that marks the
object (white, or any value above a threshold) against what is not the object (black).

The folder sits beside the photo folder (`scene/images/` + `scene/masks/`, the NeuS/IDR layout `scene/image/` +
`scene/mask/`) or inside it (`photos/masks/`). A photo's mask is the file whose name matches the photo's: the same
stem in any image format (`0001.jpg` and `0001.png`), the photo's whole file name with a suffix added (COLMAP's
`0001.jpg.png`), the stem with `_mask` or `-mask` after it, or a stem that differs only in the zero-padding of its
numbers (NeuS's DTU releases name masks `000.png` beside images `000000.png`). A name that matches two photos, or a
photo that two masks match, is not guessed at: those photos count as having no mask.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from PIL import Image, ImageOps

from plenoxels.core.errors import UserError
from stages.capture.photos import orient

MASK_FOLDERS = ("masks", "mask")
MASK_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".bmp", ".gif"}
# Lossy formats leave noise around black: there a value must pass the middle of the range to mark the object.
LOSSY_SUFFIXES = {".jpg", ".jpeg", ".webp"}
LOSSY_THRESHOLD = 127
NAME_TAILS = ("_mask", "-mask", ".mask")
# A mask's aspect may differ from its photo's by this share and still be resized onto it (rounding in a resize).
ASPECT_TOLERANCE = 0.02
# The EXIF orientations that turn a photo a quarter: its stored pixels have the other shape.
TURNING = (5, 6, 7, 8)


def mask_folder(photos: Path) -> Path | None:
    """The masks folder for a folder of photos: inside it, or beside it; None when there is none."""
    for place in (photos, photos.parent):
        for name in MASK_FOLDERS:
            folder = place / name
            if folder.is_dir() and folder != photos and any(_is_mask_file(p) for p in folder.iterdir()):
                return folder
    return None


def _is_mask_file(path: Path) -> bool:
    return path.is_file() and not path.name.startswith(".") and path.suffix.lower() in MASK_SUFFIXES


def _unpadded(name: str) -> str:
    """The name with each run of digits written without leading zeros: 000012 and 12 read the same."""
    return re.sub(r"\d+", lambda m: str(int(m.group())), name)


def _keys(mask: Path) -> list[str]:
    """The photo names a mask file may belong to, most exact first."""
    stem = mask.stem
    keys = [stem]
    for tail in NAME_TAILS:
        if stem.lower().endswith(tail):
            keys.append(stem[:-len(tail)])
    if Path(stem).suffix:  # COLMAP's photo.jpg.png: the photo's stem too
        keys.append(Path(stem).stem)
    return keys


def match_masks(photos: list[Path], folder: Path, masks: list[Path] | None = None) -> dict[Path, Path]:
    """Each photo's mask in `folder` (or among `masks`, where the folder is the photos' own; photos without one are
    absent): by exact name first, then with numbers read without their zero-padding; a name two photos or two masks
    share is left unmatched."""
    masks = sorted(masks if masks is not None else (p for p in folder.iterdir() if _is_mask_file(p)))
    found: dict[Path, Path] = {}
    for normalise in (lambda name: name, _unpadded):
        photo_of: dict[str, list[Path]] = {}
        for photo in photos:
            if photo not in found:
                photo_of.setdefault(normalise(photo.stem), []).append(photo)
                photo_of.setdefault(normalise(photo.name), []).append(photo)
        claims: dict[Path, list[Path]] = {}
        for mask in masks:
            for key in _keys(mask):
                owners = photo_of.get(normalise(key), [])
                if len(owners) == 1:
                    claims.setdefault(owners[0], []).append(mask)
                    break
        for photo, claimed in claims.items():
            unique = sorted(set(claimed))
            if len(unique) == 1 and unique[0] not in found.values():
                found[photo] = unique[0]
    return found


def read_mask(path: Path, size: tuple[int, int], threshold: int | Literal["auto"] = "auto",
              photo_orientation: int = 1) -> np.ndarray:
    """A mask file as uint8 [h, w] (255 object, 0 not) at the photo's upright `size` (w, h): upright per its EXIF, or
    per its photo's (`photo_orientation`) where it has the shape of the photo's pixels as stored, turned (a mask made
    from a phone photo by a tool that ignores EXIF); its brightest channel (or its alpha where it has one and is
    otherwise opaque), resized when it was made at another size of the same shape, and above `threshold` = object
    (auto: any value above 0, or above the middle for lossy files, whose black is noisy)."""
    try:
        with Image.open(path) as im:
            im = ImageOps.exif_transpose(im)
            values = np.asarray(im.convert("RGBA" if "A" in im.getbands() else "RGB"))
    except Exception as e:  # any decoder failure means the same thing: this mask cannot be read
        raise UserError(f"cannot read the mask {path} ({str(e).splitlines()[0][:60] or type(e).__name__}); "
                        "fix or remove it") from None
    if values.shape[2] == 4 and values[..., 3].min() < 255:
        grey = values[..., 3]
    else:
        grey = values[..., :3].max(axis=2)
    h, w = grey.shape
    aspect = size[0] / size[1]
    if photo_orientation in TURNING and abs(h / w - aspect) <= ASPECT_TOLERANCE * aspect < abs(w / h - aspect):
        grey = orient(grey, photo_orientation)
        h, w = grey.shape
    if (w, h) != tuple(size):
        if abs(w / h - aspect) > ASPECT_TOLERANCE * aspect:
            raise UserError(f"the mask {path} is {w}x{h} but its photo is {size[0]}x{size[1]}, another shape; "
                            "give a mask of the photo's shape or remove it")
        grey = cv2.resize(grey, tuple(size), interpolation=cv2.INTER_LINEAR)
    if threshold == "auto":
        threshold = LOSSY_THRESHOLD if path.suffix.lower() in LOSSY_SUFFIXES else 0
    return np.where(grey > threshold, 255, 0).astype(np.uint8)
