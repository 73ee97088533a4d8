"""Splats of a fitted scene model: started from its grid where the training views see it, then distilled against its
own renders of those views (plenoxels/splats/from_grid.py, plenoxels/splats/distill.py).

The model is the one exports read (SceneModel.foreground_model: a contracted grid's inner cube, with nothing behind
it, so a contracted grid's outer shell is not among the splats). A multi-sphere background model behind a bounded grid
becomes splats too, one per texel that is not clear (plenoxels/splats/background_splats.py), distilled with the rest.
The splats are composited on the model's background colour (the far colour behind its spheres), as its renders are.
"""
from __future__ import annotations

import time

import numpy as np
import torch

from plenoxels.core.cameras import Intrinsics, rays_from_camera
from plenoxels.core.render import max_weights
from plenoxels.core.scene_model import SceneModel
from plenoxels.splats.distill import TargetView, distill
from plenoxels.splats.background_splats import splats_from_background
from plenoxels.splats.from_grid import splats_from_grid
from plenoxels.splats.model import Splats


def training_views(frames: list[dict], limit: int) -> list[dict]:
    """The training frames (every one, or `limit` of them spread evenly; 0: all)."""
    train = [f for f in frames if f.get("split", "train") == "train"] or frames
    if limit and len(train) > limit:
        train = [train[i] for i in np.linspace(0, len(train) - 1, limit).round().astype(int)]
    return train


def target_views(model: SceneModel, frames: list[dict], scale: float, track=lambda items, desc: items
                 ) -> tuple[list[TargetView], torch.Tensor]:
    """The model's renders of the frames at `scale` of their size, and per grid row the largest rendering weight any of
    their rays gives it."""
    views, weights = [], torch.zeros(model.grid.num_occupied)
    for record in track(frames, desc="rendering the training views for the splats"):
        k = Intrinsics.from_frame(record).scaled(scale)
        c2w = np.asarray(record["transform_matrix"], dtype=np.float64)
        with torch.no_grad():
            rgb = model.render_camera(c2w, k)["rgb"].cpu()
            o, d = rays_from_camera(c2w, k)
            o, d = model.fit_frame.rays(o.reshape(-1, 3), d.reshape(-1, 3))
            weights = torch.maximum(weights, max_weights(model.grid, o, d, model.render_options).cpu())
        views.append(TargetView(c2w, k, rgb))
    return views, weights


def fit_splats(model: SceneModel, frames: list[dict], max_splats: int, min_weight: float, scale: float,
               max_views: int, seconds: float, window: int, seed: int = 0, track=lambda items, desc: items
               ) -> tuple[Splats, dict]:
    """Splats of the model in its normalised world, and a record of how they were made."""
    started = time.monotonic()
    views, weights = target_views(model, training_views(frames, max_views), scale, track)
    splats = splats_from_grid(model.grid, model.fit_frame, weights, max_splats, min_weight)
    grid_count, background_count = splats.count, 0
    if model.background is not None:
        centre = model.background.centre.detach().cpu().double().numpy()
        reach = max(float(np.linalg.norm(np.asarray(f["transform_matrix"])[:3, 3] - centre)) for f in frames)
        behind = splats_from_background(model.background, splats.sh.shape[2], reach)
        background_count = behind.count
        splats = Splats(**{name: torch.cat([t, getattr(behind, name)]) for name, t in splats.tensors().items()})
    splats, distilled = distill(splats, views, model.background_color, seconds, window, seed)
    return splats, {"count": splats.count, "grid_splats": grid_count, "background_splats": background_count,
                    "capped": grid_count >= max_splats,
                    "sh_degree": splats.sh_degree, "training_views": len(views), "view_scale": scale,
                    "distillation": distilled, "seconds": round(time.monotonic() - started, 2)}
