"""What in a video's picture is not the scene: black bars around it (a portrait clip exported in a landscape frame, a
film's letterbox), and a still overlay on it (a watermark, a caption, a timestamp an app burned in), found in frames
spread over the clip (stages/capture/video.py reads them; photos saved from such a clip are looked at in
stages/capture/photos.py)."""
from __future__ import annotations

import cv2
import numpy as np

# A video's rows or columns at its frame's edge that are dark and flat (grey mean at most BAR_MEAN, spread at most
# BAR_SPREAD, of 255) in each of BAR_SAMPLES frames spread over the clip are black bars (a portrait clip exported in a
# landscape frame, a film's letterbox), not scene: cropped from every frame where they are at least BAR_MIN_SHARE of
# the frame across and leave at least BAR_MIN_PICTURE of it. Bars decode to 0-4 with 18 at most where the codec rings
# beside the picture; the darkest edge lines of ball, fox, cup, fern and apple have means of 23-140.
BAR_SAMPLES = 24
BAR_MEAN = 12.0
BAR_SPREAD = 6.0
BAR_MIN_SHARE = 0.01
BAR_MIN_PICTURE = 0.2
# A still overlay stays at the same pixels while the view moves: pixels whose grey spreads by at most OVERLAY_SPREAD
# (of 255, the standard deviation) over the samples are still, and a connected region of still pixels holding at least
# OVERLAY_MIN_EDGES crisp edges (Sobel magnitude of the samples' median at least OVERLAY_EDGE) and at most
# OVERLAY_MAX_SHARE of the picture is an overlay, grown by OVERLAY_GROW pixels for its soft rim and the codec's
# ringing. Where more than half the picture is still, the view barely moved and nothing tells an overlay apart.
# A still region without such edges is a flat wall, sky or backdrop, whatever its size. Measured on ball's clip with
# white text and a solid box drawn on: text and box found whole; on the clip as filmed, and on apple's, none.
OVERLAY_SPREAD = 4.0
OVERLAY_EDGE = 60.0
OVERLAY_MIN_EDGES = 12
OVERLAY_MAX_SHARE = 0.15
OVERLAY_GROW = 2


def _dark_lines(grey: np.ndarray, axis: int) -> np.ndarray:
    """Which rows (axis 1) or columns (axis 0) of a grey frame are dark and flat."""
    return (grey.mean(axis=axis) <= BAR_MEAN) & (grey.std(axis=axis) <= BAR_SPREAD)


def _edge_run(dark: np.ndarray) -> tuple[int, int]:
    """How many lines from each end of `dark` are dark without a break."""
    lit = np.flatnonzero(~dark)
    return (int(lit[0]), int(len(dark) - 1 - lit[-1])) if len(lit) else (len(dark), 0)


def picture_box(greys: list[np.ndarray]) -> tuple[slice, slice] | None:
    """The (rows, columns) of a video's frames that hold its picture, within the black bars along their edges
    (BAR_MEAN, BAR_SPREAD) in every one of `greys`; None where there are no bars worth cropping or no picture
    would be left (a clip dark throughout)."""
    if not greys:
        return None
    dark_rows = np.logical_and.reduce([_dark_lines(g, 1) for g in greys])
    dark_columns = np.logical_and.reduce([_dark_lines(g, 0) for g in greys])
    (top, bottom), (left, right) = _edge_run(dark_rows), _edge_run(dark_columns)
    height, width = greys[0].shape
    top, bottom = (v if v >= BAR_MIN_SHARE * height else 0 for v in (top, bottom))
    left, right = (v if v >= BAR_MIN_SHARE * width else 0 for v in (left, right))
    if not (top or bottom or left or right):
        return None
    if height - top - bottom < BAR_MIN_PICTURE * height or width - left - right < BAR_MIN_PICTURE * width:
        return None
    return slice(top, height - bottom), slice(left, width - right)


def still_overlay(greys: list[np.ndarray]) -> np.ndarray | None:
    """The pixels (a boolean mask of the frames' shape) a still overlay covers in frames spread over a clip, or None
    where there is none, or where the view barely moved (OVERLAY_SPREAD and the rest above)."""
    if len(greys) < 8 or len({g.shape for g in greys}) > 1:
        return None
    stack = np.stack(greys).astype(np.float32)
    still = stack.std(axis=0) <= OVERLAY_SPREAD
    if still.mean() > 0.5:
        return None
    median = np.median(stack, axis=0)
    crisp = np.hypot(cv2.Sobel(median, cv2.CV_32F, 1, 0), cv2.Sobel(median, cv2.CV_32F, 0, 1)) >= OVERLAY_EDGE
    # Grown first, so a word's letters make one region, and a thin stroke's edges (beside it) count for it.
    grown = cv2.dilate(still.astype(np.uint8), np.ones((2 * OVERLAY_GROW + 1,) * 2, np.uint8))
    count, labels, stats, _ = cv2.connectedComponentsWithStats(grown, connectivity=8)
    edges = np.bincount(labels[(grown > 0) & crisp], minlength=count)
    overlay = (edges >= OVERLAY_MIN_EDGES) & (stats[:, cv2.CC_STAT_AREA] <= OVERLAY_MAX_SHARE * still.size)
    overlay[0] = False  # the label of the pixels that moved
    return overlay[labels] if overlay.any() else None


def paint_over(rgb: np.ndarray, overlay: np.ndarray) -> np.ndarray:
    """A frame with the overlay's pixels (a mask of any size, taken to the frame's) painted from around them
    (Telea's inpainting): a guess of the scene, which trains nothing wrong where the overlay was."""
    mask = cv2.resize(overlay.astype(np.uint8), (rgb.shape[1], rgb.shape[0]), interpolation=cv2.INTER_AREA) > 0
    if not mask.any():
        return rgb
    return cv2.inpaint(rgb, mask.astype(np.uint8), 3, cv2.INPAINT_TELEA)
