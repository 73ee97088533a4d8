"""The fit frame: the frame the grid lives in, the normalised world or NDC of the average camera.

`FitFrame(ndc)` maps world rays into the fit frame (torch tensors, as the renderer takes them) and points
between the frames (numpy arrays [N, 3], computed in float64). With `ndc=None` every map is the identity.
"""
from __future__ import annotations

import numpy as np
import torch

from plenoxels.ndc import NDCMapping


class FitFrame:
    """Maps between the fit frame (where the grid lives) and the normalised world: the identity, or NDC."""

    def __init__(self, ndc: NDCMapping | None = None):
        self.ndc = ndc

    def rays(self, origins: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World rays [B, 3] -> fit-frame rays (unchanged without NDC)."""
        if self.ndc is None:
            return origins, dirs
        return self.ndc.rays(origins, dirs)

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """Fit-frame points [N, 3] -> world points."""
        if self.ndc is None:
            return points
        return self.ndc.points_to_world(torch.as_tensor(points, dtype=torch.float64)).numpy()

    def from_world(self, points: np.ndarray) -> np.ndarray:
        """World points [N, 3] -> fit-frame points."""
        if self.ndc is None:
            return points
        return self.ndc.points_to_ndc(torch.as_tensor(points, dtype=torch.float64)).numpy()

    def flips_orientation(self, near: np.ndarray) -> bool:
        """Whether the map to the world mirrors (its Jacobian at `near` has a negative determinant),
        which reverses which side of a face is out. The NDC map is smooth, so one point decides."""
        if self.ndc is None:
            return False
        h = 1e-4
        columns = [(self.to_world(near[None] + h * e) - self.to_world(near[None] - h * e))[0] / (2 * h) for e in np.eye(3)]
        return bool(np.linalg.det(np.stack(columns, axis=1)) < 0)
