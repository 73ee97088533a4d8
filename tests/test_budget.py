"""The fit's time budget: durations, the cached calibration, plans that fit, and budgeted fits that end on time."""
import dataclasses
import json
import os
import shutil
import signal
import time

import pytest
import torch
from test_fit import QUICK, make_scene, run_stage

from pipeline import config
from pipeline.io import read_json
from plenoxels import budget
from plenoxels.budget import CostModel, FitFacts, Outlook, Rung
from plenoxels.errors import UserError
from plenoxels.train import Fitter
from stages import fit

# A tiny ladder and a cost model that thinks every step is free: the plan then asks for far more steps than the
# budget holds, and only the deadline's stop can end the fit on time.
TINY_LADDER = (Rung((16, 32), (400, 800)),)
FREE = CostModel(step_fixed=1e-6, step_per_voxel=1e-12, pass_per_ray=1e-12, change_per_voxel=1e-12,
                 checkpoint_per_voxel=1e-12, save_per_voxel=1e-12)
# Roughly what this machine measured with the fast preset's options on one thread.
MEASURED = CostModel(step_fixed=0.018, step_per_voxel=7e-8, pass_per_ray=1.7e-8, change_per_voxel=5e-7,
                     checkpoint_per_voxel=4e-7, save_per_voxel=1e-7)
FACTS = FitFacts(box_voxels=lambda r: r ** 3, prune_rays=lambda r: 170_000, eval_rays=3600, eval_every=250,
                 checkpoint_every=180.0, voxel_budget=16_000_000)
