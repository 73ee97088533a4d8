"""The plan of a budgeted fit: predictions, the plan chosen for a budget, and the re-plans of a fit under way."""
import dataclasses

import pytest

from plenoxels.planning import fit_plan
from plenoxels.planning.fit_cost import CostModel
from plenoxels.planning.fit_plan import FitFacts, Outlook, Rung

# Roughly what this machine measured with the fast preset's options on one thread.
MEASURED = CostModel(step_fixed=0.018, step_per_voxel=7e-8, pass_per_ray=1.7e-8, change_per_voxel=5e-7,
                     checkpoint_per_voxel=4e-7, save_per_voxel=1e-7)
FACTS = FitFacts(box_voxels=lambda r: r ** 3, prune_rays=lambda r: 170_000, eval_rays=3600, eval_every=250,
                 checkpoint_every=180.0, voxel_budget=16_000_000)


def test_a_plan_never_predicts_more_than_its_budget_and_more_time_buys_a_finer_grid():
    finals = []
    for seconds in (20, 30, 45, 60, 90, 120, 180, 300, 600, 1200, 3600):
        plan = fit_plan.choose(seconds, MEASURED, FACTS)
        assert plan.fits and plan.predicted <= seconds, (seconds, plan)
        finest = plan.resolutions[-1] == max(r.resolutions[-1] for r in fit_plan.LADDER)
        assert fit_plan.MIN_SHARE <= plan.share <= (fit_plan.FINEST_MAX_SHARE if finest else fit_plan.MAX_SHARE)
        rung = next(r for r in fit_plan.LADDER if list(r.resolutions) == plan.resolutions)
        assert plan.steps == rung.scaled(plan.share)
        finer = [r for r in fit_plan.LADDER if r.resolutions[-1] > plan.resolutions[-1]]
        for other in finer:  # the finest that fits: no finer rung fits with its fewest steps
            now, fewest = Outlook(voxels=FACTS.box_voxels(other.resolutions[0])), other.scaled(fit_plan.MIN_SHARE)
            assert fit_plan.predict(MEASURED, FACTS, now, list(other.resolutions), fewest) > seconds
        finals.append(plan.resolutions[-1])
    assert finals == sorted(finals) and finals[-1] > finals[0] and len(set(finals)) >= 4, finals


def test_a_plan_is_no_finer_than_the_photos_have_pixels():
    small_photos = FitFacts(**{**FACTS.__dict__, "max_resolution": 160})
    plan = fit_plan.choose(3600, MEASURED, small_photos)
    assert plan.resolutions[-1] == 160 and plan.share == fit_plan.FINEST_MAX_SHARE and plan.predicted < 3600
    assert fit_plan.choose(3600, MEASURED, FACTS).resolutions[-1] == max(r.resolutions[-1] for r in fit_plan.LADDER) == 512


@pytest.mark.parametrize("first_level_scale", [1.0, 0.75])
def test_a_little_more_time_never_skips_two_grids_below_128(first_level_scale):
    """Between 64 and 128 each final grid 16 finer is a plan of its own: a budget a few seconds short of one falls to
    the grid 16 coarser, not 32 (a room's ladder starts its first levels at 0.75 of theirs)."""
    ladder = fit_plan.ladder_at(first_level_scale)
    finals, seconds = [], 1.0
    while seconds < 400:
        final = fit_plan.choose(seconds, MEASURED, FACTS, ladder).resolutions[-1]
        if final > 128:
            break
        if not finals or final != finals[-1]:
            finals.append(final)
        seconds *= 1.01
    assert finals == [64, 80, 96, 112, 128], finals


def test_a_budget_below_the_coarsest_plan_gets_what_fits_of_it():
    plan = fit_plan.choose(2.0, MEASURED, FACTS)
    coarsest = min(fit_plan.LADDER, key=lambda r: (r.resolutions[-1], len(r.resolutions)))
    assert not plan.fits and plan.resolutions == list(coarsest.resolutions) and plan.share < fit_plan.MIN_SHARE
    assert plan.predicted <= 2.0


