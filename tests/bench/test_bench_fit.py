"""The fit and scaling benchmarks' bookkeeping: Pareto fronts, the single-knob sweep, stale results, image picks."""
import dataclasses
import json

import pytest

from bench.fit import (BUDGETS, budget_verdict, fronts, knob_variants, load_results, pareto, plan, resolve, run_key,
                       still_valid, table)
from bench.scaling import training_frames
from pipeline import config
from plenoxels.core.errors import UserError
from stages import fit


def test_pareto_keeps_only_undominated_points_in_cost_order():
    points = [(1.0, 10.0), (2.0, 9.0), (2.0, 12.0), (3.0, 11.0), (4.0, 13.0), (0.5, 5.0), (4.0, 13.0)]
    assert pareto(points) == [5, 0, 2, 4]


def _changed(base, variant_overrides: dict) -> set[str]:
    values = {**config.to_dict(base), **variant_overrides}
    changed = config.build(fit.Settings, "fit", values)  # every variant must be a valid setting
    return {f.name for f in dataclasses.fields(fit.Settings) if getattr(changed, f.name) != getattr(base, f.name)}


@pytest.mark.parametrize("preset", ["fast", "default"])
def test_each_knob_variant_changes_only_its_knob(preset):
    base = resolve(preset, "object", {})
    variants = knob_variants(base)
    expected = {"resolution": {"resolutions", "steps"}, "sh": {"sh_degree"}, "image_scale": {"image_scale"},
                "steps": {"steps"}}
    for knob, label, overrides in variants:
        changed = _changed(base, overrides)
        assert changed and changed <= expected[knob], (label, changed)
        if knob == "resolution":
            assert overrides["resolutions"][-1] != base.resolutions[-1]
            assert sum(overrides["steps"]) == base.total_steps
    assert {o["sh_degree"] for k, _, o in variants if k == "sh"} | {base.sh_degree} == {0, 1, 2, 3}
    totals = sorted(sum(o["steps"]) for k, _, o in variants if k == "steps")
    assert totals[0] < base.total_steps < totals[1]


def test_a_smaller_final_resolution_merges_the_levels_it_passes():
    base = fit.Settings(resolutions=[32, 64, 128], steps=[10, 20, 30])
    by_final = {o["resolutions"][-1]: o for k, _, o in knob_variants(base) if k == "resolution"}
    assert by_final[64] == {"resolutions": [32, 64], "steps": [10, 50]}
    assert by_final[96] == {"resolutions": [32, 64, 96], "steps": [10, 20, 30]}
    assert by_final[192] == {"resolutions": [32, 64, 192], "steps": [10, 20, 30]}


def _record(preset: str, overrides: dict, settings_overrides: dict | None = None) -> dict:
    settings = resolve(preset, "object", {**overrides, **(settings_overrides or {})})
    scoring = {"eval_scale": 0.5, "val_limit": None}
    return {"key": run_key("synthetic", preset, overrides, scoring), "scene": "synthetic", "scene_type": "object",
            "preset": preset, "overrides": overrides, "scoring": scoring,
            "settings": json.loads(json.dumps(config.to_dict(settings)))}


def test_stored_runs_whose_settings_changed_since_are_dropped(tmp_path):
    current = _record("fast", {"sh_degree": 0})
    stale = _record("fast", {}, settings_overrides={"batch_size": 123})  # as if the preset had changed since
    old_format = {"scene": "lego", "preset": "fast", "label": "fast", "overrides": {}}
    path = tmp_path / "fit.json"
    path.write_text(json.dumps({"runs": [current, stale, old_format]}))
    assert [r["key"] for r in load_results(path, fresh=False)["runs"]] == [current["key"]]
    assert load_results(path, fresh=True)["runs"] == []


def test_settings_added_since_at_their_default_and_unused_background_settings_keep_a_run():
    before = _record("fast", {})
    del before["settings"]["time_budget"]  # stored before the setting existed
    assert still_valid(before)
    before["settings"]["background_width"] = 128  # an object scene has no background model to use it
    assert still_valid(before)
    unbounded = {**_record("fast", {}), "scene_type": "unbounded"}
    unbounded["settings"] = json.loads(json.dumps(config.to_dict(resolve("fast", "unbounded", {}))))
    assert still_valid(unbounded)
    unbounded["settings"]["background_width"] += 1
    assert not still_valid(unbounded)
    later = _record("fast", {})
    later["settings"]["a_setting_since_removed"] = 1
    assert not still_valid(later)


