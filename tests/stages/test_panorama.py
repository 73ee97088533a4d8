"""360 captures: equirectangular frames are told apart from ordinary 2:1 pictures, cut into pinhole views that are the
views a pinhole at the same place sees, ingested as such from a video or a folder of photos, posed as one known
camera, and held out a whole frame at a time."""
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from pipeline.report import Reporter
from pipeline.runner import Pipeline
from plenoxels.core.cameras import Intrinsics, look_at
from plenoxels.core.errors import UserError
from stages.capture.panorama import (POLES, looks_equirect, photos_equirect, says_equirect, split_frame, view_focal,
                                     view_rotation, view_side)
from stages.capture.synthetic import write_panorama_video
from stages.capture.synthetic_scenes import (OBJECT_CENTRE, build_scene, render_equirect, render_float, to_uint8,
                                             walk_poses)
from stages.framing.options import SceneOptions
from stages.framing.scene_frame import held_out_frames
from stages.framing.sightings import Cameras
from stages.sfm.compare import compare_poses

ROOM = build_scene("room", 0)


@pytest.fixture(scope="module")
def equirect() -> tuple[np.ndarray, np.ndarray]:
    """One 360 frame of the room kind, 512 x 256, and its camera."""
    c2w = walk_poses(8)[1]
    return to_uint8(render_equirect(ROOM, c2w, 512, supersample=1)), c2w


