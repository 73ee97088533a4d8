"""What the parts of a fit cost on this machine: the cost model a time budget plans with, and its calibration.

`calibrate(options, device, background)` times train steps of the real Fitter on a small synthetic object (thin
opaque surfaces, the vertices within 3 voxels of them allocated, as pruning leaves a fit) at a few resolutions, a
pruning pass, a level change and the steps on the grid it upsampled, and steps of a first level (a new model's grid,
the whole box) at a few resolutions, on the device and with the threads the fit uses (a few seconds). The
`CostModel` fitted to those times is

- seconds per step = a + b x occupied voxels, one line for pruned grids and one for first levels: a first level's
  step marches every ray through the whole box with nothing to skip and nothing opaque to stop it, dearer than a
  pruned grid's step of as many voxels;
- seconds per pass (pruning, held-out renders) = c + d x rays x resolution;
- per-voxel costs of a level change, a checkpoint and the final save;
- the ratio of a just-upsampled grid's steps to the line (a thicker, softer shell than a converged grid, whose rays
  march more samples), which predicts a later level until the fit has measured its own.

Times that do not grow over the sizes measured are a fixed cost (`_line`): a GPU's steps and passes at these sizes
are kernel launches and read-backs, and a line drawn through the origin would call them per-voxel cost and predict a
finer grid's steps many times slower than they run.

The model is cached as JSON under `$XDG_CACHE_HOME/voxfield/` (else `~/.cache/voxfield/`), keyed by the CPU and GPU
model, the thread counts, the device, the code of the native core and of this package, and the options that set what
a step costs; a changed key measures again. A cached one is timed again on its first grid (two rounds, the faster
counts; a fraction of the calibration's time) and its times scaled by how much slower or faster the machine runs now:
a shared machine's speed drifts, and a plan from a calibration made at a fast moment starves its last level. A reading
far from the calibration is checked with a few more rounds, as a moment's stall would otherwise scale the whole plan.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib.util
import itertools
import json
import math
import os
import platform
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from plenoxels.core import native
from plenoxels.core.cameras import Intrinsics, look_at
from plenoxels.core.grid import SparseGrid, row_stride, sh_count
from plenoxels.core.scene_model import SceneModel
from plenoxels.core.train import Fitter, pruning_rays
from plenoxels.core.ray_set import RaySet

CACHE_VERSION = 4
# Resolutions the calibration times steps at (grids as pruning leaves a fit).
CALIBRATION_RESOLUTIONS = (64, 128, 192)
# Resolutions it times a first level's steps at: the whole box allocated, as a fit starts. Such a step marches every
# ray through the box with nothing to skip and nothing opaque to stop it, dearer than a pruned grid's step of as many
# voxels, so first levels get a line of their own.
DENSE_RESOLUTIONS = (32, 64, 96)
DENSE_STEPS = 4  # timed steps at each (fewer than the surface grids': these steps are the dearest)
CALIBRATION_WARMUP = 2
CALIBRATION_STEPS = 8
# Rounds of CALIBRATION_STEPS a cached calibration's first step is timed again in (see calibrate), and the rounds
# added when the faster of those reads the machine more than RETIME_CHECK slower or faster than the calibration did: a
# moment's stall at the start of a fit can read 1.3x on a machine whose steps then run at the calibration's speed, and
# the plan it scales chooses a grid a level too coarse for the budget (bench/README.md, "The time budget").
RETIME_ROUNDS = 2
RETIME_MORE = 3
RETIME_CHECK = 0.1
# The calibration's cameras: this many views of this many pixels a side, around the synthetic object.
CALIBRATION_VIEWS = 24
CALIBRATION_SIDE = 64


@dataclass
class CostModel:
    """Seconds the parts of a fit take on one machine, for one set of the options that set them."""
    step_fixed: float
    """Seconds of one train step whatever the grid (the batch, its rays, the calls)."""
    step_per_voxel: float
    """Seconds of one train step per occupied voxel."""
    pass_per_ray: float
    """Seconds per ray and per vertex of resolution of a pass that marches the grid (pruning, held-out renders)."""
    change_per_voxel: float
    """Seconds per voxel of the upsampled grid at a level change, beyond its pruning passes (upsampling, optimiser
    state)."""
    checkpoint_per_voxel: float
    """Seconds per voxel to write a checkpoint (at each level change, every checkpoint_every seconds, at a stop)."""
    save_per_voxel: float
    """Seconds per voxel to save the fitted model."""
    dense_fixed: float | None = None
    """Seconds of one step of a first level (its whole box allocated) whatever the grid; None: as a pruned grid's."""
    dense_per_voxel: float | None = None
    """Seconds of one step of a first level per voxel of its box."""
    pass_fixed: float = 0.0
    """Seconds of a pass whatever its rays (the calls, the chunks' hand-offs: all of a GPU's pass at these sizes)."""
    upsampled_ratio: float = 1.0
    """A step on a grid just upsampled from a pruned one over the model's at its voxels: a fit's later levels start
    from such a grid, a thicker and softer shell than a converged one, whose rays march more samples per voxel."""

    def scaled(self, factor: float) -> "CostModel":
        """Every time `factor` times longer (the machine that slower); the upsampled grid's ratio as it is."""
        times = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "upsampled_ratio"}
        return dataclasses.replace(self, **{k: v * factor for k, v in times.items() if v is not None})

    def step_seconds(self, voxels: float, dense: bool = False) -> float:
        if dense and self.dense_fixed is not None:
            return self.dense_fixed + self.dense_per_voxel * voxels
        return self.step_fixed + self.step_per_voxel * voxels

    def pass_seconds(self, rays: float, resolution: int) -> float:
        return self.pass_fixed + self.pass_per_ray * rays * resolution

    def describe(self) -> str:
        line = f"{1000 * self.step_fixed:.1f} ms per step plus {1e8 * self.step_per_voxel:.1f} ms per 100k voxels"
        if self.dense_fixed is not None:
            line += (f" ({1000 * self.dense_fixed:.1f} ms plus {1e8 * self.dense_per_voxel:.1f} ms per 100k voxels "
                     f"at a first level)")
        return line + f", {self.upsampled_ratio:.2f}x on an upsampled grid"


