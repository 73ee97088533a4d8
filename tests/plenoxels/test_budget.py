"""The fit's time budget: the setting's durations, and budgeted fits that end on time, stop, resume and pace their
levels (the cost model and the plan have their own tests: test_fit_cost.py, test_fit_plan.py)."""
import json
import os
import shutil
import signal
import time

import pytest
from tests.stages.test_fit import QUICK, make_scene, run_stage

from pipeline import config
from stages.common.json_files import read_json
from plenoxels.planning import budget
from plenoxels.planning.fit_cost import CostModel
from plenoxels.planning.fit_plan import FINEST_MAX_SHARE, UPSAMPLE_BAND_PRIOR, Rung, upsample_band
from plenoxels.core.errors import UserError
from plenoxels.core.train import Fitter
from stages import fit

# A tiny ladder and a cost model that thinks every step is free: the plan then asks for far more steps than the
# budget holds, and only the deadline's stop can end the fit on time.
TINY_LADDER = (Rung((16, 32), (400, 800)),)
FREE = CostModel(step_fixed=1e-6, step_per_voxel=1e-12, pass_per_ray=1e-12, change_per_voxel=1e-12,
                 checkpoint_per_voxel=1e-12, save_per_voxel=1e-12)
# What the budgeted fits of the tiny scene share with tests/stages/test_fit.py, without its levels.
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


def test_the_wall_clock_set_forward_mid_fit_takes_nothing_from_the_budget(fresh, monkeypatch):
    """A laptop asleep for an hour, or a clock set by the network: the budget counts the time the fit ran, not the
    calendar's. The wall clock jumps an hour on once the fit has taken 5 steps."""
    real_time, steps = time.time, []
    monkeypatch.setattr(time, "time", lambda: real_time() + (3600.0 if len(steps) > 5 else 0.0))
    step = Fitter.train_step
    monkeypatch.setattr(Fitter, "train_step", lambda self: steps.append(1) or step(self))
    seconds = 6.0
    started = time.monotonic()
    run_stage(fresh, fit, {**BUDGETED, "time_budget": f"{seconds:g}s"})
    record = read_json(fresh / "fit" / "fit.json")
    assert record["complete"] and len(steps) > 50, len(steps)
    # It ran for its budget (a fit cut at the jump ends within its calibration's share of it).
    assert time.monotonic() - started > 0.5 * seconds and record["budget"]["stage_seconds"] <= 1.1 * seconds + 4.0


def test_a_budget_on_a_busy_machine_calibrates_within_its_share_and_ends_on_time(fresh, monkeypatch):
    """Every timing of the calibration 0.5 s slower (a machine running twice its cores' work): its finer points, past
    CALIBRATION_SHARE of the budget, are left to a longer budget, and the fit still ends on time."""
    from plenoxels.planning import fit_cost
    timings = []
    original = fit_cost._time_steps
    monkeypatch.setattr(fit_cost, "_time_steps", lambda fitter, device, steps=8: timings.append(1) or time.sleep(0.5)
                        or original(fitter, device, steps))
    seconds = 8.0
    started = time.time()
    summary = run_stage(fresh, fit, {**BUDGETED, "time_budget": f"{seconds:g}s"})
    took = time.time() - started
    assert took <= 1.1 * seconds + 4.0, took
    calibration = read_json(fresh / "fit" / "fit.json")["budget"]["calibration"]
    whole = len(fit_cost.CALIBRATION_RESOLUTIONS) + len(fit_cost.DENSE_RESOLUTIONS) + 1  # the upsampled grid's too
    assert calibration["partial"] and 3 <= len(timings) < whole, (timings, calibration)
    assert 0 < calibration["allowance"] <= budget.CALIBRATION_SHARE * seconds  # of what was left of the budget
    assert "partial" in summary["line"] and read_json(fresh / "fit" / "fit.json")["complete"]


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
    # 2 ms more a step: the free calibration's plan (the tiny ladder's only rung, so its finest, at FINEST_MAX_SHARE)
    # then outlasts the budget on any machine (a fast one had run all of its tiny steps before the deadline).
    monkeypatch.setattr(Fitter, "train_step", lambda self: time.sleep(0.002) or step(self))
    seconds = 4.0
    started = time.time()
    summary = run_stage(fresh, fit, {**BUDGETED, "time_budget": seconds})
    assert time.time() - started <= seconds + 3.0
    record = read_json(fresh / "fit" / "fit.json")
    assert record["budget"]["stopped_at_deadline"] and record["complete"]
    assert record["steps"] < record["total_steps"] == sum(TINY_LADDER[0].scaled(FINEST_MAX_SHARE))
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
    # The plan's, its only rung being its finest: 2x the first level's steps, FINEST_MAX_SHARE the last's.
    assert record["resolutions"] == [16, 32]
    assert record["steps"] == record["total_steps"] == sum(budget.LADDER[0].scaled(FINEST_MAX_SHARE)) == 80 + 160
    # What the level change's prune kept, measured before the stop, not the scene type's prior.
    first = record["levels"][0]
    assert record["budget"]["kept_share"]["first_prune"] == pytest.approx(first["kept"] / first["pruned_from"], abs=1e-4)
    assert first["kept"] / first["pruned_from"] != pytest.approx(record["budget"]["kept_share"]["first_prune_prior"])


