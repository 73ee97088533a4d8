"""Moves a mesh's vertices along their normals to where the training views agree on their colour.

Marching cubes puts the surface where the fitted density crosses a level, but the photos pin down where the colour
is: a fit's solid is a soft shell whose level set can sit a voxel or two off the surface the views see. Baked into a
texture, that offset shows: each view's ray through a vertex meets the surface a little to the side, by the offset
times the tangent of its angle, so the views baked into a texel and a new camera looking at it see different parts
of the surface (on a finely patterned object, most of the texture's error). Multi-view stereo's answer: try depths
along the normal and keep the one where the views that see the vertex agree best on its colour.

Per vertex: up to `view_count` of the training views that see it (plenoxels.surface.views.view_cosines), each weighted by
its squared cosine with the surface, and their renders from the fitted grid (plenoxels.surface.views.render_views, the
colour divided by the opacity). Candidates lie every STEP_VOXELS along the normal within `reach` voxels. A
candidate's cost is the weighted variance of the colours those renders show where it projects; one that any of the
views sees through (a pixel less than OPAQUE opaque) is not on the surface and is never chosen. A prior keeps the
fitted surface unless the views clearly agree better elsewhere (PRIOR_PER_VOXEL, on the vertex's own median cost,
at least COST_FLOOR: a uniform colour gives no reason to move). A vertex stays where it is when fewer than MIN_VIEWS
views see it, or when even their best agreement is poor (colours more than AGREEMENT apart, a standard deviation):
a surface whose colour turns with the view (a highlight, a sheen) gives no depth, and on a strongly view-dependent
field the depth of least disagreement drifts off the surface. A view that meets the vertex on its silhouette (a pixel
around it not opaque) leaves its set: what lies behind mixes in there. The mesh's open edges, where it was cut or no
view saw on, and BOUNDARY_RINGS rings inside them stay: the colour places a surface, not where it ends (on the
synthetic rooms, free edges at the ground's cut moved inwards and lost pixels the objects cover). The chosen offsets
are smoothed over the mesh's edges (SMOOTHING passes, each vertex with the mean of its neighbours), so one noisy
vertex does not tear the surface. One pass only: repeated passes roughen the surface more than they help
(bench/README.md).
"""
from __future__ import annotations

import numpy as np
import trimesh

from plenoxels.core.cameras import project
from plenoxels.core.fit_frame import FitFrame
from plenoxels.surface.mesh import boundary_vertices
from plenoxels.surface.views import ViewRender, view_cosines
from plenoxels.surface.texture import sample_pixels

# Candidate offsets along the normal are this many voxels apart.
STEP_VOXELS = 0.5
# A candidate's cost grows by this share of the vertex's median cost per squared voxel of offset...
PRIOR_PER_VOXEL = 0.05
# ...that median taken as at least this variance (colours 0.01 apart: a couple of 8-bit levels, noise).
COST_FLOOR = 1e-4
# A vertex whose views' colours stay further apart than this (standard deviation, colours in [0, 1]) stays.
AGREEMENT = 0.1
# Passes of neighbour averaging over the chosen offsets.
SMOOTHING = 2
# A vertex moves only if at least this many views see it.
MIN_VIEWS = 2
# A view's pixel this opaque shows the surface; a fainter one is seen through.
OPAQUE = 0.5
# Rings of vertices inside the mesh's open edges that stay where they are.
BOUNDARY_RINGS = 2