def change_passes(before: int, after: int, prune_upsampled: bool) -> tuple[int, ...]:
    """The resolutions of the pruning passes a level change from `before` to `after` runs: the coarse grid's, and
    where the fit prunes each upsampled grid on its own render (fit.prune_upsampled), the finer one's."""
    return (before, after) if prune_upsampled and after != before else (before,)


def cache_dir() -> Path:
    """Where calibrations are kept: $XDG_CACHE_HOME/voxfield, else ~/.cache/voxfield."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "voxfield"


def processor_name() -> str:
    """The CPU's model name (what a calibration holds for)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


@functools.lru_cache(maxsize=4)
def _file_digest(path: str, size: int, mtime: float) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def code_hash() -> str:
    """The native core's build and this package's sources: the code a step runs."""
    digest = hashlib.sha256()
    spec = importlib.util.find_spec("plenoxels._C")
    if spec is not None and spec.origin:
        stat = os.stat(spec.origin)
        digest.update(_file_digest(spec.origin, stat.st_size, stat.st_mtime).encode())
    for source in sorted(Path(__file__).resolve().parent.glob("*.py")):
        digest.update(source.name.encode() + source.read_bytes())
    return digest.hexdigest()[:16]


def calibration_key(options, device: torch.device, background: dict | None,
                    resolutions=CALIBRATION_RESOLUTIONS, dense_resolutions=DENSE_RESOLUTIONS) -> dict:
    """What a calibration holds for: the machine, the code, the options (of the fit's Settings, a TrainOptions and a
    ModelOptions) that set what a step costs, and the fit's background model (n_spheres, width; None: none)."""
    cost_options = {name: getattr(options, name) for name in (
        "batch_size", "batch_mode", "tile_size", "coherent_batches", "sh_degree", "step_size", "stop_transmittance",
        "tv_sample_fraction", "prune_ray_scale", "prune_rays_per_cell", "prune_upsampled")}
    return {
        "version": CACHE_VERSION, "cpu": processor_name(),
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "device": device.type, "threads": native.num_threads(), "torch_threads": torch.get_num_threads(),
        "code": code_hash(), "background": background, "options": cost_options, "resolutions": list(resolutions),
        "first_level_resolutions": list(dense_resolutions),
    }


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _surface_distance(points: torch.Tensor) -> torch.Tensor:
    """Signed distance (negative inside) to the calibration object in [-1, 1]^3: a ball, a box and a thin slab."""
    ball = (points - torch.tensor([0.25, 0.1, 0.05])).norm(dim=-1) - 0.45
    q = (points - torch.tensor([-0.35, -0.2, -0.15])).abs() - torch.tensor([0.3, 0.25, 0.35])
    box = q.clamp_min(0).norm(dim=-1) + q.max(dim=-1).values.clamp_max(0)
    slab = torch.maximum((points[..., 2] + 0.6).abs() - 0.05, (points[..., :2].abs() - 0.9).max(dim=-1).values)
    return torch.minimum(torch.minimum(ball, box), slab)


