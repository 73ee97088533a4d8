"""Frame images as the fit and evaluate stages see them: float RGB in [0, 1], masks composited, resized."""
from __future__ import annotations

from pathlib import Path

import cv2
import imageio.v3 as iio
import numpy as np

from pipeline.io import read_rgb
from plenoxels.cameras import Intrinsics
from plenoxels.errors import UserError


def load_frame(root: Path, frame: dict, scale: float, background_color) -> tuple[np.ndarray, Intrinsics]:
    """A frame's image as float32 RGB [h,w,3] in [0,1], resized by `scale`, its mask (if any) composited
    onto `background_color`; and the intrinsics of the resized image."""
    path = root / frame["file_path"]
    if not path.is_file():
        raise UserError(f"image {path} listed in scene.json is missing; re-run the stages before fit")
    rgb = read_rgb(path).astype(np.float32) / 255.0
    k = Intrinsics.from_frame(frame)
    if (rgb.shape[1], rgb.shape[0]) != (k.w, k.h):
        raise UserError(f"{path} is {rgb.shape[1]}x{rgb.shape[0]} but scene.json says {k.w}x{k.h}; re-run normalize")
    if frame.get("mask_path"):
        alpha = read_alpha(root / frame["mask_path"])
        if alpha.shape != rgb.shape[:2]:
            raise UserError(f"mask {frame['mask_path']} is not the size of its image; re-run ingest")
        rgb = rgb * alpha[..., None] + np.asarray(background_color, dtype=np.float32) * (1 - alpha[..., None])
    k = k.scaled(scale) if scale != 1 else k
    if (k.w, k.h) != (rgb.shape[1], rgb.shape[0]):
        rgb = cv2.resize(rgb, (k.w, k.h), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(rgb), k


def read_alpha(path: Path) -> np.ndarray:
    """A mask as float32 [h,w] in [0,1]: a grey image, or the alpha channel of an RGBA one."""
    image = iio.imread(path)
    if image.ndim == 3:
        image = image[..., 3] if image.shape[2] == 4 else image[..., 0]
    scale = 65535.0 if image.dtype == np.uint16 else 255.0
    return image.astype(np.float32) / scale
