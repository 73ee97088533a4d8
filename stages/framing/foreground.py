"""The foreground box: the bulk of the points most cameras see, grown to what the cameras aim at, or the visual hull
of the photos' silhouettes; and the surroundings box around it for captures with a real background."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from plenoxels.core.cameras import Intrinsics, project
from plenoxels.core.errors import UserError
from stages.framing.backdrop import BACKDROP_MIN_PHOTOS, Backdrop
from stages.framing.options import SceneOptions
from stages.framing.sightings import Cameras, MIN_POINTS, MIN_POINTS_PER_IMAGE
from stages.framing.visual_hull import DISAGREEING_SHARE, carve, cut_photos, held_box, read_silhouettes, shown_box


# A point belongs to the foreground candidates when at least this share of the cameras has it in view.
COVISIBLE_SHARE = 0.7
# Robust box of the foreground points: the bulk between these percentiles on each axis, widened to the
# points within BOX_REACH times its size (see robust_box).
BOX_PERCENTILES = (2.0, 98.0)
BOX_REACH = 0.2
# What a camera is aimed at: the sparse points it sees in the middle AIM_SHARE of its image's width and height
# (aimed_points); where at least AIM_MIN_SHARE of the cameras are aimed outside the foreground box, it grows to
# AIM_MARGIN of its size beyond their points. Fewer are views off the object (a few frames of an orbit aimed at the
# floor or a wall), and growing the box for those spends cells on what the capture is not about.
AIM_SHARE = 0.2
AIM_MIN_SHARE = 0.1
AIM_MARGIN = 0.1
# The surroundings box grows toward the points around the foreground in steps of this share (surroundings_box).
SURROUNDINGS_STEP = 0.05
# The box from the training photos' silhouettes (stages/framing/visual_hull.py): at least this many photos, the hull grown
# by a voxel and this share of its size on each side; on a flat backdrop a tenth of the photos may disagree with a
# voxel before it goes (the colour test is rougher than a mask).
MIN_SILHOUETTES = 4
HULL_MARGIN = 0.02
BACKDROP_DISAGREEING_SHARE = 0.1



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



def surroundings_box(xyz_world: np.ndarray, foreground_box: np.ndarray, camera_origins: np.ndarray,
                     beyond_factor: float) -> tuple[np.ndarray, float]:
    """([2,3] box, growth): what a bounded grid of a room holds. The foreground box is what most cameras see; the
    walls and floor around it, seen by fewer, lie outside it, and a background sphere shows them without the parallax
    the cameras see between them (bench/README.md, "The scene model by trial": how normalize boxes a room). So the box grows
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



def hold_what_cameras_aim_at(box_rot: np.ndarray, box_from: str, xyz: np.ndarray, cams: Cameras, seen: list[np.ndarray],
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



def silhouette_box(cams: Cameras, train: list[int], poses_dir: Path, backdrop: Backdrop | None,
                    rotation: np.ndarray, axes_point: np.ndarray, camera_distance: float,
                    found: tuple[np.ndarray, str], options: SceneOptions, measured: dict,
                    own: tuple[np.ndarray, float] | None = None) -> tuple[np.ndarray, str]:
    """The box (rotated frame) the training photos' silhouettes give (stages/framing/visual_hull.py) and what it came from:
    the box of what some photo sees of their masks' visual hull, or on a flat backdrop the same of what is not the
    backdrop, joined with the box `found` otherwise (colour alone may miss a part of the backdrop's colour, so the
    points keep their say); `found` where the photos carry neither, and where the silhouettes do not bound the object
    (cut by the photos' edges), `found` grown to hold what each silhouette shows. A box from the masks' hull that cuts
    what a photo's mask shows can only come from wrong masks or poses: that stops here."""
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
    if hull.bounded:
        shown = shown_box(silhouettes, hull, rotation)
    else:
        # The hull runs out of the carved region where every photo that looks that way has the object cut by its
        # frame (a capture in an arc, the object's base out of every frame): there the points say where the object
        # ends, the box of theirs grown to hold what each photo shows of the hull beyond it.
        shown = held_box(silhouettes, hull, found[0], rotation)
    measured["visual_hull"]["box_shown"] = shown.round(6).tolist()
    grow = hull.voxel + HULL_MARGIN * (shown[1] - shown[0])
    box = np.stack([shown[0] - grow, shown[1] + grow])
    if not hull.bounded:
        # The points' box, not the silhouettes' hull: what it still cuts (pixels whose rays meet none of the hull's
        # voxels a photo sees) says nothing against the masks or poses, so the measure goes with the box.
        measured["visual_hull"]["cut_photos"] = len(cut_photos(silhouettes, box, rotation))
        shown_by = "masks" if from_masks else "silhouettes on their flat backdrop"
        return box, f"{found[1]}, grown to hold what {len(silhouettes)} training photos' {shown_by} show"
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
