"""Distillation: the splats refined against the field's own renders of the training views, for a bounded time.

Each step renders a random window of one view (the rasterizer is tile-free, so a window costs what its pixels cost)
and takes an Adam step on the squared error to the field's render there. The field, not the photos, is the target:
the splats are an export of the fit, and its renders exist at every pixel of every training view, background included.

Only the splats that may touch the window take part in a step: their rows are gathered, rendered, and updated by a
row-wise Adam (each row keeps its own step count for the bias correction, as if it were optimised alone), so a step
costs what the window's splats cost, not what all of them do; torch runs on one thread meanwhile (rasterize.one_thread).
Together they took lego's steps from 0.17 to about 7 a second (bench/README.md, "Splats"). Learning rates are per
attribute, each mean's in units of its splat's own size.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from plenoxels.core.cameras import Intrinsics
from plenoxels.splats.model import Splats
from plenoxels.splats.rasterize import in_window, one_thread, project, render_window

LR = {"means": 0.05, "log_scales": 0.01, "quats": 0.005, "opacity_logits": 0.05, "sh_dc": 0.01, "sh_rest": 0.0025}
BETAS = (0.9, 0.999)
EPS = 1e-15


@dataclass
class TargetView:
    c2w: np.ndarray  # OpenGL camera-to-world, normalised world
    k: Intrinsics
    rgb: torch.Tensor  # [h, w, 3] the field's render


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(torch.mean((a.float() - b.float()) ** 2))
    return float("inf") if mse == 0 else -10.0 * float(np.log10(mse))


class RowAdam:
    """Adam over the rows of named tensors where each step touches only some rows; a rate is a number or a tensor of
    per-row rates."""

    def __init__(self, tensors: dict[str, torch.Tensor], rates: dict[str, float | torch.Tensor]):
        self.tensors, self.rates = tensors, rates
        self.first = {name: torch.zeros_like(t) for name, t in tensors.items()}
        self.second = {name: torch.zeros_like(t) for name, t in tensors.items()}
        self.steps = torch.zeros(next(iter(tensors.values())).shape[0])

    def step(self, rows: torch.Tensor, grads: dict[str, torch.Tensor]) -> None:
        self.steps[rows] += 1
        t = self.steps[rows]
        for name, grad in grads.items():
            shape = (-1,) + (1,) * (grad.dim() - 1)
            m = self.first[name][rows].mul_(BETAS[0]).add_(grad, alpha=1 - BETAS[0])
            v = self.second[name][rows].mul_(BETAS[1]).addcmul_(grad, grad, value=1 - BETAS[1])
            self.first[name][rows], self.second[name][rows] = m, v
            m_hat = m / (1 - BETAS[0] ** t).reshape(shape)
            v_hat = v / (1 - BETAS[1] ** t).reshape(shape)
            rate = self.rates[name]
            rate = rate[rows] if isinstance(rate, torch.Tensor) else rate
            self.tensors[name][rows] -= rate * m_hat / (v_hat.sqrt() + EPS)


def distill(splats: Splats, views: list[TargetView], background, seconds: float, window: int = 96, seed: int = 0,
            max_steps: int | None = None) -> tuple[Splats, dict]:
    """The splats after up to `seconds` (or max_steps) of steps on windows up to window x window pixels; and a record
    (steps, seconds, steps per second, the windows' PSNR over the first and the last tenth of the steps)."""
    if not views or splats.count == 0 or (seconds <= 0 and not max_steps):
        return splats, {"steps": 0, "seconds": 0.0}
    # Each splat's mean moves in units of its own size: a background sphere's splats are thousands of times a voxel's.
    size = torch.exp(splats.log_scales.detach().float()).mean(dim=1)
    tensors = {"means": splats.means, "log_scales": splats.log_scales, "quats": splats.quats,
               "opacity_logits": splats.opacity_logits, "sh_dc": splats.sh[:, :, :1], "sh_rest": splats.sh[:, :, 1:]}
    tensors = {name: t.detach().float().clone().contiguous() for name, t in tensors.items()}
    rates = dict(LR, means=LR["means"] * size[:, None])
    optimiser = RowAdam(tensors, rates)
    rng = np.random.default_rng(seed)
    background = torch.as_tensor(background, dtype=torch.float32)
    started, scores = time.time(), []
    with one_thread():
        _steps(tensors, optimiser, views, background, window, rng, seconds, max_steps, started, scores)
    elapsed = time.time() - started
    tenth = max(1, len(scores) // 10)
    out = Splats(tensors["means"], tensors["log_scales"], tensors["quats"], tensors["opacity_logits"],
                 torch.cat([tensors["sh_dc"], tensors["sh_rest"]], dim=2))
    return out, {"steps": len(scores), "seconds": round(elapsed, 2),
                 "steps_per_second": round(len(scores) / elapsed, 3), "window": window, "window_psnr_first": round(float(np.mean(scores[:tenth])), 3),
                 "window_psnr_last": round(float(np.mean(scores[-tenth:])), 3)}


def _steps(tensors: dict[str, torch.Tensor], optimiser: RowAdam, views: list[TargetView], background: torch.Tensor,
           window: int, rng: np.random.Generator, seconds: float, max_steps: int | None, started: float,
           scores: list[float]) -> None:
    while (max_steps is None or len(scores) < max_steps) and (max_steps is not None or time.time() - started < seconds):
        view = views[rng.integers(len(views))]
        w, h = min(window, view.k.w), min(window, view.k.h)
        x0, y0 = int(rng.integers(view.k.w - w + 1)), int(rng.integers(view.k.h - h + 1))
        shapes = Splats(tensors["means"], tensors["log_scales"], tensors["quats"], tensors["opacity_logits"],
                        tensors["sh_dc"])
        near = in_window(shapes, view.c2w, view.k, (x0, y0, w, h))
        leaves = {name: t[near].requires_grad_(True) for name, t in tensors.items()}
        current = Splats(leaves["means"], leaves["log_scales"], leaves["quats"], leaves["opacity_logits"],
                         torch.cat([leaves["sh_dc"], leaves["sh_rest"]], dim=2))
        rgb, _ = render_window(project(current, view.c2w, view.k), (x0, y0, w, h), background)
        loss = torch.mean((rgb - view.rgb[y0:y0 + h, x0:x0 + w]) ** 2)
        if len(near):
            loss.backward()
            with torch.no_grad():
                optimiser.step(near, {name: leaf.grad for name, leaf in leaves.items()})
        scores.append(-10.0 * float(np.log10(max(float(loss.detach()), 1e-12))))
