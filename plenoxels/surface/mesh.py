"""A mesh from the fitted density: lattice, auto level, marching cubes, surface colours, cleaning, decimation.

Geometry is extracted in the fit frame (`plenoxels.core.fit_frame.FitFrame`) and mapped to the normalised world with
`mesh_to_world`.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from plenoxels.core.errors import UserError
from plenoxels.core.fit_frame import FitFrame
from plenoxels.core.memory import release_freed
from plenoxels.core.options import MeshOptions
from plenoxels.surface.ground import RIM_SHARE, cut_ground, find_ground, reaches_box_sides
from plenoxels.core.render import COLOUR_OFFSET, SH_C0, RenderOptions, ray_samples
from plenoxels.surface.views import Terminations, ViewRender, as_numpy, density_gradient, sample_field, seen_vertices

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
# Free space is where the opaque training rays pass: these shares of the way to where each ends.
FREE_SPACE_SHARES = (0.25, 0.5, 0.75)


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
    """The mean spacing of the grid's vertices, in fit-frame units (where they are finest, on a grid with knots)."""
    return float(np.mean(1.0 / np.asarray(grid.scale)))


def grid_lattice_voxel_world(grid, frame: FitFrame, mesh: trimesh.Trimesh) -> float:
    """The grid's voxel in world units, measured at the mesh's centre (NDC voxels grow with depth)."""
    if frame.ndc is None or len(mesh.vertices) == 0:
        return grid_lattice_voxel(grid)
    centre = frame.from_world(np.asarray(mesh.vertices).mean(0, keepdims=True))
    step = grid_lattice_voxel(grid)
    return float(np.mean([np.linalg.norm(frame.to_world(centre + step * e) - frame.to_world(centre)) for e in np.eye(3)]))


def grid_lattice(grid, box: tuple[np.ndarray, np.ndarray] | None = None) -> Lattice:
    """The grid's own vertices as a dense array of raw density. A grid with knots: its raw density as the renderer
    interpolates it, on a lattice of its finest cells' spacing over `box` (fit frame; the grid's whole box without one),
    so a surface crosses from fine cells to coarse ones without a crack."""
    if grid.warped:
        lo, hi = grid_box(grid)
        if box is not None:
            lo, hi = np.maximum(lo, box[0]), np.minimum(hi, box[1])
        spacing = 1.0 / np.asarray(grid.scale)
        shape = np.maximum(np.ceil((hi - lo) / spacing - 1e-9).astype(int) + 1, 2)
        spacing = (hi - lo) / (shape - 1)
        y, z = np.meshgrid(lo[1] + np.arange(shape[1]) * spacing[1], lo[2] + np.arange(shape[2]) * spacing[2],
                           indexing="ij")
        values = np.stack([sample_field(grid, np.stack([np.full_like(y, lo[0] + i * spacing[0]), y, z], -1)
                                        .reshape(-1, 3))[0].reshape(y.shape) for i in range(shape[0])])
        return Lattice(values.astype(np.float32), lo, spacing)
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
    steps = np.arange(16)                               # a chunk of samples per ray per pass
    optical_depth, peak = np.zeros(len(rays.origins)), np.zeros(len(rays.origins))
    for piece in range(lattice["n"].shape[1]):          # a grid with knots cuts rays into pieces
        t_start, dt, n = (lattice[key][:, piece].numpy() for key in ("t_start", "dt", "n"))
        done_samples = np.zeros(len(n), dtype=np.int64)
        marching = np.flatnonzero((n > 0) & (optical_depth < PEAK_OPTICAL_DEPTH))
        while len(marching):
            index = done_samples[marching, None] + steps[None]                        # [M, S]
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


# The 13 lines through a lattice cell (each direction up to its sign): an opening is ringed by solid along every
# line of some plane through it.
LATTICE_LINES = tuple(d for d in itertools.product((-1, 0, 1), repeat=3) if d > (0, 0, 0))
PLANE_LINES = tuple(tuple(d for d in LATTICE_LINES if np.dot(d, normal) == 0) for normal in LATTICE_LINES)
# Slabs of the lattice sealed at a time (planes along its first axis), to bound the memory on large lattices.
SEAL_SLAB = 32


