"""The synthetic scene generator: determinism, exact geometry, camera layouts, the true mesh, and SIFT-friendliness."""
import json
import shutil

import cv2
import imageio.v3 as iio
import numpy as np
import pytest
import torch
import trimesh

from stages.capture.synthetic import paint_passers_by, write_scene

from stages.capture.synthetic_scenes import KINDS, build_scene, camera_poses, intrinsics_for, render_view, surface_colour, surface_points, trace

from stages.capture.synthetic_shapes import Sphere
from plenoxels.core.cameras import Intrinsics, pixel_directions, project, rays_from_camera
from plenoxels.core.errors import UserError


def _images(folder):
    return {p.name: p.read_bytes() for p in sorted((folder / "images").iterdir())}


def test_same_seed_gives_same_bytes_and_another_seed_does_not(tmp_path):
    a = write_scene("unbounded", tmp_path / "a", n_views=3, width=48, height=36, seed=5)
    b = write_scene("unbounded", tmp_path / "b", n_views=3, width=48, height=36, seed=5)
    c = write_scene("unbounded", tmp_path / "c", n_views=3, width=48, height=36, seed=6)
    assert len(_images(a)) == 3 and _images(a) == _images(b)
    assert (a / "transforms.json").read_bytes() == (b / "transforms.json").read_bytes()
    assert all(_images(a)[name] != image for name, image in _images(c).items())
    assert json.loads((a / "transforms.json").read_text())["frames"] != json.loads((c / "transforms.json").read_text())["frames"]


def test_written_scene_has_the_poses_stage_layout(tmp_path):
    out = write_scene("object", tmp_path / "scene", n_views=4, width=40, height=30, seed=2)
    transforms = json.loads((out / "transforms.json").read_text())
    assert transforms["camera_model"] == "PINHOLE" and (transforms["w"], transforms["h"]) == (40, 30)
    assert transforms["synthetic"]["kind"] == "object" and transforms["synthetic"]["seed"] == 2
    k = intrinsics_for("object", 40, 30)
    assert (transforms["fl_x"], transforms["fl_y"], transforms["cx"], transforms["cy"]) == (k.fl_x, k.fl_y, k.cx, k.cy)
    poses = camera_poses(build_scene("object", 2), 4)
    for frame, c2w in zip(transforms["frames"], poses):
        assert np.array(iio.imread(out / frame["file_path"])).shape == (30, 40, 3)
        assert np.allclose(frame["transform_matrix"], c2w)
    truth = json.loads((out / "ground_truth" / "scene.json").read_text())
    mesh = trimesh.load(out / "ground_truth" / "mesh.ply")
    assert np.allclose([truth["object_bounds"]["min"], truth["object_bounds"]["max"]], mesh.bounds)
    assert truth["world_up"] == [0.0, 0.0, 1.0] and len(truth["views"]) == 4
    for view in truth["views"]:
        assert 0 < view["near_depth"] < view["far_depth"] and view["near_distance"] >= view["near_depth"]


def test_alpha_images_composite_back_to_the_rgb_images(tmp_path):
    rgb_dir = write_scene("object", tmp_path / "rgb", n_views=2, width=48, height=36, seed=3)
    rgba_dir = write_scene("object", tmp_path / "rgba", n_views=2, width=48, height=36, seed=3, alpha=True)
    background = np.asarray(build_scene("object", 3).background)
    for name in ("0000.png", "0001.png"):
        rgb = np.array(iio.imread(rgb_dir / "images" / name)).astype(np.float64) / 255
        rgba = np.array(iio.imread(rgba_dir / "images" / name)).astype(np.float64) / 255
        alpha = rgba[..., 3:]
        assert rgba.shape[-1] == 4 and alpha.min() == 0 and alpha.max() == 1 and 0 < alpha.mean() < 1
        assert np.abs(alpha * rgba[..., :3] + (1 - alpha) * background - rgb).max() < 2.5 / 255


