"""The object alone: the ground (or table) it stands on, found as a plane in the mesh and cut away with what lies
below it, and the pieces of the room the foreground box cut through.

Evidence: the mesh is the field's opaque surface inside the foreground box (normalize's box of the sparse points most
cameras see, or the viewer's crop box), seen by the training views. The ground is the plane that carries the most
upward-facing surface (RANSAC over the faces, tilted at most MAX_TILT_DEG from the scene's up) when something stands
on it and it runs out of the box: a floor or a table continues past the foreground, so its surface reaches the
box's sides along a good part of their length (RIM_SHARE), while a slab or base plate that belongs to the object ends
inside the box and is kept. The cut takes every face within the plane's band (its measured roughness, at least
CUT_VOXELS voxels) or below it, but for the walls of what stands on the ground, which run down through the band.
What then stands on the plane is the object; of the rest, pieces that run into the box's sides are the room (a wall,
furniture, the floor beyond a step), which the box cut through, and go.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

# The ground's normal is at most this far from the scene's up.
MAX_TILT_DEG = 30.0
# RANSAC: planes tried, faces each is scored on, and the inlier band (voxels) while searching.
RANSAC_PLANES = 256
RANSAC_FACES = 20_000
SEARCH_BAND_VOXELS = 2.0
# Upward faces must carry at least this share of the mesh's area for a ground to be looked for.
MIN_UPWARD_AREA = 0.05
# The plane is the ground when its surface reaches the box's sides along at least this share of the rim where the
# plane meets them (within RIM_REACH_VOXELS), and at least MIN_ABOVE_SHARE of the rest of the mesh stands above it
# (what lies below is the ground's own underside and what its fit holds inside, or a table's legs and the floor).
RIM_SHARE = 0.25
MIN_ABOVE_SHARE = 0.1
RIM_REACH_VOXELS = 4.0
RIM_SAMPLES = 400
# The cut: faces whose vertices all lie below this height over the plane (voxels; at least), or below the plane.
CUT_VOXELS = 2.0
# The band grows to this quantile of the inliers' heights, times CUT_SPREAD, where the fitted ground is rough.
CUT_QUANTILE = 0.9
CUT_SPREAD = 1.5
MAX_CUT_VOXELS = 8.0
# A face in the band this far or more from level (either way up) is a wall: the side of what stands on the ground.
WALL_DEG = 45.0


@dataclass
class Ground:
    """A plane n . x = offset (n: unit, towards the object) and how it was judged."""
    normal: np.ndarray
    offset: float
    tilt_deg: float
    area_share: float        # of the mesh's area, within the search band of the plane and facing up
    rim_share: float         # of the box's rim at the plane, reached by the plane's surface
    above_share: float       # of the rest of the mesh's area, above the plane
    is_ground: bool
    cut_height: float        # world units

    def heights(self, points: np.ndarray) -> np.ndarray:
        return points @ self.normal - self.offset

    def describe(self) -> dict:
        return {"normal": self.normal.round(5).tolist(), "offset": round(float(self.offset), 6),
                "tilt_deg": round(self.tilt_deg, 2), "area_share": round(self.area_share, 4),
                "rim_share": round(self.rim_share, 4), "above_share": round(self.above_share, 4),
                "is_ground": self.is_ground, "cut_height": round(float(self.cut_height), 6)}


def find_ground(mesh: trimesh.Trimesh, up: np.ndarray, box_min: np.ndarray, box_max: np.ndarray, voxel: float,
                seed: int = 0) -> Ground | None:
    """The plane carrying the most upward-facing surface, and whether it is ground to cut (module docstring);
    None when the mesh has too little upward surface for one. `voxel`: world units."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    centres, normals, area = np.asarray(mesh.triangles_center), np.asarray(mesh.face_normals), np.asarray(mesh.area_faces)
    upward = normals @ up > math.cos(math.radians(MAX_TILT_DEG))
    if area.sum() <= 0 or area[upward].sum() < MIN_UPWARD_AREA * area.sum():
        return None
    rng = np.random.default_rng(seed)
    candidates = np.flatnonzero(upward)
    weight = area[candidates] / area[candidates].sum()
    band = SEARCH_BAND_VOXELS * voxel

    triples = centres[candidates[rng.choice(len(candidates), size=(RANSAC_PLANES, 3), p=weight)]]
    plane_normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    plane_normals *= np.sign(plane_normals @ up)[:, None]
    length = np.linalg.norm(plane_normals, axis=1)
    ok = (length > 1e-12) & (plane_normals @ up > math.cos(math.radians(MAX_TILT_DEG)) * np.maximum(length, 1e-12))
    if not ok.any():
        return None
    plane_normals = plane_normals[ok] / length[ok, None]
    offsets = np.einsum("ij,ij->i", plane_normals, triples[ok, 0])
    scored = candidates[rng.choice(len(candidates), size=min(RANSAC_FACES, len(candidates)), p=weight)]
    support = (np.abs(centres[scored] @ plane_normals.T - offsets) < band).sum(axis=0)
    normal, offset = plane_normals[np.argmax(support)], float(offsets[np.argmax(support)])

    for _ in range(3):  # least squares on the inliers (area-weighted), then their new band
        inliers = upward & (np.abs(centres @ normal - offset) < band)
        if inliers.sum() < 3:
            return None
        w = area[inliers] / area[inliers].sum()
        mean = w @ centres[inliers]
        spread = (centres[inliers] - mean) * np.sqrt(w)[:, None]
        normal = np.linalg.svd(spread, full_matrices=False)[2][-1]
        normal = normal * np.sign(normal @ up)
        offset = float(normal @ mean)

    heights = centres @ normal - offset
    inliers = upward & (np.abs(heights) < band)
    rest = ~inliers
    above = area[rest & (heights > 0)].sum() / max(area[rest].sum(), 1e-12)
    rim = _rim_share(np.asarray(mesh.vertices)[np.unique(mesh.faces[inliers])], normal, offset, box_min, box_max,
                     RIM_REACH_VOXELS * voxel)
    roughness = float(np.quantile(np.abs(heights[inliers]), CUT_QUANTILE)) if inliers.any() else 0.0
    cut = float(np.clip(CUT_SPREAD * roughness, CUT_VOXELS * voxel, MAX_CUT_VOXELS * voxel))
    tilt = math.degrees(math.acos(float(np.clip(normal @ up, -1.0, 1.0))))
    return Ground(normal, offset, tilt, float(area[inliers].sum() / area.sum()), rim, float(above),
                  bool(rim >= RIM_SHARE and above >= MIN_ABOVE_SHARE), cut)


