"""A time budget for the fit: a cost model measured on this machine, the plan it picks, and a pacer that keeps
the fit on time.

- `calibrate(options, device, background)`: times train steps of the real Fitter on a small synthetic object (thin
  opaque surfaces, the vertices within 3 voxels of them allocated, as pruning leaves a fit) at a few resolutions, a
  pruning pass and a level change and the steps on the grid it upsampled, steps of a first level (a new model's grid,
  the whole box) at a few resolutions, on the device and with the threads the fit uses. The `CostModel` fitted to that
  is cached as JSON under `$XDG_CACHE_HOME/voxfield/` (else `~/.cache/voxfield/`), keyed by the CPU and GPU model,
  the thread counts, the device, the code of the native core and of this package, and the options that set what a
  step costs; a changed key measures again (a few seconds), and a cached one is timed again on its first grid and
  its times scaled to the machine's speed now.
- `TimeBudget`: picks the plan (levels, resolutions, steps) whose predicted time fits what is left of the budget;
  attached to the Fitter, it measures what the real scene costs as the fit goes, re-plans the steps of the levels
  under way and to come every few steps and at each level change (in a scene that fills its box, lowering a last
  level too dear for half its steps), and says when the fit must stop to end on time.

What a prediction adds up, from where the fit stands to its end: steps times seconds per step (for the level under
way, what its steps measure, or before they have, the first-level model at its box's voxels; for later levels, the
cost model at their occupied voxels, times the ratio of this scene's measured steps to the model's; a first level's
ratio, and that of a first level's early-pruned rest, counts only above 1, as such a level clears its empty space and
gets cheaper as it goes while a busy machine does not, and until a level at a finer resolution has measured its own,
it is times what an upsampled grid's steps cost over the model in the calibration), level changes (a pruning
pass over the training rays at the old resolution, then upsampling and a checkpoint that grow with the new grid),
held-out evaluations, checkpoints, and the end (the last pruning pass, the held-out PSNR, the save). A later level's
voxels are the level before's, times the share pruning keeps, times the upsampling's growth; the share is a prior
until a level change has measured it.

Which plan, from what the project measured (bench/README.md, "Fit: quality against cost"): grid resolution buys more
than steps for the same time (lego `fast` with a 192^3 last level: 29.17 dB in 68 s; with twice the steps at 128^3:
28.73 dB in 67 s), and a level needs enough steps to converge, but half the presets' steps lose less than one rung of
resolution does (lego `fast` with half its steps: 27.44 dB; at 96^3 with all of them: 26.96 dB). A grid finer than
the training photos have pixels across buys nothing (the bench's synthetic scene, trained on 200x150 photos: 128^3
34.38 dB, 192^3 34.98 dB, 256^3 35.36 dB with more steps than 192^3's 35.43; the demo, trained on 160x120: `fast`'s
128^3 34.75 dB, a 192^3 plan with fewer steps 34.69 dB). So the rule is: the finest rung of LADDER no finer than the
photos' longest side whose predicted time fits with at least MIN_SHARE of its steps, given as many steps as the time
allows up to MAX_SHARE of them (twice the steps bought lego `fast` 0.5 dB). A budget beyond that ends early.

The coarsest rungs start at 32^3: a first level's step marches its whole box, so it is the dearest step of a fit for
its voxels, and a 32^3 level finds the occupied space for a fraction of a 64^3 one's time (lego at 200x200, held out:
32->64->128 with 100+250+600 steps 30.31 dB in 27 s, 64->128 with 300+600 30.41 dB in 36 s; 32->64 with 100+200
25.63 dB in 4.5 s, 64 alone with 170 steps 25.53 dB in 8.8 s).
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib.util
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

from plenoxels import native
from plenoxels.cameras import Intrinsics, look_at
from plenoxels.grid import SparseGrid, sh_count
from plenoxels.scene_model import SceneModel
from plenoxels.train import Fitter, RaySet, coarse_start, pruning_rays

CACHE_VERSION = 4
# Resolutions the calibration times steps at (grids as pruning leaves a fit: about 50k, 230k and 520k voxels).
CALIBRATION_RESOLUTIONS = (64, 128, 192)
# Resolutions it times a first level's steps at: the whole box allocated, as a fit starts (33k, 262k and 885k voxels).
# Such a step marches every ray through the box with nothing to skip and nothing opaque to stop it: 2-4x a pruned
# grid's step of as many voxels (64^3: 85 ms against 14 ms for the surface grid's 50k voxels).
DENSE_RESOLUTIONS = (32, 64, 96)
DENSE_STEPS = 4  # timed steps at each (a new 96^3 grid's step takes about 0.15 s)
CALIBRATION_WARMUP = 2
CALIBRATION_STEPS = 8
# Rounds of CALIBRATION_STEPS a cached calibration's first step is timed again in (see calibrate).
RETIME_ROUNDS = 2
# The calibration's cameras: this many views of this many pixels a side, around the synthetic object.
CALIBRATION_VIEWS = 24
CALIBRATION_SIDE = 64

# Shares of a rung's steps a plan may give: at least MIN_SHARE (a level needs enough steps to converge), at most
# MAX_SHARE (past it, time goes further in a finer grid).
MIN_SHARE = 0.5
MAX_SHARE = 2.0
# Priors for the share of a level's voxels that pruning keeps, until a level change has measured it: the first prune
# (of a first level's whole box) by the scene type, and later ones (of grids pruned before: the demo's last prune keeps
# 50%). An object's or a forward capture's box is mostly air in front of and around thin surfaces (the demo object
# keeps 10-25%); an unbounded scene's box is the room the cameras stand in, seen from every side, and keeps most of
# itself (fox 80%, cup 78%, the synthetic unbounded scene 58%). Too high a prior picks a coarser plan than the time
# allows (re-plans then give it more steps), too low a finer one (re-plans then give it fewer: a fox 2-minute budget
# planned 128->256 on the object's prior and ran a third of its steps).
FIRST_KEEP_PRIOR = {"object": 0.2, "forward": 0.2, "unbounded": 0.75}
LATER_KEEP_PRIOR = 0.6
# Re-plan every this many steps; a level's step time is the mean of its latest STEP_WINDOW, after its first few.
REPLAN_EVERY = 20
STEP_WINDOW = 100
LEVEL_WARMUP = 3
# Re-plans aim this share of the budget short of the deadline, so that noise in the step times ends the schedule
# before the deadline's stop does (which would cut the last level's learning-rate decay short).
SLACK = 0.02
# A last level too dear for half its steps is lowered this many vertices at a time (see replan), in a scene whose
# first prune kept more than FULL_BOX of its box: a room seen from inside (fox 91-97%, cup 78-89%, the synthetic
# unbounded scene 67%), not an object on a backdrop (lego 15-20%, the demo object 10-25%).
LOWER_BY = 16
FULL_BOX = 0.5


@dataclass(frozen=True)
class Rung:
    """A candidate schedule: the resolution of each level and its steps at a share of 1."""
    resolutions: tuple[int, ...]
    steps: tuple[int, ...]
    fixed: int = 0
    """Leading levels whose steps stay as they are whatever the share (a first level's early prune)."""

    def scaled(self, share: float) -> list[int]:
        return [n if level < self.fixed else max(1, round(share * n)) for level, n in enumerate(self.steps)]


def _pruned_early(resolutions: tuple[int, ...], steps: tuple[int, ...]) -> Rung:
    """A rung whose first level prunes after a fifth of its steps, as the presets' do, and goes on at the same
    resolution: the prune comes after that many steps whatever the share, as what a grid keeps after fewer is still
    diffuse."""
    early = steps[0] // 5
    return Rung((resolutions[0],) + resolutions, (early, steps[0] - early) + steps[1:], fixed=1)


# Candidate schedules, coarse to fine, at the presets' step counts: the presets' levels (fast 64->128, balanced
# 96->192, default 128->256, quality 128->256->384) and rungs between them made the same way, each first level pruned
# early as the presets' are (a first level's steps march its whole box until a prune clears it: lego `default` 31.19 dB
# in 246 s without, 31.24 dB in 216 s with); at the bottom, two that start at 32^3 (see the module's docstring), 32->64
# being what a budget too short for any plan gets. A share scaled the early prune too in an earlier form of these rungs,
# down to 73-132 steps, and what a grid keeps after so few steps is still diffuse: more voxels than the plan assumed
# (22-25% of the box against 15% at lego `default`'s step 200) and a finer grid twice the size (lego at 400x400: 1 min
# 27.81 dB, 2 min 28.84 dB, against 28.41 and 29.88 dB with no early prune); hence `fixed`.
LADDER = (
    Rung((32, 64), (300, 600)),
    Rung((48, 96), (500, 1000)),
    Rung((32, 64, 128), (250, 500, 1000)),
    _pruned_early((64, 128), (500, 1000)),
    _pruned_early((80, 160), (600, 1200)),
    _pruned_early((96, 192), (750, 1500)),
    _pruned_early((112, 224), (900, 1500)),
    _pruned_early((128, 256), (1000, 1500)),
    _pruned_early((128, 256, 320), (1000, 1500, 1500)),
    _pruned_early((128, 256, 384), (1000, 1500, 1500)),
)


# ---- the cost model and its calibration --------------------------------------------------------------------------
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
    """Seconds per voxel of the new grid at a level change, beyond its pruning pass (upsampling, optimiser state)."""
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
        "tv_sample_fraction", "prune_ray_scale", "prune_rays_per_cell")}
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
    lo, hi = model.grid.bbox_min, model.grid.bbox_max
    axes = [torch.linspace(lo[a], hi[a], shape[a]) for a in range(3)]
    voxel = max((hi[a] - lo[a]) / (shape[a] - 1) for a in range(3))
    y, z = torch.meshgrid(axes[1], axes[2], indexing="ij")
    distance = torch.stack([_surface_distance(torch.stack([torch.full_like(y, float(x)), y, z], dim=-1))
                            for x in axes[0]])  # a slab at a time: little memory at any resolution
    keep = distance.abs() < 3 * voxel
    links = torch.full(shape, -1, dtype=torch.int32)
    count = int(keep.sum())
    links[keep] = torch.arange(count, dtype=torch.int32)
    density = 300.0 * torch.sigmoid(-distance[keep] / voxel) - 10.0
    sh = torch.randn(count, 3 * sh_count(sh_degree), generator=torch.Generator().manual_seed(0)) * 0.3
    return SparseGrid.from_values(links, density, sh, lo, hi, sh_degree)


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
    per-voxel cost and predict a finer grid's steps many times slower than they run (bench/README.md, session 27)."""
    voxels, seconds = np.array([p[0] for p in points], dtype=np.float64), np.array([p[1] for p in points])
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
        self.model_options = dataclasses.replace(options, ndc="off", background="on" if background else "off")
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
            dense_resolutions=DENSE_RESOLUTIONS) -> dict:
    """Times the real Fitter with these options (and a background model of `background`'s n_spheres and width) on
    the calibration object: steps and a pruning pass at each resolution, steps of a new model's grid (a first level)
    at each dense resolution, then one level change. Returns the cost model's fields and what was measured."""
    started = time.perf_counter()
    calibration = CalibrationObject(options, device, background, resolutions[0])
    fitter_at, views = calibration.fitter_at, calibration.views
    rays = {r: pruning_rays(views.sizes, r, options) for r in resolutions}
    points, passes = [], []
    for resolution in resolutions:
        fitter = fitter_at([resolution])
        points.append((fitter.model.grid.num_occupied, _time_steps(fitter, device)))
        _sync(device)
        begun = time.perf_counter()
        fitter.measure_weights()
        _sync(device)
        passes.append((rays[resolution] * resolution, time.perf_counter() - begun))
        del fitter
    fixed, slope = _line(points)
    dense_points = []
    for resolution in dense_resolutions:
        fitter = fitter_at([resolution], first=True)
        dense_points.append((fitter.model.grid.num_occupied, _time_steps(fitter, device, DENSE_STEPS)))
        del fitter
    dense_fixed, dense_slope = _line(dense_points)
    pass_fixed, pass_per_ray = _line(passes)

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
    new_voxels = fitter.model.grid.num_occupied
    upsampled = _time_steps(fitter, device)
    return {
        "costs": {"step_fixed": fixed, "step_per_voxel": slope,
                  "pass_fixed": pass_fixed, "pass_per_ray": pass_per_ray,
                  "change_per_voxel": max(0.0, change - pass_fixed
                                          - pass_per_ray * rays[resolutions[0]] * resolutions[0]) / new_voxels,
                  "checkpoint_per_voxel": checkpoint / new_voxels, "save_per_voxel": save / new_voxels,
                  "dense_fixed": dense_fixed, "dense_per_voxel": dense_slope,
                  "upsampled_ratio": upsampled / (fixed + slope * new_voxels)},
        "points": [{"resolution": r, "voxels": n, "step_seconds": round(t, 5)}
                   for r, (n, t) in zip(resolutions, points)],
        "first_level_points": [{"resolution": r, "voxels": n, "step_seconds": round(t, 5)}
                               for r, (n, t) in zip(dense_resolutions, dense_points)],
        "passes": [{"resolution": r, "rays": rays[r], "seconds": round(t, 5)}
                   for r, (_, t) in zip(resolutions, passes)],
        "level_change": {"voxels": new_voxels, "seconds": round(float(change), 4), "step_seconds": round(upsampled, 5),
                         "checkpoint_seconds": round(float(checkpoint), 4), "save_seconds": round(float(save), 4)},
        "seconds": round(time.perf_counter() - started, 2),
        "load_average": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
        "when": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }


