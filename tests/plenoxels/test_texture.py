"""Textures: the rasteriser, seam padding down the mip chain, which colour is baked, and the textured files."""
import numpy as np
import pytest
import torch
import trimesh
from scipy.ndimage import binary_erosion
from scipy.spatial import cKDTree

from stages.common.media import GLTF_FROM_ZUP
from stages.interchange.mesh_files import write_mesh_files
from plenoxels.core.cameras import Intrinsics, rays_from_camera
from plenoxels.core.fit_frame import FitFrame
from plenoxels.surface.mesh import build_mesh, transform_points
from plenoxels.core.render import render
from plenoxels.surface.views import render_views
from plenoxels.surface import texture
from plenoxels.surface.texture import (bake, rasterize, render_mesh, sample_texture, surface_normals, texel_surface,
                               texture_mesh, unwrap)
from stages.settings.export import Settings
from tests.stages.test_export import BOX, SPHERE_CENTRE, _Quiet, look_at, sphere_field

RED, BLUE = np.array([0.9, 0.1, 0.1]), np.array([0.1, 0.1, 0.9])


@pytest.fixture(scope="module")
def sphere():
    """The analytic sphere field (red where x > 0.1, blue elsewhere, plus a strong view-dependent SH degree-1 term),
    its mesh, and the mesh's textures baked with either colour."""
    field = sphere_field(40)
    mesh, _ = build_mesh(field, FitFrame(), *BOX, Settings(), _Quiet())
    return field, mesh, {colour: texture_mesh(field, FitFrame(), mesh, 256, colour) for colour in ("normal", "mean")}


def test_rasterizer_gives_the_same_answer_in_chunks(monkeypatch):
    rng = np.random.default_rng(3)
    corners = rng.uniform(0, 40, (60, 1, 2)) + rng.uniform(-4, 4, (60, 3, 2))
    depth = rng.uniform(1, 3, (60, 3))
    whole = [rasterize(corners, 40, 30, reach=2.0), rasterize(corners, 40, 30, depth=depth)]
    monkeypatch.setattr(texture, "RASTER_CHUNK", 37)  # a few triangles' boxes a chunk
    for (face, weights), (chunked_face, chunked_weights) in zip(whole, [rasterize(corners, 40, 30, reach=2.0),
                                                                        rasterize(corners, 40, 30, depth=depth)]):
        assert (face >= 0).sum() > 150 and np.array_equal(face, chunked_face)
        assert np.allclose(weights, chunked_weights)


def test_rasterizer_covers_exactly_the_pixel_centres_inside_with_weights_that_rebuild_them():
    corners = np.array([[[2.0, 2.0], [12.5, 3.0], [4.0, 13.0]]])
    face, weights = rasterize(corners, 16, 16)
    ys, xs = np.mgrid[0:16, 0:16]
    centres = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], axis=-1)
    a, b, c = corners[0]
    cross = lambda o, p, q: (p[0] - o[0]) * (q[:, 1] - o[1]) - (p[1] - o[1]) * (q[:, 0] - o[0])
    inside = (cross(a, b, centres) >= 0) & (cross(b, c, centres) >= 0) & (cross(c, a, centres) >= 0)
    assert inside.sum() > 40 and np.array_equal(face >= 0, inside)
    assert np.allclose(weights[inside] @ corners[0], centres[inside], atol=1e-9)

    # The nearer of two overlapping triangles wins, with perspective-correct weights. Triangle 1's depth is 1 at
    # x = 0 and 3 at x = 16; 1/z is linear on screen, so it is 1 / (1 - x / 24): nearer than triangle 0 (at 2) for
    # x < 12. Its weights interpolate depth to exactly that.
    same = np.array([[0.0, 0.0], [16.0, 0.0], [0.0, 16.0]])
    face, weights = rasterize(np.stack([same, same]), 16, 16, depth=np.array([[2.0, 2.0, 2.0], [1.0, 3.0, 1.0]]))
    covered = face >= 0
    x = centres[covered, 0]
    assert covered.sum() > 100 and np.array_equal(face[covered], np.where(x < 12, 1, 0))
    near = covered & (face == 1)
    assert np.allclose(weights[near] @ np.array([1.0, 3.0, 1.0]), 1 / (1 - centres[near, 0] / 24), rtol=1e-9)

    # A gutter: pixels within `reach` outside take the triangle at their nearest point on it.
    face, weights = rasterize(corners, 16, 16, reach=2.0)
    gutter = (face >= 0) & ~inside
    nearest = weights[gutter] @ corners[0]
    assert gutter.sum() > 20 and np.linalg.norm(nearest - centres[gutter], axis=1).max() <= 2.0 + 1e-9
    assert (weights[gutter] >= -1e-12).all() and np.allclose(weights[gutter].sum(axis=1), 1.0)


