"""Gaussian splats as the original 3D Gaussian Splatting code keeps them, in torch.

Each splat: a mean, log scales along its own axes, a rotation quaternion (w, x, y, z; not necessarily unit, read
normalised), an opacity logit and SH coefficients [3, K] (channel-major, the grid's layout). Its colour seen along a
unit direction d (from the camera to the splat) is relu(sum_k sh_k Y_k(d) + 0.5), the grid's own colour rule
(plenoxels/core/render.py), so a grid vertex's SH serve a splat unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

from plenoxels.core.render import COLOUR_OFFSET, SH_C0, sh_basis


def sh_degree_of(k: int) -> int:
    degree = round(k ** 0.5) - 1
    if (degree + 1) ** 2 != k or not 0 <= degree <= 3:
        raise ValueError(f"{k} SH coefficients per channel is no degree 0-3")
    return degree


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Unit-normalised (w, x, y, z) quaternions [N, 4] -> rotation matrices [N, 3, 3]."""
    w, x, y, z = (q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)).unbind(-1)
    return torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1).reshape(-1, 3, 3)


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotation matrices [N, 3, 3] -> unit (w, x, y, z) quaternions [N, 4] with w >= 0 (Shepperd's method)."""
    r = np.asarray(r, dtype=np.float64).reshape(-1, 3, 3)
    trace = np.trace(r, axis1=1, axis2=2)
    candidates = np.stack([
        np.stack([1 + trace, r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], -1),
        np.stack([r[:, 2, 1] - r[:, 1, 2], 1 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2], r[:, 0, 1] + r[:, 1, 0],
                  r[:, 0, 2] + r[:, 2, 0]], -1),
        np.stack([r[:, 0, 2] - r[:, 2, 0], r[:, 0, 1] + r[:, 1, 0], 1 - r[:, 0, 0] + r[:, 1, 1] - r[:, 2, 2],
                  r[:, 1, 2] + r[:, 2, 1]], -1),
        np.stack([r[:, 1, 0] - r[:, 0, 1], r[:, 0, 2] + r[:, 2, 0], r[:, 1, 2] + r[:, 2, 1],
                  1 - r[:, 0, 0] - r[:, 1, 1] + r[:, 2, 2]], -1)], axis=1)
    best = np.argmax(np.stack([trace, r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], -1), axis=1)
    q = candidates[np.arange(len(r)), best]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def sh_rotation(degree: int, rotation: np.ndarray) -> list[np.ndarray]:
    """Per degree l >= 1, the matrix M_l [(2l+1), (2l+1)] such that coefficients c' = M_l c seen along R d give what c
    gave along d: found by least squares on directions spread over the sphere (each degree's functions span a space
    rotations keep)."""
    dirs = torch.as_tensor(np.random.default_rng(0).normal(size=(256, 3)))
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    rotated = dirs @ torch.as_tensor(np.asarray(rotation, dtype=np.float64)).T
    y, y_rot = sh_basis(degree, dirs).numpy(), sh_basis(degree, rotated).numpy()
    out = []
    for l in range(1, degree + 1):
        band = slice(l * l, (l + 1) ** 2)
        # y_rot = y A^T per band; c'.Y(R d) = c.Y(d) for all d gives A^T c' = c.
        a_t = np.linalg.lstsq(y[:, band], y_rot[:, band], rcond=None)[0]
        out.append(np.linalg.inv(a_t))
    return out


@dataclass
class Splats:
    means: torch.Tensor  # [N, 3]
    log_scales: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4] (w, x, y, z)
    opacity_logits: torch.Tensor  # [N]
    sh: torch.Tensor  # [N, 3, K]

    @property
    def count(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_of(self.sh.shape[2])

    def tensors(self) -> dict[str, torch.Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def detached(self) -> "Splats":
        return Splats(**{k: v.detach().clone() for k, v in self.tensors().items()})

    def subset(self, keep) -> "Splats":
        return Splats(**{k: v[keep] for k, v in self.tensors().items()})

    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    def covariances(self) -> torch.Tensor:
        """[N, 3, 3]: R S S^T R^T."""
        m = quat_to_matrix(self.quats) * torch.exp(self.log_scales)[:, None, :]
        return m @ m.transpose(1, 2)

    def colours(self, dirs: torch.Tensor) -> torch.Tensor:
        """RGB [N, 3] seen along unit directions [N, 3] (from the camera towards each splat)."""
        basis = sh_basis(self.sh_degree, dirs)
        return torch.relu((self.sh * basis[:, None, :]).sum(-1) + COLOUR_OFFSET)

    def diffuse(self) -> torch.Tensor:
        """RGB [N, 3] in [0, 1] of the degree-0 term alone: the colour viewers without SH draw."""
        return torch.clamp(self.sh[:, :, 0] * SH_C0 + COLOUR_OFFSET, 0.0, 1.0)

    def transformed(self, matrix: np.ndarray) -> "Splats":
        """The splats under a similarity (a uniform scale, a rotation and a shift: a 4x4 matrix), the SH turned with it
        so each splat keeps its colour along each direction."""
        m = np.asarray(matrix, dtype=np.float64)
        linear = m[:3, :3]
        scale = float(np.cbrt(np.linalg.det(linear)))
        rotation = linear / scale
        if scale <= 0 or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-5):
            raise ValueError("splats follow only a similarity with a positive scale (no shear, no mirror)")
        as_t = lambda a: torch.as_tensor(a, dtype=self.means.dtype)  # noqa: E731
        means = self.means.detach() @ as_t(linear).T + as_t(m[:3, 3])
        turned = quat_to_matrix(self.quats.detach()).double().numpy()
        quats = as_t(matrix_to_quat(rotation[None] @ turned))
        sh = self.sh.detach().clone()
        for l, band_matrix in enumerate(sh_rotation(self.sh_degree, rotation), start=1):
            band = slice(l * l, (l + 1) ** 2)
            sh[:, :, band] = sh[:, :, band] @ as_t(band_matrix).T
        return Splats(means, self.log_scales.detach() + float(np.log(scale)), quats,
                      self.opacity_logits.detach().clone(), sh)
