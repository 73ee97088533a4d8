"""The crop box a user sets in the viewer: saved to OUT/view/crop.json, used by the export stage through
its `export.crop` setting (the six numbers themselves, so the export's cache key follows the box)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.common.json_files import read_json, write_json

CROP_FILE = Path("view") / "crop.json"


def crop_setting(lo, hi) -> str:
    """The `--set` value that hands this box to the export stage, e.g. export.crop=[-0.5,-0.5,0,0.5,0.5,1]."""
    return "export.crop=[" + ",".join(f"{float(x):.4g}" for x in (*lo, *hi)) + "]"


def write_crop(out: Path, lo, hi) -> Path:
    lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)
    path = Path(out) / CROP_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, {"frame": "normalized", "min": lo.tolist(), "max": hi.tolist(),
                      "setting": crop_setting(lo, hi)})
    return path


def read_crop(out: Path) -> tuple[np.ndarray, np.ndarray] | None:
    path = Path(out) / CROP_FILE
    if not path.is_file():
        return None
    record = read_json(path)
    return np.asarray(record["min"], dtype=np.float64), np.asarray(record["max"], dtype=np.float64)