def test_a_mesh_charted_in_pieces_packs_them_into_one_atlas_without_overlap(monkeypatch):
    mesh = trimesh.creation.icosphere(subdivisions=3)
    monkeypatch.setattr(texture, "CHART_PIECE_FACES", 200)
    atlas = unwrap(mesh.vertices, mesh.faces, 128)
    assert np.array_equal(atlas.vertex_map[atlas.faces], mesh.faces) and atlas.charted.all()
    assert atlas.charts >= 8  # 1280 faces in pieces of at most 200
    # Every texel centre lies inside at most one face's UV triangle: the pieces' charts share the atlas.
    corners = texture.uv_to_pixels(atlas.uv, atlas.size)[atlas.faces]
    covered = np.zeros(atlas.size[::-1], dtype=np.int64)
    for tri in corners:
        lo, hi = np.floor(tri.min(axis=0)).astype(int), np.ceil(tri.max(axis=0)).astype(int)
        x, y = np.meshgrid(np.arange(lo[0], hi[0]) + 0.5, np.arange(lo[1], hi[1]) + 0.5)
        p = np.stack([x.ravel(), y.ravel()], axis=1)
        side, to = np.stack([tri[(k + 1) % 3] - tri[k] for k in range(3)]), p[None] - tri[:, None]
        edges = side[:, None, 0] * to[..., 1] - side[:, None, 1] * to[..., 0]
        inside = (edges > 1e-9).all(axis=0) | (edges < -1e-9).all(axis=0)
        np.add.at(covered, (p[inside, 1].astype(int), p[inside, 0].astype(int)), 1)
    assert covered.max() == 1 and covered.sum() > 0.3 * covered.size
    # The pieces are the mesh cut in halves along its longest extent: each face once, each piece whole and compact.
    centres = mesh.triangles_center
    pieces = texture.chart_pieces(centres, 200)
    assert len(pieces) == 8 and max(map(len, pieces)) <= 200
    assert np.array_equal(np.sort(np.concatenate(pieces)), np.arange(len(mesh.faces)))
    spread = np.mean([np.linalg.norm(centres[piece] - centres[piece].mean(axis=0), axis=1).mean() for piece in pieces])
    assert spread < 0.5 * np.linalg.norm(centres - centres.mean(axis=0), axis=1).mean()


def face_centres(mesh: trimesh.Trimesh, atlas) -> tuple[np.ndarray, np.ndarray]:
    """The centres [F', 3] of the faces xatlas charted, and their UVs [F', 2] (marching cubes leaves a few slivers of
    next to no area, which it does not chart)."""
    assert atlas.charted.mean() > 0.99
    return mesh.triangles_center[atlas.charted], atlas.uv[atlas.faces[atlas.charted]].mean(axis=1)


def mip_levels(image: np.ndarray) -> list[np.ndarray]:
    """A 2x box-filtered mip chain, as a GPU builds it."""
    levels = [image]
    while min(levels[-1].shape[:2]) > 1:
        im = levels[-1]
        h, w = im.shape[0] // 2 * 2, im.shape[1] // 2 * 2
        im = im[:h, :w]
        levels.append((im[0::2, 0::2] + im[1::2, 0::2] + im[0::2, 1::2] + im[1::2, 1::2]) / 4)
    return levels


def red_blue_mix(image: np.ndarray) -> np.ndarray:
    """Which texels are a mix of the sphere's red and blue (green 0.1, red + blue 1): anything else is a colour that
    is not the surface's."""
    return (np.abs(image[..., 1] - 0.1) < 0.02) & (np.abs(image[..., 0] + image[..., 2] - 1.0) < 0.03)


