"""Splats from a fitted grid: one per vertex the training views see, before any distillation.

A vertex's value spreads over the cells around it by trilinear interpolation, a tent one voxel wide each way whose
standard deviation is 1/sqrt(6) of a voxel; the splat takes a Gaussian of about that width (TENT_SIGMA voxels along
each grid axis). A ray through the vertex crosses an integrated density of (raw density) x (one voxel of fit-frame
length), so the splat's peak opacity is 1 - exp(-that). Its SH are the vertex's. In the fit frame of a forward scene
(NDC) or of a contracted grid's inner cube, the voxel's three edges are mapped to the world through the frame's
Jacobian at the vertex, so the splat's covariance is the voxel's shape in the world; a forward scene's vertices near
the NDC far plane map to the far distance and are left out (FAR_NDC).

Which vertices: those whose largest rendering weight over the training views' rays reaches `min_weight` (the surface
the views see; plenoxels.core.render.max_weights), the heaviest first up to `max_splats`, leaving out vertices
whose own opacity over a voxel is under 1/255.
"""
from __future__ import annotations

import numpy as np
import torch

from plenoxels.core.fit_frame import FitFrame
from plenoxels.core.grid import SparseGrid, sh_count
from plenoxels.splats.model import Splats, matrix_to_quat

TENT_SIGMA = 0.5
FAR_NDC = 0.98
OPACITY_RANGE = (0.005, 0.99)
MIN_OPTICAL_DEPTH = 1.0 / 255.0


def vertex_points(grid: SparseGrid, rows: torch.Tensor) -> np.ndarray:
    """Fit-frame positions [M, 3] of the given rows' vertices."""
    lo = np.asarray(grid.bbox_min, dtype=np.float64)
    return lo + grid.coords()[rows].double().numpy() / np.asarray(grid.scale)


def voxel_edges_world(frame: FitFrame, points: np.ndarray, voxel: np.ndarray) -> np.ndarray:
    """[M, 3, 3]: column a is the world vector one voxel along fit-frame axis a, at each point (central differences)."""
    columns = []
    for a in range(3):
        step = np.zeros(3)
        step[a] = voxel[a] / 2
        columns.append(frame.to_world(points + step) - frame.to_world(points - step))
    return np.stack(columns, axis=2)


def splats_from_grid(grid: SparseGrid, frame: FitFrame, weights: torch.Tensor, max_splats: int,
                     min_weight: float) -> Splats:
    """Splats (in the normalised world) for the rows whose weight reaches min_weight, at most max_splats of them."""
    weights = weights.detach().cpu()
    voxel = 1.0 / np.asarray(grid.scale)
    # A sample's weight reaches all eight corners of its cell: a corner with next to no density of its own adds nothing.
    optical_depth = torch.relu(grid.density.detach().cpu()).double() * float(np.mean(voxel))
    candidates = torch.nonzero((weights >= min_weight) & (optical_depth >= MIN_OPTICAL_DEPTH)).squeeze(1)
    candidates = candidates[torch.argsort(weights[candidates], descending=True)]
    points = vertex_points(grid, candidates)
    if frame.ndc is not None:
        near_enough = points[:, 2] < FAR_NDC
        candidates, points = candidates[torch.as_tensor(near_enough)], points[near_enough]
    candidates, points = candidates[:max_splats], points[:max_splats]

    edges = voxel_edges_world(frame, points, voxel)
    cov = TENT_SIGMA ** 2 * edges @ edges.transpose(0, 2, 1)
    variances, axes = np.linalg.eigh(cov)
    axes[np.linalg.det(axes) < 0, :, 0] *= -1  # a proper rotation: a mirror flips one axis of a symmetric shape
    log_scales = 0.5 * np.log(np.clip(variances, 1e-20, None))

    opacity = np.clip(1.0 - np.exp(-optical_depth[candidates].numpy()), *OPACITY_RANGE)
    k = sh_count(grid.sh_degree)
    sh = grid.sh.detach().cpu()[candidates].reshape(-1, 3, k)
    world = frame.to_world(points)
    as_t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    return Splats(as_t(world), as_t(log_scales), as_t(matrix_to_quat(axes)),
                  as_t(np.log(opacity) - np.log1p(-opacity)), sh.float().clone())