def align_to_views(mesh: trimesh.Trimesh, views: list[ViewRender], frame: FitFrame, voxel: float, tolerance: float,
                   opacity: float, reach: float, view_count: int = 8) -> tuple[trimesh.Trimesh, dict]:
    """The mesh (normalised world) with each vertex moved along its normal, by up to `reach` voxels (`voxel`: world
    units), to where the views (with their colours, `rgb`) agree best (module docstring); `tolerance` and `opacity`
    as view_cosines takes them. Returns the new mesh (same faces) and what moved, in voxels."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    steps = int(np.floor(reach / STEP_VOXELS))
    offsets = np.arange(-steps, steps + 1) * STEP_VOXELS
    record = {"reach_voxels": reach, "vertices": len(vertices)}
    if steps == 0 or len(vertices) == 0 or not views or any(view.rgb is None for view in views):
        return mesh, {**record, "moved": 0.0, "median_shift_voxels": 0.0, "p90_shift_voxels": 0.0}

    cosines = view_cosines(mesh, views, frame, voxel, tolerance, opacity)
    best = np.argsort(-cosines, axis=1)[:, :min(view_count, len(views))]
    weight = np.take_along_axis(cosines, best, axis=1).astype(np.float64)
    weight = np.where(weight > 0, weight ** 2, 0.0)
    # Per view: the vertices it serves and their weights, so each candidate projects a vertex into each view once. A
    # view that sees a vertex on its silhouette (not opaque all round) mixes in what lies behind: it does not serve it.
    served = []
    total = np.zeros(len(vertices))
    for index, view in enumerate(views):
        vertex, slot = np.nonzero((best == index) & (weight > 0))
        if len(vertex):
            _, opaque = _sample(view, vertices[vertex])
            vertex, w = vertex[opaque], weight[vertex[opaque], slot[opaque]]
            served.append((view, vertex, w))
            total[vertex] += w
    views_per_vertex = np.zeros(len(vertices), dtype=np.int64)
    for _, vertex, _ in served:
        views_per_vertex[vertex] += 1

    cost = np.full((len(offsets), len(vertices)), np.nan)
    for c, offset in enumerate(offsets):
        points = vertices + offset * voxel * normals
        first = np.zeros((len(vertices), 3))
        second = np.zeros(len(vertices))
        opaque_weight = np.zeros(len(vertices))
        for view, vertex, w in served:
            colour, opaque = _sample(view, points[vertex])
            w = w * opaque
            first[vertex] += w[:, None] * colour  # a view serves a vertex at most once
            second[vertex] += w * (colour ** 2).sum(axis=1)
            opaque_weight[vertex] += w
        on_surface = (total > 0) & (opaque_weight >= total * (1 - 1e-9))
        mean = first[on_surface] / total[on_surface, None]
        cost[c, on_surface] = second[on_surface] / total[on_surface] - (mean ** 2).sum(axis=1)

    known = ~np.isnan(cost).all(axis=0)
    cost[:, ~known] = 0.0
    prior = PRIOR_PER_VOXEL * offsets[:, None] ** 2 * np.maximum(np.nanmedian(cost, axis=0), COST_FLOOR)[None]
    choice = np.argmin(np.where(np.isnan(cost), np.inf, cost + prior), axis=0)
    agreement = np.sqrt(np.maximum(cost[choice, np.arange(len(vertices))], 0.0))
    shift = offsets[choice]
    # Agreement gained over the fitted surface (any, where some view sees through the fitted surface itself).
    gain = np.where(np.isnan(cost[steps]), np.inf, cost[steps] - cost[choice, np.arange(len(vertices))])
    shift[~known | (views_per_vertex < MIN_VIEWS) | (agreement > AGREEMENT) | (gain < COST_FLOOR)] = 0.0
    boundary = boundary_vertices(mesh)
    shift[_grow(boundary, mesh.edges_unique, BOUNDARY_RINGS)] = 0.0
    shift = _smooth(shift, mesh.edges_unique, SMOOTHING)
    shift[boundary] = 0.0

    aligned = trimesh.Trimesh(vertices + (shift * voxel)[:, None] * normals, np.asarray(mesh.faces), process=False)
    magnitude = np.abs(shift)
    return aligned, {**record, "moved": float((magnitude >= STEP_VOXELS / 2).mean()),
                     "median_shift_voxels": float(np.median(shift)),
                     "p90_shift_voxels": float(np.percentile(magnitude, 90))}


def _sample(view: ViewRender, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The view's colour [N, 3] in [0, 1] where world `points` project, bilinear (clamped at the image's edge), and
    whether all four pixels read are at least OPAQUE [N]."""
    pixels, _ = project(points, view.c2w, view.k)
    colour = sample_pixels(view.rgb.reshape(view.k.h, view.k.w, 3), pixels) / 255.0
    opaque = (view.opacity >= OPAQUE).reshape(view.k.h, view.k.w)
    x0, y0 = (np.floor(pixels - 0.5).astype(np.int64)[:, axis] for axis in (0, 1))
    all_opaque = np.ones(len(points), dtype=bool)
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        all_opaque &= opaque[np.clip(y0 + dy, 0, view.k.h - 1), np.clip(x0 + dx, 0, view.k.w - 1)]
    return colour, all_opaque


def _grow(marked: np.ndarray, edges: np.ndarray, rings: int) -> np.ndarray:
    """`marked` [V] and the vertices up to `rings` edges away from one."""
    for _ in range(rings):
        grown = marked.copy()
        grown[edges[:, 0]] |= marked[edges[:, 1]]
        grown[edges[:, 1]] |= marked[edges[:, 0]]
        marked = grown
    return marked


def _smooth(values: np.ndarray, edges: np.ndarray, passes: int) -> np.ndarray:
    """Each pass: every vertex's value becomes the mean of its own and its neighbours' (along `edges`)."""
    degree = np.bincount(edges.ravel(), minlength=len(values)).astype(np.float64)
    for _ in range(passes):
        neighbours = np.bincount(edges[:, 0], weights=values[edges[:, 1]], minlength=len(values))
        neighbours += np.bincount(edges[:, 1], weights=values[edges[:, 0]], minlength=len(values))
        values = (values + neighbours) / (1.0 + degree)
    return values
