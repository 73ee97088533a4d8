"""Distillation: the splats refined against the field's own renders of the training views, for a bounded time.

Each step renders a random window of one view (the rasterizer is tile-free, so a window costs what its pixels cost,
plus projecting every splat) and takes an Adam step on the squared error to the field's render there. The field,
not the photos, is the target: the splats are an export of the fit, and its renders exist at every pixel of every
training view, background included. Learning rates are per attribute, the means' in units of the splats' own size.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from plenoxels.core.cameras import Intrinsics
from plenoxels.splats.model import Splats
from plenoxels.splats.rasterize import in_window, project, render_window

LR = {"means": 0.05, "log_scales": 0.01, "quats": 0.005, "opacity_logits": 0.05, "sh_dc": 0.01, "sh_rest": 0.0025}


@dataclass
class TargetView:
    c2w: np.ndarray  # OpenGL camera-to-world, normalised world
    k: Intrinsics
    rgb: torch.Tensor  # [h, w, 3] the field's render


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(torch.mean((a.float() - b.float()) ** 2))
    return float("inf") if mse == 0 else -10.0 * float(np.log10(mse))


def _parameters(splats: Splats) -> tuple[dict[str, torch.Tensor], torch.optim.Adam]:
    params = {name: t.detach().clone().requires_grad_(True) for name, t in splats.tensors().items()}
    size = float(torch.exp(splats.log_scales).mean()) if splats.count else 1.0
    groups = [{"params": [params["means"]], "lr": LR["means"] * size},
              {"params": [params["log_scales"]], "lr": LR["log_scales"]},
              {"params": [params["quats"]], "lr": LR["quats"]},
              {"params": [params["opacity_logits"]], "lr": LR["opacity_logits"]}]
    return params, groups


def distill(splats: Splats, views: list[TargetView], background, seconds: float, window: int = 96, seed: int = 0,
            max_steps: int | None = None) -> tuple[Splats, dict]:
    """The splats after up to `seconds` (or max_steps) of steps on windows up to window x window pixels; and a record
    (steps, seconds, the windows' PSNR over the first and the last tenth of the steps)."""
    if not views or splats.count == 0 or (seconds <= 0 and not max_steps):
        return splats, {"steps": 0, "seconds": 0.0}
    params, groups = _parameters(splats)
    dc = params["sh"][:, :, :1].detach().clone().requires_grad_(True)
    rest = params["sh"][:, :, 1:].detach().clone().requires_grad_(True)
    groups += [{"params": [dc], "lr": LR["sh_dc"]}, {"params": [rest], "lr": LR["sh_rest"]}]
    optimiser = torch.optim.Adam(groups, eps=1e-15)
    rng = np.random.default_rng(seed)
    background = torch.as_tensor(background, dtype=torch.float32)
    started, scores = time.time(), []
    while (max_steps is None or len(scores) < max_steps) and (max_steps is not None or time.time() - started < seconds):
        view = views[rng.integers(len(views))]
        w, h = min(window, view.k.w), min(window, view.k.h)
        x0, y0 = int(rng.integers(view.k.w - w + 1)), int(rng.integers(view.k.h - h + 1))
        near = in_window(Splats(params["means"], params["log_scales"], params["quats"], params["opacity_logits"], dc),
                         view.c2w, view.k, (x0, y0, w, h))
        current = Splats(params["means"][near], params["log_scales"][near], params["quats"][near],
                         params["opacity_logits"][near], torch.cat([dc[near], rest[near]], dim=2))
        rgb, _ = render_window(project(current, view.c2w, view.k), (x0, y0, w, h), background)
        target = view.rgb[y0:y0 + h, x0:x0 + w]
        loss = torch.mean((rgb - target) ** 2)
        optimiser.zero_grad(set_to_none=False)
        loss.backward()
        optimiser.step()
        scores.append(-10.0 * float(np.log10(max(float(loss.detach()), 1e-12))))
    tenth = max(1, len(scores) // 10)
    out = Splats(params["means"].detach(), params["log_scales"].detach(), params["quats"].detach(),
                 params["opacity_logits"].detach(), torch.cat([dc, rest], dim=2).detach())
    return out, {"steps": len(scores), "seconds": round(time.time() - started, 2),
                 "window": window, "window_psnr_first": round(float(np.mean(scores[:tenth])), 3),
                 "window_psnr_last": round(float(np.mean(scores[-tenth:])), 3)}