def calibrate(options, device: torch.device, background: dict | None = None, resolutions=CALIBRATION_RESOLUTIONS,
              dense_resolutions=DENSE_RESOLUTIONS, say: Callable[[str], None] | None = None) -> tuple[CostModel, dict]:
    """The cost model for these options on this machine: from the cache when its key matches, with its times scaled by
    how much longer the calibration's first step takes now (the faster of RETIME_ROUNDS timings) than it did (a shared
    host's speed drifts: 1.2x within an hour on the 2-core one the benches ran on, and a plan from a calibration made
    at a fast moment starves its last level), else measured (a few seconds) and cached. Returns it and the
    calibration's record, with `cached`, `file` and `slower_now` (that scale; 1 for a calibration just measured)
    added."""
    key = calibration_key(options, device, background, resolutions, dense_resolutions)
    path = cache_dir() / f"fit-cost-{hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]}.json"
    try:
        record = json.loads(path.read_text())
        if record.get("key") == key:
            reference = record["points"][0]
            fitter = CalibrationObject(options, device, background, reference["resolution"]).fitter_at(
                [reference["resolution"]])
            # The faster of two rounds: the first can pay for faulting in the new grid's tables, or catch the host
            # at a slow moment, and one such round scaled a lego 1-minute plan by 1.55 when its steps then ran at
            # 0.9 of the model.
            slower = min(_time_steps(fitter, device) for _ in range(RETIME_ROUNDS)) / reference["step_seconds"]
            return (CostModel(**record["costs"]).scaled(slower),
                    {**record, "cached": True, "file": str(path), "slower_now": round(slower, 3)})
    except (OSError, ValueError, TypeError, KeyError, ZeroDivisionError):
        pass  # none yet, or unreadable: measure
    if say is not None:
        say(f"measuring what the fit costs on this machine ({key['device']}, {key['threads']} threads; once, then "
            f"cached in {path.parent})")
    record = {"key": key, **measure(options, device, background, resolutions, dense_resolutions)}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(record, indent=2))
        tmp.replace(path)
    except OSError:
        pass  # an unwritable cache: measure again next time
    return CostModel(**record["costs"]), {**record, "cached": False, "file": str(path), "slower_now": 1.0}