def test_the_baked_texture_holds_the_surface_colour_at_every_mip_level_with_no_background_bleeding_in(sphere):
    field, mesh, textures = sphere
    texture = textures["mean"]
    # At each face's centre, away from the red/blue seam, the texture gives the view-independent colour.
    centre, uv = face_centres(mesh, texture.atlas)
    colour = sample_texture(texture.image, uv)
    assert np.abs(colour[centre[:, 0] > 0.2] - RED).max() < 0.03
    assert np.abs(colour[centre[:, 0] < 0.0] - BLUE).max() < 0.03
    # Every texel of every mip level is surface colour: the charts' gutters and the space between them are padded.
    for level in mip_levels(texture.image):
        assert red_blue_mix(level).all()
    # The same bake without padding (black between the charts) fails that: the check can tell.
    texels, points, _ = texel_surface(mesh.vertices, mesh.vertex_normals, texture.atlas)
    bare = np.zeros_like(texture.image).reshape(-1, 3)
    bare[texels] = texture.image.reshape(-1, 3)[texels]
    assert not all(red_blue_mix(level).all() for level in mip_levels(bare.reshape(texture.image.shape)))


def test_the_gaps_between_charts_take_the_nearest_coarse_level_that_holds_colour():
    # 6x6 with red at (0, 0) and blue at (5, 5): a texel sharing a 2x2 block with one takes it, (2, 2) the 4x4
    # block that holds red alone, the opposite corners the whole image's mean; a covered texel keeps its colour.
    image, covered = np.zeros((6, 6, 3), dtype=np.float32), np.zeros((6, 6), dtype=bool)
    image[0, 0], image[5, 5], covered[0, 0], covered[5, 5] = RED, BLUE, True, True
    image[3, 1] = 7.0   # not covered: whatever it held goes
    filled = texture.pull_push(image, covered)
    for (y, x), expected in [((0, 0), RED), ((1, 1), RED), ((2, 2), RED), ((3, 1), RED), ((5, 5), BLUE),
                             ((4, 4), BLUE), ((0, 5), (RED + BLUE) / 2), ((5, 0), (RED + BLUE) / 2)]:
        assert np.allclose(filled[y, x], expected, atol=1e-6), (y, x, filled[y, x])
    # Odd sides at every level: one covered texel fills everything.
    for shape in [(5, 7), (1, 9), (13, 2)]:
        image, covered = np.zeros(shape + (3,), dtype=np.float32), np.zeros(shape, dtype=bool)
        image[-1, -1], covered[-1, -1] = BLUE, True
        assert np.allclose(texture.pull_push(image, covered), BLUE, atol=1e-6), shape


@pytest.mark.parametrize("count", [1, 3, 12, 40])
def test_each_texel_gets_the_views_that_face_it_most_squarely_best_first(monkeypatch, count):
    # Against every row sorted whole, across chunk ends; a vertex no view sees ties every view at 0, and those picks
    # are never used (view_colour_texels reads a view only where its cosine is above 0).
    monkeypatch.setattr(texture, "VIEW_CHUNK", 1000)
    rng = np.random.default_rng(3)
    cosines = np.where(rng.random((500, 12)) < 0.4, rng.random((500, 12)), 0.0).astype(np.float32)
    cosines[:20] = 0.0
    faces = rng.integers(0, 500, (4321, 3)).astype(np.int32)
    faces[:300] = rng.integers(0, 20, (300, 3))
    weights = rng.random((4321, 3)).astype(np.float32)
    weights /= weights.sum(axis=1, keepdims=True)
    best, score = texture.facing_views(faces, weights, cosines, count)
    blended = np.einsum("nk,nkc->nc", weights, cosines[faces])
    order = np.argsort(-blended, axis=1, kind="stable")[:, :min(count, 12)]
    assert best.shape == score.shape == order.shape
    assert np.array_equal(score, np.take_along_axis(blended, order, axis=1))
    assert np.array_equal(best[score > 0], order[score > 0]) and (score[:300] == 0).all()