def test_people_painted_into_a_capture_stay_out_of_its_held_out_photos_and_where_the_truth_says(tmp_path):
    """A capture with people painted into it (real photos, for the bench): about the share asked, never a photo
    normalize holds out, each person's pixels in ground_truth/passers_by/ where the photo changed and nowhere else."""
    clean = write_scene("room", tmp_path / "clean", n_views=24, width=96, height=72)
    painted = tmp_path / "painted"
    shutil.copytree(clean, painted)
    for path in sorted((painted / "images").glob("*.png"))[1::2]:  # JPEGs too, as a phone writes them
        cv2.imwrite(str(path.with_suffix(".jpg")), cv2.imread(str(path)), [cv2.IMWRITE_JPEG_QUALITY, 98])
        path.unlink()
    before = {p.stem: iio.imread(p).astype(np.int16) for p in (painted / "images").iterdir()}
    count = paint_passers_by(painted, share=0.5, size=0.5, seed=1)
    truths = sorted((painted / "ground_truth" / "passers_by").iterdir())
    assert len(truths) == count and 6 <= count <= 16
    assert not any(int(t.stem) % 8 == 0 for t in truths)  # held out (every 8th by name): as taken
    for path in (painted / "images").iterdir():
        changed = np.abs(iio.imread(path).astype(np.int16) - before[path.stem]).max(axis=-1) > 24
        truth = painted / "ground_truth" / "passers_by" / f"{path.stem}.png"
        person = iio.imread(truth) > 127 if truth.is_file() else np.zeros(changed.shape, bool)
        assert (changed & ~person).mean() < 0.01  # a JPEG's ringing round a person, at most
        assert not person.any() or (person & changed).sum() > 0.5 * person.sum()
        assert 0.005 < person.mean() < 0.2 or not truth.is_file()  # at half size: a person farther off


def test_bad_requests_are_user_errors_and_leave_other_folders_alone(tmp_path):
    with pytest.raises(UserError, match="kind"):
        write_scene("indoor", tmp_path / "x")
    with pytest.raises(UserError, match="alpha"):
        write_scene("forward", tmp_path / "x", alpha=True)
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "mine.jpg").write_bytes(b"not ours")
    with pytest.raises(UserError, match="not a synthetic scene"):
        write_scene("object", photos, n_views=1, width=16, height=12)
    assert [p.name for p in photos.iterdir()] == ["mine.jpg"]


def _sphere_intersection(origin, direction, centre, radius):
    """Smallest positive t with |origin + t direction - centre| = radius (nan for a miss)."""
    oc = origin - centre
    a, b, c = direction @ direction, direction @ oc, oc @ oc - radius ** 2
    disc = b * b - a * c
    return (-b - np.sqrt(disc)) / a if disc >= 0 else np.nan


def _bilinear(image, uv):
    """image sampled at continuous pixel coordinates (pixel centres at +0.5)."""
    x, y = uv[0] - 0.5, uv[1] - 0.5
    i, j = int(np.floor(x)), int(np.floor(y))
    fx, fy = x - i, y - j
    top = (1 - fx) * image[j, i] + fx * image[j, i + 1]
    bottom = (1 - fx) * image[j + 1, i] + fx * image[j + 1, i + 1]
    return (1 - fy) * top + fy * bottom


