"""The options of the model's machinery, free of torch: how rays are marched (`MarchOptions`, which a render's
`RenderOptions` extends), what a new SceneModel is made of (`ModelOptions`), how it is fitted (`TrainOptions`) and how
a mesh is drawn from it (`MeshOptions`). The fit and export stages' settings extend them (stages/settings/), so a
settings listing and the pipeline's cache keys read them without loading the model.

Each class holds its options' defaults and help, and its `check(section)` raises a one-line UserError for a bad value,
naming the key as `section.name` (the section defaults to the stage whose settings hold the options); a class that
extends another checks through the other's `check`, never again by itself."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from plenoxels.core.errors import require


@dataclass
class MarchOptions:
    """How rays are marched through the grid: set for the fit (ModelOptions), kept in the model for its renders."""

    step_size: float = 0.5
    """Ray sample spacing in voxels."""
    stop_transmittance: float = 0.01
    """A ray stops once this little light gets through; what lies behind then shows as the background. At 0.01, not
    1e-4, a fitted room's training ray meets two thirds of the samples (fox 16 against 24) and each preset fits in
    0.77-0.92x the time at the same held-out PSNR (bench/README.md, "Kernels")."""

    def check(self, section: str = "fit") -> None:
        require(self.step_size > 0, f"{section}.step_size must be positive (voxels)")
        require(0 <= self.stop_transmittance < 1, f"{section}.stop_transmittance must be in [0, 1)")


@dataclass
class ModelOptions(MarchOptions):
    """What a new SceneModel is made of beyond the scene: its fit frame, colour model, background and sampling."""

    ndc: Literal["auto", "on", "off"] = "auto"
    """Fit in NDC of the average camera: auto (forward scenes), on or off."""
    contract: Literal["auto", "on", "off"] = "auto"
    """A contracted grid that holds all of space, the foreground box at its centre at full resolution and the world
    around it ever more coarsely out to infinity (mip-NeRF 360): auto (unbounded scenes whose sparse points reach far
    beyond the foreground: outdoors, streets, wide rooms), on or off."""
    background: Literal["auto", "on", "off"] = "auto"
    """Multi-sphere background model behind the grid: auto (unbounded scenes without a contracted grid), on or off."""
    background_color: list[float] = field(default_factory=lambda: [1.0, 1.0, 1.0])
    """RGB in [0, 1] behind the grid and under image masks."""
    sh_degree: int = 2
    """Spherical-harmonic degree of the colour, 0-3."""
    init_density: float = 0.1
    """Raw density of every vertex at the start."""
    box_padding: float = 0.05
    """The grid box is the foreground box grown by this share of its size on each side."""
    surroundings_cells: float = 1.0
    """A room's bounded grid (an unbounded scene without a contracted grid), whose box holds the walls and floor around
    the foreground: its cells there are this many times the foreground's across, so the foreground gets finer cells
    at the same resolution, however far the surroundings reach (1: one cell size over the box; `fast` takes 2;
    bench/README.md, "Cells that follow the scene")."""
    shell_cells: float = 1.0
    """A contracted grid: its cells in the shell around the inner cube (the world beyond the foreground box, out to
    infinity) are this many times the inner cube's across, so the foreground gets finer cells at the same resolution
    (1: one cell size over the contracted box; bench/README.md, "Cells that follow the scene")."""
    near_share: float = 0.5
    """Contracted grids: rays start this share of the nearest sparse point any camera saw (normalize's near) from their
    camera, so that no haze hangs in front of the lenses."""
    background_spheres: int = 32
    """Background model: number of spheres."""
    background_width: int = 0
    """Background model: texture width in texels (the height is half); 0: from the training photos, so that a texel
    spans about background_texel_px of their pixels (between 64 and 2048 texels)."""
    background_texel_px: float = 2.0
    """Background model with background_width 0: how many training pixels one texel spans."""
    tv_background: float = 1e-3
    """Background model: TV weight of its density and colour."""

    def check(self, section: str = "fit") -> None:
        MarchOptions.check(self, section)
        require(len(self.background_color) == 3 and all(0 <= c <= 1 for c in self.background_color),
                f"{section}.background_color must be three numbers in [0, 1] (for example [1, 1, 1])")
        require(0 <= self.sh_degree <= 3, f"{section}.sh_degree must be 0, 1, 2 or 3")
        require(self.box_padding >= 0, f"{section}.box_padding must be >= 0")
        require(self.surroundings_cells >= 1, f"{section}.surroundings_cells must be >= 1")
        require(0 <= self.near_share < 1, f"{section}.near_share must be in [0, 1)")
        require(self.background_spheres >= 1 and (self.background_width == 0 or self.background_width >= 4),
                f"{section}.background_spheres must be >= 1 and {section}.background_width 0 (from the photos) or >= 4")
        require(self.background_texel_px > 0, f"{section}.background_texel_px must be positive")
        require(self.tv_background >= 0, f"{section}.tv_background must be >= 0")


@dataclass
class TrainOptions:
    """How a SceneModel is fitted: the levels, the batches, the optimiser, the regularisers and the pruning."""

    resolutions: list[int] = field(default_factory=lambda: [128, 128, 256])
    """Grid vertices along the longest axis, one per level. A level at the resolution of the one before prunes the
    grid without upsampling it: a first level's grid is the whole box, and until it is pruned every ray marches all of
    it, so the presets prune it after a fifth of its steps: the rest of the level then marches only what the photos
    see, in less time for the same held-out PSNR (bench/README.md, "Fit: quality against cost")."""
    steps: list[int] = field(default_factory=lambda: [200, 800, 1500])
    """Optimiser steps per level."""
    converged_db: float = 0.0
    """The last level ends early once it has converged: once its train PSNR rose less than this many dB over the
    latest quarter of its steps (looked at from half of them on), it runs a tenth of its steps more, over which the
    learning rates fall to their final values, and the fit ends there (0: every step as set; a time budget runs its
    plan; bench/README.md, "Fit: quality against cost")."""
    first_level_scale: float = 1.0
    """The first level's resolution (its early-pruned rest too) as this share of the one set, or of a time budget's
    plan (never below 32, or the level's own resolution if that is less). A room seen from inside fills most of its
    box, and a coarser first level is as good a start for the finer ones; an object loses thin parts to it
    (configs/scene_types/unbounded.yaml sets it for rooms)."""
    batch_size: int = 8192
    """Rays per step."""
    batch_mode: Literal["tiles", "rays"] = "rays"
    """rays: random pixels; tiles: random square tiles of pixels (faster kernel, less progress per step)."""
    tile_size: int = 32
    """Tile side in pixels (batch_mode tiles)."""
    photo_colour: bool = False
    """Fit each training photo's own colour (a gain per channel, plenoxels/core/photo_colour.py) and train
    the field against the photos taken back to their common colour, for a phone's exposure and white balance, which
    change as it turns. A new view is rendered in the common colour; a held-out photo in the colour of its neighbours
    in the capture's order, as the phone was set when it took it. Where masks cut the object out, the gains are
    measured inside them and the backdrop colour the masks put round it keeps its colour (bench/README.md, "Real
    captures", "Object captures")."""
    photo_colour_min_db: float = 0.15
    """The least the photos' gains must bring the renders nearer their photos (dB of PSNR), on average over the fit's
    first measures of them (plenoxels/core/photo_colour.py, DECIDING_MEASURES), for the fit to fit them; below, the
    photos agree on colour, and gains would take up the field's own errors instead (lego -0.8 dB held-out), so they
    are taken as they are (bench/README.md, "Object captures")."""
    photo_colour_cells: int = 8
    """Where the fit fits the photos' colours: cells along a photo's longer side of the lattice of gains measured
    across each photo's frame once the fit ends, for light that differs across a frame from photo to photo (a
    capturer's shadow, a glossy floor's glow; plenoxels/core/photo_colour.py, gain_fields). A held-out photo takes its
    capture neighbours' lattices where they predict the training photos' own better than their gains do
    (PhotoGains.fields_follow_order). 1: one gain per photo."""
    empty_backdrop: bool = True
    """Where the photos come with masks and the model shows one colour past an object (no background model), a ray
    through a pixel no mask covers sees a random colour past the grid and is trained toward it: what the photos show
    empty the fit leaves empty. Against the photos' own backdrop colour, haze of that colour costs nothing (a skirt
    under lego's baseplate, white where the photos see it, grey from below; bench/README.md, "The papers' protocol")."""
    covered_backdrop_share: float = 0.5
    """Where empty_backdrop applies, this share of the rays through pixels a mask covers whole see a random colour
    past the grid (their targets are the photo's, whatever lies behind): such a ray is right only where the field is
    opaque, so an object as pale or as dark as its backdrop is not fitted half see-through (bench/README.md,
    "Object captures"). The rest see their photo's backdrop, so a mask's edge can hold some of it."""
    clipped_floors: bool = True
    """A photo's clipped channels (within a byte of the top, where its own light fills the pixel) trained as floors:
    the render is wrong there only below the photo's value, never above it; in the photo's gains where the fit fits
    them (plenoxels/core/ray_set.py, clipped_bits; bench/README.md, "Object captures")."""
    error_share: float = 0.0
    """Share of each batch of random rays drawn where the render still disagrees with the photos, in proportion to
    the RMS error of each block of pixels (plenoxels/core/error_map.py); the rest are uniform (0: every ray uniform;
    batch_mode rays only)."""
    leave_out_transients: bool = True
    """Leave out of the fit what moved between the photos (a person walking through, a car): the patches of a photo
    whose colour the render, fitted to all of them, says is not the scene's, found at each measurement from the
    second level on (plenoxels/core/error_map.py, find_transients; batch_mode rays only)."""
    measure_every: int = 200
    """Steps between two measurements of the training photos against the render (their colours, the error map, what
    moved between them); each level's start measures them too. Only a fit that uses one of them measures."""
    measure_rays: int = 1 << 17
    """Rays one measurement renders: an even lattice of every photo's pixels, as fine as this allows (at most a quarter
    of the default where it measures the photos' colours alone, with no error map to draw from or find what moved in:
    plenoxels/core/photo_colour.py, COLOUR_RAYS)."""
    coherent_batches: bool = True
    """Order each batch's rays so that rays passing near each other sit together (the same rays, in another order:
    the kernel's threads then read neighbouring voxels, which is faster; bench/README.md, "Kernels")."""
    lr_density: float = 30.0
    """RMSProp rate of the density at the start, decayed exponentially to lr_density_final."""
    lr_density_final: float = 3.0
    """RMSProp rate of the density at the end."""
    lr_density_delay: float = 0.1
    """Share of the steps over which the density rate ramps up from 1% (0: none)."""
    lr_density_reference_resolution: int = 128
    """A level finer than this (its entry in `resolutions`) steps its density at its rates times (its resolution /
    this): the density that makes a cell opaque grows as the cell shrinks, while a rate steps it by fixed amounts, so
    rates set for a coarser grid leave a finer one's surfaces many cells thick (lego's 30 at 512^3; bench/README.md,
    "The papers' protocol") (0: the rates as set on every level)."""
    lr_per_level: bool = True
    """Each level after the first decays the rates from their start values to their final ones over its own steps,
    not once over the whole fit: the finest level, where the detail is learnt, starts at the full rates (lego at
    `default` +0.3 dB; bench/README.md, "Fit: quality against cost"). The first level keeps the whole fit's ramp."""
    lr_sh: float = 0.05
    """RMSProp rate of the SH coefficients at the start, decayed exponentially to lr_sh_final."""
    lr_sh_final: float = 5e-3
    """RMSProp rate of the SH coefficients at the end."""
    rmsprop_beta: float = 0.95
    """RMSProp decay of the squared-gradient average, in [0, 1)."""
    tv_density: float = 1e-10
    """TV weight of the density per sampled vertex (the MSE is a mean over the batch)."""
    tv_sh: float = 1e-8
    """TV weight of the SH coefficients per sampled vertex."""
    tv_sample_fraction: float = 0.01
    """Share of the occupied vertices the TV term looks at each step, drawn in runs of neighbouring rows on large grids
    (plenoxels/core/regularizers.py, SAMPLE_RUN_ROWS)."""
    sparsity: float = 0.0
    """Weight of a Cauchy prior that density is zero, per vertex of a random sample as large as TV's, at the first
    level's resolution: pulls faint haze, which no photo needs but pruning keeps wherever some ray sees it, off the
    grid before the first upsampling builds the finer levels from it; they then fit detail without it (0: off)."""
    tv_views: float = 32.0
    """Few views: where the training photos see each point of the grid's box fewer than this many times on average,
    both TV weights grow by (tv_views / views)^tv_views_power (0: the weights as set, whatever the capture)."""
    tv_views_power: float = 2.0
    """How fast TV grows as the views per point fall below tv_views."""
    tv_views_max_scale: float = 1000.0
    """The most that few views multiply the TV weights by."""
    tv_reference_resolution: int = 0
    """A level finer than this (its entry in `resolutions`) gets both TV weights times (this / its resolution)^2: each
    vertex's share of a batch's samples falls with the square of the resolution while its TV gradient does not, so
    weights set for a coarser grid outweigh the photos on a finer one (0: the weights as set on every level)."""
    lr_background: float = 0.01
    """RMSProp rate of the background model's texels."""
    near_gradient_distance: float = 1.0
    """A sample nearer its ray's camera than this (fit-frame units: the normalised scene's, whose foreground box is
    about 2 across) passes on (distance / this)^2 of its photometric gradient (Philip and Deschaintre, "Floaters No
    More", 2023): the space just in front of a camera, which few other photos see, then takes what farther views say
    of it over what one photo alone wants there, and holds no floaters (0: the whole gradient everywhere; NDC fits
    take none; bench/README.md, "Real captures")."""
    prune_weight: float = 0.002
    """Pruning keeps only vertices that some training ray weighs by more than this (max rendering weight)."""
    prune_density: float = 0.0
    """Pruning keeps only vertices whose raw density is above this (fit-frame units)."""
    prune_dilation: int = 2
    """What pruning keeps is then grown by this many voxels."""
    prune_ray_scale: float = 0.5
    """The densest set of training rays that measure weights for pruning: images at this share of their size."""
    prune_rays_per_cell: float = 16.0
    """A pruning pass marches about this many rays per cell of the grid's largest face (resolution squared), through
    an even lattice of every photo's pixels (never denser than prune_ray_scale; 0: always that dense). What it must
    find, the voxels some photo sees, grows with the grid's faces, not with the photos: many large photos then
    prune in a fraction of the time, and a voxel still meets rays from several photos."""
    prune_final: bool = True
    """Prune the same way after the last level too (smaller model, fewer floaters)."""
    prune_upsampled: bool = True
    """Prune an upsampled grid the same way before it trains, on its own render (its dilation in its own, finer
    voxels): the coarser grid's dilation, carried up, holds a shell of vertices the finer grid's surfaces never reach.
    A time budget prices it as a pass at the finer resolution and plans the level on the share it keeps. Budgets one
    run after the other, each from its own cold calibration (B, 2026-12-04, 541b3f7): fox at 30 s / 1 / 2 minutes
    28.13 / 28.81 / 29.44 dB against 27.86 / 28.67 / 29.32 (2 minutes in 1.2 against 1.8 GiB), the synthetic room at
    2 minutes 22.67 against 22.07 (192^3 against 160^3), ball at 1 minute 26.87 against 26.84; fixed plans: lego
    `default` 32.24 against 32.26 in 1.20 against 1.30 GiB (bench/README.md, "The time budget")."""
    voxel_budget: int = 16_000_000
    """Most occupied vertices after an upsample."""
    seed: int = 0
    """Seed of the batches and of the TV samples."""

    @property
    def total_steps(self) -> int:
        return sum(self.steps)

    def check(self, section: str = "fit") -> None:
        require(len(self.resolutions) >= 1 and all(r >= 8 for r in self.resolutions),
                f"{section}.resolutions must be a list of at least one resolution, each >= 8 (for example [128, 256])")
        require(all(b >= a for a, b in zip(self.resolutions, self.resolutions[1:])),
                f"{section}.resolutions must not decrease from level to level (for example [128, 128, 256]: a repeated "
                "resolution prunes the grid without upsampling it)")
        require(len(self.steps) == len(self.resolutions) and all(s >= 1 for s in self.steps),
                f"{section}.steps must list one positive step count per resolution ({len(self.resolutions)} here)")
        require(self.converged_db >= 0, f"{section}.converged_db must be >= 0 (0: the last level runs every step)")
        require(0 < self.first_level_scale <= 1,
                f"{section}.first_level_scale must be in (0, 1] (1: the first level as set)")
        require(self.batch_size >= 1, f"{section}.batch_size must be at least 1")
        require(self.tile_size >= 1, f"{section}.tile_size must be at least 1")
        require(0 <= self.error_share <= 1, f"{section}.error_share must be in [0, 1] (0: every ray uniform)")
        require(0 <= self.covered_backdrop_share <= 1,
                f"{section}.covered_backdrop_share must be in [0, 1] (0: every covered ray sees its photo's backdrop)")
        require(self.photo_colour_cells >= 1, f"{section}.photo_colour_cells must be at least 1")
        require(self.measure_every >= 1 and self.measure_rays >= 1,
                f"{section}.measure_every and {section}.measure_rays must be at least 1")
        require(self.lr_density > 0 and self.lr_density_final > 0 and self.lr_sh > 0 and self.lr_sh_final > 0,
                f"{section}.lr_density, {section}.lr_density_final, {section}.lr_sh and {section}.lr_sh_final must be "
                "positive")
        require(0 <= self.lr_density_delay < 1, f"{section}.lr_density_delay must be in [0, 1)")
        require(self.lr_density_reference_resolution >= 0,
                f"{section}.lr_density_reference_resolution must be >= 0 (0: the density's rates as set everywhere)")
        require(0 <= self.rmsprop_beta < 1, f"{section}.rmsprop_beta must be in [0, 1)")
        require(self.tv_density >= 0 and self.tv_sh >= 0, f"{section}.tv_density and {section}.tv_sh must be >= 0")
        require(0 < self.tv_sample_fraction <= 1, f"{section}.tv_sample_fraction must be in (0, 1]")
        require(self.sparsity >= 0, f"{section}.sparsity must be >= 0 (0: off)")
        require(self.tv_reference_resolution >= 0,
                f"{section}.tv_reference_resolution must be >= 0 (0: the TV weights as set on every level)")
        require(self.lr_background > 0, f"{section}.lr_background must be > 0")
        require(self.near_gradient_distance >= 0, f"{section}.near_gradient_distance must be >= 0 (0: off)")
        require(self.prune_weight >= 0 and self.prune_dilation >= 0,
                f"{section}.prune_weight and {section}.prune_dilation must be >= 0")
        require(0 < self.prune_ray_scale <= 1, f"{section}.prune_ray_scale must be in (0, 1]")
        require(self.prune_rays_per_cell >= 0,
                f"{section}.prune_rays_per_cell must be >= 0 (0: every pixel at {section}.prune_ray_scale)")
        require(self.voxel_budget >= 1000, f"{section}.voxel_budget must be at least 1000")


@dataclass
class MeshOptions:
    """How the mesh is extracted from the fitted density, cleaned and simplified (the export stage's settings)."""
    resolution: int | Literal["auto"] = "auto"
    """Marching-cubes cells along the grid's longest axis; auto: the fit's own."""
    level: float | Literal["auto"] = "auto"
    """Density iso-level; auto: see level_share."""
    level_share: float = 0.5
    """Auto level: this share of the peak density the opaque training rays meet (auto_level)."""
    level_opacity: float = 0.5
    """Auto level without such points: the density at which one voxel is this opaque."""
    crop_margin: float = 0.05
    """The foreground box is grown by this share of its size before cropping."""
    min_piece_fraction: float = 0.01
    """Pieces with fewer faces than this share of the largest piece are dropped."""
    max_gap: float = 0.05
    """Pieces farther than this share of the foreground diagonal from the largest are dropped (unless they stood on
    the ground that object_only cut away, or every photo is masked: the masks drew what is the object)."""
    fill_voxels: int = 4
    """Before marching cubes, seal openings in the fitted solids' skins up to 2 x this - 1 voxels across (those
    solid rings in some plane; slots, gaps between solids and the edges where they meet the ground stay open) and
    fill the cavities they close off, so the mesh is the solids' outside without the holes the fit's foam leaves
    (0: the density as fitted; bench/README.md measures it)."""
    unseen: Literal["drop", "keep"] = "drop"
    """Faces no training view sees (insides of the fit's shells, undersides)."""
    seen_tolerance: float = 1.0
    """A vertex this many voxels behind what a view's pixel sees is still seen."""
    align_voxels: float = 2.5
    """Move each vertex along its normal, up to this many voxels, to where the training views that see it agree best
    on its colour (plenoxels/surface/view_alignment.py); 0: the fitted density's level set as it is."""
    object_only: Literal["auto", "on", "off"] = "auto"
    """The object alone: cut away the ground or table it stands on and the room the box cuts through
    (plenoxels/surface/ground.py); auto: on for object and unbounded scenes, off for forward ones. export.crop, when set, is
    the box."""
    max_faces: int = 200_000
    """Decimate to at most this many faces (quadric, keeping boundaries and topology); 0 keeps every face."""
    point_opacity: float = 0.5
    """A pixel gives a point only where its ray is at least this opaque (points, seen faces)."""
    seed: int = 0
    """Seed of the random subsets (points, the auto level's rays, the ground's RANSAC)."""

    def check(self, section: str = "export") -> None:
        require(self.resolution == "auto" or 8 <= self.resolution <= 2048,
                f"{section}.resolution must be auto or between 8 and 2048 cells")
        require(self.level == "auto" or self.level > 0, f"{section}.level must be auto or a positive density")
        require(0.0 < self.level_share < 1.0, f"{section}.level_share must be in (0, 1)")
        require(0.0 < self.level_opacity < 1.0, f"{section}.level_opacity must be in (0, 1)")
        require(self.crop_margin >= 0.0, f"{section}.crop_margin must be 0 or more")
        require(0.0 <= self.min_piece_fraction <= 1.0, f"{section}.min_piece_fraction must be in [0, 1]")
        require(self.max_gap > 0.0, f"{section}.max_gap must be positive")
        require(self.fill_voxels >= 0, f"{section}.fill_voxels must be 0 (no filling) or more voxels")
        require(self.seen_tolerance >= 0.0, f"{section}.seen_tolerance must be 0 or more voxels")
        require(self.align_voxels >= 0.0, f"{section}.align_voxels must be 0 (no alignment) or more voxels")
        require(self.max_faces == 0 or self.max_faces >= 4, f"{section}.max_faces must be 0 (keep all) or at least 4")
        require(0.0 < self.point_opacity < 1.0, f"{section}.point_opacity must be in (0, 1)")
