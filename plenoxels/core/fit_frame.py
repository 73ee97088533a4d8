"""The fit frame: the frame the grid lives in: the normalised world, NDC of the average camera, or the contracted
frame of an unbounded scene.

`FitFrame(ndc)` or `FitFrame(contraction=...)` maps world rays into the frame the kernels take them in (torch tensors,
as the renderer takes them) and points between the grid's frame and the world (numpy arrays [N, 3], computed in
float64). With neither, every map is the identity.

A contraction (unbounded scenes) first moves and scales the world so that the foreground's cube is [-1, 1]^3 (the
*inner frame*; rays are given to the kernels there), then contracts it (csrc/plenoxels_math.h, contract_point): the
grid spans [-2, 2]^3 and holds all of space, the world outside the cube ever more coarsely towards infinity.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np
import torch

from plenoxels.core.ndc import NDCMapping

# The contracted grid's box: all of space.
CONTRACTED_BOX = ((-2.0, -2.0, -2.0), (2.0, 2.0, 2.0))


def _max_norm(x):
    """|x|_inf over the last axis, kept [N, 1] (numpy or torch)."""
    if isinstance(x, torch.Tensor):
        return x.abs().amax(dim=-1, keepdim=True)
    return np.abs(x).max(axis=-1, keepdims=True)


def contract(q):
    """Inner-frame points [N, 3] (numpy or torch) -> contracted points: q where |q|_inf <= 1, else
    (2 - 1/m) q / m with m = |q|_inf."""
    m = _max_norm(q)
    safe = np.maximum(m, 1) if not isinstance(m, torch.Tensor) else m.clamp_min(1)
    return ((2 - 1 / safe) / safe) * q  # the kernels' order of operations (csrc/plenoxels_math.h, contract_point)


def uncontract(c):
    """Contracted points [N, 3] with |c|_inf < 2 -> inner-frame points (contract's inverse)."""
    n = _max_norm(c)
    safe = np.clip(n, 1, 2 - 1e-12) if not isinstance(n, torch.Tensor) else n.clamp(1, 2 - 1e-12)
    return c / (safe * (2 - safe))


@dataclass(frozen=True)
class Contraction:
    """An unbounded scene's frame: inner = (world - centre) / half_size, then contracted when `contracts`."""

    centre: tuple[float, float, float]
    half_size: float
    contracts: bool = True  # the grid's points are contracted; False: the inner frame itself (exports' crop)

    @classmethod
    def around_box(cls, lo, hi) -> "Contraction":
        """The cube that holds the box [lo, hi] (its longest side) as the inner cube."""
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        return cls(tuple(((lo + hi) / 2).tolist()), float((hi - lo).max() / 2))

    def inner(self) -> "Contraction":
        return replace(self, contracts=False)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, record: dict) -> "Contraction":
        return cls(tuple(float(v) for v in record["centre"]), float(record["half_size"]), bool(record.get("contracts", True)))

    def rays(self, origins: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        centre = torch.tensor(self.centre, dtype=origins.dtype, device=origins.device)
        return (origins - centre) / self.half_size, dirs

    def to_world(self, points: np.ndarray) -> np.ndarray:
        inner = uncontract(points) if self.contracts else points
        return inner * self.half_size + np.asarray(self.centre)

    def from_world(self, points: np.ndarray) -> np.ndarray:
        inner = (points - np.asarray(self.centre)) / self.half_size
        return contract(inner) if self.contracts else inner


class FitFrame:
    """Maps between the fit frame (where the grid lives) and the normalised world: the identity, NDC or a contraction."""

    def __init__(self, ndc: NDCMapping | None = None, contraction: Contraction | None = None):
        self.ndc = ndc
        self.contraction = contraction

    @property
    def name(self) -> str:
        return "ndc" if self.ndc is not None else "contracted" if self.contraction is not None else "world"

    def rays(self, origins: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World rays [B, 3] -> the rays the kernels take (unchanged without NDC or a contraction)."""
        if self.ndc is not None:
            return self.ndc.rays(origins, dirs)
        if self.contraction is not None:
            return self.contraction.rays(origins, dirs)
        return origins, dirs

    def world_distance_scale(self) -> float:
        """World distance per unit of the kernels' t, where that is one number (not in NDC)."""
        return self.contraction.half_size if self.contraction is not None else 1.0

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """Fit-frame points [N, 3] -> world points."""
        if self.ndc is not None:
            return self.ndc.points_to_world(torch.as_tensor(points, dtype=torch.float64)).numpy()
        if self.contraction is not None:
            return self.contraction.to_world(np.asarray(points, dtype=np.float64))
        return points

    def from_world(self, points: np.ndarray) -> np.ndarray:
        """World points [N, 3] -> fit-frame points."""
        if self.ndc is not None:
            return self.ndc.points_to_ndc(torch.as_tensor(points, dtype=torch.float64)).numpy()
        if self.contraction is not None:
            return self.contraction.from_world(np.asarray(points, dtype=np.float64))
        return points

    def flips_orientation(self, near: np.ndarray) -> bool:
        """Whether the map to the world mirrors (its Jacobian at `near` has a negative determinant),
        which reverses which side of a face is out. The NDC map is smooth, so one point decides."""
        if self.ndc is None:
            return False
        h = 1e-4
        columns = [(self.to_world(near[None] + h * e) - self.to_world(near[None] - h * e))[0] / (2 * h) for e in np.eye(3)]
        return bool(np.linalg.det(np.stack(columns, axis=1)) < 0)