def grey(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def turned_to(c2w: np.ndarray, view_name: str, mirror: bool = False) -> np.ndarray:
    """A frame's camera-to-world turned to its view of `view_name` (the frame's name, then the view's yaw or pole), or
    turned the other way (`mirror`)."""
    tail = view_name.rsplit("_", 1)[1]
    pole = {name: pitch for pitch, name in POLES.items()}
    yaw, pitch = (0.0, pole[tail]) if tail in pole else (float(tail), 0.0)
    turned = c2w.copy()
    turned[:3, :3] = c2w[:3, :3] @ (view_rotation(-yaw, -pitch) if mirror else view_rotation(yaw, pitch))
    return turned


def test_each_view_is_what_a_pinhole_at_its_yaw_and_pitch_sees(equirect):
    frame, c2w = equirect
    side = 64
    k = Intrinsics(view_focal(side), view_focal(side), side / 2, side / 2, side, side)
    views = split_frame(frame, side, poles="both")
    assert [(turn["yaw"], turn["pitch"]) for turn, _ in views] == [
        (0, 0), (45, 0), (90, 0), (135, 0), (180, 0), (225, 0), (270, 0), (315, 0), (0, -90), (0, 90)]
    for turn, view in views:
        name = f"frame_{POLES[turn['pitch']] if turn['pitch'] else round(turn['yaw'])}"
        error = np.median(np.abs(view / 255 - render_float(ROOM, turned_to(c2w, name), k, 1)[0]))
        assert error < 0.03, (name, error)
        if turn["pitch"] or turn["yaw"] not in (0, 180):  # turned the other way, it shows another wall, or pole
            assert np.median(np.abs(view / 255 - render_float(ROOM, turned_to(c2w, name, True), k, 1)[0])) > 3 * error
    assert [len(split_frame(frame, side, poles)) for poles in ("up", "none")] == [9, 8]


def test_equirect_frames_are_told_from_ordinary_two_to_one_pictures(equirect):
    frame, c2w = equirect
    assert looks_equirect([grey(frame)])
    # The same room through a wide pinhole, 2:1: its left and right edges are different walls, its top no pole.
    wide = Intrinsics(180.0, 180.0, 128.0, 64.0, 256, 128)
    assert not looks_equirect([grey(to_uint8(render_float(ROOM, c2w, wide, 1)[0]))])
    # A thing on a plain backdrop, 2:1: its edges meet and its top row is flat, but the edges hold nothing.
    backdrop = np.full((128, 256), 235, np.uint8)
    backdrop[20:118, 30:226] = grey(frame)[80:178, 150:346]
    assert not looks_equirect([backdrop])
    # Cut off a strip, it is no longer 2:1; turned upside down (poles swapped) it still is one.
    assert not looks_equirect([grey(frame[:, 20:])])
    assert looks_equirect([grey(frame[::-1])])


def run_ingest(scene: Path, out: Path, *overrides: str) -> dict:
    Pipeline(scene, out, overrides=list(overrides), reporter=Reporter(quiet=True)).run(["ingest"])
    return json.loads((out / "ingest" / "images.json").read_text())


def test_a_360_video_is_ingested_as_views_around_the_horizon_and_at_the_poles(tmp_path):
    clip = tmp_path / "walk.mp4"
    write_panorama_video(clip, n_frames=12, width=384, fps=4)
    listing = run_ingest(clip, tmp_path / "out", "ingest.video_frames=0")
    views = listing["images"]
    frames = sorted({r["panorama"]["frame"] for r in views})
    assert len(views) == 9 * len(frames) and len(frames) >= 6  # eight around the horizon, one up
    side = view_side(384, 960)
    assert {(r["width"], r["height"]) for r in views} == {(side, side)}
    assert all(r["focal"] == pytest.approx(side / 2) for r in views)
    first = [r for r in views if r["panorama"]["frame"] == frames[0]]
    assert [r["name"] for r in first] == [f"{frames[0]}_{yaw:03d}" for yaw in range(0, 360, 45)] + [f"{frames[0]}_up"]
    for poles, views in (("both", 10), ("none", 8)):
        listed = run_ingest(clip, tmp_path / poles, "ingest.video_frames=0", f"ingest.equirect_poles={poles}")
        assert len(listed["images"]) == views * len(frames)
    # Told not to, ingest keeps the frames whole, as any video's.
    whole = run_ingest(clip, tmp_path / "whole", "ingest.video_frames=0", "ingest.equirect=no")["images"]
    assert whole and all("panorama" not in r and r["width"] == 2 * r["height"] for r in whole)


def test_an_ordinary_video_is_not_cut_and_yes_on_one_not_two_to_one_stops_with_one_line(tmp_path):
    clip = tmp_path / "pan.mp4"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"mp4v"), 4, (160, 120))
    c2w = look_at(OBJECT_CENTRE + np.array([3.0, 0.0, 1.0]), OBJECT_CENTRE)
    k = Intrinsics(140.0, 140.0, 80.0, 60.0, 160, 120)
    for n in range(12):
        turned = c2w.copy()
        turned[:3, 3] += np.array([0.0, 0.08 * n, 0.0])
        writer.write(to_uint8(render_float(ROOM, turned, k, 1)[0])[..., ::-1])
    writer.release()
    assert all("panorama" not in r for r in run_ingest(clip, tmp_path / "out", "ingest.video_frames=0")["images"])
    with pytest.raises(UserError, match="not the 2:1") as stopped:
        run_ingest(clip, tmp_path / "yes", "ingest.equirect=yes")
    assert "\n" not in str(stopped.value)


def test_360_photos_are_cut_where_their_metadata_or_their_pixels_say_so(tmp_path, equirect):
    frame, _ = equirect
    folder = tmp_path / "photos"
    folder.mkdir()
    Image.fromarray(frame).save(folder / "pano0.png")
    for n, c2w in enumerate(walk_poses(8)[2:4], start=1):
        Image.fromarray(to_uint8(render_equirect(ROOM, c2w, 512, supersample=1))).save(folder / f"pano{n}.png")
    listing = run_ingest(folder, tmp_path / "out")
    assert len(listing["images"]) == 27 and {r["panorama"]["frame"] for r in listing["images"]} == {
        "pano0", "pano1", "pano2"}
    # A 360 camera's JPEG says so in its XMP: read as one even where its pixels would not tell (a flat one).
    marked = tmp_path / "marked"
    marked.mkdir()
    xmp = (b'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
           b'<rdf:Description xmlns:GPano="http://ns.google.com/photos/1.0/panorama/" '
           b'GPano:ProjectionType="equirectangular"/></rdf:RDF></x:xmpmeta>')
    flat = np.full((128, 256, 3), 120, np.uint8)
    Image.fromarray(flat).save(marked / "theta.jpg", xmp=xmp)
    assert photos_equirect([marked / "theta.jpg"])
    Image.fromarray(flat).save(marked / "plain.jpg")
    assert not photos_equirect([marked / "plain.jpg"])