def test_the_texture_shows_what_a_camera_looking_straight_at_the_surface_sees(sphere):
    # The field's colour depends on the view (SH degree 1). Baked along the normal, the texture matches the field's own
    # render where the camera faces the surface; the view-independent mean (degree 0) does not.
    field, mesh, textures = sphere
    k = Intrinsics(120.0, 120.0, 64.0, 64.0, 128, 128)
    c2w = look_at(SPHERE_CENTRE + np.array([2.2, -1.0, 0.6]), SPHERE_CENTRE)
    origins, directions = rays_from_camera(c2w, k)
    with torch.no_grad():
        out = render(field, origins.reshape(-1, 3), directions.reshape(-1, 3))
    field_rgb = (out.rgb / out.opacity.clamp_min(1e-6)[:, None]).numpy().reshape(128, 128, 3)
    renders = {}
    for colour, texture in textures.items():
        vertices = mesh.vertices[texture.atlas.vertex_map]
        renders[colour], covered = render_mesh(vertices, texture.atlas.faces, c2w, k, uv=texture.atlas.uv,
                                               image=texture.image)
    # Pixels where the surface faces the camera within about 6 degrees (this field's colour turns by 0.4 a radian).
    normals = render_mesh(mesh.vertices, mesh.faces, c2w, k, vertex_colours=mesh.vertex_normals)[0]
    to_camera = c2w[:3, 3] - SPHERE_CENTRE
    facing = covered & (normals @ (to_camera / np.linalg.norm(to_camera)) > 0.995)
    assert facing.sum() > 10
    normal_error = np.abs(renders["normal"] - field_rgb)[facing].mean()
    mean_error = np.abs(renders["mean"] - field_rgb)[facing].mean()
    assert normal_error < 0.035 and mean_error > 0.07, (normal_error, mean_error)


def test_the_texture_shows_what_the_training_view_facing_the_surface_saw(sphere):
    # The field's colour depends on the view (SH degree 1). Baked along the direction from the training camera that
    # faces each texel, the texture rendered from that camera matches the field's own render on everything the camera
    # sees, its oblique parts included; baked along the normal, it strays there.
    field, mesh, textures = sphere
    k = Intrinsics(120.0, 120.0, 64.0, 64.0, 128, 128)
    c2w = look_at(SPHERE_CENTRE + np.array([2.2, -1.0, 0.6]), SPHERE_CENTRE)
    record = {"transform_matrix": c2w.tolist(), "fl_x": k.fl_x, "fl_y": k.fl_y, "cx": k.cx, "cy": k.cy, "w": k.w,
              "h": k.h, "split": "train"}
    views = render_views(field, FitFrame(), [record], 1.0, 0, _Quiet())
    facing = texture_mesh(field, FitFrame(), mesh, 256, "view", views)
    origins, directions = rays_from_camera(c2w, k)
    with torch.no_grad():
        out = render(field, origins.reshape(-1, 3), directions.reshape(-1, 3))
    field_rgb = (out.rgb / out.opacity.clamp_min(1e-6)[:, None]).numpy().reshape(128, 128, 3)
    renders = {}
    for colour, baked in (("view", facing), ("normal", textures["normal"])):
        vertices = mesh.vertices[baked.atlas.vertex_map]
        renders[colour], covered = render_mesh(vertices, baked.atlas.faces, c2w, k, uv=baked.atlas.uv,
                                               image=baked.image)
    # Pixels two in from the silhouette, off the red/blue seam, where the surface turns 25 degrees or more away.
    normals, _ = render_mesh(mesh.vertices, mesh.faces, c2w, k, vertex_colours=mesh.vertex_normals)
    points, _ = render_mesh(mesh.vertices, mesh.faces, c2w, k, vertex_colours=mesh.vertices)
    to_camera = c2w[:3, 3] - points
    cosine = (normals * to_camera).sum(axis=-1) / np.linalg.norm(to_camera, axis=-1)
    oblique = binary_erosion(covered, iterations=2) & (np.abs(points[..., 0] - 0.1) > 0.05) & (cosine < 0.9)
    assert oblique.sum() > 200
    view_error = np.abs(renders["view"] - field_rgb)[oblique].mean()
    normal_error = np.abs(renders["normal"] - field_rgb)[oblique].mean()
    assert view_error < 0.03 and normal_error > 0.08, (view_error, normal_error)
    assert facing.colour == "view"