# ---- predictions and plans ----------------------------------------------------------------------------------------
@dataclass
class FitFacts:
    """What a prediction needs to know of the fit besides its schedule."""
    box_voxels: Callable[[int], int]   # vertices of a first level's grid (its whole box) at a resolution
    prune_rays: Callable[[int], int]   # rays of a pruning pass at a resolution
    eval_rays: int                     # rays of one held-out evaluation (0: none)
    eval_every: int
    checkpoint_every: float
    voxel_budget: int
    max_resolution: int = 1 << 30      # the finest final resolution worth fitting: the photos' longest side
    first_keep: float = FIRST_KEEP_PRIOR["object"]  # the first prune's kept share until it is measured (by scene type)

    def outlook(self, **where) -> "Outlook":
        """The state of a fit of this scene at `where`, with the scene's prior for what the first prune keeps."""
        return Outlook(**{"first_keep": self.first_keep, **where})


@dataclass
class Outlook:
    """Where the fit stands and what it has measured: the state a prediction starts from."""
    level: int = 0
    step: int = 0
    voxels: int = 0                    # of the current grid
    dense: bool = True                 # the current grid is a first level's (nothing pruned yet)
    step_seconds: float | None = None  # measured at the current level
    step_ratio: float = 1.0            # for later levels: this scene's measured step time over the model's
    ratio_at_first: bool = True        # step_ratio is the first resolution's (or a prior): not yet of an upsampled grid
    change_ratio: float = 1.0          # this scene's measured level changes (and their checkpoints) over the model's
    eval_ratio: float = 1.0            # this scene's measured held-out evaluations over the model's
    first_keep: float = FIRST_KEEP_PRIOR["object"]
    later_keep: float = LATER_KEEP_PRIOR


