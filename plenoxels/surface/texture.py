"""A texture for a mesh: a UV atlas (xatlas), the fitted field's colour baked into it with its seams padded, and a
z-buffer renderer of a textured or vertex-coloured mesh (to hold a texture against the field's own render).

Colour baked (`colour="view"`, the default): what the training views that face the surface most squarely saw there,
i.e. rays rendered by the field itself (`plenoxels.core.render.render`, every SH degree) from a couple of voxels outside
the surface towards it, along the directions from those views' cameras, each composite divided by its opacity; the
texel takes their mean weighted by the squared cosine between the surface's normal and each view (up to `view_count` of
them). Which views see a texel comes from its face's vertices (plenoxels.surface.views.view_cosines: in the image, facing
the camera, not hidden). A texture holds one colour for every viewer, while the field's colour turns with the view
even on a matte surface (its SH fits each photo): rendered from a held-out camera, the field's colour there matches
the texture's only as well as the directions baked stand for that camera's. The mean over several views does that
better than the one view facing most squarely (bench/README.md, "Export"). Only directions some photo saw are pinned down by the fit: its higher SH degrees are free elsewhere,
so the colour along the normal (`colour="normal"`, the fallback where no view sees a texel) strays on any surface no
photo looked at head-on (the lower half of a ball seen from above), and the SH degree-0 term (`colour="mean"`, the
mean over all directions, as the PLY's vertex colours are) averages in every unseen direction.

Seams: every texel a triangle covers, and every texel within GUTTER_TEXELS of one, is baked at the nearest point of
that triangle, so bilinear filtering at a chart's edge reads surface colour; the rest of the atlas is filled by
pull-push (each empty texel takes the coverage-weighted mean of the coarsest level around it that holds colour), so
no mip level, however coarse, averages in a colour that is not the surface's.

UV convention: (u, v) in [0, 1] with v up (OBJ's; trimesh flips it for glTF), texel row r at v = 1 - (r + 0.5) / H.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
import trimesh
import xatlas

from plenoxels.core.cameras import Intrinsics, project
from plenoxels.core.fit_frame import FitFrame
from plenoxels.core.memory import release_freed
from plenoxels.surface.mesh import grid_lattice_voxel, grid_lattice_voxel_world, surface_colours
from plenoxels.core.render import render
from plenoxels.surface.views import ViewRender, view_cosines

# Texels beyond a chart's edge baked with its edge's colour (bilinear filtering reads one; a mip level or two more).
GUTTER_TEXELS = 2
# Pixels (and texels) tested per chunk by the rasteriser, to bound memory.
RASTER_CHUNK = 1 << 20
# The ray baked per texel starts this many voxels outside the surface, along its normal.
BAKE_START_VOXELS = 2.0
# Atlas texels rasterised at a time (a band of its rows): the rasteriser holds some 40 bytes a pixel, and a
# 2048-texel atlas has nearly ten million.
TEXEL_BAND = 1 << 20
# Texels per chunk when choosing each one's view: each holds its face's cosines with every view (1.2 kB with 100).
VIEW_CHUNK = 1 << 14
# Rays rendered per chunk when baking.
BAKE_CHUNK = 1 << 18
# Texels baked at a time: each holds a few hundred bytes of points, normals, views and colours on the way, and a
# 4096-texel atlas has millions.
TEXEL_CHUNK = 1 << 19
# A baked ray at least this opaque gives its colour; fainter ones take the degree-0 colour at the surface.
BAKE_MIN_OPACITY = 0.05
# Faces charted together at most: xatlas merges neighbouring charts at a cost that grows faster than their count
# (jpcy/xatlas#103), and a marching-cubes surface starts as thousands of small ones, so the mesh is charted in spatial
# pieces of this many faces and packed as one atlas (bench/README.md, "Export").
CHART_PIECE_FACES = 8192


@dataclass
class Atlas:
    """A mesh's UV layout: atlas vertex i is mesh vertex `vertex_map[i]` at `uv[i]`; `faces` index atlas vertices
    (the mesh's faces, one to one, with vertices split along the seams); the texture is `size` (width, height)."""
    vertex_map: np.ndarray   # [A] int64
    faces: np.ndarray        # [F, 3] int64
    uv: np.ndarray           # [A, 2] float64
    size: tuple[int, int]
    charts: int
    charted: np.ndarray      # [F] bool: the faces xatlas laid out (not the slivers it found degenerate)


def unwrap(vertices: np.ndarray, faces: np.ndarray, resolution: int) -> Atlas:
    """xatlas charts and packs the mesh into about `resolution` texels on a side, GUTTER_TEXELS + 1 texels apart:
    charted in pieces of at most CHART_PIECE_FACES faces (no chart crosses from one to the next), packed together."""
    vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    pieces = chart_pieces(vertices[faces].mean(axis=1), CHART_PIECE_FACES)
    atlas = xatlas.Atlas()
    piece_vertices = []
    for piece in pieces:
        used, local = np.unique(faces[piece], return_inverse=True)
        piece_vertices.append(used)
        atlas.add_mesh(np.ascontiguousarray(vertices[used], dtype=np.float32),
                       np.ascontiguousarray(local.reshape(-1, 3), dtype=np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = resolution
    pack.padding = GUTTER_TEXELS + 1
    pack.bilinear = True
    atlas.generate(xatlas.ChartOptions(), pack)
    vertex_map, uv = [], []
    atlas_faces = np.zeros((len(faces), 3), dtype=np.int64)
    start = 0
    for i, (piece, used) in enumerate(zip(pieces, piece_vertices)):
        piece_map, piece_faces, piece_uv = (np.asarray(a) for a in atlas[i])
        vertex_map.append(used[piece_map.astype(np.int64)])
        uv.append(piece_uv.astype(np.float64))
        atlas_faces[piece] = piece_faces.astype(np.int64) + start
        start += len(piece_map)
    vertex_map, uv = np.concatenate(vertex_map), np.concatenate(uv)
    # xatlas charts no face it finds degenerate (marching cubes leaves slivers) and leaves its corners at UV (0, 0):
    # give each such corner its vertex's UV in a chart, so even a sliver shows its own surface's colour.
    corners = uv[atlas_faces]
    charted_faces = ~(corners == corners[:, :1]).all(axis=(1, 2))
    charted = np.zeros(len(uv), dtype=bool)
    charted[atlas_faces[charted_faces].ravel()] = True
    in_chart = np.full((int(vertex_map.max(initial=-1)) + 1, 2), np.nan)
    in_chart[vertex_map[charted]] = uv[charted]
    fix = ~charted & np.isfinite(in_chart[vertex_map, 0])
    uv[fix] = in_chart[vertex_map[fix]]
    return Atlas(vertex_map, atlas_faces, uv, (int(atlas.width), int(atlas.height)), int(atlas.chart_count),
                 charted_faces)


def chart_pieces(centres: np.ndarray, most: int) -> list[np.ndarray]:
    """Face indices [n] split in halves along their centres' [F, 3] longest extent until each holds at most `most`."""
    pieces, done = [np.arange(len(centres))], []
    while pieces:
        piece = pieces.pop()
        if len(piece) <= most:
            done.append(piece)
            continue
        axis = int(np.argmax(np.ptp(centres[piece], axis=0)))
        ordered = piece[np.argsort(centres[piece, axis], kind="stable")]
        pieces += [ordered[len(ordered) // 2:], ordered[:len(ordered) // 2]]
    return done


def uv_to_pixels(uv: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """UV [N, 2] -> continuous texel coordinates (x right, y down; texel centres at +0.5)."""
    return np.stack([uv[:, 0] * size[0], (1.0 - uv[:, 1]) * size[1]], axis=-1)


def rasterize(corners: np.ndarray, width: int, height: int, depth: np.ndarray | None = None,
              reach: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Which triangle each pixel centre falls in, vectorised over triangles and the pixels of their bounding boxes.

    corners [F, 3, 2]: pixel coordinates (pixel centres at +0.5). Returns per pixel [h*w] the triangle (-1: none)
    and its barycentric weights [h*w, 3]. With `depth` [F, 3] (positive, along the view) the nearest triangle wins
    and the weights are perspective-correct; without, a pixel no triangle covers but within `reach` pixels of one's
    edge takes the nearest such triangle, at the nearest point on it (texture gutters)."""
    face = np.full(width * height, -1, dtype=np.int64)
    weights = np.zeros((width * height, 3))
    best = np.full(width * height, np.inf)
    area = ((corners[:, 1, 0] - corners[:, 0, 0]) * (corners[:, 2, 1] - corners[:, 0, 1])
            - (corners[:, 1, 1] - corners[:, 0, 1]) * (corners[:, 2, 0] - corners[:, 0, 0]))
    valid = np.isfinite(corners).all(axis=(1, 2)) & (np.abs(area) > 1e-12)
    if depth is not None:
        valid &= (depth > 0).all(axis=1)
    for margin, wanted in ((0.0, None), (reach, "gutter")):
        if wanted is not None:
            if margin <= 0 or depth is not None:
                break
            wanted = face < 0
        for tri, pixel, point in _candidates(corners, valid, width, height, margin, wanted):
            bary, distance = _barycentric(point, corners[tri], area[tri], nearest=margin > 0)
            keep = distance <= margin
            if depth is not None:
                inverse = bary / depth[tri]
                z = 1.0 / inverse.sum(axis=1)
                bary, score = inverse * z[:, None], z
            else:
                score = distance
            tri, pixel, bary, score = tri[keep], pixel[keep], bary[keep], score[keep]
            order = np.lexsort((score, pixel))
            pixel, first = np.unique(pixel[order], return_index=True)
            chosen = order[first]
            better = score[chosen] < best[pixel]
            pixel, chosen = pixel[better], chosen[better]
            best[pixel], face[pixel], weights[pixel] = score[chosen], tri[chosen], bary[chosen]
    return face, weights


def _candidates(corners: np.ndarray, valid: np.ndarray, width: int, height: int, margin: float,
                wanted: np.ndarray | None):
    """(triangle [N], flat pixel [N], pixel centre [N, 2]) for the pixels of each valid triangle's bounding box grown
    by `margin` (only the `wanted` [h*w] ones, when given), in chunks of about RASTER_CHUNK."""
    lo = np.maximum(np.floor(corners.min(axis=1) - 0.5 - margin).astype(np.int64), 0)
    hi = np.minimum(np.ceil(corners.max(axis=1) - 0.5 + margin).astype(np.int64), [width - 1, height - 1])
    span = np.where(valid[:, None], np.maximum(hi - lo + 1, 0), 0)
    count = span[:, 0] * span[:, 1]
    ends = np.cumsum(count)
    start = 0
    while start < len(count):
        before = int(ends[start - 1]) if start else 0   # candidates of the triangles before this chunk
        stop = max(int(np.searchsorted(ends, before + RASTER_CHUNK, side="right")), start + 1)
        tri = np.repeat(np.arange(start, stop), count[start:stop])
        start = stop
        local = before + np.arange(len(tri)) - (ends[tri] - count[tri])   # index in the triangle's own box
        px = lo[tri, 0] + local % np.maximum(span[tri, 0], 1)
        py = lo[tri, 1] + local // np.maximum(span[tri, 0], 1)
        pixel = py * width + px
        if wanted is not None:
            keep = wanted[pixel]
            tri, pixel, px, py = tri[keep], pixel[keep], px[keep], py[keep]
        if len(tri):
            yield tri, pixel, np.stack([px + 0.5, py + 0.5], axis=-1)


def _barycentric(p: np.ndarray, corners: np.ndarray, area: np.ndarray,
                 nearest: bool) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric weights [N, 3] of 2D points in their triangles [N, 3, 2] (signed `area` [N]: twice theirs), and
    the points' distance [N] outside them (0 in or on them; inf without `nearest`). With `nearest`, a point outside
    gets the weights of the nearest point of its triangle."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]

    def cross(o, e1, e2):
        return (e1[:, 0] - o[:, 0]) * (e2[:, 1] - o[:, 1]) - (e1[:, 1] - o[:, 1]) * (e2[:, 0] - o[:, 0])

    bary = np.stack([cross(b, c, p), cross(c, a, p), cross(a, b, p)], axis=-1) / area[:, None]
    inside = (bary >= -1e-9).all(axis=1)
    distance = np.where(inside, 0.0, np.inf)
    if not nearest or inside.all():
        return bary, distance
    out = np.flatnonzero(~inside)
    q, corners = p[out], (a[out], b[out], c[out])
    best = np.full(len(out), np.inf)
    weights = np.zeros((len(out), 3))
    for i in range(3):  # the three edges, i -> i + 1
        e0, e1 = corners[i], corners[(i + 1) % 3]
        edge = e1 - e0
        t = np.clip(np.einsum("ij,ij->i", q - e0, edge) / np.maximum(np.einsum("ij,ij->i", edge, edge), 1e-18), 0, 1)
        d = np.linalg.norm(e0 + t[:, None] * edge - q, axis=1)
        closer = d < best
        best[closer] = d[closer]
        w = np.zeros((len(out), 3))
        w[:, i], w[:, (i + 1) % 3] = 1.0 - t, t
        weights[closer] = w[closer]
    bary[out], distance[out] = weights, best
    return bary, distance


def texel_faces(atlas: Atlas) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texels the atlas's triangles cover or lie within GUTTER_TEXELS of: their flat indices [T] (row-major in
    the atlas image), the mesh face [T, 3] (vertex indices) each lies on and its barycentric weights there [T, 3]."""
    width, height = atlas.size
    charted = np.flatnonzero(atlas.charted)
    corners = uv_to_pixels(atlas.uv, atlas.size)[atlas.faces[charted]]
    top, bottom = corners[..., 1].min(axis=1), corners[..., 1].max(axis=1)
    rows = max(TEXEL_BAND // max(width, 1), 1)
    texels, faces, weights = [], [], []
    for y0 in range(0, height, rows):
        y1 = min(y0 + rows, height)
        # Every triangle whose box, grown by the gutter, reaches these rows: each texel weighs the candidates it
        # would in the whole atlas, in the same order.
        near = np.flatnonzero((bottom >= y0 - GUTTER_TEXELS - 1) & (top <= y1 + GUTTER_TEXELS + 1))
        face, weight = rasterize(corners[near] - np.array([0.0, y0]), width, y1 - y0, reach=GUTTER_TEXELS)
        hit = np.flatnonzero(face >= 0)
        texels.append(hit + y0 * width)
        # Compact: the faces and weights of millions of texels stay until their colours are found.
        faces.append(atlas.vertex_map[atlas.faces[charted[near[face[hit]]]]].astype(np.int32))
        weights.append(weight[hit].astype(np.float32))
    return (np.concatenate(texels) if texels else np.zeros(0, dtype=np.int64),
            np.concatenate(faces) if faces else np.zeros((0, 3), dtype=np.int32),
            np.concatenate(weights) if weights else np.zeros((0, 3), dtype=np.float32))


def texel_surface(vertices: np.ndarray, normals: np.ndarray, atlas: Atlas) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texels of texel_faces, and the surface point [T, 3] and unit normal [T, 3] each stands for (mesh
    vertices' frame)."""
    texels, faces, weights = texel_faces(atlas)
    w = weights[..., None]
    points = (vertices[faces] * w).sum(axis=1)
    n = (normals[faces] * w).sum(axis=1)
    return texels, points, n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def facing_views(faces: np.ndarray, weights: np.ndarray, cosines: np.ndarray, count: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Per surface point (on `faces` [N, 3] at barycentric `weights` [N, 3]), the `count` views that face it most
    squarely, best first [N, count], and their cosines [N, count]: its face's vertices' `cosines` [V, C] (0: unseen)
    blended by the weights."""
    count = min(count, cosines.shape[1])
    best = np.zeros((len(faces), count), dtype=np.int32)   # millions of texels by `count` views: keep it small
    score = np.zeros((len(faces), count), dtype=np.float32)
    for start in range(0, len(faces), VIEW_CHUNK):
        part = slice(start, start + VIEW_CHUNK)
        blended = np.einsum("nk,nkc->nc", weights[part], cosines[faces[part]])
        if count < blended.shape[1]:   # the `count` best by partition: sorting whole rows would take most of the time
            top = np.sort(np.argpartition(-blended, count - 1, axis=1)[:, :count], axis=1)
        else:
            top = np.broadcast_to(np.arange(count), blended.shape)
        # Best first; between equal cosines the lower view.
        top = np.take_along_axis(top, np.argsort(-np.take_along_axis(blended, top, axis=1), axis=1, kind="stable"), 1)
        best[part], score[part] = top, np.take_along_axis(blended, top, axis=1)
    return best, score


def surface_normals(vertices: np.ndarray, faces: np.ndarray, weights: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Unit normals [N, 3] at points on `faces` [N, 3] (vertex indices) at barycentric `weights` [N, 3]: the vertex
    `normals` blended. Where they cancel (a sheet of the mesh folded onto itself, whose vertices' normals point both
    ways) or are not numbers (a degenerate face's), the face's own normal stands in, and up where that has no length."""
    blended = (normals[faces] * weights[..., None]).sum(axis=1)
    length = np.linalg.norm(blended, axis=1)
    flat = ~(length > 1e-9)
    if flat.any():
        corner = vertices[faces[flat]]
        face = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])
        face_length = np.linalg.norm(face, axis=1)
        face[~(face_length > 1e-12)] = (0.0, 0.0, 1.0)
        blended[flat], length[flat] = face, np.where(face_length > 1e-12, face_length, 1.0)
    return blended / length[:, None]


def seen_colours(grid, frame: FitFrame, points: np.ndarray, directions: np.ndarray, voxel_world: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """What the field renders [N, 3] at world surface `points` along rays that start BAKE_START_VOXELS voxels
    (`voxel_world`: world units) out along the unit `directions` (towards the viewer) and look back along them, each
    divided by its opacity, and whether the ray was at least BAKE_MIN_OPACITY opaque [N]. In chunks."""
    colours = np.zeros((len(points), 3))
    opaque = np.zeros(len(points), dtype=bool)
    for start in range(0, len(points), BAKE_CHUNK):
        part = slice(start, start + BAKE_CHUNK)
        p, u = points[part], directions[part]
        origins, rays = frame.rays(torch.as_tensor(p + BAKE_START_VOXELS * voxel_world * u), torch.as_tensor(-u))
        with torch.no_grad():
            out = render(grid, origins.float(), rays.float())
        opacity = out.opacity.detach().cpu().numpy().astype(np.float64)
        rgb = out.rgb.detach().cpu().numpy().astype(np.float64)
        opaque[part] = opacity >= BAKE_MIN_OPACITY
        colours[part] = np.clip(rgb / np.maximum(opacity, BAKE_MIN_OPACITY)[:, None], 0.0, 1.0)
    return colours, opaque


def surface_colour_texels(grid, frame: FitFrame, points: np.ndarray, directions: np.ndarray, voxel_world: float,
                          colour: Literal["view", "normal", "mean"]) -> np.ndarray:
    """The colour [N, 3] of the field at world surface `points`: with "view" or "normal", what the field renders
    looking back along the unit `directions` [N, 3] (towards the viewer: a training view's camera, or the outward
    normal; seen_colours); with "mean", and where that ray stays fainter than BAKE_MIN_OPACITY, the degree-0 colour
    (plenoxels.surface.mesh.surface_colours)."""
    faint = np.ones(len(points), dtype=bool)
    colours = np.zeros((len(points), 3))
    if colour != "mean":
        colours, opaque = seen_colours(grid, frame, points, directions, voxel_world)
        faint = ~opaque
    if faint.any():
        colours[faint] = surface_colours(grid, frame.from_world(points[faint]), grid_lattice_voxel(grid))
    return colours


def view_colour_texels(grid, frame: FitFrame, points: np.ndarray, normals: np.ndarray, best: np.ndarray,
                       cosines: np.ndarray, centres: np.ndarray, voxel_world: float) -> np.ndarray:
    """The colour [N, 3] of the field at world surface `points` as the training views `best` [N, K] (cameras at
    `centres` [C, 3]) saw it, their mean weighted by their squared `cosines` [N, K] (0: not seen) with the surface
    (seen_colours); along the unit `normals` [N, 3] where no view sees a point or every ray there is faint."""
    total = np.zeros((len(points), 3))
    weight = np.zeros(len(points))
    for k in range(best.shape[1]):
        wanted = np.flatnonzero(cosines[:, k] > 0)
        towards = centres[best[wanted, k]] - points[wanted]
        towards /= np.maximum(np.linalg.norm(towards, axis=1, keepdims=True), 1e-12)
        seen, opaque = seen_colours(grid, frame, points[wanted], towards, voxel_world)
        w = cosines[wanted, k].astype(np.float64) ** 2 * opaque
        total[wanted] += w[:, None] * seen
        weight[wanted] += w
    colours = total / np.maximum(weight, 1e-30)[:, None]
    unseen = ~(weight > 0)
    if unseen.any():
        colours[unseen] = surface_colour_texels(grid, frame, points[unseen], normals[unseen], voxel_world, "normal")
    return colours


@dataclass
class Texture:
    """A mesh's atlas and the texture baked into it ([H, W, 3] in [0, 1]), and which colour was baked."""
    atlas: Atlas
    image: np.ndarray
    colour: str


@dataclass
class ViewSight:
    """What baking "view" colour needs of the training views: per mesh vertex and view [V, C], the cosine between the
    vertex normal and the direction to the camera where the view sees it (0: unseen; plenoxels.surface.views.
    view_cosines), and the cameras' centres [C, 3] (world)."""
    cosines: np.ndarray
    centres: np.ndarray


def view_sight(grid, frame: FitFrame, mesh: trimesh.Trimesh, views: list[ViewRender], seen_tolerance: float = 1.0,
               opacity: float = 0.5) -> ViewSight:
    """The views' sight of the mesh (world frame): a vertex `seen_tolerance` voxels behind what a view's pixel at
    least `opacity` opaque sees is still seen (view_cosines)."""
    voxel_world = grid_lattice_voxel_world(grid, frame, mesh)
    return ViewSight(view_cosines(mesh, list(views), frame, voxel_world, seen_tolerance * voxel_world, opacity),
                     np.stack([view.c2w[:3, 3] for view in views]))


def texture_mesh(grid, frame: FitFrame, mesh: trimesh.Trimesh, resolution: int,
                 colour: Literal["view", "normal", "mean"], views: list[ViewRender] = (), seen_tolerance: float = 1.0,
                 opacity: float = 0.5, view_count: int = 1, layout_vertices: np.ndarray | None = None,
                 sight: ViewSight | None = None) -> Texture:
    """Unwraps the mesh (world frame) into an atlas of about `resolution` texels on a side and bakes the field's
    colour into it (module docstring). "view" needs the training `views` (plenoxels.surface.views.render_views), or
    their `sight` of the mesh (view_sight) when the views themselves are let go first, and blends up to `view_count`
    of them per texel. `layout_vertices` [V, 3]: where the atlas is charted, if not at the mesh's own vertices (the
    same faces a little elsewhere); the colour is baked at the mesh's own."""
    if colour == "view" and sight is None:
        if not views:
            raise ValueError('texture colour "view" needs the training views')
        sight = view_sight(grid, frame, mesh, views, seen_tolerance, opacity)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    voxel_world = grid_lattice_voxel_world(grid, frame, mesh)
    atlas = unwrap(vertices if layout_vertices is None else layout_vertices, np.asarray(mesh.faces), resolution)
    texels, faces, weights = texel_faces(atlas)
    release_freed()
    colours = np.empty((len(texels), 3), dtype=np.float32)
    for start in range(0, len(texels), TEXEL_CHUNK):
        part = slice(start, start + TEXEL_CHUNK)
        points = (vertices[faces[part]] * weights[part, :, None]).sum(axis=1)
        outward = surface_normals(vertices, faces[part], weights[part], normals)
        if colour == "view":
            best, facing = facing_views(faces[part], weights[part], sight.cosines, view_count)
            colours[part] = view_colour_texels(grid, frame, points, outward, best, facing, sight.centres, voxel_world)
        else:
            colours[part] = surface_colour_texels(grid, frame, points, outward, voxel_world, colour)
    del faces, weights  # before the bake's full-size images
    release_freed()
    return Texture(atlas, bake(texels, colours, atlas.size), colour)


def _block_sums(a: np.ndarray) -> np.ndarray:
    """The sums of `a` [H, W, ...] over 2x2 blocks, an odd last row or column's blocks over what is there."""
    h, w = a.shape[:2]
    sums = np.zeros(((h + 1) // 2, (w + 1) // 2) + a.shape[2:], dtype=a.dtype)
    for dy, dx in ((0, 0), (0, 1), (1, 0), (1, 1)):
        part = a[dy::2, dx::2]
        sums[:part.shape[0], :part.shape[1]] += part
    return sums


def pull_push(image: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """`image` [H, W, C] (float32) with every texel outside `covered` [H, W] filled from the covered ones, in place:
    each takes the coverage-weighted mean of the finest level of a 2x pyramid that holds colour at its place. A
    2048-texel atlas has nearly ten million texels: past `image` this holds its coverage as weights, the pyramid's
    coarser levels (a third of the finest) and a quarter level's mask at a time: about 15 bytes a texel."""
    image[~covered] = 0.0
    levels = [(image, covered.astype(np.float32))]   # colour weighted by coverage, and the coverage
    while max(levels[-1][1].shape) > 1:
        levels.append(tuple(_block_sums(a) for a in levels[-1]))
    filled = levels[-1][0] / np.maximum(levels[-1][1], 1e-12)[..., None]
    for colour, weight in reversed(levels[:-1]):
        colour /= np.maximum(weight, 1e-12)[..., None]   # at the finest level a covered texel's own colour: weight 1
        for dy, dx in ((0, 0), (0, 1), (1, 0), (1, 1)):
            part, empty = colour[dy::2, dx::2], weight[dy::2, dx::2] == 0
            part[empty] = filled[:part.shape[0], :part.shape[1]][empty]
        filled = colour
    return filled


def bake(texels: np.ndarray, colours: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The texture [H, W, 3] in [0, 1]: `colours` [T, 3] at flat texel indices `texels`, the rest pulled and pushed."""
    width, height = size
    image = np.zeros((height * width, 3), dtype=np.float32)
    covered = np.zeros(height * width, dtype=bool)
    image[texels], covered[texels] = colours, True
    return pull_push(image.reshape(height, width, 3), covered.reshape(height, width))


def sample_texture(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup [N, C] of `image` [H, W, C] at UV [N, 2] (edges clamped)."""
    height, width = image.shape[:2]
    return sample_pixels(image, uv_to_pixels(uv, (width, height)))


def sample_pixels(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Bilinear lookup [N, C] (float64) of `image` [H, W, C] at continuous pixel coordinates [N, 2] (x, y; pixel
    centres at +0.5, edges clamped)."""
    height, width = image.shape[:2]
    xy = pixels - 0.5
    x0, y0 = np.floor(xy[:, 0]).astype(np.int64), np.floor(xy[:, 1]).astype(np.int64)
    fx, fy = (xy[:, 0] - x0)[:, None], (xy[:, 1] - y0)[:, None]

    def at(x, y):
        return image[np.clip(y, 0, height - 1), np.clip(x, 0, width - 1)].astype(np.float64)

    return ((1 - fy) * ((1 - fx) * at(x0, y0) + fx * at(x0 + 1, y0))
            + fy * ((1 - fx) * at(x0, y0 + 1) + fx * at(x0 + 1, y0 + 1)))


def render_mesh(vertices: np.ndarray, faces: np.ndarray, c2w: np.ndarray, k: Intrinsics,
                vertex_colours: np.ndarray | None = None, uv: np.ndarray | None = None,
                image: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A pinhole view (OpenGL camera-to-world, the vertices' frame) of a mesh, unlit: each pixel centre shows the
    nearest face's colour there, from `vertex_colours` [V, 3] (interpolated) or from the texture `image` [H, W, 3]
    at the interpolated `uv` [V, 2] (per vertex of `faces`). Returns RGB [h, w, 3] in [0, 1] (0 where no face is)
    and the covered pixels [h, w]."""
    pixels, depth = project(np.asarray(vertices, dtype=np.float64), np.asarray(c2w, dtype=np.float64), k)
    face, weights = rasterize(pixels[faces], k.w, k.h, depth=depth[faces])
    hit = face >= 0
    corners = faces[face[hit]]
    w = weights[hit][..., None]
    rgb = np.zeros((k.w * k.h, 3))
    if uv is not None:
        rgb[hit] = sample_texture(image, (uv[corners] * w).sum(axis=1))[:, :3]
    else:
        rgb[hit] = (vertex_colours[corners] * w).sum(axis=1)
    return rgb.reshape(k.h, k.w, 3), hit.reshape(k.h, k.w)
