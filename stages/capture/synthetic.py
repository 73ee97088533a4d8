"""Synthetic scenes with exact cameras: ray-cast textured analytic shapes, for the demo and the tests.

Five kinds, matching the scene types the pipeline handles and the captures it must refuse or mask:
- `object`: a still life (spheres and boxes on a slab) seen by an inward orbit; nothing else in the
  scene, so rays that miss it see a plain background colour (or are transparent, with `alpha=True`).
- `forward`: objects at several depths in front of a textured floor and back wall, seen by cameras
  on a small grid in one plane that all look the same way (like LLFF's fern).
- `unbounded`: the `object` still life (without its slab) on an endless textured ground, inside a
  textured environment sphere of radius 24 (12 times the object's width), seen by an inward orbit:
  a bounded grid around the object cannot hold it.
- `room`: the `object` still life (without its slab) standing on the floor of a closed, textured room
  (four walls and a ceiling a few units away), seen by an inward orbit inside the room: what a capture of
  things on a floor indoors looks like. Only the objects are foreground (the true mesh); floor and walls
  are the room around them.
- `turntable`: the still life (without its slab) on a turntable's plate, turning one revolution in front of a
  still, textured room (floor and walls) while the camera stays put. In the object's frame the cameras orbit it and
  the room turns with them, so only the object's pixels agree with one rigid scene; the masks (`masks=True`) mark
  the object alone (not its plate).

`mast=True` adds a thin mast (a few pixels wide) rising well above the still life: a part the sparse points
barely see, which the photos' silhouettes show.

The world frame is deliberately not normalised (z up, the object about 2 units wide, centred at
OBJECT_CENTRE, off the origin) so the normalize stage has real work to do.

Surfaces carry solid textures (value noise over several octaves, hard-edged colour patches and
spots), so the same 3D point looks the same from every view and SIFT has plenty to match; Lambertian
shading from one fixed light makes the geometry read. Colours are supersampled per pixel to keep the
fine texture from aliasing differently in each view; depth and coverage come from the pixel centre.

Written to disk by `write_scene`:
    images/NNNN.png              8-bit RGB (RGBA with alpha=True, object kind only)
    masks/NNNN.png               with masks=True: 8-bit grey, the share of each pixel the object covers
    transforms.json              shared PINHOLE camera + OpenGL camera-to-world per frame, as the poses stage writes it
    ground_truth/mesh.ply        the foreground shapes, triangulated, in the same world frame
    ground_truth/scene.json      kind, object bounds, world up, the shapes, and each view's near/far hit depths"""
from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from plenoxels.core.cameras import Intrinsics, look_at
from plenoxels.core.errors import UserError
from stages.capture.synthetic_scenes import (ENVIRONMENT_RADIUS, WORLD_UP, camera_directions, render_equirect,
                                             render_fisheye, render_float, to_uint8, build_scene, camera_poses,
                                             intrinsics_for, render_view, turn_angles, view_scene, walk_poses)
from stages.common.json_files import read_json, write_json
from stages.common.media import write_png
from stages.framing.options import SceneOptions


def _silently(items, total=None, desc=""):
    return items