def _surface_grid(model: SceneModel, resolution: int, sh_degree: int) -> SparseGrid:
    """The calibration object in the model's box as a converged, pruned fit has it: opaque within a voxel inside its
    surfaces, empty elsewhere, the vertices within 3 voxels of a surface allocated."""
    shape = model.resolution_for(resolution)
    lo, hi, knots = model.grid.bbox_min, model.grid.bbox_max, model.grid.knots
    lattice = SparseGrid(torch.full(shape, -1, dtype=torch.int32), torch.zeros(0, row_stride(sh_degree)), lo, hi,
                         sh_degree, knots=knots)
    axes = [lattice.grid_to_world(torch.arange(n, dtype=torch.float64)[:, None].expand(n, 3))[:, a].float()
            for a, n in enumerate(shape)]
    voxel = max(1.0 / s for s in lattice.scale)
    y, z = torch.meshgrid(axes[1], axes[2], indexing="ij")
    distance = torch.stack([_surface_distance(torch.stack([torch.full_like(y, float(x)), y, z], dim=-1))
                            for x in axes[0]])  # a slab at a time: little memory at any resolution
    keep = distance.abs() < 3 * voxel
    links = torch.full(shape, -1, dtype=torch.int32)
    count = int(keep.sum())
    links[keep] = torch.arange(count, dtype=torch.int32)
    density = 300.0 * torch.sigmoid(-distance[keep] / voxel) - 10.0
    sh = torch.randn(count, 3 * sh_count(sh_degree), generator=torch.Generator().manual_seed(0)) * 0.3
    return SparseGrid.from_values(links, density, sh, lo, hi, sh_degree, knots=knots)


def _calibration_views(model: SceneModel) -> RaySet:
    """CALIBRATION_VIEWS cameras on a band of a sphere around the object, looking at it, with `model`'s renders as
    their photos."""
    images, c2ws, ks = [], [], []
    side = CALIBRATION_SIDE
    for i in range(CALIBRATION_VIEWS):
        z = 0.9 - 1.4 * (i + 0.5) / CALIBRATION_VIEWS
        angle = i * math.pi * (3 - math.sqrt(5))
        eye = 3.0 * np.array([math.sqrt(1 - z * z) * math.cos(angle), math.sqrt(1 - z * z) * math.sin(angle), z])
        c2ws.append(look_at(eye, (0.0, 0.0, 0.0)))
        ks.append(Intrinsics(1.2 * side, 1.2 * side, side / 2, side / 2, side, side))
        images.append(model.render_camera(c2ws[-1], ks[-1])["rgb"].cpu().numpy())
    return RaySet(images, c2ws, ks)