def _rim_share(points: np.ndarray, normal: np.ndarray, offset: float, box_min: np.ndarray, box_max: np.ndarray,
               reach: float) -> float:
    """The share of the box's rim where the plane meets its four vertical sides (x and y faces) that has one of
    `points` within `reach`: how much of the box's edge the plane's surface runs out to."""
    if len(points) == 0:
        return 0.0
    rims = []
    steps = np.linspace(0.0, 1.0, RIM_SAMPLES // 4)
    for axis in (0, 1):
        other = 1 - axis
        for side in (box_min[axis], box_max[axis]):
            p = np.zeros((len(steps), 3))
            p[:, axis] = side
            p[:, other] = box_min[other] + steps * (box_max[other] - box_min[other])
            # z from the plane: n . p = offset (the ground is nowhere near vertical, so n_z is well away from 0).
            p[:, 2] = (offset - p[:, 0] * normal[0] - p[:, 1] * normal[1]) / normal[2]
            inside = (p[:, 2] >= box_min[2]) & (p[:, 2] <= box_max[2])
            rims.append(p[inside])
    rim = np.concatenate(rims)
    if len(rim) == 0:
        return 0.0
    distance, _ = cKDTree(points).query(rim, k=1)
    return float((distance <= reach).mean())


def cut_ground(mesh: trimesh.Trimesh, ground: Ground) -> tuple[np.ndarray, np.ndarray]:
    """Which faces [F] stay once the ground's band and everything below it go, and which vertices [V] of the faces
    that stay touch the cut (the object's footprint on the ground).

    An object's walls run down through the band to the ground: the steep faces in the band (more than WALL_DEG from
    facing up or down) stay where they join, face to face through steep faces, what stands above the band. So the
    object keeps its sides down to the ground; the ground's own bumps, joined to nothing above the band, go."""
    heights = ground.heights(np.asarray(mesh.vertices))
    face_heights = heights[mesh.faces]
    above = (face_heights.max(axis=1) >= ground.cut_height) & (face_heights.min(axis=1) >= -ground.cut_height)
    steep = np.abs(np.asarray(mesh.face_normals) @ ground.normal) < math.cos(math.radians(WALL_DEG))
    wall = steep & (face_heights.min(axis=1) >= -ground.cut_height) & ~above
    allowed = above | wall
    pairs = np.asarray(mesh.face_adjacency).reshape(-1, 2)
    pairs = pairs[allowed[pairs].all(axis=1)]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(mesh.faces),) * 2)
    _, labels = connected_components(graph, directed=False)
    joined = np.bincount(labels[above], minlength=labels.max(initial=-1) + 1) > 0
    keep = allowed & joined[labels]
    touching = np.zeros(len(mesh.vertices), dtype=bool)
    kept_vertices = np.unique(mesh.faces[keep])
    touching[kept_vertices] = heights[kept_vertices] < 2 * ground.cut_height
    return keep, touching


def reaches_box_sides(mesh: trimesh.Trimesh, labels: np.ndarray, box_min: np.ndarray, box_max: np.ndarray,
                      reach: float) -> np.ndarray:
    """Per piece (face label 0..L-1): whether it comes within `reach` of one of the box's four vertical sides, i.e.
    the box cut through it."""
    vertices = np.asarray(mesh.vertices)
    near = ((vertices[:, :2] - box_min[:2] < reach) | (box_max[:2] - vertices[:, :2] < reach)).any(axis=1)
    face_near = near[mesh.faces].any(axis=1)
    return np.bincount(labels[face_near], minlength=int(labels.max(initial=-1)) + 1) > 0
