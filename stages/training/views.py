"""The photos a fit learns from and the few it checks itself against: normalize/scene.json's training frames as a
RaySet, and a handful of held-out views, small, for the held-out PSNR the fit reports as it goes."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from stages.common.frames import load_frames
from stages.common.text import short_list
from plenoxels.core.errors import UserError
from plenoxels.core.scene_model import SceneModel, psnr
from plenoxels.core.ray_set import RaySet, as_bytes, clipped_bits


class HeldOut:
    """A few held-out views, small, to report held-out PSNR while fitting."""

    def __init__(self, root: Path, frames: list[dict], views: int, scale: float, background_color):
        pick = frames if len(frames) <= views else [frames[i] for i in
                                                    np.linspace(0, len(frames) - 1, views).round().astype(int)]
        self.names = [frame["name"] for frame in pick]
        self.views = [(np.asarray(frame["transform_matrix"], dtype=np.float64), k, torch.from_numpy(image),
                       frame.get("backdrop")) for frame, (image, k, _) in zip(pick, load_frames(root, pick, scale,
                                                                                           background_color))]

    def __bool__(self) -> bool:
        return bool(self.views)

    @property
    def rays(self) -> int:
        """Rays of one evaluation."""
        return sum(k.w * k.h for _, k, _, _ in self.views)

    def psnr(self, model: SceneModel) -> float:
        """Mean PSNR of the views' renders, each in its photo's colour where the fit measured the photos' colours."""
        errors = []
        for name, (c2w, k, image, backdrop) in zip(self.names, self.views):
            rgb = model.render_camera(c2w, k, backdrop=backdrop, photo=name)["rgb"].cpu()
            errors.append(float(((rgb - image) ** 2).mean()))
        return float(np.mean([psnr(e) for e in errors]))


def training_frames(scene: dict, report) -> tuple[list[dict], list[dict]]:
    """The frames to fit and the held-out ones. Where the capture carries masks, a training photo without one is left
    out (with a warning): its whole frame would put what surrounds the object into the grid, where every other photo
    says there is nothing."""
    frames = scene.get("frames") or []
    train = [f for f in frames if f.get("split", "train") == "train"]
    held_out = [f for f in frames if f.get("split") == "test"]
    unmasked = [f["name"] for f in train if not f.get("mask_path")]
    if unmasked and len(unmasked) < len(train):
        report.warn(f"{len(unmasked)} training photo(s) have no mask where the others do, so the fit leaves them out: "
                    f"{short_list(unmasked)}")
        train = [f for f in train if f.get("mask_path")]
    if not train:
        raise UserError("scene.json has no training frames; re-run normalize with fewer held out (normalize.holdout_every)")
    return train, held_out


def load_training(root: Path, frames: list[dict], scale: float, background_color, report,
                  with_masks: bool = False, with_cover: bool = False, with_clipped: bool = False) -> RaySet:
    """The training frames' pixels (masks composited onto `background_color`), cameras and, where normalize found
    each photo's own backdrop colour, those; `with_masks`, the masks too where the photos have them (what the fit's
    measure of each photo's colour leaves out); `with_cover`, where every photo has a mask, each pixel's coverage by
    it (the fit trains some rays toward random backdrops); `with_clipped`, each pixel's clipped channels
    (clipped_bits). Each photo is turned to bytes as it is read, so the floats of one photo at a time are held, never
    of all (lego's 100 photos at 800x800: 0.2 GB, not 0.8)."""
    images, c2ws, ks, masks, cover, clipped = [], [], [], [], [], []
    loaded = load_frames(root, frames, scale, background_color)
    for frame, (image, k, mask) in zip(frames, report.track(loaded, total=len(frames), desc="loading training images")):
        images.append(as_bytes(image))
        c2ws.append(np.asarray(frame["transform_matrix"], dtype=np.float64))
        ks.append(k)
        mask = None if mask is None else as_bytes(mask)
        clipped.append(clipped_bits(images[-1], mask) if with_clipped else None)
        masks.append(mask if with_masks else None)
        cover.append(mask if with_cover else None)
    backdrops = [frame.get("backdrop") for frame in frames]
    behind = [frame.get("backdrop") or background_color for frame in frames]
    return RaySet(images, c2ws, ks, backdrops if all(b is not None for b in backdrops) else None,
                  masks if all(m is not None for m in masks) else None, behind,
                  cover if all(c is not None for c in cover) else None, clipped if with_clipped else None)