def _ringed(solid: np.ndarray, reach: int) -> np.ndarray:
    """Free cells with solid within `reach` cells on both sides along every line of some plane through them."""
    padded = np.pad(solid, reach)
    n = solid.shape

    def solid_at(d, k):   # solid at cell + k * d, for every cell
        return padded[tuple(slice(reach + k * c, reach + k * c + n[i]) for i, c in enumerate(d))]

    bracketed = {}
    for d in LATTICE_LINES:
        ahead, behind = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        for k in range(1, reach + 1):
            ahead |= solid_at(d, k)
            behind |= solid_at(d, -k)
        bracketed[d] = ahead & behind
    ringed = np.zeros(n, dtype=bool)
    for lines in PLANE_LINES:
        ringed |= np.logical_and.reduce([bracketed[d] for d in lines])
    return ringed & ~solid


def seal_openings(lattice: Lattice, level: float, rays: Terminations | None, reach: int) -> tuple[Lattice, dict]:
    """The lattice with the fitted solids' small openings sealed and their enclosed cavities filled (raised above
    `level`), and what was filled.

    A fit of a few small photos makes its solids soft shells over an empty foam, their skins pierced by openings
    a voxel or a few across. Marching cubes meshes the foam's walls too; the unseen faces go, and a camera then
    sees through each opening into the object, and out of it where no view saw the far side. A cell is sealed when
    solid rings it within `reach` cells along every line of some plane through it (repeated until nothing changes),
    which closes an opening in a sheet up to 2 * reach - 1 cells across but leaves open what solid brackets along
    one line only (a slot, the gap between two solids) or meets along an edge (where an object stands on the
    ground); a corner where three faces meet inwards (a room's) is rounded by up to `reach` cells. Then every region
    of free space that neither reaches the lattice's border nor holds the opaque training `rays` (fit frame) on
    their way to their ends (FREE_SPACE_SHARES of the way) is a cavity inside a solid and is filled, so its walls
    are not meshed."""
    solid = lattice.values > level
    if reach <= 0 or not solid.any():
        return lattice, {"voxels": 0, "sealed": 0, "cavities": 0}
    sealed = np.zeros_like(solid)
    changed = solid   # a cell's ring can only close where something within the reach changed
    for _ in range(2 * reach):
        new = np.zeros_like(solid)
        for start in range(0, solid.shape[0], SEAL_SLAB):
            lo, hi = max(start - reach, 0), min(start + SEAL_SLAB + reach, solid.shape[0])
            if changed[lo:hi].any():
                ringed = _ringed(solid[lo:hi] | sealed[lo:hi], reach)
                new[start:start + SEAL_SLAB] = ringed[start - lo:start - lo + SEAL_SLAB]
        if not new.any():
            break
        sealed |= new
        changed = new
    labels, count = ndimage.label(~(solid | sealed))
    reached = np.zeros(count + 1, dtype=bool)
    reached[0] = True   # label 0: the solid and the sealed cells
    for axis in range(3):
        for end in (0, -1):
            reached[np.unique(np.take(labels, end, axis=axis))] = True
    if rays is not None and len(rays.t):
        shape = np.array(labels.shape)
        for share in FREE_SPACE_SHARES:
            points = rays.origins + (share * rays.t)[:, None] * rays.directions
            index = np.round((points - lattice.origin) / lattice.spacing).astype(np.int64)
            index = index[((index >= 0) & (index < shape)).all(axis=1)]
            reached[np.unique(labels[index[:, 0], index[:, 1], index[:, 2]])] = True
    cavities = ~reached[labels]
    filled = sealed | cavities
    if not filled.any():
        return lattice, {"voxels": 0, "sealed": 0, "cavities": 0}
    values = lattice.values.copy()
    values[filled] = np.maximum(values[filled], 2.0 * level if level > 0 else level + 1.0)
    return Lattice(values, lattice.origin, lattice.spacing), {"voxels": int(filled.sum()), "sealed": int(sealed.sum()),
                                                              "cavities": int((~reached[1:]).sum())}


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
    dropped_room: int = 0


