"""The evaluate stage: metrics against a direct computation, the files it writes, the camera paths."""
import math

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from stages.scoring import lpips
from stages.scoring.camera_paths import orbit_path, spiral_path
from stages.common.frames import load_frame, read_frame
from stages.common.json_files import read_json
from stages.scoring.visuals import colour_depth
from plenoxels.core.photo_colour import PhotoGains
from plenoxels.core.scene_model import SceneModel
from stages import evaluate, fit
from tests.stages.test_fit import QUICK, make_scene, run_stage


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    root = make_scene(tmp_path_factory.mktemp("evaluate"), views=15, width=40)
    run_stage(root, fit, {**QUICK, "resolutions": [16, 24], "steps": [60, 60]})
    return root


def test_metrics_match_a_direct_computation(fitted):
    summary = run_stage(fitted, evaluate, {"video_frames": 6, "video_side": 32, "sheet_side": 40})
    metrics = read_json(fitted / "evaluate" / "metrics.json")
    scene = read_json(fitted / "normalize" / "scene.json")
    held_out = [f for f in scene["frames"] if f["split"] == "test"]
    assert metrics["count"] == len(held_out) == 3
    model = SceneModel.load(fitted / "fit")
    direct_psnr, direct_ssim = [], []
    for frame, view in zip(held_out, metrics["views"]):
        truth, k = load_frame(fitted, frame, 1.0, (1.0, 1.0, 1.0))
        render = model.render_camera(np.asarray(frame["transform_matrix"]), k)["rgb"].numpy()
        mse = float(np.mean((render.astype(np.float64) - truth) ** 2))
        direct_psnr.append(-10 * math.log10(mse))
        direct_ssim.append(structural_similarity(truth, render, channel_axis=-1, data_range=1.0,
                                                 gaussian_weights=True, sigma=1.5, use_sample_covariance=False))
        assert view["name"] == frame["name"]
        assert view["psnr"] == pytest.approx(direct_psnr[-1], abs=1e-3)
        assert view["ssim"] == pytest.approx(direct_ssim[-1], abs=1e-4)
        # The PNGs hold the same images, to 8 bits.
        saved_render = iio.imread(fitted / "evaluate" / "renders" / f"{frame['name']}.png") / 255.0
        saved_truth = iio.imread(fitted / "evaluate" / "gt" / f"{frame['name']}.png") / 255.0
        assert -10 * math.log10(np.mean((saved_render - saved_truth) ** 2)) == pytest.approx(direct_psnr[-1], abs=0.1)
        assert iio.imread(fitted / "evaluate" / "depth" / f"{frame['name']}.png").shape == (k.h, k.w, 3)
    assert metrics["mean"]["psnr"] == pytest.approx(np.mean(direct_psnr), abs=1e-3)
    assert metrics["mean"]["ssim"] == pytest.approx(np.mean(direct_ssim), abs=1e-4)
    assert f"PSNR {metrics['mean']['psnr']:.2f} dB" in summary["line"]
    if lpips.weights_available() and min(k.w, k.h) >= lpips.MIN_SIDE:
        assert all(0 <= view["lpips"] < 1 for view in metrics["views"])
        assert metrics["mean"]["lpips"] == pytest.approx(np.mean([v["lpips"] for v in metrics["views"]]), abs=1e-5)
        assert f"LPIPS {metrics['mean']['lpips']:.3f}" in summary["line"]

    video = [f for f in iio.imiter(fitted / "evaluate" / "video.mp4")]
    assert len(video) == 6 and video[0].shape[1] == 32
    sheet = iio.imread(fitted / "evaluate" / "contact_sheet.png")
    assert sheet.shape[0] > 3 * 30 and sheet.shape[1] > 3 * 40  # three rows of three tiles


