"""The plan of a fit under a time budget: the candidate schedules, what each is predicted to take, the one chosen
before the fit starts, and the re-plan of the steps (and levels) left as the fit measures its own costs.

What a prediction adds up, from where the fit stands to its end: steps times seconds per step (for the level under
way, what its steps measure, or before they have, the first-level model at its box's voxels; for later levels, the
cost model at their occupied voxels, times the ratio of this scene's measured steps to the model's; a first level's
ratio, and that of a first level's early-pruned rest, counts only above 1, as such a level clears its empty space and
gets cheaper as it goes while a busy machine does not; until a level at a finer resolution has measured its own, it is
what an upsampled grid's steps cost over the model in the calibration, times the first resolution's ratio only where
that is below 1, as a coarse grid's pruned rest runs dearer than the finer levels after it), level changes (a pruning
pass over the training rays at the old resolution, then upsampling and a checkpoint that grow with the new grid, and
with fit.prune_upsampled a pruning pass at the new resolution), held-out evaluations, checkpoints, and the end (the
last pruning pass, the held-out PSNR, the save). A later level's voxels are the level before's, times the share
pruning keeps, times the upsampling's growth, times (with fit.prune_upsampled) the share the upsampled grid's own
pass keeps (a shell's, by the growth: upsample_keep); each share is a prior until a level change has measured it.

Which plan (bench/README.md, "Fit: quality against cost" and "The time budget"): grid resolution buys more than
steps for the same time, and a level needs enough steps to converge, but half the presets' steps lose less than one
rung of resolution does. A grid finer than the training photos have pixels across buys nothing: it has no detail to
learn that the photos show. So the rule is: the finest rung of LADDER no finer than the photos' longest side whose
predicted time fits with at least MIN_SHARE of its steps (FINE_MIN_SHARE for a rung finer than COARSE_LAST where the
fit has a bounded grid and the background spheres), given as many steps as the time allows up to MAX_SHARE of
them (more steps still help, less than a finer grid would), or up to FINEST_MAX_SHARE where no finer grid can take the
time: at the finest rung the photos are worth, and once the fit is in its last level. A budget beyond that ends early.
A re-plan holds a last level still to come to the same rule on the scene's own costs: raised where they leave it time
to spare, lowered where they leave it less than half its steps.

The coarsest rungs start at 32^3: a first level's step marches its whole box, so it is the dearest step of a fit for
its voxels, and a 32^3 level finds the occupied space for a fraction of a 64^3 one's time, for about the same
quality at the end.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

from plenoxels.core.schedule import coarse_start
from plenoxels.planning.fit_cost import CostModel, change_passes

# Shares of a rung's steps a plan may give: at least MIN_SHARE (a level needs enough steps to converge), at most
# MAX_SHARE (past it, time goes further in a finer grid).
MIN_SHARE = 0.5
MAX_SHARE = 2.0
# The least share of a plan whose last level is finer than COARSE_LAST where the fit has the background spheres behind a
# bounded grid (a room's foreground box: a phone's capture of a thing on a floor): there a finer last level short of
# steps loses to a coarser one with them. One run after the other (B, 2026-12-04, a share of 1 at every rung by a switch
# on 3c97059, against half): fox at 2 / 5 minutes 29.16 / 29.60 dB in 1.3 / 2.1 GiB (192^3, 256^3) against 28.94 /
# 29.38 in 2.2 / 3.8 GiB (256^3, 384^3); ball at 5 minutes 27.16 against 27.10 dB. At or below COARSE_LAST the trade
# goes the other way: fox at 30 s planned 64^3 with a share of 1, 25.81-26.07 dB, against 2cec6ea's 27.07 at 112^3
# beside it. A contracted room keeps MIN_SHARE everywhere: its cells spread over all of space, and the synthetic room
# at 2 minutes lost 0.93 dB with a share of 1 (bench/README.md, "The time budget").
FINE_MIN_SHARE = 1.0
COARSE_LAST = 128
# Where no finer grid can take the time (the finest rung the photos are worth, or a fit already in its last level), the
# last level's steps may grow to FINEST_MAX_SHARE, the levels before staying at MAX_SHARE: each doubling of lego's
# 512^3 steps at 800x800 gave about 0.5 dB, and a budget that ends early leaves that on the table: lego at the papers'
# protocol in 30 minutes 34.34 dB against 33.75 with the steps capped at 2x, which ended 412 s early (bench/README.md,
# "The papers' protocol").
FINEST_MAX_SHARE = 4.0
# Priors for the share of a level's voxels that pruning keeps, until a level change has measured it: the first prune
# (of a first level's whole box) by the scene type, and later ones (of grids pruned before, which keep more of
# themselves). An object's box is mostly air around thin surfaces; a forward capture's box is its cameras' frustum in
# NDC, filled with the scene out to the far plane (fern's first prunes keep 67-83%), and an unbounded scene's box is
# the room the cameras stand in, seen from every side: both keep most of themselves. Too high a prior picks a coarser
# plan than the time allows (re-plans then give it more steps), too low a finer one (re-plans then give it fewer, and
# a room planned on an object's prior runs a fraction of its steps). Evidence: bench/README.md, "The time budget".
FIRST_KEEP_PRIOR = {"object": 0.2, "forward": 0.7, "unbounded": 0.75}
LATER_KEEP_PRIOR = 0.6
# With fit.prune_upsampled, what an upsampled grid's own pruning pass keeps (upsample_keep) is a shell's share: its
# surfaces' band (UPSAMPLE_BAND_PRIOR of the dilation's thickness on each side, in the coarse grid's cells, until a
# level change has measured it) grows with the cells, the dilation around it does not. Measured (B, 2026-12-04,
# e16e1cb): lego 0.22 (128->256, keeping 0.59) and 0.25 (256->384, 0.73: the band read at 256 predicts 0.73), fox
# 0.19-0.60, ball 0.12, the synthetic room 0 (its pass kept 0.33 of 72->192, about the 0.375 of a band of none). A grid
# that began as such an upsample is tight already: the prune that ends its level keeps SETTLED_KEEP_PRIOR of it until
# measured (lego 0.97, where the same prune of an upsample left whole keeps 0.6-0.7).
UPSAMPLE_BAND_PRIOR = 0.25
SETTLED_KEEP_PRIOR = 0.95
# A last level too dear for half its steps is lowered this many vertices at a time (see replan).
LOWER_BY = 16


@dataclass(frozen=True)
class Rung:
    """A candidate schedule: the resolution of each level and its steps at a share of 1."""
    resolutions: tuple[int, ...]
    steps: tuple[int, ...]
    fixed: int = 0
    """Leading levels whose steps stay as they are whatever the share (a first level's early prune)."""

    def scaled(self, share: float) -> list[int]:
        """The steps at a share; past MAX_SHARE only the last level's grow, as that is where the detail is learnt."""
        steps = [n if level < self.fixed else max(1, round(min(share, MAX_SHARE) * n))
                 for level, n in enumerate(self.steps)]
        if share > MAX_SHARE:
            steps[-1] = max(1, round(share * self.steps[-1]))
        return steps


def _pruned_early(resolutions: tuple[int, ...], steps: tuple[int, ...]) -> Rung:
    """A rung whose first level prunes after a fifth of its steps, as the presets' do, and goes on at the same
    resolution: the prune comes after that many steps whatever the share, as what a grid keeps after fewer is still
    diffuse."""
    early = steps[0] // 5
    return Rung((resolutions[0],) + resolutions, (early, steps[0] - early) + steps[1:], fixed=1)


# Candidate schedules, coarse to fine, at the presets' step counts: the presets' levels (balanced 96->192, default
# 128->256, quality 128->256->384; fast's 64->144 lies between rungs) and rungs made the same way, each first level
# pruned early as the presets' are (a first level's steps march its whole box until a prune clears it, so an early prune
# saves time at no cost in quality); at the bottom, three that start at 32^3 (see the module's docstring), 32->64
# being what a budget too short for any plan gets. The early prune stays at its step whatever the share (`fixed`):
# scaled down with it, it prunes a grid still diffuse, which keeps more voxels than the plan assumed and upsamples to
# a finer grid larger than planned, which loses to no early prune at all (bench/README.md, "The time budget").
# Between 64 and 128 the final grids are 16 apart, as the re-plans' LOWER_BY: a grid 16 finer costs 1.1-1.5x at half
# its steps, one 32 finer about 2x, and a budget a few seconds short of a rung falls one grid, not two (fox at 30 s:
# 112^3 27.18 dB, 96^3 26.20; bench/README.md, "The time budget").
LADDER = (
    Rung((32, 64), (300, 600)),
    Rung((32, 80), (400, 800)),
    Rung((48, 96), (500, 1000)),
    Rung((32, 64, 128), (250, 500, 1000)),
    _pruned_early((64, 96), (500, 1000)),
    _pruned_early((64, 112), (500, 1000)),
    _pruned_early((64, 128), (500, 1000)),
    _pruned_early((80, 160), (600, 1200)),
    _pruned_early((96, 192), (750, 1500)),
    _pruned_early((112, 224), (900, 1500)),
    _pruned_early((128, 256), (1000, 1500)),
    _pruned_early((128, 256, 320), (1000, 1500, 1500)),
    _pruned_early((128, 256, 384), (1000, 1500, 1500)),
    _pruned_early((128, 256, 448), (1000, 2000, 3000)),
    _pruned_early((128, 256, 512), (1000, 2000, 6000)),
)


def ladder_at(first_level_scale: float, ladder: tuple[Rung, ...] | None = None) -> tuple[Rung, ...]:
    """The ladder (LADDER unless given) with each rung's first level, and its early-pruned rest, at `first_level_scale`
    of its resolution (coarse_start), as a fit of that scene type starts."""
    return tuple(dataclasses.replace(rung, resolutions=tuple(coarse_start(rung.resolutions, first_level_scale)))
                 for rung in ladder or LADDER)


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
    finish_rays: Callable[[], int] = lambda: 0  # rays rendered once as the fit ends (the photos' gains across frames)
    fine_min_share: float = MIN_SHARE  # the least share of a plan ending finer than COARSE_LAST (by the fit's model)
    prune_upsampled: bool = False      # each upsampled grid is pruned on its own render before it trains

    def least_share(self, last_resolution: int) -> float:
        """The least share of its rung's steps a plan ending at `last_resolution` may give."""
        return self.fine_min_share if last_resolution > COARSE_LAST else MIN_SHARE

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
    upsample_band: float = UPSAMPLE_BAND_PRIOR  # surfaces' band an upsampled grid's own pass keeps (upsample_keep)
    settled_keep: float = SETTLED_KEEP_PRIOR    # pruning's share of a level that began as such an upsample

    def kept(self, name: str, share: float) -> None:
        """Records the share a prune kept (`name`: first_keep, later_keep or settled_keep). The first prune's share
        speaks for the later prunes' until one is measured where it is above their prior: a room seen from inside
        keeps most of itself at its second prune too (ball's first prunes keep 0.97, its second at the same
        resolution 0.93; fox 0.82 and 0.78-0.92), where an object's first prune clears its box's air and its rest
        keeps the prior's share (bench/README.md, "The time budget")."""
        setattr(self, name, share)
        if name == "first_keep":
            self.later_keep = max(self.later_keep, share)


def upsample_keep(band: float, growth: float) -> float:
    """The share of an upsampled grid that its own pruning pass keeps (fit.prune_upsampled), its cells `growth` times
    finer: a shell around the surfaces whose band (`band` times the dilation on each side, in the coarse cells) grows
    with the cells, while the dilation around it is as many cells as before."""
    return 1.0 if growth <= 1 else (growth * band + 1) / (growth * (band + 1))


def upsample_band(keep: float, growth: float) -> float:
    """The band (upsample_keep's) of an upsample `growth` times finer whose own pass kept `keep` of it."""
    if growth <= 1 or keep >= 1:
        return 1e6  # kept whole: a band that fills the shell
    return max(0.0, (keep * growth - 1) / (growth * (1 - keep)))


def began_upsampled(resolutions: list[int], level: int) -> bool:
    """Whether the level before `level` began as an upsample (its resolution finer than the one before it): with
    fit.prune_upsampled, the prune at the change to `level` is then of a grid pruned once already (settled_keep)."""
    return level > 1 and resolutions[level - 2] != resolutions[level - 1]


def change_seconds(costs: CostModel, facts: FitFacts, before: int, after: int, upsampled: float,
                   voxels: float) -> float:
    """A level change from resolution `before` to `after` at the model's costs: the pruning pass at `before`, the
    upsample to `upsampled` voxels (the pruned grid's where `after` is `before`), and where the fit prunes an
    upsampled grid on its own render, that pass at `after`; then the checkpoint of the `voxels` left."""
    return (sum(costs.pass_seconds(facts.prune_rays(r), r) for r in change_passes(before, after, facts.prune_upsampled))
            + costs.change_per_voxel * upsampled + costs.checkpoint_per_voxel * voxels)


def finish_seconds(costs: CostModel, facts: FitFacts, now: Outlook, resolution: int, voxels: float,
                   stop: bool = False) -> float:
    """The end of a fit at this resolution and size: the last pruning pass (of a pruned grid, as the calibration's
    are, at the ratio this scene's held-out renders through the same grid measured against the model), the held-out
    PSNR, the photos' gains across their frames where the fit measures them, and the save; after a `stop`, the
    checkpoint the stop writes first."""
    finish_rays = facts.finish_rays()
    return (now.eval_ratio * costs.pass_seconds(facts.prune_rays(resolution), resolution)
            + costs.save_per_voxel * voxels
            + now.eval_ratio * costs.pass_seconds(facts.eval_rays, resolution)
            + (now.eval_ratio * costs.pass_seconds(finish_rays, resolution) if finish_rays else 0.0)
            + (costs.checkpoint_per_voxel * voxels if stop else 0.0))


def predict(costs: CostModel, facts: FitFacts, now: Outlook, resolutions: list[int], steps: list[int]) -> float:
    """Seconds from where the fit stands to its end for this schedule, whose levels before `now.level` are done."""
    seconds, voxels, start, remaining = 0.0, float(now.voxels), sum(steps[:now.level]), 0
    # A level at another resolution than the first starts from an upsampled grid, whose steps the calibration measured
    # at costs.upsampled_ratio of its model, until this scene's steps at such a level have been measured. The first
    # resolution's ratio speaks for them only below 1 (a machine faster now than its retime read it): above, it is a
    # coarse grid's pruned rest still clearing its air, up to 2x the model where the finer levels after it ran 0.4-1.6x
    # (bench/README.md, "The time budget").
    upsampled = min(1.0, now.step_ratio) * costs.upsampled_ratio if now.ratio_at_first else now.step_ratio
    for level in range(now.level, len(resolutions)):
        ratio = now.step_ratio if resolutions[level] == resolutions[0] else upsampled
        if level == now.level:
            step = now.step_seconds or ratio * costs.step_seconds(voxels, dense=now.dense)
        else:
            before, after = resolutions[level - 1], resolutions[level]
            settled = facts.prune_upsampled and began_upsampled(resolutions, level)
            kept = (now.first_keep if level == 1 else now.settled_keep if settled else now.later_keep) * voxels
            grown = min(facts.voxel_budget, kept * (after / before) ** 3)
            voxels = grown * (upsample_keep(now.upsample_band, after / before) if facts.prune_upsampled else 1.0)
            seconds += now.change_ratio * change_seconds(costs, facts, before, after, grown, voxels)
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
    fits: bool         # whether it fits with at least its least share of its steps (FitFacts.least_share)

    def describe(self) -> str:
        levels = f"{len(self.resolutions)} level{'s' if len(self.resolutions) > 1 else ''}"
        return f"{levels} {'->'.join(map(str, self.resolutions))}, {'+'.join(map(str, self.steps))} steps"


def photo_scale(longest_side: int, image_scale: float, finest: int) -> float:
    """The share of their size a budgeted fit takes its photos at: `image_scale`, or more (whole at most) where their
    longest side (`longest_side` pixels, as ingested) would otherwise fall below `finest`, the finest grid the preset
    fits without a budget. A plan goes no finer than its photos' pixels, so small photos at a preset's downscale would
    hold a long budget's grid below the preset's own; a step costs the same whatever their size (a batch is so many
    rays). Larger photos than that buy a budget nothing: lego's 800-pixel photos at 512 pixels, not 400, took 448^3 and
    512^3 grids that scored lower at 5 and 10 minutes (bench/README.md, "The time budget")."""
    return min(1.0, max(image_scale, finest / max(longest_side, 1)))


def finest_worth(resolution: int, max_resolution: int, ladder: tuple[Rung, ...] | None = None) -> bool:
    """Whether no rung of the ladder ends finer than `resolution` and still no finer than the photos' pixels."""
    return not any(resolution < r.resolutions[-1] <= max_resolution for r in ladder or LADDER)


def _finest_first(ladder) -> list[Rung]:
    return sorted(ladder, key=lambda r: (r.resolutions[-1], len(r.resolutions)), reverse=True)


def choose(seconds: float, costs: CostModel, facts: FitFacts, ladder: tuple[Rung, ...] | None = None) -> Plan:
    """The plan for a fit that has not started: the finest rung (no finer than `facts.max_resolution`) whose predicted
    time fits `seconds` with at least its least share of its steps (MIN_SHARE, or `facts.fine_min_share` for a rung
    ending finer than COARSE_LAST), with the most steps that fit up to MAX_SHARE
    (FINEST_MAX_SHARE at the finest rung; of rungs ending at the same resolution, the one that gets the largest share);
    when none fits, the coarsest rung with the steps that fit (at least one a level)."""
    ladder = _finest_first(ladder or LADDER)
    ladder = [r for r in ladder if r.resolutions[-1] <= facts.max_resolution] or ladder[-1:]

    def seconds_for(rung: Rung, share: float) -> float:
        now = facts.outlook(voxels=facts.box_voxels(rung.resolutions[0]))
        return predict(costs, facts, now, list(rung.resolutions), rung.scaled(share))

    def plan(rung: Rung, share: float) -> Plan:
        fits = share >= facts.least_share(rung.resolutions[-1])
        return Plan(list(rung.resolutions), rung.scaled(share), share, seconds_for(rung, share), fits)

    for finest in sorted({r.resolutions[-1] for r in ladder}, reverse=True):
        cap = FINEST_MAX_SHARE if finest_worth(finest, facts.max_resolution, ladder) else MAX_SHARE
        least = facts.least_share(finest)
        shares = [(share, rung) for rung in ladder if rung.resolutions[-1] == finest
                  for share in [_largest_share(lambda s: seconds_for(rung, s) <= seconds, least, cap)]
                  if share is not None]
        if shares:
            share, rung = max(shares, key=lambda pair: pair[0])  # the first of equal shares: ladder order
            return plan(rung, share)
    coarsest = ladder[-1]
    least = facts.least_share(coarsest.resolutions[-1])
    return plan(coarsest, _largest_share(lambda s: seconds_for(coarsest, s) <= seconds, 0.0, least) or 0.0)


def replan(seconds: float, costs: CostModel, facts: FitFacts, now: Outlook, rung: Rung, resolutions: list[int],
           steps: list[int], measured: bool) -> tuple[list[int], list[int], float]:
    """(resolutions, steps, share) for a fit under way, the levels done kept: the most steps (a share of the rung's, at
    most MAX_SHARE, or FINEST_MAX_SHARE with every level kept where no finer grid can take the time) whose predicted
    time fits `seconds`. A level still to come is dropped when keeping it would leave less than MIN_SHARE of the steps:
    with `measured` costs (once the fit has left its first resolution) any such level; before that only one past the
    second resolution, as what pruning keeps is still a prior and a first resolution alone, pruned early or not, is
    never a whole fit. Without that, a first level gives up the steps a level dropped later would have needed, and the
    fit ends with neither. A level is not dropped where the levels before it, at MAX_SHARE, would end the fit early
    (leaving budget unused): it stays, with what fits. When no schedule gets MIN_SHARE, the fewest levels allowed get
    what fits. A fine least share (FitFacts.fine_min_share) chooses and raises last levels but never drops or lowers
    one: a fit that runs slower than planned keeps its levels down to MIN_SHARE.

    Once the first prune has measured what the scene keeps, a last level not yet started that would get less than
    MIN_SHARE of its steps (and is not dropped) is lowered, by LOWER_BY, to the finest resolution that gets MIN_SHARE:
    the rule the plan was chosen by, now on the scene's own costs. A finer grid short of steps loses to a coarser one
    with them, in a room and on an object alike: lego at 800 pixels in 5 minutes, 512^3 with 1943 steps 31.15 dB,
    lowered to 352^3 with 4235 steps 32.43 (bench/README.md, "The time budget").

    In any scene, a last level not yet started that gets MAX_SHARE with every level kept (time past it would go into
    steps, where a finer grid buys more), below the finest rung the photos are worth, is raised to the finest
    resolution (by LOWER_BY, up to that rung) that gets its least share (FitFacts.least_share): the rule the plan was
    chosen by, on the scene's own costs. A scene whose first level runs several times cheaper than the calibration's
    (a contracted room's 32^3 at 0.25x) otherwise pours the time its plan saved into steps of a grid coarser than it
    could afford, and its finer levels run cheaper than predicted too (0.34-0.88 of the model), so a raised level gets
    more steps as it runs.
    Raised before a level's costs are measured, wherever a finer one would get MIN_SHARE, objects lost: their levels
    got too few steps (bench/README.md, "The time budget")."""
    chosen = _replan_levels(seconds, costs, facts, now, rung, resolutions, steps, measured)
    if (len(chosen[0]) == len(resolutions) and now.level < len(resolutions) - 1 and chosen[2] >= MAX_SHARE
            and not finest_worth(resolutions[-1], facts.max_resolution)):
        return _raised(seconds, costs, facts, now, rung, resolutions, steps, measured) or chosen
    if (chosen[2] >= MIN_SHARE or len(chosen[0]) < len(resolutions) or now.level >= len(resolutions) - 1
            or now.dense):
        return chosen
    for last in range(resolutions[-1] - LOWER_BY, resolutions[-2], -LOWER_BY):
        lowered = _replan_levels(seconds, costs, facts, now, rung, resolutions[:-1] + [last], steps, measured)
        if lowered[2] >= MIN_SHARE and len(lowered[0]) == len(resolutions):
            return lowered
    return chosen


def _raised(seconds: float, costs: CostModel, facts: FitFacts, now: Outlook, rung: Rung, resolutions: list[int],
            steps: list[int], measured: bool) -> tuple[list[int], list[int], float] | None:
    """The re-plan with the last level at the finest resolution above its own, by LOWER_BY down from the finest rung
    the photos are worth, that keeps every level with its least share of the steps (None where none does)."""
    top = max((r.resolutions[-1] for r in LADDER if r.resolutions[-1] <= facts.max_resolution), default=0)
    for last in range(top, resolutions[-1], -LOWER_BY):
        trial, least = resolutions[:-1] + [last], facts.least_share(last)
        if predict(costs, facts, now, trial, _schedule(rung, steps, now, least, len(trial))) > seconds:
            continue  # one prediction rules a resolution out before the search for its share
        raised = _replan_levels(seconds, costs, facts, now, rung, trial, steps, measured)
        if len(raised[0]) == len(trial) and raised[2] >= least:
            return raised
    return None


def _schedule(rung: Rung, steps: list[int], now: Outlook, share: float, levels: int) -> list[int]:
    """The first `levels` levels' steps at `share` of the rung's, the levels done as they ran and the level under way
    no shorter than the steps it has run."""
    new = rung.scaled(share)[:levels]
    new[:now.level] = steps[:now.level]
    new[now.level] = max(now.step - sum(steps[:now.level]), new[now.level])
    return new


def _replan_levels(seconds: float, costs: CostModel, facts: FitFacts, now: Outlook, rung: Rung,
                   resolutions: list[int], steps: list[int], measured: bool) -> tuple[list[int], list[int], float]:
    def schedule(share: float, levels: int) -> list[int]:
        return _schedule(rung, steps, now, share, levels)

    def fits(levels: int) -> Callable[[float], bool]:
        return lambda s: predict(costs, facts, now, resolutions[:levels], schedule(s, levels)) <= seconds

    # A first level pruned early goes on at its resolution: the second level is then the one after that.
    second = next((level + 1 for level, r in enumerate(resolutions) if r != resolutions[0]), len(resolutions))
    fewest = now.level + 1 if measured else min(len(resolutions), max(now.level + 1, second))
    # All levels kept, extra time can only go into steps where the last is the finest rung the photos are worth or
    # the fit has reached it.
    finest = now.level == len(resolutions) - 1 or finest_worth(resolutions[-1], facts.max_resolution)
    for levels in range(len(resolutions), fewest - 1, -1):
        cap = FINEST_MAX_SHARE if finest and levels == len(resolutions) else MAX_SHARE
        share = _largest_share(fits(levels), MIN_SHARE, cap)
        if share is None:
            continue
        if levels < len(resolutions) and share >= MAX_SHARE:  # the fit would end early: the level stays, short
            levels += 1
            share = _largest_share(fits(levels), 0.0, MIN_SHARE) or 0.0
        return resolutions[:levels], schedule(share, levels), share
    share = _largest_share(fits(fewest), 0.0, MIN_SHARE) or 0.0
    return resolutions[:fewest], schedule(share, fewest), share
