"""The protocol benchmark's bookkeeping: which layout a folder is, the settings that make a run follow the papers'
protocol, the ablations' schedules, and a whole run on a tiny NeRF-synthetic folder scored on its test split."""
import json
from argparse import Namespace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from bench.protocol import capped_levels, protocol_settings, runs_to_do, scene_kind, table
from stages.scoring import lpips
from stages.common.json_files import read_json
from stages.capture.synthetic import write_scene
from plenoxels.core.errors import UserError
from prerequisites import missing


def blender_folder(root: Path, splits: dict[str, list[int]]) -> Path:
    """A NeRF-synthetic folder from the synthetic object scene: RGBA photos named r_<i> in each split folder, with a
    depth render beside each test photo as the published test/ folders have."""
    scene = write_scene("object", root / "source", n_views=10, width=64, height=48, seed=2, supersample=1)
    truth = read_json(scene / "transforms.json")
    frames = sorted(truth["frames"], key=lambda f: f["file_path"])
    folder = root / "blender"
    for split, indices in splits.items():
        (folder / split).mkdir(parents=True)
        entries = []
        for i, index in enumerate(indices):
            rgb = np.asarray(Image.open(scene / frames[index]["file_path"]).convert("RGB"))
            Image.fromarray(np.dstack([rgb, np.full(rgb.shape[:2], 255, np.uint8)])).save(folder / split / f"r_{i}.png")
            if split == "test":
                Image.new("RGBA", rgb.shape[1::-1]).save(folder / split / f"r_{i}_depth_0001.png")
            entries.append({"file_path": f"./{split}/r_{i}", "transform_matrix": frames[index]["transform_matrix"]})
        angle = 2 * np.arctan(0.5 * truth["w"] / truth["fl_x"])
        (folder / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": entries}))
    return folder


def test_a_folder_is_nerf_synthetic_llff_or_refused(tmp_path):
    folder = blender_folder(tmp_path, {"train": [0, 1, 2], "test": [3]})
    assert scene_kind(folder) == "nerf_synthetic"
    llff = tmp_path / "llff"
    (llff / "images_4").mkdir(parents=True)
    np.save(llff / "poses_bounds.npy", np.zeros((3, 17)))
    assert scene_kind(llff) == "llff"
    with pytest.raises(UserError, match="neither a NeRF-synthetic folder"):
        scene_kind(tmp_path / "source")


def test_protocol_settings_score_every_held_out_view_at_full_size():
    synthetic = protocol_settings("nerf_synthetic", "test")
    assert {"ingest.max_side=0", "evaluate.scale=1", "evaluate.max_views=0", "ingest.holdout_split=test"} <= set(synthetic)
    llff = protocol_settings("llff", "test")
    assert "normalize.holdout_every=8" in llff and not any(s.startswith("ingest.holdout_split") for s in llff)


def test_a_capped_schedule_keeps_the_total_steps_and_the_levels_under_the_cap():
    resolutions, steps = [128, 128, 256, 512], [200, 800, 2000, 3000]
    assert capped_levels(resolutions, steps, 512) == (resolutions, steps)
    assert capped_levels(resolutions, steps, 256) == ([128, 128, 256], [200, 800, 5000])
    assert capped_levels(resolutions, steps, 64) == ([64], [6000])


def test_the_views_ablation_trains_a_quarter_with_low_and_high_tv(tmp_path):
    args = Namespace(split="test", set=[], presets=["fast"], ablation="views", budgets=[])
    runs = runs_to_do(args, "nerf_synthetic", "lego", blender_folder(tmp_path, {"train": [0, 1, 2], "test": [3]}))
    few = [r for r in runs if "normalize.train_every=4" in r["settings"]]
    assert len(runs) == 3 and len(few) == 2
    assert sum("fit.tv_views=0" in r["settings"] for r in few) == 1
    assert all(r["split"] == "test" and "ingest.holdout_split=test" in r["settings"] for r in runs)


def test_a_copy_without_the_test_split_is_scored_on_val_and_says_so(tmp_path):
    args = Namespace(split="test", set=[], presets=["paper"], ablation=None, budgets=[])
    runs = runs_to_do(args, "nerf_synthetic", "lego", blender_folder(tmp_path, {"train": [0, 1, 2], "val": [3]}))
    assert [r["split"] for r in runs] == ["val"]
    assert "ingest.holdout_split=val" in runs[0]["settings"] and "ingest.holdout_split=test" not in runs[0]["settings"]


def test_a_run_scores_the_test_split_and_its_table_names_the_machine_and_commit(tmp_path, monkeypatch):
    import bench.protocol as protocol

    if not lpips.weights_available():
        missing("LPIPS weights not installed: run `make install` (or python -m stages.scoring.lpips install)")
    folder = blender_folder(tmp_path, {"train": [0, 1, 2, 4, 5, 6, 7], "test": [3, 8]})
    monkeypatch.setattr(protocol, "CACHE", tmp_path / "out")
    results = tmp_path / "protocol.json"
    argv = ["--scene", f"tiny={folder}", "--presets", "fast", "--results", str(results),
            "--set", "resolutions=[16,32]", "--set", "steps=[20,20]"]
    assert protocol.main(argv) == 0
    run = json.loads(results.read_text())["runs"][0]
    assert run["held_out_views"] == 2 and run["split"] == "test" and run["eval_size"] == [64, 48]
    assert run["train_images"] == 7 and 5 < run["mean"]["psnr"] < 60
    assert run["commit"] and run["machine"]["cores"] >= 1
    text = table(json.loads(results.read_text()))
    assert "| fast, resolutions=[16,32] steps=[20,20] |" in text and run["commit"] in text

    # A later invocation (a curve run one budget at a time) starts from the earlier run's stages before the fit.
    assert protocol.main(argv[:-1] + ["steps=[20,30]"]) == 0
    first, later = (tmp_path / "out" / f"tiny-{protocol.slug(label)}" for label in
                    ("fast, resolutions=[16,32] steps=[20,20]", "fast, resolutions=[16,32] steps=[20,30]"))
    for stage in ("ingest", "poses", "normalize"):
        assert read_json(later / stage / "manifest.json")["run_id"] == read_json(first / stage / "manifest.json")["run_id"]
    assert read_json(later / "fit" / "manifest.json")["run_id"] != read_json(first / "fit" / "manifest.json")["run_id"]
    assert len(json.loads(results.read_text())["runs"]) == 2