@pytest.mark.parametrize("budget_seconds, finest, scale", [("1m", 64, 1.0), ("1m", 16, 0.5), (0, 64, 0.5)])
def test_a_budget_fits_photos_coarser_than_the_presets_finest_grid_at_up_to_their_own_size(fresh, monkeypatch,
                                                                                         budget_seconds, finest, scale):
    """The tiny scene's 48-pixel photos at fit.image_scale 0.5 are 24 pixels across: coarser than a preset's 64^3 grid,
    so a budget fits them whole and records the scale, which evaluate renders at; beside a 16^3 grid, or without a
    budget, the setting holds."""
    monkeypatch.setattr(budget, "LADDER", (Rung((16, 32), (20, 20)),))
    monkeypatch.setattr(budget, "calibrate", lambda *a, **k: (FREE, {"cached": True, "file": "-", "key": {}}))
    run_stage(fresh, fit, {**BUDGETED, "image_scale": 0.5, "time_budget": budget_seconds,
                           "resolutions": [16, finest], "steps": [20, 20]})
    frames = [f for f in read_json(fresh / "normalize" / "scene.json")["frames"] if f["split"] == "train"]
    whole = sum(f["w"] * f["h"] for f in frames)
    assert read_json(fresh / "fit" / "model.json")["fit_settings"]["image_scale"] == scale
    assert read_json(fresh / "fit" / "fit.json")["train_pixels"] == pytest.approx(whole * scale ** 2, rel=0.1)


@pytest.mark.parametrize("scene_type", ["object", "unbounded"])
def test_a_budgeted_fit_plans_with_its_scene_types_priors(fresh, monkeypatch, scene_type):
    """The first prune's kept share by scene type, and the least share of a fine rung's steps a plan gives by the model
    (a bounded grid with the background spheres: more)."""
    monkeypatch.setattr(budget, "LADDER", (Rung((16, 32), (20, 20)),))
    monkeypatch.setattr(budget, "calibrate", lambda *a, **k: (FREE, {"cached": True, "file": "-", "key": {}}))
    scene = read_json(fresh / "normalize" / "scene.json")
    (fresh / "normalize" / "scene.json").write_text(json.dumps({**scene, "type": scene_type}))
    run_stage(fresh, fit, {**BUDGETED, "time_budget": "1m"})
    record = read_json(fresh / "fit" / "fit.json")["budget"]
    model = read_json(fresh / "fit" / "model.json")
    fine = budget.FINE_MIN_SHARE if model["background"] and not model["contraction"] else budget.MIN_SHARE
    assert f"({fine:g}x ending finer than {budget.COARSE_LAST}^3)" in record["why"]
    kept = record["kept_share"]
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
        (self.schedule.resolutions[self.fitter.level], self.now.step_ratio)) or replan_budget(self, why))
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


def test_the_first_levels_steps_can_take_back_a_retime_that_read_the_machine_slower_than_it_runs(fresh, monkeypatch):
    """A cached calibration scaled by a retime that read the machine 4x slower (a stall while it was timed): the first
    level's steps, far cheaper than that, bring the ratio down to the calibration as measured (1/4 of the scaled
    model), no further, as a grid that is still clearing its air speaks of its own level, not of the machine."""
    monkeypatch.setattr(budget, "LADDER", (Rung((16, 32), (20, 20)),))
    # Half a second a step: the tiny scene's steps run under a quarter of that even on a loaded machine (80 ms measured
    # with two test suites sharing two cores).
    dear = CostModel(**{**FREE.__dict__, "step_fixed": 0.5})
    monkeypatch.setattr(budget, "calibrate", lambda *a, **k: (dear, {"cached": True, "file": "-", "key": {},
                                                                     "slower_now": 4.0}))
    ratios = []
    replan_budget = budget.TimeBudget._replan
    monkeypatch.setattr(budget.TimeBudget, "_replan", lambda self, why: ratios.append(
        (self.schedule.resolutions[self.fitter.level], self.now.step_ratio)) or replan_budget(self, why))
    run_stage(fresh, fit, {**BUDGETED, "time_budget": "30s"})
    at_first = [r for res, r in ratios if res == 16]
    assert at_first and at_first[-1] == pytest.approx(0.25)
    assert read_json(fresh / "fit" / "fit.json")["budget"]["calibration"]["slower_now"] == 4.0