def finish_seconds(costs: CostModel, facts: FitFacts, now: Outlook, resolution: int, voxels: float,
                   stop: bool = False) -> float:
    """The end of a fit at this resolution and size: the last pruning pass (of a pruned grid, as the calibration's
    are, at the ratio this scene's held-out renders through the same grid measured against the model), the held-out
    PSNR and the save; after a `stop`, the checkpoint the stop writes first."""
    return (now.eval_ratio * costs.pass_seconds(facts.prune_rays(resolution), resolution)
            + costs.save_per_voxel * voxels
            + now.eval_ratio * costs.pass_seconds(facts.eval_rays, resolution)
            + (costs.checkpoint_per_voxel * voxels if stop else 0.0))


def predict(costs: CostModel, facts: FitFacts, now: Outlook, resolutions: list[int], steps: list[int]) -> float:
    """Seconds from where the fit stands to its end for this schedule, whose levels before `now.level` are done."""
    seconds, voxels, start, remaining = 0.0, float(now.voxels), sum(steps[:now.level]), 0
    # A level at another resolution than the first starts from an upsampled grid, whose steps the calibration measured
    # at costs.upsampled_ratio of its model, until this scene's steps at such a level have been measured.
    upsampled = now.step_ratio * (costs.upsampled_ratio if now.ratio_at_first else 1.0)
    for level in range(now.level, len(resolutions)):
        ratio = now.step_ratio if resolutions[level] == resolutions[0] else upsampled
        if level == now.level:
            step = now.step_seconds or ratio * costs.step_seconds(voxels, dense=now.dense)
        else:
            kept = (now.first_keep if level == 1 else now.later_keep) * voxels
            voxels = min(facts.voxel_budget, kept * (resolutions[level] / resolutions[level - 1]) ** 3)
            seconds += now.change_ratio * (costs.pass_seconds(facts.prune_rays(resolutions[level - 1]),
                                                              resolutions[level - 1])
                                           + (costs.change_per_voxel + costs.checkpoint_per_voxel) * voxels)
            step = ratio * costs.step_seconds(voxels)
        end = start + steps[level]
        first = max(start, now.step)
        seconds += (end - first) * step
        remaining += end - first
        if facts.eval_every and facts.eval_rays:
            evaluations = end // facts.eval_every - first // facts.eval_every
            seconds += evaluations * now.eval_ratio * costs.pass_seconds(facts.eval_rays, resolutions[level])
        start = end
    checkpoints = min(remaining, math.floor(seconds / facts.checkpoint_every))  # at most one a step
    seconds += checkpoints * costs.checkpoint_per_voxel * voxels
    return seconds + finish_seconds(costs, facts, now, resolutions[-1], voxels)


