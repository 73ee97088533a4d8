"""Rendering from chosen cameras (stages/scoring/camera_renders.py, `python -m pipeline render`): camera files read
into the fit's world through scene.json's transform, renders scored against photos, paths made into videos."""
from __future__ import annotations

import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from pipeline import cli
from stages.scoring import lpips
from stages.scoring import camera_renders as rc
from stages.common.json_files import read_json, write_json
from plenoxels.core.cameras import Intrinsics, look_at
from plenoxels.core.errors import UserError
from plenoxels.core.grid import SparseGrid
from plenoxels.core.scene_model import SceneModel

SIZE = 32


def _world_from_input() -> np.ndarray:
    """A similarity: scale 0.5, a rotation about a tilted axis, a shift (as normalize writes one)."""
    axis = np.array([1.0, 2.0, 3.0]) / math.sqrt(14)
    angle = 0.7
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross
    m = np.eye(4)
    m[:3, :3] = 0.5 * rotation
    m[:3, 3] = [0.2, -0.1, 0.3]
    return m


def _ring(n: int, radius: float, height: float, arc_deg: float = 360.0, start_deg: float = 0.0) -> list[np.ndarray]:
    step = arc_deg / n if arc_deg >= 360 else arc_deg / max(1, n - 1)
    return [look_at((radius * math.cos(a), radius * math.sin(a), height), (0.0, 0.0, 0.0))
            for a in np.radians(start_deg + step * np.arange(n))]


@pytest.fixture(scope="module")
def scene_out(tmp_path_factory) -> Path:
    """A pipeline output folder with a small hand-made model (a textured ball) in fit/ and its scene.json."""
    out = tmp_path_factory.mktemp("render")
    res = 24
    axis = np.linspace(-1, 1, res)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    density = np.where(x ** 2 + y ** 2 + z ** 2 < 0.45, 60.0, 0.0).ravel()
    sh = np.stack([np.sin(4 * x), np.cos(3 * y), np.sin(2 * z + x)], axis=-1).reshape(-1, 3) * 1.2
    grid = SparseGrid.from_values(torch.arange(res ** 3, dtype=torch.int32).reshape(res, res, res),
                                  torch.tensor(density, dtype=torch.float32), torch.tensor(sh, dtype=torch.float32),
                                  (-1, -1, -1), (1, 1, 1), 0)
    world_from_input = _world_from_input()
    transforms = {"world_from_input": world_from_input.tolist(),
                  "input_from_world": np.linalg.inv(world_from_input).tolist(), "scale": 0.5}
    (out / "fit").mkdir()
    SceneModel(grid, "object", transforms=transforms).save(out / "fit")
    k = Intrinsics(30.0, 30.0, SIZE / 2, SIZE / 2, SIZE, SIZE)
    frames = [{"name": f"v{i}", "transform_matrix": c2w.tolist(), "fl_x": k.fl_x, "fl_y": k.fl_y, "cx": k.cx,
               "cy": k.cy, "w": k.w, "h": k.h, "near": 1.0, "far": 5.0, "split": "train"}
              for i, c2w in enumerate(_ring(12, 3.0, 1.0))]
    (out / "normalize").mkdir()
    write_json(out / "normalize" / "scene.json", {"type": "object", **transforms, "frames": frames,
                                                  "foreground": {"min": [-0.7] * 3, "max": [0.7] * 3}})
    return out


