"""Ingest: every kind of photo becomes an upright 8-bit RGB PNG; bad input is reported, never a traceback."""
import json
import os
import subprocess
import tracemalloc

import cv2
import numpy as np
import PIL.features
import pytest
from PIL import Image

from stages.capture.picture import picture_box, still_overlay
from stages.capture.video import frames_by_motion
from stages.common.media import read_rgb
from pipeline.report import Reporter
from pipeline.scenes import scene_name
from pipeline.runner import Pipeline
from plenoxels.core.errors import UserError


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


def test_photos_as_browsers_and_old_cameras_save_them(photos, tmp_path):
    Image.fromarray(textured(seed=5)).save(photos / "download.jfif", format="JPEG", quality=95)
    Image.fromarray(textured(seed=6)).save(photos / "scan.bmp")
    kinds = ["download", "p0", "p1", "p2", "scan"]
    if PIL.features.check("avif"):
        Image.fromarray(textured(seed=7)).save(photos / "phone.avif", quality=95)
        kinds.append("phone")
    out, listing = run_ingest(photos, tmp_path)
    assert sorted(r["name"] for r in listing["images"]) == sorted(kinds) and not listing["skipped"]
    assert np.abs(read_rgb(out / "images" / "scan.png").astype(int) - textured(seed=6)).max() == 0


@pytest.mark.parametrize("name, says", [
    ("p0.jpg", "p0.jpg is one photo; give the folder that holds the scene's photos"),
    ("photos.zip", "photos.zip is an archive; unpack it and give the folder"),
    ("notes.txt", "notes.txt is neither a folder of photos nor a video"),
    ("VID_0001.insv", "a 360 camera's own file .* export it from the camera's app as an equirectangular MP4")])
def test_a_file_that_is_no_scene_says_what_to_give(photos, tmp_path, name, says):
    given = photos / name
    if not given.exists():
        given.write_bytes(b"PK\x03\x04" if name.endswith(".zip") else b"a note")
    with pytest.raises(UserError, match=says):
        run_ingest(given, tmp_path)


def test_names_in_another_systems_encoding_are_read_and_made_text(photos, tmp_path):
    """Names whose bytes are not UTF-8 (Latin-1 from an old camera card or another system): Python keeps them as lone
    surrogates, which OpenCV and COLMAP cannot take (OpenCV crashed on a PNG so named)."""
    latin = os.fsdecode(b"caf\xe9")
    wide = (textured(seed=3).astype(np.uint16) * 257)
    cv2.imencode(".png", cv2.cvtColor(wide, cv2.COLOR_RGB2BGR))[1].tofile(photos / f"{latin}.png")
    out, listing = run_ingest(photos, tmp_path / "a")
    assert "caf%e9" in [r["name"] for r in listing["images"]] and (out / "images" / "caf%e9.png").is_file()
    video = panning_video(tmp_path / "pan.avi", 30, step_px=2).rename(tmp_path / f"{latin}.avi")
    _, frames = run_ingest(video, tmp_path / "b", "ingest.video_fps=100", "ingest.video_min_frames=3")
    assert len(frames["images"]) >= 3 and frames["images"][0]["source"] == f"{latin}.avi"
    assert scene_name(tmp_path / latin / "images") == "caf%e9"
    with pytest.raises(UserError, match="not UTF-8 text"):
        Pipeline(photos, tmp_path / latin, reporter=Reporter(quiet=True))


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
    (photos / "IMG_0001.insp").write_bytes(b"x")  # a 360 camera's unstitched photo
    _, listing = run_ingest(photos, tmp_path)
    assert len(listing["images"]) == 3
    assert any("broken.jpg" in s for s in listing["skipped"]) and any("notes.docx" in s for s in listing["skipped"])
    assert any("IMG_0001.insp (a 360 camera's unstitched file" in s for s in listing["skipped"])
    warning = [l for l in capsys.readouterr().err.splitlines() if "skipped 3 file(s)" in l]
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


def test_photos_only_in_subfolders_name_them(photos, tmp_path):
    top = tmp_path / "trip"
    (top / "day1").mkdir(parents=True)
    (top / "notes").mkdir()
    (top / "notes" / "plan.txt").write_text("x")
    photos.rename(top / "day2")
    Image.fromarray(textured(seed=6)).save(top / "day1" / "a.jpg")
    with pytest.raises(UserError, match=r"no photos in .*trip itself, but its folders day1/ \(1 photo\), "
                                        r"day2/ \(3 photos\) hold some"):
        run_ingest(top, tmp_path)
    assert not (tmp_path / "out" / "ingest").exists()


