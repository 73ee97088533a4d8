"""The scene model chosen by evidence (plenoxels/planning/model_trial.py): which captures ask, what a trial picks on small
synthetic scenes whose better model is known, and what the fit stage records of it."""
from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from stages.common.frames import load_frame
from stages.common.json_files import read_json, write_json
from stages.framing.options import SceneOptions
from stages.framing.scene_frame import normalize_scene
from stages.framing.sightings import Points
from stages.capture.synthetic import write_scene
from plenoxels.planning import model_trial
from plenoxels.core.options import ModelOptions, TrainOptions
from plenoxels.core.ray_set import RaySet
from stages import fit
from tests.stages.test_fit import run_stage

# A trial small enough for two cores: 64x48 photos, a 40^3 level of 250 steps per model.
TRIAL = dict(resolutions=[40], steps=[250], batch_size=2048, sh_degree=0, lr_density=5.0, lr_density_final=0.5,
             lr_density_delay=0.3, lr_sh=0.05, lr_sh_final=0.005, tv_density=0.0, tv_sh=0.0, background_spheres=8,
             background_width=32, lr_background=0.05, prune_ray_scale=1.0)


@dataclass
class Options(TrainOptions, ModelOptions):
    """A model and its training, as the fit stage combines them."""


def _auto(scene: dict, **measured) -> dict:
    """`scene` as normalize types it without a hand-set type, with these measures (None: not measured)."""
    scene = copy.deepcopy(scene)
    scene["overridden"] = False
    for key, value in measured.items():
        if value is None:
            scene["measured"].pop(key, None)
        else:
            scene["measured"][key] = value
    return scene


@pytest.fixture(scope="module")
def unbounded(tmp_path_factory) -> tuple[dict, Path]:
    """The synthetic unbounded scene (an object on an endless ground inside a far sphere), 40 views of 64x48."""
    root = write_scene("unbounded", tmp_path_factory.mktemp("unbounded") / "synth", n_views=40, width=64, height=48,
                       seed=0, supersample=1)
    transforms = read_json(root / "transforms.json")
    for frame, view in zip(transforms["frames"], read_json(root / "ground_truth" / "scene.json")["views"]):
        frame["near"], frame["far"] = view["near_depth"], view["far_depth"]
    scene = normalize_scene(transforms, Points.empty(), SceneOptions(scene_type="unbounded", holdout_every=4),
                            poses_dir=root, path_prefix="")
    return scene, root


def _training(scene: dict, root: Path) -> RaySet:
    images, c2ws, ks = [], [], []
    for frame in (f for f in scene["frames"] if f["split"] == "train"):
        image, k = load_frame(root, frame, 1.0, (1.0, 1.0, 1.0))
        images.append(image)
        c2ws.append(np.asarray(frame["transform_matrix"]))
        ks.append(k)
    return RaySet(images, c2ws, ks)


# ---- which captures ask ----------------------------------------------------------------------------------------
def _typed(scene_type: str, **measured) -> dict:
    return {"type": scene_type, "overridden": False, "frames": [],
            "measured": {"view_cone_deg": 60.0, "borderline": False, **measured},
            "thresholds": {"forward_max_cone_deg": 30.0, "unbounded_min_beyond_fraction": 0.1,
                           "object_min_empty_fraction": 0.2}}


@pytest.mark.parametrize("scene, asked", [
    (_typed("unbounded", beyond_fraction=0.004, empty_pixel_fraction=0.05), []),           # a room around a cup
    (_typed("unbounded", beyond_fraction=0.23, empty_pixel_fraction=0.0), [("contracted", "bounded + background")]),
    (_typed("unbounded", empty_pixel_fraction=0.02), [("contracted", "bounded + background")]),  # no points
    (_typed("unbounded", beyond_fraction=0.8, empty_pixel_fraction=0.0), []),              # a street
    (_typed("unbounded", beyond_fraction=0.12, empty_pixel_fraction=0.02),
     [("contracted", "bounded + background"), ("bounded", "bounded + background")]),
    (_typed("object", beyond_fraction=0.0, empty_pixel_fraction=0.3), [("bounded", "bounded + background")]),
    (_typed("object", beyond_fraction=0.0, empty_pixel_fraction=0.7), []),                 # a turntable on white
    (_typed("object", empty_pixel_fraction=0.3, masked=True), []),
    ({**_typed("unbounded", beyond_fraction=0.0, empty_pixel_fraction=0.0, borderline=True, view_cone_deg=34.0),
      "forward": {"reference_c2w": np.eye(4).tolist(), "near": 0.5}}, [("ndc", "bounded + background")]),
    (_typed("forward", view_cone_deg=10.0), []),
])
def test_only_captures_near_the_proxies_thresholds_ask_for_a_trial(scene, asked):
    assert [q.models for q in model_trial.questions(scene, Options())] == asked


