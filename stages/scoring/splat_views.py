"""The exported splats scored on the held-out views: rendered by the reference rasterizer
(plenoxels/splats/rasterize.py) and compared with the photos and with the field's own render of the same view.

Each view's photo is loaded as evaluate loads it (resized, its mask composited onto its backdrop or the fit's
background colour); the splats are composited on that same colour. Scores are means of the per-view PSNRs, as
evaluate's are, so `field_psnr` here is evaluate's PSNR on these views.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from stages.common.frames import load_frame
from stages.scoring.metrics import image_psnr
from plenoxels.core.scene_model import SceneModel
from plenoxels.splats.model import Splats
from plenoxels.splats.rasterize import render


def spread(items: list, limit: int) -> list:
    if limit <= 0 or len(items) <= limit:
        return items
    return [items[i] for i in np.linspace(0, len(items) - 1, limit).round().astype(int)]


def score_splats(root: Path, splats: Splats, model: SceneModel, frames: list[dict], scale: float, limit: int,
                 track=lambda items, desc: items) -> dict:
    """{views, psnr (splats vs photos), psnr_vs_field, field_psnr (field vs photos), seconds} over up to `limit`
    held-out views (split "test"); views 0 and no scores where there are none."""
    held_out = spread([f for f in frames if f.get("split") == "test"], limit)
    started, rows = time.monotonic(), []
    for frame in track(held_out, desc="scoring the splats on the held-out views"):
        truth, k = load_frame(root, frame, scale, model.background_color)
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
        with torch.no_grad():
            field = model.render_camera(c2w, k, backdrop=frame.get("backdrop"), photo=frame["name"])["rgb"].cpu().numpy()
        # The splats hold the field's common colour: scored as the photo was taken.
        behind = frame.get("backdrop") or model.background_color
        drawn = render(splats, c2w, k, background=behind)
        ours = model.as_photographed(drawn["rgb"], frame["name"], drawn["opacity"], behind).numpy()
        rows.append((image_psnr(ours, truth), image_psnr(ours, field), image_psnr(field, truth)))
    if not rows:
        return {"views": 0}
    psnr, vs_field, field_psnr = (round(float(np.mean(column)), 3) for column in zip(*rows))
    return {"views": len(rows), "scale": scale, "psnr": psnr, "psnr_vs_field": vs_field, "field_psnr": field_psnr,
            "seconds": round(time.monotonic() - started, 2)}