def test_a_first_level_is_predicted_at_its_own_cost_model():
    """A first level's steps march the whole box: with a first-level model its prediction is its steps times that
    model at the box's voxels, and a later level's is the pruned model's as before."""
    dear = CostModel(**{**MEASURED.__dict__, "dense_fixed": 0.05, "dense_per_voxel": 3e-7})
    box = FACTS.box_voxels(64)
    first = Outlook(voxels=box)
    gap = fit_plan.predict(dear, FACTS, first, [64, 128], [500, 1000]) - fit_plan.predict(MEASURED, FACTS, first, [64, 128],
                                                                                      [500, 1000])
    assert gap == pytest.approx(500 * (dear.step_seconds(box, dense=True) - MEASURED.step_seconds(box)), rel=1e-6)
    later = Outlook(level=1, step=500, voxels=200_000, dense=False)
    assert fit_plan.predict(dear, FACTS, later, [64, 128], [500, 1000]) == fit_plan.predict(MEASURED, FACTS, later,
                                                                                       [64, 128], [500, 1000])
    # The dearer first levels buy a coarser (or shorter) plan for the same fit_plan.
    for seconds in (30, 120):
        mine, before = fit_plan.choose(seconds, dear, FACTS), fit_plan.choose(seconds, MEASURED, FACTS)
        assert mine.predicted <= seconds
        assert (mine.resolutions[-1], mine.share) < (before.resolutions[-1], before.share), (seconds, mine, before)


def test_an_upsampled_level_is_predicted_at_the_calibrations_ratio_until_the_scene_measures_one():
    """The calibration's upsampled grid costs `upsampled_ratio` times its model: a level at a finer resolution is
    predicted at that until the fit has measured steps at such a level, whatever the first resolution measured above
    the model (a coarse grid's pruned rest runs dearer than the finer levels after it), and times the first
    resolution's ratio where that is below 1 (a machine faster than its retime read it); a first level's early-pruned
    rest, at the first resolution, is not upsampled."""
    dear = CostModel(**{**MEASURED.__dict__, "upsampled_ratio": 1.5})
    facts = FitFacts(**{**FACTS.__dict__, "checkpoint_every": 1e9, "eval_rays": 0})  # the steps' time alone
    resolutions, steps, voxels = [128, 128, 256], [200, 800, 1500], 300_000
    rest = Outlook(level=1, step=400, voxels=voxels, dense=False, step_ratio=1.2)
    finer = min(facts.voxel_budget, rest.later_keep * voxels * 8)
    gap = fit_plan.predict(dear, facts, rest, resolutions, steps) - fit_plan.predict(MEASURED, facts, rest, resolutions,
                                                                                 steps)
    assert gap == pytest.approx(1500 * 0.5 * MEASURED.step_seconds(finer), rel=1e-6)

    # Right after the level change, before the finer level's steps are measured: its steps at the upsampled ratio,
    # the first resolution's ratio counting only below 1.
    def changed(first_ratio: float) -> float:
        now = Outlook(level=2, step=1000, voxels=finer, dense=False, step_ratio=first_ratio)
        return fit_plan.predict(dear, facts, now, resolutions, steps)

    assert changed(2.0) == changed(1.2) == changed(1.0)
    assert changed(1.0) - fit_plan.predict(MEASURED, facts, Outlook(level=2, step=1000, voxels=finer, dense=False),
                                           resolutions, steps) == pytest.approx(gap, rel=1e-6)
    assert changed(1.0) - changed(0.8) == pytest.approx(1500 * 0.2 * 1.5 * MEASURED.step_seconds(finer), rel=1e-6)
    # Measured there: the scene's own ratio, whatever the calibration said.
    measured = Outlook(level=2, step=1100, voxels=finer, dense=False, step_ratio=1.7, ratio_at_first=False)
    assert fit_plan.predict(dear, facts, measured, resolutions, steps) == fit_plan.predict(MEASURED, facts, measured,
                                                                                       resolutions, steps)
    # The first resolution's levels alone are not upsampled.
    assert fit_plan.predict(dear, facts, rest, resolutions[:2], steps[:2]) == fit_plan.predict(
        MEASURED, facts, rest, resolutions[:2], steps[:2])
    for seconds in (60, 240):  # a dearer upsampled grid buys a coarser (or shorter) plan, which fits
        mine, before = fit_plan.choose(seconds, dear, FACTS), fit_plan.choose(seconds, MEASURED, FACTS)
        assert mine.predicted <= seconds
        assert (mine.resolutions[-1], mine.share) < (before.resolutions[-1], before.share), (seconds, mine, before)


