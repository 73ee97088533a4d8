"""Dataset folders in: a nerfstudio/instant-ngp folder (images/ + transforms.json), a COLMAP project (images/ +
sparse/0), an LLFF folder (images_N/ + poses_bounds.npy) and a NeRF synthetic scene (train/ val/ test/ with
transforms_<split>.json) each give their photos, poses and splits to the stages when the folder itself is named."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from stages.common.json_files import read_json
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from stages.capture.synthetic import write_scene
from plenoxels.core.errors import UserError

N_VIEWS = 8


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> Path:
    return write_scene("object", tmp_path_factory.mktemp("datasets") / "object", n_views=N_VIEWS, width=120,
                       height=90, seed=3, supersample=1)


@pytest.fixture(scope="module")
def truth(synthetic) -> dict:
    return read_json(synthetic / "transforms.json")


def run(scene: Path, out: Path, until: str, *overrides: str) -> dict:
    stages = ["ingest", "poses", "normalize"]
    return Pipeline(scene, out, overrides=list(overrides), reporter=Reporter(quiet=True)).run(
        stages[:stages.index(until) + 1])


def c2w_by_stem(transforms: dict) -> dict[str, np.ndarray]:
    return {Path(f["file_path"]).stem: np.asarray(f["transform_matrix"]) for f in transforms["frames"]}


def assert_same_poses(out: Path, truth: dict, names: dict[str, str] | None = None) -> None:
    """The poses stage's cameras equal the true ones (`names` maps the stage's image names to the truth's)."""
    got, want = c2w_by_stem(read_json(out / "poses" / "transforms.json")), c2w_by_stem(truth)
    names = names or {stem: stem for stem in want}
    assert sorted(got) == sorted(names)
    for stem, c2w in got.items():
        np.testing.assert_allclose(c2w, want[names[stem]], atol=1e-6)


def test_nerfstudio_folder_with_images_and_transforms(synthetic, truth, tmp_path):
    run(synthetic, tmp_path / "out", "poses")
    assert read_json(tmp_path / "out" / "poses" / "transforms.json")["source"] == "transforms"
    assert_same_poses(tmp_path / "out", truth)


def test_colmap_project_with_images_and_sparse_0(synthetic, truth, tmp_path):
    # The poses stage's own output is a COLMAP model of its images; laid out as a COLMAP project it is read back.
    run(synthetic, tmp_path / "first", "poses")
    project = tmp_path / "project"
    shutil.copytree(tmp_path / "first" / "poses" / "images", project / "images")
    shutil.copytree(tmp_path / "first" / "poses" / "sparse", project / "sparse" / "0")
    run(project, tmp_path / "out", "poses")
    assert read_json(tmp_path / "out" / "poses" / "transforms.json")["source"] == "colmap"
    assert_same_poses(tmp_path / "out", truth)


