"""Ingest: every kind of photo becomes an upright 8-bit RGB PNG; bad input is reported, never a traceback."""
import json

import cv2
import numpy as np
import pytest
from PIL import Image

from pipeline.io import read_rgb
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from plenoxels.errors import UserError


def textured(h=60, w=80, seed=0):
    rng = np.random.default_rng(seed)
    return cv2.resize(rng.integers(0, 256, (h // 4, w // 4, 3), dtype=np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)


def run_ingest(photos, tmp_path, *overrides):
    pipe = Pipeline(photos, tmp_path / "out", overrides=list(overrides), reporter=Reporter(quiet=True))
    pipe.run(["ingest"])
    return tmp_path / "out" / "ingest", json.loads((tmp_path / "out" / "ingest" / "images.json").read_text())


@pytest.fixture
def photos(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    for i in range(3):
        Image.fromarray(textured(seed=i)).save(folder / f"p{i}.jpg", quality=95)
    return folder


def test_plain_jpgs(photos, tmp_path):
    out, listing = run_ingest(photos, tmp_path)
    assert [r["name"] for r in listing["images"]] == ["p0", "p1", "p2"]
    image = read_rgb(out / "images" / "p0.png")
    assert image.shape == (60, 80, 3) and image.dtype == np.uint8
    assert not listing["skipped"] and not (out / "masks").exists()


def test_exif_orientation_is_applied(photos, tmp_path):
    pixels = textured(60, 80, seed=9)
    pixels[:10, :10] = 255  # a white top-left corner marks the stored orientation
    exif = Image.Exif()
    exif[0x0112] = 6  # stored rotated: viewers turn it 90 degrees clockwise
    Image.fromarray(pixels).save(photos / "rotated.jpg", exif=exif, quality=95)
    out, _ = run_ingest(photos, tmp_path)
    upright = read_rgb(out / "images" / "rotated.png")
    assert upright.shape == (80, 60, 3)
    assert upright[:10, -10:].mean() > 200  # the stored top-left corner is now top-right


def test_sixteen_bit_greyscale_and_rgba(photos, tmp_path):
    wide = (textured(seed=3).astype(np.uint16) * 257)
    cv2.imwrite(str(photos / "wide.png"), cv2.cvtColor(wide, cv2.COLOR_RGB2BGR))
    Image.fromarray(textured(seed=4)[..., 0]).save(photos / "grey.png")
    rgba = np.dstack([textured(seed=5), np.full((60, 80), 128, np.uint8)])
    Image.fromarray(rgba, "RGBA").save(photos / "cutout.png")
    out, listing = run_ingest(photos, tmp_path)
    by_name = {r["name"]: r for r in listing["images"]}
    assert np.abs(read_rgb(out / "images" / "wide.png").astype(int) - textured(seed=3)).max() <= 1
    grey = read_rgb(out / "images" / "grey.png")
    assert grey.shape == (60, 80, 3) and (grey[..., 0] == grey[..., 2]).all()
    assert by_name["cutout"]["mask"] == "masks/cutout.png"
    assert (read_rgb(out / "masks" / "cutout.png")[..., 0] == 128).all()
    assert by_name["wide"]["mask"] is None


def test_downscale_keeps_aspect_and_records_scale(photos, tmp_path):
    _, listing = run_ingest(photos, tmp_path, "ingest.max_side=40")
    record = listing["images"][0]
    assert (record["width"], record["height"]) == (40, 30)
    assert record["scale"] == pytest.approx(0.5)


def test_unreadable_files_are_listed_and_skipped(photos, tmp_path, capsys):
    (photos / "broken.jpg").write_bytes(b"not a jpeg at all")
    (photos / "notes.docx").write_bytes(b"x")
    _, listing = run_ingest(photos, tmp_path)
    assert len(listing["images"]) == 3
    assert any("broken.jpg" in s for s in listing["skipped"]) and any("notes.docx" in s for s in listing["skipped"])
    warning = [l for l in capsys.readouterr().err.splitlines() if "skipped 2 file(s)" in l]
    assert len(warning) == 1 and "broken.jpg" in warning[0] and "notes.docx" in warning[0]


def test_too_few_images_is_a_clear_error(tmp_path):
    folder = tmp_path / "two"
    folder.mkdir()
    for i in range(2):
        Image.fromarray(textured(seed=i)).save(folder / f"{i}.png")
    (folder / "bad.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(UserError, match=r"only 2 usable image\(s\).*at least 3"):
        run_ingest(folder, tmp_path)
    assert not (tmp_path / "out" / "ingest").exists()


def test_blurriest_are_dropped(photos, tmp_path):
    Image.fromarray(cv2.GaussianBlur(textured(seed=7), (0, 0), 4)).save(photos / "blurry.jpg")
    _, listing = run_ingest(photos, tmp_path, "ingest.drop_blurry_fraction=0.25")
    assert listing["dropped_blurry"] == ["blurry"]
    assert "blurry" not in [r["name"] for r in listing["images"]]


def test_video_keeps_the_sharpest_frame_per_window(tmp_path):
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (80, 60))
    for i in range(20):
        frame = textured(seed=i // 5)
        if i % 5 != 2:  # in each half-second window, only frame 2 is sharp
            frame = cv2.GaussianBlur(frame, (0, 0), 3)
        writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    writer.release()
    _, listing = run_ingest(video, tmp_path, "ingest.video_fps=2")
    assert [r["name"] for r in listing["images"]] == ["frame_000002", "frame_000007", "frame_000012", "frame_000017"]
