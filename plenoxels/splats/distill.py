"""Distillation: the splats refined against the field's own renders of the training views, for a bounded time.

Each step renders a window of one view and takes an Adam step on the squared error to the field's render there. The
field, not the photos, is the target: the splats are an export of the fit, and its renders exist at every pixel of
every training view, background included.

Where effort goes: half the windows are drawn where the splats were last measured furthest from the field
(WindowErrors; before a tile is measured, where its target has detail), half uniformly. A view once drawn serves
WINDOWS_PER_VISIT windows from one look at where every splat lands in it.

What a step costs: only the splats that may touch the window take part, their rows gathered from one packed table
(SplatRows), rendered by the native core's compositing (csrc/cpu_splats.cpp) and updated by its row-wise Adam
(csrc/cpu_optim.cpp; each row keeps its own step count for the bias correction, as if it were optimised alone); torch
runs on one thread meanwhile (rasterize.one_thread). Measured steps per second and what they buy: bench/README.md,
"Splats". Learning rates are per attribute, each mean's in units of its splat's own size.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from plenoxels.core.cameras import Intrinsics
from plenoxels.core.native import ops
from plenoxels.splats.model import Splats
from plenoxels.splats.rasterize import footprints, one_thread, project, render_window

LR = {"means": 0.05, "log_scales": 0.01, "quats": 0.005, "opacity_logits": 0.05, "sh_dc": 0.01, "sh_rest": 0.0025}
BETAS = (0.9, 0.999)
EPS = 1e-15
ERROR_SHARE = 0.5
ERROR_POWER = 1.0
WINDOWS_PER_VISIT = 8


@dataclass
class TargetView:
    c2w: np.ndarray  # OpenGL camera-to-world, normalised world
    k: Intrinsics
    rgb: torch.Tensor  # [h, w, 3] the field's render


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(torch.mean((a.float() - b.float()) ** 2))
    return float("inf") if mse == 0 else -10.0 * float(np.log10(mse))


class SplatRows:
    """The splats packed one row each ([N, D] float32: mean, log scales, quaternion, opacity logit, SH degree-0 term,
    the other SH terms), so that a step gathers, differentiates and updates one tensor, not six."""

    def __init__(self, splats: Splats):
        k = splats.sh.shape[2]
        parts = {"means": splats.means, "log_scales": splats.log_scales, "quats": splats.quats,
                 "opacity_logits": splats.opacity_logits[:, None], "sh_dc": splats.sh[:, :, 0],
                 "sh_rest": splats.sh[:, :, 1:].reshape(-1, 3 * (k - 1))}
        self.columns, at = {}, 0
        for name, part in parts.items():
            self.columns[name] = slice(at, at + part.shape[1])
            at += part.shape[1]
        self.k = k
        self.data = torch.cat([p.detach().float() for p in parts.values()], dim=1).contiguous()

    def splats(self) -> Splats:
        """All the splats, each attribute a tensor of its own."""
        return self.splats_of([part.contiguous() for part in self.data.split(self.widths, dim=1)])

    @property
    def widths(self) -> list[int]:
        return [c.stop - c.start for c in self.columns.values()]

    def splats_of(self, parts: list[torch.Tensor]) -> Splats:
        """The splats of per-attribute tensors, as split from rows of the table by `widths`."""
        means, log_scales, quats, opacity, dc, rest = parts
        return Splats(means, log_scales, quats, opacity[:, 0],
                      torch.cat([dc[:, :, None], rest.reshape(-1, 3, self.k - 1)], dim=2))

    def shapes(self) -> Splats:
        """All the splats with their SH degree-0 term alone: where they are and how large, without copying colours."""
        c = self.columns
        return Splats(self.data[:, c["means"]], self.data[:, c["log_scales"]], self.data[:, c["quats"]],
                      self.data[:, c["opacity_logits"]][:, 0], self.data[:, c["sh_dc"]][:, :, None])

    def rates(self, rates: dict[str, float]) -> torch.Tensor:
        out = torch.zeros(self.data.shape[1])
        for name, columns in self.columns.items():
            out[columns] = rates[name]
        return out


class RowAdam:
    """Adam over the rows of a tensor where each step touches only some rows: per column a rate, times a per-row factor
    on the columns `scaled`; each row keeps its own step count for the bias correction, as if it were optimised
    alone."""

    def __init__(self, data: torch.Tensor, rates: torch.Tensor, row_factor: torch.Tensor, scaled: slice):
        self.data, self.scaled = data, scaled
        self.first, self.second = torch.zeros_like(data), torch.zeros_like(data)
        self.steps = torch.zeros(data.shape[0])
        self.rates, self.row_factor = rates.float().contiguous(), row_factor.float().contiguous()

    def step(self, rows: torch.Tensor, grad: torch.Tensor, native: bool = True) -> None:
        """One step on distinct rows: by the native core (csrc/cpu_optim.cpp), or in torch with native=False, its
        reference."""
        if native:
            ops.adam_rows(self.data, self.first, self.second, self.steps, rows, grad.float().contiguous(), self.rates,
                          self.row_factor, self.scaled.start, self.scaled.stop, BETAS[0], BETAS[1], EPS)
            return
        self.steps[rows] += 1
        t = self.steps[rows][:, None]
        m = self.first[rows].mul_(BETAS[0]).add_(grad, alpha=1 - BETAS[0])
        v = self.second[rows].mul_(BETAS[1]).addcmul_(grad, grad, value=1 - BETAS[1])
        self.first[rows], self.second[rows] = m, v
        rate = self.rates.expand(len(rows), -1).clone()
        rate[:, self.scaled] *= self.row_factor[rows][:, None]
        update = rate * (m / (1 - BETAS[0] ** t)) / ((v / (1 - BETAS[1] ** t)).sqrt() + EPS)
        self.data.index_put_((rows,), self.data[rows] - update)


class WindowErrors:
    """Where the splats still differ from the field: per view, a lattice of window-sized tiles, each holding the mean
    squared error its last window measured. A tile not yet measured is estimated from its target's variance (detail is
    where splats start furthest from the field), scaled by the ratio of error to variance over the tiles measured so
    far. A share of the draws (of a view, then of a tile in it) goes in proportion to error ** power, the rest
    uniformly, which also keeps the measures fresh."""

    def __init__(self, views: list[TargetView], window: int, share: float, power: float):
        self.window, self.share, self.power = window, share, power
        self.shapes, variance = [], []
        for view in views:
            h, w = view.rgb.shape[:2]
            ty, tx = -(-h // window), -(-w // window)
            padded = torch.nn.functional.pad(view.rgb.permute(2, 0, 1)[None].float(),
                                             (0, tx * window - w, 0, ty * window - h), mode="replicate")
            mean = torch.nn.functional.avg_pool2d(padded, window)
            square = torch.nn.functional.avg_pool2d(padded * padded, window)
            variance.append((square - mean * mean).clamp_min(0).sum(dim=1).reshape(-1))
            self.shapes.append((ty, tx))
        self.first = np.cumsum([0] + [ty * tx for ty, tx in self.shapes])
        self.variance = torch.cat(variance).double().numpy() + 1e-6
        self.error = np.full_like(self.variance, np.nan)

    def _weights(self, tiles: slice = slice(None)) -> np.ndarray:
        seen = ~np.isnan(self.error)
        ratio = self.error[seen].sum() / self.variance[seen].sum() if seen.any() else 1.0
        estimate = np.where(seen, self.error, self.variance * ratio)[tiles]
        return np.clip(estimate, 0, None) ** self.power + 1e-20  # all measured perfect: uniform

    def draw_view(self, rng: np.random.Generator) -> int:
        if rng.random() >= self.share:
            return int(rng.integers(len(self.shapes)))
        per_view = np.add.reduceat(self._weights(), self.first[:-1])
        return int(rng.choice(len(per_view), p=per_view / per_view.sum()))

    def draw_tile(self, view: int, rng: np.random.Generator) -> tuple[int, int]:
        """A tile of the view: (row, column)."""
        count = int(self.first[view + 1] - self.first[view])
        if rng.random() >= self.share:
            tile = int(rng.integers(count))
        else:
            p = self._weights(slice(int(self.first[view]), int(self.first[view + 1])))
            tile = int(rng.choice(count, p=p / p.sum()))
        return divmod(tile, self.shapes[view][1])

    def measured(self, view: int, row: int, col: int, mse: float) -> None:
        self.error[int(self.first[view]) + row * self.shapes[view][1] + col] = mse


def distill(splats: Splats, views: list[TargetView], background, seconds: float, window: int = 96, seed: int = 0,
            max_steps: int | None = None, error_share: float = ERROR_SHARE, error_power: float = ERROR_POWER,
            windows_per_visit: int = WINDOWS_PER_VISIT) -> tuple[Splats, dict]:
    """The splats after up to `seconds` (or max_steps) of steps on windows up to window x window pixels; and a record
    (steps, seconds, steps per second, the windows' PSNR over the first and the last tenth of the steps)."""
    if not views or splats.count == 0 or (seconds <= 0 and not max_steps):
        return splats, {"steps": 0, "seconds": 0.0}
    rows = SplatRows(splats)
    # Each splat's mean moves in units of its own size: a background sphere's splats are thousands of times a voxel's.
    size = torch.exp(splats.log_scales.detach().float()).mean(dim=1)
    optimiser = RowAdam(rows.data, rows.rates(LR), size, rows.columns["means"])
    rng = np.random.default_rng(seed)
    background = torch.as_tensor(background, dtype=torch.float32)
    started, scores = time.monotonic(), []
    with one_thread():
        errors = WindowErrors(views, window, error_share, error_power)
        _steps(rows, optimiser, views, background, errors, windows_per_visit, rng, seconds, max_steps, started, scores)
    elapsed = time.monotonic() - started
    tenth = max(1, len(scores) // 10)
    return rows.splats(), {"steps": len(scores), "seconds": round(elapsed, 2),
                           "steps_per_second": round(len(scores) / elapsed, 3), "window": window,
                           "window_psnr_first": round(float(np.mean(scores[:tenth])), 3),
                           "window_psnr_last": round(float(np.mean(scores[-tenth:])), 3)}


def _steps(rows: SplatRows, optimiser: RowAdam, views: list[TargetView], background: torch.Tensor,
           errors: WindowErrors, windows_per_visit: int, rng: np.random.Generator, seconds: float,
           max_steps: int | None, started: float, scores: list[float]) -> None:
    def more() -> bool:
        return len(scores) < max_steps if max_steps is not None else time.monotonic() - started < seconds

    while more():
        index = errors.draw_view(rng)
        view = views[index]
        # One look at where every splat lands serves the visit's windows: a step moves a splat by a small part of
        # its size, and each footprint has a pixel to spare.
        seen = footprints(rows.shapes(), view.c2w, view.k)
        for _ in range(windows_per_visit):
            if not more():
                break
            row, col = errors.draw_tile(index, rng)
            w, h = min(errors.window, view.k.w), min(errors.window, view.k.h)
            # The window is centred within half a window of its tile's centre, so the tiles' seams do not stay put.
            cx = (col + 0.5 + rng.uniform(-0.5, 0.5)) * errors.window
            cy = (row + 0.5 + rng.uniform(-0.5, 0.5)) * errors.window
            x0 = int(np.clip(round(cx - w / 2), 0, view.k.w - w))
            y0 = int(np.clip(round(cy - h / 2), 0, view.k.h - h))
            near = seen.in_window((x0, y0, w, h))
            # One leaf per attribute: slices of a single leaf would each send back a zero-filled table of all columns.
            leaves = [part.contiguous().requires_grad_(True) for part in rows.data[near].split(rows.widths, dim=1)]
            rgb, _ = render_window(project(rows.splats_of(leaves),
                                           view.c2w, view.k), (x0, y0, w, h), background)
            loss = torch.mean((rgb - view.rgb[y0:y0 + h, x0:x0 + w]) ** 2)
            if len(near):
                loss.backward()
                with torch.no_grad():
                    optimiser.step(near, torch.cat([leaf.grad for leaf in leaves], dim=1))
            errors.measured(index, row, col, float(loss.detach()))
            scores.append(-10.0 * float(np.log10(max(float(loss.detach()), 1e-12))))
