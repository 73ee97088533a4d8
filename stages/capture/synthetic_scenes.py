"""The synthetic scenes' layouts (a still life alone, on a ground inside an environment, in a room, on a turntable;
objects in front of a wall for forward cameras), their cameras, and the ray casting that renders a view of them."""
from __future__ import annotations

import colorsys
import functools
import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
import trimesh

from plenoxels.core.cameras import Intrinsics, look_at, pixel_directions
from plenoxels.core.errors import UserError
from stages.capture.panorama import frame_directions
from stages.capture.synthetic_shapes import (Box, Plane, Shape, Sphere, Texture, Turned, dot_rows, rotate_rows,
                                             turn_about, z_rotation)


KINDS = ("object", "forward", "unbounded", "room", "turntable")
WORLD_UP = (0.0, 0.0, 1.0)
OBJECT_CENTRE = np.array([0.3, -0.2, 0.5])
ENVIRONMENT_RADIUS = 24.0
HORIZONTAL_FOV_DEG = {"object": 55.0, "forward": 60.0, "unbounded": 60.0, "room": 60.0, "turntable": 50.0}
# The turntable rig: the still camera's distance from the object's centre and its elevation (degrees), and the
# radius of the room around them.
TURNTABLE_DISTANCE, TURNTABLE_ELEVATION_DEG, ROOM_RADIUS = 3.2, 28.0, 7.0



@dataclass(frozen=True)
class SceneSpec:
    """Everything that decides what the cameras see; `build_scene(kind, seed)` makes one."""
    kind: str
    seed: int
    shapes: tuple[Shape, ...]
    background: tuple[float, float, float]   # what a ray that hits nothing sees (object kind)
    light: tuple[float, float, float]        # unit vector towards the light
    ambient: float                           # share of the light that reaches surfaces facing away from it
    look_at: tuple[float, float, float]      # where the orbit cameras point (the object's centre)
    # Turntable kind: what stays still in the room while the object turns; in the object's frame each view sees it
    # turned with the camera (`view_scene`).
    room: tuple[Shape, ...] = ()

    def foreground(self) -> list[Shape]:
        return [s for s in self.shapes if s.foreground]

    def object_bounds(self) -> np.ndarray:
        """[2,3] min and max corners of the foreground shapes' axis-aligned bounding box."""
        return self.mesh().bounds

    def mesh(self) -> trimesh.Trimesh:
        """The foreground shapes, triangulated, in the world frame."""
        return trimesh.util.concatenate([s.mesh() for s in self.foreground()])

    def to_json(self) -> dict:
        shapes = [{"type": type(s).__name__.lower(), **asdict(s)} for s in self.shapes]
        return {**asdict(self), "shapes": shapes}



def surface_colour(scene: SceneSpec, shape: Shape, points: np.ndarray) -> np.ndarray:
    """The shaded colour [N,3] in [0,1] of `shape` at world points [N,3] on its surface (view-independent)."""
    albedo = shape.texture.albedo(points)
    if not shape.shaded:
        return albedo
    lambert = np.clip(dot_rows(shape.normals(points), np.asarray(scene.light)), 0.0, None)
    return albedo * (scene.ambient + (1 - scene.ambient) * lambert)[:, None]



