"""Export: the fitted radiance field -> a coloured mesh and a coloured point cloud, in the input frame.

Writes export/mesh.ply, mesh.obj and mesh.glb (one mesh: marching cubes over the fitted density,
view-averaged colours, small pieces and floaters removed, cropped to the foreground, faces no
training view sees dropped, optionally decimated), export/points.ply (points where the training views' rays terminate, with colours and
normals) and export/export.json (the frame, counts, sizes, bounds, level and resolution).

Seen faces: a fit only pins down density where rays stop, so its surfaces are shells whose insides
(and the undersides no camera looks at) are guesses; marching cubes turns them into inner surfaces.
With `unseen: drop` (the default) a face stays only if a training view, rendered from the grid, sees
one of its vertices: facing the camera and not behind the view's own depth (`seen_tolerance` voxels).
The mesh then shows what the photos show and is open where they show nothing.

Frames: geometry is extracted in the fit frame (the normalised world, or NDC for forward scenes),
mapped to the normalised world, cropped there, then written in the input (COLMAP) frame through
scene.json's `input_from_world`, or left in the normalised frame with `frame: normalized`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import trimesh
from scipy.ndimage import maximum_filter
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes
from trimesh.exchange.ply import export_ply

from plenoxels.cameras import Intrinsics, project, rays_from_camera
from pipeline.config import require
from plenoxels.errors import UserError
from pipeline.io import read_json, write_json
from plenoxels.reference import ray_lattice
from plenoxels.render import RenderOptions, native_available, render
from plenoxels.scene_model import SceneModel

NAME = "export"
DEPENDS: tuple[str, ...] = ("normalize", "fit")
VERSION = 1
CODE = ("plenoxels",)

# Real SH basis constant of degree 0: the DC coefficient times this is the colour averaged over all directions.
SH_C0 = 0.28209479177387814
# The fit adds this to the SH sum before its relu, so all-zero coefficients give mid grey (csrc/plenoxels_math.h).
COLOUR_OFFSET = 0.5
# glTF is y-up; these axes make a z-up frame stand upright in glTF viewers, and importers that convert
# glTF to z-up (Blender) get the frame's own coordinates back.
GLTF_FROM_ZUP = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
# Where along the inward normal a vertex's colour is gathered, in voxels (negative: outside the surface).
COLOUR_PROBE_VOXELS = np.arange(-1.0, 3.01, 0.5)
# Points sampled per chunk when asking the grid for values, to bound memory.
CHUNK = 1 << 18
# Fewer opaque training rays than this do not decide the auto level.
MIN_LEVEL_RAYS = 100
# How far (voxels) along its ray a point may move onto the mesh's level.
SNAP_VOXELS = 6.0
# The mesh's own z-buffer (seen_vertices): pixels this many voxels wide, at most this many pixels on a side, and
# at most this much (voxels) of a slanted surface's spread in depth over one pixel forgiven.
ZBUFFER_PIXEL_VOXELS = 2.0
MAX_ZBUFFER_PIXELS = 4096
GRAZING_VOXELS = 3.0
# The auto level: rays at least this opaque decide it, at most LEVEL_RAYS of them (a seeded subset), each sampled
# MARCH_STEP_VOXELS apart until its optical depth reaches PEAK_OPTICAL_DEPTH (95% opaque).
LEVEL_RAY_OPACITY = 0.95
LEVEL_RAYS = 20_000
MARCH_STEP_VOXELS = 0.5
PEAK_OPTICAL_DEPTH = -math.log(0.05)


@dataclass
class Settings:
    frame: Literal["input", "normalized"] = "input"   # input: the poses' (COLMAP) frame; normalized: the fit's world
    resolution: int | Literal["auto"] = "auto"         # marching-cubes cells along the grid's longest axis; auto: the fit's own
    level: float | Literal["auto"] = "auto"            # density iso-level; auto: see level_share
    level_share: float = 0.5          # auto level: this share of the peak density the opaque training rays meet (auto_level)
    level_opacity: float = 0.5        # auto level without such points: the density at which one voxel is this opaque
    crop_margin: float = 0.05         # the foreground box is grown by this share of its size before cropping
    min_piece_fraction: float = 0.01  # pieces with fewer faces than this share of the largest piece are dropped
    max_gap: float = 0.05             # pieces farther than this share of the foreground diagonal from the largest are dropped
    target_faces: int = 0             # decimate to this many faces; 0 keeps every face
    points: int = 200_000             # points kept in points.ply (a random, seeded subset)
    point_scale: float = 0.5          # training views are rendered at this share of their size (points, seen faces)
    point_views: int = 0              # training views rendered for the points; 0: all
    point_opacity: float = 0.5        # a pixel gives a point only where its ray is at least this opaque
    unseen: Literal["drop", "keep"] = "drop"  # faces no training view sees (insides of the fit's shells, undersides)
    seen_tolerance: float = 1.0       # a vertex this many voxels behind what a view's pixel sees is still seen
    seed: int = 0

    def check(self) -> None:
        require(self.resolution == "auto" or 8 <= self.resolution <= 2048,
                "export.resolution must be auto or between 8 and 2048 cells")
        require(self.level == "auto" or self.level > 0, "export.level must be auto or a positive density")
        require(0.0 < self.level_share < 1.0, "export.level_share must be in (0, 1)")
        require(0.0 < self.level_opacity < 1.0, "export.level_opacity must be in (0, 1)")
        require(self.crop_margin >= 0.0, "export.crop_margin must be 0 or more")
        require(0.0 <= self.min_piece_fraction <= 1.0, "export.min_piece_fraction must be in [0, 1]")
        require(self.max_gap > 0.0, "export.max_gap must be positive")
        require(self.target_faces == 0 or self.target_faces >= 4, "export.target_faces must be 0 (keep all) or at least 4")
        require(self.points >= 0, "export.points must be 0 (no point cloud) or more")
        require(0.0 < self.point_scale <= 1.0, "export.point_scale must be in (0, 1]")
        require(self.point_views >= 0, "export.point_views must be 0 (all training views) or more")
        require(0.0 < self.point_opacity < 1.0, "export.point_opacity must be in (0, 1)")
        require(self.seen_tolerance >= 0.0, "export.seen_tolerance must be 0 or more voxels")


# ---------------------------------------------------------------------------------------------------
# The fitted grid, read through its documented attributes only


@dataclass
class Lattice:
    """Raw (pre-activation) density on a regular lattice of the fit frame: vertex (i, j, k) is at
    origin + (i, j, k) * spacing. Unallocated grid vertices hold 0, as the renderer reads them."""
    values: np.ndarray    # [X, Y, Z] float32
    origin: np.ndarray    # [3]
    spacing: np.ndarray   # [3]

    @property
    def voxel(self) -> float:
        return float(np.mean(self.spacing))


def _numpy(x: Any) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def grid_box(grid) -> tuple[np.ndarray, np.ndarray]:
    return _numpy(grid.bbox_min).astype(np.float64).reshape(3), _numpy(grid.bbox_max).astype(np.float64).reshape(3)


def grid_lattice_voxel(grid) -> float:
    """The mean spacing of the grid's vertices, in fit-frame units."""
    lo, hi = grid_box(grid)
    return float(np.mean((hi - lo) / (np.array(_numpy(grid.links).shape) - 1)))


