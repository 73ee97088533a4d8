"""Volume rendering of a SparseGrid: forward, fused loss+gradient, and max weights for pruning.

Every function runs the native core (plenoxels/core/native.py) on the device of the grid's tensors; the
math is stated in reference.py, the PyTorch twin the tests hold the kernels to.

Rays arrive in the fit frame. Directions need not be unit length: t, `near` and depth are fit-frame
distances along the normalised direction. Density is integrated per fit-frame unit of distance while
samples are spaced `step_size` voxels apart in grid coordinates, so anisotropic boxes work.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from plenoxels.core import native
from plenoxels.core.errors import require
from plenoxels.core.grid import OCCUPANCY_BLOCK, SparseGrid
from plenoxels.core.optim import GridGrad
from plenoxels.core.options import MarchOptions

# Real spherical-harmonic basis constants up to degree 3 and the offset added before the colour's relu,
# as csrc/plenoxels_math.h has them (tests compare the two through the kernels' output).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)
COLOUR_OFFSET = 0.5


@dataclass
class RenderOptions(MarchOptions):
    """How a render marches its rays: the fit's step size and stopping threshold (MarchOptions, which checks them),
    and what only a render sets."""

    near: float = 0.0
    """Rays start this far along (fit-frame units); they are also clipped to the grid's box."""
    sigma_threshold: float = 0.0
    """Samples with density at or below this are skipped."""
    max_samples_per_ray: int = 4096
    """A finer step is widened so that no ray takes more samples."""

    def check(self, section: str = "fit") -> "RenderOptions":
        """Raises a one-line UserError for a bad value; returns the options, checked."""
        MarchOptions.check(self, section)
        require(self.sigma_threshold >= 0, f"sigma_threshold must be >= 0, got {self.sigma_threshold}")
        require(self.max_samples_per_ray >= 1, f"max_samples_per_ray must be >= 1, got {self.max_samples_per_ray}")
        require(self.near == self.near, "near must be a number")
        return self


@dataclass
class RenderResult:
    rgb: torch.Tensor  # [B, 3]
    depth: torch.Tensor  # [B] expected termination distance (fit-frame units), weights not renormalised
    opacity: torch.Tensor  # [B] 1 - final transmittance


def light_past_grid(transmittance: torch.Tensor, stop_transmittance: float) -> torch.Tensor:
    """What of the colour behind the grid shows on rays that left the grid with `transmittance` (1 - opacity): all of
    it from twice stop_transmittance up, none below it (the march stopped the ray), a ramp between so that colours do
    not jump; stop 0: all of it on every ray (plx::light_past_grid). Differentiable (the twin's loss takes its
    gradient). The kernels cut a background this way only where it is the spheres (`past_grid_only`), whose drawing
    costs a ray more than the grid: a flat colour costs nothing, and cut it cost an object's fit under a strong sparsity
    prior 0.5 dB held-out (bench/README.md, "Real captures", the background's row)."""
    s = float(stop_transmittance)
    if s <= 0:
        return transmittance
    ramp = transmittance * ((transmittance - s) / s).clamp(0.0, 1.0)
    return torch.where(transmittance >= s, ramp, torch.zeros_like(transmittance))