def test_a_32_start_reaches_a_128_grid_on_a_budget_a_dense_64_start_cannot():
    """A first level is its whole box: starting at 32^3 makes a 128^3 plan cheaper than 64->128's, and a budget
    between the two gets the 32^3 start rather than a coarser grid."""
    three = next(r for r in fit_plan.LADDER if r.resolutions == (32, 64, 128))
    two = next(r for r in fit_plan.LADDER if r.resolutions[0] == 64 and r.resolutions[-1] == 128)

    def fewest(rung):
        now = FACTS.outlook(voxels=FACTS.box_voxels(rung.resolutions[0]))
        return fit_plan.predict(MEASURED, FACTS, now, list(rung.resolutions), rung.scaled(fit_plan.MIN_SHARE))

    assert fewest(three) < fewest(two)
    plan = fit_plan.choose((fewest(three) + fewest(two)) / 2, MEASURED, FACTS)
    assert plan.resolutions == [32, 64, 128] and plan.fits


def test_of_rungs_ending_at_one_resolution_the_plan_takes_the_one_that_gets_the_most_steps():
    """Rungs that end at the same resolution: the budget gets whichever its cost model says gets the larger share of
    its steps, not the first in the ladder's order."""
    three = next(r for r in fit_plan.LADDER if r.resolutions == (32, 64, 128))

    def fewest(rung):
        now = FACTS.outlook(voxels=FACTS.box_voxels(rung.resolutions[0]))
        return fit_plan.predict(MEASURED, FACTS, now, list(rung.resolutions), rung.scaled(fit_plan.MIN_SHARE))

    for other in (Rung((64, 128), (100, 200)), Rung((64, 128), (5000, 10000))):
        cheaper = other if fewest(other) < fewest(three) else three
        seconds = 1.5 * max(fewest(other), fewest(three))  # both fit with more than MIN_SHARE
        plan = fit_plan.choose(seconds, MEASURED, FACTS, (three, other))
        assert tuple(plan.resolutions) == cheaper.resolutions and plan.fits and plan.predicted <= seconds
    assert fewest(Rung((64, 128), (100, 200))) < fewest(three) < fewest(Rung((64, 128), (5000, 10000)))


@pytest.mark.parametrize("scene_type", ["unbounded", "forward"])
def test_a_scene_that_fills_its_box_is_planned_coarser_for_the_same_budget(scene_type):
    """An unbounded scene's first prune keeps most of its box (the room), as does a forward capture's (its frustum, the
    scene out to the far plane), so its later levels cost more than an object's: the same budget buys it a coarser or
    shorter plan, which its prediction says fits."""
    room = FitFacts(**{**FACTS.__dict__, "first_keep": fit_plan.FIRST_KEEP_PRIOR[scene_type]})
    assert room.first_keep > FACTS.first_keep
    coarser = 0
    for seconds in (60, 120, 300):
        mine, objects = fit_plan.choose(seconds, MEASURED, room), fit_plan.choose(seconds, MEASURED, FACTS)
        assert mine.fits and mine.predicted <= seconds
        assert (mine.resolutions[-1], mine.share) <= (objects.resolutions[-1], objects.share), (seconds, mine, objects)
        # What the room's plan predicts for the object's plan is over the budget: the prior is what changed it.
        if mine.resolutions != objects.resolutions:
            coarser += 1
            now = room.outlook(voxels=room.box_voxels(objects.resolutions[0]))
            assert fit_plan.predict(MEASURED, room, now, objects.resolutions, objects.steps) > seconds
    assert coarser >= 2


def test_a_replan_follows_the_measured_cost_and_drops_a_level_that_cannot_converge():
    rung = Rung((128, 256, 384), (1000, 1500, 1500))
    resolutions, steps = list(rung.resolutions), rung.scaled(1.0)
    now = Outlook(level=1, step=1100, voxels=2_000_000, dense=False)
    fast_left = fit_plan.predict(MEASURED, FACTS, now, resolutions, steps)
    kept, new_steps, share = fit_plan.replan(fast_left, MEASURED, FACTS, now, rung, resolutions, steps, measured=True)
    assert kept == resolutions and share == pytest.approx(1.0, abs=0.02)
    assert fit_plan.predict(MEASURED, FACTS, now, kept, new_steps) <= fast_left

    # Measured at the 256 level (upsampled): three times slower than modelled.
    now.step_seconds, now.step_ratio, now.ratio_at_first = 3 * MEASURED.step_seconds(2_000_000), 3.0, False
    kept, new_steps, share = fit_plan.replan(fast_left, MEASURED, FACTS, now, rung, resolutions, steps, measured=True)
    assert fit_plan.predict(MEASURED, FACTS, now, kept, new_steps) <= fast_left
    assert new_steps[0] == steps[0] and new_steps[1] >= 100  # the levels done stay as they were
    assert kept == resolutions[:2] and share >= fit_plan.MIN_SHARE  # the 384 level could not get half its steps