# What the budgeted fits of the tiny scene share with tests/test_fit.py, without its levels.
BUDGETED = {k: v for k, v in QUICK.items() if k not in ("resolutions", "steps")} | {"sh_degree": 1}


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    """Calibrations go to a folder of the test's own, never to the user's cache."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("budget"))


@pytest.fixture
def fresh(scene, tmp_path):
    root = tmp_path / "scene"
    shutil.copytree(scene / "synth", root / "synth")
    shutil.copytree(scene / "normalize", root / "normalize")
    return root


# ---- the setting ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("value, seconds", [("90s", 90), ("5m", 300), ("2m30s", 150), ("1h", 3600), (90, 90),
                                            ("90", 90), (12.5, 12.5), ("1.5m", 90), (0, 0), ("0", 0), ("", 0)])
def test_time_budget_takes_durations(value, seconds):
    assert config.build(fit.Settings, "fit", {"time_budget": value}).budget_seconds == seconds


@pytest.mark.parametrize("raw", ["5x", "abc", "-3", "30s2m", "5m5m", "m", "null", "inf"])
def test_a_bad_time_budget_is_a_one_line_error_naming_the_key(raw):
    values = config.parse_overrides([f"fit.time_budget={raw}"])["fit"]
    with pytest.raises(UserError) as info:
        config.build(fit.Settings, "fit", values)
    message = str(info.value)
    assert "fit.time_budget" in message and "\n" not in message


def test_the_default_is_no_budget():
    assert fit.Settings().budget_seconds == 0


# ---- the calibration -----------------------------------------------------------------------------------------------
def test_the_calibration_is_cached_reused_and_measured_again_for_another_key(monkeypatch):
    options = config.build(fit.Settings, "fit", {"batch_size": 512, "sh_degree": 0})
    small, first = (16, 24, 32), (8, 16)
    measured = []
    original = budget.measure
    monkeypatch.setattr(budget, "measure", lambda *a, **k: measured.append(1) or original(*a, **k))
    cpu = torch.device("cpu")

    costs, record = budget.calibrate(options, cpu, None, small, first)
    assert not record["cached"] and len(measured) == 1
    assert costs.step_fixed + costs.step_per_voxel * 1e5 > 0 and costs.pass_seconds(1e5, 32) > 0
    assert costs.step_seconds(1e5, dense=True) > 0 and costs.dense_fixed is not None
    assert [p["voxels"] for p in record["first_level_points"]] == [8 ** 3, 16 ** 3]  # a new model's whole box
    assert [p["resolution"] for p in record["passes"]] == list(small)
    assert all(p["seconds"] > 0 for p in record["passes"])
    # The steps on the grid the level change upsampled, over the model at its voxels.
    change = record["level_change"]
    assert change["step_seconds"] > 0 and costs.upsampled_ratio == pytest.approx(
        change["step_seconds"] / costs.step_seconds(change["voxels"]), abs=1e-5 / costs.step_seconds(change["voxels"]))
    assert record["file"].startswith(os.environ["XDG_CACHE_HOME"])
    assert record["key"]["threads"] >= 1 and record["key"]["code"] and record["key"]["device"] == "cpu"

    again, record = budget.calibrate(options, cpu, None, small, first)
    assert record["cached"] and len(measured) == 1
    # The record's factor is rounded to 3 decimals: a factor far from 1 (a loaded machine's first timing) is off by
    # more than a relative 1e-3 of itself.
    assert again.step_fixed == pytest.approx(record["slower_now"] * costs.step_fixed, abs=5e-4 * costs.step_fixed)

    budget.calibrate(config.build(fit.Settings, "fit", {"batch_size": 256, "sh_degree": 0}), cpu, None, small, first)
    assert len(measured) == 2  # other options that set a step's cost
    budget.calibrate(options, cpu, {"n_spheres": 4, "width": 16}, small, first)
    assert len(measured) == 3  # a background model
    monkeypatch.setattr(budget.native, "num_threads", lambda: 97)
    budget.calibrate(options, cpu, None, small, first)
    assert len(measured) == 4  # another thread count
    monkeypatch.setattr(budget, "code_hash", lambda: "changed")
    _, record = budget.calibrate(options, cpu, None, small, first)
    assert len(measured) == 5 and not record["cached"]  # other code
    with open(record["file"], "w") as handle:
        handle.write("{ not json")
    _, record = budget.calibrate(options, cpu, None, small, first)
    assert len(measured) == 6 and not record["cached"]  # an unreadable cache file is measured again
    budget.calibrate(options, cpu, None, small, (8, 12))
    assert len(measured) == 7  # other first-level resolutions
    assert len(list(budget.cache_dir().glob("fit-cost-*.json"))) == 6

    # A cached calibration's times follow the machine's speed now, timed again on the calibration's first step.
    _, record = budget.calibrate(options, cpu, None, small, (8, 12))
    fresh_costs, reference = CostModel(**record["costs"]), record["points"][0]
    timed = []
    # Timed twice, the faster round counts: the first at 3x (a slow moment, fresh pages), the second at 2x.
    monkeypatch.setattr(budget, "_time_steps", lambda fitter, device, steps=8: timed.append(
        fitter.model.grid.num_occupied) or (3 if len(timed) == 1 else 2) * reference["step_seconds"])
    slower, record = budget.calibrate(options, cpu, None, small, (8, 12))
    assert record["cached"] and len(measured) == 7 and timed == [reference["voxels"]] * budget.RETIME_ROUNDS
    assert record["slower_now"] == pytest.approx(2.0)
    assert slower.step_fixed == pytest.approx(2 * fresh_costs.step_fixed)
    assert slower.step_seconds(1e5, dense=True) == pytest.approx(2 * fresh_costs.step_seconds(1e5, dense=True))
    assert slower.pass_seconds(1e5, 32) == pytest.approx(2 * fresh_costs.pass_seconds(1e5, 32))
    assert slower.upsampled_ratio == fresh_costs.upsampled_ratio  # a ratio of two times, whatever the speed


@pytest.mark.parametrize("points, grows", [
    ([(49_671, 0.00853), (228_352, 0.01501), (515_119, 0.02129)], True),    # a 2-core CPU's steps: a line
    ([(49_671, 0.00402), (228_352, 0.00423), (515_119, 0.00364)], False),   # an H100's: flat at these sizes
    ([(49_671, 0.00100), (228_352, 0.00900), (515_119, 0.02400)], True),    # rising faster than a line: no intercept
])
def test_the_step_line_reads_the_calibration_points_within_a_fifth(points, grows):
    """Steps that do not grow with the grid are a fixed cost: a line through the origin would put a GPU's 50k-voxel
    step at an eighth of what it measured, and the plan would carry that ratio to its finer levels."""
    fixed, per_voxel = budget._line(points)
    model = CostModel(step_fixed=fixed, step_per_voxel=per_voxel, pass_per_ray=0, change_per_voxel=0,
                      checkpoint_per_voxel=0, save_per_voxel=0)
    assert fixed >= 0 and per_voxel >= 0 and (per_voxel > 0) == grows
    # A line steeper than its points allow an intercept for is drawn through the origin: it reads the largest.
    for voxels, seconds in points[-1:] if grows and fixed == 0 else points:
        assert model.step_seconds(voxels) == pytest.approx(seconds, rel=0.2), (voxels, seconds, fixed, per_voxel)


# ---- plans ---------------------------------------------------------------------------------------------------------
def test_a_plan_never_predicts_more_than_its_budget_and_more_time_buys_a_finer_grid():
    finals = []
    for seconds in (20, 30, 45, 60, 90, 120, 180, 300, 600, 1200, 3600):
        plan = budget.choose(seconds, MEASURED, FACTS)
        assert plan.fits and plan.predicted <= seconds, (seconds, plan)
        assert budget.MIN_SHARE <= plan.share <= budget.MAX_SHARE
        rung = next(r for r in budget.LADDER if list(r.resolutions) == plan.resolutions)
        assert plan.steps == rung.scaled(plan.share)
        finer = [r for r in budget.LADDER if r.resolutions[-1] > plan.resolutions[-1]]
        for other in finer:  # the finest that fits: no finer rung fits with its fewest steps
            now, fewest = Outlook(voxels=FACTS.box_voxels(other.resolutions[0])), other.scaled(budget.MIN_SHARE)
            assert budget.predict(MEASURED, FACTS, now, list(other.resolutions), fewest) > seconds
        finals.append(plan.resolutions[-1])
    assert finals == sorted(finals) and finals[-1] > finals[0] and len(set(finals)) >= 4, finals


def test_a_plan_is_no_finer_than_the_photos_have_pixels():
    small_photos = FitFacts(**{**FACTS.__dict__, "max_resolution": 160})
    plan = budget.choose(3600, MEASURED, small_photos)
    assert plan.resolutions[-1] == 160 and plan.share == budget.MAX_SHARE and plan.predicted < 3600
    assert budget.choose(3600, MEASURED, FACTS).resolutions[-1] == 384


def test_a_budget_below_the_coarsest_plan_gets_what_fits_of_it():
    plan = budget.choose(2.0, MEASURED, FACTS)
    coarsest = min(budget.LADDER, key=lambda r: (r.resolutions[-1], len(r.resolutions)))
    assert not plan.fits and plan.resolutions == list(coarsest.resolutions) and plan.share < budget.MIN_SHARE
    assert plan.predicted <= 2.0


def test_a_first_level_is_predicted_at_its_own_cost_model():
    """A first level's steps march the whole box: with a first-level model its prediction is its steps times that
    model at the box's voxels, and a later level's is the pruned model's as before."""
    dear = CostModel(**{**MEASURED.__dict__, "dense_fixed": 0.05, "dense_per_voxel": 3e-7})
    box = FACTS.box_voxels(64)
    first = Outlook(voxels=box)
    gap = budget.predict(dear, FACTS, first, [64, 128], [500, 1000]) - budget.predict(MEASURED, FACTS, first, [64, 128],
                                                                                      [500, 1000])
    assert gap == pytest.approx(500 * (dear.step_seconds(box, dense=True) - MEASURED.step_seconds(box)), rel=1e-6)
    later = Outlook(level=1, step=500, voxels=200_000, dense=False)
    assert budget.predict(dear, FACTS, later, [64, 128], [500, 1000]) == budget.predict(MEASURED, FACTS, later,
                                                                                       [64, 128], [500, 1000])
    # The dearer first levels buy a coarser (or shorter) plan for the same budget.
    for seconds in (30, 120):
        mine, before = budget.choose(seconds, dear, FACTS), budget.choose(seconds, MEASURED, FACTS)
        assert mine.predicted <= seconds
        assert (mine.resolutions[-1], mine.share) < (before.resolutions[-1], before.share), (seconds, mine, before)