def trace(scene: SceneSpec, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest hit per ray: ray parameter t [N] (inf for a miss) and index into scene.shapes [N] (-1 for a miss)."""
    t = np.full(len(dirs), np.inf)
    index = np.full(len(dirs), -1)
    for k, shape in enumerate(scene.shapes):
        t_k = shape.intersect(origin, dirs)
        closer = t_k < t
        t[closer], index[closer] = t_k[closer], k
    return t, index



def shade(scene: SceneSpec, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The colour [N,3] in [0,1] each ray sees (the background where it meets nothing) and the index into
    scene.shapes of what it meets (-1 for a miss)."""
    t, index = trace(scene, origin, dirs)
    colour = np.broadcast_to(np.asarray(scene.background), dirs.shape).copy()
    for s, shape in enumerate(scene.shapes):
        hit = index == s
        if hit.any():
            colour[hit] = surface_colour(scene, shape, origin + t[hit, None] * dirs[hit])
    return colour, index



def render_view(scene: SceneSpec, c2w: np.ndarray, intrinsics: Intrinsics,
                supersample: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Renders one view.

    Returns rgb [h,w,3] uint8 (background colour where nothing is hit), depth [h,w] float64 along the
    camera's viewing axis (-z in camera space) at the pixel centre, inf where nothing is hit, and
    alpha [h,w] float64 in [0,1]: the share of the pixel covered by foreground shapes.
    """
    rgb, depth, alpha = render_float(scene, c2w, intrinsics, supersample)
    return to_uint8(rgb), depth, alpha



def surface_points(scene: SceneSpec, c2w: np.ndarray, k: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel centre's ray first meets a shape: world points [h*w,3] (inf for a miss) and the index into
    scene.shapes [h*w] (-1 for a miss)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    dirs = rotate_rows(camera_directions(k), c2w[:3, :3])
    t, index = trace(scene, c2w[:3, 3], dirs)
    return c2w[:3, 3] + t[:, None] * dirs, index



def render_float(scene: SceneSpec, c2w: np.ndarray, k: Intrinsics, supersample: int):
    c2w = np.asarray(c2w, dtype=np.float64)
    origin, rot = c2w[:3, 3], c2w[:3, :3]
    # Camera-space directions have z = -1, so the ray parameter t is the depth along the viewing axis.
    centre = camera_directions(k)
    depth, _ = trace(scene, origin, rotate_rows(centre, rot))

    # Sub-pixel offsets (dx, dy) in pixels shift the camera-space direction by (dx / fl_x, -dy / fl_y, 0).
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    shifts = np.array([(dx / k.fl_x, -dy / k.fl_y, 0.0) for dy in offsets for dx in offsets])
    dirs = rotate_rows((centre[None] + shifts[:, None]).reshape(-1, 3), rot)
    colour, index = shade(scene, origin, dirs)
    # The trailing False is what a miss (index -1) picks.
    foreground = np.array([s.foreground for s in scene.shapes] + [False])
    rgb = colour.reshape(len(shifts), k.h, k.w, 3).mean(axis=0)
    alpha = foreground[index].reshape(len(shifts), k.h, k.w).mean(axis=0)
    return rgb, depth.reshape(k.h, k.w), alpha



def render_equirect(scene: SceneSpec, c2w: np.ndarray, width: int, supersample: int = 2) -> np.ndarray:
    """An equirectangular view [width/2, width, 3] in [0,1] from c2w's centre, as a 360 camera records it: columns
    the longitude (-180 to 180 degrees, the camera's forward -z at the middle, +x at three quarters), rows the
    latitude (+90, the camera's +y, at the top)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    offsets = (np.arange(supersample) + 0.5) / supersample
    colour = sum(shade(scene, c2w[:3, 3], rotate_rows(frame_directions(width, du, dv).reshape(-1, 3), c2w[:3, :3]))[0]
                 for dv in offsets for du in offsets)
    return (colour / supersample ** 2).reshape(width // 2, width, 3)


def render_fisheye(scene: SceneSpec, c2w: np.ndarray, width: int, height: int, focal: float,
                   supersample: int = 2) -> np.ndarray:
    """A view [height, width, 3] in [0,1] through an equidistant fisheye (a pixel's angle from the axis is its distance
    from the image's centre over `focal`), as an action camera's wide mode records it."""
    c2w = np.asarray(c2w, dtype=np.float64)
    offsets = (np.arange(supersample) + 0.5) / supersample
    colour = 0.0
    for dv in offsets:
        for du in offsets:
            x, y = np.meshgrid((np.arange(width) + du - width / 2) / focal,
                               (np.arange(height) + dv - height / 2) / focal)
            angle = np.hypot(x, y)
            along = np.sin(angle) / np.maximum(angle, 1e-12)
            dirs = np.stack([along * x, -along * y, -np.cos(angle)], -1).reshape(-1, 3)
            colour = colour + shade(scene, c2w[:3, 3], rotate_rows(dirs, c2w[:3, :3]))[0]
    return (colour / supersample ** 2).reshape(height, width, 3)


def walk_poses(n_frames: int, radius: float = 1.9, height: float = 1.3) -> np.ndarray:
    """[n,4,4] camera-to-world matrices of a 360 camera carried upright once around OBJECT_CENTRE inside the room
    kind, `height` above its floor, facing the way it goes with a little sway."""
    poses = []
    for n in range(n_frames):
        angle = 2 * math.pi * n / n_frames
        heading = angle + math.pi / 2 + 0.25 * math.sin(3 * angle)
        forward = np.array([math.cos(heading), math.sin(heading), 0.0])
        c2w = np.eye(4)
        c2w[:3, 0] = np.cross(forward, WORLD_UP)
        c2w[:3, 1] = WORLD_UP
        c2w[:3, 2] = -forward
        wobble = 0.08 * math.sin(5 * angle)
        c2w[:3, 3] = OBJECT_CENTRE + np.array([(radius + wobble) * math.cos(angle), radius * math.sin(angle),
                                               height - 0.5 + 0.05 * math.cos(2 * angle)])
        poses.append(c2w)
    return np.stack(poses)


@functools.lru_cache(maxsize=8)
def camera_directions(k: Intrinsics) -> np.ndarray:
    """[h*w,3] camera-space directions through the pixel centres, z = -1."""
    return pixel_directions(k, torch.float64).numpy().reshape(-1, 3)



def to_uint8(values: np.ndarray) -> np.ndarray:
    return np.round(np.clip(values, 0.0, 1.0) * 255).astype(np.uint8)



def build_scene(kind: str, seed: int = 0, mast: bool = False) -> SceneSpec:
    """The shapes, light and background of one kind of scene; the seed varies layout, sizes and textures. `mast`
    adds a thin mast to the still life (not the forward kind)."""
    if kind not in KINDS:
        raise UserError(f"unknown synthetic scene kind {kind!r}; choose one of {', '.join(KINDS)}")
    if mast and kind == "forward":
        raise UserError("a mast only stands on the still life (object, unbounded and turntable kinds)")
    rng = np.random.default_rng([seed, KINDS.index(kind)])
    light = np.array([0.45, -0.35, 0.82])
    room: tuple[Shape, ...] = ()
    if kind == "forward":
        shapes = _forward_shapes(rng)
    else:
        shapes = _still_life(rng, with_slab=kind == "object")
        if mast:
            # Rising from the still life's middle to 1.6 units above its base (the rest stands at most 1.1 high):
            # about 2 pixels wide in the object kind's photos at 320 pixels.
            cx, cy, cz = OBJECT_CENTRE
            shapes.append(Box((cx, cy, cz - 0.5 + 0.8), (0.012, 0.012, 0.8), 0.3, _texture(rng, 6.0)))
        if kind == "turntable":
            # The plate turns with the object but is not part of it (the masks leave it out); the room stands still.
            floor = float(OBJECT_CENTRE[2] - 0.5)
            shapes.append(Box((OBJECT_CENTRE[0], OBJECT_CENTRE[1], floor - 0.04), (0.95, 0.95, 0.04), 0.0,
                              _texture(rng, 3.0), foreground=False))
            room = (Plane((0.0, 0.0, floor - 0.7), (0.0, 0.0, 1.0), _texture(rng, 2.0)),
                    Sphere(tuple(OBJECT_CENTRE), ROOM_RADIUS, _texture(rng, 1.0), foreground=False, inward=True,
                           shaded=False))
        if kind == "unbounded":
            ground_z = float(OBJECT_CENTRE[2] - 0.5)
            shapes += [
                Plane((0.0, 0.0, ground_z), (0.0, 0.0, 1.0),
                      _texture(rng, 4.0, zoom_centre=tuple(OBJECT_CENTRE), zoom_radius=2.0)),
                Sphere(tuple(OBJECT_CENTRE), ENVIRONMENT_RADIUS, _texture(rng, 0.4),
                       foreground=False, inward=True, shaded=False),
            ]
        elif kind == "room":
            shapes += _room(rng)
    return SceneSpec(kind=kind, seed=seed, shapes=tuple(shapes), background=(1.0, 1.0, 1.0),
                     light=tuple(light / np.linalg.norm(light)), ambient=0.5, look_at=tuple(OBJECT_CENTRE), room=room)



def turn_angles(n_views: int) -> np.ndarray:
    """Turntable kind: how far (radians) the object has turned at each view, one revolution in all."""
    return 2 * math.pi * np.arange(n_views) / n_views



def view_scene(scene: SceneSpec, angle: float) -> SceneSpec:
    """What the camera sees with the object turned by `angle`, in the object's frame: the room turned back by it.
    Scenes without a room are the same at every view."""
    if not scene.room:
        return scene
    turned = tuple(Turned(shape, -angle, scene.look_at) for shape in scene.room)
    return SceneSpec(scene.kind, scene.seed, scene.shapes + turned, scene.background, scene.light, scene.ambient,
                     scene.look_at)



def _still_life(rng: np.random.Generator, with_slab: bool) -> list[Shape]:
    """Two spheres and two boxes standing on the plane z = OBJECT_CENTRE.z - 0.5 (on a 1.8-unit square
    slab when with_slab), up to 1 unit from OBJECT_CENTRE sideways and 0.6 up, with gaps between them
    so their meshes do not intersect."""
    cx, cy, cz = OBJECT_CENTRE
    floor = cz - 0.5
    spin = rng.uniform(0, 2 * math.pi)
    c, s = math.cos(spin), math.sin(spin)
    shapes: list[Shape] = []
    if with_slab:
        shapes.append(Box((cx, cy, floor - 0.06), (0.9, 0.9, 0.06), spin, _texture(rng, 3.0)))
    # The corners of a 0.84-unit square on the slab, in order around it; every piece fits within
    # 0.4 of its corner, so neighbours (0.84 apart) keep a gap.
    corners = [(0.42, 0.42), (-0.42, 0.42), (-0.42, -0.42), (0.42, -0.42)]
    x0, x1, x2, x3 = (cx + c * u - s * v for u, v in corners)
    y0, y1, y2, y3 = (cy + s * u + c * v for u, v in corners)
    big_r, small_r = rng.uniform(0.34, 0.4), rng.uniform(0.2, 0.26)
    box_a = (rng.uniform(0.22, 0.28), rng.uniform(0.2, 0.24), rng.uniform(0.4, 0.55))
    box_b = (rng.uniform(0.16, 0.2), rng.uniform(0.16, 0.2), rng.uniform(0.15, 0.22))
    shapes += [
        Sphere((x0, y0, floor + big_r), big_r, _texture(rng, 4.0)),
        Box((x1, y1, floor + box_a[2]), box_a, rng.uniform(0, math.pi), _texture(rng, 4.0)),
        Sphere((x2, y2, floor + small_r), small_r, _texture(rng, 4.5)),
        Box((x3, y3, floor + box_b[2]), box_b, rng.uniform(0, math.pi), _texture(rng, 4.5)),
    ]
    return shapes



def _room(rng: np.random.Generator) -> list[Shape]:
    """A closed room around OBJECT_CENTRE: the floor the still life stands on, four walls ROOM_HALF_WIDTH
    sideways (varied per seed) and a ceiling ROOM_HEIGHT above the floor, each plane facing inwards.
    A camera inside a convex room meets one of its planes first along every ray, so endless planes
    draw its walls."""
    cx, cy, cz = OBJECT_CENTRE
    floor = cz - 0.5
    half_x, half_y = rng.uniform(*ROOM_HALF_WIDTH, size=2)
    height = rng.uniform(*ROOM_HEIGHT)
    walls = _texture(rng, 1.5)
    return [
        Plane((cx, cy, floor), (0.0, 0.0, 1.0), _texture(rng, 3.0)),
        Plane((cx, cy, floor + height), (0.0, 0.0, -1.0), _texture(rng, 1.0)),
        Plane((cx - half_x, cy, floor), (1.0, 0.0, 0.0), walls),
        Plane((cx + half_x, cy, floor), (-1.0, 0.0, 0.0), walls),
        Plane((cx, cy - half_y, floor), (0.0, 1.0, 0.0), _texture(rng, 1.5)),
        Plane((cx, cy + half_y, floor), (0.0, -1.0, 0.0), _texture(rng, 1.5)),
    ]



# The room kind: its walls' distance from OBJECT_CENTRE sideways and its ceiling's height above the floor (ranges).
ROOM_HALF_WIDTH = (3.6, 4.6)
ROOM_HEIGHT = (3.2, 3.8)
# The forward-facing rig: camera grid centre, the direction every camera faces, and where the back wall stands.
FORWARD_EYE = np.array([0.3, -4.2, 1.0])
FORWARD_DIRECTION = np.array([0.0, 1.0, 0.0])
FORWARD_WALL_DEPTH = 9.0
FORWARD_FLOOR_Z = 0.0



def _forward_shapes(rng: np.random.Generator) -> list[Shape]:
    """Objects standing on the floor at depths 2.5 to 7 from the camera grid, spread across the view."""
    shapes: list[Shape] = []
    # (sideways offset, depth) slots; sizes grow with depth so far objects still fill some pixels.
    slots = [(-0.75, 2.6), (0.7, 3.3), (-1.6, 4.4), (0.25, 5.0), (1.9, 5.8), (-0.8, 6.8)]
    for n, (side, depth) in enumerate(slots):
        x = FORWARD_EYE[0] + side + rng.uniform(-0.1, 0.1)
        y = FORWARD_EYE[1] + depth + rng.uniform(-0.15, 0.15)
        size = 0.3 + 0.06 * depth + rng.uniform(-0.05, 0.05)
        if n % 2 == 0:
            shapes.append(Sphere((x, y, FORWARD_FLOOR_Z + size), size, _texture(rng, 2.5)))
        else:
            half = (size * 0.8, size * 0.7, size * rng.uniform(0.9, 1.4))
            shapes.append(Box((x, y, FORWARD_FLOOR_Z + half[2]), half, rng.uniform(0, math.pi), _texture(rng, 2.5)))
    wall_y = FORWARD_EYE[1] + FORWARD_WALL_DEPTH
    shapes += [
        Plane((0.0, 0.0, FORWARD_FLOOR_Z), (0.0, 0.0, 1.0), _texture(rng, 1.5)),
        Plane((0.0, wall_y, 0.0), (0.0, -1.0, 0.0), _texture(rng, 1.2), shaded=False),
    ]
    return shapes



def _texture(rng: np.random.Generator, frequency: float, **zoom) -> Texture:
    """Random, contrasting colours: a light base, a darker patch colour of another hue, and bright or dark spots."""
    hue = rng.uniform()
    base = colorsys.hsv_to_rgb(hue, rng.uniform(0.35, 0.8), rng.uniform(0.65, 0.9))
    patch = colorsys.hsv_to_rgb((hue + rng.uniform(0.3, 0.7)) % 1.0, rng.uniform(0.4, 0.9), rng.uniform(0.2, 0.45))
    spot = colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(0.0, 0.6), rng.choice([0.08, 0.97]))
    return Texture(int(rng.integers(0, 2 ** 31)), frequency, base, patch, spot, **zoom)



def camera_poses(scene: SceneSpec, n_views: int) -> np.ndarray:
    """[n,4,4] OpenGL camera-to-world matrices, ordered so that consecutive views are neighbours."""
    rng = np.random.default_rng([scene.seed, KINDS.index(scene.kind), 1])
    centre = np.asarray(scene.look_at)
    if scene.kind == "forward":
        return _forward_grid(rng, n_views)
    if scene.kind == "turntable":
        # The still camera, and in the object's frame the object's turn undone: an orbit at one elevation.
        elevation = math.radians(TURNTABLE_ELEVATION_DEG)
        azimuth = rng.uniform(0, 2 * math.pi)
        eye = centre + TURNTABLE_DISTANCE * np.array([math.cos(elevation) * math.cos(azimuth),
                                                      math.cos(elevation) * math.sin(azimuth), math.sin(elevation)])
        still = look_at(eye, centre)
        poses = []
        for angle in turn_angles(n_views):
            c2w = still.copy()
            c2w[:3, :3] = z_rotation(-angle) @ still[:3, :3]
            c2w[:3, 3] = turn_about(still[None, :3, 3], -angle, centre)[0]
            poses.append(c2w)
        return np.stack(poses)
    # A two-turn spiral up the upper hemisphere: neighbours are 720/n degrees apart, and each
    # azimuth is seen from two elevations.
    s = (np.arange(n_views) + 0.5) / n_views
    low, high, radius = {"object": (12.0, 65.0, 4.0), "room": (10.0, 45.0, 3.0)}.get(scene.kind, (6.0, 40.0, 3.5))
    azimuth = rng.uniform(0, 2 * math.pi) + 4 * math.pi * s
    elevation = np.radians(low + (high - low) * s)
    offsets = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], -1)
    return np.stack([look_at(centre + radius * o, centre) for o in offsets])



def _forward_grid(rng: np.random.Generator, n_views: int) -> np.ndarray:
    """Cameras on a grid about 1.2 x 0.8 units in the plane facing FORWARD_DIRECTION, visited row by row
    in a snake so neighbours stay close; all look at one point near the back wall."""
    cols = max(1, math.ceil(math.sqrt(n_views * 1.5)))
    rows = math.ceil(n_views / cols)
    right = np.cross(FORWARD_DIRECTION, WORLD_UP)
    target = FORWARD_EYE + FORWARD_DIRECTION * (FORWARD_WALL_DEPTH - 1.0)
    poses = []
    for n in range(n_views):
        row, col = divmod(n, cols)
        if row % 2:
            col = cols - 1 - col
        x = (col / max(cols - 1, 1) - 0.5) * 1.2 + rng.uniform(-0.03, 0.03)
        z = (row / max(rows - 1, 1) - 0.5) * 0.8 + rng.uniform(-0.03, 0.03)
        eye = FORWARD_EYE + x * right + z * np.asarray(WORLD_UP)
        poses.append(look_at(eye, target))
    return np.stack(poses)



def intrinsics_for(kind: str, width: int, height: int) -> Intrinsics:
    """Square pixels, principal point at the image centre, the kind's horizontal field of view."""
    focal = (width / 2) / math.tan(math.radians(HORIZONTAL_FOV_DEG[kind]) / 2)
    return Intrinsics(focal, focal, width / 2, height / 2, width, height)
