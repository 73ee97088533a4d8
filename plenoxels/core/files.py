"""The files a saved scene model is made of (SceneModel.save and load; the fit stage's output), free of torch so that
the pipeline's planning can name them without loading the model; and how every file another run reads back is
written."""
import os
from pathlib import Path

MODEL_FILE = "model.json"   # the frame, options, background and grid header
GRID_FILE = "grid.pt"       # the grid's tensors


def write_whole(path, write) -> None:
    """Calls `write(tmp)` on a temporary file beside `path`, flushes it to the disk and renames it over `path`: a
    reader sees the old file or the new one, never part of one, even after a crash or a full disk (a failed write
    removes the temporary file and leaves `path` as it was)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        write(tmp)
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