def clean_mesh(mesh: trimesh.Trimesh, box_min: np.ndarray, box_max: np.ndarray, min_piece_fraction: float,
               max_gap: float, anchored: np.ndarray | None = None, room_reach: float | None = None
               ) -> tuple[trimesh.Trimesh, CleanReport]:
    """Crops to the box (faces with a vertex outside go), then keeps the largest connected piece and every piece
    that is big enough and either close enough to it (`max_gap`, the mesh's units) or holds an `anchored` vertex
    [V] (one that stood on the ground that was cut away). With `room_reach`, a piece that comes that close to one
    of the box's vertical sides is the room the box cut through, and goes (plenoxels.surface.ground.reaches_box_sides)."""
    faces_in = len(mesh.faces)
    inside = np.all((mesh.vertices >= box_min) & (mesh.vertices <= box_max), axis=1)
    keep_faces = inside[mesh.faces].all(axis=1)
    if anchored is not None:
        anchored = anchored & inside
    mesh, anchored = submesh(mesh, keep_faces, anchored)
    cropped = faces_in - len(mesh.faces)
    if len(mesh.faces) == 0:
        return mesh, CleanReport(faces_in, cropped, 0, 0, 0)

    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    sizes = np.bincount(labels)
    room = (reaches_box_sides(mesh, labels, box_min, box_max, room_reach) if room_reach is not None
            else np.zeros(len(sizes), dtype=bool))
    if room.all():  # the box cuts through everything: nothing tells the object from the room
        room[:] = False
    main = int(np.argmax(np.where(room, -1, sizes)))
    on_ground = (np.bincount(labels[anchored[mesh.faces].any(axis=1)], minlength=len(sizes)) > 0
                 if anchored is not None else np.zeros(len(sizes), dtype=bool))
    main_tree = cKDTree(mesh.vertices[np.unique(mesh.faces[labels == main])])
    kept, small, far, room_pieces = {main}, 0, 0, 0
    for label in np.argsort(-sizes):
        if label == main:
            continue
        if room[label]:
            room_pieces += 1
            continue
        if sizes[label] < min_piece_fraction * sizes[main]:
            small += 1
            continue
        if not on_ground[label]:
            gap, _ = main_tree.query(mesh.vertices[np.unique(mesh.faces[labels == label])], k=1)
            if gap.min() > max_gap:
                far += 1
                continue
        kept.add(int(label))
    mesh, _ = submesh(mesh, np.isin(labels, list(kept)))
    return mesh, CleanReport(faces_in, cropped, len(sizes), small, far, room_pieces)


def submesh(mesh: trimesh.Trimesh, face_mask: np.ndarray, vertex_mask: np.ndarray | None = None
            ) -> tuple[trimesh.Trimesh, np.ndarray | None]:
    """The faces in face_mask, with unreferenced vertices removed and vertex colours carried along, and
    `vertex_mask` [V] (if any) for the vertices that stay."""
    faces = mesh.faces[face_mask]
    used = np.unique(faces)
    remap = np.full(len(mesh.vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    out = trimesh.Trimesh(mesh.vertices[used], remap[faces], process=False)
    if mesh.visual.kind == "vertex":
        out.visual.vertex_colors = mesh.visual.vertex_colors[used]
    return out, (vertex_mask[used] if vertex_mask is not None else None)


def boundary_vertices(mesh: trimesh.Trimesh) -> np.ndarray:
    """The vertices [V] on an edge that only one face has (the edges of holes and of open surfaces)."""
    unique, counts = np.unique(np.sort(np.asarray(mesh.edges), axis=1), axis=0, return_counts=True)
    on_boundary = np.zeros(len(mesh.vertices), dtype=bool)
    on_boundary[unique[counts == 1].ravel()] = True
    return on_boundary


def topology(mesh: trimesh.Trimesh) -> dict:
    """What decimation must not change: boundary loops (the edges of holes and of open surfaces), the Euler number
    and the connected pieces; and the non-manifold edges (more than two faces), which it must not add."""
    unique, counts = np.unique(np.sort(np.asarray(mesh.edges), axis=1), axis=0, return_counts=True)
    boundary = unique[counts == 1]
    loops = 0
    if len(boundary):
        graph = coo_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(len(mesh.vertices),) * 2)
        _, labels = connected_components(graph, directed=False)
        loops = len(np.unique(labels[boundary[:, 0]]))
    pieces = len(np.unique(trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))))
    return {"faces": len(mesh.faces), "boundary_loops": loops, "boundary_edges": len(boundary),
            "non_manifold_edges": int((counts > 2).sum()), "euler": int(mesh.euler_number), "pieces": pieces}