def grid_lattice_voxel_world(grid, frame: "FitFrame", mesh: trimesh.Trimesh) -> float:
    """The grid's voxel in world units, measured at the mesh's centre (NDC voxels grow with depth)."""
    if frame.ndc is None or len(mesh.vertices) == 0:
        return grid_lattice_voxel(grid)
    centre = frame.from_world(np.asarray(mesh.vertices).mean(0, keepdims=True))
    step = grid_lattice_voxel(grid)
    return float(np.mean([np.linalg.norm(frame.to_world(centre + step * e) - frame.to_world(centre)) for e in np.eye(3)]))


def grid_lattice(grid) -> Lattice:
    """The grid's own vertices as a dense array of raw density."""
    links = _numpy(grid.links)
    density = _numpy(grid.density).reshape(-1).astype(np.float32)
    values = np.zeros(links.shape, dtype=np.float32)
    allocated = links >= 0
    values[allocated] = density[links[allocated]]
    lo, hi = grid_box(grid)
    return Lattice(values, lo, (hi - lo) / (np.array(links.shape) - 1))


def refine(lattice: Lattice, resolution: int, level: float) -> Lattice:
    """The lattice resampled (trilinearly, as the renderer interpolates) so its longest axis has
    `resolution` cells, over the part that holds density above `level` only (plus one cell)."""
    cells = np.array(lattice.values.shape) - 1
    factor = resolution / cells.max()
    if abs(factor - 1.0) < 1e-9:
        return lattice
    above = np.argwhere(lattice.values > level)
    if len(above) == 0:
        return lattice
    lo = np.maximum(above.min(0) - 1, 0)
    hi = np.minimum(above.max(0) + 1, cells)
    crop = lattice.values[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1, lo[2]:hi[2] + 1]
    size = [max(2, int(round((h - l) * factor)) + 1) for l, h in zip(lo, hi)]
    fine = torch.nn.functional.interpolate(torch.from_numpy(np.ascontiguousarray(crop))[None, None], size=size,
                                           mode="trilinear", align_corners=True)[0, 0].numpy()
    spacing = lattice.spacing * (hi - lo) / (np.array(size) - 1)
    return Lattice(fine, lattice.origin + lo * lattice.spacing, spacing)


