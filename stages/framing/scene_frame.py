"""The scene frame: from posed cameras and sparse points, one world frame (z up, foreground in the unit cube),
the scene type, near/far per image and the train/held-out split, i.e. everything in normalize/scene.json.

The scene type decides what the fit models:
- `forward`: every camera looks the same way (viewing directions within a narrow cone), so the scene
  is a frustum in front of them; the fit uses NDC around the `forward.reference_c2w` camera.
- `object`: cameras look inward at a foreground and little lies beyond it (few sparse points far from
  it, or an empty backdrop: transparent pixels or one flat colour).
- `unbounded`: cameras look inward but there is a real background (many points far beyond the
  foreground, or photos with no empty backdrop); the fit needs a background model."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from plenoxels.core.errors import UserError
from stages.framing.backdrop import (BACKDROP_MIN_PHOTOS, Backdrop, STILL_TEXTURED_SHARE, from_nearest_cameras,
                                     masked_out_colours, measure_backdrop, own_backdrops, shows_backdrop_outside_mask)
from stages.framing.depths import (NEAR_FAR_MARGIN, forward_depth_guess, forward_depths, near_far_from_box,
                                   near_far_from_points)
from stages.framing.foreground import (COVISIBLE_SHARE, hold_what_cameras_aim_at, silhouette_box, covisible_counts,
                                       frustum_box, min_half_fov, robust_box, surroundings_box)
from stages.framing.options import SceneOptions
from stages.framing.orientation import (reference_camera, camera_up, closest_point_of_axes, horizontal_heading,
                                        rotation_to_z_up, view_cone_deg)
from stages.framing.sightings import Cameras, MIN_POINTS, Points, points_seen_by_frame, read_cameras


SceneType = Literal["object", "forward", "unbounded"]



@dataclass
class Aim:
    """Where the capture points, in the input frame: the turn that makes it z up and the point the optical axes meet."""
    rotation: np.ndarray       # [3, 3] input frame -> z-up frame (before centring and scaling)
    up: np.ndarray             # the cameras' own up axis in the input frame (a forward reference is level with it)
    axes_point: np.ndarray     # where the cameras' optical axes come closest
    camera_distance: float     # the cameras' median distance from it


@dataclass
class Spread:
    """How widely the viewing directions spread, and what that makes of the capture."""
    cone_deg: float
    borderline: bool           # near the forward limit: typed inward, with the forward block kept for the fit's trial
    looks_forward: bool
    reason: str


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
    spread = viewing_spread(cams, options)
    measured: dict = {"frames": n, "points": int(len(xyz)), "view_cone_deg": round(spread.cone_deg, 2),
                      "borderline": spread.borderline}
    reasons = [spread.reason]
    family_forward = options.scene_type == "forward" or (options.scene_type == "auto" and spread.looks_forward)

    aim = aim_of(cams, spread.looks_forward, measured, gravity_of(transforms))
    reference_input = reference_camera(cams, cams.view_dirs, aim.up) if family_forward else None
    box_rot, box_from = first_box(cams, xyz, seen, family_forward, aim, reference_input, measured)
    backdrop, own = backdrops(cams, poses_dir, spread.looks_forward, options, measured)
    held_out = held_out_frames(cams, options)
    if not family_forward and poses_dir is not None and options.silhouette_box:
        box_rot, box_from = silhouette_box(cams, [i for i in range(n) if i not in held_out], poses_dir, backdrop,
                                           aim.rotation, aim.axes_point, aim.camera_distance, (box_rot, box_from),
                                           options, measured, own)
    measured["foreground_from"] = box_from

    # Centre on the box rather than on the axes' meeting point: the box was found around that point, and
    # centring on it wastes none of the unit cube when the foreground sits off the axes (a table below them).
    rotation = aim.rotation
    centre = rotation.T @ box_rot.mean(axis=0)
    half_size = float(np.max(box_rot[1] - box_rot[0]) / 2)
    if half_size <= 0:
        raise UserError("the cameras and points give a foreground of zero size; check the poses stage's output")
    scale = 1.0 / ((1.0 + options.margin) * half_size)
    world_from_input = np.eye(4)
    world_from_input[:3, :3] = scale * rotation
    world_from_input[:3, 3] = -scale * rotation @ centre
    foreground_box = (box_rot - rotation @ centre) * scale
    c2w_world = np.einsum("ij,njk->nik", world_from_input, cams.c2w)
    c2w_world[:, :3, :3] /= scale
    xyz_world = xyz @ world_from_input[:3, :3].T + world_from_input[:3, 3]
    measured["camera_distance"] = round(aim.camera_distance * scale, 4)

    detected: SceneType = "forward" if spread.looks_forward else _inward_type(
        xyz_world, has_points, backdrop, options, measured, reasons, own[1] if own is not None else None)
    overridden = options.scene_type != "auto"
    scene_type = options.scene_type if overridden else detected
    if overridden:
        reasons.append(f"scene type set to {scene_type} by normalize.scene_type (detected: {detected})")

    near_far = near_far_per_frame(cams, xyz_world, seen, c2w_world, scale, foreground_box, measured)
    own_colours = own[0] if measured.get("own_backdrops") and scene_type == "object" else None
    scene = {
        "type": scene_type, "detected": detected, "reasons": reasons, "measured": measured,
        "thresholds": {"forward_max_cone_deg": options.forward_max_cone_deg, "beyond_factor": options.beyond_factor,
                       "unbounded_min_beyond_fraction": options.unbounded_min_beyond_fraction,
                       "object_min_empty_fraction": options.object_min_empty_fraction, "min_points": MIN_POINTS},
        "overridden": overridden,
        "world_from_input": world_from_input.tolist(), "input_from_world": np.linalg.inv(world_from_input).tolist(),
        "scale": scale, "foreground": {"min": foreground_box[0].tolist(), "max": foreground_box[1].tolist()},
        "frames": scene_frames(cams, held_out, near_far, c2w_world, options, poses_dir, path_prefix, own_colours),
        **({"georeference": transforms["georeference"]} if "georeference" in transforms else {}),
    }
    if not family_forward and has_points:
        surroundings, growth = surroundings_box(xyz_world, foreground_box, c2w_world[:, :3, 3], options.beyond_factor)
        scene["surroundings"] = {"min": surroundings[0].tolist(), "max": surroundings[1].tolist()}
        measured["surroundings_growth"] = growth
    if scene_type == "forward" or (spread.borderline and not overridden):
        # A borderline spread keeps the forward block too, so that the fit can try NDC against the inward model
        # (plenoxels/planning/model_trial.py).
        if reference_input is None:
            reference_input = reference_camera(cams, cams.view_dirs, aim.up)
        reference = world_from_input @ reference_input
        reference[:3, :3] /= scale
        scene["forward"] = {"reference_c2w": reference.tolist(),
                            **forward_depths(xyz_world if has_points else None, reference, cams, scale, foreground_box)}
    return scene


def viewing_spread(cams: Cameras, options: SceneOptions) -> Spread:
    """The spread of the viewing directions against the forward limit.

    Near the limit a few degrees of pose noise or one more photo would flip the model, and a capture that is only
    almost forward (a facade shot from an arc) puts views where NDC's frustum has nothing: so the band around it types
    the scene for the inward model, which holds any spread, says it did, and keeps the forward block so that the fit
    can try NDC against it (plenoxels/planning/model_trial.py)."""
    cone = view_cone_deg(cams.view_dirs)
    limit, band = options.forward_max_cone_deg, options.borderline_deg
    borderline = abs(cone - limit) <= band
    looks_forward = cone <= limit - (band if borderline else 0.0)
    reason = f"90% of viewing directions lie within {cone:.1f} deg of their mean " + (
        f"(<= {limit:g}): the cameras face one way" if looks_forward
        else f"(> {limit:g}): the cameras look inward from around the scene" if not borderline
        else f"(within {band:g} of {limit:g}, borderline): modelled as seen from around the scene, which holds where "
             "the forward model's single frustum would not (the fit tries NDC against it; normalize.scene_type=forward "
             "sets NDC)")
    return Spread(cone, borderline, looks_forward, reason)


def gravity_of(transforms: dict) -> np.ndarray | None:
    """The world's up the poses' source fixes (transforms.json's `up`), where it is a direction."""
    try:
        up = np.asarray(transforms.get("up"), dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        return None
    return up if np.isfinite(up).all() and np.linalg.norm(up) > 1e-9 else None


def aim_of(cams: Cameras, looks_forward: bool, measured: dict, gravity: np.ndarray | None = None) -> Aim:
    """Up, the turn to z up (heading from the first camera by name) and where the optical axes meet. Up is
    `gravity` where the poses' source gives it (a phone's world, a survey's, a drone's gimbal), else found from the
    cameras; a forward capture's reference camera stays level with the cameras' own up (a survey looks down along
    gravity)."""
    dirs = cams.view_dirs
    level, up_rule = camera_up(cams.c2w, inward=not looks_forward)
    up = level
    if gravity is not None:
        up, up_rule = gravity / np.linalg.norm(gravity), "gravity, as the poses' source gives it (transforms.json's up)"
        measured["cameras_up_from_gravity_deg"] = round(float(np.degrees(np.arccos(np.clip(level @ up, -1, 1)))), 2)
    axes_point, axes_conditioning = closest_point_of_axes(cams.origins, dirs)
    first_by_name = min(range(len(cams.names)), key=lambda i: cams.names[i])
    rotation = rotation_to_z_up(up, horizontal_heading(dirs, up, first_by_name))
    measured.update({"up_in_input_frame": up.round(6).tolist(), "up_from": up_rule,
                     "axes_closest_point": axes_point.round(6).tolist(),
                     "axes_conditioning": round(axes_conditioning, 6)})
    if axes_conditioning < 1e-3:  # parallel axes meet nowhere: stand in a point in front of the cameras
        axes_point = cams.origins.mean(axis=0) + dirs.mean(axis=0) * np.linalg.norm(np.ptp(cams.origins, axis=0))
    camera_distance = float(np.median(np.linalg.norm(cams.origins - axes_point, axis=1)))
    return Aim(rotation, level, axes_point, camera_distance)


def first_box(cams: Cameras, xyz: np.ndarray, seen: list[np.ndarray] | None, family_forward: bool, aim: Aim,
              reference_input: np.ndarray | None, measured: dict) -> tuple[np.ndarray, str]:
    """The foreground box in the z-up frame before any silhouettes: the bulk of the points most cameras see (grown to
    what inward cameras aim at), else a forward camera's frustum, else what every camera sees where the axes meet."""
    n = len(cams.names)
    covisible = covisible_counts(xyz, cams) if seen is not None else np.zeros(0, dtype=np.int64)
    foreground = covisible >= max(2, COVISIBLE_SHARE * n)
    if not family_forward and seen is not None:
        foreground &= np.linalg.norm(xyz - aim.axes_point, axis=1) < aim.camera_distance
    measured["foreground_points"] = int(foreground.sum())
    if foreground.sum() >= MIN_POINTS:
        box_rot, box_from = robust_box(xyz[foreground] @ aim.rotation.T), "sparse points seen by most cameras"
        if family_forward:
            return box_rot, box_from
        return hold_what_cameras_aim_at(box_rot, box_from, xyz, cams, seen, aim.rotation, aim.axes_point,
                                        aim.camera_distance, measured)
    if family_forward:
        near, far, box_from = forward_depth_guess(cams)
        return frustum_box(reference_input, cams.intrinsics[0], near, far, aim.rotation), box_from
    # What every camera sees at the point the axes meet: the region the capture was aimed at.
    half = aim.camera_distance * math.tan(min_half_fov(cams))
    centre_rot = aim.rotation @ aim.axes_point
    return (np.stack([centre_rot - half, centre_rot + half]),
            "cameras: the view of the narrowest camera where the optical axes meet")


def backdrops(cams: Cameras, poses_dir: Path | None, looks_forward: bool, options: SceneOptions,
              measured: dict) -> tuple[Backdrop | None, tuple[np.ndarray, float] | None]:
    """What the photos show of an empty backdrop, refusing a still textured room behind a turning object, and each
    photo's own backdrop colour where the photos show no one colour but might each show one of their own."""
    backdrop = measure_backdrop(cams, poses_dir) if poses_dir is not None and not looks_forward else None
    if backdrop is None:
        return None, None
    measured["still_textured_pixels"] = round(backdrop.still_textured, 4)
    if backdrop.still_textured >= STILL_TEXTURED_SHARE:
        raise UserError(f"{backdrop.still_textured:.0%} of the photos' pixels show the same texture at the same "
                        "place in every sampled photo: a still background behind a turning object (a turntable in "
                        "a room), which no model of one scene shows; give a mask of the object for each photo (a "
                        "masks/ folder beside the photos, white on the object, each named like its photo)")
    if (not backdrop.from_masks and backdrop.photos_showing < BACKDROP_MIN_PHOTOS
            and backdrop.empty_fraction >= options.object_min_empty_fraction):
        return backdrop, own_backdrops(cams, poses_dir)
    return backdrop, None


def near_far_per_frame(cams: Cameras, xyz_world: np.ndarray, seen: list[np.ndarray] | None, c2w_world: np.ndarray,
                       scale: float, foreground_box: np.ndarray, measured: dict) -> list[tuple[float, float]]:
    """Near and far of each frame: from the points it sees, else from LLFF's bounds, else from the foreground box."""
    near_far, sources = [], {"points": 0, "llff bounds": 0, "foreground box": 0}
    for i in range(len(cams.names)):
        estimate = near_far_from_points(xyz_world[seen[i]], c2w_world[i], cams.intrinsics[i]) if seen is not None else None
        source = "points"
        if estimate is None and cams.bounds is not None:
            estimate = (float(cams.bounds[i, 0] * scale * (1 - NEAR_FAR_MARGIN)),
                        float(cams.bounds[i, 1] * scale * (1 + NEAR_FAR_MARGIN)))
            source = "llff bounds"
        if estimate is None:
            estimate, source = near_far_from_box(c2w_world[i], foreground_box), "foreground box"
        near_far.append(estimate)
        sources[source] += 1
    measured["near_far_from"] = {k: v for k, v in sources.items() if v}
    return near_far


def scene_frames(cams: Cameras, held_out: set[int], near_far: list[tuple[float, float]], c2w_world: np.ndarray,
                 options: SceneOptions, poses_dir: Path | None, path_prefix: str,
                 own_colours: np.ndarray | None) -> list[dict]:
    """scene.json's frames, by name: pose in the world frame, intrinsics, near/far, split (`unused`: past
    normalize.train_every's share, or a photo without colour among colour ones) and, where the fit trains what lies
    outside the object as empty, the photo's backdrop colour."""
    masked_out = None
    if (options.masked_backdrop == "own" and poses_dir is not None and cams.frames
            and all(shows_backdrop_outside_mask(f) for f in cams.frames)):
        masked_out = masked_out_colours(cams, poses_dir)
        if masked_out is not None:
            masked_out = from_nearest_cameras(masked_out, c2w_world[:, :3, 3], held_out)
    backdrop_colours = own_colours if own_colours is not None else masked_out
    frames, train_rank = [], 0
    for i in sorted(range(len(cams.names)), key=lambda i: cams.names[i]):
        k, frame = cams.intrinsics[i], cams.frames[i]
        split = "test" if i in held_out else "train" if train_rank % options.train_every == 0 else "unused"
        train_rank += i not in held_out
        if frame.get("colourless"):  # a greyscale photo among colour ones (ingest): posed, neither fitted nor scored
            split = "unused"
        frames.append({
            "name": cams.names[i], "file_path": path_prefix + frame["file_path"],
            "mask_path": path_prefix + frame["mask_path"] if frame.get("mask_path") else None,
            "transform_matrix": c2w_world[i].tolist(), "fl_x": k.fl_x, "fl_y": k.fl_y, "cx": k.cx, "cy": k.cy,
            "w": k.w, "h": k.h, "near": near_far[i][0], "far": near_far[i][1],
            "split": split, **({"colourless": True} if frame.get("colourless") else {}),
        })
        if backdrop_colours is not None:
            frames[-1]["backdrop"] = [round(float(c), 4) for c in backdrop_colours[i]]
    return frames


def held_out_frames(cams: Cameras, options: SceneOptions) -> set[int]:
    """The frames held out for scoring: a dataset's own held-out split where it names its splits (NeRF synthetic
    train/val/test), else every holdout_every-th by sorted name; the views of a 360 frame as one, so that a held-out
    view is not one turn of a trained camera."""
    if any(f.get("split") for f in cams.frames):
        return {i for i, f in enumerate(cams.frames) if f.get("split") == "test"}
    groups = [f.get("panorama_frame", name) for f, name in zip(cams.frames, cams.names)]
    held = {g for rank, g in enumerate(sorted(set(groups)))
            if options.holdout_every > 0 and rank % options.holdout_every == 0}
    return {i for i, g in enumerate(groups) if g in held}


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
