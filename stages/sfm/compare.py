"""Comparing two sets of camera poses of the same images, up to the similarity (scale, rotation,
translation) that SfM cannot know: used by the poses tests and the poses benchmark."""
from __future__ import annotations

import numpy as np


def umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale s, rotation R, translation t minimising sum |s R source_i + t - target_i|^2 (Umeyama 1991)."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    a, b = source - mu_s, target - mu_t
    u, d, vt = np.linalg.svd(b.T @ a / len(source))
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ sign @ vt
    scale = float(np.trace(np.diag(d) @ sign) / (a ** 2).sum(1).mean())
    return scale, rotation, mu_t - scale * rotation @ mu_s


def compare_poses(estimate: np.ndarray, reference: np.ndarray) -> dict:
    """Camera-to-world [N,4,4] estimates against references of the same images (any one convention shared by both).

    Aligns the estimated centres to the references by a similarity, then reports each camera's centre
    error as a share of the reference spread (RMS distance of the centres from their mean) and the
    angle of its residual rotation in degrees."""
    scale, rotation, translation = umeyama(estimate[:, :3, 3], reference[:, :3, 3])
    centres = scale * estimate[:, :3, 3] @ rotation.T + translation
    spread = float(np.sqrt(((reference[:, :3, 3] - reference[:, :3, 3].mean(0)) ** 2).sum(1).mean()))
    centre_share = np.linalg.norm(centres - reference[:, :3, 3], axis=1) / spread
    residual = np.einsum("nji,njk->nik", rotation @ estimate[:, :3, :3], reference[:, :3, :3])
    cos = np.clip((np.trace(residual, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    rotation_deg = np.degrees(np.arccos(cos))
    return {"centre_error_share": centre_share, "rotation_error_deg": rotation_deg,
            "centre_error_share_max": float(centre_share.max()), "centre_error_share_median": float(np.median(centre_share)),
            "rotation_error_deg_max": float(rotation_deg.max()), "rotation_error_deg_median": float(np.median(rotation_deg))}