def test_held_out_views_are_scored_in_the_colour_of_their_capture_neighbours(tmp_path):
    """Photos whose exposure drifts along the capture, as a phone's does: the fit measures each training photo's gains,
    and evaluate renders a held-out view in the gains between its neighbours, which the drift puts near its own."""
    root = make_scene(tmp_path, views=20, width=40, alpha=False)
    scene = read_json(root / "normalize" / "scene.json")
    # At most 0.95: a photo clipped at white would say less of its gain.
    drift = np.linspace(0.0, 1.0, len(scene["frames"]))[:, None] * np.array([0.35, 0.25, -0.3]) + np.array([0.6, 0.7, 0.95])
    for frame, gain in zip(scene["frames"], drift):
        photo = iio.imread(root / frame["file_path"])[..., :3] / 255.0
        iio.imwrite(root / frame["file_path"], np.round(np.clip(photo * gain, 0, 1) * 255).astype(np.uint8))
    run_stage(root, fit, {**QUICK, "photo_colour": True, "measure_every": 40, "sh_degree": 0})
    summary = run_stage(root, evaluate, {"video_frames": 0, "sheet_side": 40})
    metrics = read_json(root / "evaluate" / "metrics.json")
    model = SceneModel.load(root / "fit")
    held_out = [(i, f) for i, f in enumerate(scene["frames"]) if f["split"] == "test"]
    # The fitted gains average 1 over the training photos: the field holds their mean colour.
    trained = [i for i, f in enumerate(scene["frames"]) if f["split"] == "train"]
    common_colour = drift[trained].mean(0)
    assert metrics["colour"] == "capture neighbours' gains" and "neighbours in the capture" in summary["line"]
    common = []
    for (i, frame), view in zip(held_out, metrics["views"]):
        truth, k = load_frame(root, frame, 1.0, model.background_color)
        render = model.render_camera(np.asarray(frame["transform_matrix"]), k)["rgb"].numpy().astype(np.float64)
        gain = np.asarray(view["gain"])
        # The gains follow the drift as far as the neighbours tell it (the first view has a neighbour after it only, so
        # it takes that one's), ...
        between = np.array([np.interp(i, trained, drift[trained, c]) for c in range(3)])
        np.testing.assert_allclose(gain, between / common_colour, atol=0.06)
        # ... and the view is scored as rendered through them.
        assert view["psnr"] == pytest.approx(-10 * math.log10(np.mean((np.clip(render * gain, 0, 1) - truth) ** 2)),
                                             abs=1e-3)
        common.append(-10 * math.log10(np.mean((render - truth) ** 2)))
    assert metrics["mean"]["psnr"] > np.mean(common) + 0.5


def test_depth_colours_follow_depth_and_blank_empty_pixels():
    depth = np.tile(np.linspace(1.0, 3.0, 50), (4, 1))
    opacity = np.ones_like(depth)
    opacity[:, :5] = 0.0
    image = colour_depth(depth, opacity)
    assert (image[:, :5] == 0).all()
    # turbo runs from blue (near) to red (far).
    assert image[0, 6, 2] > image[0, 6, 0] and image[0, -1, 0] > image[0, -1, 2]


def test_orbit_and_spiral_cameras_look_at_the_scene():
    scene = {"foreground": {"min": [-1, -1, -1], "max": [1, 1, 1]}}
    frames = [{"transform_matrix": np.eye(4).tolist()} for _ in range(3)]
    for frame, angle in zip(frames, (0.0, 2.0, 4.0)):
        c2w = np.eye(4)
        c2w[:3, 3] = [3 * math.cos(angle), 3 * math.sin(angle), 1.0]
        frame["transform_matrix"] = c2w.tolist()
    path = orbit_path(scene, frames, 8)
    assert len(path) == 8
    for c2w in path:
        assert np.linalg.norm(c2w[:3, 3]) == pytest.approx(math.sqrt(10), rel=1e-6)
        # The camera looks down -z at the foreground centre.
        np.testing.assert_allclose(-c2w[:3, 2], -c2w[:3, 3] / np.linalg.norm(c2w[:3, 3]), atol=1e-9)

    reference = np.eye(4)
    forward_frames = []
    for dx, dy in ((-0.2, 0.1), (0.2, -0.1), (0.0, 0.0)):
        c2w = np.eye(4)
        c2w[:3, 3] = [dx, dy, 0.0]
        forward_frames.append({"transform_matrix": c2w.tolist(), "near": 1.0, "far": 10.0})
    spiral = spiral_path({"forward": {"reference_c2w": reference.tolist()}}, forward_frames, 10)
    for c2w in spiral:
        assert np.all(np.abs(c2w[:3, 3]) <= 0.2 + 1e-9)
        assert c2w[2, 2] > 0.9  # still facing the way the capture faced (down -z)


