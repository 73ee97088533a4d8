"""Where the training views' rays end on the fitted field, and what of a mesh those views see.

Rendering training views from the grid alone (`render_views`), the rays' expected termination points
(`ray_terminations`), sampling the field at points (`sample_field`, `density_gradient`), snapping points onto a
density level (`snap_to_level`), their normals (`point_normals`) and the mesh's own z-buffer per view
(`seen_vertices`, `view_cosines`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import trimesh
from scipy.ndimage import maximum_filter

from plenoxels.core.cameras import Intrinsics, project, rays_from_camera
from plenoxels.core.fit_frame import FitFrame
from plenoxels.core.render import render

# Points sampled per chunk when asking the grid for values, to bound memory.
CHUNK = 1 << 18
# How far (voxels) along its ray a point may move onto the mesh's level.
SNAP_VOXELS = 6.0
# The mesh's own z-buffer (seen_vertices): pixels this many voxels wide, at most this many pixels on a side, and
# at most this much (voxels) of a slanted surface's spread in depth over one pixel forgiven.
ZBUFFER_PIXEL_VOXELS = 2.0
MAX_ZBUFFER_PIXELS = 4096
GRAZING_VOXELS = 3.0
# A rendered view's colour is divided by its opacity, at least this much (fainter pixels stay dark).
MIN_COLOUR_OPACITY = 0.05


def as_numpy(x: Any) -> np.ndarray:
    """A tensor (any device) or array-like as a numpy array."""
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def sample_field(grid, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Density [N] (activated) and SH [N, 3, K] at fit-frame points, in chunks."""
    densities, coefficients = [], []
    for start in range(0, len(points), CHUNK):
        chunk = torch.as_tensor(points[start:start + CHUNK], dtype=torch.float32)
        with torch.no_grad():
            density, sh = grid.sample(chunk)
        densities.append(np.maximum(as_numpy(density).reshape(-1), 0.0))
        coefficients.append(as_numpy(sh).reshape(len(chunk), 3, -1))
    if not densities:
        return np.zeros(0), np.zeros((0, 3, 1))
    return np.concatenate(densities), np.concatenate(coefficients)


def density_gradient(grid, points: np.ndarray, step: float) -> np.ndarray:
    """Central-difference gradient [N,3] of the activated density at fit-frame points."""
    offsets = np.eye(3) * step
    stacked = np.concatenate([points + o for o in offsets] + [points - o for o in offsets])
    density, _ = sample_field(grid, stacked)
    density = density.reshape(6, len(points))
    return (density[:3] - density[3:]).T / (2 * step)


@dataclass
class Terminations:
    """Where training-view rays end: fit-frame origins [N,3], unit directions [N,3], distances [N] and
    the rays' opacity [N]."""
    origins: np.ndarray
    directions: np.ndarray
    t: np.ndarray
    opacity: np.ndarray

    def fit_points(self) -> np.ndarray:
        return self.origins + self.t[:, None] * self.directions

    def world(self, frame: "FitFrame") -> np.ndarray:
        return frame.to_world(self.fit_points())

    def subset(self, keep: np.ndarray) -> "Terminations":
        return Terminations(self.origins[keep], self.directions[keep], self.t[keep], self.opacity[keep])


@dataclass
class ViewRender:
    """One training view rendered from the fitted grid alone: its camera (normalised world, at the
    rendered size) and, per pixel [h*w], the distance t along its fit-frame ray (`rays`) to the
    expected termination point (opacity-normalised), the ray's opacity and its colour. The rays themselves are
    recomputed when needed, so a hundred large views stay small in memory."""
    c2w: np.ndarray
    k: Intrinsics
    t: np.ndarray         # float32
    opacity: np.ndarray   # float32
    rgb: np.ndarray | None = None   # uint8 [h*w, 3]: the grid's colour, divided by the opacity

    def rays(self, frame: FitFrame) -> tuple[np.ndarray, np.ndarray]:
        """Fit-frame origins and unit directions [h*w, 3]."""
        origins, directions = _fit_rays(self.c2w, self.k, frame)
        directions = directions.numpy()
        return origins.numpy(), directions / np.linalg.norm(directions, axis=1, keepdims=True)


def _fit_rays(c2w: np.ndarray, k: Intrinsics, frame: FitFrame) -> tuple[torch.Tensor, torch.Tensor]:
    origins, directions = rays_from_camera(c2w, k, dtype=torch.float64)
    return frame.rays(origins.reshape(-1, 3), directions.reshape(-1, 3))


