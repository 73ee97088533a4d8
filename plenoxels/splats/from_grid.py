"""Splats from a fitted grid: one per cell the training views see, before any distillation.

A cell's splat sits at its centre with the field's own values there (trilinear: raw density and SH), so a surface cell
takes the colour its outer, nearly empty corners give it as the field does. Its peak opacity is what a ray crossing
one voxel of that density keeps: 1 - exp(-density x voxel length). Its shape is the voxel's: a Gaussian TENT_SIGMA
voxels wide along each grid axis, narrower than the tent of trilinear interpolation (1/sqrt(6) voxel) since the
renderer's low-pass filter widens every splat on screen and neighbours overlap (bench/README.md, "Splats"). In the fit
frame of a forward scene (NDC) or of a contracted grid's inner cube, the voxel's three edges are mapped to the world
through the frame's Jacobian at the centre, so the covariance is the voxel's shape in the world; a forward scene's
cells near the NDC far plane map to the far distance and are left out (FAR_NDC), and since its field reads SH along
NDC directions, each splat starts with the colour the reference camera sees it in (_seen_from_reference).

Which cells: those whose rendering weight over the training views' rays reaches `min_weight` (the surface the views
see; plenoxels.core.render.max_weights, per cell the smallest of its corners'), the heaviest first up to `max_splats`,
leaving out cells whose own opacity over a voxel is under 1/255.
"""
from __future__ import annotations

import numpy as np
import torch

from plenoxels.core.fit_frame import FitFrame
from plenoxels.core.grid import SparseGrid, sh_count
from plenoxels.core.render import COLOUR_OFFSET, SH_C0
from plenoxels.core.render import sh_basis
from plenoxels.splats.model import Splats, matrix_to_quat, sh_degree_of

TENT_SIGMA = 0.25
FAR_NDC = 0.98
OPACITY_RANGE = (0.005, 0.99)
MIN_OPTICAL_DEPTH = 1.0 / 255.0


CORNERS = [(dx, dy, dz) for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)]


def seen_cells(grid: SparseGrid, weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The cells whose lower corner is allocated: their lower corners [M, 3] (grid coordinates) and, per cell, the
    smallest of its corners' weights. A corner's weight is the largest of any sample in the eight cells around it, so
    the smallest over a cell's corners bounds what its own samples weighed (an unallocated corner: 0)."""
    coords = grid.coords().long().cpu()
    inside = (coords < torch.tensor(grid.resolution) - 1).all(dim=1)
    lower = coords[inside]
    links = grid.links.cpu()
    weight = torch.full((len(lower),), float("inf"))
    for d in CORNERS:
        corner = lower + torch.tensor(d)
        rows = links[corner[:, 0], corner[:, 1], corner[:, 2]].long()
        weight = torch.minimum(weight, torch.where(rows >= 0, weights[rows.clamp_min(0)], torch.zeros(())))
    return lower, weight


def voxel_edges_world(frame: FitFrame, points: np.ndarray, voxel: np.ndarray) -> np.ndarray:
    """[M, 3, 3]: column a is the world vector one voxel along fit-frame axis a, at each point (central differences);
    `voxel` is each point's voxel [M, 3] or one for all [3]."""
    voxel = np.broadcast_to(voxel, points.shape)
    columns = []
    for a in range(3):
        step = np.zeros(points.shape)
        step[:, a] = voxel[:, a] / 2
        columns.append(frame.to_world(points + step) - frame.to_world(points - step))
    return np.stack(columns, axis=2)


def splats_from_grid(grid: SparseGrid, frame: FitFrame, weights: torch.Tensor, max_splats: int,
                     min_weight: float) -> Splats:
    """Splats (in the normalised world) for the cells whose weight reaches min_weight, at most max_splats of them."""
    lower, weight = seen_cells(grid, weights.detach().cpu().float())
    keep = weight >= min_weight
    lower, weight = lower[keep], weight[keep]
    # Each cell's centre and size (a grid with knots has cells of more than one size).
    points = grid.grid_to_world(lower.double() + 0.5).numpy()
    voxel = (grid.grid_to_world(lower.double() + 1.0) - grid.grid_to_world(lower.double())).numpy()
    density, sh = grid.sample(torch.as_tensor(points, dtype=torch.float32, device=grid.data.device))
    optical_depth = torch.relu(density.cpu()).double().numpy() * voxel.mean(axis=1)
    keep = optical_depth >= MIN_OPTICAL_DEPTH
    if frame.ndc is not None:
        keep &= points[:, 2] < FAR_NDC
    order = np.argsort(-weight.numpy()[keep], kind="stable")[:max_splats]
    points, optical_depth, voxel = points[keep][order], optical_depth[keep][order], voxel[keep][order]
    sh = sh.cpu()[torch.as_tensor(np.nonzero(keep)[0][order])]

    edges = voxel_edges_world(frame, points, voxel)
    cov = TENT_SIGMA ** 2 * edges @ edges.transpose(0, 2, 1)
    variances, axes = np.linalg.eigh(cov)
    axes[np.linalg.det(axes) < 0, :, 0] *= -1  # a proper rotation: a mirror flips one axis of a symmetric shape
    log_scales = 0.5 * np.log(np.clip(variances, 1e-20, None))

    opacity = np.clip(1.0 - np.exp(-optical_depth), *OPACITY_RANGE)
    sh = sh.reshape(-1, 3, sh_count(grid.sh_degree))
    world = frame.to_world(points)
    if frame.ndc is not None:
        sh = _seen_from_reference(sh, frame, world)
    as_t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    return Splats(as_t(world), as_t(log_scales), as_t(matrix_to_quat(axes)),
                  as_t(np.log(opacity) - np.log1p(-opacity)), sh.float().clone())


def _seen_from_reference(sh: torch.Tensor, frame: FitFrame, world: np.ndarray) -> torch.Tensor:
    """A forward scene's field takes its SH along NDC directions, which no world direction stands for alone: each splat
    starts with the colour the reference camera's ray to it sees, as its degree-0 term (distillation fits the rest)."""
    centre = torch.tensor(frame.ndc.reference_c2w, dtype=torch.float64)[:3, 3]
    d = torch.as_tensor(world, dtype=torch.float64) - centre
    _, ndc_dirs = frame.rays(centre.expand_as(d).contiguous(), d / d.norm(dim=1, keepdim=True))
    ndc_dirs = (ndc_dirs / ndc_dirs.norm(dim=1, keepdim=True)).float()
    colour = torch.relu((sh * sh_basis(sh_degree_of(sh.shape[2]), ndc_dirs)[:, None, :]).sum(-1) + COLOUR_OFFSET)
    out = torch.zeros_like(sh)
    out[:, :, 0] = (colour - COLOUR_OFFSET) / SH_C0
    return out