def test_rays_that_miss_the_grid_see_the_background(fitted):
    model = SceneModel.load(fitted / "fit")
    o = torch.zeros(4, 3)
    o[:, 0] = 5.0
    d = torch.tensor([[-1.0, 0, 0], [-1, 0.1, 0], [0, 0, 1], [1, 0, 0]])
    result = model.render_rays(o, d / d.norm(dim=1, keepdim=True))
    assert torch.isfinite(result.rgb).all()
    np.testing.assert_allclose(result.rgb[2:].numpy(), [model.background_color] * 2, atol=1e-6)
    assert float(result.opacity[0]) > 0.5  # the ray through the object's centre is stopped


def test_masked_photos_take_their_gains_on_the_object_alone(tmp_path):
    """Photos cut out by masks whose light drifts along the capture (a DTU-style set): the fit measures each photo's
    gains inside the masks; a held-out view is rendered with its neighbours' gains on the object and the masks'
    backdrop colour left as the masks put it; inside the masks it scores nearer its photo than in the common colour."""
    root = make_scene(tmp_path, views=20, width=64, alpha=True)
    scene = read_json(root / "normalize" / "scene.json")
    drift = np.linspace(0.0, 1.0, len(scene["frames"]))[:, None] * np.array([0.5, 0.4, -0.5]) + np.array([0.45, 0.55, 0.95])
    for frame, gain in zip(scene["frames"], drift):
        photo = iio.imread(root / frame["file_path"]) / 255.0
        photo[..., :3] = np.clip(photo[..., :3] * gain, 0, 1)
        iio.imwrite(root / frame["file_path"], np.round(photo * 255).astype(np.uint8))
    # Longer than QUICK: the gains are measured on the object alone, against a render that must come near it first.
    run_stage(root, fit, {**QUICK, "photo_colour": True, "measure_every": 40, "sh_degree": 0, "steps": [400, 400], "resolutions": [32, 64]})
    assert read_json(root / "fit" / "fit.json")["photo_colour"]["used"]
    run_stage(root, evaluate, {"video_frames": 0, "sheet_side": 40})
    metrics = read_json(root / "evaluate" / "metrics.json")
    model = SceneModel.load(root / "fit")
    assert model.photo_gains.backdrop_as_taken
    held_out = [(i, f) for i, f in enumerate(scene["frames"]) if f["split"] == "test"]
    train = [f["split"] == "train" for f in scene["frames"]]
    # Each held-out photo's true gains as its neighbours' true gains give them: the measured ones follow those.
    truth_between = PhotoGains([f["name"] for f in scene["frames"]], {
        f["name"]: gain for f, gain, fitted in zip(scene["frames"], drift / drift[train].mean(0), train) if fitted})
    backdrop = np.asarray(model.background_color)
    common, oracle = [], []
    for (i, frame), view in zip(held_out, metrics["views"]):
        truth, k, mask = read_frame(root, frame, 1.0, model.background_color)
        mask = mask > 0.5
        plain = model.render_camera(np.asarray(frame["transform_matrix"]), k)
        seen = model.render_camera(np.asarray(frame["transform_matrix"]), k, photo=frame["name"])
        render, opacity, photographed = (plain["rgb"].numpy().astype(np.float64), plain["opacity"].numpy()[..., None],
                                         seen["rgb"].numpy().astype(np.float64))
        gain = np.asarray(view["gain"])
        np.testing.assert_allclose(gain, truth_between.of(frame["name"]), atol=0.06)
        # The gains take the object's part of each pixel; the backdrop's part stays the masks' colour.
        expected = np.clip((render - (1 - opacity) * backdrop) * gain + (1 - opacity) * backdrop, 0, 1)
        np.testing.assert_allclose(photographed, expected, atol=1e-4)
        empty = opacity[..., 0] < 0.01
        assert empty.mean() > 0.2 and np.abs(photographed[empty] - backdrop).max() < 0.02
        common.append(-10 * math.log10(np.mean((render[mask] - truth[mask]) ** 2)))
        between = np.clip(render * truth_between.of(frame["name"]), 0, 1)
        oracle.append(-10 * math.log10(np.mean((between[mask] - truth[mask]) ** 2)))
    # The field's own error inside the masks of a few views is most of it: of what the neighbours' true gains would
    # bring the held-out views, the measured ones bring most.
    brought, could = metrics["mean"]["psnr_masked"] - np.mean(common), np.mean(oracle) - np.mean(common)
    assert could > 0.3 and brought > 0.7 * could, (brought, could)