def test_the_budget_sweep_plans_each_budget_on_the_base_preset():
    class Args:
        scenes, presets, knobs, base, eval_scale, val_limit = ["synthetic"], [], ["budget"], {"synthetic": "fast"}, 0.5, 25
        budgets = list(BUDGETS)

    specs = plan(Args, {})
    assert [s["overrides"] for s in specs] == [{"time_budget": b} for b in BUDGETS]
    assert {s["knob"] for s in specs} == {"budget"} and len({s["key"] for s in specs}) == len(BUDGETS)


def test_a_budget_run_is_judged_against_the_presets_that_took_no_longer():
    presets = [run("fast", 40, 500, 28.0), run("default", 250, 900, 31.0)]
    for r in presets:
        r["common"] = {}

    def budget(seconds, psnr):
        return {**run(f"budget {seconds}", seconds, 500, psnr), "knob": "budget", "common": {}}

    assert budget_verdict(budget(60, 29.0), presets) == "on or above the presets' front"
    assert budget_verdict(budget(60, 27.5), presets).startswith("below fast (28.00 dB in 40 s)")
    assert budget_verdict(budget(300, 30.0), presets).startswith("below default")
    assert budget_verdict(budget(30, 20.0), presets) == "on or above the presets' front"  # no preset was that quick


def run(label, seconds, rss, psnr, eval_size=(200, 150)):
    return {"key": label, "scene": "synthetic", "knob": None, "label": label, "psnr": psnr, "ssim": psnr / 40,
            "wall_seconds": seconds, "peak_rss_mb": rss, "eval_size": list(eval_size), "held_out_views": 6,
            "model_bytes": 2**20, "resolution": [64, 64, 64], "occupied": 1000, "threads": "1",
            "load_average": {"before": [1.0, 1, 1], "after": [2.0, 1, 1]}}


def test_table_marks_the_runs_on_each_front():
    runs = [run("cheap", 10, 900, 20.0), run("slow-but-lean", 100, 500, 25.0), run("worse", 50, 950, 19.0)]
    on_front = fronts(runs)
    assert on_front["synthetic 200x150", "psnr", "wall_seconds"] == {"cheap", "slow-but-lean"}
    assert on_front["synthetic 200x150", "psnr", "peak_rss_mb"] == {"slow-but-lean"}
    rows = {line.split(" | ")[1]: line for line in table({"runs": runs}).splitlines() if line.startswith("| synth")}
    assert rows["cheap"].endswith("| yes / - |")
    assert rows["slow-but-lean"].endswith("| yes / yes |")
    assert rows["worse"].endswith("| - / - |")


def test_runs_scored_at_other_sizes_have_their_own_front():
    # PSNR scored on smaller images is higher; it must not push the full-size runs off their front.
    runs = [run("full", 100, 900, 25.0), run("small-scored", 100, 900, 30.0, eval_size=(100, 75))]
    on_front = fronts(runs)
    assert on_front["synthetic 200x150", "psnr", "wall_seconds"] == {"full"}
    assert on_front["synthetic 100x75", "psnr", "wall_seconds"] == {"small-scored"}


def test_image_counts_are_spread_over_the_training_frames():
    scene = {"frames": [{"name": f"t{i}", "split": "train"} for i in range(10)] + [{"name": "v", "split": "test"}]}
    assert [f["name"] for f in training_frames(scene, 4)] == ["t0", "t3", "t6", "t9"]
    assert len(training_frames(scene, None)) == 10
    assert [f["name"] for f in training_frames(scene, 1)] == ["t0"]
    with pytest.raises(UserError, match="10 training images"):
        training_frames(scene, 11)


def test_real_scenes_quarter_keeps_every_held_out_view_and_every_fourth_training_view():
    from bench.real_scenes import with_views

    frames = [{"name": f"{i:02d}", "split": "test" if i % 8 == 0 else "train"} for i in range(40)]
    scene = {"type": "unbounded", "frames": frames}
    quarter = with_views(scene, 4)
    train = [f["name"] for f in frames if f["split"] == "train"]
    assert [f["name"] for f in quarter["frames"] if f["split"] == "test"] == ["00", "08", "16", "24", "32"]
    assert [f["name"] for f in quarter["frames"] if f["split"] == "train"] == train[::4]
    assert with_views(scene, 1)["frames"] == frames and scene["frames"] == frames