def test_a_replan_keeps_a_short_level_rather_than_end_the_fit_early_without_it():
    """After a level change, steps dearer than modelled leave the last level less than half its steps; without it the
    levels before, at twice their steps, would end the fit with time unused: it stays, lowered to the finest
    resolution that gets half its steps."""
    rung = next(r for r in fit_plan.LADDER if r.resolutions == (32, 64, 128))
    resolutions, planned = list(rung.resolutions), rung.scaled(0.6)
    now = Outlook(level=1, step=planned[0] + 20, voxels=50_000, dense=False, step_ratio=1.3, ratio_at_first=False,
                  step_seconds=1.3 * MEASURED.step_seconds(50_000))

    def left(levels, share, last=resolutions[-1]):  # the first level done as planned
        steps = planned[:1] + rung.scaled(share)[1:]
        return fit_plan.predict(MEASURED, FACTS, now, (resolutions[:-1] + [last])[:levels], steps[:levels])

    two_at_most, three_at_least = left(2, fit_plan.MAX_SHARE), left(3, fit_plan.MIN_SHARE)
    assert two_at_most < three_at_least
    seconds = (two_at_most + three_at_least) / 2
    kept, steps, share = fit_plan.replan(seconds, MEASURED, FACTS, now, rung, resolutions, planned, measured=True)
    assert kept[:2] == resolutions[:2] and kept[2] < resolutions[2] and share >= fit_plan.MIN_SHARE
    assert (resolutions[2] - kept[2]) % fit_plan.LOWER_BY == 0
    assert left(3, fit_plan.MIN_SHARE, kept[2] + fit_plan.LOWER_BY) > seconds  # one rung finer does not get half
    assert fit_plan.predict(MEASURED, FACTS, now, kept, steps) <= seconds
    # Where the levels before would use the time, the level is dropped, as before.
    seconds = two_at_most * 0.99
    kept, steps, share = fit_plan.replan(seconds, MEASURED, FACTS, now, rung, resolutions, planned, measured=True)
    assert kept == resolutions[:2] and fit_plan.MIN_SHARE <= share < fit_plan.MAX_SHARE


def test_a_replan_during_the_first_level_drops_a_third_level_but_keeps_two():
    """Steps 3x dearer than modelled, measured early in the first level: a plan that cannot give its levels half their
    steps loses its third level before the first level gives up steps for it, never its second (the level after the
    first resolution, not the first level's own early prune)."""
    three = next(r for r in fit_plan.LADDER if r.resolutions == (128, 128, 256, 384))
    two = next(r for r in fit_plan.LADDER if r.resolutions == (128, 128, 256))
    now = Outlook(level=0, step=100, voxels=FACTS.box_voxels(128), dense=True, step_ratio=3.0,
                  step_seconds=3 * MEASURED.step_seconds(FACTS.box_voxels(128)))
    planned = three.scaled(fit_plan.MIN_SHARE)
    seconds = 0.6 * fit_plan.predict(MEASURED, FACTS, now, list(three.resolutions), planned)
    kept, steps, share = fit_plan.replan(seconds, MEASURED, FACTS, now, three, list(three.resolutions), planned,
                                       measured=False)
    assert kept == [128, 128, 256] and share >= fit_plan.MIN_SHARE and steps[1] > planned[1]
    assert steps[0] == planned[0]  # the early prune stays where it was
    assert fit_plan.predict(MEASURED, FACTS, now, kept, steps) <= seconds
    # Not even two resolutions get half their steps: both stay, with what fits.
    tight = 0.3 * fit_plan.predict(MEASURED, FACTS, now, list(two.resolutions), two.scaled(fit_plan.MIN_SHARE))
    kept, steps, share = fit_plan.replan(tight, MEASURED, FACTS, now, two, list(two.resolutions), two.scaled(1.0),
                                       measured=False)
    assert kept == [128, 128, 256] and 0 < share < fit_plan.MIN_SHARE
    assert fit_plan.predict(MEASURED, FACTS, now, kept, steps) <= tight


