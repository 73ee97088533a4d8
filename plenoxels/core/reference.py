"""The PyTorch twin of every native kernel: short, vectorised, autograd-based. It is the readable
statement of the math; tests hold the C++ (and CUDA) kernels to it, and it is far too slow to fit with.

Rendering one ray (all kernels agree on every step):
1. Normalise the direction u = d/|d|; t is fit-frame distance along the ray o + t u.
2. Clip to the grid box and to t >= near: [t_start, t_exit). A grid with knots (grid.py) cuts the ray at every knot
   plane it crosses into pieces; on each the map to grid coordinates is linear, og + t * dg with
   og = g_j + (o - x_j) * slope_j and dg = u * slope_j per axis (one piece, og = (o - bbox_min) * scale, without knots).
3. On each piece, samples at t_i = t_start + (i + 0.5) * dt, dt = step_size / |dg| (step_size voxels in grid units),
   keeping t_i before the piece's end; a ray that would need more than max_samples_per_ray gets exactly that many:
   the piece where they run out is stretched over the rest of them and later pieces get none. This lattice is computed in float64 so that every backend takes the same
   samples; the twin uses the product's own lattice, render.ray_samples (tests check it against the kernels' sample
   counts).
4. At each sample: raw density and SH coefficients interpolated trilinearly from the 8 corners of its
   cell (an empty corner counts as zeros). sigma = raw density; samples with sigma <= sigma_threshold
   (>= 0) are skipped. colour = relu(sum_k sh_k Y_k(u) + 0.5) per channel.
5. alpha_i = 1 - exp(-sigma_i dt), T_i = prod_{j<i} (1 - alpha_j), weight_i = T_i alpha_i.
   A sample is used only while T_i >= stop_transmittance (early termination).
6. rgb = sum_i weight_i c_i + L * background; depth = sum_i weight_i t_i; opacity = 1 - T_final, with T_final the
   light left after the last used sample and L what of it reaches the background: T_final; where the background
   shows only past the grid (past_grid_only: the spheres), T_final from twice stop_transmittance s up, none below s
   (behind the stop nothing counts, the background as little as the dropped samples), T_final (T_final - s) / s
   between, so that colours do not jump (render.light_past_grid).
7. The loss's gradient reaches a sample's density and coefficients times min(1, (t_i / near_gradient)^2) (none
   scaled where near_gradient is 0): the values are untouched, only what flows back through them.

A contracted grid (unbounded scenes; plenoxels/core/fit_frame.py) spans [-2, 2]^3 of the contracted frame and the rays
come in the frame before the contraction. Steps 2-3 become a march from t = near: each step is step_size grid units
long at the speed |S J u| where it starts (J the contraction's Jacobian, S the grid's slopes per axis at the contracted
point: with knots, coarser cells take longer steps; no longer than a quarter of |q|_inf), its sample half way, until it
leaves for infinity, half a step through the finest cells short of the cube's faces and moving out
(contracted_samples); step 5 integrates each sample over its step's contracted length, step x |J u| at the sample.
"""
from __future__ import annotations

import math

import torch

from plenoxels.core.background import BACKGROUND_STOP_TRANSMITTANCE
from plenoxels.core.fit_frame import contract
from plenoxels.core.grid import SparseGrid, sh_count
from plenoxels.core.render import COLOUR_OFFSET, light_past_grid, ray_samples, sh_basis

TV_EPS = 1e-9
# csrc/plenoxels_math.h's PLX_CONTRACTED_MAX_STEP.
CONTRACTED_MAX_STEP = 0.25


