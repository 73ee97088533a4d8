"""Object captures: a turntable in front of a still room posed from inside its masks (and refused without them),
fitted and exported as the object alone; the object box from the photos' silhouettes, which keeps a thin part the
sparse points miss and stops where masks and poses disagree; a backdrop that is not one colour behind every photo
gets a model of what surrounds the object."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from stages.common.json_files import read_json, write_json
from stages.scoring.metrics import mesh_scores
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from stages.framing.options import SceneOptions
from stages.framing.scene_frame import normalize_scene
from stages.framing.sightings import read_points
from stages.sfm.compare import compare_poses, umeyama
from stages.capture.synthetic import write_scene
from stages.capture.synthetic_scenes import OBJECT_CENTRE
from stages.framing.visual_hull import Silhouettes, carve, cut_photos, shown_box
from stages.normalize import summary_line
from plenoxels.core.cameras import Intrinsics, look_at, rays_from_camera
from plenoxels.core.errors import UserError
from plenoxels.core.scene_model import SceneModel

TURNTABLE_VIEWS, WIDTH, HEIGHT = 24, 480, 360
# A short fit, as the export end-to-end test's, on the photos at a quarter of their size. Its rates are svox2's (the
# density's falling 600x, not the presets' 10x), decayed once over the whole fit: restarted on a second level of 150
# steps they fall from 30 to 0.05 within it, and its mesh reached 5.4% of the object's size below it.
SHORT_FIT = ["fit.resolutions=[24,48]", "fit.steps=[150,150]", "fit.batch_size=2048", "fit.image_scale=0.25",
             "fit.eval_every=0", "fit.lr_density=30", "fit.lr_density_final=0.05", "fit.lr_density_delay=0.2",
             "fit.lr_sh=0.01", "fit.lr_sh_final=0.000005", "fit.sh_degree=1", "fit.prune_ray_scale=1.0",
             "evaluate.video_frames=0", "evaluate.scale=0.25", "export.points=2000", "export.splat_seconds=0",
             "export.texture_size=256", "fit.lr_per_level=false"]


def run(scene: Path, out: Path, stages: list[str], *overrides: str) -> dict:
    return Pipeline(scene, out, overrides=list(overrides), reporter=Reporter(quiet=True)).run(stages)


def frames_by_name(transforms: dict) -> dict[str, np.ndarray]:
    return {Path(f["file_path"]).stem: np.asarray(f["transform_matrix"]) for f in transforms["frames"]}


@pytest.fixture(scope="module")
def turntable(tmp_path_factory) -> Path:
    return write_scene("turntable", tmp_path_factory.mktemp("turntable") / "scan", n_views=TURNTABLE_VIEWS,
                       width=WIDTH, height=HEIGHT, seed=0, masks=True, supersample=1)


@pytest.fixture(scope="module")
def turntable_fitted(turntable, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("turntable_out")
    run(turntable, out, ["evaluate", "export"], "poses.source=sfm", *SHORT_FIT)
    return out


def test_turntable_with_masks_poses_every_photo_within_half_a_degree(turntable, turntable_fitted):
    summary = read_json(turntable_fitted / "poses" / "manifest.json")["summary"]
    assert summary["registered"] == TURNTABLE_VIEWS and summary["masked_images"] == TURNTABLE_VIEWS
    assert f"features only inside the masks of {TURNTABLE_VIEWS} images" in summary["line"]
    assert not summary["still_matches"]["still_background"] and summary["still_matches"]["share"] < 0.05
    got = frames_by_name(read_json(turntable_fitted / "poses" / "transforms.json"))
    want = frames_by_name(read_json(turntable / "transforms.json"))
    names = sorted(want)
    errors = compare_poses(np.array([got[n] for n in names]), np.array([want[n] for n in names]))
    assert errors["rotation_error_deg_max"] < 0.5 and errors["centre_error_share_max"] < 0.01, errors


def test_turntable_without_masks_is_refused_for_its_still_background(turntable, tmp_path):
    with pytest.raises(UserError, match=r"still background behind a turning object: \d+% of .* give a mask of the "
                                        r"object for each photo \(a masks/ folder"):
        run(turntable, tmp_path / "out", ["poses"], "poses.source=sfm", "ingest.masks=false")
    assert not (tmp_path / "out" / "poses").exists()


def test_turntable_with_imported_poses_and_no_masks_is_refused_before_any_fit(turntable, tmp_path):
    # Poses that come with the photos (here the true ones, beside them) skip SfM's check; the photos still show the room
    # standing still behind the object in every one of them.
    with pytest.raises(UserError, match=r"\d+% of the photos' pixels show the same texture at the same place in every "
                                        r"sampled photo: a still background behind a turning object"):
        run(turntable, tmp_path / "out", ["normalize"], "ingest.masks=false")
    assert read_json(tmp_path / "out" / "poses" / "transforms.json")["source"] == "transforms"
    assert not (tmp_path / "out" / "normalize").exists()


def test_turntable_with_masks_fits_and_exports_the_object_alone(turntable, turntable_fitted):
    scene = read_json(turntable_fitted / "normalize" / "scene.json")
    assert scene["type"] == "object" and scene["measured"]["masked"]
    assert scene["measured"]["visual_hull"]["source"] == "masks"
    assert read_json(turntable_fitted / "fit" / "model.json")["background"] is None
    metrics = read_json(turntable_fitted / "evaluate" / "metrics.json")
    # Scored inside the masks (an empty render scores about 3 dB there) and below the whole image, whose backdrop any
    # empty render matches.
    assert all("psnr_masked" in view for view in metrics["views"])
    assert 15 < metrics["mean"]["psnr_masked"] < metrics["mean"]["psnr"] - 3

    # The mesh, brought into the truth's frame through the cameras, lies on the turning object: neither the still
    # room (floor 0.7 below the object, walls 7 away) nor the turntable's plate, which the masks leave out.
    truth = trimesh.load(turntable / "ground_truth" / "mesh.ply", force="mesh", process=False)
    got = frames_by_name(read_json(turntable_fitted / "poses" / "transforms.json"))
    want = frames_by_name(read_json(turntable / "transforms.json"))
    names = sorted(want)
    scale, rotation, translation = umeyama(np.array([got[n][:3, 3] for n in names]),
                                           np.array([want[n][:3, 3] for n in names]))
    mesh = trimesh.load(turntable_fitted / "export" / "mesh.ply", force="mesh", process=False)
    vertices = scale * np.asarray(mesh.vertices) @ rotation.T + translation
    size = float(np.max(truth.bounds[1] - truth.bounds[0]))
    assert len(vertices) > 500
    # Nothing of the plate or the floor. Under the objects lies space no view sees, which no mask carves: this short
    # fit's cells are about 2.5% of the objects' size, and a cell or two of it may stay.
    assert vertices[:, 2].min() > truth.bounds[0][2] - 0.075 * size
    assert np.abs(vertices - truth.bounds.mean(0)).max() < 0.75 * size       # nothing of the room
    aligned = trimesh.Trimesh(vertices, mesh.faces, process=False)
    scores = mesh_scores(aligned, truth, 0.05 * size, samples=10_000)
    assert scores["precision"] > 0.9 and scores["max_vertex_distance"] < 0.15 * size, scores
    # Every one of the four objects, though they stand apart: the masks drew each of them as the object.
    assert scores["recall"] > 0.9, scores
    assert read_json(turntable_fitted / "export" / "export.json")["pieces_apart_kept"]


@pytest.fixture(scope="module")
def mast_scene(tmp_path_factory) -> tuple[Path, Path]:
    """The synthetic object with a thin mast, in RGBA, posed by its true cameras, through normalize."""
    root = tmp_path_factory.mktemp("mast")
    scene = write_scene("object", root / "synth", n_views=24, width=320, height=240, seed=1, alpha=True, mast=True)
    run(scene, root / "out", ["normalize"])
    return scene, root / "out"


def mast_top(scene: Path) -> np.ndarray:
    shapes = read_json(scene / "ground_truth" / "scene.json")["scene"]["shapes"]
    mast = min((s for s in shapes if s["type"] == "box"), key=lambda s: s["half_extents"][0])
    return np.asarray(mast["centre"]) + [0.0, 0.0, mast["half_extents"][2]]


def inside_box(point_input: np.ndarray, scene_json: dict) -> bool:
    world = np.asarray(scene_json["world_from_input"]) @ np.append(point_input, 1.0)
    return bool(np.all(world[:3] >= scene_json["foreground"]["min"]) and np.all(world[:3] <= scene_json["foreground"]["max"]))


def test_the_box_from_the_silhouettes_holds_a_thin_part_the_points_cut(mast_scene):
    scene, out = mast_scene
    top = mast_top(scene)
    assert top[2] > OBJECT_CENTRE[2] + 1.0                        # well above the still life's bulk
    framed = read_json(out / "normalize" / "scene.json")
    assert framed["measured"]["visual_hull"]["source"] == "masks" and framed["type"] == "object"
    assert "visual hull of 21 training photos' masks" in framed["measured"]["foreground_from"]
    assert inside_box(top, framed) and inside_box(top - [0.0, 0.0, 1.6], framed)
    # The box tight around the object: its height is the object's, not the whole region the cameras see.
    bounds = read_json(scene / "ground_truth" / "scene.json")["object_bounds"]
    height = (np.asarray(framed["foreground"]["max"]) - framed["foreground"]["min"])[2] / framed["scale"]
    assert height < 1.15 * (bounds["max"][2] - bounds["min"][2])
    # The same cameras and points without the photos: the box of the points' bulk, which cuts the mast.
    from_points = normalize_scene(read_json(out / "poses" / "transforms.json"), read_points(out / "poses" / "points.npz"),
                                  SceneOptions(), poses_dir=None)
    assert not inside_box(top, from_points)


def plate_silhouettes(half_extents: np.ndarray, elevations_deg: np.ndarray) -> Silhouettes:
    """A box centred at the origin seen from a ring of cameras 4 units away, all above it: the pixels whose rays hit it."""
    k = Intrinsics(110.0, 110.0, 64.0, 48.0, 128, 96)
    poses, shown = [], []
    for i, elevation in enumerate(np.radians(elevations_deg)):
        azimuth = 2.4 * i
        pose = look_at(4 * np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                                     np.sin(elevation)]), (0.0, 0.0, 0.0))
        origins, directions = (t.numpy() for t in rays_from_camera(pose, k, dtype=torch.float64))
        with np.errstate(divide="ignore", invalid="ignore"):
            near, far = (-half_extents - origins) / directions, (half_extents - origins) / directions
        enter, leave = np.minimum(near, far).max(-1), np.maximum(near, far).min(-1)
        poses.append(pose)
        shown.append(enter < leave)
    return Silhouettes([f"{i:03d}" for i in range(len(poses))], np.stack(poses), [k] * len(poses), shown, "masks")


def test_the_box_leaves_out_what_every_photo_sees_only_through_the_object():
    # Seen only from above, the hull of a plate goes on below it in a cone that every photo sees through the plate; the
    # box leaves the cone out, holds the whole plate (its sides show) and every silhouette.
    half = np.array([0.6, 0.45, 0.05])
    silhouettes = plate_silhouettes(half, np.linspace(15, 60, 16))
    hull = carve(silhouettes, np.eye(3), np.zeros(3), 2.0)
    assert hull is not None and hull.box[0][2] < -half[2] - 0.2
    box = shown_box(silhouettes, hull, np.eye(3))
    assert not cut_photos(silhouettes, box, np.eye(3))
    assert np.all(box[0] <= -half + hull.voxel / 2) and np.all(box[1] >= half - hull.voxel / 2)
    assert box[0][2] > -half[2] - 4 * hull.voxel


def test_a_box_that_cuts_what_a_mask_shows_stops_normalize(mast_scene, tmp_path):
    scene, out = mast_scene
    poses = tmp_path / "poses"
    (poses / "masks").mkdir(parents=True)
    (poses / "images").symlink_to(out / "poses" / "images")
    transforms = read_json(out / "poses" / "transforms.json")
    # One photo's mask claims a block beside the object that no other photo shows.
    for frame in transforms["frames"]:
        mask = np.asarray(Image.open(out / "poses" / frame["mask_path"])).copy()
        if frame["name"] == "0005":
            mask[20:80, 10:70] = 255
        Image.fromarray(mask).save(poses / frame["mask_path"])
    points = read_points(out / "poses" / "points.npz")
    with pytest.raises(UserError, match=r"cuts what 1 photo\(s\) show \(0005: \d+% of its mask\).*masks or poses"):
        normalize_scene(transforms, points, SceneOptions(), poses_dir=poses)


def cropped_above_the_base(out: Path, poses: Path, masks: bool) -> dict:
    """The mast scene's photos cropped a little above the object's lowest point (as a capture in an arc whose frames
    all cut the object's base), with their masks, or composited on white without them; their transforms."""
    (poses / "images").mkdir(parents=True)
    if masks:
        (poses / "masks").mkdir()
    transforms = read_json(out / "poses" / "transforms.json")
    for frame in transforms["frames"]:
        mask = np.asarray(Image.open(out / "poses" / frame["mask_path"]))
        keep = int(np.flatnonzero((mask > 127).any(1))[-1]) - 12
        rgb = np.asarray(Image.open(out / "poses" / frame["file_path"]))[:keep, :, :3]
        if masks:
            Image.fromarray(mask[:keep]).save(poses / frame["mask_path"])
        else:
            alpha = mask[:keep, :, None] / 255.0
            rgb = np.round(rgb * alpha + 255 * (1 - alpha)).astype(np.uint8)
            del frame["mask_path"]
        Image.fromarray(rgb).save(poses / frame["file_path"])
        frame.update({key: transforms[key] for key in ("fl_x", "fl_y", "cx", "cy", "w")}, h=keep)
    return transforms


@pytest.mark.parametrize("masks", [True, False], ids=["masks", "flat backdrop"])
def test_silhouettes_whose_hull_stays_open_grow_the_points_box_to_hold_what_they_show(mast_scene, tmp_path, masks):
    # Every frame cuts the object's base, so the hull runs on below, out of every frame: the silhouettes cannot bound
    # the object there. The box of the points' bulk, which cuts the mast, grows until it holds what every silhouette
    # shows, and no further than it must.
    scene, out = mast_scene
    transforms = cropped_above_the_base(out, tmp_path / "poses", masks)
    points = read_points(out / "poses" / "points.npz")
    framed = normalize_scene(transforms, points, SceneOptions(), poses_dir=tmp_path / "poses")
    hull, shown_by = framed["measured"]["visual_hull"], "masks" if masks else "silhouettes on a flat backdrop"
    assert hull["source"] == ("masks" if masks else "backdrop") and not hull["bounded"]
    assert "grown to hold what 21 training photos'" in framed["measured"]["foreground_from"]
    assert f"box from the points, grown to hold what 21 photos' {shown_by} show" in summary_line(framed)
    assert inside_box(mast_top(scene), framed) and hull["cut_photos"] == 0
    from_points = normalize_scene(transforms, points, SceneOptions(), poses_dir=None)
    assert not inside_box(mast_top(scene), from_points)
    # Grown no further than the silhouettes ask: about the object's size, where the hull's box runs on past the
    # cameras.
    bounds = read_json(scene / "ground_truth" / "scene.json")["object_bounds"]
    size = (np.asarray(framed["foreground"]["max"]) - framed["foreground"]["min"]) / framed["scale"]
    truth, open_box = np.subtract(bounds["max"], bounds["min"]), np.asarray(hull["box"])
    assert np.all(open_box[1] - open_box[0] > 3 * truth) and np.all(size < 1.4 * truth)


def backdrop_scene(synthetic: Path, folder: Path, dark_every: int) -> Path:
    """The RGBA synthetic object composited as plain photos: on white, and on near-black for every `dark_every`-th."""
    truth = read_json(synthetic / "transforms.json")
    (folder / "images").mkdir(parents=True)
    for i, frame in enumerate(truth["frames"]):
        rgba = np.asarray(Image.open(synthetic / frame["file_path"])).astype(float) / 255
        backdrop = 0.05 if dark_every and i % dark_every == 0 else 1.0
        rgb = rgba[..., :3] * rgba[..., 3:] + backdrop * (1 - rgba[..., 3:])
        Image.fromarray(np.round(rgb * 255).astype(np.uint8)).save(folder / frame["file_path"])
    write_json(folder / "transforms.json", truth)
    return folder


def test_a_backdrop_that_differs_between_photos_is_each_photos_own(tmp_path):
    synthetic = write_scene("object", tmp_path / "synth", n_views=12, width=96, height=72, seed=0, alpha=True,
                            supersample=1)
    for dark_every in (0, 2):
        folder = backdrop_scene(synthetic, tmp_path / f"photos_{dark_every}", dark_every)
        run(folder, tmp_path / f"out_{dark_every}", ["normalize"])
        framed = read_json(tmp_path / f"out_{dark_every}" / "normalize" / "scene.json")
        assert framed["type"] == "object", framed["reasons"]
        if dark_every:
            assert framed["measured"]["backdrop_photos_showing"] <= 0.6
            assert framed["measured"]["own_backdrops"] >= 0.8
            assert any("one flat colour of their own" in reason for reason in framed["reasons"])
            # Each photo's silhouette on its own colour frames the object, as one colour's do.
            assert framed["measured"]["visual_hull"]["source"] == "backdrop"
            for i, frame in enumerate(sorted(framed["frames"], key=lambda f: f["name"])):
                expected = 0.05 if i % dark_every == 0 else 1.0
                assert np.allclose(frame["backdrop"], expected, atol=2 / 255), (frame["name"], frame["backdrop"])
        else:
            assert framed["measured"]["visual_hull"]["source"] == "backdrop"
            assert all("backdrop" not in frame for frame in framed["frames"])


def test_photos_on_backdrops_of_their_own_colours_fit_as_the_object_alone(tmp_path):
    # Half the photos on white, half on near-black: a background model cannot show both in one place (6 dB held-out
    # typed unbounded); each photo's own colour behind the grid leaves the grid the object alone.
    synthetic = write_scene("object", tmp_path / "synth", n_views=24, width=96, height=72, seed=0, alpha=True,
                            supersample=1)
    folder = backdrop_scene(synthetic, tmp_path / "photos", 2)
    # Each photo's gains fitted too, whatever they bring: they take the object's part of each pixel alone.
    run(folder, tmp_path / "out", ["evaluate"], "fit.resolutions=[32,48]", "fit.steps=[200,200]", "fit.batch_size=2048",
        "fit.image_scale=1", "fit.eval_every=0", "fit.sh_degree=0", "fit.photo_colour=true",
        "fit.photo_colour_min_db=-100")
    fitted = read_json(tmp_path / "out" / "fit" / "fit.json")
    assert fitted["photo_colour"]["used"] and SceneModel.load(tmp_path / "out" / "fit").photo_gains.backdrop_as_taken
    assert not fitted["model"]["background_model"] and fitted["background_added"] is None
    assert fitted["own_backdrops"] and fitted["train_psnr"] > 18
    assert "flat backdrop of its own colour" in read_json(tmp_path / "out" / "normalize" / "manifest.json")["summary"]["line"]
    assert "each photo's own backdrop colour" in read_json(tmp_path / "out" / "fit" / "manifest.json")["summary"]["line"]
    assert read_json(tmp_path / "out" / "evaluate" / "metrics.json")["mean"]["psnr"] > 18
    # The renders show each held-out photo's own backdrop around the object.
    scene = read_json(tmp_path / "out" / "normalize" / "scene.json")
    for frame in [f for f in scene["frames"] if f["split"] == "test"]:
        render = np.asarray(Image.open(tmp_path / "out" / "evaluate" / "renders" / f"{frame['name']}.png")) / 255
        assert np.allclose(render[0, 0], frame["backdrop"], atol=0.1)


def test_masked_photos_are_trained_on_their_own_colour_outside_the_masks_unless_cut_out(tmp_path):
    synthetic = write_scene("object", tmp_path / "synth", n_views=16, width=64, height=48, seed=0, alpha=True,
                            supersample=1)
    truth = read_json(synthetic / "transforms.json")
    folder = tmp_path / "scan"
    (folder / "images").mkdir(parents=True)
    (folder / "masks").mkdir()
    cloth, ramp = {}, []
    held_out = set(sorted(Path(f["file_path"]).stem for f in truth["frames"])[::4])
    for i, frame in enumerate(truth["frames"]):
        rgba = np.asarray(Image.open(synthetic / frame["file_path"])).astype(float) / 255
        colour = np.array([0.2 + 0.04 * i, 0.5, 0.8 - 0.03 * i])  # a cloth lit a little differently in each photo
        name = Path(frame["file_path"]).stem
        if name in held_out:
            colour = np.array([0.9, 0.1, 0.1])  # what a held-out view must not take from its own photo
        else:
            ramp.append(colour)
        cloth[name] = colour
        rgb = rgba[..., :3] * rgba[..., 3:] + colour * (1 - rgba[..., 3:])
        Image.fromarray(np.round(rgb * 255).astype(np.uint8)).save(folder / frame["file_path"])
        Image.fromarray(np.round(rgba[..., 3] * 255).astype(np.uint8)).save(folder / "masks" / f"{name}.png")
    write_json(folder / "transforms.json", truth)
    fit = ["fit.resolutions=[24,32]", "fit.steps=[150,50]", "fit.batch_size=2048", "fit.image_scale=1",
           "fit.eval_every=0", "fit.sh_degree=0"]
    ramp = np.array(ramp)
    for choice in ("fit", "own"):
        out = tmp_path / f"out_{choice}"
        run(folder, out, ["evaluate"], f"normalize.masked_backdrop={choice}", "normalize.holdout_every=4", *fit)
        scene = read_json(out / "normalize" / "scene.json")
        assert scene["type"] == "object" and all(f["mask_path"] for f in scene["frames"])
        assert {f["name"] for f in scene["frames"] if f["split"] == "test"} == held_out
        said = read_json(out / "normalize" / "manifest.json")["summary"]["line"]
        assert ("own colour outside its mask" in said) == (choice == "own"), said
        for frame in scene["frames"]:
            if choice == "fit":
                assert "backdrop" not in frame
            elif frame["split"] != "test":
                assert np.allclose(frame["backdrop"], cloth[frame["name"]], atol=0.02)
            else:  # its nearest training cameras' cloth, somewhere along their ramp
                assert np.all(frame["backdrop"] >= ramp.min(axis=0) - 0.02), frame["backdrop"]
                assert np.all(frame["backdrop"] <= ramp.max(axis=0) + 0.02), frame["backdrop"]
        for frame in [f for f in scene["frames"] if f["split"] == "test"]:
            expected = np.asarray(frame["backdrop"]) if choice == "own" else np.ones(3)
            truth_image = np.asarray(Image.open(out / "evaluate" / "gt" / f"{frame['name']}.png")) / 255
            render = np.asarray(Image.open(out / "evaluate" / "renders" / f"{frame['name']}.png")) / 255
            assert np.allclose(truth_image[0, 0], expected, atol=0.02), (choice, truth_image[0, 0], expected)
            assert np.allclose(render[0, 0], expected, atol=0.1), (choice, render[0, 0], expected)
    # Photos cut out by their own alpha hold nothing of a backdrop outside it: they keep fit.background_color.
    run(synthetic, tmp_path / "out_cutout", ["normalize"])
    scene = read_json(tmp_path / "out_cutout" / "normalize" / "scene.json")
    assert all(f["mask_path"] and "backdrop" not in f for f in scene["frames"])


def test_an_object_fit_that_cannot_reproduce_its_photos_gets_a_background_model(tmp_path):
    # The synthetic unbounded scene typed as an object: one colour behind its grid cannot show its ground and sky.
    scene = write_scene("unbounded", tmp_path / "synth", n_views=16, width=64, height=48, seed=0, supersample=1)
    fit = ["fit.resolutions=[24,32]", "fit.steps=[150,50]", "fit.batch_size=2048", "fit.image_scale=1",
           "fit.eval_every=0", "fit.sh_degree=0"]
    run(scene, tmp_path / "out", ["fit"], "normalize.scene_type=object", *fit)
    record = read_json(tmp_path / "out" / "fit" / "fit.json")
    assert "below 20 dB" in record["background_added"] and record["model"]["background_model"]
    assert "(added: train PSNR" in read_json(tmp_path / "out" / "fit" / "manifest.json")["summary"]["line"]
    # An object on a white backdrop keeps one colour behind its grid.
    scene = write_scene("object", tmp_path / "object", n_views=16, width=64, height=48, seed=0, supersample=1)
    run(scene, tmp_path / "object_out", ["fit"], *fit)
    record = read_json(tmp_path / "object_out" / "fit" / "fit.json")
    assert record["background_added"] is None and not record["model"]["background_model"]


def test_the_backdrop_check_waits_for_a_coarsest_level_long_enough_to_tell():
    from types import SimpleNamespace

    from plenoxels.core.scene_model import BACKDROP_CHECK_MIN_STEPS, backdrop_check_step

    plain = SimpleNamespace(background=None, fit_frame=SimpleNamespace(ndc=None, contraction=None))
    assert backdrop_check_step(plain, [128, 128, 256], [200, 800, 1500]) == 1000  # the early-pruned rest counts
    assert backdrop_check_step(plain, [16], [BACKDROP_CHECK_MIN_STEPS - 1]) is None  # a quick look: too few to tell
    assert backdrop_check_step(plain, [16, 32], [BACKDROP_CHECK_MIN_STEPS, 40]) == BACKDROP_CHECK_MIN_STEPS
    behind = SimpleNamespace(background=object(), fit_frame=plain.fit_frame)
    assert backdrop_check_step(behind, [128, 256], [1000, 1000]) is None