def _input_transforms(folder: Path, model: SceneModel, with_images: bool, nerf_layout: bool = False) -> Path:
    """A transforms.json in the input frame: four cameras around the ball, with photos rendered from the
    model at the world cameras they should map to (RGBA, transparent where the ball is not)."""
    input_from_world = np.linalg.inv(_world_from_input())
    k = Intrinsics(30.0, 30.0, SIZE / 2, SIZE / 2, SIZE, SIZE)
    frames = []
    (folder / "images").mkdir(parents=True, exist_ok=True)
    for i, c2w_world in enumerate(_ring(4, 2.5, 0.8, start_deg=20)):
        c2w_input = input_from_world @ c2w_world
        c2w_input[:3, :3] /= np.linalg.norm(c2w_input[:3, :3], axis=0)  # the input frame is twice the size
        frame = {"transform_matrix": c2w_input.tolist()}
        if with_images:
            out = model.render_camera(c2w_world, k)
            # Straight alpha: the render over white is rgb_premultiplied + (1 - a), so rgb = (render - (1 - a)) / a.
            a = out["opacity"].numpy()[..., None]
            colour = np.clip((out["rgb"].numpy() - (1 - a)) / np.maximum(a, 1e-6), 0, 1)
            rgba = np.concatenate([colour, a], axis=-1)
            iio.imwrite(folder / "images" / f"r_{i}.png", (rgba * 255 + 0.5).astype(np.uint8))
        frame["file_path"] = f"images/r_{i}" if nerf_layout else f"images/r_{i}.png"
        frames.append(frame)
    data = ({"camera_angle_x": 2 * math.atan(SIZE / 2 / 30.0), "frames": frames} if nerf_layout else
            {"fl_x": 30.0, "fl_y": 30.0, "cx": SIZE / 2, "cy": SIZE / 2, "w": SIZE, "h": SIZE, "frames": frames})
    path = folder / "transforms.json"
    write_json(path, data)
    return path


def test_transforms_cameras_land_in_the_fit_world_and_score_against_their_photos(scene_out, tmp_path):
    model = SceneModel.load(scene_out / "fit")
    path = _input_transforms(tmp_path / "nerf", model, with_images=True, nerf_layout=True)
    metrics, dest = rc.render_scene(scene_out, str(path), report=_Quiet())
    assert dest == scene_out / "render" / "transforms"
    assert metrics["count"] == metrics["scored"] == 4 and metrics["video"] is None
    # The photos are the model's own renders at the cameras the file should map to: near-perfect scores.
    for view in metrics["views"]:
        assert view["psnr"] > 38 and view["ssim"] > 0.98
        if lpips.weights_available():
            assert view["lpips"] < 0.01
    for name in ("r_0", "r_3"):
        assert iio.imread(dest / "renders" / f"{name}.png").shape == (SIZE, SIZE, 3)
        assert iio.imread(dest / "depth" / f"{name}.png").shape == (SIZE, SIZE, 3)
        assert iio.imread(dest / "opacity" / f"{name}.png").shape == (SIZE, SIZE)
        depth = np.load(dest / "depth" / f"{name}.npy")
        # In the input frame's units, twice the world's; the ray through the centre meets the ball's front.
        assert 1.5 < depth[SIZE // 2, SIZE // 2] / 2 < 2.5 - math.sqrt(0.45) + 0.2
    written = read_json(dest / "metrics.json")
    assert written["mean"]["psnr"] == pytest.approx(np.mean([v["psnr"] for v in written["views"]]), abs=1e-3)


def test_a_scored_set_with_a_misplaced_frame_scores_low(scene_out, tmp_path):
    """The same file read as if already normalised puts the cameras elsewhere: the scores say so."""
    model = SceneModel.load(scene_out / "fit")
    path = _input_transforms(tmp_path / "plain", model, with_images=True)
    right = rc.render_scene(scene_out, str(path), dest=tmp_path / "a", report=_Quiet())[0]
    wrong = rc.render_scene(scene_out, str(path), dest=tmp_path / "b", frame="normalized", report=_Quiet())[0]
    assert right["mean"]["psnr"] > wrong["mean"]["psnr"] + 10


def test_camera_path_json_renders_a_video(scene_out, tmp_path):
    keyframes = [{"camera_to_world": (np.linalg.inv(_world_from_input()) @ c2w).ravel().tolist(), "fov": 50.0}
                 for c2w in _ring(5, 2.5, 0.5)]
    path = tmp_path / "camera_path.json"
    write_json(path, {"camera_type": "perspective", "render_width": 40, "render_height": 30, "fps": 10,
                      "camera_path": keyframes})
    cameras = rc.load_cameras(str(path), read_json(scene_out / "normalize" / "scene.json"))
    assert cameras.is_path and cameras.fps == 10 and len(cameras.cameras) == 5
    k = cameras.cameras[0].intrinsics
    assert (k.w, k.h) == (40, 30) and k.fl_y == pytest.approx(15 / math.tan(math.radians(25)))
    rotation = cameras.cameras[0].c2w[:3, :3]
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-9)
    assert cli.main(["render", str(scene_out), "--cameras", str(path), "--quiet", "--to", str(tmp_path / "v")]) == 0
    video = list(iio.imiter(tmp_path / "v" / "video.mp4"))
    assert len(video) == 5 and video[0].shape[:2] == (30, 40)
    assert read_json(tmp_path / "v" / "metrics.json")["mean"] is None  # no photos, nothing scored


