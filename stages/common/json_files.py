"""The pipeline's JSON records (manifests, scene.json, fit.json, ...): written atomically, read back."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from plenoxels.core.files import write_whole


def write_json(path: Path, data: Any) -> None:
    """Writes beside the target and renames, so a reader never sees half a file."""
    text = json.dumps(data, indent=2, default=_jsonable)
    write_whole(path, lambda tmp: Path(tmp).write_text(text))


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
