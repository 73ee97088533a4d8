"""What in a video's picture is not the scene: black bars around it (a portrait clip exported in a landscape frame, a
film's letterbox), found in frames spread over the clip (stages/capture/video.py reads them; photos saved from such
a clip are looked at in stages/capture/photos.py)."""
from __future__ import annotations

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