def test_an_upsampled_level_is_predicted_at_the_calibrations_ratio_until_the_scene_measures_one():
    """The calibration's upsampled grid costs `upsampled_ratio` times its model: a level at a finer resolution is
    predicted at that times the scene's ratio until the fit has measured steps at such a level; a first level's
    early-pruned rest, at the first resolution, is not upsampled."""
    dear = CostModel(**{**MEASURED.__dict__, "upsampled_ratio": 1.5})
    facts = FitFacts(**{**FACTS.__dict__, "checkpoint_every": 1e9, "eval_rays": 0})  # the steps' time alone
    resolutions, steps, voxels = [128, 128, 256], [200, 800, 1500], 300_000
    rest = Outlook(level=1, step=400, voxels=voxels, dense=False, step_ratio=1.2)
    finer = min(facts.voxel_budget, rest.later_keep * voxels * 8)
    gap = budget.predict(dear, facts, rest, resolutions, steps) - budget.predict(MEASURED, facts, rest, resolutions,
                                                                                 steps)
    assert gap == pytest.approx(1500 * 1.2 * 0.5 * MEASURED.step_seconds(finer), rel=1e-6)
    # Right after the level change, before the finer level's steps are measured: its steps at the upsampled ratio.
    changed = Outlook(level=2, step=1000, voxels=finer, dense=False, step_ratio=1.2)
    assert budget.predict(dear, facts, changed, resolutions, steps) - budget.predict(
        MEASURED, facts, changed, resolutions, steps) == pytest.approx(gap, rel=1e-6)
    # Measured there: the scene's own ratio, whatever the calibration said.
    measured = Outlook(level=2, step=1100, voxels=finer, dense=False, step_ratio=1.7, ratio_at_first=False)
    assert budget.predict(dear, facts, measured, resolutions, steps) == budget.predict(MEASURED, facts, measured,
                                                                                       resolutions, steps)
    # The first resolution's levels alone are not upsampled.
    assert budget.predict(dear, facts, rest, resolutions[:2], steps[:2]) == budget.predict(
        MEASURED, facts, rest, resolutions[:2], steps[:2])
    for seconds in (60, 240):  # a dearer upsampled grid buys a coarser (or shorter) plan, which fits
        mine, before = budget.choose(seconds, dear, FACTS), budget.choose(seconds, MEASURED, FACTS)
        assert mine.predicted <= seconds
        assert (mine.resolutions[-1], mine.share) < (before.resolutions[-1], before.share), (seconds, mine, before)