def test_the_mean_of_several_views_stands_for_a_view_between_them(sphere):
    # The field's colour turns with the view. Two training cameras 30 degrees either side of a held-out one: the
    # texture baked as their mean (cos^2-weighted) renders nearer the field's own render from the held-out camera
    # than one baked from whichever faces each texel most squarely.
    field, mesh, _ = sphere
    k = Intrinsics(120.0, 120.0, 64.0, 64.0, 128, 128)

    def camera(degrees: float) -> np.ndarray:
        angle = np.radians(degrees)
        return look_at(SPHERE_CENTRE + 2.5 * np.array([np.cos(angle), np.sin(angle), 0.3]), SPHERE_CENTRE)

    records = [{"transform_matrix": camera(d).tolist(), "fl_x": k.fl_x, "fl_y": k.fl_y, "cx": k.cx, "cy": k.cy,
                "w": k.w, "h": k.h, "split": "train"} for d in (-30.0, 30.0)]
    views = render_views(field, FitFrame(), records, 1.0, 0, _Quiet())
    held_out = camera(0.0)
    origins, directions = rays_from_camera(held_out, k)
    with torch.no_grad():
        out = render(field, origins.reshape(-1, 3), directions.reshape(-1, 3))
    field_rgb = (out.rgb / out.opacity.clamp_min(1e-6)[:, None]).numpy().reshape(128, 128, 3)
    errors = {}
    for count in (1, 2):
        baked = texture_mesh(field, FitFrame(), mesh, 256, "view", views, view_count=count)
        vertices = mesh.vertices[baked.atlas.vertex_map]
        rgb, covered = render_mesh(vertices, baked.atlas.faces, held_out, k, uv=baked.atlas.uv, image=baked.image)
        points, _ = render_mesh(mesh.vertices, mesh.faces, held_out, k, vertex_colours=mesh.vertices)
        normals, _ = render_mesh(mesh.vertices, mesh.faces, held_out, k, vertex_colours=mesh.vertex_normals)
        to_camera = held_out[:3, 3] - points
        cosine = (normals * to_camera).sum(axis=-1) / np.linalg.norm(to_camera, axis=-1)
        # Where the surface faces the held-out camera (so both training cameras see it), off the red/blue seam.
        facing = binary_erosion(covered, iterations=2) & (np.abs(points[..., 0] - 0.1) > 0.05) & (cosine > 0.9)
        errors[count] = np.abs(rgb - field_rgb)[facing].mean()
    assert facing.sum() > 300
    assert errors[2] < 0.7 * errors[1], errors


def test_a_sheet_folded_onto_itself_bakes_with_every_texel_facing_somewhere(sphere):
    # Two faces on the same three vertices with opposite windings (a thin wall the marching cubes closed on itself):
    # their vertices' normals cancel, so each texel's ray takes its face's normal (a zero direction is no ray to
    # render); a degenerate face takes up.
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [2.0, 2.0, 2.0]])
    faces = np.array([[0, 1, 2], [0, 2, 1], [3, 3, 3]])
    weights = np.full((3, 3), 1 / 3)
    zero = np.zeros((4, 3))
    zero[3] = np.nan
    unit = surface_normals(vertices, faces, weights, zero)
    np.testing.assert_allclose(unit, [[0, 0, 1], [0, 0, -1], [0, 0, 1]], atol=1e-12)
    field, mesh, _ = sphere
    folded = trimesh.Trimesh(vertices=SPHERE_CENTRE + 0.3 * vertices[:3], faces=faces[:2], process=False)
    baked = texture_mesh(field, FitFrame(), folded, 32, "normal")
    assert np.isfinite(baked.image).all()