def test_a_model_set_by_hand_is_never_tried():
    scene = _typed("unbounded", beyond_fraction=0.23)
    assert model_trial.questions(scene, Options(contract="off")) == []
    assert model_trial.forced_by(scene, Options(contract="off")) == ["fit.contract=off"]
    assert model_trial.questions({**scene, "overridden": True}, Options()) == []
    assert model_trial.forced_by({**scene, "overridden": True}, Options()) == ["normalize.scene_type=unbounded"]


# ---- what a trial picks ----------------------------------------------------------------------------------------
def _trial(scene: dict, photos):
    """The questions normalize's measures leave open for `scene`, the trial's outcome on them, and its scores."""
    asked = model_trial.questions(scene, Options(**TRIAL))
    outcome = model_trial.run(scene, Options(**TRIAL), _training(scene, photos), torch.device("cpu"), asked)
    scores = {t["model"]: t["held_out_psnr"] for t in outcome.record["tried"]}
    print(f"trial: {scores}")
    return asked, outcome, scores


def test_the_trial_overrules_the_proxies_where_far_content_needs_a_contracted_grid(unbounded, monkeypatch):
    """Points just short of the threshold make the proxies pick a bounded grid with background spheres; the scene's
    ground and sky reach far, and a contracted grid shows them better on photos the trial did not fit."""
    monkeypatch.setattr(model_trial, "STEPS", 250)
    scene = _auto(unbounded[0], beyond_fraction=0.04)
    assert model_trial.proxies_pick(scene) == "bounded + background"
    asked, outcome, scores = _trial(scene, unbounded[1])
    assert [q.models for q in asked] == [("contracted", "bounded + background")]
    assert set(scores) == {"contracted", "bounded + background"}
    assert outcome.model == "contracted", outcome.why
    assert scores["contracted"] >= scores["bounded + background"] + model_trial.MARGIN_DB
    assert outcome.record["scored_photos"] == 3 and outcome.record["fitted_photos"] == 27


def test_the_trial_gives_scenery_its_background_model(unbounded, monkeypatch):
    """Typed an object (the backdrop proxy near its threshold), the same scene is better with background spheres than
    with one colour behind a bounded grid, which paints the world as floaters."""
    monkeypatch.setattr(model_trial, "STEPS", 250)
    scene = _auto({**unbounded[0], "type": "object"}, empty_pixel_fraction=0.25)
    assert model_trial.proxies_pick(scene) == "bounded"
    asked, outcome, scores = _trial(scene, unbounded[1])
    assert [q.models for q in asked] == [("bounded", "bounded + background")]
    assert outcome.model == "bounded + background", outcome.why
    assert "by trial" in model_trial.summary(outcome.record) and "bounded + background" in model_trial.summary(outcome.record)


def test_a_budget_too_short_to_reach_the_early_prune_keeps_the_proxies_pick(unbounded, monkeypatch):
    """Under a budget whose share would stop a model before the trial's early prune, no model is scored: each runs
    its probe only and the proxies' pick stands, the summary saying so; given the time, the same trial runs every step
    of its level and overrules them."""
    monkeypatch.setattr(model_trial, "STEPS", 250)
    scene = _auto(unbounded[0], beyond_fraction=0.04)
    asked, train = model_trial.questions(scene, Options(**TRIAL)), _training(scene, unbounded[1])
    short = model_trial.run(scene, Options(**TRIAL), train, torch.device("cpu"), asked, seconds=0.05)
    assert short.model == model_trial.proxies_pick(scene) == "bounded + background"
    assert "tried" not in short.record and "chosen" not in short.record
    assert "early prune at step 50" in short.record["skipped"]
    assert [p["steps"] for p in short.record["probed"]] == [model_trial.PROBE_STEPS] * 2
    assert "untried" in model_trial.summary(short.record) and "bounded + background" in model_trial.summary(short.record)
    ample = model_trial.run(scene, Options(**TRIAL), train, torch.device("cpu"), asked, seconds=3600.0)
    assert "probed" not in ample.record and [t["steps"] for t in ample.record["tried"]] == [250, 250]
    assert ample.model == "contracted", ample.why


# ---- the fit stage ---------------------------------------------------------------------------------------------
STAGE = {"resolutions": [32, 32], "steps": [40, 160], "batch_size": 2048, "image_scale": 1.0, "eval_every": 0,
         "eval_scale": 1.0, "sh_degree": 0, "tv_density": 0.0, "tv_sh": 0.0, "background_spheres": 8,
         "background_width": 32, "prune_ray_scale": 1.0}