def decimate(mesh: trimesh.Trimesh, max_faces: int) -> tuple[trimesh.Trimesh, dict]:
    """Quadric decimation (fast-simplification through trimesh) to at most about `max_faces` faces (0: every face
    kept), and the topology before and after. Its collapses keep boundary vertices on the boundary, so open edges
    stay where they were and no hole opens; the record lets a test and the summary say so. No face it leaves repeats
    another's three vertices."""
    before = topology(mesh)
    if max_faces <= 0 or len(mesh.faces) <= max_faces:
        return mesh, {"decimated": False, "before": before, "after": before}
    simplified = mesh.simplify_quadric_decimation(face_count=max_faces)
    # Its collapses can leave two faces on the same three vertices, which importers (Blender's) merge into one.
    simplified.update_faces(simplified.unique_faces() & simplified.nondegenerate_faces())
    simplified.remove_unreferenced_vertices()
    return simplified, {"decimated": True, "before": before, "after": topology(simplified)}


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


# normalize's world frame is z up: the direction the ground's normal is looked for around.
WORLD_UP = np.array([0.0, 0.0, 1.0])
# A piece the box cut through comes within this many voxels of the box's vertical sides.
ROOM_REACH_VOXELS = 2.0


def isolate_object(mesh: trimesh.Trimesh, box_min: np.ndarray, box_max: np.ndarray, voxel: float, options: MeshOptions,
                   user_box: bool, max_gap: float | None = None) -> tuple[trimesh.Trimesh, dict]:
    """The mesh without the ground it stands on and the room around it (plenoxels/surface/ground.py), and what was cut.
    `voxel`: world units; `user_box`: the box is the user's crop, which may cut through the object on purpose, so no
    piece goes for reaching its sides; `max_gap`: clean_mesh's (None: options.max_gap of the box's diagonal)."""
    faces_in = len(mesh.faces)
    ground = find_ground(mesh, WORLD_UP, box_min, box_max, voxel, options.seed)
    record = {"ground": ground.describe() if ground is not None else None, "ground_faces_cut": 0,
              "room_pieces_dropped": 0, "faces_before": faces_in}
    if ground is None or not ground.is_ground:
        record.update(faces_after=faces_in, cut="nothing: " + (
            "no plane under the object" if ground is None else
            f"the plane under the object reaches {ground.rim_share:.0%} of the box's edge, so it is part of the object"
            if ground.rim_share < RIM_SHARE else "nothing stands on the plane found"))
        return mesh, record
    keep, touching = cut_ground(mesh, ground)
    cut, anchored = submesh(mesh, keep, touching)
    if max_gap is None:
        max_gap = options.max_gap * float(np.linalg.norm(box_max - box_min))
    cleaned, report = clean_mesh(cut, box_min, box_max, options.min_piece_fraction, max_gap, anchored=anchored,
                                 room_reach=None if user_box else ROOM_REACH_VOXELS * voxel)
    if len(cleaned.faces) == 0:
        record.update(faces_after=faces_in, cut="nothing: cutting the ground left no object")
        return mesh, record
    record.update(ground_faces_cut=int((~keep).sum()), room_pieces_dropped=report.dropped_room,
                  small_pieces_dropped=report.dropped_small, far_pieces_dropped=report.dropped_far,
                  faces_after=len(cleaned.faces))
    share = 1.0 - len(cleaned.faces) / max(faces_in, 1)
    record["cut"] = (f"the ground (a plane tilted {ground.tilt_deg:.1f} deg from up, reaching {ground.rim_share:.0%} of "
                     f"the box's edge) and what lies below it" +
                     (f", {report.dropped_room} piece{'s' * (report.dropped_room != 1)} of the room at the box's edge"
                      if report.dropped_room else "") + f": {share:.0%} of the faces")
    return cleaned, record