def test_a_32_start_reaches_a_128_grid_on_a_budget_a_dense_64_start_cannot():
    """A first level is its whole box: starting at 32^3 makes a 128^3 plan cheaper than 64->128's, and a budget
    between the two gets the 32^3 start rather than a coarser grid."""
    three = next(r for r in budget.LADDER if r.resolutions == (32, 64, 128))
    two = next(r for r in budget.LADDER if r.resolutions[0] == 64 and r.resolutions[-1] == 128)

    def fewest(rung):
        now = FACTS.outlook(voxels=FACTS.box_voxels(rung.resolutions[0]))
        return budget.predict(MEASURED, FACTS, now, list(rung.resolutions), rung.scaled(budget.MIN_SHARE))

    assert fewest(three) < fewest(two)
    plan = budget.choose((fewest(three) + fewest(two)) / 2, MEASURED, FACTS)
    assert plan.resolutions == [32, 64, 128] and plan.fits


def test_of_rungs_ending_at_one_resolution_the_plan_takes_the_one_that_gets_the_most_steps():
    """Rungs that end at the same resolution: the budget gets whichever its cost model says gets the larger share of
    its steps, not the first in the ladder's order."""
    three = next(r for r in budget.LADDER if r.resolutions == (32, 64, 128))

    def fewest(rung):
        now = FACTS.outlook(voxels=FACTS.box_voxels(rung.resolutions[0]))
        return budget.predict(MEASURED, FACTS, now, list(rung.resolutions), rung.scaled(budget.MIN_SHARE))

    for other in (Rung((64, 128), (100, 200)), Rung((64, 128), (5000, 10000))):
        cheaper = other if fewest(other) < fewest(three) else three
        seconds = 1.5 * max(fewest(other), fewest(three))  # both fit with more than MIN_SHARE
        plan = budget.choose(seconds, MEASURED, FACTS, (three, other))
        assert tuple(plan.resolutions) == cheaper.resolutions and plan.fits and plan.predicted <= seconds
    assert fewest(Rung((64, 128), (100, 200))) < fewest(three) < fewest(Rung((64, 128), (5000, 10000)))


def test_a_scene_that_fills_its_box_is_planned_coarser_for_the_same_budget():
    """An unbounded scene's first prune keeps most of its box (the room), so its later levels cost more than an
    object's: the same budget buys it a coarser or shorter plan, which its prediction says fits."""
    room = FitFacts(**{**FACTS.__dict__, "first_keep": budget.FIRST_KEEP_PRIOR["unbounded"]})
    assert room.first_keep > FACTS.first_keep
    coarser = 0
    for seconds in (60, 120, 300):
        mine, objects = budget.choose(seconds, MEASURED, room), budget.choose(seconds, MEASURED, FACTS)
        assert mine.fits and mine.predicted <= seconds
        assert (mine.resolutions[-1], mine.share) <= (objects.resolutions[-1], objects.share), (seconds, mine, objects)
        # What the room's plan predicts for the object's plan is over the budget: the prior is what changed it.
        if mine.resolutions != objects.resolutions:
            coarser += 1
            now = room.outlook(voxels=room.box_voxels(objects.resolutions[0]))
            assert budget.predict(MEASURED, room, now, objects.resolutions, objects.steps) > seconds
    assert coarser >= 2