def test_textured_files_carry_uvs_a_matte_material_and_the_png_in_the_input_frame(sphere, tmp_path):
    field, mesh, textures = sphere
    texture = textures["mean"]
    moved = mesh.copy()
    input_from_world = trimesh.transformations.rotation_matrix(0.6, [0.2, -0.4, 0.9]) * 1.8
    input_from_world[3], input_from_world[:3, 3] = [0, 0, 0, 1], [2.0, -1.0, 4.0]
    moved.apply_transform(input_from_world)
    files = write_mesh_files(moved, tmp_path, texture)
    assert files == {"ply": "mesh.ply", "obj": "mesh.obj", "glb": "mesh.glb", "mtl": "mesh.mtl", "png": "mesh.png"}
    mtl = (tmp_path / "mesh.mtl").read_text()
    assert "map_Kd mesh.png" in mtl and "Kd 1 1 1" in mtl and "Ks 0 0 0" in mtl
    ply = trimesh.load(tmp_path / "mesh.ply", force="mesh", process=False)
    assert ply.visual.kind == "vertex" and len(ply.faces) == len(mesh.faces)
    for kind in ("obj", "glb"):
        loaded = trimesh.load(tmp_path / files[kind], force="mesh", process=False)
        assert len(loaded.faces) == len(mesh.faces), kind
        vertices = transform_points(np.linalg.inv(GLTF_FROM_ZUP), np.asarray(loaded.vertices))
        # Each written vertex is a vertex of the input-frame mesh, and its UV shows that vertex's colour.
        gap, nearest = cKDTree(moved.vertices).query(vertices)
        assert gap.max() < 1e-5, kind
        material = loaded.visual.material
        image = getattr(material, "baseColorTexture", None) or material.image
        assert image.size == tuple(texture.atlas.size), kind
        colours = sample_texture(np.asarray(image.convert("RGB")) / 255.0, np.asarray(loaded.visual.uv))
        x = mesh.vertices[nearest, 0]
        assert np.abs(colours[x > 0.2] - RED).max() < 0.04 and np.abs(colours[x < 0.0] - BLUE).max() < 0.04, kind
    glb = trimesh.load(tmp_path / "mesh.glb", force="mesh", process=False).visual.material
    assert glb.metallicFactor == 0.0 and glb.roughnessFactor == 1.0


def test_an_atlas_rasterised_in_bands_of_rows_gives_each_texel_the_face_and_weights_of_the_whole(monkeypatch):
    mesh = trimesh.creation.icosphere(subdivisions=3)
    atlas = unwrap(mesh.vertices, mesh.faces, 96)
    width, height = atlas.size
    charted = np.flatnonzero(atlas.charted)
    corners = texture.uv_to_pixels(atlas.uv, atlas.size)[atlas.faces[charted]]
    face, weights = rasterize(corners, width, height, reach=texture.GUTTER_TEXELS)
    whole = np.flatnonzero(face >= 0)
    monkeypatch.setattr(texture, "TEXEL_BAND", 3 * width + 5)  # bands of three rows: gutters cross their edges
    texels, faces, banded = texture.texel_faces(atlas)
    assert height > 30 and np.array_equal(texels, whole)
    assert np.array_equal(faces, atlas.vertex_map[atlas.faces[charted[face[whole]]]])
    assert np.allclose(banded, weights[whole], atol=1e-6)


def test_unwrap_keeps_every_face_and_its_corners():
    mesh = trimesh.creation.icosphere(subdivisions=3)
    atlas = unwrap(mesh.vertices, mesh.faces, 128)
    assert np.array_equal(atlas.vertex_map[atlas.faces], mesh.faces)
    assert (atlas.uv >= 0).all() and (atlas.uv <= 1).all() and atlas.charts >= 1
    texels, points, normals = texel_surface(mesh.vertices, mesh.vertex_normals, atlas)
    # Texel points lie on the sphere (flat triangles sit just inside it) with outward normals.
    radius = np.linalg.norm(points, axis=1)
    assert radius.min() > 0.97 and radius.max() < 1.0 + 1e-9
    assert (np.einsum("ij,ij->i", normals, points / radius[:, None]) > 0.95).all()
    image = bake(texels, np.abs(normals), atlas.size)
    assert image.shape == (atlas.size[1], atlas.size[0], 3)
