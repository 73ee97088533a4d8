"""The object alone: the ground plane found and cut away with the room the box cuts through, a base that belongs to
the object kept, the viewer's box respected; and the export stage cutting a floor away from under a sphere."""
import math

import numpy as np
import trimesh
from skimage.measure import marching_cubes

from stages.scoring.metrics import surface_distance
from plenoxels.surface.ground import find_ground
from plenoxels.surface.mesh import isolate_object
from stages.common.json_files import read_json
from stages.settings.export import Settings
from tests.stages.test_export import (SPHERE_CENTRE, SPHERE_RADIUS, cluttered_sphere_field, identity_scene, orbit_frames,
                         radial_error, run_stage)

VOXEL = 0.02
BOX_MIN, BOX_MAX = np.array([-1.0, -1.0, -0.7]), np.array([1.0, 1.0, 1.0])
FLOOR_Z = -0.5


def dense(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Faces about a voxel wide, as marching cubes makes them."""
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=1.5 * VOXEL)
    return trimesh.Trimesh(vertices, faces)


def slab(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return dense(trimesh.creation.box(extents=hi - lo).apply_translation((lo + hi) / 2))


def objects() -> list[trimesh.Trimesh]:
    """A box and a sphere standing on the floor, well apart, and well inside the box."""
    box = slab([-0.6, -0.3, FLOOR_Z], [-0.2, 0.1, FLOOR_Z + 0.5])
    ball = dense(trimesh.creation.icosphere(subdivisions=3, radius=0.25).apply_translation([0.45, 0.2, FLOOR_Z + 0.25]))
    return [box, ball]


def room_scene(tilt_deg: float = 0.0) -> tuple[trimesh.Trimesh, list[trimesh.Trimesh], np.ndarray]:
    """The objects on a floor that runs out of the box on every side, a wall the box cuts through, a small floater
    and, tilted by `tilt_deg` about x: the mesh, the objects (tilted alike) and the tilt."""
    floor = slab([-1.2, -1.2, FLOOR_Z - 0.05], [1.2, 1.2, FLOOR_Z])
    wall = slab([0.9, -1.2, FLOOR_Z], [1.0, 1.2, 0.9])
    floater = dense(trimesh.creation.icosphere(subdivisions=1, radius=0.03).apply_translation([0.0, -0.6, 0.6]))
    rotation = trimesh.transformations.rotation_matrix(math.radians(tilt_deg), [1, 0, 0])
    things = objects()
    mesh = trimesh.util.concatenate([floor, wall, floater] + things).apply_transform(rotation)
    # What the box holds: the crop the export applies before it looks for the ground.
    inside = np.all((mesh.vertices >= BOX_MIN) & (mesh.vertices <= BOX_MAX), axis=1)[mesh.faces].all(axis=1)
    mesh.update_faces(inside)
    mesh.remove_unreferenced_vertices()
    return mesh, [t.copy().apply_transform(rotation) for t in things], rotation


def near(mesh: trimesh.Trimesh, reference: trimesh.Trimesh, tolerance: float) -> np.ndarray:
    """Which vertices of `mesh` lie within `tolerance` of `reference`'s surface."""
    return surface_distance(reference, np.asarray(mesh.vertices), np.random.default_rng(0)) < tolerance


def test_the_floor_and_the_room_go_and_the_objects_standing_on_the_floor_stay():
    for tilt in (0.0, 8.0):
        mesh, things, rotation = room_scene(tilt)
        kept, record = isolate_object(mesh, BOX_MIN, BOX_MAX, VOXEL, Settings(), user_box=False)
        ground = record["ground"]
        assert ground["is_ground"] and abs(ground["tilt_deg"] - tilt) < 0.5 and ground["rim_share"] > 0.9, record
        assert record["room_pieces_dropped"] == 1 and record["ground_faces_cut"] > 0, record
        assert "ground" in record["cut"] and "room" in record["cut"]
        together = trimesh.util.concatenate(things)
        # Everything kept is one of the objects, and each object is all there but its footprint on the floor.
        assert near(kept, together, 1e-6).all(), tilt
        for thing in things:
            heights = (thing.vertices @ rotation[:3, :3]) [:, 2] - FLOOR_Z
            above = thing.vertices[heights > 3 * VOXEL]
            assert near(trimesh.Trimesh(above, np.zeros((0, 3), int)), kept, 2 * VOXEL).mean() > 0.99


def test_what_stands_on_a_rough_floor_keeps_its_walls_down_to_the_floor():
    # Marching cubes joins an object to the floor it stands on in one surface, and the cut band over the floor is a few
    # voxels tall (more where the fitted floor is rough): the object's walls stay down through it to the floor; the
    # floor's bumps go.
    rng = np.random.default_rng(3)
    axes = [np.arange(lo, hi + 1e-9, VOXEL) for lo, hi in ((-1.0, 1.0), (-1.0, 1.0), (FLOOR_Z - 0.1, 0.2))]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    bumps = sum(0.6 * VOXEL * np.sin(f1 * x + p1) * np.sin(f2 * y + p2)
                for f1, f2, p1, p2 in rng.uniform([4, 4, 0, 0], [12, 12, 6, 6], size=(3, 4)))
    floor = FLOOR_Z + bumps / 3 - z
    lo, hi = np.array([-0.4, -0.3, FLOOR_Z - 0.1]), np.array([0.4, 0.3, FLOOR_Z + 0.5])
    inside_box = np.minimum.reduce([np.stack([x, y, z])[i] - lo[i] for i in range(3)]
                                   + [hi[i] - np.stack([x, y, z])[i] for i in range(3)])
    values = np.maximum(floor, inside_box)
    vertices, faces, _, _ = marching_cubes(values, level=0.0, spacing=(VOXEL,) * 3)
    mesh = trimesh.Trimesh(vertices + [a[0] for a in axes], faces[:, ::-1])
    kept, record = isolate_object(mesh, BOX_MIN, BOX_MAX, VOXEL, Settings(), user_box=False)
    ground = record["ground"]
    assert ground["is_ground"] and ground["cut_height"] >= 2 * VOXEL, record
    # The box's walls, from a voxel above the floor up through the band, are all in the mesh kept.
    t = np.linspace(0.0, 1.0, 200)
    heights = np.linspace(FLOOR_Z + VOXEL, FLOOR_Z + ground["cut_height"], 4)
    walls = np.concatenate([np.stack([lo[0] + t * (hi[0] - lo[0]), np.full_like(t, side), np.full_like(t, h)], -1)
                            for side in (lo[1], hi[1]) for h in heights]
                           + [np.stack([np.full_like(t, side), lo[1] + t * (hi[1] - lo[1]), np.full_like(t, h)], -1)
                              for side in (lo[0], hi[0]) for h in heights])
    # (Marching cubes bevels the box's edges: the samples on them lie up to 0.7 voxels off its surface.)
    assert (surface_distance(kept, walls, rng) < 0.25 * VOXEL).mean() > 0.95
    # Nothing of the floor stays but where it meets the walls.
    box = trimesh.creation.box(extents=hi - lo).apply_translation((lo + hi) / 2)
    assert (surface_distance(box, kept.vertices, rng) < 2 * VOXEL).mean() > 0.995


def test_a_base_that_ends_inside_the_box_is_part_of_the_object():
    # A masked object on a plinth (lego's base plate, the synthetic object's slab): the plane under the objects is the
    # plinth's top, which stops well inside the box: nothing is cut.
    plinth = slab([-0.8, -0.7, FLOOR_Z - 0.1], [0.8, 0.7, FLOOR_Z])
    mesh = trimesh.util.concatenate([plinth] + objects())
    kept, record = isolate_object(mesh, BOX_MIN, BOX_MAX, VOXEL, Settings(), user_box=False)
    assert record["ground"] is not None and not record["ground"]["is_ground"], record
    assert record["ground"]["rim_share"] < 0.05
    assert len(kept.faces) == len(mesh.faces) and record["cut"].startswith("nothing")


def test_the_users_box_decides_what_the_room_is():
    # With the viewer's crop box, a piece the box cuts through is what the user framed: it stays; the floor still goes.
    mesh, things, _ = room_scene()
    kept, record = isolate_object(mesh, BOX_MIN, BOX_MAX, VOXEL, Settings(), user_box=True)
    assert record["ground"]["is_ground"] and record["room_pieces_dropped"] == 0
    wall_top = kept.vertices[(kept.vertices[:, 0] > 0.85) & (kept.vertices[:, 2] > 0.5)]
    assert len(wall_top) > 10


def test_no_ground_without_upward_surface_or_with_nothing_standing_on_it():
    up = np.array([0, 0, 1.0])
    ball = dense(trimesh.creation.icosphere(subdivisions=3, radius=0.4))
    standing = slab([-0.05, -0.05, -0.6], [0.05, 0.05, 0.6])
    assert find_ground(standing, up, BOX_MIN, BOX_MAX, VOXEL) is None
    ground = find_ground(ball, up, BOX_MIN, BOX_MAX, VOXEL)
    assert ground is None or not ground.is_ground
    # A floor that runs out of the box with nothing on it is all there is: it stays.
    floor = slab([-1.0, -1.0, FLOOR_Z - 0.05], [1.0, 1.0, FLOOR_Z])
    ground = find_ground(floor, up, BOX_MIN, BOX_MAX, VOXEL)
    assert ground.rim_share > 0.9 and ground.above_share < 0.1 and not ground.is_ground


def test_the_export_cuts_the_floor_from_under_a_sphere_and_says_so(tmp_path):
    # The sphere rests on a floor slab that runs through the whole grid, past the foreground box. The level is the
    # sphere's (the floor's denser matter would raise the auto level).
    floor_top = SPHERE_CENTRE[2] - SPHERE_RADIUS
    field = cluttered_sphere_field(40, lambda p: (p[..., 2] < floor_top) & (p[..., 2] > floor_top - 0.2))
    scene = identity_scene("object", orbit_frames(6, size=32))
    # The level set's own place is scored (align_voxels 0), as in test_export's frame and cropping tests.
    options = {"frame": "normalized", "points": 2000, "point_scale": 1.0, "texture": False,
               "level": math.log(2) / (2 / 39), "align_voxels": 0}
    cut, folder = run_stage(tmp_path, field, scene, Settings(**options), "cut")
    kept, kept_folder = run_stage(tmp_path, field, scene, Settings(**options, object_only="off"), "kept")
    assert "the ground" in cut["cut_away"] and "cut away: the ground" in cut["line"]
    assert kept["cut_away"].startswith("nothing") and "object_only is off" in kept["cut_away"]
    record = read_json(folder / "export.json")["object_only"]
    assert record["ground"]["is_ground"] and record["ground"]["tilt_deg"] < 1.0
    assert abs(record["ground"]["offset"] - floor_top) < 2 * 2 / 39

    mesh = trimesh.load(folder / "mesh.ply", force="mesh", process=False)
    points = np.asarray(trimesh.load(folder / "points.ply").vertices)
    # Only the sphere is left (and the fillet where it meets the floor), all of it that the views see but a band at its
    # foot; the points too.
    above = mesh.vertices[:, 2] > floor_top + 0.1
    assert radial_error(mesh.vertices[above]).max() < 0.02 and radial_error(mesh.vertices).max() < 0.08
    assert np.median(radial_error(points)) < 0.02 and points[:, 2].min() > floor_top
    assert mesh.vertices[:, 2].max() > SPHERE_CENTRE[2] + 0.9 * SPHERE_RADIUS
    whole = trimesh.load(kept_folder / "mesh.ply", force="mesh", process=False)
    assert np.ptp(whole.vertices[:, 0]) > 1.6 and np.ptp(mesh.vertices[:, 0]) < 2.2 * SPHERE_RADIUS