def test_llff_folder_takes_its_largest_downscaled_images(synthetic, truth, tmp_path):
    folder = tmp_path / "llff"
    rows = []
    for frame in sorted(truth["frames"], key=lambda f: f["file_path"]):
        c2w = np.asarray(frame["transform_matrix"])
        llff = np.stack([-c2w[:3, 1], c2w[:3, 0], c2w[:3, 2], c2w[:3, 3]], 1)
        # LLFF's hwf is the full-size photo's; the folder has it at 1/2 (images_2) and 1/4 (images_4).
        hwf = np.array([[2 * truth["h"]], [2 * truth["w"]], [2 * truth["fl_x"]]])
        rows.append(np.concatenate([np.concatenate([llff, hwf], 1).ravel(), [1.0, 10.0]]))
        photo = Image.open(synthetic / frame["file_path"])
        for factor, size in ((2, photo.size), (4, (photo.size[0] // 2, photo.size[1] // 2))):
            (folder / f"images_{factor}").mkdir(parents=True, exist_ok=True)
            photo.resize(size).save(folder / f"images_{factor}" / f"{Path(frame['file_path']).stem}.png")
    np.save(folder / "poses_bounds.npy", np.array(rows))
    run(folder, tmp_path / "out", "poses")
    transforms = read_json(tmp_path / "out" / "poses" / "transforms.json")
    assert transforms["source"] == "llff" and (transforms["w"], transforms["h"]) == (truth["w"], truth["h"])
    np.testing.assert_allclose(transforms["fl_x"], truth["fl_x"], rtol=1e-6)
    assert_same_poses(tmp_path / "out", truth)


def nerf_synthetic(synthetic: Path, truth: dict, folder: Path, splits: dict[str, list[int]]) -> dict[str, str]:
    """A Blender-style dataset: <split>/r_<i>.png (RGBA) and transforms_<split>.json with extensionless paths and
    camera_angle_x, file names repeating across splits as lego's do. Returns stage name -> truth stem."""
    frames = sorted(truth["frames"], key=lambda f: f["file_path"])
    names = {}
    for split, indices in splits.items():
        (folder / split).mkdir(parents=True)
        entries = []
        for i, index in enumerate(indices):
            rgb = np.asarray(Image.open(synthetic / frames[index]["file_path"]).convert("RGB"))
            rgba = np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 255, np.uint8)], -1)
            Image.fromarray(rgba).save(folder / split / f"r_{i}.png")
            entries.append({"file_path": f"./{split}/r_{i}", "transform_matrix": frames[index]["transform_matrix"]})
            names[f"{split}_r_{i}"] = Path(frames[index]["file_path"]).stem
        angle = 2 * np.arctan(0.5 * truth["w"] / truth["fl_x"])
        (folder / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": entries}))
    return names


def test_nerf_synthetic_fits_train_and_holds_out_the_named_split(synthetic, truth, tmp_path):
    folder = tmp_path / "blender"
    names = nerf_synthetic(synthetic, truth, folder, {"train": [0, 1, 2, 3, 4], "val": [5, 6], "test": [7]})
    run(folder, tmp_path / "out", "normalize")
    assert_same_poses(tmp_path / "out", truth, {n: s for n, s in names.items() if not n.startswith("test")})
    scene = read_json(tmp_path / "out" / "normalize" / "scene.json")
    splits = {f["name"]: f["split"] for f in scene["frames"]}
    assert splits == {n: ("test" if n.startswith("val") else "train") for n in names if not n.startswith("test")}

    run(folder, tmp_path / "test_split", "normalize", "ingest.holdout_split=test")
    scene = read_json(tmp_path / "test_split" / "normalize" / "scene.json")
    assert sorted(f["name"] for f in scene["frames"] if f["split"] == "test") == ["test_r_0"]
    assert sum(f["split"] == "train" for f in scene["frames"]) == 5


def test_nerf_synthetic_without_the_named_split_is_a_one_line_error(synthetic, truth, tmp_path):
    folder = tmp_path / "blender"
    nerf_synthetic(synthetic, truth, folder, {"train": [0, 1, 2, 3], "val": [4, 5]})
    with pytest.raises(UserError, match="no test photos to hold out.*ingest.holdout_split"):
        run(folder, tmp_path / "out", "ingest", "ingest.holdout_split=test")
    # none: every train photo is used, and normalize holds out every Nth as for any capture.
    run(folder, tmp_path / "none", "normalize", "ingest.holdout_split=none", "normalize.holdout_every=2")
    scene = read_json(tmp_path / "none" / "normalize" / "scene.json")
    assert len(scene["frames"]) == 4 and sum(f["split"] == "test" for f in scene["frames"]) == 2


def test_nerf_synthetic_as_published_takes_only_the_frames_its_transforms_list(synthetic, truth, tmp_path):
    # The published test/ folders hold a depth and a normal render beside each photo; they are not frames.
    folder = tmp_path / "blender"
    names = nerf_synthetic(synthetic, truth, folder, {"train": [0, 1, 2, 3, 4], "test": [5, 6]})
    for i in range(2):
        for extra in ("depth", "normal"):
            Image.new("RGBA", (truth["w"], truth["h"])).save(folder / "test" / f"r_{i}_{extra}_0001.png")
    run(folder, tmp_path / "out", "normalize", "ingest.holdout_split=test")
    assert sorted(r["name"] for r in read_json(tmp_path / "out" / "ingest" / "images.json")["images"]) == sorted(names)
    scene = read_json(tmp_path / "out" / "normalize" / "scene.json")
    assert sorted(f["name"] for f in scene["frames"]) == sorted(names)
    assert_same_poses(tmp_path / "out", truth, names)


def test_split_folders_of_links_pose_each_photo_with_its_own_split_camera(synthetic, truth, tmp_path):
    # A common layout: the split folders hold links to photos kept elsewhere. r_0 is a name in train/ and test/, and
    # each must get the camera of its own split's file.
    published = tmp_path / "published"
    names = nerf_synthetic(synthetic, truth, published, {"train": [0, 1, 2, 3, 4], "test": [5, 6]})
    pool, linked = tmp_path / "pool", tmp_path / "linked"
    pool.mkdir()
    for split in ("train", "test"):
        (linked / split).mkdir(parents=True)
        shutil.copy(published / f"transforms_{split}.json", linked)
        for photo in (published / split).iterdir():
            shutil.copy(photo, pool / f"{split}_{photo.name}")
            (linked / split / photo.name).symlink_to(pool / f"{split}_{photo.name}")
    run(linked, tmp_path / "out", "poses", "ingest.holdout_split=test")
    assert_same_poses(tmp_path / "out", truth, names)


def test_photos_that_match_several_frames_only_by_name_are_refused(synthetic, truth, tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    frames = sorted(truth["frames"], key=lambda f: f["file_path"])[:4]
    for frame in frames:
        shutil.copy(synthetic / frame["file_path"], folder / Path(frame["file_path"]).name)
    # Written on another machine: no path matches, and two frames share the stem of the first photo.
    stem = Path(frames[0]["file_path"]).stem
    elsewhere = [{"file_path": f"/elsewhere/{split}/{stem}.png", "transform_matrix": frames[0]["transform_matrix"]}
                 for split in ("train", "test")]
    others = [{"file_path": f"/elsewhere/train/{Path(f['file_path']).name}", "transform_matrix": f["transform_matrix"]}
              for f in frames[1:]]
    intrinsics = {key: truth[key] for key in ("fl_x", "fl_y", "cx", "cy", "w", "h")}
    (folder / "transforms.json").write_text(json.dumps({**intrinsics, "frames": elsewhere + others}))
    with pytest.raises(UserError, match=f"several frames by name \\({stem}.png\\)"):
        run(folder, tmp_path / "out", "poses")