def ray_peaks(grid, rays: "Terminations") -> np.ndarray:
    """Per ray [N] (fit frame): the highest density it meets, sampled as the renderer samples it (clipped to the grid
    box, MARCH_STEP_VOXELS apart), until it is all but opaque (optical depth PEAK_OPTICAL_DEPTH); NaN for a ray that
    leaves the box before it has let half its light through."""
    lattice = ray_lattice(grid, torch.as_tensor(rays.origins), torch.as_tensor(rays.directions),
                          RenderOptions(step_size=MARCH_STEP_VOXELS).check())
    t_start, dt, n = (lattice[key].numpy() for key in ("t_start", "dt", "n"))
    steps = np.arange(16)                               # a chunk of samples per ray per pass
    optical_depth, peak = np.zeros(len(n)), np.zeros(len(n))
    done_samples = np.zeros(len(n), dtype=np.int64)
    marching = np.flatnonzero(n > 0)
    while len(marching):
        index = done_samples[marching, None] + steps[None]                            # [M, S]
        t = t_start[marching, None] + (index + 0.5) * dt[marching, None]
        density, _ = _sample(grid, (rays.origins[marching, None] + t[..., None] * rays.directions[marching, None]
                                    ).reshape(-1, 3))
        density = np.where(index < n[marching, None], density.reshape(t.shape), 0.0)
        depth = optical_depth[marching, None] + np.cumsum(density * dt[marching, None], axis=1)
        # Samples up to and including the one that makes the ray all but opaque.
        upto = np.concatenate([np.ones((len(marching), 1), dtype=bool), depth[:, :-1] < PEAK_OPTICAL_DEPTH], axis=1)
        peak[marching] = np.maximum(peak[marching], np.where(upto, density, 0.0).max(axis=1))
        optical_depth[marching] = depth[:, -1]
        done_samples[marching] += len(steps)
        marching = marching[(depth[:, -1] < PEAK_OPTICAL_DEPTH) & (done_samples[marching] < n[marching])]
    return np.where(optical_depth >= math.log(2.0), peak, np.nan)


def auto_level(grid, lattice: Lattice, opaque_rays: "Terminations | None", s: Settings) -> tuple[float, str]:
    """The iso-level the fit itself suggests, and how it was chosen.

    With enough opaque training rays (fit frame): `level_share` of the median of the peak density each meets before it
    is all but opaque (ray_peaks). A fit blurs each surface into a ramp of density over a few voxels; a blurred step's
    edge lies at half its height, and a ray sees the ramp's top before it is opaque, for soft and sharp fits alike. (On
    the synthetic object scene the fit's solids are soft shells over an empty foam, so the density at the rays' expected
    depth, inside the foam, does not say where the surface is.) Without such rays: the density at which one voxel of
    travel has `level_opacity` opacity, sigma = -ln(1 - opacity) / voxel (density is per fit-frame unit)."""
    if opaque_rays is not None and len(opaque_rays.t) >= MIN_LEVEL_RAYS:
        if len(opaque_rays.t) > LEVEL_RAYS:
            pick = np.random.default_rng(s.seed).choice(len(opaque_rays.t), LEVEL_RAYS, replace=False)
            opaque_rays = opaque_rays.subset(np.sort(pick))
        peaks = ray_peaks(grid, opaque_rays)
        peaks = peaks[peaks > 0]
        if len(peaks) >= MIN_LEVEL_RAYS:
            median = float(np.median(peaks))
            return s.level_share * median, (f"auto: {s.level_share:g} x the median peak density ({median:.4g}) that "
                                            f"{len(peaks)} opaque training rays meet before they are 95% opaque")
    level = -math.log(1.0 - s.level_opacity) / lattice.voxel
    return level, f"auto: one voxel ({lattice.voxel:.4g} fit units) at this density is {s.level_opacity:.0%} opaque"


def extract_surface(lattice: Lattice, level: float) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes at `level`: vertices [V,3] in the fit frame and faces [F,3] wound so their
    normals point out of the dense region."""
    if not (lattice.values > level).any():
        peak = float(lattice.values.max(initial=0.0))
        raise UserError(f"no fitted density reaches the export level {level:.3g} (the highest is {peak:.3g}); "
                        f"set export.level lower")
    padded = np.pad(lattice.values, 1, constant_values=min(0.0, float(lattice.values.min())))
    vertices, faces, _, _ = marching_cubes(padded, level=level, spacing=tuple(lattice.spacing))
    vertices = vertices - lattice.spacing + lattice.origin
    # skimage winds faces so their normals point towards decreasing values: flip them to point outwards.
    return vertices, np.ascontiguousarray(faces[:, ::-1])


def _sample(grid, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Density [N] (activated) and SH [N, 3, K] at fit-frame points, in chunks."""
    densities, coefficients = [], []
    for start in range(0, len(points), CHUNK):
        chunk = torch.as_tensor(points[start:start + CHUNK], dtype=torch.float32)
        with torch.no_grad():
            density, sh = grid.sample(chunk)
        densities.append(np.maximum(_numpy(density).reshape(-1), 0.0))
        coefficients.append(_numpy(sh).reshape(len(chunk), 3, -1))
    if not densities:
        return np.zeros(0), np.zeros((0, 3, 1))
    return np.concatenate(densities), np.concatenate(coefficients)


def density_gradient(grid, points: np.ndarray, step: float) -> np.ndarray:
    """Central-difference gradient [N,3] of the activated density at fit-frame points."""
    offsets = np.eye(3) * step
    stacked = np.concatenate([points + o for o in offsets] + [points - o for o in offsets])
    density, _ = _sample(grid, stacked)
    density = density.reshape(6, len(points))
    return (density[:3] - density[3:]).T / (2 * step)