def test_a_360_frames_views_are_held_out_together():
    names = [f"f{frame:02d}_{yaw:03d}" for frame in range(16) for yaw in range(0, 360, 45)]
    frames = [{"panorama_frame": name[:3]} for name in names]
    cams = Cameras(names, frames, np.repeat(np.eye(4)[None], len(names), 0), [], None)
    held = held_out_frames(cams, SceneOptions(holdout_every=8))
    assert {names[i][:3] for i in held} == {"f00", "f08"} and len(held) == 16


def test_a_360_video_is_posed_as_views_of_one_known_camera_that_share_each_frames_centre(tmp_path):
    clip = tmp_path / "walk.mp4"
    truth = write_panorama_video(clip, n_frames=16, width=640, fps=4)
    manifest = Pipeline(clip, tmp_path / "out", overrides=["ingest.video_frames=0", "ingest.equirect_poles=both"],
                        reporter=Reporter(quiet=True)).run(["ingest", "poses"])
    views = manifest["ingest"]["summary"]["images"]
    assert manifest["poses"]["summary"]["registered"] == views
    transforms = json.loads((tmp_path / "out" / "poses" / "transforms.json").read_text())
    side = view_side(640, 960)
    assert transforms["fl_x"] == pytest.approx(view_focal(side), rel=1e-6)  # kept by bundle adjustment
    frames = transforms["frames"]
    got = np.array([f["transform_matrix"] for f in frames])
    want = [turned_to(truth[int(f["panorama_frame"].split("_")[1])], f["name"]) for f in frames]
    assert sum(f["name"].endswith(("_up", "_down")) for f in frames) == 2 * len({f["panorama_frame"] for f in frames})
    errors = compare_poses(got, np.array(want))
    # Measured: the worst view 0.42 degrees and 1.3% of the path's spread off, the median 0.09 and 0.3%.
    assert errors["rotation_error_deg_max"] < 1.0 and errors["centre_error_share_max"] < 0.04, errors
    assert errors["centre_error_share_median"] < 0.01, errors