def test_a_level_a_replan_dropped_comes_back_once_the_measured_steps_leave_time_for_it(fresh, monkeypatch):
    """A level dropped on costs predicted before the fit reached it (a machine that seemed slow when the fit began)
    comes back once the steps measured since leave time for it: the fit does not end early without it."""
    monkeypatch.setattr(budget, "LADDER", (Rung((16, 24, 32), (20, 20, 20)),))
    monkeypatch.setattr(budget, "calibrate", lambda *a, **k: (FREE, {"cached": True, "file": "-", "key": {}}))
    replan, calls = budget.replan, []

    def dear_at_first(seconds, costs, facts, now, rung, resolutions, steps, measured):
        calls.append(list(resolutions))
        if len(calls) == 1:  # the first re-plan drops the last level, as dear predicted costs would
            resolutions, steps = resolutions[:-1], steps[:-1]
        return replan(seconds, costs, facts, now, rung, resolutions, steps, measured)

    monkeypatch.setattr(budget, "replan", dear_at_first)
    run_stage(fresh, fit, {**BUDGETED, "time_budget": "1m"})
    record = read_json(fresh / "fit" / "fit.json")
    replans = record["budget"]["replans"]
    assert replans[0]["dropped_levels"] == [32] and [r for r in replans if r.get("restored_levels") == [32]]
    assert record["resolutions"] == record["budget"]["ran"]["resolutions"] == [16, 24, 32] and record["complete"]
    # At the free costs every level gets twice its steps, and the last, once the fit is in it, FINEST_MAX_SHARE.
    assert record["steps"] == record["total_steps"] == sum(budget.LADDER[0].scaled(FINEST_MAX_SHARE)) == 40 + 40 + 80


def test_a_budget_measures_what_an_upsampled_grids_own_pruning_keeps_and_prices_its_pass(fresh, monkeypatch):
    """With fit.prune_upsampled the upsampled grid is pruned on its own render: the level change is priced with that
    pass and the upsample's voxels (not the fewer it leaves), and the share it kept replaces the prior for the levels
    after it; a level change at the same resolution (the early prune) measures no such share."""
    monkeypatch.setattr(budget, "LADDER", (Rung((16, 16, 32), (20, 40, 40), fixed=1),))
    monkeypatch.setattr(budget, "calibrate", lambda *a, **k: (FREE, {"cached": True, "file": "-", "key": {}}))
    changes, keeps = [], []
    change_seconds, replan = budget.change_seconds, budget.replan
    monkeypatch.setattr(budget, "change_seconds", lambda costs, facts, *args: changes.append(
        (facts.prune_upsampled, *args)) or change_seconds(costs, facts, *args))
    monkeypatch.setattr(budget, "replan", lambda *args, **kwargs: keeps.append(
        (args[3].level, args[3].upsample_band)) or replan(*args, **kwargs))
    run_stage(fresh, fit, {**BUDGETED, "time_budget": "30s", "prune_upsampled": True})
    record = read_json(fresh / "fit" / "fit.json")
    first, second = record["levels"]
    assert first["upsampled"] is None and first["occupied"] == first["kept"]
    assert second["upsampled"] > second["occupied"] > 0 and second["upsampled"] >= second["kept"]
    assert changes == [(True, 16, 16, first["occupied"], first["occupied"]),
                       (True, 16, 32, second["upsampled"], second["occupied"])]
    share = second["occupied"] / second["upsampled"]
    assert record["budget"]["kept_share"]["upsampled_grids"] == [pytest.approx(share, abs=1e-4)]
    assert {band for level, band in keeps if level < 2} == {UPSAMPLE_BAND_PRIOR}
    assert {band for level, band in keeps if level == 2} == {upsample_band(share, 2.0)}