def test_a_last_level_short_of_half_its_steps_is_lowered_once_the_first_prune_has_measured_the_scene():
    """Steps 2.5x dearer than modelled, measured after the first level's early prune, in a room seen from inside (90%
    of the box kept) and in an object's scene (20%): the 256 level cannot get half its steps, so it is lowered by
    LOWER_BY to the finest resolution that can; with the time for it, it stays at 256. Before the first prune has
    measured what the scene keeps, it stays at 256, short."""
    two = next(r for r in fit_plan.LADDER if r.resolutions == (128, 128, 256))
    resolutions, planned = list(two.resolutions), two.scaled(1.0)

    def at_half(now: Outlook, last: int) -> float:
        return fit_plan.predict(MEASURED, FACTS, now, resolutions[:2] + [last], two.scaled(fit_plan.MIN_SHARE))

    scenes = [Outlook(level=1, step=two.steps[0] + 50, voxels=voxels, dense=False, step_ratio=2.5,
                      step_seconds=2.5 * MEASURED.step_seconds(voxels), first_keep=first_keep)
              for first_keep in (0.9, 0.2) for voxels in [int(first_keep * FACTS.box_voxels(128))]]
    for now in scenes:
        seconds = 0.6 * at_half(now, 256)
        kept, steps, share = fit_plan.replan(seconds, MEASURED, FACTS, now, two, resolutions, planned, measured=False)
        assert kept[:2] == [128, 128] and 128 < kept[2] < 256 and (256 - kept[2]) % fit_plan.LOWER_BY == 0
        assert share >= fit_plan.MIN_SHARE and steps[0] == planned[0]
        assert fit_plan.predict(MEASURED, FACTS, now, kept, steps) <= seconds
        assert at_half(now, kept[2] + fit_plan.LOWER_BY) > seconds  # the finest that fits: one rung finer does not

        kept, steps, share = fit_plan.replan(1.01 * at_half(now, 256), MEASURED, FACTS, now, two, resolutions,
                                           planned, measured=False)
        assert kept == resolutions and share >= fit_plan.MIN_SHARE

    dense = dataclasses.replace(scenes[0], level=0, step=100, dense=True)
    seconds = 0.6 * at_half(dense, 256)
    kept, steps, share = fit_plan.replan(seconds, MEASURED, FACTS, dense, two, resolutions, planned, measured=False)
    assert kept == resolutions and share < fit_plan.MIN_SHARE


def test_the_last_pruning_pass_is_predicted_at_the_held_out_renders_measured_ratio():
    slower = Outlook(eval_ratio=3.0)
    assert fit_plan.finish_seconds(MEASURED, FACTS, slower, 128, 1e5) - fit_plan.finish_seconds(
        MEASURED, FACTS, Outlook(), 128, 1e5) == pytest.approx(
        2 * MEASURED.pass_seconds(FACTS.prune_rays(128) + FACTS.eval_rays, 128))  # the last pruning pass and the held-out
    # A fit that measures its photos' gains across their frames as it ends keeps the time of that pass too.
    lattice = dataclasses.replace(FACTS, finish_rays=lambda: 300_000)
    assert fit_plan.finish_seconds(MEASURED, lattice, slower, 128, 1e5) - fit_plan.finish_seconds(
        MEASURED, FACTS, slower, 128, 1e5) == pytest.approx(3.0 * MEASURED.pass_seconds(300_000, 128))


def test_time_left_goes_into_steps_where_no_finer_grid_can_take_it():
    """Past MAX_SHARE the steps grow, up to FINEST_MAX_SHARE, only where a finer grid is no option: at the finest rung
    the photos are worth, or once the fit is in its last level. A last level still to come, with finer rungs the
    photos are worth above it, is raised to the finest of them instead."""
    rung = next(r for r in fit_plan.LADDER if r.resolutions == (128, 128, 256, 384))
    resolutions, planned = list(rung.resolutions), rung.scaled(1.0)
    plenty = 1e6
    before = Outlook(level=2, step=sum(planned[:2]) + 10, voxels=300_000, dense=False)
    kept, _, share = fit_plan.replan(plenty, MEASURED, FACTS, before, rung, resolutions, planned, measured=True)
    assert kept == resolutions[:3] + [512] and share == fit_plan.FINEST_MAX_SHARE
    inside = Outlook(level=3, step=sum(planned[:3]) + 10, voxels=2_000_000, dense=False)
    kept, steps, share = fit_plan.replan(plenty, MEASURED, FACTS, inside, rung, resolutions, planned, measured=True)
    assert kept == resolutions and share == fit_plan.FINEST_MAX_SHARE
    assert steps[:3] == planned[:3] and steps[3] == rung.scaled(fit_plan.FINEST_MAX_SHARE)[3]
    photos_of_400 = FitFacts(**{**FACTS.__dict__, "max_resolution": 400})
    kept, _, share = fit_plan.replan(plenty, MEASURED, photos_of_400, before, rung, resolutions, planned, measured=True)
    assert kept == resolutions and share == fit_plan.FINEST_MAX_SHARE