def test_real_scenes_budget_runs_compare_with_the_front_label_at_their_own_scoring_size():
    from bench.real_scenes import budget_verdict

    def record(preset, label, seconds, psnr, size=(266, 474), overrides=None):
        return {"scene": "fox", "views": "all", "preset": preset, "label": label, "fit_seconds": seconds,
                "mean": {"psnr": psnr}, "image_size": list(size), "overrides": overrides or {}}

    runs = [record("default", "after", 400, 26.0), record("fast", "after", 80, 27.0, size=(178, 316)),
            record("default", "before", 100, 30.0)]
    budget = record("default", "budget 2m", 120, 25.0, overrides={"time_budget": "2m"})
    # fast was scored on smaller images, `before` is not the front's label: neither beats it.
    assert budget_verdict(budget, runs, ["after"]) == "on or above the presets' front"
    assert budget_verdict({**budget, "fit_seconds": 450}, runs, ["after"]) == "below default (26.00 dB in 400 s)"
    assert "no preset run" in budget_verdict(budget, runs, ["nothing"])
    assert "no preset run" in budget_verdict(budget, runs, ["aft"])  # a label, not a piece of one
    # Several labels: each scene compares with its runs under any of them (scenes benched on different days).
    assert budget_verdict(budget, runs, ["nothing", "before"]) == "below default (30.00 dB in 100 s)"


def test_real_scenes_budgets_compare_with_each_scenes_newest_sweep_of_the_presets_by_default():
    from bench.real_scenes import newest_front

    def record(scene, label, recorded, overrides=None):
        return {"scene": scene, "views": "all", "label": label, "recorded": recorded, "overrides": overrides or {}}

    runs = [record("fox", "2026-11-25 aaaaaaa", "2026-11-25 aaaaaaa"),
            record("cup", "2026-11-25 aaaaaaa", "2026-11-25 aaaaaaa"),
            record("fox", "2026-11-26 bbbbbbb", "2026-11-26 bbbbbbb"),
            record("fox", "2026-11-27 ccccccc, probe, tv x4", "2026-11-27 ccccccc"),  # a named variant
            record("fox", "budget 1m", "2026-11-27 ccccccc", {"time_budget": "1m"}),
            record("fox", "2026-11-27 ddddddd", "2026-11-27 ddddddd", {"tv_density": 1e-9})]  # overridden
    assert newest_front(runs) == ["2026-11-25 aaaaaaa", "2026-11-26 bbbbbbb"]


def test_real_scenes_runs_scored_at_one_size_compare_whatever_size_they_fit_at():
    from bench.real_scenes import budget_verdict

    def record(preset, label, seconds, psnr, fit_size, overrides=None):
        return {"scene": "fox", "views": "all", "preset": preset, "label": label, "fit_seconds": seconds,
                "mean": {"psnr": psnr}, "image_size": list(fit_size), "score_size": [180, 320],
                "overrides": overrides or {}}

    runs = [record("fast", "after", 80, 27.0, (178, 316)), record("default", "after", 400, 26.0, (266, 474))]
    budget = record("default", "budget 2m", 120, 26.5, (266, 474), overrides={"time_budget": "2m"})
    # Scored at the same size, fast's smaller photos do not keep it off the budget's front.
    assert budget_verdict(budget, runs, ["after"]) == "below fast (27.00 dB in 80 s)"
    assert budget_verdict({**budget, "mean": {"psnr": 27.5}}, runs, ["after"]) == "on or above the presets' front"


def test_real_scenes_results_are_written_a_run_to_a_line_and_read_back_whole(tmp_path):
    from bench.common import write_runs

    results = {"machine": {"cpu": "test", "cores": 2},
               "runs": [{"scene": "fox", "budget": {"replans": [{"step": s, "steps": [s, 2 * s]} for s in range(40)]}},
                        {"scene": "ball", "label": "a label, with \"quotes\"\nand a line break", "mean": {"psnr": 26.5}}]}
    path = tmp_path / "real_scenes.json"
    write_runs(path, results)
    assert json.loads(path.read_text()) == results
    lines = path.read_text().splitlines()
    assert len(lines) == 1 + len(results["runs"]) + 1  # the machine, a line a run, the close
    write_runs(path, {"runs": []})
    assert json.loads(path.read_text()) == {"runs": []}