def surface_colours(grid, points: np.ndarray, voxel: float) -> np.ndarray:
    """View-averaged colour [N,3] in [0,1] at surface points of the fit frame.

    Each point's colour is composited, as a ray would be, along a short probe that enters the surface
    against the density gradient, from one voxel outside to a few inside: the colour a camera facing
    the surface sees, rather than the grey that unallocated neighbours would blend into a colour read
    at the surface itself. Each sample's colour is the SH degree-0 term (the mean over directions)."""
    if len(points) == 0:
        return np.zeros((0, 3))
    gradient = density_gradient(grid, points, 0.5 * voxel)
    inward = gradient / np.maximum(np.linalg.norm(gradient, axis=1, keepdims=True), 1e-12)
    offsets = COLOUR_PROBE_VOXELS * voxel
    probes = points[None] + offsets[:, None, None] * inward[None]
    density, sh = _sample(grid, probes.reshape(-1, 3))
    density = density.reshape(len(offsets), len(points))
    colour = np.clip(SH_C0 * sh[:, :, 0] + COLOUR_OFFSET, 0.0, 1.0).reshape(len(offsets), len(points), 3)
    alpha = 1.0 - np.exp(-density * (offsets[1] - offsets[0]))
    transmittance = np.cumprod(np.vstack([np.ones((1, len(points))), 1.0 - alpha[:-1]]), axis=0)
    weight = transmittance * alpha
    total = weight.sum(0)
    # Where the probe finds (almost) nothing, fall back to the colour one voxel inside.
    one_inside = int(np.argmin(np.abs(COLOUR_PROBE_VOXELS - 1.0)))
    blended = (weight[..., None] * colour).sum(0) / np.maximum(total, 1e-12)[:, None]
    return np.where((total > 1e-3)[:, None], blended, colour[one_inside])


# ---------------------------------------------------------------------------------------------------
# Mesh cleaning


@dataclass
class CleanReport:
    faces_in: int
    cropped_faces: int
    pieces: int
    dropped_small: int
    dropped_far: int


def clean_mesh(mesh: trimesh.Trimesh, box_min: np.ndarray, box_max: np.ndarray, min_piece_fraction: float,
               max_gap: float) -> tuple[trimesh.Trimesh, CleanReport]:
    """Crops to the box (faces with a vertex outside go), then keeps the largest connected piece and
    every piece that is both big enough and close enough to it. `max_gap` is in the mesh's units."""
    faces_in = len(mesh.faces)
    inside = np.all((mesh.vertices >= box_min) & (mesh.vertices <= box_max), axis=1)
    keep_faces = inside[mesh.faces].all(axis=1)
    mesh = _submesh(mesh, keep_faces)
    cropped = faces_in - len(mesh.faces)
    if len(mesh.faces) == 0:
        return mesh, CleanReport(faces_in, cropped, 0, 0, 0)

    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    sizes = np.bincount(labels)
    main = int(np.argmax(sizes))
    main_tree = cKDTree(mesh.vertices[np.unique(mesh.faces[labels == main])])
    kept, small, far = {main}, 0, 0
    for label in np.argsort(-sizes):
        if label == main:
            continue
        if sizes[label] < min_piece_fraction * sizes[main]:
            small += 1
            continue
        gap, _ = main_tree.query(mesh.vertices[np.unique(mesh.faces[labels == label])], k=1)
        if gap.min() > max_gap:
            far += 1
            continue
        kept.add(int(label))
    mesh = _submesh(mesh, np.isin(labels, list(kept)))
    return mesh, CleanReport(faces_in, cropped, len(sizes), small, far)