def test_a_replan_follows_the_measured_cost_and_drops_a_level_that_cannot_converge():
    rung = Rung((128, 256, 384), (1000, 1500, 1500))
    resolutions, steps = list(rung.resolutions), rung.scaled(1.0)
    now = Outlook(level=1, step=1100, voxels=2_000_000, dense=False)
    fast_left = budget.predict(MEASURED, FACTS, now, resolutions, steps)
    kept, new_steps, share = budget.replan(fast_left, MEASURED, FACTS, now, rung, resolutions, steps, measured=True)
    assert kept == resolutions and share == pytest.approx(1.0, abs=0.02)
    assert budget.predict(MEASURED, FACTS, now, kept, new_steps) <= fast_left

    now.step_seconds, now.step_ratio = 3 * MEASURED.step_seconds(2_000_000), 3.0  # three times slower than modelled
    kept, new_steps, share = budget.replan(fast_left, MEASURED, FACTS, now, rung, resolutions, steps, measured=True)
    assert budget.predict(MEASURED, FACTS, now, kept, new_steps) <= fast_left
    assert new_steps[0] == steps[0] and new_steps[1] >= 100  # the levels done stay as they were
    assert kept == resolutions[:2] and share >= budget.MIN_SHARE  # the 384 level could not get half its steps


def test_a_replan_keeps_a_short_level_rather_than_end_the_fit_early_without_it():
    """After a level change, steps dearer than modelled leave the last level less than half its steps; without it the
    levels before, at twice their steps, would end the fit with time unused: it stays, with what fits."""
    rung = next(r for r in budget.LADDER if r.resolutions == (32, 64, 128))
    resolutions, planned = list(rung.resolutions), rung.scaled(0.6)
    now = Outlook(level=1, step=planned[0] + 20, voxels=50_000, dense=False, step_ratio=1.3,
                  step_seconds=1.3 * MEASURED.step_seconds(50_000))

    def left(levels, share):  # the first level done as planned
        steps = planned[:1] + rung.scaled(share)[1:]
        return budget.predict(MEASURED, FACTS, now, resolutions[:levels], steps[:levels])

    two_at_most, three_at_least = left(2, budget.MAX_SHARE), left(3, budget.MIN_SHARE)
    assert two_at_most < three_at_least
    seconds = (two_at_most + three_at_least) / 2
    kept, steps, share = budget.replan(seconds, MEASURED, FACTS, now, rung, resolutions, planned, measured=True)
    assert kept == resolutions and 0 < share < budget.MIN_SHARE
    assert budget.predict(MEASURED, FACTS, now, kept, steps) <= seconds
    # Where the levels before would use the time, the level is dropped, as before.
    seconds = two_at_most * 0.99
    kept, steps, share = budget.replan(seconds, MEASURED, FACTS, now, rung, resolutions, planned, measured=True)
    assert kept == resolutions[:2] and budget.MIN_SHARE <= share < budget.MAX_SHARE


def test_a_replan_during_the_first_level_drops_a_third_level_but_keeps_two():
    """Steps 3x dearer than modelled, measured early in the first level: a plan that cannot give its levels half their
    steps loses its third level before the first level gives up steps for it, never its second (the level after the
    first resolution, not the first level's own early prune)."""
    three, two = budget.LADDER[-1], budget.LADDER[-3]  # 128 -> 128 -> 256 -> 384 and 128 -> 128 -> 256
    assert three.resolutions == (128, 128, 256, 384) and two.resolutions == (128, 128, 256)
    now = Outlook(level=0, step=100, voxels=FACTS.box_voxels(128), dense=True, step_ratio=3.0,
                  step_seconds=3 * MEASURED.step_seconds(FACTS.box_voxels(128)))
    planned = three.scaled(budget.MIN_SHARE)
    seconds = 0.6 * budget.predict(MEASURED, FACTS, now, list(three.resolutions), planned)
    kept, steps, share = budget.replan(seconds, MEASURED, FACTS, now, three, list(three.resolutions), planned,
                                       measured=False)
    assert kept == [128, 128, 256] and share >= budget.MIN_SHARE and steps[1] > planned[1]
    assert steps[0] == planned[0]  # the early prune stays where it was
    assert budget.predict(MEASURED, FACTS, now, kept, steps) <= seconds
    # Not even two resolutions get half their steps: both stay, with what fits.
    tight = 0.3 * budget.predict(MEASURED, FACTS, now, list(two.resolutions), two.scaled(budget.MIN_SHARE))
    kept, steps, share = budget.replan(tight, MEASURED, FACTS, now, two, list(two.resolutions), two.scaled(1.0),
                                       measured=False)
    assert kept == [128, 128, 256] and 0 < share < budget.MIN_SHARE
    assert budget.predict(MEASURED, FACTS, now, kept, steps) <= tight


