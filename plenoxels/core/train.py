"""The training loop: fits a SceneModel to the pixels of posed images, coarse to fine.

Each step renders a batch of rays (random pixels, or random square tiles of pixels, which keep the
kernel's memory reads local) and takes one sparse RMSProp step on MSE + TV; the background model, if
any, takes an Adam step. Both grid rates decay exponentially over the whole fit. TV weights are per
sampled vertex; a vertex's TV gradient does not shrink with the cell size while its MSE gradient does,
so the same weight bites harder on finer grids. At each level change vertices that no training ray
weighs (max rendering weight) or that hold no density are pruned, the survivors are dilated, and the
grid is upsampled within a voxel budget; the optimiser state follows the vertices.

A `Fitter` holds the state of one fit; `Fitter.run` steps it to the end of its schedule, writing
checkpoints (always from finite parameters) from which a new Fitter resumes on the same step and the
same batches. A loss or parameter that stops being finite raises `Diverged`.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import torch

from plenoxels.core.background import BackgroundOptimiser
from plenoxels.core.error_map import ErrorMap, block_side, kept_inside, measure_stride
from plenoxels.core.errors import UserError
from plenoxels.core.files import write_whole
from plenoxels.core.grid import SparseGrid, sh_count
from plenoxels.core.memory import voxels_that_fit
from plenoxels.core.optim import GridGrad, SparseRMSProp, decayed_lr, density_rate_scale
from plenoxels.core.options import TrainOptions
from plenoxels.core.photo_colour import (COLOUR_RAYS, DECIDING_MEASURES, PhotoColour, gain_field_lattice,
                                         gain_fields)
from plenoxels.core.ray_set import RaySet, lattice_pixels, random_backdrops
from plenoxels.core.regularizers import (sparsity_loss_and_grad, tv_loss_and_grad, tv_scale_for_resolution,
                                    tv_scale_for_views, views_per_point)
from plenoxels.core.render import (colour_error, floor_targets, loss_and_grad, loss_and_grad_before_spheres,
                                    max_weights, render)
from plenoxels.core.scene_model import SceneModel, psnr
from plenoxels.core.schedule import Schedule

# A render this opaque inside a photo's mask shows the object's colour, to measure the photo's gains against.
OPAQUE = 0.98
# The running train PSNR averages the MSE of this many recent steps.
LOSS_WINDOW = 50
# Parameters are checked for NaN/inf this often (and before every checkpoint); the loss every step.
GUARD_EVERY = 25
# Rays per call when measuring max weights for pruning.
RAY_CHUNK = 1 << 16


def pruning_stride(sizes: torch.Tensor, resolution: int, options: TrainOptions) -> int:
    """The pixel stride of a pruning pass over photos of these [N, 2] sizes on a grid of this resolution: the
    largest that still gives prune_rays_per_cell rays per face cell, no smaller than prune_ray_scale's."""
    densest = max(1, round(1 / options.prune_ray_scale))
    if options.prune_rays_per_cell <= 0:
        return densest
    pixels = float((sizes[:, 0].double() * sizes[:, 1].double()).sum())
    return max(densest, math.floor(math.sqrt(pixels / (options.prune_rays_per_cell * resolution ** 2))))


def pruning_rays(sizes: torch.Tensor, resolution: int, options: TrainOptions) -> int:
    """How many rays a pruning pass at this resolution marches (as RaySet.strided_rays takes them)."""
    stride = pruning_stride(sizes, resolution, options)
    return sum(lattice_pixels(h, w, stride) for h, w in sizes.tolist())


def prune_mask(grid: SparseGrid, weights: torch.Tensor, options: TrainOptions) -> torch.Tensor:
    """Rows to keep: weighed by some training ray and holding density, grown by the dilation."""
    keep = (weights > options.prune_weight) & (grid.density > options.prune_density)
    return grid.dilate(keep, options.prune_dilation)


