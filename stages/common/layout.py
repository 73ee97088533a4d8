"""The output layout, spelled in one place: the stages in the order they run, the folder each writes under a scene's
output root, the files in it that other stages and tools read, and the runner's own folders.

    <out>/<stage>/manifest.json   a complete output (written last)
    <out>/.work/<stage>/          the output being written        <out>/.resume/<stage>/  a stage's checkpoints
    <out>/.trash/<stage>/         the previous output during the swap

The Makefile reads STAGE_ORDER from this file, so its lines keep their shape: one tuple of names.
"""
from __future__ import annotations

from pathlib import Path

from plenoxels.core.files import GRID_FILE, MODEL_FILE

STAGE_ORDER = ("ingest", "poses", "normalize", "fit", "evaluate", "export")

# The runner's bookkeeping.
MANIFEST = "manifest.json"
WORK, RESUME, TRASH = ".work", ".resume", ".trash"
# In a stage's summary (its manifest's), where it lowered its settings to fit in the memory its run had: the bytes its
# settings as set need. The runner runs it again once that much memory is there.
MEMORY_AS_SET = "memory_as_set"

# What each stage writes that others read, by stage.
IMAGES_JSON = "images.json"              # ingest: the ingested images and what was skipped
TRANSFORMS_JSON = "transforms.json"      # poses: cameras (nerfstudio layout)
POINTS_NPZ = "points.npz"                # poses: sparse points and their observations
SCENE_JSON = "scene.json"                # normalize: the scene frame, type, near/far and split
MODEL_JSON = MODEL_FILE                  # fit: the scene model and the fit's settings (a saved SceneModel)
GRID_PT = GRID_FILE                      # fit: the fitted grid
FIT_JSON = "fit.json"                    # fit: the record of the fit
CHECKPOINT_PT = "checkpoint.pt"          # fit: the checkpoint a stopped fit resumes from (under .resume/fit/)
METRICS_JSON = "metrics.json"            # evaluate: scores per held-out view and their mean
EXPORT_JSON = "export.json"              # export: what was written, in which frame
MESH_PLY = "mesh.ply"                    # export: the mesh


def stage_file(out: Path, stage: str, name: str) -> Path:
    """A file of `stage`'s complete output under the scene's output root `out`."""
    return Path(out) / stage / name


def scene_json(out: Path) -> Path:
    """The normalize stage's scene.json under the output root `out`."""
    return stage_file(out, "normalize", SCENE_JSON)
