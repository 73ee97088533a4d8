"""The scene frame: from posed cameras and sparse points, one world frame (z up, foreground in the unit cube),
the scene type, near/far per image and the train/held-out split, i.e. everything in normalize/scene.json.

The scene type decides what the fit models:
- `forward`: every camera looks the same way (viewing directions within a narrow cone), so the scene
  is a frustum in front of them; the fit uses NDC around the `forward.reference_c2w` camera.
- `object`: cameras look inward at a foreground and little lies beyond it (few sparse points far from
  it, or an empty backdrop: transparent pixels or one flat colour).
- `unbounded`: cameras look inward but there is a real background (many points far beyond the
  foreground, or photos with no empty backdrop); the fit needs a background model.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from PIL import Image

from stages.framing.options import SceneOptions
from stages.framing.visual_hull import DISAGREEING_SHARE, carve, cut_photos, read_silhouettes, shown_box
from plenoxels.core.cameras import Intrinsics, project
from plenoxels.core.errors import UserError

# At least this many sparse points before they are trusted to describe the scene or one image's depths.
MIN_POINTS = 30
MIN_POINTS_PER_IMAGE = 10
# A point belongs to the foreground candidates when at least this share of the cameras has it in view.
COVISIBLE_SHARE = 0.7
# Robust box of the foreground points: the bulk between these percentiles on each axis, widened to the
# points within BOX_REACH times its size (see robust_box).
BOX_PERCENTILES = (2.0, 98.0)
BOX_REACH = 0.2
# Near/far per image: these percentiles of the depths of the points seen there, widened by NEAR_FAR_MARGIN.
NEAR_FAR_PERCENTILES = (1.0, 99.0)
NEAR_FAR_MARGIN = 0.1
# What a camera is aimed at: the sparse points it sees in the middle AIM_SHARE of its image's width and height
# (aimed_points); where at least AIM_MIN_SHARE of the cameras are aimed outside the foreground box, it grows to
# AIM_MARGIN of its size beyond their points. Fewer are views off the object: ball (a phone orbit of a ball on a floor)
# has 6 of 125 aimed at the floor just past its box, fox 1 of 43 at the wall, and growing for them cost fox 0.4 dB.
AIM_SHARE = 0.2
AIM_MIN_SHARE = 0.1
AIM_MARGIN = 0.1
# The surroundings box grows toward the points around the foreground in steps of this share (surroundings_box).
SURROUNDINGS_STEP = 0.05
# Sampled images and their size when measuring how much of the photos show an empty backdrop.
BACKDROP_SAMPLES = 12
BACKDROP_SIDE = 96
BACKDROP_TOLERANCE = 6  # 8-bit levels from the backdrop colour that still count as backdrop
# A still background behind a turning object: textured pixels (a local contrast of STILL_TEXTURE_LEVELS) that look the
# same in every sampled photo, on this share of the pixels. Measured: the synthetic turntable without masks 39% (at
# 480x360) and 57% (320x240, the object smaller); fox, cup, ball and fern 0%.
STILL_TEXTURE_LEVELS = 24
STILL_TEXTURED_SHARE = 0.1
# One backdrop behind the whole capture: at least BACKDROP_MIN_PHOTOS of the sampled photos show its colour on at least
# BACKDROP_BORDER_SHARE of their borders (an object in front of a flat backdrop leaves most of every border to it).
BACKDROP_BORDER_SHARE = 0.5
BACKDROP_MIN_PHOTOS = 0.8
# The box from the training photos' silhouettes (stages/framing/visual_hull.py): at least this many photos, the hull grown
# by a voxel and this share of its size on each side; on a flat backdrop a tenth of the photos may disagree with a
# voxel before it goes (the colour test is rougher than a mask).
MIN_SILHOUETTES = 4
HULL_MARGIN = 0.02
BACKDROP_DISAGREEING_SHARE = 0.1
# Up from the camera x axes needs them to spread: the middle eigenvalue (per camera) must exceed this.
RIGHT_AXES_MIN_SPREAD = 0.01

SceneType = Literal["object", "forward", "unbounded"]


@dataclass
class Cameras:
    names: list[str]
    frames: list[dict]                  # the poses stage's frame records, in the same order
    c2w: np.ndarray                     # [N,4,4] input frame
    intrinsics: list[Intrinsics]
    bounds: np.ndarray | None           # [N,2] LLFF near/far depths (input units) when every frame has them

    @property
    def origins(self) -> np.ndarray:
        return self.c2w[:, :3, 3]

    @property
    def view_dirs(self) -> np.ndarray:
        return -self.c2w[:, :3, 2] / np.linalg.norm(self.c2w[:, :3, 2], axis=1, keepdims=True)


@dataclass
class Points:
    xyz: np.ndarray                     # [P,3]
    obs_frame: np.ndarray               # [V] index into the frames of transforms.json
    obs_point: np.ndarray               # [V]

    @staticmethod
    def empty() -> "Points":
        return Points(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))


# ----------------------------------------------------------------------------------------------
# Reading the poses stage's output


def read_cameras(transforms: dict) -> Cameras:
    frames = transforms.get("frames") or []
    if len(frames) < 2:
        raise UserError(f"the poses hold {len(frames)} camera(s); at least 2 posed images are needed to normalise a scene")
    names, c2w, intrinsics = [], [], []
    for frame in frames:
        names.append(frame.get("name") or Path(frame["file_path"]).stem)
        c2w.append(np.asarray(frame["transform_matrix"], dtype=np.float64))
        intrinsics.append(Intrinsics.from_frame({**transforms, **frame}))  # per-frame values override shared ones
    bounds = None
    if all("near" in f and "far" in f for f in frames):
        bounds = np.array([[f["near"], f["far"]] for f in frames], dtype=np.float64)
    return Cameras(names, frames, np.stack(c2w), intrinsics, bounds)


def read_points(path: Path) -> Points:
    if not path.is_file():
        return Points.empty()
    with np.load(path) as data:
        xyz = np.asarray(data["xyz"], dtype=np.float64).reshape(-1, 3)
        obs_frame = np.asarray(data["obs_frame"], dtype=np.int64) if "obs_frame" in data else np.zeros(0, np.int64)
        obs_point = np.asarray(data["obs_point"], dtype=np.int64) if "obs_point" in data else np.zeros(0, np.int64)
    return Points(xyz, obs_frame, obs_point)


# ----------------------------------------------------------------------------------------------
# Frame: up, centre, heading


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _trimmed(vectors: np.ndarray, residual) -> np.ndarray:
    """Drops the vectors whose residual is far above the typical one (a few tilted or rotated shots)."""
    r = residual(vectors)
    keep = r <= max(3.0 * np.median(r), 0.05)
    return vectors[keep] if keep.sum() >= 2 else vectors


def camera_up(c2w: np.ndarray, inward: bool) -> tuple[np.ndarray, str]:
    """World up from the cameras, and which rule found it.

    People keep the horizon level far more than they keep the pitch fixed, so for inward captures up is
    the direction most nearly perpendicular to every camera's x (right) axis; that needs the right axes
    to spread, which an orbit gives. Forward captures (and narrow arcs) use the mean camera up axis.
    Either way the sign follows the mean camera up axis.
    """
    rights = _unit(c2w[:, :3, 0])
    ups = _unit(c2w[:, :3, 1])
    mean_up = _unit(ups.mean(axis=0))
    if inward:
        def smallest_axis(v):
            values, vectors = np.linalg.eigh(v.T @ v / len(v))
            return values, vectors[:, 0]
        values, axis = smallest_axis(rights)
        if values[1] > RIGHT_AXES_MIN_SPREAD:
            kept = _trimmed(rights, lambda v: np.abs(v @ axis))
            axis = smallest_axis(kept)[1]
            return (axis if axis @ mean_up >= 0 else -axis), "perpendicular to the cameras' right axes"
    kept = _trimmed(ups, lambda v: 1.0 - v @ mean_up)
    return _unit(kept.mean(axis=0)), "mean of the cameras' up axes"


def closest_point_of_axes(origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, float]:
    """The point nearest to all optical axes (least squares, down-weighting axes that pass far from it,
    so a few shots aimed elsewhere do not pull it), and how well the axes pin it down: the smallest
    eigenvalue of the normal matrix per camera (0 when the axes are parallel)."""
    weights = np.ones(len(origins))
    point = origins.mean(axis=0)
    conditioning = 0.0
    for _ in range(5):
        projectors = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]
        a = np.einsum("n,nij->ij", weights, projectors)
        b = np.einsum("n,nij,nj->i", weights, projectors, origins)
        conditioning = float(np.linalg.eigvalsh(a / weights.sum())[0])
        if conditioning < 1e-6:
            break
        point = np.linalg.solve(a, b)
        offsets = point - origins
        miss = np.linalg.norm(offsets - (offsets * dirs).sum(1, keepdims=True) * dirs, axis=1)
        weights = 1.0 / np.maximum(miss, np.median(miss) + 1e-12)
    return point, conditioning


def view_cone_deg(dirs: np.ndarray) -> float:
    """90th percentile of the angles between the viewing directions and their mean direction."""
    mean = dirs.mean(axis=0)
    if np.linalg.norm(mean) < 1e-9:
        return 180.0
    cos = np.clip(dirs @ _unit(mean), -1.0, 1.0)
    return float(np.degrees(np.percentile(np.arccos(cos), 90)))


def rotation_to_z_up(up: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """Rotation (rows = new axes in input coordinates) taking `up` to +z and `heading`'s horizontal part to +y."""
    z = _unit(up)
    y = heading - (heading @ z) * z
    if np.linalg.norm(y) < 1e-6:  # heading straight up or down: any horizontal direction will do
        y = np.cross(z, [1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.cross(z, [0.0, 1.0, 0.0])
    y = _unit(y)
    return np.stack([np.cross(y, z), y, z])


def horizontal_heading(dirs: np.ndarray, up: np.ndarray, first: int) -> np.ndarray:
    """The mean viewing direction's horizontal part when the cameras agree on one; otherwise (a full orbit,
    where the mean is near zero and noisy) camera `first`'s, so the frame stays well defined."""
    flat = dirs - (dirs @ up)[:, None] * up
    mean = flat.mean(axis=0)
    if np.linalg.norm(mean) >= 0.5 * np.linalg.norm(flat, axis=1).mean():
        return mean
    return flat[first] if np.linalg.norm(flat[first]) > 1e-6 else dirs[first]


# ----------------------------------------------------------------------------------------------
# Foreground


def covisible_counts(xyz: np.ndarray, cams: Cameras) -> np.ndarray:
    """How many cameras have each point in front of them and inside their image."""
    counts = np.zeros(len(xyz), dtype=np.int64)
    for c2w, k in zip(cams.c2w, cams.intrinsics):
        uv, depth = project(xyz, c2w, k)
        counts += (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= k.w) & (uv[:, 1] >= 0) & (uv[:, 1] <= k.h)
    return counts


def robust_box(points_rot: np.ndarray) -> np.ndarray:
    """[2,3] the box holding the points, ignoring strays: percentiles find the bulk, then the box grows
    to the farthest points within BOX_REACH of the bulk's size, so sparse edges (corners of a table)
    are kept while a few far-off points are not."""
    bulk = np.percentile(points_rot, BOX_PERCENTILES, axis=0)
    reach = BOX_REACH * (bulk[1] - bulk[0])
    near_bulk = np.all((points_rot >= bulk[0] - reach) & (points_rot <= bulk[1] + reach), axis=1)
    kept = points_rot[near_bulk]
    return np.stack([kept.min(axis=0), kept.max(axis=0)])


def frustum_box(c2w: np.ndarray, k: Intrinsics, near: float, far: float, rotation: np.ndarray) -> np.ndarray:
    """[2,3] axis-aligned box (in the rotated frame) around a camera's view between depths near and far."""
    corners = []
    for depth in (near, far):
        for u in (0.0, k.w):
            for v in (0.0, k.h):
                d_cam = np.array([(u - k.cx) / k.fl_x, -(v - k.cy) / k.fl_y, -1.0]) * depth
                corners.append(c2w[:3, :3] @ d_cam + c2w[:3, 3])
    corners = np.asarray(corners) @ rotation.T
    return np.stack([corners.min(0), corners.max(0)])


def min_half_fov(cams: Cameras) -> float:
    return min(min(math.atan2(k.w / 2, k.fl_x), math.atan2(k.h / 2, k.fl_y)) for k in cams.intrinsics)


# ----------------------------------------------------------------------------------------------
# Backdrop: how much of the photos show nothing (transparent, or one flat colour)


def _thumbnail(path: Path, mode: str) -> np.ndarray:
    """A small copy of an image; for masks ("L") an image with an alpha channel gives its alpha."""
    with Image.open(path) as im:
        im = im.getchannel("A") if mode == "L" and "A" in im.getbands() else im.convert(mode)
        im.thumbnail((BACKDROP_SIDE, BACKDROP_SIDE), Image.Resampling.BOX)
        return np.asarray(im)


@dataclass
class Backdrop:
    """How much of the photos shows nothing: from masks (transparent or masked-out pixels), or from one flat colour."""
    empty_fraction: float               # share of sampled pixels that show the empty backdrop
    from_masks: bool
    colour: np.ndarray | None           # the flat backdrop's RGB (0-255) where no masks say it
    photos_showing: float               # share of the sampled photos whose borders mostly show that colour
    still_textured: float = 0.0         # share of pixels with texture that is the same in every sampled photo


def measure_backdrop(cams: Cameras, poses_dir: Path) -> Backdrop | None:
    """The empty backdrop of a few evenly spread photos (small copies): where every one has a mask, its masked-out
    pixels; otherwise the one flat colour that dominates the image borders, and how many of the photos show it around
    their own borders (a white table in some photos and a dark room in others is no one colour). None when the
    images cannot be read."""
    picks = np.unique(np.linspace(0, len(cams.frames) - 1, min(BACKDROP_SAMPLES, len(cams.frames))).round().astype(int))
    frames = [cams.frames[i] for i in picks]
    try:
        if all(f.get("mask_path") for f in frames):
            empty = [_thumbnail(poses_dir / f["mask_path"], "L") < 128 for f in frames]
            return Backdrop(float(np.mean(np.concatenate([e.ravel() for e in empty]))), True, None, 1.0)
        images = [_thumbnail(poses_dir / f["file_path"], "RGB").astype(np.int32) for f in frames]
    except (OSError, ValueError):
        return None
    borders = [_border(im) for im in images]
    colour = _flat_colour(np.concatenate(borders))
    empty = [np.abs(im - colour).max(axis=-1) <= BACKDROP_TOLERANCE for im in images]
    showing = [np.mean(np.abs(b - colour).max(axis=-1) <= BACKDROP_TOLERANCE) >= BACKDROP_BORDER_SHARE for b in borders]
    return Backdrop(float(np.mean(np.concatenate([e.ravel() for e in empty]))), False, colour, float(np.mean(showing)),
                    still_textured_share(images))


def _border(image: np.ndarray) -> np.ndarray:
    """[M,3] the pixels of an image's outer two rows and columns."""
    return np.concatenate([image[:2].reshape(-1, 3), image[-2:].reshape(-1, 3), image[:, :2].reshape(-1, 3),
                           image[:, -2:].reshape(-1, 3)])


def _flat_colour(pixels: np.ndarray) -> np.ndarray:
    """The colour that dominates these pixels: the median of the most common 32-level bin."""
    bins = pixels // 32
    keys, counts = np.unique(bins, axis=0, return_counts=True)
    return np.median(pixels[(bins == keys[counts.argmax()]).all(axis=1)], axis=0)


def own_backdrops(cams: Cameras, poses_dir: Path) -> tuple[np.ndarray, float] | None:
    """([N,3] RGB in [0, 1], share): each photo's own backdrop colour, the flat colour that dominates its border, and
    the share of the photos whose border shows it on at least BACKDROP_BORDER_SHARE of its pixels: an object
    photographed on a white table from one side and before a dark room from the other, each photo on one flat colour
    of its own. None when the images cannot be read."""
    colours, flat = [], []
    try:
        for frame in cams.frames:
            border = _border(_thumbnail(poses_dir / frame["file_path"], "RGB").astype(np.int32))
            colour = _flat_colour(border)
            colours.append(colour / 255.0)
            flat.append(np.mean(np.abs(border - colour).max(axis=-1) <= BACKDROP_TOLERANCE) >= BACKDROP_BORDER_SHARE)
    except (OSError, ValueError):
        return None
    return np.asarray(colours), float(np.mean(flat))


def masked_out_colours(cams: Cameras, poses_dir: Path) -> np.ndarray | None:
    """[N,3] RGB in [0, 1]: each masked photo's median colour outside its mask (small copies; where a mask leaves no
    pixel out, its border's median). None when an image or mask cannot be read."""
    colours = []
    try:
        for frame in cams.frames:
            image = _thumbnail(poses_dir / frame["file_path"], "RGB").astype(np.float64)
            mask = _thumbnail(poses_dir / frame["mask_path"], "L")
            if mask.shape != image.shape[:2]:
                mask = np.asarray(Image.fromarray(mask).resize((image.shape[1], image.shape[0]), Image.Resampling.BOX))
            outside = image[mask < 128]
            colours.append(np.median(outside if len(outside) else _border(image), axis=0) / 255.0)
    except (OSError, ValueError):
        return None
    return np.asarray(colours)


def still_textured_share(images: list[np.ndarray]) -> float:
    """The share of pixels that show texture (a local contrast of STILL_TEXTURE_LEVELS or more) and look the same
    (within BACKDROP_TOLERANCE) in every one of these photos, taken from around the scene: a still background behind
    an object that turned, not the scene the cameras moved around. 0 where the photos differ in size."""
    if len(images) < 3 or len({im.shape for im in images}) > 1:
        return 0.0
    stack = np.stack(images).astype(np.int16)
    still = (stack.max(axis=0) - stack.min(axis=0)).max(axis=-1) <= BACKDROP_TOLERANCE
    grey = np.median(stack, axis=0).mean(axis=-1).astype(np.float32)
    contrast = cv2.dilate(grey, np.ones((3, 3), np.uint8)) - cv2.erode(grey, np.ones((3, 3), np.uint8))
    return float(np.mean(still & (contrast >= STILL_TEXTURE_LEVELS)))


# ----------------------------------------------------------------------------------------------
# Near / far


def points_seen_by_frame(points: Points, cams: Cameras) -> list[np.ndarray]:
    """Indices of the points each frame sees: its SfM observations, or (without any) the points inside its image."""
    if len(points.obs_frame):
        order = np.argsort(points.obs_frame, kind="stable")
        splits = np.searchsorted(points.obs_frame[order], np.arange(len(cams.names) + 1))
        return [points.obs_point[order[splits[i]:splits[i + 1]]] for i in range(len(cams.names))]
    seen = []
    for c2w, k in zip(cams.c2w, cams.intrinsics):
        uv, depth = project(points.xyz, c2w, k)
        inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= k.w) & (uv[:, 1] >= 0) & (uv[:, 1] <= k.h)
        seen.append(np.flatnonzero(inside))
    return seen


def near_far_from_points(xyz: np.ndarray, c2w: np.ndarray, k: Intrinsics) -> tuple[float, float] | None:
    """Near from depths along the viewing axis, far from distances along the rays, so [near, far] brackets
    the points whichever of the two a sampler measures (depth <= distance)."""
    _, depth = project(xyz, c2w, k)
    in_front = depth > 0
    if in_front.sum() < MIN_POINTS_PER_IMAGE:
        return None
    distance = np.linalg.norm(xyz[in_front] - c2w[:3, 3], axis=1)
    near = np.percentile(depth[in_front], NEAR_FAR_PERCENTILES[0]) * (1 - NEAR_FAR_MARGIN)
    far = np.percentile(distance, NEAR_FAR_PERCENTILES[1]) * (1 + NEAR_FAR_MARGIN)
    return float(near), float(far)


def near_far_from_box(c2w: np.ndarray, box: np.ndarray) -> tuple[float, float]:
    """Near: the camera's distance to the box (a small value when it is inside); far: its farthest corner."""
    origin = c2w[:3, 3]
    outside = np.maximum(np.maximum(box[0] - origin, origin - box[1]), 0.0)
    corners = np.array([[box[i][0], box[j][1], box[l][2]] for i in (0, 1) for j in (0, 1) for l in (0, 1)])
    far = np.linalg.norm(corners - origin, axis=1).max()
    near = max(float(np.linalg.norm(outside)), 0.01 * far)
    return near, float(far)


# ----------------------------------------------------------------------------------------------
# The whole decision


def normalize_scene(transforms: dict, points: Points, options: SceneOptions, poses_dir: Path | None = None,
                    path_prefix: str = "poses/") -> dict:
    """Everything that goes into scene.json, from the poses stage's transforms and points.

    `poses_dir` is where the frames' image and mask paths are relative to (None: do not look at the
    photos); `path_prefix` is put before those paths in the output (relative to the scene's output folder).
    """
    cams = read_cameras(transforms)
    n = len(cams.names)
    xyz = points.xyz
    has_points = len(xyz) >= MIN_POINTS
    # Which points each camera sees, found once in the input frame (where the cameras are): the box and near/far use it.
    seen = points_seen_by_frame(points, cams) if has_points else None
    dirs = cams.view_dirs
    cone = view_cone_deg(dirs)
    # Near the threshold a few degrees of pose noise or one more photo would flip the model, and a capture that
    # is only almost forward (a facade shot from an arc) puts views where NDC's frustum has nothing: so the band
    # around it types the scene for the inward model, which holds any spread, says it did, and keeps the forward
    # block so that the fit can try NDC against it (plenoxels/planning/model_trial.py).
    borderline = abs(cone - options.forward_max_cone_deg) <= options.borderline_deg
    looks_forward = cone <= options.forward_max_cone_deg - (options.borderline_deg if borderline else 0.0)
    measured: dict = {"frames": n, "points": int(len(xyz)), "view_cone_deg": round(cone, 2), "borderline": borderline}
    reasons = [f"90% of viewing directions lie within {cone:.1f} deg of their mean "
               + (f"(<= {options.forward_max_cone_deg:g}): the cameras face one way" if looks_forward
                  else f"(> {options.forward_max_cone_deg:g}): the cameras look inward from around the scene"
                  if not borderline else
                  f"(within {options.borderline_deg:g} of {options.forward_max_cone_deg:g}, borderline): modelled as "
                  "seen from around the scene, which holds where the forward model's single frustum would not "
                  "(the fit tries NDC against it; normalize.scene_type=forward sets NDC)")]
    family_forward = options.scene_type == "forward" or (options.scene_type == "auto" and looks_forward)

    up, up_rule = camera_up(cams.c2w, inward=not looks_forward)
    axes_point, axes_conditioning = closest_point_of_axes(cams.origins, dirs)
    first_by_name = min(range(n), key=lambda i: cams.names[i])
    rotation = rotation_to_z_up(up, horizontal_heading(dirs, up, first_by_name))
    measured.update({"up_in_input_frame": up.round(6).tolist(), "up_from": up_rule,
                     "axes_closest_point": axes_point.round(6).tolist(),
                     "axes_conditioning": round(axes_conditioning, 6)})
    if axes_conditioning < 1e-3:  # parallel axes meet nowhere: stand in a point in front of the cameras
        axes_point = cams.origins.mean(axis=0) + dirs.mean(axis=0) * np.linalg.norm(np.ptp(cams.origins, axis=0))

    camera_distance = float(np.median(np.linalg.norm(cams.origins - axes_point, axis=1)))
    covisible = covisible_counts(xyz, cams) if has_points else np.zeros(0, dtype=np.int64)
    foreground = covisible >= max(2, COVISIBLE_SHARE * n)
    if not family_forward and has_points:
        foreground &= np.linalg.norm(xyz - axes_point, axis=1) < camera_distance
    measured["foreground_points"] = int(foreground.sum())

    reference_input = None
    if family_forward:
        reference_input = _reference_camera(cams, dirs, up)
        if foreground.sum() >= MIN_POINTS:
            box_rot, box_from = robust_box(xyz[foreground] @ rotation.T), "sparse points seen by most cameras"
        else:
            near, far, box_from = _forward_depth_guess(cams)
            box_rot = frustum_box(reference_input, cams.intrinsics[0], near, far, rotation)
    elif foreground.sum() >= MIN_POINTS:
        box_rot, box_from = robust_box(xyz[foreground] @ rotation.T), "sparse points seen by most cameras"
        box_rot, box_from = _hold_what_cameras_aim_at(box_rot, box_from, xyz, cams, seen, rotation, axes_point,
                                                      camera_distance, measured)
    else:
        # What every camera sees at the point the axes meet: the region the capture was aimed at.
        half = camera_distance * math.tan(min_half_fov(cams))
        centre_rot = rotation @ axes_point
        box_rot = np.stack([centre_rot - half, centre_rot + half])
        box_from = "cameras: the view of the narrowest camera where the optical axes meet"
    backdrop = measure_backdrop(cams, poses_dir) if poses_dir is not None and not looks_forward else None
    if backdrop is not None:
        measured["still_textured_pixels"] = round(backdrop.still_textured, 4)
        if backdrop.still_textured >= STILL_TEXTURED_SHARE:
            raise UserError(f"{backdrop.still_textured:.0%} of the photos' pixels show the same texture at the same "
                            "place in every sampled photo: a still background behind a turning object (a turntable in "
                            "a room), which no model of one scene shows; give a mask of the object for each photo (a "
                            "masks/ folder beside the photos, white on the object, each named like its photo)")
    # Each photo's own backdrop colour, where the photos show no one colour but might each show one of their own.
    own = None
    if (not looks_forward and backdrop is not None and not backdrop.from_masks
            and backdrop.photos_showing < BACKDROP_MIN_PHOTOS and backdrop.empty_fraction >= options.object_min_empty_fraction):
        own = own_backdrops(cams, poses_dir)
    held_out = held_out_frames(cams, options)
    if not family_forward and poses_dir is not None and options.silhouette_box:
        box_rot, box_from = _silhouette_box(cams, [i for i in range(n) if i not in held_out], poses_dir, backdrop,
                                            rotation, axes_point, camera_distance, (box_rot, box_from), options,
                                            measured, own)
    measured["foreground_from"] = box_from

    # Centre on the box rather than on the axes' meeting point: the box was found around that point, and
    # centring on it wastes none of the unit cube when the foreground sits off the axes (a table below them).
    centre = rotation.T @ box_rot.mean(axis=0)
    half_size = float(np.max(box_rot[1] - box_rot[0]) / 2)
    if half_size <= 0:
        raise UserError("the cameras and points give a foreground of zero size; check the poses stage's output")
    scale = 1.0 / ((1.0 + options.margin) * half_size)
    world_from_input = np.eye(4)
    world_from_input[:3, :3] = scale * rotation
    world_from_input[:3, 3] = -scale * rotation @ centre
    input_from_world = np.linalg.inv(world_from_input)
    foreground_box = (box_rot - rotation @ centre) * scale

    c2w_world = np.einsum("ij,njk->nik", world_from_input, cams.c2w)
    c2w_world[:, :3, :3] /= scale
    xyz_world = xyz @ world_from_input[:3, :3].T + world_from_input[:3, 3]
    measured["camera_distance"] = round(camera_distance * scale, 4)

    # ---- scene type -------------------------------------------------------------------------------
    thresholds = {"forward_max_cone_deg": options.forward_max_cone_deg, "beyond_factor": options.beyond_factor,
                  "unbounded_min_beyond_fraction": options.unbounded_min_beyond_fraction,
                  "object_min_empty_fraction": options.object_min_empty_fraction,
                  "min_points": MIN_POINTS}
    if looks_forward:
        detected: SceneType = "forward"
    else:
        detected = _inward_type(xyz_world, has_points, backdrop, options, measured, reasons,
                                own[1] if own is not None else None)
    overridden = options.scene_type != "auto"
    scene_type = options.scene_type if overridden else detected
    if overridden:
        reasons.append(f"scene type set to {scene_type} by normalize.scene_type (detected: {detected})")

    # ---- near / far ------------------------------------------------------------------------------------
    near_far, near_far_from = [], {"points": 0, "llff bounds": 0, "foreground box": 0}
    for i in range(n):
        k = cams.intrinsics[i]
        estimate = near_far_from_points(xyz_world[seen[i]], c2w_world[i], k) if seen is not None else None
        source = "points"
        if estimate is None and cams.bounds is not None:
            estimate = (float(cams.bounds[i, 0] * scale * (1 - NEAR_FAR_MARGIN)),
                        float(cams.bounds[i, 1] * scale * (1 + NEAR_FAR_MARGIN)))
            source = "llff bounds"
        if estimate is None:
            estimate, source = near_far_from_box(c2w_world[i], foreground_box), "foreground box"
        near_far.append(estimate)
        near_far_from[source] += 1
    measured["near_far_from"] = {k: v for k, v in near_far_from.items() if v}

    # ---- frames and split -----------------------------------------------------------------------------
    masked_out = None
    if (options.masked_backdrop == "own" and poses_dir is not None and cams.frames
            and all(f.get("mask_path") for f in cams.frames)):
        masked_out = masked_out_colours(cams, poses_dir)
    frames, train_rank = [], 0
    for i in sorted(range(n), key=lambda i: cams.names[i]):
        k, frame = cams.intrinsics[i], cams.frames[i]
        split = "test" if i in held_out else "train" if train_rank % options.train_every == 0 else "unused"
        train_rank += i not in held_out
        frames.append({
            "name": cams.names[i], "file_path": path_prefix + frame["file_path"],
            "mask_path": path_prefix + frame["mask_path"] if frame.get("mask_path") else None,
            "transform_matrix": c2w_world[i].tolist(), "fl_x": k.fl_x, "fl_y": k.fl_y, "cx": k.cx, "cy": k.cy,
            "w": k.w, "h": k.h, "near": near_far[i][0], "far": near_far[i][1],
            "split": split,
        })
        if measured.get("own_backdrops") and scene_type == "object":
            frames[-1]["backdrop"] = [round(float(c), 4) for c in own[0][i]]
        elif masked_out is not None:
            frames[-1]["backdrop"] = [round(float(c), 4) for c in masked_out[i]]

    scene = {
        "type": scene_type, "detected": detected, "reasons": reasons, "measured": measured,
        "thresholds": thresholds, "overridden": overridden,
        "world_from_input": world_from_input.tolist(), "input_from_world": input_from_world.tolist(),
        "scale": scale, "foreground": {"min": foreground_box[0].tolist(), "max": foreground_box[1].tolist()},
        "frames": frames,
    }
    if not family_forward and has_points:
        surroundings, growth = surroundings_box(xyz_world, foreground_box, c2w_world[:, :3, 3], options.beyond_factor)
        scene["surroundings"] = {"min": surroundings[0].tolist(), "max": surroundings[1].tolist()}
        measured["surroundings_growth"] = growth
    if scene_type == "forward" or (borderline and not overridden):
        # A borderline spread keeps the forward block too, so that the fit can try NDC against the inward model
        # (plenoxels/planning/model_trial.py).
        if reference_input is None:
            reference_input = _reference_camera(cams, dirs, up)
        reference = world_from_input @ reference_input
        reference[:3, :3] /= scale
        scene["forward"] = {"reference_c2w": reference.tolist(),
                            **_forward_depths(xyz_world if has_points else None, reference, cams, scale, foreground_box)}
    return scene


def surroundings_box(xyz_world: np.ndarray, foreground_box: np.ndarray, camera_origins: np.ndarray,
                     beyond_factor: float) -> tuple[np.ndarray, float]:
    """([2,3] box, growth): what a bounded grid of a room holds. The foreground box is what most cameras see; the
    walls and floor around it, seen by fewer, lie outside it, and a background sphere shows them without the parallax
    the cameras see between them (fox: the wall beside the head, 4.7 dB lost in one held-out view). So the box grows
    from the foreground's toward the robust box of the sparse points within `beyond_factor` of it, by the largest
    share (in steps of SURROUNDINGS_STEP) that leaves every camera outside: a grid around its cameras fills with
    floaters in front of them. Growth 0: the foreground box as it is (a camera stands at its edge, or no points lie
    around it)."""
    near = xyz_world[np.abs(xyz_world).max(axis=1) < beyond_factor]
    if len(near) < MIN_POINTS:
        return foreground_box, 0.0
    reach = robust_box(near)
    reach = np.stack([np.minimum(reach[0], foreground_box[0]), np.maximum(reach[1], foreground_box[1])])
    for growth in np.arange(1.0, 0.0, -SURROUNDINGS_STEP):
        box = foreground_box + growth * (reach - foreground_box)
        inside = np.all((camera_origins > box[0]) & (camera_origins < box[1]), axis=1)
        if not inside.any():
            return box, round(float(growth), 3)
    return foreground_box, 0.0


def aimed_points(xyz: np.ndarray, seen: list[np.ndarray], cams: Cameras) -> np.ndarray:
    """[M,3] what each camera is aimed at: the point on its optical axis at the median depth of the sparse points it
    sees in the middle AIM_SHARE of its image's width and height (cameras with fewer than MIN_POINTS_PER_IMAGE such
    points are left out)."""
    aimed = []
    for i, (c2w, k) in enumerate(zip(cams.c2w, cams.intrinsics)):
        uv, depth = project(xyz[seen[i]], c2w, k)
        central = ((depth > 0) & (np.abs(uv[:, 0] - k.cx) <= AIM_SHARE * k.w / 2)
                   & (np.abs(uv[:, 1] - k.cy) <= AIM_SHARE * k.h / 2))
        if central.sum() >= MIN_POINTS_PER_IMAGE:
            aimed.append(cams.origins[i] + float(np.median(depth[central])) * cams.view_dirs[i])
    return np.asarray(aimed, dtype=np.float64).reshape(-1, 3)


def _hold_what_cameras_aim_at(box_rot: np.ndarray, box_from: str, xyz: np.ndarray, cams: Cameras, seen: list[np.ndarray],
                              rotation: np.ndarray, axes_point: np.ndarray, camera_distance: float,
                              measured: dict) -> tuple[np.ndarray, str]:
    """The foreground box grown to hold what each camera circling an object is aimed at. The box of the points most
    cameras see keeps their bulk: a floor's many points outvote the few on a can standing on it, the can falls partly
    outside the box, and a grid there cannot show it in the views aimed at it. What a camera is aimed at within
    camera_distance of where the optical axes meet is the object (aimed_points); where AIM_MIN_SHARE of the cameras
    or more are aimed outside the box, it grows to AIM_MARGIN of its size beyond each of their points."""
    aimed = aimed_points(xyz, seen, cams)
    aimed = aimed[np.linalg.norm(aimed - axes_point, axis=1) < camera_distance] @ rotation.T
    outside = ~np.all((aimed >= box_rot[0]) & (aimed <= box_rot[1]), axis=1)
    measured["aimed_outside_box"] = f"{int(outside.sum())}/{len(aimed)}"
    if not outside.any() or outside.mean() < AIM_MIN_SHARE:
        return box_rot, box_from
    margin = AIM_MARGIN * (box_rot[1] - box_rot[0]).max()
    grown = np.stack([np.minimum(box_rot[0], aimed[outside].min(axis=0) - margin),
                      np.maximum(box_rot[1], aimed[outside].max(axis=0) + margin)])
    return grown, f"{box_from}, grown to hold what {int(outside.sum())} of {len(aimed)} cameras are aimed at"


def held_out_frames(cams: Cameras, options: SceneOptions) -> set[int]:
    """The frames held out for scoring: a dataset's own held-out split where it names its splits (NeRF synthetic
    train/val/test), else every holdout_every-th by sorted name."""
    if any(f.get("split") for f in cams.frames):
        return {i for i, f in enumerate(cams.frames) if f.get("split") == "test"}
    order = sorted(range(len(cams.names)), key=lambda i: cams.names[i])
    return {i for rank, i in enumerate(order) if options.holdout_every > 0 and rank % options.holdout_every == 0}


def _silhouette_box(cams: Cameras, train: list[int], poses_dir: Path, backdrop: Backdrop | None,
                    rotation: np.ndarray, axes_point: np.ndarray, camera_distance: float,
                    found: tuple[np.ndarray, str], options: SceneOptions, measured: dict,
                    own: tuple[np.ndarray, float] | None = None) -> tuple[np.ndarray, str]:
    """The box (rotated frame) the training photos' silhouettes give (stages/framing/visual_hull.py) and what it came from:
    the box of what some photo sees of their masks' visual hull, or on a flat backdrop the same of what is not the
    backdrop, joined with the box `found` otherwise (colour alone may miss a part of the backdrop's colour, so the
    points keep their say); `found` where the photos carry neither, or their silhouettes do not bound the object (cut
    by the photos' edges). A box from masks that cuts what a photo's mask shows can only come from wrong masks or
    poses: that stops here."""
    flat = (backdrop is not None and not backdrop.from_masks and backdrop.empty_fraction >= options.object_min_empty_fraction
            and backdrop.photos_showing >= BACKDROP_MIN_PHOTOS)
    colours = backdrop.colour if flat else None
    if own is not None and own[1] >= BACKDROP_MIN_PHOTOS:  # each photo on a flat colour of its own
        colours = np.round(own[0][train] * 255)
    silhouettes = read_silhouettes([cams.names[i] for i in train], [cams.frames[i] for i in train], cams.c2w[train],
                                   [cams.intrinsics[i] for i in train], poses_dir, colours)
    if silhouettes is None or len(silhouettes) < MIN_SILHOUETTES:
        return found
    from_masks = silhouettes.source == "masks"
    hull = carve(silhouettes, rotation, rotation @ axes_point, camera_distance,
                 DISAGREEING_SHARE if from_masks else BACKDROP_DISAGREEING_SHARE)
    if hull is None:
        if from_masks:
            raise UserError(f"the masks of the {len(silhouettes)} training photos share no region of space: their poses "
                            "or their masks are wrong (check that each mask belongs to its photo, white on the object)")
        return found
    measured["visual_hull"] = {"photos": len(silhouettes), "source": silhouettes.source, "voxel": round(hull.voxel, 6),
                               "voxels": hull.voxels, "levels": hull.levels, "bounded": hull.bounded,
                               "box": hull.box.round(6).tolist()}
    if not hull.bounded:
        return found  # the photos' edges cut the silhouettes, so they do not say where the object ends
    shown = shown_box(silhouettes, hull, rotation)
    measured["visual_hull"]["box_shown"] = shown.round(6).tolist()
    grow = hull.voxel + HULL_MARGIN * (shown[1] - shown[0])
    box = np.stack([shown[0] - grow, shown[1] + grow])
    if not from_masks:
        box = np.stack([np.minimum(box[0], found[0][0]), np.maximum(box[1], found[0][1])])
        return box, (f"visual hull of {len(silhouettes)} training photos' silhouettes on their flat backdrop, joined "
                     f"with the box of the {found[1]}")
    cut = cut_photos(silhouettes, box, rotation)
    if cut:
        names = sorted(cut, key=lambda name: -cut[name])
        raise UserError(f"the object box the training photos' masks agree on cuts what {len(cut)} photo(s) show "
                        f"({', '.join(f'{name}: {cut[name]:.0%} of its mask' for name in names[:5])}"
                        f"{' and more' if len(names) > 5 else ''}); their masks or poses are wrong: fix those masks, "
                        "or leave those photos out")
    return box, f"visual hull of {len(silhouettes)} training photos' masks"


def _reference_camera(cams: Cameras, dirs: np.ndarray, up: np.ndarray) -> np.ndarray:
    """The average pose: at the mean camera centre, looking along the mean viewing direction, level with `up`."""
    forward = _unit(dirs.mean(axis=0))
    right = _unit(np.cross(forward, up))
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(right, forward), -forward, cams.origins.mean(axis=0)
    return c2w


def _forward_depth_guess(cams: Cameras) -> tuple[float, float, str]:
    """Depth range of a forward capture without points: LLFF bounds when the frames carry them, otherwise
    a guess from the spread of the cameras (scenes are usually several baselines away)."""
    if cams.bounds is not None:
        return float(cams.bounds[:, 0].min()), float(np.percentile(cams.bounds[:, 1], 90)), "llff bounds"
    baseline = float(np.linalg.norm(np.ptp(cams.origins, axis=0))) or 1.0
    return 2.0 * baseline, 20.0 * baseline, "guess: 2 to 20 camera baselines in front of the cameras"


def _forward_depths(xyz_world: np.ndarray | None, reference: np.ndarray, cams: Cameras, scale: float,
                    box: np.ndarray) -> dict:
    """NDC's near plane and the far depth, along the reference camera's axis (normalised units). All points
    count, not only the foreground: the floor just in front of the cameras, seen by few of them, is what
    sets the near plane."""
    if xyz_world is not None:
        depth = -((xyz_world - reference[:3, 3]) @ reference[:3, 2])
        depth = depth[depth > 0]
        if len(depth) >= MIN_POINTS:
            return {"near": float(np.percentile(depth, NEAR_FAR_PERCENTILES[0]) * (1 - NEAR_FAR_MARGIN)),
                    "far": float(np.percentile(depth, NEAR_FAR_PERCENTILES[1]) * (1 + NEAR_FAR_MARGIN)),
                    "from": "sparse points"}
    if cams.bounds is not None:
        return {"near": float(cams.bounds[:, 0].min() * scale * (1 - NEAR_FAR_MARGIN)),
                "far": float(cams.bounds[:, 1].max() * scale * (1 + NEAR_FAR_MARGIN)), "from": "llff bounds"}
    near, far = near_far_from_box(reference, box)
    return {"near": near, "far": far, "from": "foreground box"}


def _inward_type(xyz_world: np.ndarray, has_points: bool, backdrop: Backdrop | None, options: SceneOptions,
                 measured: dict, reasons: list[str], own_flat: float | None = None) -> SceneType:
    """Object or unbounded: is there a real background beyond the foreground? Masks of the object on every photo say
    there is none the fit should model. Otherwise unbounded when either the points or the pixels say so (a flat
    backdrop must be one colour behind most photos); object only when what can be measured says the surroundings
    are empty."""
    background = []
    if has_points:
        beyond = float(np.mean(np.abs(xyz_world).max(axis=1) > options.beyond_factor))
        measured["beyond_fraction"] = round(beyond, 4)
        far_away = beyond >= options.unbounded_min_beyond_fraction
        background.append(far_away)
        reasons.append(f"{beyond:.0%} of the sparse points lie beyond {options.beyond_factor:g}x the foreground "
                       f"({'>=' if far_away else '<'} {options.unbounded_min_beyond_fraction:.0%})")
    else:
        reasons.append("no sparse points to measure what lies beyond the foreground")
    if backdrop is not None:
        empty = backdrop.empty_fraction
        measured["empty_pixel_fraction"] = round(empty, 4)
        scenery = empty < options.object_min_empty_fraction
        if backdrop.from_masks and not scenery:
            measured["masked"] = True
            reasons.append(f"every photo has a mask of the object ({empty:.0%} of sampled pixels outside it): what "
                           "lies outside the masks is trained as empty, so the grid holds the object alone")
            return "object"
        reasons.append(f"{empty:.0%} of sampled pixels show an empty backdrop, transparent or one flat colour "
                       f"({'<' if scenery else '>='} {options.object_min_empty_fraction:.0%}"
                       f"{': real surroundings fill the photos' if scenery else ''})")
        if not backdrop.from_masks:
            measured["backdrop_photos_showing"] = round(backdrop.photos_showing, 3)
            if not scenery and backdrop.photos_showing < BACKDROP_MIN_PHOTOS:
                if own_flat is not None and own_flat >= BACKDROP_MIN_PHOTOS:
                    measured["own_backdrops"] = round(own_flat, 3)
                    reasons.append(f"only {backdrop.photos_showing:.0%} of the sampled photos show that colour around "
                                   f"most of their borders, but {own_flat:.0%} of the photos show one flat colour of "
                                   "their own there: each photo's own colour is trained behind the grid (scene.json's "
                                   "frame `backdrop`)")
                else:
                    scenery = True
                    reasons.append(f"but only {backdrop.photos_showing:.0%} of the sampled photos show that colour "
                                   f"around most of their borders (< {BACKDROP_MIN_PHOTOS:.0%}): the backdrop differs "
                                   "between photos, so it is not empty and a background model shows it")
        background.append(scenery)
    if not background:
        reasons.append("nothing shows the surroundings are empty, so a background is assumed")
        return "unbounded"
    return "unbounded" if any(background) else "object"