def budget_mask(grid: SparseGrid, keep: torch.Tensor, weights: torch.Tensor, budget_rows: int) -> torch.Tensor:
    """Narrows `keep` to the `budget_rows` rows with the largest weights when it holds more."""
    if int(keep.sum()) <= budget_rows:
        return keep
    narrowed = torch.zeros_like(keep)
    narrowed[torch.topk(torch.where(keep, weights, torch.full_like(weights, -1.0)), budget_rows).indices] = True
    return narrowed


class Diverged(Exception):
    """The loss or the parameters stopped being finite."""


class Fitter:
    """The state of one fit: the model, its optimisers, the step counter and the history."""

    def __init__(self, model: SceneModel, options: TrainOptions, train: RaySet,
                 device: torch.device = torch.device("cpu"), schedule: Schedule | None = None):
        self.options, self.train, self.device = options, train.to(device), device
        self.schedule = schedule if schedule is not None else Schedule.as_set(options)
        self.model = model.to(device)
        self.generator = torch.Generator().manual_seed(options.seed)  # on the CPU for every device: one stream
        self.step = 0
        self.level = 0
        self.elapsed = 0.0                 # seconds of fitting so far, over every run that resumed it
        self.history: list[dict] = []      # held-out PSNR over time
        self.levels: list[dict] = []       # what happened at each level change
        self.recent_mse: list[float] = []
        self.background_seconds = 0.0       # of this run's steps, spent training the background (and drawing it, on a GPU)
        self.checkpoint_step: int | None = None
        self.regularisation = self._regularisation()
        mapped = (options.error_share > 0 or options.leave_out_transients) and options.batch_mode == "rays"
        # What moved is found on the colours' lattice, each measured pixel a block, where the map draws no rays.
        measured_rays = options.measure_rays if options.error_share > 0 else min(options.measure_rays, COLOUR_RAYS)
        self.measure_stride = measure_stride(train.sizes, measured_rays)
        side = block_side(self.measure_stride, draws=options.error_share > 0)
        self.error_map = ErrorMap(train.sizes, self.measure_stride, side) if mapped else None
        self.colour = PhotoColour(len(train))
        self.colour_measures: list[float] = []  # what the gains of each deciding measure brought (dB nearer)
        self.colour_decided = False  # whether those measures have decided if the photos differ in colour
        self.last_level_psnr: list[float] = []  # the running train PSNR after each step of the last level
        self.converged: dict | None = None      # where the last level converged and ended early
        self._new_optimiser()

    # ---- optimiser state ------------------------------------------------------------------------
    def _new_optimiser(self) -> None:
        o = self.options
        self.grad = GridGrad(self.model.grid)
        self.optim = SparseRMSProp(self.model.grid, o.lr_density, o.lr_sh, o.rmsprop_beta)
        self.bg_optim = (BackgroundOptimiser(self.model.background, o.lr_background, o.rmsprop_beta, seed=o.seed)
                         if self.model.background is not None else None)

    def _replace_grid(self, grid: SparseGrid, old_rows: torch.Tensor) -> None:
        self.optim.remap(grid, old_rows)
        self.model.grid = grid
        self.grad = GridGrad(grid)

    def _regularisation(self) -> dict:
        """The TV weights this capture gets: as set, grown where few training views see the grid's box (world grids;
        an NDC grid's box is not a region of the world, and the forward overlay sets its own weights)."""
        o = self.options
        record = {"tv_density": o.tv_density, "tv_sh": o.tv_sh, "views_per_point": None, "tv_scale": 1.0,
                  "sparsity": o.sparsity}
        if o.tv_views > 0 and self.model.fit_frame.ndc is None:
            lo, hi = self.model.region_box()
            views = views_per_point(self.train.c2w.double().cpu().numpy(), self.train.intrinsics, lo, hi, seed=o.seed)
            scale = tv_scale_for_views(views, o.tv_views, o.tv_views_power, o.tv_views_max_scale)
            record.update(views_per_point=round(views, 2), tv_scale=scale, tv_density=o.tv_density * scale,
                          tv_sh=o.tv_sh * scale)
        return record

    # ---- the loop -------------------------------------------------------------------------------
    def run(self, checkpoint: Path, checkpoint_every: float, stop_requested: Callable[[], bool] = lambda: False,
            held_out_psnr: Callable[[SceneModel], float] | None = None, eval_every: int = 0,
            on_step: Callable[[float], None] | None = None, on_level: Callable[[SparseGrid], None] | None = None,
            on_eval: Callable[[dict], None] | None = None) -> bool:
        """Steps from where the fit stands to the end of its schedule; returns whether `stop_requested()`
        ended it early. Writes `checkpoint` at each level change, every `checkpoint_every` seconds and when
        stopped; after a complete schedule prunes once more if the options say so. Every `eval_every`
        steps (0: never) appends `held_out_psnr(model)` to the history. Callbacks: `on_step(mse)` after each
        step, `on_level(grid)` after each level change, `on_eval(history entry)` after each evaluation.
        A KeyboardInterrupt writes a checkpoint (unless the parameters are no longer finite) and
        propagates; so does Diverged, leaving the last checkpoint, which was written from finite parameters.
        The schedule is consulted at every step, so its owner may change the levels not yet done (a time budget
        does, to end on time)."""
        started = time.monotonic() - self.elapsed
        last_save = time.monotonic()
        stopped = False
        try:
            while self.step < self.schedule.total_steps:
                if self.step == self.level_end(self.level):
                    self.next_level()
                    self.elapsed = time.monotonic() - started
                    self.save_checkpoint(checkpoint)
                    last_save = time.monotonic()
                    if on_level is not None:
                        on_level(self.model.grid)
                mse = self.train_step()
                self.end_if_converged()
                if on_step is not None:
                    on_step(mse)
                if eval_every and held_out_psnr is not None and self.step % eval_every == 0:
                    self.history.append({"step": self.step, "seconds": round(time.monotonic() - started, 1),
                                         "train_psnr": round(self.train_psnr(), 3),
                                         "held_out_psnr": round(held_out_psnr(self.model), 3)})
                    if on_eval is not None:
                        on_eval(self.history[-1])
                if time.monotonic() - last_save > checkpoint_every:
                    self.elapsed = time.monotonic() - started
                    self.save_checkpoint(checkpoint)
                    last_save = time.monotonic()
                if stop_requested():
                    stopped = True
                    break
        except KeyboardInterrupt:
            self.elapsed = time.monotonic() - started
            try:
                self.save_checkpoint(checkpoint)
            except Diverged:
                pass  # keep the earlier, finite checkpoint
            raise
        self.elapsed = time.monotonic() - started
        if stopped:
            self.save_checkpoint(checkpoint)
        elif self.options.prune_final:
            self.prune()
        return stopped

    # ---- one step ------------------------------------------------------------------------------
    def level_end(self, level: int) -> int:
        return self.schedule.level_end(level)

    def train_step(self) -> float:
        """One optimiser step on one batch; returns its MSE."""
        o = self.options
        progress, ramp = self.schedule.rate_progress(self.step, self.level, o.lr_per_level)
        density_rate = decayed_lr(o.lr_density, o.lr_density_final, progress, o.lr_density_delay if ramp else 0.0)
        self.optim.set_lr(density_rate * self.density_rate_scale(), decayed_lr(o.lr_sh, o.lr_sh_final, progress))
        if self.measures() and self.step > 0 and (self.step % o.measure_every == 0 or self.level_starts()):
            self.measure_photos()
        drawn = [t.to(self.device) for t in self.train.batch(
            o.batch_size, o.batch_mode, o.tile_size, self.generator, o.coherent_batches, self.own_backdrops,
            self.error_map, o.error_share, self.colour if self.fits_colour else None, self.empty_backdrop)]
        o_w, d_w, target, cover = *drawn[:3], (drawn[-1] if self.empty_backdrop else None)
        o_fit, d_fit = self.model.fit_frame.rays(o_w, d_w)
        near_gradient = 0.0 if self.model.fit_frame.ndc is not None else o.near_gradient_distance
        # On a CPU the grid's kernel draws the background spheres itself, only on the rays it lets light past (a ray
        # it stops shows nothing behind it). Elsewhere the background's optimiser renders the whole batch first; either
        # way it keeps where each ray met each sphere for its backward.
        spheres = self.bg_optim.on_rays(o_w, d_w) if self.bg_optim is not None and not self.own_backdrops else None
        if spheres is not None:
            mse, grad_background, background = loss_and_grad_before_spheres(
                self.model.grid, o_fit, d_fit, target, spheres, self.model.render_options, self.grad, near_gradient)
        else:
            started = time.perf_counter()
            if self.own_backdrops:
                background = drawn[3]
            else:
                background = (self.bg_optim.forward(o_w, d_w) if self.bg_optim is not None
                              else self.model.background_rgb(o_w, d_w))
            self.background_seconds += time.perf_counter() - started
            if cover is not None:
                background, target = random_backdrops(cover, background, target, o.covered_backdrop_share,
                                                      self.generator)
            mse, grad_background = loss_and_grad(self.model.grid, o_fit, d_fit, target, background,
                                                 self.model.render_options, self.grad, near_gradient=near_gradient,
                                                 past_grid_only=self.model.background_past_grid_only)
        if not math.isfinite(mse):
            raise Diverged(f"the loss became {mse}")
        tv_rows = max(1, round(o.tv_sample_fraction * self.model.grid.num_occupied))
        tv = self.regularisation
        weight = tv_rows * self.tv_level_scale()
        tv_loss_and_grad(self.model.grid, self.grad, tv["tv_density"] * weight, tv["tv_sh"] * weight,
                         o.tv_sample_fraction, self.generator)
        if self.schedule.resolutions[self.level] == self.schedule.resolutions[0]:
            sparsity_loss_and_grad(self.model.grid, self.grad, o.sparsity, o.tv_sample_fraction, self.generator)
        self.optim.step(self.grad)
        if self.bg_optim is not None:
            started = time.perf_counter()
            self.bg_optim.backward(o_w, d_w, background, grad_background)
            self.bg_optim.step()
            self.background_seconds += time.perf_counter() - started
        self.step += 1
        self.recent_mse = (self.recent_mse + [mse])[-LOSS_WINDOW:]
        if self.step % GUARD_EVERY == 0:
            self.check_finite()
        return mse

    def end_if_converged(self) -> None:
        """In the last level of a schedule that ends on convergence: once the running train PSNR rose less than its
        `converged_db` over the latest quarter of the level's steps (looked at from half of them on), the level is
        shortened to end a tenth of its steps from here. The learning rates decay over the whole schedule, so they
        fall to their final values over that tail, as they would have at the end."""
        schedule, last = self.schedule, len(self.schedule.steps) - 1
        if schedule.converged_db <= 0 or self.level != last or self.converged is not None:
            return
        done, listed = self.step - sum(schedule.steps[:last]), schedule.steps[last]
        window, tail = max(LOSS_WINDOW, listed // 4), max(1, listed // 10)
        self.last_level_psnr = (self.last_level_psnr + [self.train_psnr()])[-(window + 1):]
        if done < listed // 2 or len(self.last_level_psnr) <= window or done + tail >= listed:
            return
        gain = self.last_level_psnr[-1] - self.last_level_psnr[-1 - window]
        if gain < schedule.converged_db:
            schedule.steps[last] = done + tail
            self.converged = {"step": self.step, "gain_db": round(gain, 4), "window": window, "tail": tail,
                              "steps_listed": listed, "steps_saved": listed - done - tail}

    def level_starts(self) -> bool:
        """Whether this step is the first of a level after the first."""
        return self.level > 0 and self.step == self.level_end(self.level - 1)

    def measures(self) -> bool:
        """Whether this fit measures its photos against the render: for their colours or for its error map."""
        return self.error_map is not None or self.colour_deciding or self.fits_colour

    @property
    def own_backdrops(self) -> bool:
        """Whether each photo shows its own backdrop colour past the grid (RaySet.backdrops), not a background model."""
        return self.train.backdrops is not None and self.bg_optim is None

    @property
    def empty_backdrop(self) -> bool:
        """TrainOptions.empty_backdrop where it applies: an object's fit (no background model), every photo masked."""
        return self.options.empty_backdrop and self.train.cover is not None and self.model.background is None

    @property
    def backdrop_as_taken(self) -> bool:
        """Whether what lies past the object in the photos is as they were taken, given with them (the colour their
        masks put there, or each photo's own backdrop): the photos' gains are measured on the object alone."""
        return self.train.coverage is not None or self.own_backdrops

    def backdrops_in_common(self, image: torch.Tensor) -> torch.Tensor:
        """The own backdrop colours [B, 3] of photos `image`, in the common colour where the fit fits the photos'."""
        backdrops = self.train.backdrops[image]
        return self.colour.to_common(image, backdrops) if self.fits_colour else backdrops

    @property
    def colour_gain_db(self) -> float | None:
        """What the gains of the deciding measures brought the renders nearer the photos, on average (dB); None
        until they have decided."""
        if not self.colour_decided:
            return None
        return round(sum(self.colour_measures) / len(self.colour_measures), 3)

    @property
    def colour_deciding(self) -> bool:
        """Whether the fit is asked to fit its photos' colours and is still measuring whether they differ (the photos
        are trained as they are meanwhile)."""
        return self.options.photo_colour and self.colour_gain_db is None

    @property
    def fits_colour(self) -> bool:
        """Whether this fit fits its photos' colours: asked to (photo_colour), and the gains of its deciding measures
        brought the renders at least photo_colour_min_db nearer the photos on average."""
        measured = self.colour_gain_db
        return self.options.photo_colour and measured is not None and measured >= self.options.photo_colour_min_db

    def measure_photos(self) -> None:
        """Renders an even lattice of every training photo's pixels with the model as it stands; fits the photos'
        colours where the options say so, and measures the error map against the photos in their common colour."""
        image, row, col = self.train.lattice(self.measure_stride)
        rendered, photo, opacity = self.render_pixels(image, row, col)
        pixels = [t.to(self.device) for t in (image, row, col)]
        inside, put_in = (None if t is None else t.cpu() for t in (self.train.inside(*pixels), self.train.put_in(*pixels)))
        if self.backdrop_as_taken:
            # Where the render is still partly the backdrop, its colour is not yet the object's.
            inside = (opacity > OPAQUE) & (True if inside is None else inside)
        inside = kept_inside(self.error_map, image, row, col, inside)
        if self.colour_deciding:
            # Measured against the photos as they are, which the field has been trained on: gains it has not learnt.
            self.colour.fit(image, rendered, photo, inside)
            self.colour_measures.append(round(self.colour.gain_db(image, rendered, photo, inside), 3))
            # DECIDING_MEASURES of them, or as many as a short fit has taken by its last level.
            self.colour_decided = (len(self.colour_measures) >= DECIDING_MEASURES
                                   or self.level >= len(self.schedule.resolutions) - 1)
            if self.colour_decided and not self.fits_colour:  # the photos agree on colour: as they are
                self.colour = PhotoColour(len(self.train))
                self.train.coverage = self.train.behind = None
        elif self.fits_colour:
            self.colour.fit(image, rendered, photo, inside)
        if self.error_map is not None:
            common = self.colour.to_common(image, photo, put_in) if self.fits_colour else photo
            targets = floor_targets(common, self.train.floors_at(self.train.flat(*pixels)).cpu())
            self.error_map.measure(image, row, col, colour_error(rendered, targets))
            if self.options.leave_out_transients and self.level > 0:
                self.error_map.find_transients()

    def gain_fields(self) -> torch.Tensor | None:
        """Each training photo's gains across its frame [P, rows, cols, 3] against the model as it stands, measured
        (photo_colour.gain_fields, on gain_field_lattice's pixels); None where the fit takes the photos as they are
        or measures one gain a photo (photo_colour_cells 1)."""
        if not self.fits_colour or self.options.photo_colour_cells <= 1:
            return None
        shape, stride = gain_field_lattice(self.train.sizes, self.options.photo_colour_cells)
        image, row, col = self.train.lattice(stride)
        rendered, photo, opacity = self.render_pixels(image, row, col)
        inside = self.train.inside(*(t.to(self.device) for t in (image, row, col)))
        inside = None if inside is None else inside.cpu()
        if self.backdrop_as_taken:
            inside = (opacity > OPAQUE) & (True if inside is None else inside)
        return gain_fields(image, row, col, self.train.sizes.cpu(), rendered, photo, self.colour.gain, shape,
                           kept_inside(self.error_map, image, row, col, inside))

    def gain_field_rays(self) -> int:
        """Rays gain_fields renders at the fit's end, which a budget keeps time for (0: photos taken as they are)."""
        if not (self.fits_colour or self.colour_deciding) or self.options.photo_colour_cells <= 1:
            return 0
        stride = gain_field_lattice(self.train.sizes, self.options.photo_colour_cells)[1]
        return int(((self.train.sizes + stride - 1 - stride // 2) // stride).prod(dim=1).sum())

    def render_pixels(self, image: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The render, the photo's colour [B, 3] and the render's opacity [B] at these training pixels, on the CPU."""
        rendered, photo, opacity = [], [], []
        for start in range(0, image.shape[0], RAY_CHUNK):
            i, r, c = (t[start:start + RAY_CHUNK].to(self.device) for t in (image, row, col))
            _, _, o_w, d_w, colours = self.train.pixel_rays(self.train.flat(i, r, c))  # the photo's colours with them
            with torch.no_grad():
                background = (self.backdrops_in_common(i) if self.own_backdrops
                              else self.model.background_rgb(o_w, d_w))
            o_fit, d_fit = self.model.fit_frame.rays(o_w, d_w)
            result = render(self.model.grid, o_fit, d_fit, background, self.model.render_options,
                            self.model.background_past_grid_only)
            rendered.append(result.rgb.cpu())
            opacity.append(result.opacity.cpu())
            photo.append(colours.cpu())
        return torch.cat(rendered), torch.cat(photo), torch.cat(opacity)

    def check_finite(self) -> None:
        columns = 1 + 3 * sh_count(self.model.grid.sh_degree)
        data = self.model.grid.data
        # The whole table's extremes first (a NaN or an infinity shows in them): one aminmax pass is far cheaper on the
        # CPU than isfinite().all(). Only where they are not finite are the parameter columns read (never the padding).
        extremes_finite = data.numel() > 0 and all(math.isfinite(float(x)) for x in torch.aminmax(data))
        if not extremes_finite and not bool(torch.isfinite(data[:, :columns]).all()):
            raise Diverged("a grid parameter became NaN or infinite")
        if self.model.background is not None and not all(bool(torch.isfinite(p).all())
                                                         for p in self.model.background.parameters()):
            raise Diverged("a background parameter became NaN or infinite")

    def tv_level_scale(self) -> float:
        """What the level's resolution multiplies the TV weights by (tv_reference_resolution). The level's entry in
        `resolutions`, not the grid's longest side: an NDC grid reaches past the reference image (up to twice as
        many cells across) and caps its depth, while its cells stay the size that entry gives them."""
        return tv_scale_for_resolution(self.schedule.resolutions[self.level], self.options.tv_reference_resolution)

    def density_rate_scale(self) -> float:
        """What the level's resolution multiplies the density's rates by (lr_density_reference_resolution)."""
        return density_rate_scale(self.schedule.resolutions[self.level], self.options.lr_density_reference_resolution)

    def regularisation_summary(self) -> str:
        """The fit summary's words on how TV and the density's rates were set for this capture ("" when as set)."""
        words, record = "", self.regularisation
        if record["tv_scale"] > 1.0:
            words += f", TV x{record['tv_scale']:.3g} for few views ({record['views_per_point']:.1f} per point)"
        if self.tv_level_scale() < 1.0:
            words += (f", TV x{self.tv_level_scale():.3g} on the last level "
                      f"(finer than {self.options.tv_reference_resolution}^3)")
        if self.density_rate_scale() > 1.0:
            words += (f", density rates x{self.density_rate_scale():.3g} on the last level "
                      f"(finer than {self.options.lr_density_reference_resolution}^3)")
        return words

    def colour_record(self) -> dict:
        """What the fit did about the photos' colours: whether it fitted them, what the gains of its deciding measures
        brought the renders (dB closer to their photos: their mean, and each), and the gains' range."""
        record = {"used": self.fits_colour, "asked": self.options.photo_colour, "gain_db": self.colour_gain_db,
                  "measures": self.colour_measures}
        return {**record, **self.colour.describe()} if self.fits_colour else record

    def colour_summary(self) -> str:
        """The fit summary's words on the photos' colours ("" where they were taken as they are)."""
        if not self.options.photo_colour:
            return ""
        if self.colour_gain_db is None:
            return ", the photos taken as they are (the fit ended before its measures of their colours had decided)"
        if not self.fits_colour:
            return (f", the photos agree on colour (gains {self.colour_gain_db:+.2f} dB nearer them at first, under "
                    f"{self.options.photo_colour_min_db:g}): taken as they are")
        gains = self.colour.describe()
        return (f", each photo's colour fitted (gains {min(gains['gain_min']):.2f}-{max(gains['gain_max']):.2f}, "
                f"{self.colour_gain_db:+.1f} dB at first)")

    def train_psnr(self) -> float:
        return psnr(sum(self.recent_mse) / len(self.recent_mse)) if self.recent_mse else float("nan")

    # ---- structure changes ----------------------------------------------------------------------
    def measure_weights(self, grid: SparseGrid | None = None) -> torch.Tensor:
        """Each vertex's largest weight along the rays of a pruning pass, on `grid` (the model's unless given)."""
        grid = self.model.grid if grid is None else grid
        stride = pruning_stride(self.train.sizes, max(grid.resolution), self.options)
        weights = torch.zeros(grid.num_occupied, device=self.device)
        for origins, dirs in self.train.strided_ray_chunks(stride, 16 * RAY_CHUNK):
            for start in range(0, origins.shape[0], RAY_CHUNK):
                o, d = self.model.fit_frame.rays(origins[start:start + RAY_CHUNK].to(self.device),
                                                 dirs[start:start + RAY_CHUNK].to(self.device))
                weights = torch.maximum(weights, max_weights(grid, o, d, self.model.render_options))
        return weights

    def prune(self, budget_rows: int | None = None) -> dict:
        before = self.model.grid.num_occupied
        self.grad = None  # its tables (each thread's copies too) freed before the pass and the new grid's tables
        weights = self.measure_weights()
        keep = prune_mask(self.model.grid, weights, self.options)
        if budget_rows is not None:
            keep = budget_mask(self.model.grid, keep, weights, budget_rows)
        if int(keep.sum()) == 0:
            raise UserError("pruning would remove every voxel (no training ray hits any density); check the poses, "
                            "or lower fit.prune_weight / fit.prune_density")
        grid, old_rows = self.model.grid.prune(keep)
        self._replace_grid(grid, old_rows)
        return {"before": before, "after": grid.num_occupied}

    def next_level(self) -> None:
        """Prune, upsample to the next resolution within the voxel budget (at the same resolution: prune only), carry
        the optimiser state."""
        budget = min(self.options.voxel_budget, voxels_that_fit(self.model.grid.sh_degree))
        self.level += 1
        new_shape = self.model.resolution_for(self.schedule.resolutions[self.level])
        growth = (max(new_shape) / max(self.model.grid.resolution)) ** 3
        pruned, upsampled = self.prune(budget_rows=max(1, int(budget / growth))), None
        if tuple(new_shape) != self.model.grid.resolution:
            grid, old_rows = self.model.grid.upsample(new_shape)
            if grid.num_occupied > budget:  # the estimate of the growth was short: drop the emptiest new vertices
                keep = torch.zeros(grid.num_occupied, dtype=torch.bool, device=grid.data.device)
                keep[torch.topk(grid.density, budget).indices] = True
                grid, rows = grid.prune(keep)
                old_rows = old_rows[rows]
            upsampled = grid.num_occupied
            if self.options.prune_upsampled:  # before the optimiser's state and gradients are made for it
                keep = prune_mask(grid, self.measure_weights(grid), self.options)
                grid, rows = grid.prune(keep) if bool(keep.any()) else (grid, torch.arange(len(old_rows)))
                old_rows = old_rows[rows.to(old_rows.device)]
            self._replace_grid(grid, old_rows)
        grid = self.model.grid
        self.levels.append({"step": self.step, "pruned_from": pruned["before"], "kept": pruned["after"],
                            "resolution": list(grid.resolution), "upsampled": upsampled, "occupied": grid.num_occupied,
                            "memory_bytes": grid.memory_bytes(), "tv_scale": self.tv_level_scale()})

    # ---- checkpoints ----------------------------------------------------------------------------
    def state(self) -> dict:
        return {
            "step": self.step, "level": self.level, "elapsed": self.elapsed, "history": self.history,
            "levels": self.levels, "recent_mse": self.recent_mse, "generator": self.generator.get_state(),
            "grid": self.model.grid.state_dict(), "optim": self.optim.state_dict(),
            "background": self.model.background.state_dict() if self.model.background is not None else None,
            "background_color": list(self.model.background_color),
            "bg_optim": self.bg_optim.state_dict() if self.bg_optim is not None else None,
            "error_map": self.error_map.state_dict() if self.error_map is not None else None,
            "colour": {"measures": self.colour_measures, "decided": self.colour_decided, **self.colour.state_dict()},
            "converged": self.converged, "last_level_psnr": self.last_level_psnr,
        }

    def save_checkpoint(self, path: Path) -> None:
        self.check_finite()
        state = self.state()
        write_whole(path, lambda tmp: torch.save(state, tmp))
        self.checkpoint_step = self.step

    def load_checkpoint(self, path: Path) -> None:
        state = torch.load(path, map_location="cpu", weights_only=False)
        self.model.grid = SparseGrid.from_state_dict(state["grid"])
        self.model.to(self.device)
        self.checkpoint_step = state["step"]
        self.step, self.level, self.elapsed = state["step"], state["level"], state["elapsed"]
        self.history, self.levels, self.recent_mse = state["history"], state["levels"], state["recent_mse"]
        self.generator.set_state(state["generator"])
        self._new_optimiser()
        self.optim.load_state_dict(state["optim"])
        self.optim.second_moment = self.optim.second_moment.to(self.device)
        if self.model.background is not None:
            self.model.background.load_state_dict(state["background"])
            self.bg_optim.load_state_dict(state["bg_optim"])
        if self.error_map is not None and state.get("error_map") is not None:
            self.error_map.load_state_dict(state["error_map"])
        self.last_level_psnr = list(state.get("last_level_psnr") or [])
        self.converged = state.get("converged")
        if self.converged is not None:  # the last level as it was shortened
            self.schedule.steps[-1] = self.converged["step"] - sum(self.schedule.steps[:-1]) + self.converged["tail"]
        if state.get("colour") is not None:
            self.colour_measures = list(state["colour"]["measures"])
            self.colour_decided = state["colour"]["decided"]
            self.colour.load_state_dict(state["colour"])