@pytest.mark.parametrize("pose_file", ["transforms", "metashape", "opensfm", "openmvg"])
def test_360_frames_posed_in_a_pose_file_give_each_view_its_frames_pose_turned_to_its_yaw(tmp_path, pose_file):
    # nerfstudio's camera_model EQUIRECTANGULAR, or Metashape's exported cameras of a spherical sensor (its camera
    # axes OpenCV's, its frames' longitude atan2(X, Z) across): one pose per frame.
    capture = tmp_path / "capture"
    (capture / "images").mkdir(parents=True)
    truth = walk_poses(8)[::2]
    frames = []
    for n, c2w in enumerate(truth):
        Image.fromarray(to_uint8(render_equirect(ROOM, c2w, 384, supersample=2))).save(capture / "images" / f"{n}.png")
        frames.append({"file_path": f"images/{n}.png", "transform_matrix": c2w.tolist()})
    if pose_file == "transforms":
        (capture / "transforms.json").write_text(json.dumps({"camera_model": "EQUIRECTANGULAR", "w": 384, "h": 192,
                                                             "fl_x": 192.0, "fl_y": 192.0, "frames": frames}))
    elif pose_file == "opensfm":  # OpenSfM's spherical camera: world-to-camera as an axis times its angle
        shots = {}
        for n, c2w in enumerate(truth):
            w2c = np.linalg.inv(c2w @ np.diag([1.0, -1, -1, 1]))
            shots[f"{n}.png"] = {"rotation": cv2.Rodrigues(w2c[:3, :3])[0].ravel().tolist(),
                                 "translation": w2c[:3, 3].tolist(), "camera": "theta"}
        (capture / "opensfm").mkdir()
        (capture / "opensfm" / "reconstruction.json").write_text(json.dumps([{"shots": shots, "cameras": {
            "theta": {"projection_type": "spherical", "width": 384, "height": 192}}}]))
    elif pose_file == "openmvg":  # OpenMVG's spherical camera: world-to-camera rotation and centre, cereal's JSON
        views = [{"key": n, "value": {"polymorphic_id": 1073741824, "ptr_wrapper": {"id": 0x80000001 + n, "data": {
            "filename": f"{n}.png", "id_view": n, "id_intrinsic": 0, "id_pose": n}}}} for n in range(len(truth))]
        poses = [{"key": n, "value": {"rotation": (c2w[:3, :3] @ np.diag([1.0, -1, -1])).T.tolist(),
                                      "center": c2w[:3, 3].tolist()}} for n, c2w in enumerate(truth)]
        intrinsics = [{"key": 0, "value": {"polymorphic_id": 0x80000001, "polymorphic_name": "spherical",
                                           "ptr_wrapper": {"id": 0x80000100, "data": {"width": 384, "height": 192}}}}]
        (capture / "sfm_data.json").write_text(json.dumps({"sfm_data_version": "0.3", "views": views,
                                                           "intrinsics": intrinsics, "extrinsics": poses}))
    else:
        cameras = "".join(f'<camera id="{n}" sensor_id="0" label="{n}"><transform>'
                          f'{" ".join(map(repr, (c2w @ np.diag([1.0, -1, -1, 1])).ravel().tolist()))}</transform>'
                          "</camera>" for n, c2w in enumerate(truth))
        (capture / "cameras.xml").write_text(
            '<?xml version="1.0"?><document version="2.0.0"><chunk><sensors><sensor id="0" type="spherical">'
            '<resolution width="384" height="192"/></sensor></sensors>'
            f"<cameras>{cameras}</cameras></chunk></document>")
    manifest = Pipeline(capture, tmp_path / "out", reporter=Reporter(quiet=True)).run(["ingest", "poses"])
    assert manifest["poses"]["summary"]["source"] == pose_file
    transforms = json.loads((tmp_path / "out" / "poses" / "transforms.json").read_text())
    assert len(transforms["frames"]) == 9 * len(truth)  # eight around the horizon, one up
    side = transforms["w"]
    k = Intrinsics(transforms["fl_x"], transforms["fl_y"], transforms["cx"], transforms["cy"], side, transforms["h"])
    assert k.fl_x == pytest.approx(view_focal(side))
    for f in transforms["frames"]:
        frame, yaw = f["name"].rsplit("_", 1)
        turned, mirrored = turned_to(truth[int(frame)], f["name"]), turned_to(truth[int(frame)], f["name"], True)
        assert np.allclose(f["transform_matrix"], turned, atol=1e-6), f["name"]
        # the view's pixels are what a pinhole at that pose sees, and not what one turned the other way sees
        view = np.asarray(Image.open(tmp_path / "out" / "poses" / f["file_path"]).convert("RGB")) / 255
        error = np.median(np.abs(view - render_float(ROOM, turned, k, 2)[0]))
        assert error < 0.03, (f["name"], error)
        if yaw not in ("000", "180"):
            assert np.median(np.abs(view - render_float(ROOM, mirrored, k, 2)[0])) > 3 * error, f["name"]