def _time_steps(fitter: Fitter, device: torch.device, steps: int = CALIBRATION_STEPS) -> float:
    """Median seconds of `steps` train steps after CALIBRATION_WARMUP."""
    for _ in range(CALIBRATION_WARMUP):
        fitter.train_step()
    times = []
    for _ in range(steps):
        _sync(device)
        started = time.perf_counter()
        fitter.train_step()
        _sync(device)
        times.append(time.perf_counter() - started)
    return float(np.median(times))


def _line(points: list[tuple[int, float]]) -> tuple[float, float]:
    """(fixed, per unit) seconds of a step or a pass, fitted to (voxels or rays times resolution, seconds) points;
    positive and not decreasing.

    Times that do not grow over the points cost what they measured, whatever the size: a GPU's steps at these sizes
    are launches and read-backs. A line through the origin, the fallback for a negative intercept, would call them all
    per-voxel cost and predict a finer grid's steps many times slower than they run (bench/README.md, "The time
    budget")."""
    voxels, seconds = np.array([p[0] for p in points], dtype=np.float64), np.array([p[1] for p in points])
    if len(points) == 1:  # a partial calibration's one point (see measure): its time per unit, as a CPU's grow
        return 0.0, float(seconds[0] / max(voxels[0], 1.0))
    slope, fixed = np.polyfit(voxels, seconds, 1)
    if slope <= 0:
        return float(seconds.mean()), 0.0
    if fixed < 0:
        return 0.0, float((voxels * seconds).sum() / (voxels * voxels).sum())
    return float(fixed), float(slope)


class CalibrationObject:
    """The calibration's synthetic object with its views, and Fitters on it with these options and a background model
    of `background`'s n_spheres and width (None: none)."""

    def __init__(self, options, device: torch.device, background: dict | None, resolution: int):
        self.options, self.device = options, device
        self.scene = {"type": "object", "foreground": {"min": [-1.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0]}}
        # One object in one frame whatever model the fit takes: the key does not name the model, and the object in a
        # contracted frame marches twice as far a step (a new grid's 32^3 steps 44-61 ms against 22-29 ms), so a
        # calibration measured for a contracted fit would price every bounded fit after it (bench/README.md, "The
        # time budget"). The fit's own steps, measured as it goes, carry what its model costs over this one.
        self.model_options = dataclasses.replace(options, ndc="off", contract="off",
                                                 background="on" if background else "off")
        if background:
            self.model_options = dataclasses.replace(self.model_options, background_spheres=background["n_spheres"],
                                                     background_width=background["width"])
        self.views = _calibration_views(self.model_at(resolution))

    def model_at(self, resolution: int) -> SceneModel:
        model = SceneModel.create(self.scene, self.model_options, 8)
        model.grid = _surface_grid(model, resolution, self.options.sh_degree)
        return model

    def fitter_at(self, levels: list[int], first: bool = False) -> Fitter:
        """A Fitter at `levels[0]`: on the object's pruned grid, or (`first`) on a new model's grid."""
        fit_options = dataclasses.replace(self.model_options, resolutions=levels, steps=[1_000_000] * len(levels))
        model = (SceneModel.create(self.scene, self.model_options, levels[0]) if first
                 else self.model_at(levels[0]))
        return Fitter(model, fit_options, self.views, self.device)