def test_a_last_level_to_come_with_time_to_spare_is_raised_to_the_finest_that_gets_half_its_steps():
    """A first level measured at a quarter of its model (a contracted room's 32^3): its plan of 32 -> 64 would give
    the 64 level MAX_SHARE and still leave time, so the re-plan raises that level, by LOWER_BY from the finest rung,
    to the finest resolution that gets MIN_SHARE of its steps (one finer does not fit). With time for less than
    MAX_SHARE, or once the fit is in its last level, the resolution stays."""
    rung = next(r for r in fit_plan.LADDER if r.resolutions == (32, 64))
    resolutions, planned = list(rung.resolutions), rung.scaled(1.0)
    box = FACTS.box_voxels(32)
    cheap = Outlook(level=0, step=40, voxels=box, dense=True, step_seconds=0.25 * MEASURED.step_seconds(box, dense=True),
                    first_keep=0.75)

    def at(share: float, last: int, now: Outlook = cheap) -> float:
        return fit_plan.predict(MEASURED, FACTS, now, [32, last], rung.scaled(share))

    seconds = 3 * at(fit_plan.MAX_SHARE, 64)
    kept, steps, share = fit_plan.replan(seconds, MEASURED, FACTS, cheap, rung, resolutions, planned, measured=False)
    assert kept[0] == 32 and 64 < kept[1] < 512 and (512 - kept[1]) % fit_plan.LOWER_BY == 0
    assert share >= fit_plan.MIN_SHARE and steps == rung.scaled(share)
    assert fit_plan.predict(MEASURED, FACTS, cheap, kept, steps) <= seconds
    assert at(fit_plan.MIN_SHARE, kept[1] + fit_plan.LOWER_BY) > seconds  # the finest that gets its steps

    # Time for fewer than MAX_SHARE of the steps at 64: it stays, with what fits.
    kept, steps, share = fit_plan.replan(at(1.5, 64), MEASURED, FACTS, cheap, rung, resolutions, planned,
                                       measured=False)
    assert kept == resolutions and share == pytest.approx(1.5, abs=0.01)
    # In its last level the fit cannot change the grid it is training: the time goes into steps.
    inside = Outlook(level=1, step=planned[0] + 10, voxels=50_000, dense=False)
    kept, _, share = fit_plan.replan(seconds, MEASURED, FACTS, inside, rung, resolutions, planned, measured=True)
    assert kept == resolutions and share == fit_plan.FINEST_MAX_SHARE


def test_a_budget_takes_photos_smaller_than_the_presets_finest_grid_whole():
    assert fit_plan.photo_scale(160, 0.5, 256) == 1.0
    assert fit_plan.photo_scale(160, 1.0, 256) == 1.0


def test_a_budget_takes_photos_as_fine_as_the_presets_finest_grid_and_no_finer():
    scale = fit_plan.photo_scale(320, 0.5, 256)
    assert 0.5 < scale < 1.0 and 320 * scale == pytest.approx(256)


def test_a_budget_keeps_the_presets_share_where_its_photos_already_reach_its_finest_grid():
    assert fit_plan.photo_scale(800, 0.5, 256) == 0.5
    assert fit_plan.photo_scale(1920, 0.75, 384) == 0.75