def corners(links: torch.Tensor, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows [P, 8] (-1 = empty) and trilinear weights [P, 8] of grid points g [P, 3] (float32,
    inside [0, R-1]). Corner c = 4*dx + 2*dy + dz."""
    res = torch.tensor(links.shape)
    cell = torch.minimum(g.floor().long(), res - 2).clamp_min(0)
    f = g - cell.to(g.dtype)
    f0 = 1 - f
    rows, weights = [], []
    for c in range(8):
        d = ((c >> 2) & 1, (c >> 1) & 1, c & 1)
        rows.append(links[cell[:, 0] + d[0], cell[:, 1] + d[1], cell[:, 2] + d[2]])
        fx, fy, fz = (f[:, a] if d[a] else f0[:, a] for a in range(3))
        weights.append(fx * fy * fz)
    return torch.stack(rows, dim=1), torch.stack(weights, dim=1)


def interpolate(links: torch.Tensor, values: torch.Tensor, g: torch.Tensor, rows=None, weights=None) -> torch.Tensor:
    """Trilinear interpolation of per-row values [N, C] at grid points g [P, 3]; empty corners are 0."""
    if rows is None:
        rows, weights = corners(links, g)
    out = torch.zeros(g.shape[0], values.shape[1], dtype=values.dtype)
    for c in range(8):
        r = rows[:, c]
        out = out + weights[:, c : c + 1] * (values[r.clamp_min(0).long()] * (r >= 0).unsqueeze(1))
    return out


def _major_axis(q: torch.Tensor) -> torch.Tensor:
    """The axis of |q|_inf per point [B, 1] (the first of the largest), as csrc/plenoxels_math.h's major_axis."""
    a = q.abs()
    return torch.where((a[:, 0] >= a[:, 1]) & (a[:, 0] >= a[:, 2]), 0, torch.where(a[:, 1] >= a[:, 2], 1, 2))[:, None]


def _contracted_velocity(q: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """J(q) u per ray [B, 3] (float64), csrc/plenoxels_math.h's contracted_velocity term by term."""
    k = _major_axis(q)
    m = q.abs().gather(1, k)[:, 0]
    ms = m.clamp_min(1.0)
    f, df = (2.0 - 1.0 / ms) / ms, (2.0 / ms - 2.0) / (ms * ms)
    uk = u.gather(1, k)[:, 0]
    along = torch.where(q.gather(1, k)[:, 0] < 0, -uk, uk)
    v = (f[:, None] * u + q * (df * along)[:, None]).scatter(1, k, (uk / (ms * ms))[:, None])
    return torch.where((m <= 1.0)[:, None], u, v)


def _norm(v: torch.Tensor) -> torch.Tensor:
    return (v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2]).sqrt()


def _contracted_speed(q: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """|J(q) u| per ray [B] (float64), csrc/plenoxels_math.h's contracted_speed."""
    return _norm(_contracted_velocity(q, u))


def _contracted_grid_speed(grid: SparseGrid, q: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Grid units per unit of t [B] (float64): J(q) u through the grid's slopes at the contracted point,
    csrc/plenoxels_math.h's contracted_grid_speed."""
    c = contract(q)
    slopes = []
    for a in range(3):
        xs, _ = grid.axis_knots(a)
        piece = sum(((c[:, a] >= x).long() for x in xs[1:-1]), torch.zeros(c.shape[0], dtype=torch.long))
        slopes.append(torch.tensor(grid.axis_slopes(a), dtype=torch.float64)[piece])
    return _norm(torch.stack(slopes, dim=1) * _contracted_velocity(q, u))


def contracted_samples(grid: SparseGrid, origins, dirs, opts) -> dict:
    """The samples of rays through a contracted grid, stepped as csrc/plenoxels_math.h's contracted_step does: each
    step step_size voxels long at its start's grid speed (_contracted_grid_speed), but at most PLX_CONTRACTED_MAX_STEP
    of |q|_inf (at least 1), its sample half way, integrating density over step x speed at the sample; until
    max_samples_per_ray steps, or half a step (through the finest cells) short of the cube's faces and moving out
    (|q|_inf growing).
    Per ray `n` and `unit`; per step `t` [B, M], the contracted points `c` [B, M, 3], the lengths `delta` [B, M] and
    which are samples, `valid` [B, M] (not past the ray's end, nor beyond the shell it comes in through from further
    out)."""
    o, d = origins.double(), dirs.double()
    norm = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]).sqrt()
    u = d / norm[:, None]
    dt = opts.step_size / max(grid.scale)
    edge = 2.0 - 0.5 * dt
    cursor = torch.full((o.shape[0],), float(opts.near), dtype=torch.float64)
    alive = torch.ones(o.shape[0], dtype=torch.bool)
    ts, cs, deltas, valid = [], [], [], []
    for _ in range(opts.max_samples_per_ray):
        q = o + cursor[:, None] * u
        cap = CONTRACTED_MAX_STEP * q.abs().amax(dim=1).clamp_min(1.0)
        step = torch.minimum(opts.step_size / _contracted_grid_speed(grid, q, u), cap)
        t = cursor + 0.5 * step
        cursor = cursor + step
        at = o + t[:, None] * u
        m = at.abs().amax(dim=1)
        inside = torch.where(m <= 1.0, m, 2.0 - 1.0 / m.clamp_min(1.0)) < edge  # |contracted point|_inf
        k = _major_axis(at)
        toward = torch.where(at.gather(1, k)[:, 0] < 0, -u.gather(1, k)[:, 0], u.gather(1, k)[:, 0])
        alive = alive & (inside | (toward < 0))  # beyond the shell and receding: gone to infinity
        if not bool(alive.any()):
            break
        ts.append(t)
        cs.append(contract(at))
        deltas.append(step * _contracted_speed(at, u))
        valid.append(alive & inside)
    empty = torch.zeros(o.shape[0], 0, dtype=torch.float64)
    stack = (lambda xs: torch.stack(xs, dim=1)) if ts else (lambda xs: empty)
    valid = stack(valid).bool() if ts else torch.zeros(o.shape[0], 0, dtype=torch.bool)
    c = torch.stack(cs, dim=1) if cs else empty[..., None].expand(-1, -1, 3)
    return {"t": stack(ts), "c": c, "delta": stack(deltas), "valid": valid, "n": valid.sum(dim=1),
            "unit": u.to(torch.float32)}


def _samples(grid: SparseGrid, origins, dirs, opts) -> tuple:
    """(ray [P], idx [P], t [P] float64, grid point [P, 3] float64 not clamped, delta [P] float64,
    unit directions [B, 3] float32, samples per ray M) of every sample of a batch (steps 1-3)."""
    if grid.contracted:
        cs = contracted_samples(grid, origins, dirs, opts)
        M = cs["t"].shape[1]
        ray, idx = torch.nonzero(cs["valid"], as_tuple=True)
        g = grid.world_to_grid(cs["c"][ray, idx])
        return ray, idx, cs["t"][ray, idx], g, cs["delta"][ray, idx], cs["unit"], M
    lat = ray_samples(grid, origins, dirs, opts)
    per_ray = lat["n"].sum(dim=1)
    M = int(per_ray.max()) if origins.shape[0] else 0
    first = torch.cumsum(lat["n"], dim=1) - lat["n"]  # each piece's first sample's index along its ray
    rays, idxs, ts, gs, deltas = [], [], [], [], []
    for p in range(lat["n"].shape[1]):
        i = torch.arange(int(lat["n"][:, p].max()) if origins.shape[0] else 0, dtype=torch.float64)
        ray, k = torch.nonzero(i.long()[None, :] < lat["n"][:, p, None], as_tuple=True)
        t = lat["t_start"][ray, p] + (k.double() + 0.5) * lat["dt"][ray, p]
        rays.append(ray)
        idxs.append(first[ray, p] + k)
        ts.append(t)
        gs.append(lat["og"][ray, p] + t[:, None] * lat["dg"][ray, p])
        deltas.append(lat["dt"][ray, p])
    return torch.cat(rays), torch.cat(idxs), torch.cat(ts), torch.cat(gs), torch.cat(deltas), lat["unit"], M


class _ScaledGradient(torch.autograd.Function):
    """x itself, its gradient times `share` [P] (per sample, over x's last axes)."""

    @staticmethod
    def forward(ctx, x, share):
        ctx.save_for_backward(share)
        return x.clone()

    @staticmethod
    def backward(ctx, g):
        (share,) = ctx.saved_tensors
        return g * share.reshape(-1, *[1] * (g.dim() - 1)), None


def march(grid: SparseGrid, origins, dirs, opts, density: torch.Tensor, sh: torch.Tensor,
          near_gradient: float = 0.0) -> dict:
    """All samples of a batch with their weights and colours (steps 1-5), differentiable in density and sh (the
    gradient scaled near the camera by step 7)."""
    ray, idx, t, g, delta, unit, M = _samples(grid, origins, dirs, opts)
    B = origins.shape[0]
    dtype = density.dtype  # float32 like the kernels; float64 for gradcheck
    hi = torch.tensor(grid.resolution, dtype=dtype) - 1
    g = torch.minimum(g.to(dtype).clamp_min(0), hi)
    rows, weights = corners(grid.links, g)
    interpolated = interpolate(grid.links, density[:, None], g, rows, weights)[:, 0]
    share = (t.to(dtype) / near_gradient).clamp_max(1) ** 2 if near_gradient > 0 else None
    raw = interpolated if share is None else _ScaledGradient.apply(interpolated, share)
    used = raw > opts.sigma_threshold
    sigma = torch.where(used, raw, torch.zeros_like(raw))
    delta = delta.to(dtype)
    tau = torch.zeros(B, M, dtype=dtype).index_put((ray, idx), sigma * delta)
    used_pad = torch.zeros(B, M, dtype=torch.bool).index_put((ray, idx), used)
    t_before = torch.exp(-(torch.cumsum(tau, dim=1) - tau))
    alive = used_pad & (t_before >= opts.stop_transmittance)
    alpha = 1 - torch.exp(-tau)
    weight = torch.where(alive, t_before * alpha, torch.zeros_like(alpha))
    t_final = torch.exp(-(tau * alive).sum(dim=1))
    K = sh_count(grid.sh_degree)
    interpolated_sh = interpolate(grid.links, sh, g, rows, weights).reshape(-1, 3, K)
    coeffs = interpolated_sh if share is None else _ScaledGradient.apply(interpolated_sh, share)
    basis = sh_basis(grid.sh_degree, unit.to(dtype))[ray]
    colour = torch.relu((coeffs * basis[:, None, :]).sum(-1) + COLOUR_OFFSET)
    colour_pad = torch.zeros(B, M, 3, dtype=dtype).index_put((ray, idx), colour)
    t_pad = torch.zeros(B, M, dtype=dtype).index_put((ray, idx), t.to(dtype))
    return {"weight": weight, "colour": colour_pad, "t": t_pad, "t_final": t_final, "alive": alive,
            "ray": ray, "idx": idx, "rows": rows, "corner_weights": weights,
            "density_samples": interpolated, "sh_samples": interpolated_sh}


def _light(m: dict, opts, past_grid_only: bool) -> torch.Tensor:
    return light_past_grid(m["t_final"], opts.stop_transmittance if past_grid_only else 0.0)


def render(grid: SparseGrid, origins, dirs, background, opts, density=None, sh=None, past_grid_only: bool = False):
    """(rgb [B,3], depth [B], opacity [B]); differentiable in density, sh and background."""
    density = grid.density if density is None else density
    sh = grid.sh if sh is None else sh
    m = march(grid, origins, dirs, opts, density, sh)
    rgb = (m["weight"][..., None] * m["colour"]).sum(dim=1)
    if background is not None:
        rgb = rgb + _light(m, opts, past_grid_only)[:, None] * background
    depth = (m["weight"] * m["t"]).sum(dim=1)
    return rgb, depth, 1 - m["t_final"]


def _used_rows(m: dict) -> torch.Tensor:
    """Rows read by samples that contributed (alive), as the native kernels touch them."""
    alive = m["alive"][m["ray"], m["idx"]]
    rows = m["rows"][alive].reshape(-1)
    return torch.unique(rows[rows >= 0]).long()


def loss_and_grad(grid: SparseGrid, origins, dirs, targets, background, opts, grad,
                  near_gradient: float = 0.0, past_grid_only: bool = False) -> tuple[float, torch.Tensor]:
    """Mean squared error over the batch's B*3 values; adds its gradient (step 7) into `grad`."""
    density = grid.density.detach().clone().requires_grad_(True)
    sh = grid.sh.detach().clone().requires_grad_(True)
    bg = background.detach().clone().requires_grad_(True)
    m = march(grid, origins, dirs, opts, density, sh, near_gradient)
    rgb = (m["weight"][..., None] * m["colour"]).sum(dim=1) + _light(m, opts, past_grid_only)[:, None] * bg
    # A target below zero is a floor at -target (a photo's clipped channel): wrong only below it.
    error = torch.where(targets >= 0, rgb - targets, (rgb + targets).clamp(max=0))
    mse = (error ** 2).mean()
    mse.backward()
    rows = _used_rows(m)
    grad.accumulate(rows, density.grad[rows], sh.grad[rows])
    return float(mse.detach()), bg.grad


def max_weights(grid: SparseGrid, origins, dirs, opts) -> torch.Tensor:
    """Per row, the largest weight of any sample that reads it with a non-zero trilinear weight."""
    with torch.no_grad():
        m = march(grid, origins, dirs, opts, grid.density, grid.sh)
        w = m["weight"][m["ray"], m["idx"]]
        rows, cw = m["rows"], m["corner_weights"]
        use = (rows >= 0) & (cw > 0) & m["alive"][m["ray"], m["idx"]][:, None]
        w8 = w[:, None].expand_as(cw)
        out = torch.zeros(grid.num_occupied, dtype=torch.float32)
        return out.scatter_reduce(0, rows[use].long(), w8[use], reduce="amax")


def tv_neighbours(grid: SparseGrid, rows: torch.Tensor) -> torch.Tensor:
    """Rows of the +x, +y, +z neighbours [M, 3] of the given rows (-1 = empty or outside)."""
    xyz = grid.coords()[rows].long()
    res = grid.resolution
    out = []
    for a in range(3):
        q = xyz.clone()
        q[:, a] += 1
        inside = q[:, a] < res[a]
        q[:, a] = q[:, a].clamp_max(res[a] - 1)
        out.append(torch.where(inside, grid.links[q[:, 0], q[:, 1], q[:, 2]], torch.full_like(q[:, 0], -1, dtype=torch.int32)))
    return torch.stack(out, dim=1)


def tv_loss(grid: SparseGrid, rows, weight_density, weight_sh, density=None, sh=None) -> torch.Tensor:
    """weight * mean over the sampled rows of sum over channels of sqrt(dx^2 + dy^2 + dz^2 + eps),
    with forward differences to allocated +axis neighbours (rows with none are left out)."""
    density = grid.density if density is None else density
    sh = grid.sh if sh is None else sh
    nb = tv_neighbours(grid, rows)
    has = nb >= 0
    counted = has.any(dim=1)
    total = torch.zeros((), dtype=density.dtype)
    for weight, values in ((weight_density, density[:, None]), (weight_sh, sh)):
        if weight == 0:
            continue
        v = values[rows][:, None, :]
        diff = torch.where(has[..., None], values[nb.clamp_min(0).long()] - v, torch.zeros_like(v))
        term = torch.sqrt((diff * diff).sum(dim=1) + TV_EPS)
        total = total + weight / rows.shape[0] * (term.sum(dim=1) * counted).sum()
    return total


def tv_loss_and_grad(grid: SparseGrid, grad, rows, weight_density, weight_sh) -> float:
    density = grid.density.detach().clone().requires_grad_(True)
    sh = grid.sh.detach().clone().requires_grad_(True)
    if rows.shape[0] == 0:
        return 0.0
    loss = tv_loss(grid, rows, weight_density, weight_sh, density, sh)
    if not loss.requires_grad:
        return float(loss)
    loss.backward()
    nb = tv_neighbours(grid, rows)
    counted = (nb >= 0).any(dim=1)
    touched = torch.cat([rows[counted], nb[nb >= 0].long()])
    touched = torch.unique(touched)
    grad.accumulate(touched, density.grad[touched], sh.grad[touched])
    return float(loss.detach())


def rmsprop_step(data, second_moment, grad, columns: int, lr_density, lr_sh, beta, eps) -> None:
    """v = beta v + (1 - beta) g^2; p -= lr g / (sqrt(v) + eps) on the touched rows; clears them."""
    rows = grad.touched()
    g = grad.data[rows, :columns]
    v = beta * second_moment[rows, :columns] + (1 - beta) * g * g
    lr = torch.full((columns,), float(lr_sh), dtype=torch.float32)
    lr[0] = lr_density
    second_moment[rows, :columns] = v
    data[rows, :columns] -= lr * g / (torch.sqrt(v) + eps)
    grad.clear()



def background_colour(origins: torch.Tensor, dirs: torch.Tensor, centre: torch.Tensor, radii: torch.Tensor,
                      texture: torch.Tensor, far_colour: torch.Tensor) -> torch.Tensor:
    """The multi-sphere background's colour [B, 3] (plenoxels/core/background.py; the native background_render), with
    autograd through `texture` [K, H, W, 4] (raw density, colour logits).

    A ray with origin o and unit direction u leaves the sphere |p - centre| = r at t = -b + sqrt(b^2 - c),
    b = (o - centre).u, c = |o - centre|^2 - r^2; it misses where b^2 < c or t <= 0. The texture is read
    bilinearly at that direction: texel centres at (i + 0.5) / W of the azimuth from -pi and (j + 0.5) / H of the
    polar angle from +z, azimuth wrapping (one wrapped column padded on each side) and rows clamping. Layers
    composite front (small radius) to back with alpha = 1 - exp(-relu(density)), colour sigmoid(logits), a ray
    stopping once less than BACKGROUND_STOP_TRANSMITTANCE of its light gets through; the transmittance left sees
    far_colour."""
    dtype = texture.dtype
    o, d = origins.to(dtype), dirs.to(dtype)
    rel = o - centre.to(dtype)
    unit = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    b = (rel * unit).sum(-1)
    c = (rel * rel).sum(-1)
    r = radii.to(dtype)[:, None]
    disc = b * b - c + r * r                                                   # [K, B]
    t = -b + disc.clamp_min(0).sqrt()
    valid = (disc >= 0) & (t > 0)
    p = rel[None] + t[..., None] * unit[None]
    p = p / p.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    azimuth = torch.atan2(p[..., 1], p[..., 0])
    elevation = torch.asin(p[..., 2].clamp(-1.0, 1.0))
    width = texture.shape[2]
    # grid_sample's [-1, 1] spans the W real columns plus one wrapped column on each side.
    grid = torch.stack([(azimuth / math.pi) * width / (width + 2), -elevation / (math.pi / 2)], dim=-1)[:, :, None, :]
    channels = texture.permute(0, 3, 1, 2)                                     # [K, 4, H, W]
    padded = torch.cat([channels[..., -1:], channels, channels[..., :1]], dim=-1)
    samples = torch.nn.functional.grid_sample(padded, grid, mode="bilinear", padding_mode="border",
                                              align_corners=False)[..., 0]      # [K, 4, B]
    alpha = (1 - torch.exp(-torch.relu(samples[:, 0]))) * valid.to(dtype)
    rgb = torch.sigmoid(samples[:, 1:])
    # Early termination: a layer counts only while the light reaching it is at least the threshold.
    reaching = torch.cumprod(torch.cat([torch.ones_like(alpha[:1]), 1 - alpha[:-1]], dim=0), dim=0)
    alpha = alpha * (reaching.detach() >= BACKGROUND_STOP_TRANSMITTANCE).to(dtype)
    transmittance = torch.cumprod(torch.cat([torch.ones_like(alpha[:1]), 1 - alpha], dim=0), dim=0)
    weights = alpha * transmittance[:-1]
    return (weights[:, None] * rgb).sum(0).T + transmittance[-1][:, None] * far_colour.to(dtype)
