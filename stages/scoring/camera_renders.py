"""Rendering a fitted scene from cameras a user chooses, and scoring the renders where the cameras come
with photos.

Cameras come from
- a `transforms.json` (NeRF, instant-ngp or nerfstudio layout: `transform_matrix` camera-to-world in
  the OpenGL convention; intrinsics `fl_x, fl_y, cx, cy, w, h` or NeRF's `camera_angle_x`, shared or
  per frame; a nerfstudio `applied_transform` is undone), in the frame the poses stage wrote (COLMAP's
  for photos posed here): `world_from_input` (normalize/scene.json) takes them into the fit's world;
- a nerfstudio `camera_path.json` (`camera_path: [{camera_to_world (16 numbers, row-major), fov
  (vertical, degrees)}]`, `render_width`, `render_height`, `fps`), in the same frame;
- a named path in the normalised world (stages/scoring/camera_paths.py): `orbit`, `spiral`, or `auto` (the
  one that suits the capture).
`frame="normalized"` reads a file's cameras as already in the normalised world instead.

`render_cameras` writes renders/<name>.png, depth/<name>.png (colour-mapped) and depth/<name>.npy
(float32 distance along each ray in the input frame's units, 0 where nothing is hit),
opacity/<name>.png, video.mp4 for a path, and metrics.json: PSNR, SSIM and LPIPS per view that has a
photo, and their means.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import imageio.v2 as imageio
import imageio.v3 as iio
import numpy as np
import torch

from stages.scoring import camera_paths
from stages.common.frames import composited, read_alpha
from stages.common.media import write_png
from stages.common.json_files import read_json, write_json
from stages.scoring.lpips import weights_available
from stages.scoring.metrics import image_scores, mean_scores, to_uint8
from stages.scoring.visuals import colour_depth
from plenoxels.core.cameras import Intrinsics
from plenoxels.core.errors import UserError
from plenoxels.core.scene_model import SceneModel
from stages.common.layout import METRICS_JSON, scene_json

NAMED_PATHS = ("auto", "orbit", "spiral")
DEFAULT_PATH_FRAMES = 120
DEFAULT_PATH_SIDE = 480
DEFAULT_FPS = 24
# Extensions tried for a NeRF-style file_path given without one ("./test/r_0").
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class RenderCamera:
    name: str
    c2w: np.ndarray                 # 4x4 camera-to-world, normalised world frame, OpenGL convention
    intrinsics: Intrinsics
    image: Path | None = None       # the photo this camera took, if known: its renders are scored
    mask: Path | None = None        # a mask for that photo (its alpha), if separate


@dataclass
class CameraSet:
    cameras: list[RenderCamera]
    source: str                     # "transforms", "camera_path", or the named path's kind
    is_path: bool                   # a camera path: the renders also make a video
    fps: float = DEFAULT_FPS


# ------------------------------------------------------------------------------------------------
# Reading cameras


def world_c2w(c2w_input: np.ndarray, world_from_input: np.ndarray) -> np.ndarray:
    """A camera-to-world in the input frame -> the normalised world (rotation kept orthonormal)."""
    c2w = np.asarray(world_from_input, dtype=np.float64) @ np.asarray(c2w_input, dtype=np.float64)
    c2w[:3, :3] /= np.linalg.norm(c2w[:3, :3], axis=0, keepdims=True)
    return c2w


def _image_path(root: Path, file_path: str | None) -> Path | None:
    if not file_path:
        return None
    path = root / file_path
    if path.is_file():
        return path
    for suffix in IMAGE_SUFFIXES:
        if path.with_name(path.name + suffix).is_file():
            return path.with_name(path.name + suffix)
    return None


def _frame_intrinsics(shared: dict, frame: dict, image: Path | None, where: str) -> Intrinsics:
    merged = {**shared, **frame}
    w, h = merged.get("w"), merged.get("h")
    if (w is None or h is None) and image is not None:
        h, w = iio.improps(image).shape[:2]
    if w is None or h is None:
        raise UserError(f"{where}: no image size (w, h) and no image to read it from")
    w, h = int(w), int(h)
    fl_x, fl_y = merged.get("fl_x"), merged.get("fl_y")
    if fl_x is None and "camera_angle_x" in merged:
        fl_x = 0.5 * w / math.tan(0.5 * float(merged["camera_angle_x"]))
    if fl_y is None and "camera_angle_y" in merged:
        fl_y = 0.5 * h / math.tan(0.5 * float(merged["camera_angle_y"]))
    if fl_x is None and fl_y is None:
        raise UserError(f"{where}: no focal length (fl_x / fl_y or camera_angle_x)")
    fl_x = float(fl_x if fl_x is not None else fl_y)
    fl_y = float(fl_y if fl_y is not None else fl_x)
    return Intrinsics(fl_x, fl_y, float(merged.get("cx", w / 2)), float(merged.get("cy", h / 2)), w, h)


def read_transforms(path: Path, world_from_input: np.ndarray, frame: str = "input") -> CameraSet:
    """The cameras of a transforms.json (see the module docstring), with their photos where they exist."""
    path = Path(path)
    data = read_json(path)
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise UserError(f"{path} has no frames: is it a transforms.json?")
    undo = np.eye(4)
    if "applied_transform" in data:
        applied = np.eye(4)
        applied[:3, :] = np.asarray(data["applied_transform"], dtype=np.float64)[:3, :]
        undo = np.linalg.inv(applied)
    shared = {k: v for k, v in data.items() if k != "frames"}
    cameras = []
    for i, record in enumerate(frames):
        if "transform_matrix" not in record:
            raise UserError(f"{path}: frame {i} has no transform_matrix")
        image = _image_path(path.parent, record.get("file_path"))
        mask = _image_path(path.parent, record.get("mask_path"))
        name = Path(record["file_path"]).stem if record.get("file_path") else f"{i:05d}"
        k = _frame_intrinsics(shared, record, image, f"{path} frame {name}")
        c2w = undo @ np.asarray(record["transform_matrix"], dtype=np.float64)
        if frame == "input":
            c2w = world_c2w(c2w, world_from_input)
        cameras.append(RenderCamera(name, c2w, k, image, mask))
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        cameras = [replace(c, name=f"{i:05d}_{c.name}") for i, c in enumerate(cameras)]
    return CameraSet(cameras, "transforms", is_path=False)


def read_camera_path(path: Path, world_from_input: np.ndarray, frame: str = "input") -> CameraSet:
    """The cameras of a nerfstudio camera_path.json (pinhole; fov is vertical, in degrees)."""
    path = Path(path)
    data = read_json(path)
    keyframes = data.get("camera_path")
    if not isinstance(keyframes, list) or not keyframes:
        raise UserError(f"{path} has no camera_path entries: is it a nerfstudio camera_path.json?")
    if data.get("camera_type", "perspective") != "perspective":
        raise UserError(f"{path}: camera_type {data['camera_type']!r} is not supported; only perspective")
    w, h = int(data.get("render_width", 0)), int(data.get("render_height", 0))
    if w <= 0 or h <= 0:
        raise UserError(f"{path}: render_width and render_height must be positive")
    cameras = []
    for i, key in enumerate(keyframes):
        c2w = np.asarray(key["camera_to_world"], dtype=np.float64).reshape(4, 4)
        if frame == "input":
            c2w = world_c2w(c2w, world_from_input)
        focal = 0.5 * h / math.tan(0.5 * math.radians(float(key["fov"])))
        cameras.append(RenderCamera(f"{i:05d}", c2w, Intrinsics(focal, focal, w / 2, h / 2, w, h)))
    return CameraSet(cameras, "camera_path", is_path=True, fps=float(data.get("fps", DEFAULT_FPS)))


def named_path(name: str, scene: dict, frames: int, side: int) -> CameraSet:
    """`auto`, `orbit` or `spiral` around the scene's training cameras (scene.json's), `frames` views whose
    longest side is `side` pixels."""
    train = [f for f in scene.get("frames", []) if f.get("split", "train") == "train"] or scene.get("frames", [])
    if not train:
        raise UserError("scene.json has no cameras to build a path from; re-run normalize")
    if name == "auto":
        kind, path = camera_paths.default_path(scene, train, frames)
    else:
        kind, path = name, (camera_paths.orbit_path if name == "orbit" else camera_paths.spiral_path)(scene, train, frames)
    k = camera_paths.median_intrinsics(train, side)
    return CameraSet([RenderCamera(f"{i:05d}", c2w, k) for i, c2w in enumerate(path)], kind, is_path=True)


def load_cameras(spec: str, scene: dict, frame: str = "input", frames: int | None = None,
                 side: int | None = None) -> CameraSet:
    """A camera file (transforms.json or camera_path.json, told apart by their contents) or a named path."""
    if spec in NAMED_PATHS:
        return named_path(spec, scene, frames or DEFAULT_PATH_FRAMES, side or DEFAULT_PATH_SIDE)
    path = Path(spec)
    if not path.is_file():
        raise UserError(f"--cameras {spec}: no such file, and not one of {', '.join(NAMED_PATHS)}")
    world_from_input = np.asarray(scene.get("world_from_input", np.eye(4)), dtype=np.float64)
    data = read_json(path)
    if "camera_path" in data:
        return read_camera_path(path, world_from_input, frame)
    return read_transforms(path, world_from_input, frame)


def resized(cameras: CameraSet, size: tuple[int, int] | int | None) -> CameraSet:
    """Every camera at `size`: a longest side in pixels (aspect kept), or (width, height). Cameras with
    photos keep their aspect, so their renders can be scored."""
    if size is None:
        return cameras
    out = []
    for cam in cameras.cameras:
        k = cam.intrinsics
        if isinstance(size, int):
            k = k.scaled(size / max(k.w, k.h))
        else:
            if cam.image is not None and abs(size[0] / size[1] - k.w / k.h) > 0.01:
                raise UserError(f"--size {size[0]}x{size[1]} changes the aspect of camera {cam.name}, which has a "
                                "photo to score against; give one number (the longest side)")
            sx, sy = size[0] / k.w, size[1] / k.h
            k = Intrinsics(k.fl_x * sx, k.fl_y * sy, k.cx * sx, k.cy * sy, size[0], size[1])
        out.append(replace(cam, intrinsics=k))
    return replace(cameras, cameras=out)


def even_size(k: Intrinsics) -> Intrinsics:
    """The same camera cropped to even width and height (H.264 in yuv420p needs them)."""
    return Intrinsics(k.fl_x, k.fl_y, k.cx - (k.w % 2) / 2, k.cy - (k.h % 2) / 2, k.w - k.w % 2, k.h - k.h % 2)


# ------------------------------------------------------------------------------------------------
# Ground truth and rendering


def read_truth(cam: RenderCamera, background_color) -> np.ndarray:
    """The camera's photo as float32 RGB [h, w, 3] in [0, 1] at the camera's size, its alpha (an RGBA
    photo's, or the mask's) composited onto `background_color` as the fit saw its photos."""
    image = iio.imread(cam.image)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    peak = 65535.0 if image.dtype == np.uint16 else 255.0
    alpha = image[..., 3].astype(np.float32) / peak if image.shape[2] == 4 else None
    if cam.mask is not None:
        alpha = read_alpha(cam.mask)
    if alpha is not None and alpha.shape != image.shape[:2]:
        raise UserError(f"mask {cam.mask} is not the size of its photo {cam.image}")
    return composited(image[..., :3].astype(np.float32), peak, alpha, cam.intrinsics, background_color)


def render_cameras(model, cameras: CameraSet, out: Path, report, input_units_per_world: float = 1.0) -> dict:
    """Renders every camera into `out` (see the module docstring) and returns what metrics.json holds.
    `input_units_per_world` converts the depths to the input frame's units (1 / scene.json's scale)."""
    out = Path(out)
    for folder in ("renders", "depth", "opacity"):
        (out / folder).mkdir(parents=True, exist_ok=True)
    scored = any(c.image is not None for c in cameras.cameras)
    with_lpips = scored and weights_available()
    if scored and not with_lpips:
        report.warn("LPIPS not scored: its weights are not installed; run `make install`")
    writer = None
    if cameras.is_path:
        cameras = replace(cameras, cameras=[replace(c, intrinsics=even_size(c.intrinsics)) for c in cameras.cameras])
        writer = imageio.get_writer(out / "video.mp4", fps=cameras.fps, codec="libx264", quality=7, macro_block_size=1)
    views = []
    started = time.monotonic()
    try:
        for cam in report.track(cameras.cameras, desc=f"rendering {len(cameras.cameras)} views"):
            with torch.no_grad():
                result = model.render_camera(cam.c2w, cam.intrinsics)
            rgb = result["rgb"].cpu().numpy().astype(np.float32)
            depth, opacity = result["depth"].cpu().numpy(), result["opacity"].cpu().numpy()
            write_png(out / "renders" / f"{cam.name}.png", to_uint8(rgb))
            write_png(out / "depth" / f"{cam.name}.png", colour_depth(depth, opacity))
            np.save(out / "depth" / f"{cam.name}.npy", (depth * input_units_per_world).astype(np.float32))
            write_png(out / "opacity" / f"{cam.name}.png", to_uint8(opacity))
            if writer is not None:
                writer.append_data(to_uint8(rgb))
            view = {"name": cam.name, "width": cam.intrinsics.w, "height": cam.intrinsics.h}
            if cam.image is not None:
                view.update(image_scores(rgb, read_truth(cam, model.background_color), with_lpips))
            views.append(view)
    finally:
        if writer is not None:
            writer.close()
    metrics = {"source": cameras.source, "count": len(views), "views": views, "mean": mean_scores(views),
               "scored": sum(1 for v in views if "psnr" in v), "render_seconds": round(time.monotonic() - started, 2),
               "video": "video.mp4" if cameras.is_path else None,
               "lpips": "AlexNet, v0.1 (stages/scoring/lpips.py)" if with_lpips else None}
    write_json(out / METRICS_JSON, metrics)
    write_json(out / "cameras.json", {"frame": "normalized", "cameras": [
        {"name": c.name, "transform_matrix": c.c2w.tolist(), "fl_x": c.intrinsics.fl_x, "fl_y": c.intrinsics.fl_y,
         "cx": c.intrinsics.cx, "cy": c.intrinsics.cy, "w": c.intrinsics.w, "h": c.intrinsics.h}
        for c in cameras.cameras]})
    return metrics


def summary_line(metrics: dict, out: Path) -> str:
    """One line for a person: how many views, the mean scores if any, where they went."""
    line = f"{metrics['count']} views ({metrics['source']})"
    mean = metrics.get("mean")
    if mean:
        line += f"; on {metrics['scored']} with photos: PSNR {mean['psnr']:.2f} dB, SSIM {mean['ssim']:.3f}"
        line += f", LPIPS {mean['lpips']:.3f}" if "lpips" in mean else ", LPIPS not scored"
    if metrics.get("video"):
        line += f"; video {metrics['video']}"
    return f"{line}; written to {out}"


# ------------------------------------------------------------------------------------------------
# The render command's work


def parse_size(text: str | None) -> tuple[int, int] | int | None:
    """"640" (the longest side) or "640x480" (width x height)."""
    if not text:
        return None
    try:
        parts = [int(p) for p in text.lower().split("x")]
    except ValueError:
        parts = []
    if len(parts) not in (1, 2) or min(parts) < 8:
        raise UserError(f"--size {text}: give the longest side (640) or width x height (640x480), at least 8 pixels")
    return parts[0] if len(parts) == 1 else (parts[0], parts[1])


def render_scene(scene_out: Path, spec: str, dest: Path | None = None, size: str | None = None,
                 frames: int | None = None, frame: str = "input", report=None) -> tuple[dict, Path]:
    """Renders the model fitted in `scene_out` (a pipeline output folder: normalize/, fit/) from the cameras
    `spec` names into `dest` (default scene_out/render/<the cameras' name>). Returns (metrics, dest)."""
    scene_out = Path(scene_out)
    scene_path = scene_json(scene_out)
    if not scene_path.is_file():
        raise UserError(f"{scene_out} holds no normalize/scene.json: run the pipeline on the scene first")
    scene = read_json(scene_path)
    model = SceneModel.load(scene_out / "fit")
    parsed = parse_size(size)
    cameras = load_cameras(spec, scene, frame, frames, parsed if isinstance(parsed, int) else None)
    if frames and spec not in NAMED_PATHS:
        report.warn("--frames applies to named paths only; ignored")
    cameras = resized(cameras, parsed)
    label = spec if spec in NAMED_PATHS else Path(spec).stem
    dest = Path(dest) if dest else scene_out / "render" / label
    metrics = render_cameras(model, cameras, dest, report, 1.0 / float(scene.get("scale", 1.0)))
    return metrics, dest
