"""File reading and writing shared by the stages: JSON written atomically, 8-bit RGB images in and out."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np


def write_json(path: Path, data: Any) -> None:
    """Writes beside the target and renames, so a reader never sees half a file."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, default=_jsonable))
    os.replace(tmp, path)


def read_json(path: Path) -> Any:
    return json.loads(Path(path).read_text())


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} to JSON")


def read_rgb(path: Path) -> np.ndarray:
    """An 8-bit RGB image [h, w, 3] (the ingest stage has already normalised every image to this)."""
    image = iio.imread(path)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    return np.ascontiguousarray(image[..., :3])


def write_png(path: Path, image: np.ndarray) -> None:
    iio.imwrite(path, np.ascontiguousarray(image), extension=".png")