def _submesh(mesh: trimesh.Trimesh, face_mask: np.ndarray) -> trimesh.Trimesh:
    """The faces in face_mask, with unreferenced vertices removed and vertex colours carried along."""
    faces = mesh.faces[face_mask]
    used = np.unique(faces)
    remap = np.full(len(mesh.vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    out = trimesh.Trimesh(mesh.vertices[used], remap[faces], process=False)
    if mesh.visual.kind == "vertex":
        out.visual.vertex_colors = mesh.visual.vertex_colors[used]
    return out


def decimate(mesh: trimesh.Trimesh, target_faces: int) -> trimesh.Trimesh:
    """Quadric decimation (fast-simplification through trimesh) to about target_faces."""
    if target_faces <= 0 or len(mesh.faces) <= target_faces:
        return mesh
    return mesh.simplify_quadric_decimation(face_count=target_faces)


# ---------------------------------------------------------------------------------------------------
# Frames


def transform_points(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def transform_normals(matrix: np.ndarray, normals: np.ndarray) -> np.ndarray:
    n = normals @ np.linalg.inv(matrix[:3, :3])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


class FitFrame:
    """Maps between the fit frame (where the grid lives) and the normalised world: the identity, or NDC."""

    def __init__(self, ndc=None):
        self.ndc = ndc

    def to_world(self, points: np.ndarray) -> np.ndarray:
        if self.ndc is None:
            return points
        return self.ndc.points_to_world(torch.as_tensor(points, dtype=torch.float64)).numpy()

    def from_world(self, points: np.ndarray) -> np.ndarray:
        if self.ndc is None:
            return points
        return self.ndc.points_to_ndc(torch.as_tensor(points, dtype=torch.float64)).numpy()

    def flips_orientation(self, near: np.ndarray) -> bool:
        """Whether the map to the world mirrors (its Jacobian at `near` has a negative determinant),
        which reverses which side of a face is out. The NDC map is smooth, so one point decides."""
        if self.ndc is None:
            return False
        h = 1e-4
        columns = [(self.to_world(near[None] + h * e) - self.to_world(near[None] - h * e))[0] / (2 * h) for e in np.eye(3)]
        return bool(np.linalg.det(np.stack(columns, axis=1)) < 0)


def mesh_to_world(vertices: np.ndarray, faces: np.ndarray, frame: FitFrame) -> tuple[np.ndarray, np.ndarray]:
    world = frame.to_world(vertices)
    if len(vertices) and frame.flips_orientation(vertices.mean(0)):
        faces = faces[:, ::-1]
    return world, np.ascontiguousarray(faces)


# ---------------------------------------------------------------------------------------------------
# The point cloud


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
    expected termination point (opacity-normalised) and the ray's opacity. The rays themselves are
    recomputed when needed, so a hundred large views stay small in memory."""
    c2w: np.ndarray
    k: Intrinsics
    t: np.ndarray         # float32
    opacity: np.ndarray   # float32

    def rays(self, frame: FitFrame) -> tuple[np.ndarray, np.ndarray]:
        """Fit-frame origins and unit directions [h*w, 3]."""
        origins, directions = _fit_rays(self.c2w, self.k, frame)
        directions = directions.numpy()
        return origins.numpy(), directions / np.linalg.norm(directions, axis=1, keepdims=True)


def _fit_rays(c2w: np.ndarray, k: Intrinsics, frame: FitFrame) -> tuple[torch.Tensor, torch.Tensor]:
    origins, directions = rays_from_camera(c2w, k, dtype=torch.float64)
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    if frame.ndc is not None:
        origins, directions = frame.ndc.rays(origins, directions)
    return origins, directions


def render_views(grid, frame: FitFrame, frames: list[dict], s: Settings, report) -> list[ViewRender]:
    """The training views (every one, or `point_views` of them) at `point_scale` of their size.

    Only the fitted grid is rendered (never a background model), so unbounded and forward scenes
    give foreground depths only; forward scenes' rays go through NDC."""
    backend = "native" if native_available() else "torch"
    train = [f for f in frames if f.get("split", "train") == "train"] or frames
    if s.point_views and len(train) > s.point_views:
        pick = np.linspace(0, len(train) - 1, s.point_views).round().astype(int)
        train = [train[i] for i in pick]
    views = []
    for record in report.track(train, desc="rendering the training views' depth"):
        k = Intrinsics.from_frame(record).scaled(s.point_scale)
        c2w = np.asarray(record["transform_matrix"], dtype=np.float64)
        origins, directions = _fit_rays(c2w, k, frame)
        out = render(grid, origins.float(), directions.float(), backend=backend)
        opacity = _numpy(out.opacity).astype(np.float64)
        # The renderer's depth (along the unit direction) is a sum of weights that total the opacity: divide it out.
        t = _numpy(out.depth).astype(np.float64) / np.maximum(opacity, 1e-12)
        views.append(ViewRender(c2w, k, t.astype(np.float32), opacity.astype(np.float32)))
    return views


def ray_terminations(grid, frame: FitFrame, frames: list[dict], s: Settings, report,
                     views: list[ViewRender] | None = None) -> Terminations:
    """The expected ray-termination points of the training views' pixels whose rays are at least
    `point_opacity` opaque (see render_views)."""
    views = render_views(grid, frame, frames, s, report) if views is None else views
    parts = [Terminations(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0))]
    for view in views:
        good = view.opacity >= s.point_opacity
        origins, directions = view.rays(frame)
        parts.append(Terminations(origins[good], directions[good], view.t[good].astype(np.float64),
                                  view.opacity[good].astype(np.float64)))
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
    """Which vertices [V] (normalised world) some training view sees: in its image, on the side of the
    surface facing the camera, not behind what the view's pixel sees by more than `tolerance` (world
    units), and not behind a nearer layer of the mesh itself.

    The rendered view: a pixel less than `opacity` opaque hides nothing. Elsewhere the pixel's termination
    distance is the largest of the opaque ones in its 3x3 neighbourhood, so a vertex on a silhouette is
    not hidden by the far side of its own edge.
    The mesh's own layers: a fit's solids can come out as soft shells over an empty foam whose walls the
    rendered depth, averaged over the shell and the foam, does not hide (on the synthetic object scene half
    the mesh was such walls, 1-5% of the object inside its true surface). Against a z-buffer of the mesh's
    vertices (`voxel`: world units) a vertex is hidden when a nearer one in its pixel is more than the
    tolerance nearer, plus what the surface's slant spreads over one pixel, up to GRAZING_VOXELS."""
    vertices = np.asarray(mesh.vertices)
    normals = np.asarray(mesh.vertex_normals)
    seen = np.zeros(len(vertices), dtype=bool)
    for view in views:
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
                                    & (cosine > 0) & unhidden_by_mesh & ~seen)
        visible = distance[candidates] <= reach[row[candidates], col[candidates]] + tolerance
        seen[candidates[visible]] = True
    return seen


def surface_points(grid, frame: FitFrame, frames: list[dict], s: Settings, report) -> np.ndarray:
    """The expected ray-termination points (normalised world) [N,3]; see ray_terminations."""
    return ray_terminations(grid, frame, frames, s, report).world(frame)


def snap_to_level(grid, terminations: Terminations, level: float, voxel: float) -> Terminations:
    """Moves each termination point along its ray to where the density first rises through `level`
    within SNAP_VOXELS voxels of it (linear between samples half a voxel apart), so points lie on the
    mesh's surface: a soft fit's expected depth sits inside the object. Rays with no such crossing
    there are dropped."""
    if len(terminations.t) == 0:
        return terminations
    offsets = np.arange(-SNAP_VOXELS, SNAP_VOXELS + 0.25, 0.5) * voxel
    t = terminations.t[:, None] + offsets[None]                                   # [N, S]
    samples = terminations.origins[:, None] + t[..., None] * terminations.directions[:, None]
    density, _ = _sample(grid, samples.reshape(-1, 3))
    density = density.reshape(t.shape)
    above = density >= level
    rises = above[:, 1:] & ~above[:, :-1]
    has = rises.any(axis=1)
    first = np.argmax(rises, axis=1)
    rows = np.arange(len(first))
    d0, d1 = density[rows, first], density[rows, first + 1]
    share = np.clip((level - d0) / np.maximum(d1 - d0, 1e-12), 0.0, 1.0)
    snapped = t[rows, first] + share * (offsets[1] - offsets[0])
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


# ---------------------------------------------------------------------------------------------------
# Writing


def write_mesh_files(mesh: trimesh.Trimesh, folder: Path) -> dict[str, str]:
    """mesh.ply (binary, with normals and colours), mesh.obj (vertex colours) and mesh.glb (y-up axes)."""
    paths = {"ply": folder / "mesh.ply", "obj": folder / "mesh.obj", "glb": folder / "mesh.glb"}
    paths["ply"].write_bytes(export_ply(mesh, encoding="binary", vertex_normal=True))
    mesh.export(paths["obj"], include_normals=True)
    gltf = mesh.copy()
    gltf.apply_transform(GLTF_FROM_ZUP)
    gltf.export(paths["glb"])
    return {k: str(p.name) for k, p in paths.items()}


def write_points(path: Path, points: np.ndarray, colours: np.ndarray, normals: np.ndarray) -> None:
    """A binary PLY of vertices with normals and 8-bit colours (no faces)."""
    cloud = trimesh.Trimesh(vertices=points, faces=np.zeros((0, 3), dtype=np.int64), vertex_normals=normals,
                            vertex_colors=_rgba8(colours), process=False)
    path.write_bytes(export_ply(cloud, encoding="binary", vertex_normal=True))


def _in_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.all((points >= lo) & (points <= hi), axis=1)


def _rgba8(colours: np.ndarray) -> np.ndarray:
    rgb = np.round(np.clip(colours, 0.0, 1.0) * 255).astype(np.uint8)
    return np.concatenate([rgb, np.full((len(rgb), 1), 255, dtype=np.uint8)], axis=1)


def _size(n_bytes: int) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n_bytes < 1000 or unit == "GB":
            return f"{n_bytes:.0f} {unit}" if unit == "B" else f"{n_bytes:.1f} {unit}"
        n_bytes /= 1000
    return f"{n_bytes} B"


def _count(n: int) -> str:
    return f"{n / 1e6:.2f}M" if n >= 1e6 else f"{n / 1e3:.1f}k" if n >= 1e4 else str(n)


def _bounds(points: np.ndarray) -> dict:
    if len(points) == 0:
        return {"min": None, "max": None}
    return {"min": points.min(0).round(6).tolist(), "max": points.max(0).round(6).tolist()}


# ---------------------------------------------------------------------------------------------------
# Judging a mesh against a reference surface (tests and benchmarks)


def mesh_scores(mesh: trimesh.Trimesh, reference: trimesh.Trimesh, tolerance: float, samples: int = 200_000,
                reference_visible=None, seed: int = 0) -> dict:
    """Accuracy and completeness of `mesh` against `reference`, both sampled uniformly by area.

    accuracy: distances from the mesh's samples to the reference surface; completeness: from the
    reference's samples to the mesh surface, counting only reference samples for which
    `reference_visible(points) -> bool mask` holds (the surface some camera saw) when it is given.
    F-score at `tolerance`, Chamfer (mean of the two mean distances), and the largest distance from
    any mesh vertex to the reference."""
    rng = np.random.default_rng(seed)
    mesh_points = _area_samples(mesh, samples, rng)[0]
    reference_points = _area_samples(reference, samples, rng)[0]
    if reference_visible is not None:
        reference_points = reference_points[reference_visible(reference_points)]
    to_reference = surface_distance(reference, mesh_points, rng)
    to_mesh = surface_distance(mesh, reference_points, rng)
    precision = float((to_reference < tolerance).mean())
    recall = float((to_mesh < tolerance).mean())
    return {
        "tolerance": tolerance,
        "precision": precision,
        "recall": recall,
        "f_score": 2 * precision * recall / max(precision + recall, 1e-12),
        "chamfer": float((to_reference.mean() + to_mesh.mean()) / 2),
        "accuracy_mean": float(to_reference.mean()),
        "completeness_mean": float(to_mesh.mean()),
        "max_vertex_distance": float(surface_distance(reference, np.asarray(mesh.vertices), rng).max()),
        "reference_samples_used": len(reference_points),
    }


def surface_distance(mesh: trimesh.Trimesh, points: np.ndarray, rng: np.random.Generator, candidates: int = 8) -> np.ndarray:
    """Distance [N] from each point to the surface of `mesh`: exact point-triangle distances to the
    faces of the nearest of a dense set of surface samples (no spatial index library needed)."""
    samples, faces = _area_samples(mesh, max(50_000, 4 * len(mesh.faces)), rng)
    samples = np.concatenate([samples, np.asarray(mesh.triangles_center)])
    faces = np.concatenate([faces, np.arange(len(mesh.faces))])
    _, nearest = cKDTree(samples).query(points, k=candidates)
    candidate_faces = faces[nearest]                                  # [N, k]
    triangles = np.asarray(mesh.triangles)[candidate_faces.reshape(-1)]
    closest = trimesh.triangles.closest_point(triangles, np.repeat(points, candidates, axis=0))
    distance = np.linalg.norm(closest - np.repeat(points, candidates, axis=0), axis=1)
    return distance.reshape(len(points), candidates).min(axis=1)


def _area_samples(mesh: trimesh.Trimesh, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points [count, 3] uniform by area on the mesh, and the face [count] each lies on."""
    triangles = np.asarray(mesh.triangles)
    area = np.asarray(mesh.area_faces)
    face = rng.choice(len(triangles), size=count, p=area / area.sum())
    u, v = rng.uniform(size=(2, count))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = triangles[face]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0]), face


# ---------------------------------------------------------------------------------------------------
# The stage


def build_mesh(grid, frame: FitFrame, box_min: np.ndarray, box_max: np.ndarray, s: Settings, report,
               level_rays: Terminations | None = None, views: list[ViewRender] | None = None) -> tuple[trimesh.Trimesh, dict]:
    """The cleaned, coloured mesh in the normalised world, and what was decided on the way.
    `level_rays`: the training views' opaque rays (fit frame), for the auto level;
    `views`: the training views rendered, to drop the faces none of them sees (with unseen: drop)."""
    lattice = grid_lattice(grid)
    if s.level == "auto":
        level, level_source = auto_level(grid, lattice, level_rays, s)
    else:
        level, level_source = float(s.level), "set"
    native = int(np.max(lattice.values.shape) - 1)
    resolution = native if s.resolution == "auto" else int(s.resolution)
    fine = refine(lattice, resolution, level)
    report.info(f"marching cubes at density {level:.4g} on a {'x'.join(map(str, fine.values.shape))} lattice")
    vertices, faces = extract_surface(fine, level)
    world, faces = mesh_to_world(vertices, faces, frame)
    mesh = trimesh.Trimesh(world, faces, process=False)

    size = box_max - box_min
    margin = s.crop_margin * size
    mesh, cleaning = clean_mesh(mesh, box_min - margin, box_max + margin, s.min_piece_fraction,
                                s.max_gap * float(np.linalg.norm(size)))
    if len(mesh.faces) == 0:
        raise UserError("the mesh is empty after cropping to the foreground box; check normalize's foreground "
                        "or raise export.crop_margin")
    unseen_faces = 0
    if s.unseen == "drop" and views:
        voxel_world = grid_lattice_voxel_world(grid, frame, mesh)
        seen = seen_vertices(mesh, views, frame, voxel_world, s.seen_tolerance * voxel_world, s.point_opacity)
        keep = seen[mesh.faces].any(axis=1)
        unseen_faces = int((~keep).sum())
        mesh, _ = clean_mesh(_submesh(mesh, keep), box_min - margin, box_max + margin, s.min_piece_fraction,
                             s.max_gap * float(np.linalg.norm(size)))
        if len(mesh.faces) == 0:
            raise UserError("no training view sees any part of the mesh; set export.unseen=keep")
    faces_before_decimation = len(mesh.faces)
    mesh = decimate(mesh, s.target_faces)
    colours = surface_colours(grid, frame.from_world(np.asarray(mesh.vertices)), lattice.voxel)
    mesh.visual.vertex_colors = _rgba8(colours)
    decisions = {
        "level": level,
        "level_source": level_source,
        "resolution": resolution,
        "fit_resolution": list(lattice.values.shape),
        "lattice": list(fine.values.shape),
        "voxel": fine.voxel,
        "cleaning": vars(cleaning),
        "unseen_faces_dropped": unseen_faces,
        "faces_before_decimation": faces_before_decimation,
        "decimated": len(mesh.faces) < faces_before_decimation,
    }
    return mesh, decisions


def run(ctx) -> dict:
    s: Settings = ctx.settings
    scene = read_json(ctx.upstream["normalize"] / "scene.json")
    model = SceneModel.load(ctx.upstream["fit"])
    grid = model.grid
    frame = FitFrame(model.ndc)
    box_min = np.asarray(scene["foreground"]["min"], dtype=np.float64)
    box_max = np.asarray(scene["foreground"]["max"], dtype=np.float64)

    crop_min, crop_max = box_min - s.crop_margin * (box_max - box_min), box_max + s.crop_margin * (box_max - box_min)
    views = render_views(grid, frame, scene["frames"], s, ctx.report)
    terminations = ray_terminations(grid, frame, scene["frames"], s, ctx.report, views)
    ends = terminations.world(frame)
    inside = _in_box(ends, crop_min, crop_max)
    terminations = terminations.subset(inside)
    # The level comes from nearly opaque rays only: a fainter one grazes an edge or crosses a thin part, whose peak is low.
    opaque = terminations.opacity >= LEVEL_RAY_OPACITY
    mesh, decisions = build_mesh(grid, frame, box_min, box_max, s, ctx.report, terminations.subset(opaque), views)

    voxel = grid_lattice_voxel(grid)
    if len(terminations.t) > 2 * s.points:  # the snap drops some rays: keep a margin, subsample after
        terminations = terminations.subset(np.random.default_rng(s.seed).choice(len(terminations.t), 2 * s.points,
                                                                                  replace=False))
    points = snap_to_level(grid, terminations, decisions["level"], voxel).world(frame)
    # A ray that grazes the foreground can snap onto matter beyond it (the ground of an unbounded scene).
    points = points[_in_box(points, crop_min, crop_max)]
    if len(points) > s.points:
        points = points[np.sort(np.random.default_rng(s.seed).choice(len(points), s.points, replace=False))]
    colours = surface_colours(grid, frame.from_world(points), voxel)
    normals = point_normals(grid, frame, points, voxel)
    if len(terminations.t) == 0:
        ctx.report.warn(f"no training-view pixel is {s.point_opacity:.0%} opaque inside the foreground box: the "
                        "level comes from export.level_opacity and points.ply is empty; lower export.point_opacity")

    if s.frame == "input":
        to_output = np.asarray(scene["input_from_world"], dtype=np.float64)
        mesh.apply_transform(to_output)
        points, normals = transform_points(to_output, points), transform_normals(to_output, normals)
    else:
        to_output = np.eye(4)
    files = write_mesh_files(mesh, ctx.work)
    if s.points > 0:
        write_points(ctx.work / "points.ply", points, colours, normals)
        files["points"] = "points.ply"
    sizes = {name: (ctx.work / f).stat().st_size for name, f in files.items()}

    frame_name = "input (the poses' COLMAP frame)" if s.frame == "input" else "normalized (z up, foreground in [-1, 1]^3)"
    record = {
        "frame": s.frame,
        "frame_description": frame_name,
        "output_from_normalized": to_output.tolist(),
        "scene_type": scene.get("type"),
        "fit_frame": "ndc" if frame.ndc is not None else "normalized",
        "files": files,
        "file_bytes": sizes,
        "mesh": {"vertices": len(mesh.vertices), "faces": len(mesh.faces), "bounds": _bounds(mesh.vertices)},
        "points": {"count": len(points), "bounds": _bounds(points)},
        "glb_axes": "glTF y-up: (x, z, -y) of the frame; z-up importers such as Blender's restore the frame's coordinates",
        **decisions,
    }
    write_json(ctx.work / "export.json", record)
    lo, hi = record["mesh"]["bounds"]["min"], record["mesh"]["bounds"]["max"]
    line = (f"mesh {_count(len(mesh.faces))} faces ({_size(sizes['ply'])} PLY), {_count(len(points))} points "
            f"({_size(sizes.get('points', 0))}) in the {s.frame} frame, bounds "
            f"[{', '.join(f'{v:.3g}' for v in lo)}] to [{', '.join(f'{v:.3g}' for v in hi)}], "
            f"level {decisions['level']:.3g}{' (auto)' if s.level == 'auto' else ''}, resolution {decisions['resolution']}")
    return {"line": line, "frame": s.frame, "faces": len(mesh.faces), "vertices": len(mesh.vertices),
            "points": len(points), "level": decisions["level"], "resolution": decisions["resolution"]}