def test_a_last_level_short_of_half_its_steps_is_lowered_in_a_scene_that_fills_its_box():
    """Steps 2.5x dearer than modelled, measured after the first level's early prune kept 90% of the box (a room seen
    from inside): the 256 level cannot get half its steps, so it is lowered by LOWER_BY to the finest resolution that
    can; with the time for it, it stays at 256. In an object's scene (20% kept), or before the first prune has measured
    what the scene keeps, it stays at 256, short."""
    two = next(r for r in budget.LADDER if r.resolutions == (128, 128, 256))
    voxels = int(0.9 * FACTS.box_voxels(128))
    room = Outlook(level=1, step=two.steps[0] + 50, voxels=voxels, dense=False, step_ratio=2.5,
                   step_seconds=2.5 * MEASURED.step_seconds(voxels), first_keep=0.9)
    resolutions, planned = list(two.resolutions), two.scaled(1.0)

    def at_half(now: Outlook, last: int) -> float:
        return budget.predict(MEASURED, FACTS, now, resolutions[:2] + [last], two.scaled(budget.MIN_SHARE))

    seconds = 0.6 * at_half(room, 256)
    kept, steps, share = budget.replan(seconds, MEASURED, FACTS, room, two, resolutions, planned, measured=False)
    assert kept[:2] == [128, 128] and 128 < kept[2] < 256 and (256 - kept[2]) % budget.LOWER_BY == 0
    assert share >= budget.MIN_SHARE and steps[0] == planned[0]
    assert budget.predict(MEASURED, FACTS, room, kept, steps) <= seconds
    assert at_half(room, kept[2] + budget.LOWER_BY) > seconds  # the finest that fits: one rung finer does not

    kept, steps, share = budget.replan(1.01 * at_half(room, 256), MEASURED, FACTS, room, two, resolutions, planned,
                                       measured=False)
    assert kept == resolutions and share >= budget.MIN_SHARE

    for now in (dataclasses.replace(room, first_keep=0.2), dataclasses.replace(room, level=0, step=100, dense=True)):
        seconds = 0.6 * at_half(now, 256)
        kept, steps, share = budget.replan(seconds, MEASURED, FACTS, now, two, resolutions, planned, measured=False)
        assert kept == resolutions and share < budget.MIN_SHARE


def test_the_last_pruning_pass_is_predicted_at_the_held_out_renders_measured_ratio():
    slower = Outlook(eval_ratio=3.0)
    assert budget.finish_seconds(MEASURED, FACTS, slower, 128, 1e5) - budget.finish_seconds(
        MEASURED, FACTS, Outlook(), 128, 1e5) == pytest.approx(
        2 * MEASURED.pass_seconds(FACTS.prune_rays(128) + FACTS.eval_rays, 128))  # the last pruning pass and the held-out


# ---- budgeted fits -------------------------------------------------------------------------------------------------
def test_a_budgeted_fit_ends_within_its_budget_with_a_complete_model(fresh):
    seconds = 12.0
    started = time.time()
    summary = run_stage(fresh, fit, {**BUDGETED, "time_budget": f"{seconds:g}s"})
    took = time.time() - started
    # The budget covers the stage, its first calibration included; generous for a machine shared with other work.
    assert took <= 1.1 * seconds + 4.0, took
    record = read_json(fresh / "fit" / "fit.json")
    assert record["complete"] and (fresh / "fit" / "grid.pt").is_file()
    plan = record["budget"]
    assert plan["seconds"] == seconds and plan["chosen"]["predicted"] <= seconds
    assert plan["ran"]["resolutions"] == record["resolutions"] and record["steps"] <= sum(plan["ran"]["steps"])
    assert plan["calibration"]["cached"] is False and plan["calibration"]["costs"]["step_fixed"] >= 0
    assert "budget 12s: " in summary["line"] and "from a calibration of" in summary["line"]
    if plan["chosen"]["fits"]:
        assert record["held_out_psnr"] > 13.0, record["held_out_psnr"]  # it learned the scene (an untrained grid: ~10)
    else:  # a machine so busy that the first calibration took most of the budget: the summary says what that left
        assert plan["calibration"]["measured_in_seconds"] > seconds / 3, plan["calibration"]
        assert "less than the coarsest plan needs" in summary["line"]