def test_a_grid_with_the_background_spheres_plans_more_steps_for_a_fine_grid_and_never_a_finer_one():
    """A bounded grid with the background spheres (a room's foreground box) gives a plan ending finer than COARSE_LAST
    at least its fine least share of the steps: where an object's plan reaches a finer grid on fewer steps, the room's
    stays a rung coarser with more of them. At or below COARSE_LAST both plan alike."""
    room = dataclasses.replace(FACTS, fine_min_share=1.0)
    assert room.least_share(fit_plan.COARSE_LAST) == fit_plan.MIN_SHARE < room.least_share(fit_plan.COARSE_LAST + 1)
    coarser = alike = 0
    for seconds in (10, 20, 30, 60, 120, 300, 600, 1200):
        ours, objects = fit_plan.choose(seconds, MEASURED, room), fit_plan.choose(seconds, MEASURED, FACTS)
        assert ours.fits and ours.predicted <= seconds, (seconds, ours)
        assert ours.share >= room.least_share(ours.resolutions[-1]), (seconds, ours)
        assert ours.resolutions[-1] <= objects.resolutions[-1], (seconds, ours, objects)
        if objects.resolutions[-1] <= fit_plan.COARSE_LAST:
            assert ours == objects, (seconds, ours, objects)
            alike += 1
        coarser += ours.resolutions[-1] < objects.resolutions[-1]
        for other in (r for r in fit_plan.LADDER if r.resolutions[-1] > ours.resolutions[-1]):
            now = Outlook(voxels=room.box_voxels(other.resolutions[0]))
            least = room.least_share(other.resolutions[-1])
            assert fit_plan.predict(MEASURED, room, now, list(other.resolutions), other.scaled(least)) > seconds
    assert coarser >= 3 and alike >= 1, (coarser, alike)


def test_a_fine_least_share_never_drops_a_planned_level():
    """A fit running slower than its plan keeps its fine last level down to MIN_SHARE of the steps, as any fit does."""
    room = dataclasses.replace(FACTS, fine_min_share=1.0)
    rung = Rung((64, 64, 256), (120, 500, 1000), 0)
    now = Outlook(level=1, step=400, voxels=2_000_000, dense=False, step_seconds=0.05)
    for seconds in (700, 900):  # time for 0.58 and 0.75 of the steps
        kept = fit_plan.replan(seconds, MEASURED, room, now, rung, [64, 64, 256], [120, 500, 1000], True)
        assert kept[0] == [64, 64, 256] and fit_plan.MIN_SHARE <= kept[2] < room.fine_min_share, kept
        assert kept == fit_plan.replan(seconds, MEASURED, FACTS, now, rung, [64, 64, 256], [120, 500, 1000], True)


def test_an_upsampled_grids_own_pruning_pass_is_priced_as_a_pass_and_its_steps_at_what_it_keeps():
    """With fit.prune_upsampled a level change to a finer resolution adds a pruning pass at that resolution, and the
    level's steps, checkpoints and save are predicted at the share of the upsample that pass keeps; a change at the
    same resolution (an early prune) has no such pass. Cheaper finer levels buy a plan at least as fine."""
    facts = FitFacts(**{**FACTS.__dict__, "checkpoint_every": 1e9, "eval_rays": 0})  # steps, changes and the end
    pruned = FitFacts(**{**facts.__dict__, "prune_upsampled": True})
    resolutions, steps, voxels = [128, 128, 256], [200, 800, 1500], 300_000
    now = Outlook(level=1, step=400, voxels=voxels, dense=False, upsample_band=0.3)
    grown, keep = now.later_keep * voxels * 8, fit_plan.upsample_keep(0.3, 2.0)
    gap = fit_plan.predict(MEASURED, facts, now, resolutions, steps) - fit_plan.predict(MEASURED, pruned, now,
                                                                                     resolutions, steps)
    saved_per_voxel = 1500 * MEASURED.step_per_voxel + MEASURED.checkpoint_per_voxel + MEASURED.save_per_voxel
    assert gap == pytest.approx(saved_per_voxel * (1 - keep) * grown - MEASURED.pass_seconds(170_000, 256), rel=1e-6)
    # The same resolution only: the early prune is not an upsample.
    first = Outlook(voxels=FACTS.box_voxels(128))
    assert fit_plan.predict(MEASURED, facts, first, resolutions[:2], steps[:2]) == fit_plan.predict(
        MEASURED, pruned, first, resolutions[:2], steps[:2])
    # A wider band of surfaces as measured: more kept, more time.
    wider = dataclasses.replace(now, upsample_band=1.0)
    assert fit_plan.predict(MEASURED, pruned, wider, resolutions, steps) > fit_plan.predict(
        MEASURED, pruned, now, resolutions, steps)
    for seconds in (60, 240, 900):
        mine, before = fit_plan.choose(seconds, MEASURED, pruned), fit_plan.choose(seconds, MEASURED, facts)
        assert mine.predicted <= seconds
        assert (mine.resolutions[-1], mine.share) >= (before.resolutions[-1], before.share), (seconds, mine, before)


