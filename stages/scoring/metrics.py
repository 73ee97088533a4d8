"""Scores: image PSNR, SSIM and LPIPS, and a mesh's accuracy and completeness against a reference surface."""
from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from skimage.metrics import structural_similarity

from stages.scoring.lpips import MIN_SIDE as LPIPS_MIN_SIDE, image_lpips
from plenoxels.core.scene_model import psnr


def image_psnr(render: np.ndarray, truth: np.ndarray) -> float:
    """PSNR in dB between float RGB images in [0, 1]."""
    return psnr(float(np.mean((render.astype(np.float64) - truth.astype(np.float64)) ** 2)))


def image_ssim(render: np.ndarray, truth: np.ndarray) -> float:
    """SSIM of float RGB images in [0, 1]: Gaussian-weighted (sigma 1.5), as in Wang et al. 2004."""
    return float(structural_similarity(truth, render, channel_axis=-1, data_range=1.0, gaussian_weights=True,
                                       sigma=1.5, use_sample_covariance=False))


def image_scores(render: np.ndarray, truth: np.ndarray, with_lpips: bool) -> dict:
    """PSNR (dB), SSIM and, with_lpips, LPIPS (AlexNet, v0.1) of a render against its photo, float RGB in [0, 1]
    (no LPIPS for images under LPIPS_MIN_SIDE pixels a side)."""
    scores = {"psnr": round(image_psnr(render, truth), 4), "ssim": round(image_ssim(render, truth), 5)}
    if with_lpips and min(render.shape[:2]) >= LPIPS_MIN_SIDE:
        scores["lpips"] = round(image_lpips(render, truth), 5)
    return scores


def masked_scores(render: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> dict:
    """PSNR and SSIM inside a mask (float [h, w] in [0, 1]; a pixel counts where it is at least half the object), as
    the DTU protocol scores object captures: the squared error's mean, and the SSIM map's, over those pixels only.
    Empty where the mask marks no pixel."""
    inside = mask >= 0.5
    if not inside.any():
        return {}
    error = (render.astype(np.float64) - truth.astype(np.float64)) ** 2
    ssim_map = structural_similarity(truth, render, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                     use_sample_covariance=False, full=True)[1]
    return {"psnr_masked": round(psnr(float(error[inside].mean())), 4),
            "ssim_masked": round(float(ssim_map[inside].mean()), 5)}


def mean_scores(views: list[dict]) -> dict | None:
    """Each score's mean over the views that have it; None when no view has any."""
    keys = [k for k in ("psnr", "ssim", "lpips", "psnr_masked", "ssim_masked") if any(k in v for v in views)]
    if not keys:
        return None
    return {k: round(float(np.mean([v[k] for v in views if k in v])), 5) for k in keys}


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Float image in [0, 1] -> uint8, rounded."""
    return (np.clip(image, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)


def mesh_scores(mesh: trimesh.Trimesh, reference: trimesh.Trimesh, tolerance: float, samples: int = 200_000,
                reference_visible=None, seed: int = 0, far: float | None = None) -> dict:
    """Accuracy and completeness of `mesh` against `reference`, both sampled uniformly by area.

    accuracy: distances from the mesh's samples to the reference surface; completeness: from the
    reference's samples to the mesh surface, counting only reference samples for which
    `reference_visible(points) -> bool mask` holds (the surface some camera saw) when it is given.
    F-score at `tolerance`, Chamfer (mean of the two mean distances), the largest distance from
    any mesh vertex to the reference and, with `far`, the share of the mesh's area farther than that from it."""
    rng = np.random.default_rng(seed)
    mesh_points = _area_samples(mesh, samples, rng)[0]
    reference_points = _area_samples(reference, samples, rng)[0]
    if reference_visible is not None:
        reference_points = reference_points[reference_visible(reference_points)]
    to_reference = surface_distance(reference, mesh_points, rng)
    to_mesh = surface_distance(mesh, reference_points, rng)
    precision = float((to_reference < tolerance).mean())
    recall = float((to_mesh < tolerance).mean())
    return {
        "tolerance": tolerance,
        "precision": precision,
        "recall": recall,
        "f_score": 2 * precision * recall / max(precision + recall, 1e-12),
        "chamfer": float((to_reference.mean() + to_mesh.mean()) / 2),
        "accuracy_mean": float(to_reference.mean()),
        "completeness_mean": float(to_mesh.mean()),
        "max_vertex_distance": float(surface_distance(reference, np.asarray(mesh.vertices), rng).max()),
        "reference_samples_used": len(reference_points),
        **({"far": far, "far_share": float((to_reference > far).mean())} if far is not None else {}),
    }


def surface_distance(mesh: trimesh.Trimesh, points: np.ndarray, rng: np.random.Generator, candidates: int = 8) -> np.ndarray:
    """Distance [N] from each point to the surface of `mesh`: exact point-triangle distances to the
    faces of the nearest of a dense set of surface samples (no spatial index library needed)."""
    samples, faces = _area_samples(mesh, max(50_000, 4 * len(mesh.faces)), rng)
    samples = np.concatenate([samples, np.asarray(mesh.triangles_center)])
    faces = np.concatenate([faces, np.arange(len(mesh.faces))])
    _, nearest = cKDTree(samples).query(points, k=candidates)
    candidate_faces = faces[nearest]                                  # [N, k]
    triangles = np.asarray(mesh.triangles)[candidate_faces.reshape(-1)]
    closest = trimesh.triangles.closest_point(triangles, np.repeat(points, candidates, axis=0))
    distance = np.linalg.norm(closest - np.repeat(points, candidates, axis=0), axis=1)
    return distance.reshape(len(points), candidates).min(axis=1)


def _area_samples(mesh: trimesh.Trimesh, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points [count, 3] uniform by area on the mesh, and the face [count] each lies on."""
    triangles = np.asarray(mesh.triangles)
    area = np.asarray(mesh.area_faces)
    face = rng.choice(len(triangles), size=count, p=area / area.sum())
    u, v = rng.uniform(size=(2, count))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = triangles[face]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0]), face