def test_blurriest_are_dropped(photos, tmp_path):
    Image.fromarray(cv2.GaussianBlur(textured(seed=7), (0, 0), 4)).save(photos / "blurry.jpg")
    _, listing = run_ingest(photos, tmp_path, "ingest.drop_blurry_fraction=0.25")
    assert listing["dropped_blurry"] == ["blurry"]
    assert "blurry" not in [r["name"] for r in listing["images"]]


def test_a_shot_saved_twice_is_kept_once_and_a_photo_beside_it_is_not(tmp_path):
    folder = tmp_path / "shots"
    folder.mkdir()
    for i in range(3):
        Image.fromarray(textured(240, 320, seed=i)).save(folder / f"p{i}.jpg", quality=95)
    Image.fromarray(np.asarray(Image.open(folder / "p1.jpg"))).save(folder / "p1_copy.png")
    Image.fromarray(np.asarray(Image.open(folder / "p2.jpg"))).save(folder / "p2.jpeg", quality=80)
    Image.fromarray(np.roll(textured(240, 320, seed=0), 4, axis=1)).save(folder / "p0_moved.jpg", quality=95)
    # A phone's copy sorts before its original ("(" before "."): the original, the shorter name, is kept.
    Image.fromarray(textured(240, 320, seed=5)).save(folder / "p5.jpg", quality=95)
    (folder / "p5(1).jpg").write_bytes((folder / "p5.jpg").read_bytes())
    out, listing = run_ingest(folder, tmp_path)
    assert listing["repeated"] == {"p1_copy_png": "p1_jpg", "p2_jpg": "p2_jpeg", "p5(1)_jpg": "p5_jpg"}
    kept = ["p0_jpg", "p0_moved_jpg", "p1_jpg", "p2_jpeg", "p5_jpg"]
    assert sorted(r["name"] for r in listing["images"]) == kept
    assert sorted(p.stem for p in (out / "images").iterdir()) == kept


def test_greyscale_photos_among_colour_ones_are_marked_and_mixed_sizes_are_counted(photos, tmp_path, capsys):
    Image.fromarray(textured(seed=8)[..., 1]).save(photos / "grey10.jpg", quality=95)
    grey_rgb = np.repeat(textured(seed=9)[..., :1], 3, axis=-1)  # stored as colour, channels equal
    Image.fromarray(np.ascontiguousarray(np.rot90(grey_rgb))).save(photos / "grey9.jpg", quality=95)
    _, listing = run_ingest(photos, tmp_path)
    marked = sorted(r["name"] for r in listing["images"] if r.get("colourless"))
    assert marked == ["grey10", "grey9"]
    summary = json.loads((tmp_path / "out" / "ingest" / "manifest.json").read_text())["summary"]
    assert summary["colourless"] == 2 and "2 without colour" in summary["line"]
    assert summary["line"].startswith("5 images at 80x60 (4), 60x80 (1)")
    warning = [line for line in capsys.readouterr().err.splitlines() if "have no colour" in line]
    assert len(warning) == 1 and "grey9, grey10;" in warning[0]  # in the capture's order, 9 before 10