@pytest.mark.parametrize("band", [0.0, 0.22, 1.0, 5.0])
def test_what_an_upsamples_own_pass_keeps_is_a_shells_share_read_back_from_one_growth_for_another(band):
    """The band of surfaces grows with the cells and the dilation does not: a finer upsample keeps less of itself, a
    band of none keeps one over the growth, and the band read from one upsample's share predicts another's (lego's
    0.59 at 128->256 read 0.73 at 256->384, as its pass then kept)."""
    shares = [fit_plan.upsample_keep(band, growth) for growth in (1.0, 1.5, 2.0, 2.5, 3.0)]
    assert shares[0] == 1.0 and all(a > b for a, b in zip(shares, shares[1:])) and all(0 < s <= 1 for s in shares)
    assert fit_plan.upsample_keep(0.0, 2.5) == pytest.approx(1 / 2.5)
    for growth in (1.5, 2.0, 2.5):
        share = fit_plan.upsample_keep(band, growth)
        assert fit_plan.upsample_band(share, growth) == pytest.approx(band, abs=1e-9)
    assert fit_plan.upsample_keep(fit_plan.upsample_band(0.59, 2.0), 1.5) == pytest.approx(0.73, abs=0.01)
    assert fit_plan.upsample_band(0.3, 2.5) == 0.0  # kept less than a band of none: none


def test_a_level_that_began_as_a_pruned_upsample_is_predicted_to_keep_more_at_its_own_prune():
    """With fit.prune_upsampled a grid that began as an upsample pruned on its own render is tight: the prune that
    ends its level keeps the settled share, where a level at the first resolution (its early-pruned rest) keeps the
    later prunes' share."""
    facts = FitFacts(**{**FACTS.__dict__, "checkpoint_every": 1e9, "eval_rays": 0, "prune_upsampled": True})
    resolutions, steps = [128, 128, 256, 384], [200, 800, 1000, 1000]
    at_256 = Outlook(level=2, step=1000, voxels=1_000_000, dense=False, later_keep=0.6)

    def predicted(**keep) -> float:
        return fit_plan.predict(MEASURED, facts, dataclasses.replace(at_256, **keep), resolutions, steps)

    assert predicted(settled_keep=0.97) > predicted(settled_keep=0.6)
    assert predicted(later_keep=0.9) == predicted()  # the 384 level's voxels follow the settled share only
    at_rest = Outlook(level=1, step=400, voxels=300_000, dense=False)
    rest = fit_plan.predict(MEASURED, facts, at_rest, resolutions[:3], steps[:3])
    assert fit_plan.predict(MEASURED, facts, dataclasses.replace(at_rest, settled_keep=0.3), resolutions[:3],
                            steps[:3]) == rest
    assert fit_plan.predict(MEASURED, facts, dataclasses.replace(at_rest, later_keep=0.3), resolutions[:3],
                            steps[:3]) < rest


def test_a_first_prune_that_keeps_most_of_its_box_speaks_for_the_later_prunes_until_one_is_measured():
    """A room seen from inside keeps most of itself at its first prune and again at the next: its early-pruned first
    resolution's rest is predicted to keep the first prune's share, not the prior's, and so its finer levels to be as
    large as they will be. An object's first prune clears its box's air, and the prior stands for its rest."""
    facts = FitFacts(**{**FACTS.__dict__, "checkpoint_every": 1e9, "eval_rays": 0})
    resolutions, steps = [48, 48, 128], [100, 200, 500]

    def after_first_prune(share: float) -> Outlook:
        now = Outlook(level=1, step=100, voxels=int(share * 48 ** 3), dense=False)
        now.kept("first_keep", share)
        return now

    room, thing = after_first_prune(0.97), after_first_prune(0.2)
    assert room.later_keep == 0.97 and thing.later_keep == fit_plan.LATER_KEEP_PRIOR
    on_prior = dataclasses.replace(room, later_keep=fit_plan.LATER_KEEP_PRIOR)
    assert (fit_plan.predict(MEASURED, facts, room, resolutions, steps)
            > fit_plan.predict(MEASURED, facts, on_prior, resolutions, steps))
    room.kept("later_keep", 0.7)  # measured: it stands
    assert room.later_keep == 0.7 and room.first_keep == 0.97
    room.kept("first_keep", 0.5)  # a first share below a measured later one leaves it
    assert room.later_keep == 0.7