def measure(options, device: torch.device, background: dict | None, resolutions=CALIBRATION_RESOLUTIONS,
            dense_resolutions=DENSE_RESOLUTIONS, allowance: float | None = None) -> dict:
    """Times the real Fitter with these options (and a background model of `background`'s n_spheres and width) on
    the calibration object: steps and a pruning pass at each resolution, steps of a new model's grid (a first level)
    at each dense resolution, and one level change, then the coarsest grid's steps again (the faster time kept: a
    cached calibration is rescaled by that point). Returns the cost model's fields and what was measured.

    The coarsest of each, and the level change, come first; the finer ones follow, coarse to fine, only while the
    time spent is under `allowance` (seconds; None: all of them). A budget's calibration comes out of its own time:
    a short budget's plans are made of coarse rungs, which the coarse points speak for, and a busy machine's whole
    calibration can take longer than such a budget (33 s against a 12 s one at twice the cores' work). A record
    short of points is `partial`."""
    started = time.perf_counter()
    calibration = CalibrationObject(options, device, background, resolutions[0])
    fitter_at, views = calibration.fitter_at, calibration.views
    rays = {r: pruning_rays(views.sizes, r, options) for r in resolutions}
    points, passes, dense_points = [], [], []

    def pruned(resolution: int) -> None:
        fitter = fitter_at([resolution])
        points.append((fitter.model.grid.num_occupied, _time_steps(fitter, device)))
        _sync(device)
        begun = time.perf_counter()
        fitter.measure_weights()
        _sync(device)
        passes.append((rays[resolution] * resolution, time.perf_counter() - begun))

    def first_level(resolution: int) -> None:
        fitter = fitter_at([resolution], first=True)
        dense_points.append((fitter.model.grid.num_occupied, _time_steps(fitter, device, DENSE_STEPS)))

    pruned(resolutions[0])
    first_level(dense_resolutions[0])
    # One level change, from the coarsest grid to twice its resolution, then a checkpoint and a save of the model.
    fitter = fitter_at([resolutions[0], 2 * resolutions[0]])
    fitter.step = fitter.level_end(0)
    with tempfile.TemporaryDirectory() as tmp:
        _sync(device)
        clock = [time.perf_counter()]
        fitter.next_level()
        _sync(device)
        clock.append(time.perf_counter())
        fitter.save_checkpoint(Path(tmp) / "checkpoint.pt")
        clock.append(time.perf_counter())
        fitter.model.save(Path(tmp))
        clock.append(time.perf_counter())
    change, checkpoint, save = np.diff(clock)
    new_voxels, upsampled_voxels = fitter.model.grid.num_occupied, fitter.levels[-1]["upsampled"]
    upsampled = _time_steps(fitter, device)
    del fitter
    finer = [part for pair in itertools.zip_longest(
        [functools.partial(pruned, r) for r in resolutions[1:]],
        [functools.partial(first_level, r) for r in dense_resolutions[1:]]) for part in pair if part is not None]
    for part in finer:
        if allowance is not None and time.perf_counter() - started >= allowance:
            break
        part()
    # The coarsest grid timed again, the faster of its two times kept, as a cached calibration's retime keeps the
    # fastest of its rounds: its first timing is the fit's first work, and one that read 1.9x what later retimes did
    # flattened the line and scaled every later fit's costs by about 0.5, planning grids whose steps then ran 1.6-2.2x
    # their prediction (bench/README.md, "The time budget").
    coarsest = fitter_at([resolutions[0]])
    points[0] = (points[0][0], min(points[0][1], _time_steps(coarsest, device)))
    del coarsest

    fixed, slope = _line(points)
    dense_fixed, dense_slope = _line(dense_points)
    pass_fixed, pass_per_ray = _line(passes)
    # The level change's own passes, priced as passes (fit_plan.change_seconds), not per voxel of what they leave.
    passes_in_change = sum(pass_fixed + pass_per_ray * pruning_rays(views.sizes, r, options) * r
                           for r in change_passes(resolutions[0], 2 * resolutions[0], options.prune_upsampled))
    return {
        "costs": {"step_fixed": fixed, "step_per_voxel": slope,
                  "pass_fixed": pass_fixed, "pass_per_ray": pass_per_ray,
                  "change_per_voxel": max(0.0, change - passes_in_change) / upsampled_voxels,
                  "checkpoint_per_voxel": checkpoint / new_voxels, "save_per_voxel": save / new_voxels,
                  "dense_fixed": dense_fixed, "dense_per_voxel": dense_slope,
                  "upsampled_ratio": upsampled / (fixed + slope * new_voxels)},
        "points": [{"resolution": r, "voxels": n, "step_seconds": round(t, 5)}
                   for r, (n, t) in zip(resolutions, points)],
        "first_level_points": [{"resolution": r, "voxels": n, "step_seconds": round(t, 5)}
                               for r, (n, t) in zip(dense_resolutions, dense_points)],
        "passes": [{"resolution": r, "rays": rays[r], "seconds": round(t, 5)}
                   for r, (_, t) in zip(resolutions, passes)],
        "level_change": {"voxels": new_voxels, "upsampled_voxels": upsampled_voxels, "seconds": round(float(change), 4),
                         "step_seconds": round(upsampled, 5),
                         "checkpoint_seconds": round(float(checkpoint), 4), "save_seconds": round(float(save), 4)},
        "partial": len(points) + len(dense_points) < len(resolutions) + len(dense_resolutions),
        "allowance": None if allowance is None else round(allowance, 2),
        "seconds": round(time.perf_counter() - started, 2),
        "load_average": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
        "when": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }


def calibrate(options, device: torch.device, background: dict | None = None, resolutions=CALIBRATION_RESOLUTIONS,
              dense_resolutions=DENSE_RESOLUTIONS, say: Callable[[str], None] | None = None,
              allowance: float | None = None) -> tuple[CostModel, dict]:
    """The cost model for these options on this machine: from the cache when its key matches (and, for a partial
    calibration, `allowance` is no longer than the one it was measured in), with its times scaled by
    how much longer the calibration's first step takes now (the fastest of RETIME_ROUNDS timings, and of RETIME_MORE
    more where those read far from the calibration) than it did (a shared host's speed drifts, and a plan from a
    calibration made at a fast moment starves its last level), else measured (a few seconds; within `allowance`
    seconds where it says, see measure) and cached. Returns it and the calibration's record, with `cached`, `file`,
    `retimed` (the rounds, in seconds) and `slower_now` (that scale; 1 for a calibration just measured) added."""
    key = calibration_key(options, device, background, resolutions, dense_resolutions)
    path = cache_dir() / f"fit-cost-{hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]}.json"
    try:
        record = json.loads(path.read_text())
        if record.get("key") == key and (not record.get("partial") or (
                allowance is not None and allowance <= (record.get("allowance") or 0.0))):
            reference = record["points"][0]
            fitter = CalibrationObject(options, device, background, reference["resolution"]).fitter_at(
                [reference["resolution"]])
            # The fastest round counts: the first can pay for faulting in the new grid's tables, or catch the host
            # at a slow moment, which would scale a plan far past what its steps then cost.
            rounds = [_time_steps(fitter, device) for _ in range(RETIME_ROUNDS)]
            if abs(min(rounds) / reference["step_seconds"] - 1) > RETIME_CHECK:
                rounds += [_time_steps(fitter, device) for _ in range(RETIME_MORE)]
            slower = min(rounds) / reference["step_seconds"]
            return (CostModel(**record["costs"]).scaled(slower),
                    {**record, "cached": True, "file": str(path), "slower_now": round(slower, 3),
                     "retimed": [round(t, 5) for t in rounds]})
    except (OSError, ValueError, TypeError, KeyError, ZeroDivisionError):
        pass  # none yet, or unreadable: measure
    if say is not None:
        say(f"measuring what the fit costs on this machine ({key['device']}, {key['threads']} threads; once, then "
            f"cached in {path.parent})")
    record = {"key": key, **measure(options, device, background, resolutions, dense_resolutions, allowance)}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(record, indent=2))
        tmp.replace(path)
    except OSError:
        pass  # an unwritable cache: measure again next time
    return CostModel(**record["costs"]), {**record, "cached": False, "file": str(path), "slower_now": 1.0}
