"""Pictures made from renders: 8-bit conversion, colour-mapped depth, error images and contact sheets."""
from __future__ import annotations

import cv2
import numpy as np
from matplotlib import colormaps

from stages.scoring.metrics import to_uint8

# Error images show |render - truth| (mean over channels) times this, so small errors are visible.
ERROR_GAIN = 4.0
DEPTH_PERCENTILES = (2.0, 98.0)
# Pixels at least this opaque count as covered in the depth maps.
DEPTH_MIN_OPACITY = 0.5
SHEET_GAP = 4
CAPTION_HEIGHT = 18


def colour_depth(depth: np.ndarray, opacity: np.ndarray) -> np.ndarray:
    """uint8 RGB [h,w,3]: depth through the turbo colour map (near blue, far red), stretched
    between its percentiles over the covered pixels; uncovered pixels black."""
    covered = opacity >= DEPTH_MIN_OPACITY
    out = np.zeros(depth.shape + (3,), dtype=np.uint8)
    if not covered.any():
        return out
    lo, hi = np.percentile(depth[covered], DEPTH_PERCENTILES)
    scaled = np.clip((depth - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    rgb = colormaps["turbo"](scaled)[..., :3]
    out[covered] = to_uint8(rgb[covered])
    return out


def error_image(render: np.ndarray, truth: np.ndarray) -> np.ndarray:
    error = np.clip(np.abs(render - truth).mean(axis=-1) * ERROR_GAIN, 0.0, 1.0)
    return to_uint8(colormaps["magma"](error)[..., :3])


def fit_to(image: np.ndarray, side: int) -> np.ndarray:
    """`image` resized so that its longest side is `side` pixels."""
    scale = side / max(image.shape[:2])
    size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST)


def contact_sheet(rows: list[tuple[np.ndarray, ...]], side: int, captions: list[str] | None = None) -> np.ndarray:
    """uint8 image: one row of tiles per view (e.g. ground truth | render | error), 4 px white gaps; with
    `captions`, each row's caption (e.g. its scores) is written in a strip under it."""
    tiles = [[fit_to(t, side) for t in row] for row in rows]
    columns = max(len(row) for row in tiles)
    h = max(t.shape[0] for row in tiles for t in row)
    w = max(t.shape[1] for row in tiles for t in row)
    strip = CAPTION_HEIGHT if captions else 0
    row_h = h + strip + SHEET_GAP
    sheet = np.full((len(tiles) * row_h + SHEET_GAP, columns * (w + SHEET_GAP) + SHEET_GAP, 3), 255, dtype=np.uint8)
    for r, row in enumerate(tiles):
        y = SHEET_GAP + r * row_h
        for c, tile in enumerate(row):
            x = SHEET_GAP + c * (w + SHEET_GAP)
            sheet[y:y + tile.shape[0], x:x + tile.shape[1]] = tile
        if captions and captions[r]:
            cv2.putText(sheet, captions[r], (SHEET_GAP, y + h + CAPTION_HEIGHT - 5), cv2.FONT_HERSHEY_SIMPLEX,
                        0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return sheet
