"""The cost model of a budgeted fit: the cached calibration, measured again for another key and rescaled to the
machine's speed now, and the line its step and pass times are read by."""
import os

import pytest
import torch

from pipeline import config
from plenoxels.planning import fit_cost
from plenoxels.planning.fit_cost import CostModel
from stages import fit


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    """Calibrations go to a folder of the test's own, never to the user's cache."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))


def test_the_calibration_is_cached_reused_and_measured_again_for_another_key(monkeypatch):
    options = config.build(fit.Settings, "fit", {"batch_size": 512, "sh_degree": 0})
    small, first = (16, 24, 32), (8, 16)
    measured = []
    original = fit_cost.measure
    monkeypatch.setattr(fit_cost, "measure", lambda *a, **k: measured.append(1) or original(*a, **k))
    cpu = torch.device("cpu")

    costs, record = fit_cost.calibrate(options, cpu, None, small, first)
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

    again, record = fit_cost.calibrate(options, cpu, None, small, first)
    assert record["cached"] and len(measured) == 1
    # The record's factor is rounded to 3 decimals: a factor far from 1 (a loaded machine's first timing) is off by
    # more than a relative 1e-3 of itself.
    assert again.step_fixed == pytest.approx(record["slower_now"] * costs.step_fixed, abs=5e-4 * costs.step_fixed)

    fit_cost.calibrate(config.build(fit.Settings, "fit", {"batch_size": 256, "sh_degree": 0}), cpu, None, small, first)
    assert len(measured) == 2  # other options that set a step's cost
    fit_cost.calibrate(options, cpu, {"n_spheres": 4, "width": 16}, small, first)
    assert len(measured) == 3  # a background model
    monkeypatch.setattr(fit_cost.native, "num_threads", lambda: 97)
    fit_cost.calibrate(options, cpu, None, small, first)
    assert len(measured) == 4  # another thread count
    monkeypatch.setattr(fit_cost, "code_hash", lambda: "changed")
    _, record = fit_cost.calibrate(options, cpu, None, small, first)
    assert len(measured) == 5 and not record["cached"]  # other code
    with open(record["file"], "w") as handle:
        handle.write("{ not json")
    _, record = fit_cost.calibrate(options, cpu, None, small, first)
    assert len(measured) == 6 and not record["cached"]  # an unreadable cache file is measured again
    fit_cost.calibrate(options, cpu, None, small, (8, 12))
    assert len(measured) == 7  # other first-level resolutions
    assert len(list(fit_cost.cache_dir().glob("fit-cost-*.json"))) == 6

    # A cached calibration's times follow the machine's speed now, timed again on the calibration's first step.
    _, record = fit_cost.calibrate(options, cpu, None, small, (8, 12))
    fresh_costs, reference = CostModel(**record["costs"]), record["points"][0]
    timed = []

    def rounds_at(*factors):
        """Each round of the retime at the next of `factors` times the calibration's step."""
        timed.clear()
        monkeypatch.setattr(fit_cost, "_time_steps", lambda fitter, device, steps=8: timed.append(
            fitter.model.grid.num_occupied) or factors[len(timed) - 1] * reference["step_seconds"])

    # Timed twice, the faster round counts: the first at 1.5x (a slow moment, fresh pages), the second at 1.04x, near
    # enough to the calibration to need no more.
    rounds_at(1.5, 1.04)
    _, record = fit_cost.calibrate(options, cpu, None, small, (8, 12))
    assert timed == [reference["voxels"]] * fit_cost.RETIME_ROUNDS and record["slower_now"] == pytest.approx(1.04)
    # Both rounds far from it (a stall at the fit's start): more rounds, and the fastest of them all counts.
    rounds_at(3.0, 2.5, 1.6, 1.05, 1.3)
    _, record = fit_cost.calibrate(options, cpu, None, small, (8, 12))
    assert len(timed) == fit_cost.RETIME_ROUNDS + fit_cost.RETIME_MORE and record["slower_now"] == pytest.approx(1.05)
    assert record["retimed"] == pytest.approx([f * reference["step_seconds"] for f in (3.0, 2.5, 1.6, 1.05, 1.3)],
                                              abs=1e-5)
    # A machine that stays twice as slow: every time of the model scaled by it.
    rounds_at(3.0, 2.0, 2.1, 2.0, 2.2)
    slower, record = fit_cost.calibrate(options, cpu, None, small, (8, 12))
    assert record["cached"] and len(measured) == 7 and record["slower_now"] == pytest.approx(2.0)
    assert slower.step_fixed == pytest.approx(2 * fresh_costs.step_fixed)
    assert slower.step_seconds(1e5, dense=True) == pytest.approx(2 * fresh_costs.step_seconds(1e5, dense=True))
    assert slower.pass_seconds(1e5, 32) == pytest.approx(2 * fresh_costs.pass_seconds(1e5, 32))
    assert slower.upsampled_ratio == fresh_costs.upsampled_ratio  # a ratio of two times, whatever the speed