def test_the_deadline_ends_a_fit_whose_plan_was_too_long_and_it_is_still_complete(fresh, monkeypatch):
    monkeypatch.setattr(budget, "LADDER", TINY_LADDER)
    monkeypatch.setattr(budget, "calibrate", lambda *a, **k: (FREE, {"cached": True, "file": "-", "key": {}}))
    # No re-plan shortens the free steps' schedule: neither every few steps nor at the level change, where a machine so
    # busy that the first level took most of the budget would cut the last level to a step and end before the deadline.
    monkeypatch.setattr(budget, "replan", lambda seconds, costs, facts, now, rung, resolutions, steps, measured: (
        resolutions, steps, 1.0))
    prunes = []
    original = Fitter.prune
    monkeypatch.setattr(Fitter, "prune", lambda self, budget_rows=None: prunes.append(budget_rows)
                        or original(self, budget_rows))
    step = Fitter.train_step
    # 2 ms more a step: the free calibration's plan (2 x 1200 steps) then outlasts the budget on any machine (a fast
    # one had run all of its tiny steps before the deadline).
    monkeypatch.setattr(Fitter, "train_step", lambda self: time.sleep(0.002) or step(self))
    seconds = 4.0
    started = time.time()
    summary = run_stage(fresh, fit, {**BUDGETED, "time_budget": seconds})
    assert time.time() - started <= seconds + 3.0
    record = read_json(fresh / "fit" / "fit.json")
    assert record["budget"]["stopped_at_deadline"] and record["complete"]
    assert record["steps"] < record["total_steps"] == 2 * 1200
    assert prunes[-1] is None  # pruned once more at the end, as a complete schedule is
    assert "stopped at the deadline" in summary["line"]


def test_ctrl_c_still_stops_a_budgeted_fit_with_a_usable_model(fresh, monkeypatch):
    monkeypatch.setattr(budget, "LADDER", TINY_LADDER)
    monkeypatch.setattr(budget, "calibrate", lambda *a, **k: (FREE, {"cached": True, "file": "-", "key": {}}))
    original = Fitter.train_step

    def interrupted(self):
        if self.step == 30:
            os.kill(os.getpid(), signal.SIGINT)
        return original(self)

    monkeypatch.setattr(Fitter, "train_step", interrupted)
    summary = run_stage(fresh, fit, {**BUDGETED, "time_budget": "1m"})
    record = read_json(fresh / "fit" / "fit.json")
    assert not record["complete"] and record["steps"] == 31 and not record["budget"]["stopped_at_deadline"]
    assert "stopped early at step 31" in summary["line"] and (fresh / "fit" / "grid.pt").is_file()


def test_a_budget_plans_its_rungs_with_the_coarse_start_the_settings_ask_for(fresh, monkeypatch):
    monkeypatch.setattr(budget, "LADDER", (Rung((64, 64, 96), (4, 16, 20), fixed=1),))
    monkeypatch.setattr(budget, "calibrate", lambda *a, **k: (FREE, {"cached": True, "file": "-", "key": {}}))
    run_stage(fresh, fit, {**BUDGETED, "time_budget": "1m", "first_level_scale": 0.5})
    plan = read_json(fresh / "fit" / "fit.json")["budget"]
    assert plan["chosen"]["resolutions"] == [32, 32, 96] and plan["ran"]["resolutions"] == [32, 32, 96]