def build_mesh(grid, frame: FitFrame, box_min: np.ndarray, box_max: np.ndarray, options: MeshOptions, report,
               level_rays: Terminations | None = None, views: list[ViewRender] | None = None,
               object_only: bool = False, user_box: bool = False, masked: bool = False) -> tuple[trimesh.Trimesh, dict]:
    """The cleaned, coloured, decimated mesh in the normalised world, and what was decided on the way.
    `level_rays`: the training views' opaque rays (fit frame), for the auto level; `views`: the training views
    rendered, to drop the faces none of them sees (with unseen: drop); `object_only`: cut the ground and the room
    away (isolate_object); `user_box`: the box is the user's crop; `masked`: every photo's mask drew what is the
    object, so a piece big enough stays however far it lies from the largest (several objects on a turntable)."""
    size = box_max - box_min
    crop_min, crop_max = box_min - options.crop_margin * size, box_max + options.crop_margin * size
    box = (frame.from_world(crop_min[None])[0], frame.from_world(crop_max[None])[0]) if grid.warped else None
    lattice = grid_lattice(grid, box)
    if options.level == "auto":
        level, level_source = auto_level(grid, lattice, level_rays, options.level_share, options.level_opacity,
                                         options.seed)
    else:
        level, level_source = float(options.level), "set"
    native = int(np.max(lattice.values.shape) - 1)
    resolution = native if options.resolution == "auto" else int(options.resolution)
    lattice, filled = seal_openings(lattice, level, level_rays, options.fill_voxels)
    fine = refine(lattice, resolution, level)
    report.info(f"marching cubes at density {level:.4g} on a {'x'.join(map(str, fine.values.shape))} lattice")
    mesh = trimesh.Trimesh(*mesh_to_world(*extract_surface(fine, level), frame), process=False)
    # The lattices go before the per-vertex work, and each step's temporaries after it: glibc keeps freed pages, and
    # they would stay charged to the steps after (plenoxels/core/memory.py, release_freed).
    voxel, fit_shape = lattice.voxel, list(lattice.values.shape)
    fine_shape, fine_voxel = list(fine.values.shape), fine.voxel
    del lattice, fine
    release_freed()

    max_gap = math.inf if masked else options.max_gap * float(np.linalg.norm(size))
    mesh, cleaning = clean_mesh(mesh, crop_min, crop_max, options.min_piece_fraction, max_gap)
    if len(mesh.faces) == 0:
        raise UserError("the mesh is empty after cropping to the foreground box; check normalize's foreground "
                        "or raise export.crop_margin")
    voxel_world = grid_lattice_voxel_world(grid, frame, mesh)
    unseen_faces = 0
    if options.unseen == "drop" and views:
        seen = seen_vertices(mesh, views, frame, voxel_world, options.seen_tolerance * voxel_world,
                             options.point_opacity)
        keep = seen[mesh.faces].any(axis=1)
        unseen_faces = int((~keep).sum())
        mesh, _ = clean_mesh(submesh(mesh, keep)[0], crop_min, crop_max, options.min_piece_fraction, max_gap)
        if len(mesh.faces) == 0:
            raise UserError("no training view sees any part of the mesh; set export.unseen=keep")
        release_freed()
    isolation = {"on": False, "cut": "nothing: export.object_only is off"}
    if object_only:
        mesh, isolation = isolate_object(mesh, crop_min, crop_max, voxel_world, options, user_box, max_gap)
        isolation["on"] = True
    mesh, decimation = decimate(mesh, options.max_faces)
    release_freed()
    colours = surface_colours(grid, frame.from_world(np.asarray(mesh.vertices)), voxel)
    mesh.visual.vertex_colors = colours  # trimesh rounds [0, 1] floats to 8 bits
    decisions = {
        "level": level,
        "level_source": level_source,
        "resolution": resolution,
        "fit_resolution": fit_shape,
        "lattice": fine_shape,
        "voxel": fine_voxel,
        "voxel_world": voxel_world,
        "filled": filled,
        "cleaning": vars(cleaning),
        "pieces_apart_kept": masked,
        "unseen_faces_dropped": unseen_faces,
        "object_only": isolation,
        "decimation": decimation,
        "faces_before_decimation": decimation["before"]["faces"],
        "decimated": decimation["decimated"],
    }
    return mesh, decisions
