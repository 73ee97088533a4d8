"""Frame images as the fit and evaluate stages see them: float RGB in [0, 1], masks composited, resized."""
from __future__ import annotations

from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Iterator

import cv2
import imageio.v3 as iio
import numpy as np
import torch

from stages.common.media import read_rgb, rgb_of
from plenoxels.core.cameras import Intrinsics
from plenoxels.core.errors import UserError


def load_frame(root: Path, frame: dict, scale: float, background_color) -> tuple[np.ndarray, Intrinsics]:
    """A frame's image as float32 RGB [h,w,3] in [0,1], resized by `scale`, its mask (if any) composited
    onto the frame's own `backdrop` colour where normalize gave it one, else onto `background_color`; and the
    intrinsics of the resized image."""
    image, k, _ = read_frame(root, frame, scale, background_color)
    return image, k


def read_frame(root: Path, frame: dict, scale: float,
               background_color) -> tuple[np.ndarray, Intrinsics, np.ndarray | None]:
    """load_frame's image and intrinsics, and the mask it composited with (float32 [h, w] in [0, 1] at the image's
    size; None where the frame has none), from the one decode."""
    path = root / frame["file_path"]
    if not path.is_file():
        raise UserError(f"image {path} listed in scene.json is missing; re-run the stages before fit")
    mask_path = frame.get("mask_path")
    if mask_path == frame["file_path"]:
        # An RGBA photo that is its own mask (a dataset read in place): one decode gives both.
        image = iio.imread(path)
        rgb, alpha = rgb_of(image), alpha_of(image)
    else:
        rgb = read_rgb(path)
        alpha = read_alpha(root / mask_path) if mask_path else None
    k = Intrinsics.from_frame(frame)
    if (rgb.shape[1], rgb.shape[0]) != (k.w, k.h):
        raise UserError(f"{path} is {rgb.shape[1]}x{rgb.shape[0]} but scene.json says {k.w}x{k.h}; re-run normalize")
    if alpha is not None and alpha.shape != rgb.shape[:2]:
        raise UserError(f"mask {mask_path} is not the size of its image; re-run ingest")
    k = k.scaled(scale) if scale != 1 else k
    image, coverage = _composite(rgb.astype(np.float32), 255.0, alpha, k, frame.get("backdrop") or background_color)
    return image, k, coverage


def composited(colour: np.ndarray, peak: float, alpha: np.ndarray | None, k: Intrinsics,
               background_color) -> np.ndarray:
    """`colour` (float32 [h, w, 3] in [0, peak]; weighted in place) with `alpha` ([h, w] in [0, 1], or None)
    composited onto `background_color`, at k's size, as float32 RGB in [0, 1]."""
    return _composite(colour, peak, alpha, k, background_color)[0]


def _composite(colour: np.ndarray, peak: float, alpha: np.ndarray | None, k: Intrinsics,
               background_color) -> tuple[np.ndarray, np.ndarray | None]:
    """composited's image and `alpha` at k's size, clipped to [0, 1] (None for None)."""
    if alpha is None:
        return np.ascontiguousarray(resized(colour, k) / peak), None
    # Colour weighted by alpha and alpha itself are resized apart, then composited: area resizing is linear, so this
    # is the composite resized, with the arithmetic done at the new size.
    colour *= alpha[..., None]
    alpha = np.clip(resized(alpha, k), 0.0, 1.0)
    background = np.asarray(background_color, dtype=np.float32)
    return np.ascontiguousarray(resized(colour, k) / peak + background * (1 - alpha[..., None])), alpha


def resized(image: np.ndarray, k: Intrinsics) -> np.ndarray:
    """`image` at k's size (area resampling: each pixel the mean of what it covers)."""
    if (k.w, k.h) == (image.shape[1], image.shape[0]):
        return image
    return cv2.resize(image, (k.w, k.h), interpolation=cv2.INTER_AREA)


def load_frames(root: Path, frames: list[dict], scale: float, background_color,
                threads: int | None = None) -> Iterator[tuple[np.ndarray, Intrinsics, np.ndarray | None]]:
    """read_frame of each frame, in order, decoded on `threads` threads (default: as many as the fit's kernels use,
    OMP_NUM_THREADS, so a batch's share of the cores holds here too; PNG decoding and resizing release the GIL),
    yielded as each is ready so a progress bar can follow. At most two frames a thread are read ahead of the one
    taken: a pool's map would decode every photo at once and hold them all as floats until taken."""
    threads = threads or torch.get_num_threads()
    if threads == 1 or len(frames) <= 1:
        yield from (read_frame(root, frame, scale, background_color) for frame in frames)
        return
    with ThreadPoolExecutor(threads) as pool:
        ahead: deque = deque()
        for frame in frames:
            ahead.append(pool.submit(read_frame, root, frame, scale, background_color))
            if len(ahead) > 2 * threads:
                yield ahead.popleft().result()
        while ahead:
            yield ahead.popleft().result()


def read_alpha(path: Path) -> np.ndarray:
    """A mask as float32 [h,w] in [0,1]: a grey image, or the alpha channel of an RGBA one."""
    return alpha_of(iio.imread(path))


def alpha_of(image: np.ndarray) -> np.ndarray:
    """A decoded mask as float32 [h,w] in [0,1]: a grey image, or the alpha channel of an RGBA one."""
    if image.ndim == 3:
        image = image[..., 3] if image.shape[2] == 4 else image[..., 0]
    scale = 65535.0 if image.dtype == np.uint16 else 255.0
    return image.astype(np.float32) / scale