@pytest.mark.parametrize("model", [{"contract": "on"}, {"ndc": "on"}, {"contract": "off", "ndc": "off"}])
def test_the_calibration_measures_one_bounded_object_whatever_model_the_fit_takes(model):
    """The key does not name the fit's model, so every model's calibration is of the same bounded object: its grids
    span the object's box, a new one's as many vertices as its resolution says, not a contracted or NDC frame's."""
    options = config.build(fit.Settings, "fit", {"batch_size": 512, "sh_degree": 0, **model})
    calibration = fit_cost.CalibrationObject(options, torch.device("cpu"), None, 16)
    for first in (False, True):
        frame = calibration.fitter_at([16], first=first).model.fit_frame
        assert frame.contraction is None and frame.ndc is None
    assert calibration.fitter_at([16], first=True).model.grid.num_occupied == 16 ** 3
    assert fit_cost.calibration_key(options, torch.device("cpu"), None) == fit_cost.calibration_key(
        config.build(fit.Settings, "fit", {"batch_size": 512, "sh_degree": 0}), torch.device("cpu"), None)


def test_a_calibration_within_an_allowance_measures_coarse_first_and_again_for_a_longer_one(monkeypatch):
    """A budget's calibration comes out of its time: within an allowance it measures the coarsest of each part and the
    level change, then finer points only while time is left; such a partial record serves budgets as short, and a
    longer one measures again."""
    options = config.build(fit.Settings, "fit", {"batch_size": 512, "sh_degree": 0})
    small, first, cpu = (16, 24, 32), (8, 16), torch.device("cpu")
    timed, measured = [], []
    original_steps, original_measure = fit_cost._time_steps, fit_cost.measure
    monkeypatch.setattr(fit_cost, "_time_steps", lambda fitter, device, steps=8: timed.append(
        fitter.model.grid.num_occupied) or original_steps(fitter, device, steps))
    monkeypatch.setattr(fit_cost, "measure", lambda *a, **k: measured.append(1) or original_measure(*a, **k))

    costs, record = fit_cost.calibrate(options, cpu, None, small, first, allowance=0.0)
    assert record["partial"] and not record["cached"] and record["allowance"] == 0.0
    assert [p["resolution"] for p in record["points"]] == [16] == [p["resolution"] for p in record["passes"]]
    assert [p["voxels"] for p in record["first_level_points"]] == [8 ** 3]
    assert record["level_change"]["step_seconds"] > 0 and len(timed) == 4  # and the coarsest grid again
    # One point a line: what it measured (rounded to 10 us in the record), per voxel (per ray and vertex for a pass).
    point = record["points"][0]
    assert costs.step_seconds(point["voxels"]) == pytest.approx(point["step_seconds"], abs=1e-5)
    assert costs.step_seconds(8 ** 3, dense=True) == pytest.approx(record["first_level_points"][0]["step_seconds"],
                                                                   abs=1e-5)
    assert costs.pass_seconds(record["passes"][0]["rays"], 16) > 0 and costs.upsampled_ratio > 0

    _, record = fit_cost.calibrate(options, cpu, None, small, first, allowance=0.0)
    assert record["cached"] and record["partial"] and len(measured) == 1  # a budget as short: no more to measure
    timed.clear()
    _, record = fit_cost.calibrate(options, cpu, None, small, first)  # no allowance: every point
    assert len(measured) == 2 and not record["cached"] and not record["partial"]
    assert [p["resolution"] for p in record["points"]] == list(small)
    assert [p["voxels"] for p in record["first_level_points"]] == [8 ** 3, 16 ** 3]
    # Coarse to fine: the coarsest pruned grid, the coarsest first level, the upsampled grid, then the finer ones.
    assert timed[1] == 8 ** 3 and timed[4] == 16 ** 3 and timed[0] < timed[3] < timed[5]
    assert len(timed) == 7 and timed[6] == timed[0]  # the coarsest grid timed again, last
    _, record = fit_cost.calibrate(options, cpu, None, small, first, allowance=0.0)
    assert record["cached"] and not record["partial"] and len(measured) == 2  # a whole one serves any budget


