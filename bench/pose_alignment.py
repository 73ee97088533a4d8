"""A held-out view scored again after its camera is aligned to the fitted field: what of the held-out error is the
pose the view was given, what is its colour, and what is left for the field itself.

Real captures' poses come from SfM (or from the capture's own files) and are sub-pixel right on the features they
matched, not on every pixel; a field fitted to the training poses may sit a fraction of a pixel off a held-out pose.
Evaluations of pose-refining methods (BARF, NeRF--, nerfstudio's camera optimiser) align each test camera to the
fitted scene before scoring for that reason. Here a held-out camera gets a small rigid motion in its own frame (a
rotation and a translation, 6 numbers) by Levenberg-Marquardt on `RAYS` random pixels, each colour channel's gain
fitted by least squares on the way, the Jacobian by central differences of native renders (the fit's kernels carry no
gradient to the rays); the whole view is then scored at the aligned pose, and again with those gains fitted to the
whole photo (an oracle of its exposure and white balance).

    .venv/bin/python -m bench.real_scenes --scenes fox ball --presets fast --views all --aligned
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from plenoxels.core.cameras import Intrinsics, rays_from_camera
from stages.scoring.metrics import image_scores

RAYS = 8192
ITERATIONS = 12
# Central-difference steps: radians, and scene units times the camera's distance to the origin (about a tenth of a
# pixel at the scored size either way).
ROTATION_STEP = 3e-4
TRANSLATION_STEP = 1e-4


def moved(c2w: np.ndarray, motion: np.ndarray, distance: float) -> np.ndarray:
    """The camera moved by `motion` (axis-angle radians, then translation in units of `distance`) in its own frame."""
    local = np.eye(4)
    local[:3, :3] = Rotation.from_rotvec(motion[:3]).as_matrix()
    local[:3, 3] = motion[3:] * distance
    return c2w @ local


def rendered(model, c2w: np.ndarray, k: Intrinsics, pixels: torch.Tensor, frame: dict) -> torch.Tensor:
    """The view's colours [N, 3] at flat pixel indices `pixels` (at most RAYS: one render call), as `frame`'s photo
    was taken: past the grid its own backdrop where it has one and the model no background (as render_camera)."""
    origins, dirs = rays_from_camera(c2w, k)
    with torch.no_grad():
        result = model.render_rays(origins.reshape(-1, 3)[pixels], dirs.reshape(-1, 3)[pixels])
    backdrop = frame.get("backdrop")
    colour = model.on_backdrop(result.rgb, result.opacity, backdrop).clamp(0, 1)
    return model.as_photographed(colour, frame["name"], result.opacity, backdrop).double()


def align(model, c2w: np.ndarray, k: Intrinsics, truth: np.ndarray, frame: dict, seed: int = 0) -> dict:
    """The camera aligned to the field on `RAYS` pixels: its pose, how far it moved, and the subset's PSNR (its gains
    fitted) before and after."""
    pixels = torch.from_numpy(np.random.default_rng(seed).choice(k.w * k.h, min(RAYS, k.w * k.h), replace=False))
    target = torch.from_numpy(truth.reshape(-1, 3)[pixels.numpy()]).double()
    distance = max(float(np.linalg.norm(c2w[:3, 3])), 1e-3)
    steps = np.array([ROTATION_STEP] * 3 + [TRANSLATION_STEP] * 3)

    def residual(motion):
        # Each channel's gain fitted on the way: a photo's exposure is not a reason to move its camera.
        colours = rendered(model, moved(c2w, motion, distance), k, pixels, frame)
        gains = torch.from_numpy(channel_gains(colours.numpy(), target.numpy()))
        return (colours * gains - target).reshape(-1)

    motion = np.zeros(6)
    current = residual(motion)
    start_loss = loss = float(current.square().mean())
    damping = 1e-3
    for _ in range(ITERATIONS):
        columns = [(residual(motion + e) - residual(motion - e)) / (2 * h) for e, h in zip(np.diag(steps), steps)]
        jacobian = torch.stack(columns, dim=1)
        normal, gradient = jacobian.T @ jacobian, jacobian.T @ current
        improved = False
        for _ in range(4):
            system = normal + damping * torch.diag(torch.diagonal(normal))
            step = -torch.linalg.solve(system, gradient).numpy()
            trial = residual(motion + step)
            trial_loss = float(trial.square().mean())
            if trial_loss < loss:
                motion, current, loss, improved = motion + step, trial, trial_loss, True
                damping = max(damping / 3, 1e-6)
                break
            damping *= 4
        if not improved or np.max(np.abs(step) / steps) < 0.05:
            break
    pixel_angle = 1.0 / k.fl_x
    return {"c2w": moved(c2w, motion, distance),
            "rotation_px": round(float(np.linalg.norm(motion[:3])) / pixel_angle, 3),
            "translation": round(float(np.linalg.norm(motion[3:])), 6),
            "subset_psnr": [round(-10 * np.log10(max(value, 1e-12)), 3) for value in (start_loss, loss)]}


def channel_gains(render: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Each channel's least-squares gain taking the render to the photo."""
    r, t = render.reshape(-1, 3).astype(np.float64), truth.reshape(-1, 3).astype(np.float64)
    return (r * t).sum(0) / np.maximum((r * r).sum(0), 1e-12)


def aligned_scores(model, frame: dict, k: Intrinsics, truth: np.ndarray, render: np.ndarray) -> dict:
    """The view (`render` at its own pose) scored with each channel's gain fitted to the photo, at its aligned pose,
    and at that pose with the gains fitted."""
    c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
    as_posed = np.clip(render * channel_gains(render, truth), 0, 1).astype(np.float32)
    fit = align(model, c2w, k, truth, frame)
    with torch.no_grad():
        render = model.render_camera(fit["c2w"], k, backdrop=frame.get("backdrop"), photo=frame["name"])["rgb"].numpy()
    regained = np.clip(render * channel_gains(render, truth), 0, 1).astype(np.float32)
    return {"regained": image_scores(as_posed, truth, with_lpips=False),
            "aligned": {**image_scores(render, truth, with_lpips=False),
                        **{key: fit[key] for key in ("rotation_px", "translation", "subset_psnr")}},
            "aligned_regained": image_scores(regained, truth, with_lpips=False)}