def test_a_capture_grey_throughout_keeps_every_photo_for_the_fit(tmp_path):
    folder = tmp_path / "grey"
    folder.mkdir()
    for i in range(4):
        Image.fromarray(textured(seed=i)[..., 0]).save(folder / f"g{i}.png")
    Image.fromarray(textured(seed=5) // 16 + 100).save(folder / "faint.png")  # colour, but faint
    _, listing = run_ingest(folder, tmp_path)
    assert not any(r.get("colourless") for r in listing["images"])


def panning_video(path, frames: int, sharp_every: int = 1, step_px: int = 1, fps: int = 10, size=(80, 60),
                  within=None, mark=None):
    """A camera panning across a textured wall, step_px pixels a frame; only every sharp_every-th frame is sharp.
    `within` (x, y, width, height) puts each frame of `size` at that place in a larger black frame, as an editor
    pads a clip of another shape; `mark(frame)` draws on each frame what an app burns in."""
    width, height = size
    wall = textured(h=height, w=width + frames * step_px, seed=11)
    x, y, outer_width, outer_height = within or (0, 0, width, height)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (outer_width, outer_height))
    for i in range(frames):
        frame = wall[:, i * step_px:i * step_px + width]
        if i % sharp_every:
            frame = cv2.GaussianBlur(frame, (0, 0), 3)
        padded = np.zeros((outer_height, outer_width, 3), np.uint8)
        padded[y:y + height, x:x + width] = frame
        if mark is not None:
            mark(padded)
        writer.write(cv2.cvtColor(padded, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def test_video_frames_follow_the_motion_and_keep_the_sharpest(tmp_path):
    # 1 px a frame on an 80x60 frame (100 px diagonal): at 8% of the diagonal a frame is due about every 8 frames.
    video = panning_video(tmp_path / "pan.avi", 60, sharp_every=3)
    _, listing = run_ingest(video, tmp_path, "ingest.video_motion=0.08", "ingest.video_fps=100",
                            "ingest.video_frames=0")
    kept = [int(r["name"].split("_")[1]) for r in listing["images"]]
    assert all(i % 3 == 0 for i in kept[1:]), kept           # of each stretch's candidates, a sharp one
    gaps = np.diff(kept)
    assert 5 <= np.median(gaps) <= 12 and gaps.max() <= 14, kept


def test_a_folder_holding_one_video_reads_the_video_and_one_of_two_names_them(tmp_path):
    clip = tmp_path / "clip"
    clip.mkdir()
    panning_video(clip / "pan.avi", 60)
    (clip / "notes.txt").write_text("shot on a phone")
    _, listing = run_ingest(clip, tmp_path, "ingest.video_min_frames=3")
    assert listing["images"] and {r["source"] for r in listing["images"]} == {"pan.avi"}
    panning_video(clip / "again.avi", 20)
    with pytest.raises(UserError, match=r"holds 2 videos and no photos: give one of them \(again.avi, pan.avi\)"):
        run_ingest(clip, tmp_path / "second")


def test_videos_beside_photos_are_named_as_not_read_not_as_unreadable(tmp_path, photos, capsys):
    for i in range(2):       # a phone's Live Photos: each photo's short clip beside it
        panning_video(photos / f"p{i}.mov", 10)
    out, listing = run_ingest(photos, tmp_path)
    assert len(listing["images"]) == 3 and listing["skipped"] == []
    assert "3 images at 80x60, 2 video(s) beside them not read" in json.loads((out / "manifest.json").read_text())[
        "summary"]["line"]
    assert "2 video(s) beside the photos are not read: p0.mov, p1.mov" in capsys.readouterr().err


def test_video_keeps_more_frames_where_the_camera_moves_faster(tmp_path):
    slow = run_ingest(panning_video(tmp_path / "slow.avi", 60, step_px=1), tmp_path / "a", "ingest.video_fps=100",
                      "ingest.video_frames=0")[1]
    fast = run_ingest(panning_video(tmp_path / "fast.avi", 60, step_px=2), tmp_path / "b", "ingest.video_fps=100",
                      "ingest.video_frames=0")[1]
    assert len(fast["images"]) >= 1.6 * len(slow["images"])
    capped = run_ingest(tmp_path / "fast.avi", tmp_path / "c", "ingest.video_fps=0.5")[1]
    assert len(capped["images"]) <= 4    # 6 s of video at most 0.5 frames a second (and the first)


def test_a_long_slow_stretch_holds_one_candidate_frame_not_all_of_them(tmp_path):
    # 0.1 px a frame on a 160x120 frame (200 px diagonal): at 30% of it, frames 36-60 px along are candidates, 240 of
    # them, 56 kB each; ingest holds the sharpest alone, whatever the stretch's length.
    wall = textured(h=120, w=260, seed=4)
    path = tmp_path / "drift.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (160, 120))
    for i in range(640):
        shift = np.float32([[1, 0, -0.1 * i], [0, 1, 0]])
        writer.write(cv2.cvtColor(cv2.warpAffine(wall, shift, (160, 120), flags=cv2.INTER_LINEAR), cv2.COLOR_RGB2BGR))
    writer.release()
    tracemalloc.start()
    try:
        frames, _ = frames_by_motion(path, 0, 0.3, 100, Reporter(quiet=True))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert 2 <= len(frames) <= 4, [name for name, _ in frames]
    assert peak < 40 * 160 * 120 * 3, peak     # the frames kept, one candidate, what reading holds: not 240 candidates


def test_a_clip_that_moves_little_is_read_again_with_frames_closer_together(tmp_path):
    # 1 px a frame: at 5% of the 100 px diagonal about 12 frames of 60; 24 wanted, so the clip is read again.
    video = panning_video(tmp_path / "slow.avi", 60, step_px=1)
    sparse = run_ingest(video, tmp_path / "a", "ingest.video_fps=100", "ingest.video_frames=0")[1]
    out, dense = run_ingest(video, tmp_path / "b", "ingest.video_fps=100", "ingest.video_frames=24",
                            "ingest.video_min_frames=12")
    assert len(sparse["images"]) < 16 and len(dense["images"]) >= 1.5 * len(sparse["images"]), (sparse, dense)
    assert dense["video"]["motion"] < 0.05 <= sparse["video"]["motion"]
    assert 0.4 < dense["video"]["total_motion"] < 0.8  # 59 px of a 100 px diagonal
    line = json.loads((out / "manifest.json").read_text())["summary"]["line"]
    assert "closer than ingest.video_motion" in line and "fewer than ingest.video_frames's 24" in line
    assert "too short" not in line     # the frames aimed for and the fewest for a good fit are two settings


def test_a_long_clip_keeps_at_most_video_max_frames_spread_over_all_of_it(tmp_path):
    # 2 px a frame at 4% of the 100 px diagonal: a frame due every 2 frames, about 60 of 120.
    video = panning_video(tmp_path / "long.avi", 120, step_px=2)
    every = run_ingest(video, tmp_path / "a", "ingest.video_fps=100", "ingest.video_motion=0.04",
                       "ingest.video_frames=0", "ingest.video_max_frames=0", "ingest.video_min_frames=3")[1]
    out, capped = run_ingest(video, tmp_path / "b", "ingest.video_fps=100", "ingest.video_motion=0.04",
                             "ingest.video_frames=0", "ingest.video_max_frames=20", "ingest.video_min_frames=3")
    due = len(every["images"])
    assert due > 40 and capped["video"]["due"] == pytest.approx(due, abs=2)
    kept = [int(r["name"].split("_")[1]) for r in capped["images"]]
    assert 15 <= len(kept) <= 20 and capped["video"]["every"] == -(-capped["video"]["due"] // 20)
    assert kept[0] == 0 and kept[-1] >= 100                    # from the clip's start to its end
    line = json.loads((out / "manifest.json").read_text())["summary"]["line"]
    assert f"one in {capped['video']['every']} of the {capped['video']['due']} that spacing gave" in line


def saved_frames(folder, frames: int, step_px: int):
    """A panning camera's frames saved one by one, as `ffmpeg -i clip.mp4 %04d.png` saves them."""
    folder.mkdir()
    wall = textured(h=60, w=80 + frames * step_px, seed=11)
    for i in range(frames):
        Image.fromarray(np.ascontiguousarray(wall[:, i * step_px:i * step_px + 80])).save(folder / f"{i:04d}.png")
    return folder


def test_a_folder_of_a_videos_frames_saved_one_by_one_is_read_as_the_video(tmp_path, capsys):
    # 1 px a frame, 1% of the 100 px diagonal: closer than a quarter of the 5% a video's frames are kept at.
    frames = saved_frames(tmp_path / "frames", 130, step_px=1)
    out, listing = run_ingest(frames, tmp_path / "a", "ingest.video_max_frames=40", "ingest.video_frames=0",
                              "ingest.video_min_frames=3")
    kept = [int(r["name"]) for r in listing["images"]]
    assert kept == list(range(0, 130, 5))         # 5% apart: every 5th, within the 40 at most
    summary = json.loads((out / "manifest.json").read_text())["summary"]
    assert summary["sequence"]["step"] == 5 and 0.007 < summary["sequence"]["apart"] < 0.013
    assert "one in 5 of 130 frames saved from a video" in summary["line"]
    assert "the 130 photos are a video's frames saved one by one" in capsys.readouterr().err
    aimed = run_ingest(frames, tmp_path / "b", "ingest.video_max_frames=40", "ingest.video_frames=60",
                       "ingest.video_min_frames=3")[1]
    assert len(aimed["images"]) == 33               # 60 aimed for allow every 2nd; 40 at most ask every 4th
    apart = saved_frames(tmp_path / "photos", 130, step_px=4)   # 4% apart: photos taken one by one
    assert len(run_ingest(apart, tmp_path / "c", "ingest.video_max_frames=40")[1]["images"]) == 130


def test_record3d_frames_are_read_as_its_video_in_their_numbers_order(tmp_path):
    # Record3D numbers its frames without padding (9.jpg, 10.jpg) and poses them by number, so a long capture is
    # read one in N, in the numbers' order; a pose file that lists its photos keeps every one.
    export = tmp_path / "record3d"
    (export / "rgb").mkdir(parents=True)
    for path in saved_frames(tmp_path / "frames", 130, step_px=1).iterdir():
        path.rename(export / "rgb" / f"{int(path.stem)}.png")
    poses = [[0.0, 0.0, 0.0, 1.0, 0.01 * i, 0.0, 0.0] for i in range(130)]
    (export / "metadata.json").write_text(json.dumps({"K": [80, 0, 0, 0, 80, 0, 40, 30, 1], "w": 80, "h": 60,
                                                      "poses": poses}))
    limits = ("ingest.video_max_frames=40", "ingest.video_frames=0", "ingest.video_min_frames=3")
    kept = [int(r["name"]) for r in run_ingest(export, tmp_path / "a", *limits)[1]["images"]]
    assert sorted(kept) == list(range(0, 130, 5))
    (export / "metadata.json").unlink()
    (export / "transforms.json").write_text(json.dumps({"fl_x": 80, "w": 80, "h": 60, "frames": [
        {"file_path": f"rgb/{i}.png", "transform_matrix": np.eye(4).tolist()} for i in range(130)]}))
    assert len(run_ingest(export, tmp_path / "b", *limits)[1]["images"]) == 130


def test_a_clip_too_short_for_a_good_fit_says_so(tmp_path):
    video = panning_video(tmp_path / "short.avi", 20, step_px=2)   # 2 s at 10 frames a second
    out, listing = run_ingest(video, tmp_path, "ingest.video_fps=3", "ingest.video_min_frames=30")
    assert len(listing["images"]) <= 7 and listing["video"]["seconds"] == pytest.approx(2.0)
    line = json.loads((out / "manifest.json").read_text())["summary"]["line"]
    assert "too short for a good fit" in line and "ingest.video_fps=3" in line and "film longer" in line
    enough = run_ingest(video, tmp_path / "b", "ingest.video_fps=100", "ingest.video_min_frames=5")[0]
    assert "too short" not in json.loads((enough / "manifest.json").read_text())["summary"]["line"]


@pytest.mark.parametrize("size, within", [((48, 80), (40, 0, 128, 80)),     # a portrait clip in a landscape frame
                                          ((96, 40), (0, 16, 96, 72))])     # a wide film letterboxed
def test_black_bars_around_a_clips_picture_are_cropped_before_it_is_read(tmp_path, size, within):
    padded = panning_video(tmp_path / "padded.avi", 40, step_px=2, size=size, within=within)
    plain = panning_video(tmp_path / "plain.avi", 40, step_px=2, size=size)
    out, listing = run_ingest(padded, tmp_path / "a", "ingest.video_fps=100", "ingest.video_min_frames=3")
    unpadded, reference = run_ingest(plain, tmp_path / "b", "ingest.video_fps=100", "ingest.video_min_frames=3")
    assert {(r["width"], r["height"]) for r in listing["images"]} == {size}
    assert listing["video"]["bars"] == {"frame": list(within[2:]), "kept": [within[0], within[1], *size]}
    # The same frames as the clip without bars: the picture's motion alone decides which are kept.
    assert [r["name"] for r in listing["images"]] == [r["name"] for r in reference["images"]]
    first = listing["images"][0]["name"]
    cropped, plain_frame = (read_rgb(folder / "images" / f"{first}.png").astype(float) for folder in (out, unpadded))
    assert np.abs(cropped - plain_frame).mean() < 4     # MJPG's blocks at the picture's edge differ a little
    line = json.loads((out / "manifest.json").read_text())["summary"]["line"]
    assert f"black bars cropped (the picture {size[0]}x{size[1]} of its {within[2]}x{within[3]} frame)" in line


def padded_photos(folder, count=5, pad=(20, 0)):
    """Photos a tool saved from a padded clip: 40x60 pictures within black columns (or rows) `pad` wide, and
    masks of the whole frame beside them."""
    (folder / "masks").mkdir(parents=True)
    for i in range(count):
        frame = np.pad(textured(h=60, w=40, seed=i), ((pad[1], pad[1]), (pad[0], pad[0]), (0, 0)))
        Image.fromarray(frame).save(folder / f"f{i}.png")
        mask = np.zeros(frame.shape[:2], np.uint8)
        mask[pad[1] + 10:pad[1] + 50, pad[0] + 5:pad[0] + 35] = 255
        Image.fromarray(mask).save(folder / "masks" / f"f{i}.png")
    return folder


def test_black_bars_of_photos_saved_from_a_padded_clip_are_cropped_with_their_masks(tmp_path):
    folder = padded_photos(tmp_path / "frames")
    Image.fromarray(textured(h=60, w=100, seed=9)).save(folder / "other.png")   # another size: left whole
    out, listing = run_ingest(folder, tmp_path)
    by_name = {r["name"]: r for r in listing["images"]}
    assert (by_name["f0"]["width"], by_name["f0"]["height"], by_name["f0"]["bars_cropped"]) == (40, 60, [20, 0, 40, 60])
    assert "bars_cropped" not in by_name["other"] and by_name["other"]["width"] == 100
    assert np.array_equal(read_rgb(out / "images" / "f3.png"), textured(h=60, w=40, seed=3))
    mask = read_rgb(out / "masks" / "f3.png")[..., 0]
    assert mask.shape == (60, 40) and mask[10:50, 5:35].all() and not mask[:10].any()
    line = json.loads((out / "manifest.json").read_text())["summary"]["line"]
    assert "black bars cropped from 5 (the picture 40x60 of their 80x60)" in line


@pytest.mark.parametrize("given", ["transforms", "colmap"])
def test_photos_a_pose_file_describes_keep_their_bars_or_take_its_camera_moved_within_them(tmp_path, given):
    """A pose file beside padded photos keeps their whole frames. Given elsewhere (poses.path), ingest crops the black
    bars as it does without one, and the file's camera of the whole frame moves with the crop: its principal point
    20 rows up; a COLMAP model's matches move with it, and its points reproject onto them as before."""
    import pycolmap
    from plenoxels.core.cameras import colmap_w2c_from_opengl_c2w, look_at

    folder = padded_photos(tmp_path / "capture" / "images", count=3, pad=(0, 20))
    c2w = [look_at([0.3 * i, -3.0, 0.2], [0.0, 0.0, 0.0]) for i in range(3)]
    frames = [{"file_path": f"images/f{i}.png", "transform_matrix": c2w[i].tolist()} for i in range(3)]
    pose_file = tmp_path / "capture" / "transforms.json"
    pose_file.write_text(json.dumps({"fl_x": 50, "fl_y": 50, "cx": 21, "cy": 52, "w": 40, "h": 100, "frames": frames}))
    _, listing = run_ingest(folder, tmp_path / "beside")
    assert {(r["width"], r["height"]) for r in listing["images"]} == {(40, 100)}
    pose_file.rename(tmp_path / "elsewhere.json")
    if given == "colmap":  # the same cameras as a model, its matches those of points before them
        model = pycolmap.Reconstruction()
        model.add_camera_with_trivial_rig(pycolmap.Camera(model="OPENCV", width=40, height=100, camera_id=1,
                                                          params=[50, 50, 21, 52, -0.05, 0, 0, 0]))
        points = np.random.default_rng(3).uniform(-0.3, 0.3, (10, 3))
        for i in range(3):
            rotation, translation = colmap_w2c_from_opengl_c2w(c2w[i])
            seen = model.cameras[1].img_from_cam(points @ rotation.T + translation)
            model.add_image_with_trivial_frame(pycolmap.Image(name=f"f{i}.png", camera_id=1, image_id=i + 1,
                                                              keypoints=seen),
                                               pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), translation))
        for n, xyz in enumerate(points):
            model.add_point3D(xyz, pycolmap.Track([pycolmap.TrackElement(i + 1, n) for i in range(3)]),
                              np.zeros(3, np.uint8))
        (tmp_path / "model").mkdir()
        model.write(tmp_path / "model")
    path = tmp_path / ("model" if given == "colmap" else "elsewhere.json")
    summary = Pipeline(folder, tmp_path / "given" / "out", overrides=[f"poses.path={path}"],
                       reporter=Reporter(quiet=True)).run(["poses"])["poses"]["summary"]
    poses = json.loads((tmp_path / "given" / "out" / "poses" / "transforms.json").read_text())
    assert len(poses["frames"]) == 3
    if given == "transforms":
        assert (poses["w"], poses["h"]) == (40, 60)
        assert [poses[key] for key in ("fl_x", "fl_y", "cx", "cy")] == pytest.approx([50, 50, 21, 32])
    else:  # undistorted: the lens's centre, where its principal point is, moved with the crop
        camera = poses["original_camera"]
        assert camera["params"][:4] == pytest.approx([50, 50, 21, 32]) and camera["params"][4] == pytest.approx(-0.05)
        assert summary["points"] == 10 and summary["mean_reprojection_error"] < 1e-6
    whole = Pipeline(folder, tmp_path / "whole" / "out", overrides=["ingest.crop_bars=false"],
                     reporter=Reporter(quiet=True))
    whole.run(["ingest"])
    assert {(r["width"], r["height"]) for r in json.loads((tmp_path / "whole" / "out" / "ingest" / "images.json")
                                                           .read_text())["images"]} == {(40, 100)}


def write_dng(path, rgb: np.ndarray, orientation: int = 1) -> None:
    """A camera's RAW file as a DNG: an RGGB mosaic of `rgb` (as sRGB) in linear 12-bit light, sRGB primaries, a white
    balance of one."""
    tifffile = pytest.importorskip("tifffile", reason="tifffile (with scikit-image) writes the test's DNG files")
    linear = (rgb / 255.0) ** 2.2 * 4095
    mosaic = np.empty(rgb.shape[:2], np.uint16)
    for (dy, dx), channel in zip([(0, 0), (0, 1), (1, 0), (1, 1)], [0, 1, 1, 2]):
        mosaic[dy::2, dx::2] = linear[dy::2, dx::2, channel]
    xyz_to_srgb = [3.2406, -1.5372, -0.4986, -0.9689, 1.8758, 0.0415, 0.0557, -0.2040, 1.0570]
    rationals = [v for x in xyz_to_srgb for v in (round(x * 10000), 10000)]
    tags = [(33421, "H", 2, (2, 2), False), (33422, "B", 4, (0, 1, 1, 2), False), (50706, "B", 4, (1, 4, 0, 0), False),
            (50708, "s", 0, "Synthetic", False), (50714, "H", 1, (0,), False), (50717, "H", 1, (4095,), False),
            (50721, "2i", 9, rationals, False), (50778, "H", 1, (21,), False), (50728, "2I", 3, (1,) * 6, False),
            (274, "H", 1, (orientation,), False)]
    tifffile.imwrite(path, mosaic, photometric=32803, extratags=tags, metadata=None, subfiletype=0)


def smooth(h=60, w=80, seed=0):
    """A photo of soft shapes, which a mosaic keeps: demosaicing rebuilds it closely."""
    return cv2.GaussianBlur(textured(h, w, seed), (0, 0), 2)


def test_raw_photos_are_developed_upright_and_a_raw_beside_its_jpeg_is_left_for_the_jpeg(tmp_path):
    pytest.importorskip("rawpy", reason="rawpy (a base dependency: make install) develops RAW photos")
    folder = tmp_path / "camera"
    folder.mkdir()
    for i in range(3):
        write_dng(folder / f"IMG_{i}.dng", smooth(seed=i))
        Image.fromarray(smooth(seed=i)).save(folder / f"IMG_{i}.JPG", quality=95)   # the camera's own JPEG
    write_dng(folder / "IMG_3.dng", smooth(seed=3))                                # RAW only
    write_dng(folder / "IMG_4.dng", smooth(seed=4), orientation=6)                 # held upright
    out, listing = run_ingest(folder, tmp_path)
    sources = sorted(r["source"] for r in listing["images"])
    assert sources == ["IMG_0.JPG", "IMG_1.JPG", "IMG_2.JPG", "IMG_3.dng", "IMG_4.dng"]
    developed = read_rgb(out / "images" / "IMG_3.png").astype(float)
    assert developed.shape == (60, 80, 3) and np.abs(developed - smooth(seed=3))[4:-4, 4:-4].mean() < 10
    turned = read_rgb(out / "images" / "IMG_4.png").astype(float)
    assert turned.shape == (80, 60, 3)
    assert np.abs(turned - np.rot90(smooth(seed=4), -1))[4:-4, 4:-4].mean() < 10
    line = json.loads((out / "manifest.json").read_text())["summary"]["line"]
    assert "3 RAW files left for the developed photos of their names" in line and "skipped" not in line



def test_a_mask_beside_its_photo_is_its_mask_and_no_photo(tmp_path):
    """`<stem>_mask.png` or `<stem>-mask.png` beside `<stem>.jpg` is the photo's mask, read as one; a name that only
    ends so, with no photo of the rest of its name beside it, is a photo."""
    folder = tmp_path / "object"
    folder.mkdir()
    for i in range(3):
        Image.fromarray(smooth(seed=i)).save(folder / f"shot{i}.jpg", quality=95)
    object_mask = np.zeros((60, 80), np.uint8)
    object_mask[20:40, 30:50] = 255
    Image.fromarray(object_mask).save(folder / "shot0_mask.png")
    Image.fromarray(object_mask).save(folder / "shot1-mask.png")
    Image.fromarray(smooth(seed=5)).save(folder / "halloween_mask.jpg", quality=95)  # a photo of a mask
    out, listing = run_ingest(folder, tmp_path)
    assert sorted(r["source"] for r in listing["images"]) == ["halloween_mask.jpg", "shot0.jpg", "shot1.jpg",
                                                              "shot2.jpg"]
    line = json.loads((out / "manifest.json").read_text())["summary"]["line"]
    assert "2 with masks (2 from mask files)" in line and "2 masks kept beside the photos of their names" in line
    masks = {r["source"]: r["mask"] for r in listing["images"]}
    assert masks["shot2.jpg"] is None and masks["halloween_mask.jpg"] is None
    np.testing.assert_array_equal(np.asarray(Image.open(out / masks["shot0.jpg"]).convert("L")), object_mask)

def watermark(frame):
    """A caption and a solid badge, as an app burns them into every frame."""
    cv2.rectangle(frame, (120, 8), (150, 24), (255, 0, 0), -1)
    cv2.putText(frame, "@me", (6, 110), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA)


def test_a_still_overlay_on_a_clip_is_painted_over_in_every_frame(tmp_path):
    video = panning_video(tmp_path / "marked.avi", 48, step_px=2, size=(160, 120), mark=watermark)
    out, listing = run_ingest(video, tmp_path / "a", "ingest.video_fps=100", "ingest.video_min_frames=3")
    assert 0.02 < listing["video"]["overlay"] < 0.1
    for record in listing["images"]:
        frame = read_rgb(out / "images" / f"{record['name']}.png").astype(int)
        badge, caption = frame[10:23, 122:149], frame[96:112, 6:44]
        assert ((badge[..., 0] > 230) & (badge[..., 1:] < 30).all(axis=-1)).mean() < 0.05, record   # its red gone
        assert (caption > 240).all(axis=-1).mean() < 0.05, record                                   # its white gone
    line = json.loads((out / "manifest.json").read_text())["summary"]["line"]
    assert "a still overlay painted over" in line
    _, kept = run_ingest(video, tmp_path / "b", "ingest.video_fps=100", "ingest.video_min_frames=3",
                         "ingest.paint_overlays=false")
    assert "overlay" not in kept["video"]
    plain = panning_video(tmp_path / "plain.avi", 48, step_px=2, size=(160, 120))
    assert "overlay" not in run_ingest(plain, tmp_path / "c", "ingest.video_fps=100", "ingest.video_min_frames=3")[1][
        "video"]


def test_a_still_overlay_is_told_from_a_flat_wall_and_from_a_camera_that_did_not_move():
    rng = np.random.default_rng(4)
    wall = cv2.resize(rng.integers(0, 256, (30, 120), dtype=np.uint8), (480, 120), interpolation=cv2.INTER_CUBIC)
    moving = [np.ascontiguousarray(wall[:, 10 * i:10 * i + 160]) for i in range(24)]
    for frame in moving:
        frame[:40] = 230                        # a white wall filling the top third of every view
    assert still_overlay(moving) is None
    marked = [f.copy() for f in moving]
    for frame in marked:
        cv2.putText(frame, "12:04", (4, 110), cv2.FONT_HERSHEY_SIMPLEX, 0.5, 255, 1, cv2.LINE_AA)  # thin strokes
    found = still_overlay(marked)
    assert found is not None and found[100:111, 6:44].mean() > 0.5 and found[:90].sum() == 0
    assert still_overlay([marked[0]] * 24) is None             # a view that never moved: nothing tells it apart


def test_a_dark_picture_and_a_thin_border_are_not_taken_for_bars():
    rng = np.random.default_rng(3)
    night = [rng.integers(0, 30, (60, 80)).astype(np.uint8) for _ in range(6)]   # dark, but with texture
    assert picture_box(night) is None
    framed = [np.pad(rng.integers(60, 200, (198, 80)).astype(np.uint8), ((1, 1), (0, 0))) for _ in range(3)]
    assert picture_box(framed) is None                  # one black row each side of 200: below BAR_MIN_SHARE
    black = [np.zeros((60, 80), np.uint8)] * 3
    assert picture_box(black) is None                    # no picture left: a clip dark throughout keeps its frames
    lit_once = [np.pad(rng.integers(60, 200, (60, 40)).astype(np.uint8), ((0, 0), (20, 20))) for _ in range(3)]
    lit_once[1][:, :20] = 90                            # the left "bar" shows something in one frame
    assert picture_box(lit_once) == (slice(0, 60), slice(0, 60))


def test_rotated_video_comes_out_upright(tmp_path):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg", reason="imageio-ffmpeg (a base dependency) writes the rotation tag")
    landscape = panning_video(tmp_path / "landscape.avi", 30, step_px=2)
    frames = tmp_path / "plain.mp4"
    reader = cv2.VideoCapture(str(landscape))
    writer = cv2.VideoWriter(str(frames), cv2.VideoWriter_fourcc(*"mp4v"), 10, (80, 60))
    first = None
    while True:
        ok, bgr = reader.read()
        if not ok:
            break
        first = bgr if first is None else first
        writer.write(bgr)
    writer.release()
    # A phone held upright records landscape pixels and a display rotation of 90 degrees (counter-clockwise).
    rotated = tmp_path / "portrait.mp4"
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-display_rotation", "90", "-i",
                    str(frames), "-c", "copy", str(rotated)], check=True)
    out, listing = run_ingest(rotated, tmp_path, "ingest.video_fps=100")
    image = read_rgb(out / "images" / f"{listing['images'][0]['name']}.png")
    assert image.shape[:2] == (80, 60)
    upright = np.rot90(cv2.cvtColor(first, cv2.COLOR_BGR2RGB), 1)
    assert np.abs(image.astype(float) - upright).mean() < 12