@pytest.mark.parametrize("first, again", [(0.020, 0.010), (0.010, 0.030)])
def test_the_calibration_keeps_the_faster_of_two_timings_of_its_coarsest_grid(monkeypatch, first, again):
    """The coarsest grid's steps are timed first, at the fit's own start, and a cached calibration is rescaled by
    that point: one slow timing kept would flatten the line and read the machine faster at every later fit."""
    options = config.build(fit.Settings, "fit", {"batch_size": 512, "sh_degree": 0})
    small, dense, cpu = (16, 24, 32), (8, 16), torch.device("cpu")
    coarsest = fit_cost.CalibrationObject(options, cpu, None, 16).fitter_at([16]).model.grid.num_occupied
    timings = {coarsest: [first, again]}

    def timed(fitter, device, steps=8):
        voxels = fitter.model.grid.num_occupied
        return timings[voxels].pop(0) if voxels in timings else 0.01 + 4e-8 * voxels

    monkeypatch.setattr(fit_cost, "_time_steps", timed)
    costs, record = fit_cost.calibrate(options, cpu, None, small, dense)
    assert timings[coarsest] == []  # timed twice
    assert record["points"][0]["step_seconds"] == pytest.approx(min(first, again))
    later = record["points"][1:]
    assert [p["step_seconds"] for p in later] == pytest.approx([0.01 + 4e-8 * p["voxels"] for p in later], abs=1e-5)
    # The line through the kept points reads the finest grid as it was timed, not flattened by the slow one.
    finest = record["points"][-1]
    assert costs.step_seconds(finest["voxels"]) == pytest.approx(finest["step_seconds"], rel=0.05)


@pytest.mark.parametrize("points, grows", [
    ([(49_671, 0.00853), (228_352, 0.01501), (515_119, 0.02129)], True),    # a 2-core CPU's steps: a line
    ([(49_671, 0.00402), (228_352, 0.00423), (515_119, 0.00364)], False),   # an H100's: flat at these sizes
    ([(49_671, 0.00100), (228_352, 0.00900), (515_119, 0.02400)], True),    # rising faster than a line: no intercept
])
def test_the_step_line_reads_the_calibration_points_within_a_fifth(points, grows):
    """Steps that do not grow with the grid are a fixed cost: a line through the origin would put a GPU's 50k-voxel
    step at an eighth of what it measured, and the plan would carry that ratio to its finer levels."""
    fixed, per_voxel = fit_cost._line(points)
    model = CostModel(step_fixed=fixed, step_per_voxel=per_voxel, pass_per_ray=0, change_per_voxel=0,
                      checkpoint_per_voxel=0, save_per_voxel=0)
    assert fixed >= 0 and per_voxel >= 0 and (per_voxel > 0) == grows
    # A line steeper than its points allow an intercept for is drawn through the origin: it reads the largest.
    for voxels, seconds in points[-1:] if grows and fixed == 0 else points:
        assert model.step_seconds(voxels) == pytest.approx(seconds, rel=0.2), (voxels, seconds, fixed, per_voxel)



@pytest.mark.parametrize("prune_upsampled", [False, True])
def test_a_level_changes_cost_per_voxel_is_of_the_upsample_beyond_its_pruning_passes(prune_upsampled):
    """The calibration's level change prunes the coarse grid and upsamples it, and with fit.prune_upsampled prunes the
    upsample on its own render: its cost per voxel is what is left after the passes (priced on the pass line, as a
    plan prices them), per voxel of the upsample, not of the fewer voxels its own pass leaves."""
    options = config.build(fit.Settings, "fit", {"batch_size": 512, "sh_degree": 0,
                                                   "prune_upsampled": prune_upsampled})
    small, first = (16, 24, 32), (8, 16)  # the change goes from 16 to 32: both passes' rays are in the record
    costs, record = fit_cost.calibrate(options, torch.device("cpu"), None, small, first)
    change, passes = record["level_change"], {p["resolution"]: p["rays"] for p in record["passes"]}
    assert change["upsampled_voxels"] > change["voxels"] if prune_upsampled else (
        change["upsampled_voxels"] == change["voxels"])
    in_passes = sum(costs.pass_seconds(passes[r], r) for r in ((16, 32) if prune_upsampled else (16,)))
    assert costs.change_per_voxel * change["upsampled_voxels"] == pytest.approx(
        max(0.0, change["seconds"] - in_passes), abs=1e-4)