def test_light_that_sweeps_across_the_frames_is_rendered_as_the_neighbours_saw_it(tmp_path):
    """Photos whose light falls off across the frame, to the right in the first and to the left in the last (a
    capturer's shadow, a lamp's glow as the camera turns): the fit measures each photo's gains across its frame, which
    follow the sweep; a held-out view is rendered with the lattice between its neighbours' and scores nearer its
    photo, inside its mask, than with their one gain a photo."""
    root = make_scene(tmp_path, views=20, width=64, alpha=True)
    scene = read_json(root / "normalize" / "scene.json")
    slopes = np.linspace(-1.6, 1.6, len(scene["frames"]))
    for frame, slope in zip(scene["frames"], slopes):
        photo = iio.imread(root / frame["file_path"]) / 255.0
        across = 1.0 + slope * (np.linspace(0, 1, photo.shape[1]) - 0.5)
        photo[..., :3] = np.clip(photo[..., :3] * across[None, :, None], 0, 1)
        iio.imwrite(root / frame["file_path"], np.round(photo * 255).astype(np.uint8))
    run_stage(root, fit, {**QUICK, "photo_colour": True, "photo_colour_min_db": -100.0, "photo_colour_cells": 4,
                          "measure_every": 40, "sh_degree": 0, "steps": [400, 400], "resolutions": [32, 64]})
    run_stage(root, evaluate, {"video_frames": 0, "sheet_side": 40})
    metrics = read_json(root / "evaluate" / "metrics.json")
    assert metrics["colour"] == "capture neighbours' gains across the frame"
    model = SceneModel.load(root / "fit")
    lattices = model.photo_gains
    assert lattices.fields_follow_order
    # Each training photo's lattice falls the way its light does: its left column over its right one.
    fitted = [(frame["name"], slope) for frame, slope in zip(scene["frames"], slopes) if frame["name"] in lattices.fields]
    falls = [np.log(lattices.fields[name][:, 0] / lattices.fields[name][:, -1]).mean() for name, _ in fitted]
    assert np.corrcoef(falls, [-slope for _, slope in fitted])[0, 1] > 0.8
    record = lattices.record()
    one_gain = PhotoGains(record["order"], record["gains"], record["backdrop_as_taken"])
    by_lattice, by_gain = [], []
    for frame, view in zip([f for f in scene["frames"] if f["split"] == "test"], metrics["views"]):
        truth, k, mask = read_frame(root, frame, 1.0, model.background_color)
        mask = mask > 0.5
        c2w = np.asarray(frame["transform_matrix"])
        with_lattice = model.render_camera(c2w, k, photo=frame["name"])["rgb"].numpy()
        by_lattice.append(-10 * math.log10(np.mean((with_lattice[mask] - truth[mask]) ** 2)))
        assert abs(view["psnr_masked"] - by_lattice[-1]) < 0.05  # evaluate scored this render
        model.photo_gains = one_gain
        with_gain = model.render_camera(c2w, k, photo=frame["name"])["rgb"].numpy()
        model.photo_gains = lattices
        by_gain.append(-10 * math.log10(np.mean((with_gain[mask] - truth[mask]) ** 2)))
    assert np.mean(by_lattice) > np.mean(by_gain), (by_lattice, by_gain)