def _largest_share(fits: Callable[[float], bool], low: float, high: float) -> float | None:
    """The largest share in [low, high] for which `fits` holds (which then holds for every smaller share)."""
    if not fits(low):
        return None
    if fits(high):
        return high
    for _ in range(30):
        middle = (low + high) / 2
        low, high = (middle, high) if fits(middle) else (low, middle)
    return low


@dataclass
class Plan:
    resolutions: list[int]
    steps: list[int]
    share: float       # of the rung's steps
    predicted: float   # seconds from when it was made to the end of the fit
    fits: bool         # whether it fits with at least MIN_SHARE of its steps

    def describe(self) -> str:
        levels = f"{len(self.resolutions)} level{'s' if len(self.resolutions) > 1 else ''}"
        return f"{levels} {'->'.join(map(str, self.resolutions))}, {'+'.join(map(str, self.steps))} steps"


def _finest_first(ladder) -> list[Rung]:
    return sorted(ladder, key=lambda r: (r.resolutions[-1], len(r.resolutions)), reverse=True)


def choose(seconds: float, costs: CostModel, facts: FitFacts, ladder: tuple[Rung, ...] | None = None) -> Plan:
    """The plan for a fit that has not started: the finest rung (no finer than `facts.max_resolution`) whose predicted
    time fits `seconds` with at least MIN_SHARE of its steps, with the most steps that fit up to MAX_SHARE (of rungs
    ending at the same resolution, the one that gets the largest share); when none fits, the coarsest rung with the
    steps that fit (at least one a level)."""
    ladder = _finest_first(ladder or LADDER)
    ladder = [r for r in ladder if r.resolutions[-1] <= facts.max_resolution] or ladder[-1:]

    def seconds_for(rung: Rung, share: float) -> float:
        now = facts.outlook(voxels=facts.box_voxels(rung.resolutions[0]))
        return predict(costs, facts, now, list(rung.resolutions), rung.scaled(share))

    def plan(rung: Rung, share: float) -> Plan:
        return Plan(list(rung.resolutions), rung.scaled(share), share, seconds_for(rung, share), share >= MIN_SHARE)

    for finest in sorted({r.resolutions[-1] for r in ladder}, reverse=True):
        shares = [(share, rung) for rung in ladder if rung.resolutions[-1] == finest
                  for share in [_largest_share(lambda s: seconds_for(rung, s) <= seconds, MIN_SHARE, MAX_SHARE)]
                  if share is not None]
        if shares:
            share, rung = max(shares, key=lambda pair: pair[0])  # the first of equal shares: ladder order
            return plan(rung, share)
    coarsest = ladder[-1]
    return plan(coarsest, _largest_share(lambda s: seconds_for(coarsest, s) <= seconds, 0.0, MIN_SHARE) or 0.0)


def replan(seconds: float, costs: CostModel, facts: FitFacts, now: Outlook, rung: Rung, resolutions: list[int],
           steps: list[int], measured: bool) -> tuple[list[int], list[int], float]:
    """(resolutions, steps, share) for a fit under way, the levels done kept: the most steps (a share of the rung's,
    at most MAX_SHARE) whose predicted time fits `seconds`. A level still to come is dropped when keeping it would leave
    less than MIN_SHARE of the steps: with `measured` costs (once the fit has left its first resolution) any such level;
    before that only one past the second resolution, as what pruning keeps is still a prior and a first resolution
    alone, pruned early or not, is never a whole fit. Without that, a first level gives up the steps a level dropped later would have needed (fox, 5-minute
    budget: 128->256->384 planned at half its steps, 256 of 1000 first-level steps run, then 384 dropped at the level
    change). A level is not dropped where the levels before it, at MAX_SHARE, would end the fit early: it stays, with
    what fits (lego, 30-second budget: 128 dropped at step 180 of 32->64->128, 64^3 at twice its steps, 25.42 dB in
    21 s). When no schedule gets MIN_SHARE, the fewest levels allowed get what fits.

    In a scene whose first prune kept more than FULL_BOX of its box, a last level not yet started that would get less
    than MIN_SHARE of its steps (and is not dropped) is lowered, by LOWER_BY, to the finest resolution that gets
    MIN_SHARE: the rule the plan was chosen by, now on the scene's own costs. Such a scene's finer levels cost about
    twice what the calibration's object predicts, and a finer grid short of steps loses to a coarser one with them
    (fox, 2-minute budget, 112->112->224 planned: 25.79 dB at 224, 26.15 dB lowered to 160; on fox no grid past 192^3
    wins at any time). On an object it is the other way round (lego, 2 minutes: 29.82 dB at 224 short of steps, 29.51
    dB lowered to 208), so there the resolution stays the plan's (bench/README.md, "Session 22")."""
    chosen = _replan_levels(seconds, costs, facts, now, rung, resolutions, steps, measured)
    if (chosen[2] >= MIN_SHARE or len(chosen[0]) < len(resolutions) or now.level >= len(resolutions) - 1
            or now.dense or now.first_keep <= FULL_BOX):
        return chosen
    for last in range(resolutions[-1] - LOWER_BY, resolutions[-2], -LOWER_BY):
        lowered = _replan_levels(seconds, costs, facts, now, rung, resolutions[:-1] + [last], steps, measured)
        if lowered[2] >= MIN_SHARE and len(lowered[0]) == len(resolutions):
            return lowered
    return chosen