def test_a_360_clip_sfm_refuses_is_read_again_as_views_of_closer_frames(tmp_path, monkeypatch):
    import stages.poses

    clip = tmp_path / "walk.mp4"
    write_panorama_video(clip, n_frames=12, width=512, fps=4)
    calls = []

    def refuse(records, *args):
        calls.append(records)
        raise UserError(f"SfM posed only 3/{len(records)} images")

    monkeypatch.setattr(stages.poses, "reconstruct", refuse)
    with pytest.raises(UserError, match="read again at full size"):
        Pipeline(clip, tmp_path / "out", overrides=["ingest.max_side=96", "ingest.video_frames=0"],
                 reporter=Reporter(quiet=True)).run(["ingest", "poses"])
    first, again = calls
    assert {(r["width"], r["focal"]) for r in first} == {(96, view_focal(96))}
    side = view_side(512, 0)
    assert {(r["width"], r["height"], r["focal"]) for r in again} == {(side, side, view_focal(side))}
    frames = {r["panorama"]["frame"] for r in again}
    assert len(again) == 8 * len(frames) and len(frames) > len({r["panorama"]["frame"] for r in first})
    assert not any(r["panorama"]["pitch"] for r in first + again)  # SfM is given the views around the horizon


def test_a_videos_spherical_metadata_says_equirect_only_with_its_projection(tmp_path):
    # Spherical Video V2: an sv3d box holding an equi projection box; the four bytes sv3d alone turn up by chance.
    marked, chance = tmp_path / "marked.mp4", tmp_path / "chance.mp4"
    marked.write_bytes(b"\0" * 64 + b"sv3d" + b"\0" * 40 + b"svhd" + b"\0" * 20 + b"proj" + b"\0" * 8 + b"equi")
    chance.write_bytes(b"\0" * 64 + b"sv3d" + b"\1" * 4096)
    assert says_equirect(marked) and not says_equirect(chance)


def test_the_holder_a_360_clip_carries_in_every_frame_is_painted_over(tmp_path):
    # A hand or a person below and behind the camera stays at the same pixels of every equirectangular frame while the
    # room turns past: trained, it is a thing fixed to every camera; posed, matches that stand still.
    plain, held = tmp_path / "plain.mp4", tmp_path / "held.mp4"
    write_panorama_video(plain, n_frames=12, width=384, fps=4)
    capture = cv2.VideoCapture(str(plain))
    writer = cv2.VideoWriter(str(held), cv2.VideoWriter_fourcc(*"mp4v"), 4, (384, 192))
    holder = cv2.resize(np.random.default_rng(3).integers(0, 256, (6, 10, 3), dtype=np.uint8), (64, 40),
                        interpolation=cv2.INTER_NEAREST)
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frame[128:168, 160:224] = holder  # 30-68 degrees below the horizon, in front: the hand holding it out
        writer.write(frame)
    writer.release()
    Pipeline(held, tmp_path / "out", overrides=["ingest.video_frames=0"], reporter=Reporter(quiet=True)).run(["ingest"])
    manifest = json.loads((tmp_path / "out" / "ingest" / "manifest.json").read_text())
    assert "its holder" in manifest["summary"]["line"]
    listing = json.loads((tmp_path / "out" / "ingest" / "images.json").read_text())
    ahead = [r for r in listing["images"] if r["panorama"]["yaw"] == 0 and r["panorama"]["pitch"] == 0]
    view = cv2.imread(str(tmp_path / "out" / "ingest" / ahead[0]["file"]))
    stamp = split_frame(np.pad(holder[..., ::-1], ((128, 24), (160, 160), (0, 0))), view.shape[0])[0][1]
    shown = stamp.any(axis=-1)  # where the holder would be in the view ahead
    assert shown.sum() > 20
    # Painted from around it, the view there no longer holds the holder's pixels.
    assert np.abs(view[..., ::-1][shown].astype(int) - stamp[shown].astype(int)).mean() > 30
