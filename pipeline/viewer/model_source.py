"""The newest radiance field of a scene: the fit stage's output (fit/) or, while a fit runs, its latest
checkpoint (.resume/fit/checkpoint.pt, written by plenoxels.core.train.Fitter.save_checkpoint)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from stages.common.json_files import read_json
from plenoxels.core.grid import SparseGrid
from plenoxels.core.scene_model import ModelOptions, SceneModel
from stages.common.layout import CHECKPOINT_PT, FIT_JSON, GRID_PT, MANIFEST, MODEL_JSON, RESUME, scene_json, stage_file

CHECKPOINT = Path(RESUME) / "fit" / CHECKPOINT_PT


@dataclass(frozen=True)
class ModelVersion:
    path: Path
    mtime_ns: int

    @property
    def is_checkpoint(self) -> bool:
        return self.path.name.endswith(".pt")


class ModelSource:
    """Finds and loads the newest model under a scene's output folder."""

    def __init__(self, out: Path):
        self.out = Path(out)

    def latest(self) -> ModelVersion | None:
        """The newer of the finished fit and the running fit's checkpoint, or None when neither exists."""
        candidates = []
        for path, stamp in ((stage_file(self.out, "fit", MODEL_JSON), stage_file(self.out, "fit", GRID_PT)),
                            (self.out / CHECKPOINT, self.out / CHECKPOINT)):
            try:
                if path.is_file():
                    candidates.append(ModelVersion(path, stamp.stat().st_mtime_ns))
            except FileNotFoundError:  # replaced between the two calls
                continue
        return max(candidates, key=lambda v: v.mtime_ns, default=None)

    def load(self, version: ModelVersion) -> tuple[SceneModel, str]:
        """The model and a line saying what it is."""
        if not version.is_checkpoint:
            model = SceneModel.load(version.path.parent)
            record_path = stage_file(self.out, "fit", FIT_JSON)
            record = read_json(record_path) if record_path.is_file() else {}
            done = "" if record.get("complete", True) else f", stopped at step {record.get('steps')}"
            return model, f"fit: {'x'.join(map(str, model.grid.resolution))} grid{done}"
        return self._from_checkpoint(version.path)

    def _from_checkpoint(self, path: Path) -> tuple[SceneModel, str]:
        # The checkpoint holds the grid and background tensors; the frame and options around them come from
        # scene.json and the fit's settings as the fit stage builds them.
        state = torch.load(path, map_location="cpu", weights_only=False)
        scene = read_json(scene_json(self.out))
        background = state.get("background")
        options = self._model_options(background)
        model = SceneModel.create(scene, options, 2)
        model.grid = SparseGrid.from_state_dict(state["grid"])
        if background is not None and model.background is not None:
            model.background.load_state_dict(background)
        if "background_color" in state:  # what the fit sees behind everything (a contracted grid's: the photos' mean)
            model.background_color = tuple(float(c) for c in state["background_color"])
        return model, f"live fit: checkpoint at step {state['step']}, {'x'.join(map(str, model.grid.resolution))} grid"

    def _model_options(self, background: dict | None) -> ModelOptions:
        """The options of the last completed fit where there is one (its manifest), else the defaults;
        the background model's presence and shape follow the checkpoint."""
        options = ModelOptions()
        manifest = stage_file(self.out, "fit", MANIFEST)
        if manifest.is_file():
            saved = read_json(manifest).get("settings", {})
            for name in ("ndc", "contract", "background_color", "step_size", "stop_transmittance", "box_padding"):
                if name in saved:
                    setattr(options, name, saved[name])
        options.background = "on" if background is not None else "off"
        if background is not None:
            if "texture" in background:   # one table [K, H, W, 4]
                spheres, _, width, _ = background["texture"].shape
            else:                           # older checkpoints: density [K, 1, H, W] and colour apart
                spheres, _, _, width = background["density"].shape
            options.background_spheres, options.background_width = int(spheres), int(width)
        return options