def test_named_paths_and_sizes(scene_out, tmp_path):
    assert cli.main(["render", str(scene_out), "--cameras", "orbit", "--frames", "4", "--size", "24x16",
                     "--quiet", "--to", str(tmp_path / "o")]) == 0
    assert len(list(iio.imiter(tmp_path / "o" / "video.mp4"))) == 4
    assert iio.imread(tmp_path / "o" / "renders" / "00000.png").shape == (16, 24, 3)
    scene = read_json(scene_out / "normalize" / "scene.json")
    auto = rc.load_cameras("auto", scene, frames=6, side=20)
    assert auto.source == "orbit" and len(auto.cameras) == 6  # the fixture's cameras ring the ball
    assert max(auto.cameras[0].intrinsics.w, auto.cameras[0].intrinsics.h) == 20


def test_sizes_and_bad_input_are_one_line_errors(scene_out, tmp_path):
    assert rc.parse_size("640") == 640 and rc.parse_size("640x480") == (640, 480) and rc.parse_size(None) is None
    for bad in ("x", "640x", "4", "1x2x3"):
        with pytest.raises(UserError):
            rc.parse_size(bad)
    model = SceneModel.load(scene_out / "fit")
    path = _input_transforms(tmp_path / "s", model, with_images=True)
    cameras = rc.load_cameras(str(path), read_json(scene_out / "normalize" / "scene.json"))
    assert rc.resized(cameras, 16).cameras[0].intrinsics.w == 16
    with pytest.raises(UserError, match="aspect"):
        rc.resized(cameras, (32, 16))
    with pytest.raises(UserError, match="no such file"):
        rc.load_cameras(str(tmp_path / "missing.json"), {})
    assert cli.main(["render", str(tmp_path / "nothing-here"), "--cameras", "orbit"]) == 2


def test_nerfstudio_applied_transform_is_undone(tmp_path):
    applied = np.eye(4)[:3]
    applied = applied[[0, 2, 1]]
    applied[2] *= -1  # what nerfstudio applies to COLMAP's frame
    c2w = _ring(1, 2.0, 0.5)[0]
    ns_c2w = np.vstack([applied, [0, 0, 0, 1]]) @ c2w
    write_json(tmp_path / "transforms.json", {"fl_x": 20, "fl_y": 20, "cx": 8, "cy": 8, "w": 16, "h": 16,
                                              "applied_transform": applied.tolist(),
                                              "frames": [{"file_path": "a.png", "transform_matrix": ns_c2w.tolist()}]})
    cameras = rc.read_transforms(tmp_path / "transforms.json", np.eye(4))
    np.testing.assert_allclose(cameras.cameras[0].c2w, c2w, atol=1e-12)
    assert cameras.cameras[0].image is None


class _Quiet:
    def warn(self, message: str) -> None:
        pass

    def track(self, items, desc: str = ""):
        return items