def render_views(grid, frame: FitFrame, frames: list[dict], scale: float, max_views: int, report) -> list[ViewRender]:
    """The training views (every one, or `max_views` of them spread evenly; 0: all) at `scale` of their size.

    Only the fitted grid is rendered (never a background model), so unbounded and forward scenes
    give foreground depths only; forward scenes' rays go through NDC."""
    train = [f for f in frames if f.get("split", "train") == "train"] or frames
    if max_views and len(train) > max_views:
        pick = np.linspace(0, len(train) - 1, max_views).round().astype(int)
        train = [train[i] for i in pick]
    views = []
    for record in report.track(train, desc="rendering the training views' depth"):
        k = Intrinsics.from_frame(record).scaled(scale)
        c2w = np.asarray(record["transform_matrix"], dtype=np.float64)
        origins, directions = _fit_rays(c2w, k, frame)
        out = render(grid, origins.float(), directions.float())
        opacity = as_numpy(out.opacity).astype(np.float64)
        # The renderer's depth (along the unit direction) is a sum of weights that total the opacity: divide it out.
        t = as_numpy(out.depth).astype(np.float64) / np.maximum(opacity, 1e-12)
        # The surface's own colour: a pixel the grid only partly covers is darkened by the black behind it.
        rgb = as_numpy(out.rgb).astype(np.float64) / np.maximum(opacity, MIN_COLOUR_OPACITY)[:, None]
        rgb = np.rint(np.clip(rgb, 0.0, 1.0) * 255).astype(np.uint8)
        views.append(ViewRender(c2w, k, t.astype(np.float32), opacity.astype(np.float32), rgb))
    return views


def ray_terminations(views: list[ViewRender], frame: FitFrame, min_opacity: float, max_rays: int = 0,
                     seed: int = 0) -> Terminations:
    """The expected ray-termination points of the rendered views' pixels whose rays are at least
    `min_opacity` opaque (see render_views): all of them, or at most `max_rays` (0: no cap), the same seeded share
    of each view's, so that a hundred large views do not hold tens of millions of rays in memory at once."""
    good = [view.opacity >= min_opacity for view in views]
    total = sum(int(g.sum()) for g in good)
    share = 1.0 if not max_rays or total <= max_rays else max_rays / total
    rng = np.random.default_rng(seed)
    parts = [Terminations(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0))]
    for view, good_pixels in zip(views, good):
        keep = np.flatnonzero(good_pixels)
        if share < 1.0:
            keep = np.sort(rng.choice(keep, int(round(share * len(keep))), replace=False))
        origins, directions = view.rays(frame)
        parts.append(Terminations(origins[keep], directions[keep], view.t[keep].astype(np.float64),
                                  view.opacity[keep].astype(np.float64)))
    return Terminations(*(np.concatenate([getattr(p, name) for p in parts]) for name in ("origins", "directions", "t", "opacity")))


def _nearest_vertex_distance(vertices: np.ndarray, distance: np.ndarray, view: ViewRender, pixel: float
                             ) -> tuple[np.ndarray, float]:
    """A z-buffer of the vertices themselves for `view`, its pixels about `pixel` wide (world units) at the vertices'
    median distance: per vertex [V], the distance of the nearest vertex in its pixel (inf outside the image, where
    nothing is hidden), and the pixel's width per unit of distance. Marching-cubes vertices lie less than a voxel
    apart, so at two voxels a pixel a surface facing the view leaves no pixel empty for what lies behind to show
    through."""
    scale = min(float(np.median(distance)) / (pixel * view.k.fl_x), MAX_ZBUFFER_PIXELS / max(view.k.w, view.k.h))
    k = view.k.scaled(scale)
    uv, depth = project(vertices, view.c2w, k)
    col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    inside = (depth > 0) & (col >= 0) & (col < k.w) & (row >= 0) & (row < k.h)
    pixel_of = np.where(inside, row * k.w + col, 0)
    nearest = np.full(k.w * k.h, np.inf)
    np.minimum.at(nearest, pixel_of[inside], distance[inside])
    return np.where(inside, nearest[pixel_of], np.inf), 1.0 / k.fl_x


def seen_vertices(mesh: trimesh.Trimesh, views: list[ViewRender], frame: FitFrame, voxel: float, tolerance: float,
                  opacity: float) -> np.ndarray:
    """Which vertices [V] (normalised world) some training view sees (view_cosines)."""
    return (view_cosines(mesh, views, frame, voxel, tolerance, opacity) > 0).any(axis=1)