def ray_samples(grid: SparseGrid, origins: torch.Tensor, dirs: torch.Tensor, opts: RenderOptions) -> dict:
    """The sample lattice every kernel marches (steps 1-3 of reference.py's docstring), in float64 so
    that it matches theirs exactly. A ray is clipped to the grid box and to t >= near, then cut at every knot plane it
    crosses (csrc/plenoxels_math.h, lay_piece) into P pieces, on each of which the map to grid coordinates is linear:
    per ray and piece [B, P] t_start, dt and n (sample i of a piece at t_start + (i + 0.5) dt, fit-frame distance), the
    grid-space origin og and direction dg [B, P, 3] (per unit t); per ray the unit fit-frame direction `unit` (float32).
    A grid without knots has one piece. A contracted grid has no lattice: its rays bend and are marched step by step
    (reference.contracted_samples states how)."""
    if grid.contracted:
        raise ValueError("a contracted grid's samples lie on no lattice: take its foreground model's grid")
    o, d = origins.double(), dirs.double()
    unit = d / _norm(d)[:, None]
    knots = [grid.axis_knots(a) for a in range(3)]
    lo = torch.tensor([xs[0] for xs, _ in knots], dtype=torch.float64, device=o.device)
    extent = torch.tensor([xs[-1] for xs, _ in knots], dtype=torch.float64, device=o.device) - lo
    t_enter, t_exit = _box_interval(o - lo, unit, extent)
    hit = t_exit > t_enter
    t_start = torch.clamp_min(t_enter, opts.near)
    crossings = [torch.full_like(t_start, float("inf"))]
    for a, (xs, _) in enumerate(knots):
        for x in xs[1:-1]:
            t = (x - o[:, a]) / unit[:, a]
            inside = (unit[:, a] != 0) & (t > t_start) & (t < t_exit)
            crossings.append(torch.where(inside, t, torch.full_like(t, float("inf"))))
    t_end = torch.maximum(t_exit, t_start)
    cuts = torch.minimum(torch.sort(torch.stack(crossings, dim=1), dim=1).values[:, :-1], t_end[:, None])
    bounds = torch.cat([t_start[:, None], cuts, t_end[:, None]], dim=1)  # [B, P + 1]
    t0, t1 = bounds[:, :-1], bounds[:, 1:]
    mid = o[:, None, :] + (0.5 * (t0 + t1))[..., None] * unit[:, None, :]
    og, dg = torch.empty_like(mid), torch.empty_like(mid)
    for a, (xs, gs) in enumerate(knots):
        piece = torch.zeros(mid.shape[:2], dtype=torch.long, device=o.device)
        for x in xs[1:-1]:
            piece += (mid[..., a] >= x).long()
        x0 = torch.tensor(xs[:-1], dtype=torch.float64, device=o.device)[piece]
        g0 = torch.tensor(gs[:-1], dtype=torch.float64, device=o.device)[piece]
        slope = torch.tensor(grid.axis_slopes(a), dtype=torch.float64, device=o.device)[piece]
        og[..., a] = g0 + (o[:, None, a] - x0) * slope
        dg[..., a] = unit[:, None, a] * slope
    length = t1 - t0
    norm = _norm(dg)
    step_t = torch.full_like(norm, opts.step_size) / norm  # a scalar over a tensor multiplies by its reciprocal
    wanted = torch.ceil(length / step_t - 0.5).clamp_min(0)
    wanted = torch.where(hit[:, None] & (length > 0), wanted, torch.zeros_like(wanted))
    n, dt = torch.zeros_like(wanted), torch.empty_like(wanted)
    budget = torch.full_like(t_start, float(opts.max_samples_per_ray))
    for p in range(wanted.shape[1]):  # sample_lattice with the samples the ray has left
        capped = wanted[:, p] > budget
        dt[:, p] = torch.where(capped, length[:, p] / budget, step_t[:, p])
        n[:, p] = torch.where(capped, budget, wanted[:, p])
        budget = budget - n[:, p]
    return {"t_start": t0, "dt": dt, "n": n.long(), "og": og, "dg": dg, "unit": unit.to(torch.float32)}


def _norm(v: torch.Tensor) -> torch.Tensor:
    """|v| over the last axis in the kernels' order of operations, so that a sample count on a tie (an axis-parallel
    ray through knots at round numbers) rounds as theirs does."""
    return torch.sqrt(v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1] + v[..., 2] * v[..., 2])


