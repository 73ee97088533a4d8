"""The peers benchmark's bookkeeping: the photos it prepares for TensoRF, and the time each side needs to reach the
other's PSNR."""
import json

import imageio.v3 as iio
import numpy as np

from bench.peers import crossings, protocol_data
from stages.common.frames import load_frame


def _blender_folder(root, views):
    """A lego-like folder: 800x800 RGBA renders with a transparent background, train and val splits."""
    rng = np.random.default_rng(0)
    for split in ("train", "val"):
        (root / split).mkdir(parents=True)
        frames = []
        for i in range(views):
            image = np.zeros((800, 800, 4), np.uint8)
            image[200:600, 300:500] = rng.integers(0, 256, (400, 200, 4))
            image[200:600, 300:500, 3] = np.where(image[200:600, 300:500, 3] > 128, 255, 0)
            iio.imwrite(root / split / f"r_{i}.png", image)
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": np.eye(4).tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))
    return {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}


def test_the_prepared_photos_are_what_our_fit_sees_and_the_scene_is_never_written(tmp_path):
    lego = tmp_path / "lego"
    before = _blender_folder(lego, views=2)
    folder = tmp_path / "peers" / "lego-200x200"
    folder.mkdir(parents=True)
    for name in ("train", "val", "transforms_train.json"):  # a layout of links into the scene, as a run may leave
        (folder / name).symlink_to(lego / name)

    protocol_data(lego, folder)

    assert {p: p.read_bytes() for p in lego.rglob("*") if p.is_file()} == before
    for split, name in (("train", "train"), ("val", "test")):
        meta = json.loads((folder / f"transforms_{name}.json").read_text())
        assert [f["file_path"] for f in meta["frames"]] == [f"./{split}/r_0", f"./{split}/r_1"]
        written = iio.imread(folder / split / "r_1.png")
        assert written.shape == (200, 200, 4) and (written[..., 3] == 255).all()
        frame = {"file_path": f"{split}/r_1.png", "mask_path": f"{split}/r_1.png", "fl_x": 1000.0, "fl_y": 1000.0,
                 "cx": 400.0, "cy": 400.0, "w": 800, "h": 800}
        ours = load_frame(lego, frame, 0.25, np.ones(3, np.float32))[0]
        assert np.abs(written[..., :3] / 255.0 - ours).max() <= 0.5 / 255 + 1e-6
        assert ours.min() < 0.5  # the object is in the picture, not only the white backdrop


def test_each_side_is_timed_to_the_others_psnr():
    tensorf = [{"seconds": 60.0, "psnr": 18.0, "steps": 100}, {"seconds": 600.0, "psnr": 23.0, "steps": 1000},
               {"seconds": 300.0, "psnr": 21.5, "steps": 500}]
    ours = [{"label": "fast", "psnr": 30.9, "seconds": 34.0}, {"label": "budget 5s", "psnr": 25.0, "seconds": 5.0},
            {"label": "budget 2s", "psnr": 21.0, "seconds": 2.0}]
    c = crossings(tensorf, ours)
    assert c["tensorf_final"]["seconds"] == 600.0
    assert c["ours_to_tensorf_final"]["label"] == "budget 5s"
    assert c["ours_to_tensorf_final"]["share_of_tensorf_time"] == 5.0 / 600.0
    assert {r["label"]: r["tensorf_seconds"] for r in c["tensorf_to_ours"]} == {
        "fast": None, "budget 5s": None, "budget 2s": 300.0}
    assert crossings(tensorf, [{"label": "slow", "psnr": 22.0, "seconds": 900.0}])["ours_to_tensorf_final"] is None