def view_cosines(mesh: trimesh.Trimesh, views: list[ViewRender], frame: FitFrame, voxel: float, tolerance: float,
                 opacity: float) -> np.ndarray:
    """Per vertex and training view [V, len(views)]: the cosine between the vertex normal and the direction to the
    camera where the view sees the vertex, 0 where it does not. A view sees a vertex in its image, on the side of the
    surface facing the camera, not behind what the view's pixel sees by more than `tolerance` (world units), and not
    behind a nearer layer of the mesh itself.

    The rendered view: a pixel less than `opacity` opaque hides nothing. Elsewhere the pixel's termination
    distance is the largest of the opaque ones in its 3x3 neighbourhood, so a vertex on a silhouette is
    not hidden by the far side of its own edge.
    The mesh's own layers: a fit's solids can come out as soft shells over an empty foam whose walls the
    rendered depth, averaged over the shell and the foam, does not hide (bench/README.md, "Export": how the
    mesh got its level). Against a z-buffer of the mesh's
    vertices (`voxel`: world units) a vertex is hidden when a nearer one in its pixel is more than the
    tolerance nearer, plus what the surface's slant spreads over one pixel, up to GRAZING_VOXELS."""
    vertices = np.asarray(mesh.vertices)
    normals = np.asarray(mesh.vertex_normals)
    cosines = np.zeros((len(vertices), len(views)), dtype=np.float32)
    for index, view in enumerate(views):
        centre = view.c2w[:3, 3]
        origins, directions = view.rays(frame)
        ends = frame.to_world(origins + view.t[:, None].astype(np.float64) * directions)
        opaque = (view.opacity >= opacity).reshape(view.k.h, view.k.w)
        reach = np.where(opaque, np.linalg.norm(ends - centre, axis=1).reshape(opaque.shape), -np.inf)
        reach = np.where(opaque, maximum_filter(reach, size=3, mode="nearest"), np.inf)

        offset = centre - vertices
        distance = np.linalg.norm(offset, axis=1)
        nearest, pixel_per_distance = _nearest_vertex_distance(vertices, distance, view, ZBUFFER_PIXEL_VOXELS * voxel)
        cosine = np.einsum("ij,ij->i", normals, offset) / np.maximum(distance, 1e-12)
        slant = distance * pixel_per_distance * np.sqrt(np.clip(1.0 - cosine ** 2, 0.0, 1.0)) / np.maximum(cosine, 1e-3)
        unhidden_by_mesh = distance <= nearest + np.minimum(tolerance + slant, GRAZING_VOXELS * voxel)

        uv, depth = project(vertices, view.c2w, view.k)
        col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        candidates = np.flatnonzero((depth > 0) & (col >= 0) & (col < view.k.w) & (row >= 0) & (row < view.k.h)
                                    & (cosine > 0) & unhidden_by_mesh)
        visible = candidates[distance[candidates] <= reach[row[candidates], col[candidates]] + tolerance]
        cosines[visible, index] = cosine[visible]
    return cosines


def surface_points(grid, frame: FitFrame, frames: list[dict], scale: float, min_opacity: float, report) -> np.ndarray:
    """The expected ray-termination points (normalised world) [N,3] of every training view at `scale` of its size;
    see ray_terminations."""
    return ray_terminations(render_views(grid, frame, frames, scale, 0, report), frame, min_opacity).world(frame)


def snap_to_level(grid, terminations: Terminations, level: float, voxel: float) -> Terminations:
    """Moves each termination point along its ray to where the density first rises through `level`
    within SNAP_VOXELS voxels of it (linear between samples half a voxel apart), so points lie on the
    mesh's surface: a soft fit's expected depth sits inside the object. Rays with no such crossing
    there are dropped."""
    if len(terminations.t) == 0:
        return terminations
    offsets = np.arange(-SNAP_VOXELS, SNAP_VOXELS + 0.25, 0.5) * voxel
    has = np.zeros(len(terminations.t), dtype=bool)
    snapped = np.zeros(len(terminations.t))
    # A chunk of rays at a time: each samples the field (density and SH) at len(offsets) points, and the export
    # snaps hundreds of thousands.
    step = max(CHUNK // len(offsets), 1)
    for start in range(0, len(terminations.t), step):
        part = slice(start, start + step)
        t = terminations.t[part, None] + offsets[None]                                   # [n, S]
        samples = terminations.origins[part, None] + t[..., None] * terminations.directions[part, None]
        density, _ = sample_field(grid, samples.reshape(-1, 3))
        density = density.reshape(t.shape)
        above = density >= level
        rises = above[:, 1:] & ~above[:, :-1]
        first = np.argmax(rises, axis=1)
        rows = np.arange(len(first))
        d0, d1 = density[rows, first], density[rows, first + 1]
        share = np.clip((level - d0) / np.maximum(d1 - d0, 1e-12), 0.0, 1.0)
        has[part] = rises.any(axis=1)
        snapped[part] = t[rows, first] + share * (offsets[1] - offsets[0])
    return Terminations(terminations.origins[has], terminations.directions[has], snapped[has], terminations.opacity[has])


def point_normals(grid, frame: FitFrame, points_world: np.ndarray, voxel: float) -> np.ndarray:
    """Outward normals [N,3] (normalised world): minus the fitted density's gradient at each point."""
    fit_points = frame.from_world(points_world)
    gradient = density_gradient(grid, fit_points, 0.5 * voxel)
    if frame.ndc is not None:
        # The world gradient is J^T times the fit-frame one, J = d(fit point)/d(world point) at each point.
        h = 1e-5
        jacobian = np.stack([(frame.from_world(points_world + h * e) - frame.from_world(points_world - h * e)) / (2 * h)
                             for e in np.eye(3)], axis=2)
        gradient = np.einsum("nji,nj->ni", jacobian, gradient)
    outward = -gradient
    return outward / np.maximum(np.linalg.norm(outward, axis=1, keepdims=True), 1e-12)
