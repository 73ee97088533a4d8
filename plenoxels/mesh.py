"""A mesh from the fitted density: lattice, auto level, marching cubes, surface colours, cleaning, decimation.

Geometry is extracted in the fit frame (`plenoxels.fit_frame.FitFrame`) and mapped to the normalised world with
`mesh_to_world`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from plenoxels.errors import UserError
from plenoxels.fit_frame import FitFrame
from plenoxels.render import COLOUR_OFFSET, SH_C0, RenderOptions, ray_samples
from plenoxels.surface import Terminations, as_numpy, density_gradient, sample_field

# Where along the inward normal a vertex's colour is gathered, in voxels (negative: outside the surface).
COLOUR_PROBE_VOXELS = np.arange(-1.0, 3.01, 0.5)
# Fewer opaque training rays than this do not decide the auto level.
MIN_LEVEL_RAYS = 100
# The auto level: rays at least this opaque decide it, at most LEVEL_RAYS of them (a seeded subset), each sampled
# MARCH_STEP_VOXELS apart until its optical depth reaches PEAK_OPTICAL_DEPTH (95% opaque).
LEVEL_RAY_OPACITY = 0.95
LEVEL_RAYS = 20_000
MARCH_STEP_VOXELS = 0.5
PEAK_OPTICAL_DEPTH = -math.log(0.05)


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


def grid_box(grid) -> tuple[np.ndarray, np.ndarray]:
    return as_numpy(grid.bbox_min).astype(np.float64).reshape(3), as_numpy(grid.bbox_max).astype(np.float64).reshape(3)


def grid_lattice_voxel(grid) -> float:
    """The mean spacing of the grid's vertices, in fit-frame units."""
    lo, hi = grid_box(grid)
    return float(np.mean((hi - lo) / (np.array(as_numpy(grid.links).shape) - 1)))


def grid_lattice_voxel_world(grid, frame: FitFrame, mesh: trimesh.Trimesh) -> float:
    """The grid's voxel in world units, measured at the mesh's centre (NDC voxels grow with depth)."""
    if frame.ndc is None or len(mesh.vertices) == 0:
        return grid_lattice_voxel(grid)
    centre = frame.from_world(np.asarray(mesh.vertices).mean(0, keepdims=True))
    step = grid_lattice_voxel(grid)
    return float(np.mean([np.linalg.norm(frame.to_world(centre + step * e) - frame.to_world(centre)) for e in np.eye(3)]))


def grid_lattice(grid) -> Lattice:
    """The grid's own vertices as a dense array of raw density."""
    links = as_numpy(grid.links)
    density = as_numpy(grid.density).reshape(-1).astype(np.float32)
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


def ray_peaks(grid, rays: Terminations) -> np.ndarray:
    """Per ray [N] (fit frame): the highest density it meets, sampled as the renderer samples it (clipped to the grid
    box, MARCH_STEP_VOXELS apart), until it is all but opaque (optical depth PEAK_OPTICAL_DEPTH); NaN for a ray that
    leaves the box before it has let half its light through."""
    lattice = ray_samples(grid, torch.as_tensor(rays.origins), torch.as_tensor(rays.directions),
                          RenderOptions(step_size=MARCH_STEP_VOXELS).check())
    t_start, dt, n = (lattice[key].numpy() for key in ("t_start", "dt", "n"))
    steps = np.arange(16)                               # a chunk of samples per ray per pass
    optical_depth, peak = np.zeros(len(n)), np.zeros(len(n))
    done_samples = np.zeros(len(n), dtype=np.int64)
    marching = np.flatnonzero(n > 0)
    while len(marching):
        index = done_samples[marching, None] + steps[None]                            # [M, S]
        t = t_start[marching, None] + (index + 0.5) * dt[marching, None]
        density, _ = sample_field(grid, (rays.origins[marching, None] + t[..., None] * rays.directions[marching, None]
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


def auto_level(grid, lattice: Lattice, opaque_rays: Terminations | None, share: float, opacity: float,
               seed: int = 0) -> tuple[float, str]:
    """The iso-level the fit itself suggests, and how it was chosen.

    With enough opaque training rays (fit frame): `share` of the median of the peak density each meets before it
    is all but opaque (ray_peaks). A fit blurs each surface into a ramp of density over a few voxels; a blurred step's
    edge lies at half its height, and a ray sees the ramp's top before it is opaque, for soft and sharp fits alike. (On
    the synthetic object scene the fit's solids are soft shells over an empty foam, so the density at the rays' expected
    depth, inside the foam, does not say where the surface is.) Without such rays: the density at which one voxel of
    travel has `opacity` opacity, sigma = -ln(1 - opacity) / voxel (density is per fit-frame unit)."""
    if opaque_rays is not None and len(opaque_rays.t) >= MIN_LEVEL_RAYS:
        if len(opaque_rays.t) > LEVEL_RAYS:
            pick = np.random.default_rng(seed).choice(len(opaque_rays.t), LEVEL_RAYS, replace=False)
            opaque_rays = opaque_rays.subset(np.sort(pick))
        peaks = ray_peaks(grid, opaque_rays)
        peaks = peaks[peaks > 0]
        if len(peaks) >= MIN_LEVEL_RAYS:
            median = float(np.median(peaks))
            return share * median, (f"auto: {share:g} x the median peak density ({median:.4g}) that "
                                            f"{len(peaks)} opaque training rays meet before they are 95% opaque")
    level = -math.log(1.0 - opacity) / lattice.voxel
    return level, f"auto: one voxel ({lattice.voxel:.4g} fit units) at this density is {opacity:.0%} opaque"


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
    density, sh = sample_field(grid, probes.reshape(-1, 3))
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
    mesh = submesh(mesh, keep_faces)
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
    mesh = submesh(mesh, np.isin(labels, list(kept)))
    return mesh, CleanReport(faces_in, cropped, len(sizes), small, far)


def submesh(mesh: trimesh.Trimesh, face_mask: np.ndarray) -> trimesh.Trimesh:
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


def transform_points(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def transform_normals(matrix: np.ndarray, normals: np.ndarray) -> np.ndarray:
    n = normals @ np.linalg.inv(matrix[:3, :3])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def mesh_to_world(vertices: np.ndarray, faces: np.ndarray, frame: FitFrame) -> tuple[np.ndarray, np.ndarray]:
    world = frame.to_world(vertices)
    if len(vertices) and frame.flips_orientation(vertices.mean(0)):
        faces = faces[:, ::-1]
    return world, np.ascontiguousarray(faces)