def _stage_root(unbounded, folder: Path, scene: dict) -> Path:
    (folder / "normalize").mkdir(parents=True)
    frames = [{**f, "file_path": str(unbounded[1] / f["file_path"])} for f in scene["frames"]]
    write_json(folder / "normalize" / "scene.json", {**scene, "frames": frames})
    write_json(folder / "normalize" / "manifest.json", {"stage": "normalize", "summary": {"line": "test scene"}})
    return folder


def test_the_fit_stage_records_the_trial_and_fits_its_winner(unbounded, tmp_path, monkeypatch):
    monkeypatch.setattr(model_trial, "STEPS", 150)
    root = _stage_root(unbounded, tmp_path, _auto(unbounded[0], beyond_fraction=0.04))
    summary = run_stage(root, fit, STAGE)
    record = read_json(root / "fit" / "fit.json")
    choice = record["model_choice"]
    assert {t["model"] for t in choice["tried"]} == {"contracted", "bounded + background"}
    assert choice["proxies_pick"] == "bounded + background" and choice["why"]
    assert record["scene_model"] == choice["chosen"]
    assert "by trial" in summary["line"] and choice["chosen"] in summary["line"]


def test_a_forced_or_clear_cut_model_costs_no_trial(unbounded, tmp_path, monkeypatch):
    def no_trial(*args, **kwargs):
        raise AssertionError("a trial ran")

    monkeypatch.setattr(model_trial, "run", no_trial)
    forced = run_stage(_stage_root(unbounded, tmp_path / "forced", _auto(unbounded[0], beyond_fraction=0.04)), fit,
                       {**STAGE, "contract": "on"})
    record = read_json(tmp_path / "forced" / "fit" / "fit.json")
    assert record["scene_model"] == "contracted" and "fit.contract=on" in record["model_choice"]["skipped"]
    assert "by trial" not in forced["line"]
    run_stage(_stage_root(unbounded, tmp_path / "clear", _auto(unbounded[0], beyond_fraction=0.9)), fit, STAGE)
    record = read_json(tmp_path / "clear" / "fit" / "fit.json")
    assert record["scene_model"] == "contracted" and "clear-cut" in record["model_choice"]["skipped"]


def test_a_resumed_fit_keeps_the_model_its_trial_chose(tmp_path, monkeypatch):
    monkeypatch.setattr(model_trial, "run", lambda *a, **k: pytest.fail("the trial ran again"))
    saved = tmp_path / "model_trial.json"
    saved.write_text(json.dumps({"chosen": "bounded + background", "tried": []}))
    options, record = model_trial.choose(_typed("unbounded", beyond_fraction=0.23), Options(), None,
                                         torch.device("cpu"), 0.0, saved)
    assert (options.contract, options.background, options.ndc) == ("off", "on", "off")
    assert record["chosen"] == "bounded + background"


def test_a_trial_under_a_time_budget_takes_its_share_of_it(tmp_path, monkeypatch):
    given = {}

    def trial(scene, options, train, device, asked, seconds=None, say=None):
        given["seconds"] = seconds
        return model_trial.Outcome("contracted", "why", {"chosen": "contracted", "tried": []})

    monkeypatch.setattr(model_trial, "run", trial)
    options, record = model_trial.choose(_typed("unbounded", beyond_fraction=0.23), Options(), None,
                                         torch.device("cpu"), 60.0, tmp_path / "model_trial.json")
    assert given["seconds"] == pytest.approx(60.0 * model_trial.BUDGET_SHARE)
    assert options.contract == "on" and json.loads((tmp_path / "model_trial.json").read_text()) == record


# ---- a held-out PSNR far below the train PSNR ------------------------------------------------------------------
def test_a_held_out_psnr_far_below_the_train_psnr_says_what_to_try():
    choice = {"tried": [{"model": "contracted", "held_out_psnr": 18.0}, {"model": "bounded + background",
                                                                          "held_out_psnr": 17.9}]}
    advice = model_trial.gap_advice(31.5, 17.9, "contracted", choice, 40.0)
    assert "13.6 dB below" in advice and "fit.contract=off fit.background=on" in advice
    assert "more photos" in model_trial.gap_advice(30.0, 20.0, "bounded + background", {}, 6.0)
    assert model_trial.gap_advice(28.0, 26.0, "contracted", choice, 40.0) == ""
    assert model_trial.gap_advice(28.0, None, "contracted", choice, 40.0) == ""
