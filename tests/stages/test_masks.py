"""Masks of the object beside the photos: found and matched by name, thresholded and resized by ingest, imported with
the NeuS/IDR layout's cameras, and scored inside by evaluate."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from stages.common.json_files import read_json
from stages.capture.masks import match_masks, read_mask
from stages.scoring.metrics import image_ssim, masked_scores
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from stages.capture.synthetic import write_scene
from stages.training.views import training_frames
from plenoxels.core.cameras import colmap_w2c_from_opengl_c2w
from plenoxels.core.errors import UserError


def textured(h=60, w=80, seed=0):
    rng = np.random.default_rng(seed)
    return np.asarray(Image.fromarray(rng.integers(0, 256, (h // 4, w // 4, 3), dtype=np.uint8)).resize((w, h)))


def disc(h=60, w=80, radius=15) -> np.ndarray:
    rows, cols = np.mgrid[:h, :w]
    return ((rows - h / 2) ** 2 + (cols - w / 2) ** 2 <= radius ** 2).astype(np.uint8) * 255


def run(scene: Path, out: Path, stages: list[str], *overrides: str) -> dict:
    return Pipeline(scene, out, overrides=list(overrides), reporter=Reporter(quiet=True)).run(stages)


def test_masks_folder_beside_the_photos_is_read_by_name_thresholded_and_resized(tmp_path, capsys):
    scene = tmp_path / "scan"
    (scene / "images").mkdir(parents=True)
    (scene / "masks").mkdir()
    for i in range(4):
        Image.fromarray(textured(seed=i)).save(scene / "images" / f"IMG_{i:04d}.jpg", quality=95)
    # A PNG mask of the same stem; a JPEG mask whose black is noisy; a mask at twice the size; one photo without.
    Image.fromarray(disc()).save(scene / "masks" / "IMG_0000.png")
    noisy = np.clip(disc().astype(int) + np.random.default_rng(0).integers(0, 40, (60, 80)), 0, 255).astype(np.uint8)
    Image.fromarray(noisy).save(scene / "masks" / "IMG_0001.jpg", quality=70)
    Image.fromarray(disc(120, 160, 30)).save(scene / "masks" / "IMG_0002_mask.png")
    run(scene, tmp_path / "out", ["ingest"], "ingest.max_side=40")
    listing = read_json(tmp_path / "out" / "ingest" / "images.json")
    by_name = {r["name"]: r for r in listing["images"]}
    assert by_name["IMG_0003"]["mask"] is None
    warnings = [line for line in capsys.readouterr().err.splitlines() if "no mask" in line]
    assert len(warnings) == 1 and "1 of 4 photos" in warnings[0] and "IMG_0003" in warnings[0]
    expected = np.asarray(Image.fromarray(disc()).resize((40, 30), Image.Resampling.BOX)).astype(float)
    for name in ("IMG_0000", "IMG_0001", "IMG_0002"):
        record = by_name[name]
        assert record["mask"] == f"masks/{name}.png" and record["mask_from"].startswith("masks/")
        mask = np.asarray(Image.open(tmp_path / "out" / "ingest" / record["mask"])).astype(float)
        # Downscaled with its photo; the JPEG's noise, under the threshold, is gone.
        assert mask.shape == (30, 40) and np.abs(mask - expected).mean() < 8
    summary = read_json(tmp_path / "out" / "ingest" / "manifest.json")["summary"]
    assert summary["masked"] == 3 and "3 with masks (3 from mask files)" in summary["line"]


def test_masks_of_another_shape_or_unreadable_stop_with_one_line(tmp_path):
    photos = tmp_path / "photos"
    (photos / "masks").mkdir(parents=True)   # a masks/ folder inside the photo folder counts too
    for i in range(3):
        Image.fromarray(textured(seed=i)).save(photos / f"{i}.png")
        Image.fromarray(disc()).save(photos / "masks" / f"{i}.png")
    Image.fromarray(disc(80, 80)).save(photos / "masks" / "1.png")
    with pytest.raises(UserError, match=r"mask .*1\.png is 80x80 but its photo is 80x60, another shape"):
        run(photos, tmp_path / "out", ["ingest"])
    (photos / "masks" / "1.png").write_bytes(b"not an image")
    with pytest.raises(UserError, match=r"cannot read the mask .*1\.png"):
        run(photos, tmp_path / "out", ["ingest"])


def test_a_mask_made_from_a_turned_photos_stored_pixels_is_turned_with_it(tmp_path):
    photos = tmp_path / "phone"
    (photos / "masks").mkdir(parents=True)
    stored = textured(seed=0).copy()
    stored[:12, :16] = 255            # a white corner, top-left as stored
    marked = np.zeros((60, 80), np.uint8)
    marked[:12, :16] = 255            # its mask, made from the pixels as stored (EXIF ignored)
    for i, orientation in enumerate((6, 8, 1)):
        exif = Image.Exif()
        exif[0x0112] = orientation
        Image.fromarray(stored).save(photos / f"{i}.jpg", exif=exif, quality=95)
        Image.fromarray(marked).save(photos / "masks" / f"{i}.png")
    run(photos, tmp_path / "out", ["ingest"])
    for i in range(3):
        photo = np.asarray(Image.open(tmp_path / "out" / "ingest" / "images" / f"{i}.png"))
        mask = np.asarray(Image.open(tmp_path / "out" / "ingest" / "masks" / f"{i}.png"))
        assert mask.shape == photo.shape[:2]
        corner = photo.min(axis=2) > 230
        assert (mask[corner] == 255).mean() > 0.95 and corner[mask == 255].mean() > 0.8


def test_mask_names_match_by_stem_suffix_and_zero_padding_never_by_guess(tmp_path):
    photos = [tmp_path / "photos" / name for name in ("000000.png", "000001.png", "a.jpg", "b.jpg", "b.png", "c.jpg")]
    folder = tmp_path / "masks"
    folder.mkdir()
    for name in ("000.png", "1.png", "a.jpg.png", "b.png", "c_mask.png", "c.png"):
        (folder / name).touch()
    found = {photo.name: mask.name for photo, mask in match_masks(photos, folder).items()}
    # 000.png and 1.png differ from their photos only in zero-padding; COLMAP's a.jpg.png names a.jpg; b.png names
    # both b.jpg and b.png, so neither is guessed; c has two masks, so it gets none.
    assert found == {"000000.png": "000.png", "000001.png": "1.png", "a.jpg": "a.jpg.png"}


def test_read_mask_takes_alpha_or_brightest_channel_above_the_threshold(tmp_path):
    rgba = np.zeros((10, 10, 4), np.uint8)
    rgba[..., 3] = 0
    rgba[2:5, 2:5, 3] = 200
    Image.fromarray(rgba, "RGBA").save(tmp_path / "cutout.png")
    mask = read_mask(tmp_path / "cutout.png", (10, 10))
    assert mask.sum() == 9 * 255
    grey = np.zeros((10, 10), np.uint8)
    grey[:, :5] = 100
    Image.fromarray(grey).save(tmp_path / "grey.png")
    assert read_mask(tmp_path / "grey.png", (10, 10)).sum() == 50 * 255
    assert read_mask(tmp_path / "grey.png", (10, 10), threshold=100).sum() == 0


def neus_layout(synthetic: Path, folder: Path) -> tuple[dict, np.ndarray]:
    """The synthetic alpha scene as NeuS's DTU release lays it out: image/000000.png, mask/000.png and
    cameras_sphere.npz (world_mat_i = K [R | t] with pixel centres at whole numbers, scale_mat_i the sphere's
    similarity). Returns the truth transforms and scale_mat."""
    truth = read_json(synthetic / "transforms.json")
    (folder / "image").mkdir(parents=True)
    (folder / "mask").mkdir()
    scale_mat = np.diag([1.7, 1.7, 1.7, 1.0])
    scale_mat[:3, 3] = [0.3, -0.2, 0.5]
    k = np.array([[truth["fl_x"], 0, truth["cx"] - 0.5], [0, truth["fl_y"], truth["cy"] - 0.5], [0, 0, 1]])
    arrays = {}
    for i, frame in enumerate(truth["frames"]):
        rgba = np.asarray(Image.open(synthetic / frame["file_path"]))
        Image.fromarray(rgba[..., :3]).save(folder / "image" / f"{i:06d}.png")
        Image.fromarray(np.repeat(np.where(rgba[..., 3:] > 127, 255, 0).astype(np.uint8), 3, -1)).save(
            folder / "mask" / f"{i:03d}.png")
        rotation, translation = colmap_w2c_from_opengl_c2w(np.asarray(frame["transform_matrix"]))
        world = np.eye(4)
        world[:3] = -2.0 * k @ np.hstack([rotation, translation[:, None]])  # any scale and sign
        arrays[f"world_mat_{i}"] = world
        arrays[f"scale_mat_{i}"] = scale_mat
    np.savez(folder / "cameras_sphere.npz", **arrays)
    return truth, scale_mat


def test_neus_idr_layout_imports_its_cameras_and_its_masks(tmp_path):
    synthetic = write_scene("object", tmp_path / "synthetic", n_views=6, width=96, height=72, seed=2, alpha=True,
                            supersample=1)
    truth, scale_mat = neus_layout(synthetic, tmp_path / "dtu_scan")
    run(tmp_path / "dtu_scan", tmp_path / "out", ["ingest", "poses"])
    listing = read_json(tmp_path / "out" / "ingest" / "images.json")
    assert [r["mask_from"] for r in listing["images"]] == [f"mask/{i:03d}.png" for i in range(6)]
    transforms = read_json(tmp_path / "out" / "poses" / "transforms.json")
    assert transforms["source"] == "idr" and len(transforms["frames"]) == 6
    assert transforms["fl_x"] == pytest.approx(truth["fl_x"]) and transforms["cx"] == pytest.approx(truth["cx"])
    # The poses come in the sphere's frame: the world's through the inverse of scale_mat.
    sphere_from_world = np.linalg.inv(scale_mat)
    for i, frame in enumerate(transforms["frames"]):
        want = np.asarray(truth["frames"][i]["transform_matrix"])
        got = np.asarray(frame["transform_matrix"])
        np.testing.assert_allclose(got[:3, :3], want[:3, :3], atol=1e-9)
        np.testing.assert_allclose(got[:3, 3], (sphere_from_world @ want[:, 3])[:3], atol=1e-9)
        assert frame["mask_path"] == f"masks/{frame['name']}.png"


def test_idr_cameras_that_do_not_match_the_photos_are_one_line_errors(tmp_path):
    synthetic = write_scene("object", tmp_path / "synthetic", n_views=4, width=64, height=48, seed=1, alpha=True,
                            supersample=1)
    scan = tmp_path / "scan"
    neus_layout(synthetic, scan)
    for photo in (scan / "image").iterdir():
        photo.rename(photo.with_name(f"view_{photo.name}"))
    (scan / "mask").rename(scan / "unused")
    with np.load(scan / "cameras_sphere.npz") as data:
        cameras = {k: data[k] for k in data.files if not k.endswith("_3")}
    np.savez(scan / "cameras_sphere.npz", **cameras)
    with pytest.raises(UserError, match="has 3 cameras but the folder has 4 photos"):
        run(scan, tmp_path / "out", ["ingest", "poses"])


def test_masked_scores_count_only_the_pixels_inside_the_mask():
    rng = np.random.default_rng(0)
    truth = rng.uniform(size=(40, 50, 3)).astype(np.float32)
    mask = np.zeros((40, 50), np.float32)
    mask[10:30, 10:40] = 1.0
    render = truth.copy()
    render[mask == 0] = 1.0 - render[mask == 0]                        # wrong only outside
    outside_wrong = masked_scores(render, truth, mask)
    # SSIM's window reaches a few pixels past the mask's edge; the whole image's SSIM is far lower.
    assert outside_wrong["psnr_masked"] >= 100 and outside_wrong["ssim_masked"] > 0.7 > 0.2 > image_ssim(render, truth)
    render = truth.copy()
    render[mask > 0] += 0.1
    inside_wrong = masked_scores(np.clip(render, 0, 1), truth, mask)
    assert 19 < inside_wrong["psnr_masked"] < 21.5 and inside_wrong["ssim_masked"] < 0.99
    assert masked_scores(render, truth, np.zeros_like(mask)) == {}


class _Warnings:
    def __init__(self):
        self.lines = []

    def warn(self, message):
        self.lines.append(message)


def test_a_masked_capture_fits_without_its_unmasked_photos():
    frames = [{"name": f"p{i}", "split": "test" if i == 0 else "train", "mask_path": f"masks/p{i}.png" if i != 2 else None}
              for i in range(5)]
    report = _Warnings()
    train, held_out = training_frames({"frames": frames}, report)
    assert [f["name"] for f in train] == ["p1", "p3", "p4"] and [f["name"] for f in held_out] == ["p0"]
    assert len(report.lines) == 1 and "p2" in report.lines[0]
    # Without masks every training photo is fitted whole, and no warning is given.
    unmasked = [{**f, "mask_path": None} for f in frames]
    train, _ = training_frames({"frames": unmasked}, report)
    assert len(train) == 4 and len(report.lines) == 1