def _box_interval(from_min: torch.Tensor, unit: torch.Tensor, extent: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """csrc/plenoxels_math.h's ray_box per ray: where rays from `from_min` (relative to the box's low corner) along
    `unit` enter and leave the box [0, extent]."""
    zero = unit == 0
    safe = torch.where(zero, torch.ones_like(unit), unit)
    ta, tb = (0 - from_min) / safe, (extent - from_min) / safe
    inside = (from_min >= 0) & (from_min <= extent)
    big = torch.full_like(ta, 1e300)
    t_lo = torch.where(zero, torch.where(inside, -big, big), torch.minimum(ta, tb))
    t_hi = torch.where(zero, torch.where(inside, big, -big), torch.maximum(ta, tb))
    return t_lo.max(dim=1).values, t_hi.min(dim=1).values


def _rays(origins: torch.Tensor, dirs: torch.Tensor, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    origins = origins.detach().to(device=device, dtype=torch.float32).reshape(-1, 3).contiguous()
    dirs = dirs.detach().to(device=device, dtype=torch.float32).reshape(-1, 3).contiguous()
    if origins.shape != dirs.shape:
        raise ValueError(f"origins {tuple(origins.shape)} and dirs {tuple(dirs.shape)} must both be [B, 3]")
    if dirs.shape[0] and not bool((dirs.abs().amax(dim=1) > 0).all()):
        raise ValueError("ray directions must be non-zero")
    return origins, dirs


def _colours(x: torch.Tensor | None, b: int, name: str, device: torch.device) -> torch.Tensor | None:
    if x is None:
        return None
    x = x.detach().to(device=device, dtype=torch.float32).reshape(-1, 3).contiguous()
    if x.shape[0] != b:
        raise ValueError(f"{name} must be [B, 3] with B = {b}, got {tuple(x.shape)}")
    return x


def _grid_args(grid: SparseGrid) -> tuple:
    native.check_device(grid.data.device)
    cells, blocks = grid.occupancy()
    return grid.data, grid.links, cells, blocks, OCCUPANCY_BLOCK, grid.lattice(), grid.sh_degree


def _march_args(opts: RenderOptions, grid: SparseGrid) -> tuple:
    return (float(opts.step_size), float(opts.stop_transmittance), float(opts.near), float(opts.sigma_threshold),
            int(opts.max_samples_per_ray), grid.contracted)


def floor_targets(targets: torch.Tensor, floors: torch.Tensor) -> torch.Tensor:
    """Targets [B, 3] with the channels `floors` [B, 3] (bool) made floors, as loss_and_grad reads them: a photo's
    clipped channel took in at least its value of light, so a render brighter there is not wrong."""
    return torch.where(floors, -targets, targets)


def colour_error(rendered: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """The error loss_and_grad squares, per value: rendered - target, and below a floor (a target below zero) alone."""
    return torch.where(targets >= 0, rendered - targets, (rendered + targets).clamp(max=0))


def render(grid: SparseGrid, origins, dirs, background=None, opts: RenderOptions | None = None,
           past_grid_only: bool = False) -> RenderResult:
    """rgb = sum_i T_i a_i c_i + T_final * background (None: black); opacity = 1 - T_final. `past_grid_only` (a
    background of spheres): light_past_grid(T_final) * background, none on a ray the march stopped below
    stop_transmittance."""
    opts = (opts or RenderOptions()).check()
    device = grid.data.device
    origins, dirs = _rays(origins, dirs, device)
    background = _colours(background, origins.shape[0], "background", device)
    rgb, depth, opacity = native.ops.render(*_grid_args(grid), origins, dirs, background, bool(past_grid_only),
                                            *_march_args(opts, grid))
    return RenderResult(rgb, depth, opacity)


def loss_and_grad(grid: SparseGrid, origins, dirs, targets, background, opts: RenderOptions | None,
                  grad: GridGrad, near_gradient: float = 0.0, past_grid_only: bool = False) -> tuple[float, torch.Tensor]:
    """Mean squared error over the B*3 colour values, forward and backward in one pass, of render's colours (with
    its `past_grid_only`). A target below zero is a floor at -target (floor_targets): wrong only below it.

    Adds d(mse)/d(density) and d(mse)/d(sh) into `grad` for the rows the batch touched, and returns
    (mse, d(mse)/d(background) [B, 3]). A sample at distance t < near_gradient along its ray passes on
    (t / near_gradient)^2 of its gradient (0: all of it; `TrainOptions.near_gradient_distance`).
    """
    opts = (opts or RenderOptions()).check()
    device = grid.data.device
    origins, dirs = _rays(origins, dirs, device)
    b = origins.shape[0]
    targets = _colours(targets, b, "targets", device)
    background = _colours(background, b, "background", device)
    if background is None:
        background = torch.zeros(b, 3, device=device)
    if grad.data.shape != grid.data.shape:
        raise ValueError("gradient storage belongs to another grid: make a new GridGrad after prune/upsample")
    sse, grad_background, grad.num_touched = native.ops.loss_and_grad(
        *_grid_args(grid), origins, dirs, targets, background, bool(past_grid_only), *_march_args(opts, grid),
        float(near_gradient),
        grad.data, grad.touched_mask,
        grad.touched_rows, grad.num_touched, *grad.scratch())
    return (sse / (3 * b) if b else 0.0), grad_background


def loss_and_grad_before_spheres(grid: SparseGrid, origins, dirs, targets, spheres: tuple, opts: RenderOptions | None,
                                 grad: GridGrad, near_gradient: float = 0.0) -> tuple[float, torch.Tensor, torch.Tensor]:
    """loss_and_grad with the background spheres behind the grid drawn in the same pass (CPU), only on the rays that
    light gets past the grid on (loss_and_grad with past_grid_only): a ray the grid stops shows nothing behind it, so
    drawing its spheres would be waste.
    `spheres`: the background's arguments on this batch's rays, with the layer record its backward reads
    (BackgroundOptimiser.on_rays). Returns (mse, d(mse)/d(background) [B, 3], the background drawn [B, 3])."""
    opts = (opts or RenderOptions()).check()
    device = grid.data.device
    origins, dirs = _rays(origins, dirs, device)
    b = origins.shape[0]
    targets = _colours(targets, b, "targets", device)
    if grad.data.shape != grid.data.shape:
        raise ValueError("gradient storage belongs to another grid: make a new GridGrad after prune/upsample")
    sse, grad_background, background, grad.num_touched = native.ops.loss_and_grad_spheres(
        *_grid_args(grid), origins, dirs, targets, *spheres, *_march_args(opts, grid), float(near_gradient),
        grad.data, grad.touched_mask, grad.touched_rows, grad.num_touched, *grad.scratch())
    return (sse / (3 * b) if b else 0.0), grad_background, background


def max_weights(grid: SparseGrid, origins, dirs, opts: RenderOptions | None = None) -> torch.Tensor:
    """Per occupied row, the largest rendering weight of a sample that reads it over these rays."""
    opts = (opts or RenderOptions()).check()
    origins, dirs = _rays(origins, dirs, grid.data.device)
    out = torch.zeros(grid.num_occupied, dtype=torch.float32, device=grid.data.device)
    native.ops.max_weights(*_grid_args(grid), origins, dirs, *_march_args(opts, grid), out)
    return out


def sample_counts(grid: SparseGrid, origins, dirs, opts: RenderOptions | None = None) -> tuple[int, int]:
    """(lattice samples inside the box, samples that contribute) over these rays."""
    opts = (opts or RenderOptions()).check()
    origins, dirs = _rays(origins, dirs, grid.data.device)
    lattice, used = native.ops.sample_counts(*_grid_args(grid), origins, dirs, *_march_args(opts, grid))
    return int(lattice), int(used)


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """Real SH basis [..., (degree+1)^2] at unit directions [..., 3], as the native core evaluates it (plenoxels_math.h)."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * x * z,
                SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z, SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)