def test_a_budgeted_fit_resumes_with_its_plan(fresh, monkeypatch):
    monkeypatch.setattr(budget, "LADDER", (Rung((16, 32), (40, 40)),))
    monkeypatch.setattr(budget, "calibrate", lambda *a, **k: (FREE, {"cached": True, "file": "-", "key": {}}))
    original = Fitter.train_step

    def interrupted(self):
        if self.step == 100:  # after the level change at step 80
            raise KeyboardInterrupt
        return original(self)

    monkeypatch.setattr(Fitter, "train_step", interrupted)
    values = {**BUDGETED, "time_budget": "1m", "checkpoint_every": 1e-6}
    with pytest.raises(KeyboardInterrupt):
        run_stage(fresh, fit, values)
    monkeypatch.setattr(Fitter, "train_step", original)
    run_stage(fresh, fit, values)
    record = read_json(fresh / "fit" / "fit.json")
    assert record["resumed_from_step"] == 100 and record["complete"]
    assert record["resolutions"] == [16, 32] and record["steps"] == record["total_steps"] == 160  # the plan's 2x
    # What the level change's prune kept, measured before the stop, not the scene type's prior.
    first = record["levels"][0]
    assert record["budget"]["kept_share"]["first_prune"] == pytest.approx(first["kept"] / first["pruned_from"], abs=1e-4)
    assert first["kept"] / first["pruned_from"] != pytest.approx(record["budget"]["kept_share"]["first_prune_prior"])


@pytest.mark.parametrize("scene_type", ["object", "unbounded"])
def test_a_budgeted_fit_plans_with_its_scene_types_prior_for_the_first_prune(fresh, monkeypatch, scene_type):
    monkeypatch.setattr(budget, "LADDER", (Rung((16, 32), (20, 20)),))
    monkeypatch.setattr(budget, "calibrate", lambda *a, **k: (FREE, {"cached": True, "file": "-", "key": {}}))
    scene = read_json(fresh / "normalize" / "scene.json")
    (fresh / "normalize" / "scene.json").write_text(json.dumps({**scene, "type": scene_type}))
    run_stage(fresh, fit, {**BUDGETED, "time_budget": "1m"})
    kept = read_json(fresh / "fit" / "fit.json")["budget"]["kept_share"]
    assert kept["first_prune_prior"] == budget.FIRST_KEEP_PRIOR[scene_type]
    assert kept["first_prune"] != kept["first_prune_prior"]  # measured at the level change, in place of the prior


def test_a_rungs_early_prune_stays_at_its_step_and_its_cheap_steps_do_not_speak_for_later_ones(fresh, monkeypatch):
    """A rung whose first level prunes early: the prune comes after the rung's steps whatever the share, prunes without
    upsampling, and the steps of the level at the first resolution, which are cheaper than the model (the grid is still
    clearing), never make the finer level's prediction cheaper than the model's; the finer level's own steps do. Its
    re-plans treat the costs as a prior until the fit leaves the first resolution."""
    monkeypatch.setattr(budget, "LADDER", (Rung((16, 16, 32), (20, 40, 40), fixed=1),))
    dear = CostModel(**{**FREE.__dict__, "step_fixed": 0.2})  # the real steps take a few ms: a ratio far below 1
    monkeypatch.setattr(budget, "calibrate", lambda *a, **k: (dear, {"cached": True, "file": "-", "key": {}}))
    ratios, measured = [], []
    replan_budget, replan = budget.TimeBudget._replan, budget.replan
    monkeypatch.setattr(budget.TimeBudget, "_replan", lambda self, why: ratios.append(
        (self.options.resolutions[self.fitter.level], self.now.step_ratio)) or replan_budget(self, why))
    monkeypatch.setattr(budget, "replan", lambda *args, **kwargs: measured.append(
        (args[3].level, kwargs["measured"])) or replan(*args, **kwargs))
    run_stage(fresh, fit, {**BUDGETED, "time_budget": "30s"})
    record = read_json(fresh / "fit" / "fit.json")
    assert record["budget"]["chosen"]["share"] > 1  # the budget gave the rung more steps, not its early prune
    assert record["resolutions"] == [16, 16, 32] and record["budget"]["ran"]["steps"][0] == 20
    first, second = record["levels"]
    assert first["step"] == 20 and first["kept"] == first["occupied"] < first["pruned_from"]  # pruned, not upsampled
    assert second["occupied"] > second["kept"]  # the next level upsamples
    assert [r for res, r in ratios if res == 16] and all(r == 1.0 for res, r in ratios if res == 16)
    assert [r for res, r in ratios if res == 32][-1] < 0.5
    # Its re-plans take the costs as measured only once the fit has left the first resolution: until then the second
    # resolution is never dropped.
    assert {level for level, _ in measured} == {0, 1, 2}
    assert all(flag == (level == 2) for level, flag in measured), measured
