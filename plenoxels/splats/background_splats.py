"""Splats of a multi-sphere background model (plenoxels/core/background.py): one per texel that is not clear.

A texel is a patch of its sphere: its splat sits at the texel centre's direction on the sphere, flat along the sphere
(the normal axis FLAT times the smaller in-plane one), BACKGROUND_SIGMA texels wide along azimuth and polar angle (a
Gaussian about as wide as the tent of the bilinear read the model does, 1/sqrt(6) texel), with the texel's own opacity
(1 - exp(-relu(density)): a layer's density is already integrated across it) and its colour as the degree-0 term (the
model's colour does not change with the view). Texel centres follow the model's read: azimuth -pi + (i + 0.5) 2 pi / W,
polar angle from +z (j + 0.5) pi / H. The splats composite front to back by camera depth, as the spheres do from the
inside; what light passes them all sees the far colour, the splats' background colour.

The model reads each sphere where a ray leaves it, never where it enters: a camera outside a sphere sees through its
near side. Splats have no such side, so a sphere smaller than the cameras' reach would veil the scene from every camera
beyond it (a phone circling an object on a floor stands outside the inner spheres). Its texels go out along their
directions to just beyond the farthest camera (OUTSIDE_CAMERAS times its distance from the centre), where every view
sees them behind the grid, as the model shows them.
"""
from __future__ import annotations

import numpy as np
import torch

from plenoxels.core.background import MultiSphereBackground
from plenoxels.core.render import COLOUR_OFFSET, SH_C0
from plenoxels.splats.from_grid import MIN_OPTICAL_DEPTH, OPACITY_RANGE
from plenoxels.splats.model import Splats, matrix_to_quat

BACKGROUND_SIGMA = 0.45
FLAT = 0.05
OUTSIDE_CAMERAS = 1.05


def splats_from_background(background: MultiSphereBackground, sh_count: int, camera_reach: float = 0.0) -> Splats:
    """Splats [N] in the normalised world for the texels whose optical depth reaches 1/255, SH [N, 3, sh_count], none
    of them nearer the centre than OUTSIDE_CAMERAS x camera_reach (the farthest camera's distance from the centre)."""
    texture = background.texture.detach().cpu().double()
    k, h, w, _ = texture.shape
    depth = torch.relu(texture[..., 0]).numpy()
    sphere, row, column = np.nonzero(depth >= MIN_OPTICAL_DEPTH)
    azimuth = -np.pi + (column + 0.5) * 2 * np.pi / w
    polar = (row + 0.5) * np.pi / h
    normal = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], axis=1)
    along = np.stack([-np.sin(azimuth), np.cos(azimuth), np.zeros_like(azimuth)], axis=1)
    axes = np.stack([along, np.cross(normal, along), normal], axis=2)  # columns; a proper rotation
    radius = np.maximum(background.radii.detach().cpu().double().numpy()[sphere], OUTSIDE_CAMERAS * camera_reach)
    widths = np.stack([radius * np.sin(polar) * 2 * np.pi / w, radius * np.pi / h], axis=1) * BACKGROUND_SIGMA
    scales = np.concatenate([widths, FLAT * widths.min(axis=1, keepdims=True)], axis=1)
    opacity = np.clip(1.0 - np.exp(-depth[sphere, row, column]), *OPACITY_RANGE)
    centre = background.centre.detach().cpu().double().numpy()
    rgb = torch.sigmoid(texture[sphere, row, column, 1:]).float()
    sh = torch.zeros(len(sphere), 3, sh_count)
    sh[:, :, 0] = (rgb - COLOUR_OFFSET) / SH_C0
    as_t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    return Splats(as_t(centre + radius[:, None] * normal), as_t(np.log(scales)), as_t(matrix_to_quat(axes)),
                  as_t(np.log(opacity) - np.log1p(-opacity)), sh)