def write_scene(kind: str, out_dir: Path | str, n_views: int = 40, width: int = 320, height: int = 240,
                seed: int = 0, alpha: bool = False, supersample: int = 2, masks: bool = False, mast: bool = False,
                passers_by: float = 0.0, track=None) -> Path:
    """Renders a synthetic scene into out_dir (replacing an earlier synthetic scene there) and returns out_dir.
    `masks` writes a mask per photo into masks/ (the object's coverage of each pixel); `mast` adds a thin mast;
    `passers_by` paints a person walking through into about that share of the views, in each somewhere else (never in
    a view normalize holds out by default, so held-out PSNR scores the scene; each person's pixels in
    ground_truth/passers_by/); `track(items, total, desc)` wraps the views rendered, for progress (a Reporter's
    `track`).

    The scene is assembled in a sibling folder and renamed into place, so out_dir is either the old
    scene or the complete new one. Same arguments, same bytes.
    """
    scene = build_scene(kind, seed, mast=mast)
    _check_arguments(kind, n_views, width, height, alpha, supersample, passers_by)
    out_dir = Path(out_dir)
    _check_replaceable(out_dir)

    tmp = out_dir.with_name(f".{out_dir.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "images").mkdir(parents=True)
    (tmp / "ground_truth").mkdir()
    if masks:
        (tmp / "masks").mkdir()
    if passers_by:
        (tmp / "ground_truth" / "passers_by").mkdir()
    walkers = np.random.default_rng(seed + 1)
    k = intrinsics_for(kind, width, height)
    poses = camera_poses(scene, n_views)
    angles = turn_angles(n_views) if scene.room else np.zeros(n_views)
    frames, views = [], []
    for n, (c2w, angle) in enumerate((track or _silently)(list(zip(poses, angles)), total=n_views,
                                                  desc=f"rendering {kind} scene")):
        rgb, depth, coverage = render_float(view_scene(scene, angle), c2w, k, supersample)
        name = f"images/{n:04d}.png"
        if n % SceneOptions().holdout_every and walkers.random() < passers_by:
            rgb, person = paint_passer_by(rgb, walkers)
            write_png(tmp / "ground_truth" / "passers_by" / f"{n:04d}.png", to_uint8(person.astype(np.float32)))
        if masks:
            write_png(tmp / "masks" / f"{n:04d}.png", to_uint8(coverage))
        if alpha:
            # Unpremultiplied colour: compositing the PNG over the background gives the RGB render back.
            with np.errstate(divide="ignore", invalid="ignore"):
                fg = (rgb - (1 - coverage[..., None]) * np.asarray(scene.background)) / coverage[..., None]
            fg = np.where(coverage[..., None] > 0, fg, 0.0)
            write_png(tmp / name, np.concatenate([to_uint8(fg), to_uint8(coverage)[..., None]], axis=-1))
        else:
            write_png(tmp / name, to_uint8(rgb))
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
        view = {"file_path": name, **_depth_range(depth, k)}
        if scene.room:
            view["turn_deg"] = math.degrees(angle)
        views.append(view)

    write_json(tmp / "transforms.json", {
        "camera_model": "PINHOLE",
        "fl_x": k.fl_x, "fl_y": k.fl_y, "cx": k.cx, "cy": k.cy, "w": k.w, "h": k.h,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "frames": frames,
        "synthetic": {"kind": kind, "seed": seed, "n_views": n_views, "alpha": alpha, "supersample": supersample,
                      "masks": masks, "mast": mast, "passers_by": passers_by},
    })
    scene.mesh().export(tmp / "ground_truth" / "mesh.ply")
    bounds = scene.object_bounds()
    write_json(tmp / "ground_truth" / "scene.json", {
        "kind": kind,
        "seed": seed,
        "world_up": list(WORLD_UP),
        "object_bounds": {"min": bounds[0].tolist(), "max": bounds[1].tolist()},
        "object_centre": list(scene.look_at),
        "environment_radius": ENVIRONMENT_RADIUS if kind == "unbounded" else None,
        "depth_convention": "depth = distance along the camera's viewing axis; distance = along the ray",
        "views": views,
        "scene": scene.to_json(),
    })
    if out_dir.exists():
        shutil.rmtree(out_dir)
    os.replace(tmp, out_dir)
    return out_dir



def paint_passer_by(rgb: np.ndarray, rng: np.random.Generator, size: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A person painted into a view (float RGB [h, w, 3]) where `rng` puts them: a body in clothes of one colour with
    folds, and a head, standing somewhere across the frame. At `size` 1 they stand 0.5-0.9 of the frame tall, cut by
    its bottom edge; smaller, they stand farther off, higher in the frame. Returns the view and the person's pixels
    [h, w] (bool). A person seen in one view and not the next is what no one scene explains."""
    h, w = rgb.shape[:2]
    centre, low, tall = rng.uniform(0.1, 0.9) * w, rng.uniform(0.8, 1.3), rng.uniform(0.5, 0.9) * h * size
    feet = h * (0.5 + size * (low - 0.5))
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    body = ((x - centre) / (0.16 * tall)) ** 2 + ((y - (feet - 0.45 * tall)) / (0.45 * tall)) ** 2 < 1.0
    head = (x - centre) ** 2 + (y - (feet - 0.98 * tall)) ** 2 < (0.09 * tall) ** 2
    grain = max(1.0, h / 240)  # the folds as wide in a large photo as in a small one, for its size
    folds = 0.8 + 0.2 * np.sin(x / (3.0 * grain) + y / (7.0 * grain))[..., None]
    painted = np.where(body[..., None], np.clip(rng.uniform(0.05, 0.95, 3) * folds, 0.0, 1.0), rgb)
    painted[head] = (0.85, 0.65, 0.5)
    return painted.astype(rgb.dtype), body | head


def paint_passers_by(folder: Path | str, share: float, size: float = 1.0, seed: int = 0) -> int:
    """Paints a person (`paint_passer_by` at `size`) into about `share` of the photos in folder/images, in place, each
    somewhere else, never into a photo normalize holds out by default (every holdout_every-th by sorted name); each
    person's pixels go to ground_truth/passers_by/<stem>.png. A real capture with people walking through it, for the
    bench. Returns how many photos were painted."""
    folder, rng, painted = Path(folder), np.random.default_rng(seed), 0
    (folder / "ground_truth" / "passers_by").mkdir(parents=True, exist_ok=True)
    photos = sorted(p for p in (folder / "images").iterdir() if p.suffix.lower() in {".png", ".jpg", ".jpeg"})
    for rank, path in enumerate(photos):
        if rank % SceneOptions().holdout_every == 0 or rng.random() >= share:
            continue
        rgb, person = paint_passer_by(cv2.imread(str(path), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255.0,
                                      rng, size)
        cv2.imwrite(str(path), to_uint8(rgb)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
        write_png(folder / "ground_truth" / "passers_by" / f"{path.stem}.png", to_uint8(person.astype(np.float32)))
        painted += 1
    return painted


def write_panorama_video(path: Path | str, n_frames: int = 48, width: int = 960, seed: int = 0, fps: float = 8.0,
                         supersample: int = 1) -> np.ndarray:
    """A 360 camera's video of the room kind (equirectangular frames `width` x `width`/2, MPEG-4), carried once
    around the still life (`walk_poses`); returns its camera-to-world matrices, the frames' in order."""
    scene = build_scene("room", seed)
    poses = walk_poses(n_frames)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (width, width // 2))
    for c2w in poses:
        writer.write(to_uint8(render_equirect(scene, c2w, width, supersample))[..., ::-1])
    writer.release()
    return poses


def write_fisheye_video(path: Path | str, n_frames: int = 48, width: int = 640, height: int = 480,
                        diagonal_fov_deg: float = 150.0, seed: int = 0, fps: float = 8.0) -> np.ndarray:
    """An action camera's video of the room kind through an equidistant fisheye seeing `diagonal_fov_deg` across its
    diagonal (MPEG-4, no EXIF), along the room's orbit (`camera_poses`); returns its camera-to-world matrices."""
    scene = build_scene("room", seed)
    poses = camera_poses(scene, n_frames)
    focal = math.hypot(width, height) / 2 / math.radians(diagonal_fov_deg / 2)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (width, height))
    for c2w in poses:
        writer.write(to_uint8(render_fisheye(scene, c2w, width, height, focal))[..., ::-1])
    writer.release()
    return poses


def write_drone_video(path: Path | str, fps: float = 24.0, hold: int = 2, seed: int = 4,
                      origin: tuple[float, float, float] = (47.3769, 8.5417, 408.0)) -> np.ndarray:
    """A drone's mapping flight over the unbounded kind as its video (320x240, MPEG-4) and the flight log DJI writes
    beside it (a subtitle file of the clip's name, a caption a frame: stages/capture/flight_log.py): four rows flown
    at 3 units up, the camera 10 degrees off straight down and heading one way throughout, so the cameras' own up
    axes all lie near the heading. Each view is held for `hold` frames; the log gives the frames' places with the
    scene's units as 100 m east, north and up of `origin` (latitude, longitude, altitude), each off by GPS's error
    (half a metre across, a metre in height). Returns each frame's camera-to-world matrix, in the scene's units."""
    scene = build_scene("unbounded", seed)
    k = Intrinsics.from_frame({"fl_x": 277.0, "fl_y": 277.0, "cx": 160.0, "cy": 120.0, "w": 320, "h": 240})
    rows, flight = np.linspace(-1.2, 0.8, 4), []
    for row, y in enumerate(rows):
        across = np.linspace(-0.9, 1.5, 17)
        flight += [(x, y) for x in (across if row % 2 == 0 else across[::-1])]
        if row + 1 < len(rows):  # over to the next row
            flight += [(flight[-1][0], y + share * (rows[1] - rows[0])) for share in (0.25, 0.5, 0.75)]
    pitch = math.radians(-80.0)
    look = math.cos(pitch) * np.array([0.0, 1.0, 0.0]) + math.sin(pitch) * np.asarray(WORLD_UP)
    error = np.random.default_rng(seed).normal(0.0, [0.5, 0.5, 1.0], (len(flight) * hold, 3))
    path = Path(path)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (320, 240))
    poses, places = [], []
    for x, y in flight:
        eye = np.array([x, y, 3.0])
        c2w = look_at(eye, eye + look)
        bgr = np.ascontiguousarray(render_view(scene, c2w, k, supersample=1)[0][..., ::-1])
        for _ in range(hold):
            writer.write(bgr)
            places.append(100.0 * eye + error[len(poses)])
            poses.append(c2w)
    writer.release()
    write_flight_log(path.with_suffix(".SRT"), np.asarray(places), fps, origin)
    return np.stack(poses)


def write_flight_log(path: Path, places: np.ndarray, fps: float, origin: tuple[float, float, float]
                     ) -> list[list[float]]:
    """The flight log DJI writes beside a clip (as a current drone labels it): a caption a frame, with the frame's
    place given as metres east, north and up of `origin` (latitude, longitude, altitude; its height above the take-off
    from there). Returns each frame's place as written (latitude, longitude, altitude)."""
    written, captions = [], []
    for index, (latitude, longitude, altitude) in enumerate(
            pycolmap.GPSTransform().enu_to_ellipsoid(np.asarray(places, dtype=np.float64), *origin)):
        span = " --> ".join(_srt_time(t / fps) for t in (index, index + 1))
        captions.append(f'{index + 1}\n{span}\n<font size="28">FrameCnt: {index + 1}, DiffTime: {1000 / fps:.0f}ms\n'
                        f"[iso: 100] [latitude: {latitude:.6f}] [longitude: {longitude:.6f}] "
                        f"[rel_alt: {altitude - origin[2]:.3f} abs_alt: {altitude:.3f}] </font>\n")
        written.append([float(latitude), float(longitude), float(altitude)])
    path.write_text("\n".join(captions))
    return written


def _srt_time(seconds: float) -> str:
    ms = round(seconds * 1000)
    return f"{ms // 3_600_000:02d}:{ms // 60_000 % 60:02d}:{ms // 1000 % 60:02d},{ms % 1000:03d}"


def _depth_range(depth: np.ndarray, k: Intrinsics) -> dict:
    """Nearest and farthest surface hit in a view, as depth along the viewing axis and as distance along the ray."""
    hit = np.isfinite(depth)
    if not hit.any():
        return {"near_depth": None, "far_depth": None, "near_distance": None, "far_distance": None}
    ray_length = np.linalg.norm(camera_directions(k), axis=-1).reshape(depth.shape)
    distance = depth[hit] * ray_length[hit]
    return {"near_depth": float(depth[hit].min()), "far_depth": float(depth[hit].max()),
            "near_distance": float(distance.min()), "far_distance": float(distance.max())}



def _check_arguments(kind: str, n_views: int, width: int, height: int, alpha: bool, supersample: int,
                     passers_by: float = 0.0) -> None:
    if n_views < 1:
        raise UserError(f"the number of views must be at least 1 (got {n_views})")
    if width < 8 or height < 8:
        raise UserError(f"images must be at least 8x8 pixels (got {width}x{height})")
    if supersample < 1:
        raise UserError(f"supersample must be at least 1 (got {supersample})")
    if alpha and kind != "object":
        raise UserError(f"alpha only applies to the object kind (the {kind} scene has no empty background)")
    if not 0.0 <= passers_by <= 1.0 or (passers_by and alpha):
        raise UserError(f"passers_by is a share of the views in [0, 1], without alpha (got {passers_by})")



def _check_replaceable(out_dir: Path) -> None:
    """Only an empty folder or an earlier synthetic scene may be replaced: never a user's photos."""
    if not out_dir.exists():
        return
    if not out_dir.is_dir():
        raise UserError(f"{out_dir} is a file; give a folder path for the synthetic scene")
    transforms = out_dir / "transforms.json"
    earlier_scene = transforms.is_file() and "synthetic" in read_json(transforms)
    if any(out_dir.iterdir()) and not earlier_scene:
        raise UserError(f"{out_dir} already holds files that are not a synthetic scene; choose an empty or new folder")
