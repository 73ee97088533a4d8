"""Where the object is, from the training photos' silhouettes: a visual hull, and the box around it.

A silhouette marks the pixels that show the object: a mask (the photo's alpha, or a mask the user gave) or, on a
flat backdrop, every pixel that is not the backdrop's colour. Whatever the object is, it lies inside the cone each
silhouette casts from its camera, so inside their intersection: carving a voxel grid by the silhouettes (a voxel
goes where its footprint falls outside some photo's silhouette) keeps every part of the object a photo shows, thin
parts included, which the sparse points' bulk misses (a ship's rigging, a plant's leaves, a mast). The carving runs
coarse to fine, each level splitting only the voxels the level before kept, on small copies of the silhouettes whose
pixels count as object where any pixel they cover does; a voxel's footprint is a disc as wide as its projected
diagonal, so carving never cuts what a silhouette shows. A few photos may disagree with a voxel (a mask that misses
a part) before it goes.

The hull still holds whatever every photo sees only through the object (under a base that all the cameras look
down on, a cone as deep as the base is wide). The box is the box of the hull's voxels that some photo sees in front of
the others, grown only as far as its outline must to hold every silhouette: what the photos show, and no more.

The box that frames the scene is then checked against every silhouette: a photo whose silhouette reaches past the
box's outline shows object that the box would cut, which only a wrong mask or a wrong pose can explain.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from plenoxels.core.cameras import Intrinsics, project

# Silhouettes are carved at this size (longest side, pixels).
SILHOUETTE_SIDE = 256
# The first level's voxels per side of the region carved; each level after splits the kept voxels in 8 until a voxel
# is at most 1/FINEST_SHARE of the kept voxels' extent.
FIRST_LEVEL = 32
FINEST_SHARE = 64
MAX_LEVELS = 5
# A voxel stays when at most this share of the photos put it outside their silhouette.
DISAGREEING_SHARE = 0.05
# A voxel some photos must judge before the silhouettes can say anything of it.
MIN_SEEN = 2
# A silhouette within this many pixels (at SILHOUETTE_SIDE) of its frame's edge may go on beyond it.
EDGE_PX = 1
# A photo's silhouette is cut by a box when more than this share of its pixels (and MIN_CUT_PIXELS) lie farther than
# CUT_TOLERANCE_PX (at SILHOUETTE_SIDE) outside the box's outline.
CUT_SHARE = 0.005
MIN_CUT_PIXELS = 4
CUT_TOLERANCE_PX = 1.5
MASK_OBJECT_LEVEL = 25   # 8-bit mask values above this mark the object (soft alpha edges of thin parts included)


@dataclass
class Silhouettes:
    """The silhouettes of some photos at SILHOUETTE_SIDE, with their cameras (the input frame of the poses)."""
    names: list[str]
    c2w: np.ndarray                 # [N, 4, 4]
    intrinsics: list[Intrinsics]    # at the silhouettes' size
    object: list[np.ndarray]        # [h, w] bool: pixels that show the object
    source: str                     # "masks" or "backdrop"

    def __len__(self) -> int:
        return len(self.names)


def _small(image: np.ndarray, k: Intrinsics) -> tuple[np.ndarray, Intrinsics]:
    """A bool image at most SILHOUETTE_SIDE a side, true where any pixel it covers is, and k at that size."""
    scale = min(1.0, SILHOUETTE_SIDE / max(image.shape))
    if scale >= 1.0:
        return image, k
    small = k.scaled(scale)
    return cv2.resize(image.astype(np.float32), (small.w, small.h), interpolation=cv2.INTER_AREA) > 0, small


def read_silhouettes(names: list[str], frames: list[dict], c2w: np.ndarray, intrinsics: list[Intrinsics],
                     poses_dir: Path, backdrop: np.ndarray | None = None) -> Silhouettes | None:
    """The silhouettes of these frames: their masks where every one has a mask, else (with `backdrop`, an RGB colour
    0-255, or one per frame [N, 3]) the pixels that are not the backdrop's colour; None where neither is known or an
    image is unreadable."""
    from_masks = all(f.get("mask_path") for f in frames)
    if not from_masks and backdrop is None:
        return None
    objects, ks = [], []
    try:
        for i, (frame, k) in enumerate(zip(frames, intrinsics)):
            if from_masks:
                with Image.open(poses_dir / frame["mask_path"]) as im:
                    shown = np.asarray(im.getchannel("A") if "A" in im.getbands() else im.convert("L")) > MASK_OBJECT_LEVEL
            else:
                with Image.open(poses_dir / frame["file_path"]) as im:
                    rgb = np.asarray(im.convert("RGB")).astype(np.int16)
                colour = backdrop[i] if np.ndim(backdrop) == 2 else backdrop
                shown = np.abs(rgb - colour).max(axis=-1) > BACKDROP_OBJECT_LEVELS
            if shown.shape != (k.h, k.w):
                return None
            small, small_k = _small(shown, k)
            objects.append(small)
            ks.append(small_k)
    except (OSError, ValueError):
        return None
    return Silhouettes(list(names), np.asarray(c2w, dtype=np.float64), ks, objects,
                       "masks" if from_masks else "backdrop")


# A voxel counts as seen by a photo within this many voxel sides behind the nearest voxel in its cell of the photo's
# depth buffer (neighbours on a surface a photo sees aslant lie a little behind one another).
SEEN_DEPTH_VOXELS = 2.0
# 8-bit levels a pixel must differ from a flat backdrop's colour (in some channel) to show the object.
BACKDROP_OBJECT_LEVELS = 12


@dataclass
class Hull:
    box: np.ndarray          # [2, 3] in the rotated frame the carving ran in
    voxel: float             # the finest voxel's side
    voxels: int              # voxels kept at the finest level
    levels: int
    bounded: bool            # False where the hull reaches the region's edge (silhouettes cut by the photos' edges)
    centres: np.ndarray      # [M, 3] the kept voxels' centres, rotated frame


def carve(silhouettes: Silhouettes, rotation: np.ndarray, centre_rot: np.ndarray, half: float,
          disagreeing_share: float = DISAGREEING_SHARE) -> Hull | None:
    """The visual hull's box inside the cube of half-size `half` around `centre_rot`, both in the frame `rotation`
    takes the input frame to (rows: its axes); None when no voxel survives."""
    distance = [cv2.distanceTransform(np.where(o, 0, 255).astype(np.uint8), cv2.DIST_L2, 3) for o in silhouettes.object]
    whole = [not (o[:EDGE_PX].any() or o[-EDGE_PX:].any() or o[:, :EDGE_PX].any() or o[:, -EDGE_PX:].any())
             for o in silhouettes.object]
    # Each photo's camera in the rotated frame.
    c2w = silhouettes.c2w.copy()
    c2w[:, :3, :3] = rotation @ c2w[:, :3, :3]
    c2w[:, :3, 3] = c2w[:, :3, 3] @ rotation.T
    size = 2.0 * half / FIRST_LEVEL
    index = np.stack(np.meshgrid(*[np.arange(FIRST_LEVEL)] * 3, indexing="ij"), -1).reshape(-1, 3)
    corner = centre_rot - half
    levels = 0
    while True:
        levels += 1
        centres = corner + (index + 0.5) * size
        keep = _consistent(centres, size, c2w, silhouettes.intrinsics, distance, whole, disagreeing_share)
        index = index[keep]
        if not len(index):
            return None
        extent = float(((index.max(0) - index.min(0) + 1) * size).max())
        if size <= extent / FINEST_SHARE or levels == MAX_LEVELS:
            break
        index = (index[:, None] * 2 + np.stack(np.meshgrid(*[np.arange(2)] * 3, indexing="ij"), -1).reshape(1, 8, 3)
                 ).reshape(-1, 3)
        size /= 2
    lo, hi = corner + index.min(0) * size, corner + (index.max(0) + 1) * size
    reach = np.round(2 * half / size).astype(int)
    bounded = bool((index.min(0) > 0).all() and (index.max(0) < reach - 1).all())
    return Hull(np.stack([lo, hi]), size, len(index), levels, bounded, corner + (index + 0.5) * size)


def _consistent(centres: np.ndarray, size: float, c2w: np.ndarray, intrinsics: list[Intrinsics],
                distance: list[np.ndarray], whole: list[bool], disagreeing_share: float) -> np.ndarray:
    """Which voxels (centres [M, 3], side `size`) no more than the allowed share of the photos put outside their
    silhouettes. A photo that holds the whole object (its silhouette clear of the frame's edges) puts outside it
    whatever it does not see too; one whose frame cuts the object says nothing of what lies beyond its frame."""
    allowed = int(np.floor(disagreeing_share * len(c2w)))
    judged = np.zeros(len(centres), dtype=np.int32)
    outside = np.zeros(len(centres), dtype=np.int32)
    active = np.arange(len(centres))
    radius = size * np.sqrt(3) / 2
    for pose, k, far, holds_all in zip(c2w, intrinsics, distance, whole):
        uv, depth = project(centres[active], pose, k)
        in_front = depth > radius
        footprint = np.where(in_front, radius * max(k.fl_x, k.fl_y) / np.maximum(depth, 1e-12), 0.0)
        col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        inside = in_front & (col >= 0) & (col < k.w) & (row >= 0) & (row < k.h)
        gap = np.full(len(active), np.inf)
        gap[inside] = far[row[inside], col[inside]]
        beyond = gap > footprint + 1.0
        if holds_all:
            # Off the frame by more than the footprint, or behind the camera: not the object, which this photo holds.
            off = ~inside & in_front & ((uv[:, 0] < -footprint) | (uv[:, 0] > k.w + footprint) |
                                        (uv[:, 1] < -footprint) | (uv[:, 1] > k.h + footprint))
            beyond = (inside & beyond) | off | (depth < -radius)
            judged[active] += 1
        else:
            beyond &= inside
            judged[active] += inside
        outside[active] += beyond
        active = active[outside[active] <= allowed]
    keep = np.zeros(len(centres), dtype=bool)
    keep[active] = judged[active] >= MIN_SEEN
    return keep


def _beyond_outline(silhouettes: Silhouettes, box_rot: np.ndarray, rotation: np.ndarray) -> list[int | None]:
    """Per photo, how many of its silhouette's pixels lie farther than CUT_TOLERANCE_PX outside the outline of the box
    (in the rotated frame); None where the photo's camera is inside the box, which it sees all around it, or where its
    silhouette is empty."""
    counts: list[int | None] = []
    for pose, k, shown in zip(silhouettes.c2w, silhouettes.intrinsics, silhouettes.object):
        beyond = _outline_distance(box_rot, rotation, pose, k) if shown.any() else None
        counts.append(None if beyond is None else int((shown & (beyond > CUT_TOLERANCE_PX)).sum()))
    return counts


def _outline_distance(box_rot: np.ndarray, rotation: np.ndarray, pose: np.ndarray, k: Intrinsics) -> np.ndarray | None:
    """Each pixel's distance outside the outline of the box (rotated frame) in the photo; None where the camera is
    inside the box."""
    corners = np.array([[box_rot[i][0], box_rot[j][1], box_rot[l][2]] for i in (0, 1) for j in (0, 1) for l in (0, 1)])
    uv, depth = project(corners @ rotation, pose, k)   # the corners back in the input frame
    if (depth <= 0).any():
        return None
    outline = np.zeros((k.h, k.w), dtype=np.uint8)
    cv2.fillConvexPoly(outline, cv2.convexHull(np.round((uv - 0.5) * 16).astype(np.int32)), 1, shift=4)
    return cv2.distanceTransform(np.where(outline > 0, 0, 255).astype(np.uint8), cv2.DIST_L2, 3)


def cut_photos(silhouettes: Silhouettes, box_rot: np.ndarray, rotation: np.ndarray) -> dict[str, float]:
    """The photos whose silhouettes reach past the outline of the box (in the rotated frame), with the share of their
    silhouette pixels outside it (see CUT_SHARE)."""
    cut = {}
    for name, shown, outside in zip(silhouettes.names, silhouettes.object, _beyond_outline(silhouettes, box_rot, rotation)):
        if outside is None:
            continue
        share = outside / int(shown.sum())
        if outside >= MIN_CUT_PIXELS and share > CUT_SHARE:
            cut[name] = round(share, 4)
    return cut


def _surface(centres: np.ndarray, size: float) -> np.ndarray:
    """Which voxels (centres on one grid of side `size`) have a face on empty space: only they can be seen."""
    index = np.round((centres - centres.min(0)) / size).astype(np.int64) + 1
    solid = np.zeros(index.max(0) + 2, dtype=bool)
    solid[tuple(index.T)] = True
    inner = np.ones(len(index), dtype=bool)
    for axis in range(3):
        for step in (-1, 1):
            neighbour = index.copy()
            neighbour[:, axis] += step
            inner &= solid[tuple(neighbour.T)]
    return ~inner


def _seen(centres_in: np.ndarray, size: float, silhouettes: Silhouettes) -> np.ndarray:
    """Which voxels (centres in the input frame) some photo sees in front of the others, within its frame."""
    seen = np.zeros(len(centres_in), dtype=bool)
    for pose, k in zip(silhouettes.c2w, silhouettes.intrinsics):
        seen |= _seen_by(centres_in, size, pose, k)
    return seen


def _seen_by(centres_in: np.ndarray, size: float, pose: np.ndarray, k: Intrinsics) -> np.ndarray:
    """Which voxels (centres in the input frame) the photo sees in front of the others, within its frame: its depth
    buffer of the voxels, on cells as wide as a voxel looks, each voxel covering its cell's neighbours too so that none
    slips between them; a voxel counts as seen within SEEN_DEPTH_VOXELS of the nearest depth in its cell."""
    seen = np.zeros(len(centres_in), dtype=bool)
    radius = size * np.sqrt(3) / 2
    offsets = np.stack(np.meshgrid(np.arange(-1, 2), np.arange(-1, 2), indexing="ij"), -1).reshape(-1, 2)
    uv, depth = project(centres_in, pose, k)
    reach = radius * max(k.fl_x, k.fl_y) / np.maximum(depth, radius)   # a voxel's radius in pixels
    front = np.flatnonzero((depth > radius) & (uv[:, 0] > -reach) & (uv[:, 0] < k.w + reach)
                           & (uv[:, 1] > -reach) & (uv[:, 1] < k.h + reach))
    if not len(front):
        return seen
    uv, depth = uv[front], depth[front]
    cell = float(np.median(2 * radius * max(k.fl_x, k.fl_y) / depth))
    grid = np.floor(uv / cell).astype(np.int64)
    grid -= grid.min(0) - 1
    width = int(grid[:, 0].max()) + 2
    own = grid[:, 1] * width + grid[:, 0]
    keys = (own[None] + offsets[:, 1:2] * width + offsets[:, 0:1]).ravel()
    depths = np.tile(depth, len(offsets))
    order = np.argsort(keys, kind="stable")
    cells, first = np.unique(keys[order], return_index=True)
    nearest = np.minimum.reduceat(depths[order], first)
    seen[front] = depth <= nearest[np.searchsorted(cells, own)] + SEEN_DEPTH_VOXELS * size
    return seen


def shown_box(silhouettes: Silhouettes, hull: Hull, rotation: np.ndarray) -> np.ndarray:
    """The box (rotated frame) of what the photos show of the hull: the box of the hull's voxels that some photo sees
    in front of the rest, grown toward the hull's box only as far as its outline must to hold every silhouette pixel
    that the hull box's outline holds.

    The hull keeps every region that all the photos see only through the object: under a base that the cameras look
    down on, a cone as deep as the base is wide. Nothing there shows in any photo, so the box leaves it out; a part
    some photo shows, however thin, is seen in front of the rest and stays. The growing step puts back what a depth
    buffer of voxels misses where a surface turns away from a camera at the silhouette's edge."""
    surface = hull.centres[_surface(hull.centres, hull.voxel)]
    seen = surface[_seen(surface @ rotation, hull.voxel, silhouettes)]
    if not len(seen):
        return hull.box
    box = np.stack([np.maximum(seen.min(0) - hull.voxel / 2, hull.box[0]), np.minimum(seen.max(0) + hull.voxel / 2, hull.box[1])])
    held = _beyond_outline(silhouettes, hull.box, rotation)

    def holds(candidate: np.ndarray) -> bool:
        return all(before is None or (now is not None and now <= before)
                   for before, now in zip(held, _beyond_outline(silhouettes, candidate, rotation)))

    if holds(box):
        return box
    # Every face moves the same share of its way out to the hull's box; bisect that share to within a voxel's move.
    gap = float(np.abs(hull.box - box).max())
    grown, short = 1.0, 0.0
    while (grown - short) * gap > hull.voxel:
        middle = 0.5 * (grown + short)
        if holds(box + middle * (hull.box - box)):
            grown = middle
        else:
            short = middle
    return box + grown * (hull.box - box)


def held_box(silhouettes: Silhouettes, hull: Hull, box: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """`box` (rotated frame) grown to hold the hull's voxels that a photo sees in front of the rest, within its frame,
    where its silhouette reaches past the box's outline: what the photos show of the object beyond the box."""
    surface = hull.centres[_surface(hull.centres, hull.voxel)]
    centres_in = surface @ rotation
    wanted = np.zeros(len(surface), dtype=bool)
    for pose, k, shown in zip(silhouettes.c2w, silhouettes.intrinsics, silhouettes.object):
        beyond = _outline_distance(box, rotation, pose, k)
        outside = shown & (beyond > CUT_TOLERANCE_PX) if beyond is not None else None
        if outside is None or not outside.any():
            continue
        seen = np.flatnonzero(_seen_by(centres_in, hull.voxel, pose, k))
        uv, _ = project(centres_in[seen], pose, k)
        pixel = np.clip(np.floor(uv).astype(np.int64), 0, [k.w - 1, k.h - 1])
        wanted[seen[outside[pixel[:, 1], pixel[:, 0]]]] = True
    if not wanted.any():
        return box
    part = surface[wanted]
    return np.stack([np.minimum(box[0], part.min(0) - hull.voxel / 2),
                     np.maximum(box[1], part.max(0) + hull.voxel / 2)])