def _replan_levels(seconds: float, costs: CostModel, facts: FitFacts, now: Outlook, rung: Rung,
                   resolutions: list[int], steps: list[int], measured: bool) -> tuple[list[int], list[int], float]:
    done = now.step - sum(steps[:now.level])

    def schedule(share: float, levels: int) -> list[int]:
        new = rung.scaled(share)[:levels]
        new[:now.level] = steps[:now.level]
        new[now.level] = max(done, new[now.level])
        return new

    def fits(levels: int) -> Callable[[float], bool]:
        return lambda s: predict(costs, facts, now, resolutions[:levels], schedule(s, levels)) <= seconds

    # A first level pruned early goes on at its resolution: the second level is then the one after that.
    second = next((level + 1 for level, r in enumerate(resolutions) if r != resolutions[0]), len(resolutions))
    fewest = now.level + 1 if measured else min(len(resolutions), max(now.level + 1, second))
    for levels in range(len(resolutions), fewest - 1, -1):
        share = _largest_share(fits(levels), MIN_SHARE, MAX_SHARE)
        if share is None:
            continue
        if levels < len(resolutions) and share >= MAX_SHARE:  # the fit would end early: the level stays, short
            levels += 1
            share = _largest_share(fits(levels), 0.0, MIN_SHARE) or 0.0
        return resolutions[:levels], schedule(share, levels), share
    share = _largest_share(fits(fewest), 0.0, MIN_SHARE) or 0.0
    return resolutions[:fewest], schedule(share, fewest), share