def _points_seen_by_both(scene, views, k, index, n_points=4000):
    """Points on sphere scene.shapes[index] that both cameras see (nothing in front, facing them, inside the
    image): the points, and their pixel coordinates and depths in each view."""
    sphere = scene.shapes[index]
    normals = np.random.default_rng(0).normal(size=(n_points, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = np.asarray(sphere.centre) + sphere.radius * normals
    seen = np.ones(n_points, bool)
    pixels, depths = [], []
    for c2w in views:
        to_point = points - c2w[:3, 3]
        distance = np.linalg.norm(to_point, axis=1)
        t, hit = trace(scene, c2w[:3, 3], to_point / distance[:, None])
        uv, depth = project(points, c2w, k)
        facing = -np.einsum("ij,ij->i", normals, to_point) > 0.5 * distance
        inside = (uv[:, 0] > 1) & (uv[:, 0] < k.w - 1) & (uv[:, 1] > 1) & (uv[:, 1] < k.h - 1)
        seen &= facing & inside & (hit == index) & (np.abs(t - distance) < 1e-6)
        pixels.append(uv)
        depths.append(depth)
    return points[seen], [uv[seen] for uv in pixels], [depth[seen] for depth in depths]


@pytest.mark.parametrize("kind", KINDS)
def test_a_known_surface_point_has_its_depth_and_colour_in_two_views(kind):
    scene = build_scene(kind, seed=1)
    k = intrinsics_for(kind, 320, 240)
    views = camera_poses(scene, 40)[[10, 11]]
    renders = [render_view(scene, c2w, k, supersample=1) for c2w in views]
    # Whichever foreground sphere the two views see most of.
    spheres = [i for i, s in enumerate(scene.shapes) if isinstance(s, Sphere) and s.foreground]
    sphere_index, (points, pixels, depths) = max(((i, _points_seen_by_both(scene, views, k, i)) for i in spheres),
                                                 key=lambda item: len(item[1][0]))
    sphere = scene.shapes[sphere_index]
    centre = np.asarray(sphere.centre)
    assert len(points) >= 30

    # The rendered depth is exact: pixel-centre rays near those points, intersected with the sphere here.
    cols, rows = np.floor(pixels[0]).astype(int).T
    rays = pixel_directions(k, torch.float64).numpy()[rows, cols] @ views[0][:3, :3].T
    _, first = trace(scene, views[0][:3, 3], rays)
    on_sphere = first == sphere_index
    assert on_sphere.sum() >= 20
    expected = [_sphere_intersection(views[0][:3, 3], ray, centre, sphere.radius) for ray in rays[on_sphere]]
    assert np.allclose(renders[0][1][rows[on_sphere], cols[on_sphere]], expected, rtol=0, atol=1e-9)

    # Those points land on pixels whose depth is the point's depth and whose colour is the texture's colour there.
    expected_colour = surface_colour(scene, sphere, points)
    colour_errors = []
    for (rgb, depth_image, _), uv, depth in zip(renders, pixels, depths):
        rendered_depth = np.array([_bilinear(depth_image, p) for p in uv])
        assert np.allclose(rendered_depth, depth, rtol=0.01)
        rendered = np.array([_bilinear(rgb.astype(np.float64) / 255, p) for p in uv])
        colour_errors.append(np.abs(rendered - expected_colour).max(axis=1))
    errors = np.concatenate(colour_errors)
    # The texture varies far more between points than the rendered colours differ from it.
    assert np.median(errors) < 0.04 and np.quantile(errors, 0.9) < 0.1
    assert expected_colour.std(axis=0).max() > 4 * np.median(errors)


@pytest.mark.parametrize("kind", ["object", "unbounded"])
def test_orbit_cameras_look_at_the_centre_from_above(kind):
    scene = build_scene(kind, seed=2)
    poses = camera_poses(scene, 24)
    centre = np.asarray(scene.look_at)
    for c2w in poses:
        rotation, eye = c2w[:3, :3], c2w[:3, 3]
        assert np.allclose(rotation.T @ rotation, np.eye(3)) and np.isclose(np.linalg.det(rotation), 1)
        forward = -rotation[:, 2]
        to_centre = centre - eye
        # The optical axis passes through the centre, and the image's x axis is level (no roll).
        assert np.linalg.norm(to_centre - (to_centre @ forward) * forward) < 1e-9 and to_centre @ forward > 0
        assert abs(rotation[:, 0] @ [0, 0, 1]) < 1e-9
        assert eye[2] > centre[2]
    distances = np.linalg.norm(poses[:, :3, 3] - centre, axis=1)
    assert np.ptp(distances) < 1e-9
    elevations = np.degrees(np.arcsin((poses[:, 2, 3] - centre[2]) / distances))
    assert np.ptp(elevations) > 25
    azimuths = np.arctan2(poses[:, 1, 3] - centre[1], poses[:, 0, 3] - centre[0])
    assert np.ptp(np.unwrap(azimuths)) > 2 * np.pi


@pytest.mark.parametrize("seed", [0, 1])
def test_object_kind_keeps_the_whole_object_inside_every_frame(seed):
    scene = build_scene("object", seed)
    k = intrinsics_for("object", 80, 60)
    for c2w in camera_poses(scene, 40):
        _, depth, alpha = render_view(scene, c2w, k, supersample=1)
        border = np.concatenate([alpha[0], alpha[-1], alpha[:, 0], alpha[:, -1]])
        assert border.max() == 0 and np.isinf(depth[alpha == 0]).all() and 0.1 < alpha.mean() < 0.5


def test_forward_cameras_lie_on_a_plane_and_look_one_way():
    scene = build_scene("forward", seed=2)
    poses = camera_poses(scene, 20)
    forwards = -poses[:, :3, 2]
    mean = forwards.mean(axis=0) / np.linalg.norm(forwards.mean(axis=0))
    assert np.degrees(np.arccos(np.clip(forwards @ mean, -1, 1))).max() < 10
    offsets = poses[:, :3, 3] - poses[:, :3, 3].mean(axis=0)
    spread = np.linalg.svd(offsets, compute_uv=False)
    assert spread[1] > 0.2 * spread[0] and spread[2] < 0.05 * spread[1]
    # Every foreground shape is in front of every camera.
    for shape in scene.foreground():
        assert np.all((np.asarray(shape.centre) - poses[:, :3, 3]) @ mean > 1.0)


def _first_hit_on_mesh(mesh, origins, dirs):
    """Distance along unit rays [N] to the nearest triangle of the mesh (inf for a miss), Moller-Trumbore.
    (trimesh's own ray queries need rtree or embree, which the project does not install.)"""
    a, b, c = (mesh.triangles[:, n][None] for n in range(3))
    e1, e2 = b - a, c - a
    d = dirs[:, None]
    p = np.cross(d, e2)
    det = np.einsum("rfk,rfk->rf", p, e1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = origins[:, None] - a
        u = np.einsum("rfk,rfk->rf", p, s) / det
        q = np.cross(s, e1)
        v = np.einsum("rfk,rfk->rf", q, d) / det
        t = np.einsum("rfk,rfk->rf", q, e2) / det
    hit = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return np.where(hit, t, np.inf).min(axis=1)


@pytest.mark.parametrize("kind", ["object", "unbounded"])
def test_true_mesh_matches_the_rendered_depth(tmp_path, kind):
    out = write_scene(kind, tmp_path / kind, n_views=2, width=64, height=48, seed=4)
    mesh = trimesh.load(out / "ground_truth" / "mesh.ply")
    transforms = json.loads((out / "transforms.json").read_text())
    k = Intrinsics.from_frame(transforms)
    scene = build_scene(kind, 4)
    rng = np.random.default_rng(1)
    for frame in transforms["frames"]:
        c2w = np.asarray(frame["transform_matrix"])
        _, depth, alpha = render_view(scene, c2w, k, supersample=1)
        origins, dirs = (x.numpy().reshape(-1, 3) for x in rays_from_camera(c2w, k, torch.float64))
        # Pixels away from silhouettes, where the mesh's flat facets may miss the true sphere.
        near = np.where(alpha == 1, depth, 1e6).astype(np.float32)
        window = np.ones((3, 3), np.uint8)
        interior = ((alpha == 1) & (cv2.dilate(near, window) - cv2.erode(near, window) < 0.05 * near)).ravel()
        covered, uncovered = np.flatnonzero(interior), np.flatnonzero(alpha.ravel() == 0)
        picks = np.concatenate([rng.choice(covered, 20, replace=False), rng.choice(uncovered, 20, replace=False)])
        distance = _first_hit_on_mesh(mesh, origins[picks], dirs[picks])
        mesh_depth = distance * (dirs[picks] @ -c2w[:3, 2])
        on_object = np.arange(len(picks)) < 20
        assert np.allclose(mesh_depth[on_object], depth.ravel()[picks[on_object]], rtol=2e-3)
        # Where the render shows no foreground, the mesh is missed or lies behind what the render shows.
        assert np.all(mesh_depth[~on_object] >= depth.ravel()[picks[~on_object]] - 1e-9)


@pytest.mark.parametrize("kind", KINDS)
def test_sift_finds_many_keypoints_that_match_correctly_between_neighbouring_views(kind):
    scene = build_scene(kind, seed=0)
    k = intrinsics_for(kind, 320, 240)
    views = camera_poses(scene, 40)[[10, 11]]
    sift = cv2.SIFT_create()
    features, depths = [], []
    for c2w in views:
        rgb, depth, _ = render_view(scene, c2w, k)
        features.append(sift.detectAndCompute(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), None))
        depths.append(depth)
    assert min(len(keypoints) for keypoints, _ in features) > 300
    pairs = cv2.BFMatcher().knnMatch(features[0][1], features[1][1], k=2)
    good = [m for m, second in pairs if m.distance < 0.75 * second.distance]
    assert len(good) > 60
    # Each match, carried through the true depth and poses, lands where SIFT found it.
    uv_a = np.array([features[0][0][m.queryIdx].pt for m in good]) + 0.5   # OpenCV puts pixel centres at integers
    uv_b = np.array([features[1][0][m.trainIdx].pt for m in good]) + 0.5
    rows, cols = np.clip(uv_a[:, 1].astype(int), 0, k.h - 1), np.clip(uv_a[:, 0].astype(int), 0, k.w - 1)
    depth = depths[0][rows, cols]
    finite = np.isfinite(depth)
    cam = np.stack([(uv_a[:, 0] - k.cx) / k.fl_x, -(uv_a[:, 1] - k.cy) / k.fl_y, -np.ones(len(uv_a))], -1) * depth[:, None]
    world = cam[finite] @ views[0][:3, :3].T + views[0][:3, 3]
    projected, _ = project(world, views[1], k)
    correct = np.linalg.norm(projected - uv_b[finite], axis=1) < 3
    assert correct.mean() > 0.8


@pytest.mark.parametrize("kind", KINDS)
def test_surface_points_lie_at_the_rendered_depth_on_the_shape_they_name(kind):
    scene = build_scene(kind, seed=2)
    k = intrinsics_for(kind, 64, 48)
    c2w = camera_poses(scene, 12)[5]
    points, index = surface_points(scene, c2w, k)
    _, depth, _ = render_view(scene, c2w, k, supersample=1)
    hit = index >= 0
    assert hit.sum() > 300
    # Depth runs along the viewing axis (camera -z).
    along_axis = (points[hit] - c2w[:3, 3]) @ -c2w[:3, 2]
    assert np.allclose(along_axis, depth.reshape(-1)[hit], rtol=1e-9, atol=1e-9)
    assert np.all(np.isinf(depth.reshape(-1)[~hit]))
    dirs = points[hit] - c2w[:3, 3]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    points, index = points[hit], index[hit]
    for s in np.unique(index):
        on = index == s
        # The shape it names is met exactly there: it is the nearest of all the shapes.
        t = scene.shapes[s].intersect(c2w[:3, 3], dirs[on])
        assert np.allclose(c2w[:3, 3] + t[:, None] * dirs[on], points[on], rtol=0, atol=1e-9)