# ---- the budget of one fit ----------------------------------------------------------------------------------------
class TimeBudget:
    """Plans a fit to end by `started + seconds` and keeps it on time.

    Made before the Fitter, whose options are then `options` (the fit's, with the plan's levels and steps), and
    `attach`ed to it once it exists (resumed or new). While it runs, the caller calls `step()` after each step and
    `level()` after each level change, wraps held-out evaluations in `timed`, and stops the fit when `due()`.
    `line()` says what was chosen and why; `record()` says it all, for fit.json.
    """

    def __init__(self, seconds: float, options, new_model: Callable[[int], SceneModel], train: RaySet,
                 eval_rays: int, device: torch.device, started: float, plan_file: Path | None = None,
                 resume: bool = False, say: Callable[[str], None] | None = None,
                 ladder: tuple[Rung, ...] | None = None):
        """`new_model(resolution)` makes the fit's first model (its box and background are what a plan needs)."""
        self.seconds, self.started, self.plan_file = float(seconds), started, plan_file
        self.deadline = started + self.seconds
        scale = options.first_level_scale
        ladder = tuple(dataclasses.replace(rung, resolutions=tuple(coarse_start(rung.resolutions, scale)))
                       for rung in ladder or LADDER)
        probe = new_model(8)  # an 8^3 grid: kept, as its shape at each resolution sets a pruning pass's rays
        firsts = {rung.resolutions[0] for rung in ladder}
        box_voxels = {r: int(np.prod(probe.resolution_for(r))) for r in firsts}
        background = probe.background.config() if probe.background is not None else None
        self.facts = FitFacts(box_voxels=box_voxels.__getitem__, eval_rays=eval_rays,
                              prune_rays=functools.lru_cache(maxsize=None)(
                                  lambda r: pruning_rays(train.sizes, max(probe.resolution_for(r)), options)),
                              eval_every=options.eval_every, checkpoint_every=options.checkpoint_every,
                              voxel_budget=options.voxel_budget, max_resolution=int(train.sizes.max()),
                              first_keep=FIRST_KEEP_PRIOR[probe.scene_type])
        background = background and {"n_spheres": background["n_spheres"], "width": background["width"]}
        self.costs, self.calibration = calibrate(options, device, background, say=say)
        saved = json.loads(plan_file.read_text()) if resume and plan_file is not None and plan_file.is_file() else None
        if saved is not None:  # a resumed fit keeps the plan its checkpoint was made with
            self.rung = Rung(tuple(saved["rung"]["resolutions"]), tuple(saved["rung"]["steps"]),
                             saved["rung"].get("fixed", 0))
            self.plan = Plan(**saved["plan"])
            resolutions, steps = saved["resolutions"], saved["steps"]
        else:
            self.plan = choose(self.left(), self.costs, self.facts, ladder)
            self.rung = next(r for r in ladder if list(r.resolutions) == self.plan.resolutions)
            resolutions, steps = self.plan.resolutions, self.plan.steps
        self.options = dataclasses.replace(options, resolutions=list(resolutions), steps=list(steps))
        self.now = self.facts.outlook()
        self.fitter: Fitter | None = None
        self.replans: list[dict] = []          # at each level change, and the latest one within each level
        self.level_seconds: list[float] = []   # the step time measured at each level
        self._intervals: list[float] = []      # the current level's latest step times
        self._last = time.perf_counter()
        self._eval_seconds = 0.0               # of held-out evaluations since the last step
        self._save_plan()

    def left(self) -> float:
        return self.deadline - time.time()

    def attach(self, fitter: Fitter) -> None:
        """Follows `fitter` from here; a resumed fit has already used `fitter.elapsed` of the budget, and its level
        changes have measured what its prunes keep."""
        self.fitter = fitter
        self.deadline = self.started + self.seconds - fitter.elapsed
        start = sum(self.options.steps[:fitter.level])
        self.options.steps[fitter.level] = max(self.options.steps[fitter.level], fitter.step - start)
        kept = [_kept_share(entry) for entry in fitter.levels]
        measured = {"first_keep": kept[0]} if kept else {}
        if len(kept) > 1:
            measured["later_keep"] = kept[-1]
        self.now = self.facts.outlook(level=fitter.level, step=fitter.step, voxels=fitter.model.grid.num_occupied,
                                      dense=not fitter.levels, **measured)
        self._last = time.perf_counter()

    def due(self) -> bool:
        """True when what is left of the budget is what it takes to end the fit as it stands (the stop's checkpoint,
        the last pruning pass, the held-out PSNR and the save)."""
        resolution = self.options.resolutions[self.fitter.level]
        return self.left() <= finish_seconds(self.costs, self.facts, self.now, resolution, self.now.voxels, stop=True)

    def step(self) -> None:
        """After each step: its time (held-out evaluations left out), and a re-plan every REPLAN_EVERY steps."""
        clock = time.perf_counter()
        interval, self._last, self._eval_seconds = clock - self._last - self._eval_seconds, clock, 0.0
        if self.fitter.step - sum(self.options.steps[:self.fitter.level]) > LEVEL_WARMUP:
            self._intervals = (self._intervals + [interval])[-STEP_WINDOW:]
        if self.fitter.step % REPLAN_EVERY == 0 and len(self._intervals) >= 5:
            measured = float(np.mean(self._intervals))
            ratio = measured / self.costs.step_seconds(self.now.voxels, dense=self.now.dense)
            # A grid at the first resolution, pruned early or not, is still clearing: cheaper than what comes after it
            # (lego 1- to 4-minute budgets: 0.86-1.04 of the model there, 1.28-1.6 at the last level).
            self.now.ratio_at_first = self._at_first_resolution()
            self.now.step_ratio = max(1.0, ratio) if self.now.ratio_at_first else ratio
            self.now.step_seconds = measured
            self._replan("steps")

    def level(self) -> None:
        """After a level change: what it took, the share pruning kept, the new grid; then a re-plan."""
        fitter = self.fitter
        change, self._eval_seconds = time.perf_counter() - self._last - self._eval_seconds, 0.0
        entry = fitter.levels[-1]
        before = self.options.resolutions[fitter.level - 1]
        predicted = (self.costs.pass_seconds(self.facts.prune_rays(before), before)
                     + (self.costs.change_per_voxel + self.costs.checkpoint_per_voxel) * entry["occupied"])
        self.now.change_ratio = change / max(predicted, 1e-9)
        kept = _kept_share(entry)
        if self.now.dense:
            self.now.first_keep = kept
        else:
            self.now.later_keep = kept
        if self._intervals:
            self.level_seconds.append(round(float(np.mean(self._intervals)), 5))
        self.now.level, self.now.voxels, self.now.dense = fitter.level, entry["occupied"], False
        self.now.step_seconds = None
        self._intervals = []
        self._last = time.perf_counter()
        self._replan("level change")

    def timed(self, evaluate: Callable[[SceneModel], float]) -> Callable[[SceneModel], float]:
        """`evaluate` (a held-out evaluation), timed: kept out of the step times, and what later ones will take."""
        def run(model: SceneModel) -> float:
            begun = time.perf_counter()
            value = evaluate(model)
            took = time.perf_counter() - begun
            self._eval_seconds += took
            if self.facts.eval_rays:
                self.now.eval_ratio = took / max(self.costs.pass_seconds(self.facts.eval_rays,
                                                                         max(model.grid.resolution)), 1e-9)
            return value
        return run

    def _at_first_resolution(self) -> bool:
        """Whether the fit is still at its first level's resolution (its early-pruned rest included)."""
        return self.options.resolutions[self.fitter.level] == self.options.resolutions[0]

    def _replan(self, why: str) -> None:
        self.now.step = self.fitter.step
        resolutions, steps, share = replan(self.left() - SLACK * self.seconds, self.costs, self.facts, self.now,
                                           self.rung, self.options.resolutions, self.options.steps,
                                           measured=not self._at_first_resolution())
        entry = {"why": why, "step": self.fitter.step, "seconds_left": round(self.left(), 1), "share": round(share, 3),
                 "steps": steps, "step_seconds": round(self.now.step_seconds or 0.0, 5)}
        if len(resolutions) < len(self.options.resolutions):
            entry["dropped_levels"] = self.options.resolutions[len(resolutions):]
        elif resolutions[-1] != self.options.resolutions[-1]:
            entry["lowered_last_level"] = [self.options.resolutions[-1], resolutions[-1]]
        # In place: the Fitter reads its schedule from these lists at every step (Fitter.run).
        self.options.resolutions[:] = resolutions
        self.options.steps[:] = steps
        # A steps-only re-plan replaces the one before it, unless either dropped or lowered a level (that stays in the
        # record).
        if (why == "steps" and self.replans and self.replans[-1]["why"] == "steps"
                and not {"dropped_levels", "lowered_last_level"} & (set(entry) | set(self.replans[-1]))):
            self.replans[-1] = entry
        else:
            self.replans.append(entry)
        self._save_plan()

    def _save_plan(self) -> None:
        if self.plan_file is None:
            return
        state = {"rung": dataclasses.asdict(self.rung), "plan": dataclasses.asdict(self.plan),
                 "resolutions": self.options.resolutions, "steps": self.options.steps}
        tmp = self.plan_file.with_name(self.plan_file.name + ".tmp")
        tmp.write_text(json.dumps(state))
        tmp.replace(self.plan_file)

    # ---- what it says -----------------------------------------------------------------------------------------
    def line(self) -> str:
        """'budget 90s: 2 levels 96->192, 600+900 steps, predicted 84 s from a calibration of ... on this machine'."""
        note = ""
        if not self.plan.fits:
            note = " (less than the coarsest plan needs: it stops at the deadline)"
        elif self.plan.share >= MAX_SHARE and not any(
                self.plan.resolutions[-1] < r.resolutions[-1] <= self.facts.max_resolution for r in LADDER):
            note = (f" (as fine as the {self.facts.max_resolution}-pixel photos are worth, with twice the steps: more "
                    f"time would not help)")
        slower = self.calibration.get("slower_now")
        cached = (f" (cached, scaled by {slower:.2f} to the machine's speed now)"
                  if self.calibration["cached"] and slower else "")
        return (f"budget {_duration(self.seconds)}: {self.plan.describe()}, predicted {self.plan.predicted:.0f} s"
                f"{note} from a calibration of {self.costs.describe()}{cached} on this machine")

    def record(self, stopped_at_deadline: bool) -> dict:
        latest = [round(float(np.mean(self._intervals)), 5)] if self._intervals else []
        return {
            "seconds": self.seconds, "line": self.line(),
            "why": (f"the finest candidate (plenoxels/budget.py LADDER) no finer than the photos' "
                    f"{self.facts.max_resolution} pixels whose predicted time fits with at least {MIN_SHARE:g}x its "
                    f"steps, given the most steps that fit, up to {MAX_SHARE:g}x"),
            "chosen": {**dataclasses.asdict(self.plan), "share": round(self.plan.share, 3),
                       "predicted": round(self.plan.predicted, 1)},
            "ran": {"resolutions": list(self.options.resolutions), "steps": list(self.options.steps)},
            "stopped_at_deadline": stopped_at_deadline,
            "step_seconds_per_level": self.level_seconds + latest,
            "scene_over_model": {"later_steps": round(self.now.step_ratio, 3),
                                 "level_change": round(self.now.change_ratio, 3),
                                 "held_out": round(self.now.eval_ratio, 3)},
            "kept_share": {"first_prune": round(self.now.first_keep, 4), "later_prunes": round(self.now.later_keep, 4),
                           "first_prune_prior": self.facts.first_keep},
            "replans": self.replans,
            "calibration": {"costs": dataclasses.asdict(self.costs), "points": self.calibration.get("points"),
                            "first_level_points": self.calibration.get("first_level_points"),
                            "passes": self.calibration.get("passes"),
                            "level_change": self.calibration.get("level_change"),
                            "cached": self.calibration["cached"], "file": self.calibration["file"],
                            "slower_now": self.calibration.get("slower_now"),
                            "key": self.calibration["key"], "measured_in_seconds": self.calibration.get("seconds"),
                            "load_average": self.calibration.get("load_average"),
                            "when": self.calibration.get("when")},
        }


def _kept_share(level_change: dict) -> float:
    """The share of the grid's voxels a level change's prune kept (one of Fitter.levels)."""
    return level_change["kept"] / max(1, level_change["pruned_from"])


def _duration(seconds: float) -> str:
    """90 -> '1m30s', 300 -> '5m', 45 -> '45s'."""
    minutes, rest = divmod(int(round(seconds)), 60)
    return f"{minutes}m{rest:02d}s" if minutes and rest else f"{minutes}m" if minutes else f"{rest}s"
