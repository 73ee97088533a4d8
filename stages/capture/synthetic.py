"""Synthetic scenes with exact cameras: ray-cast textured analytic shapes, for the demo and the tests.

Five kinds, matching the scene types the pipeline handles and the captures it must refuse or mask:
- `object`: a still life (spheres and boxes on a slab) seen by an inward orbit; nothing else in the
  scene, so rays that miss it see a plain background colour (or are transparent, with `alpha=True`).
- `forward`: objects at several depths in front of a textured floor and back wall, seen by cameras
  on a small grid in one plane that all look the same way (like LLFF's fern).
- `unbounded`: the `object` still life (without its slab) on an endless textured ground, inside a
  textured environment sphere of radius 24 (12 times the object's width), seen by an inward orbit:
  a bounded grid around the object cannot hold it.
- `room`: the `object` still life (without its slab) standing on the floor of a closed, textured room
  (four walls and a ceiling a few units away), seen by an inward orbit inside the room: what a capture of
  things on a floor indoors looks like. Only the objects are foreground (the true mesh); floor and walls
  are the room around them.
- `turntable`: the still life (without its slab) on a turntable's plate, turning one revolution in front of a
  still, textured room (floor and walls) while the camera stays put. In the object's frame the cameras orbit it and
  the room turns with them, so only the object's pixels agree with one rigid scene; the masks (`masks=True`) mark
  the object alone (not its plate).

`mast=True` adds a thin mast (a few pixels wide) rising well above the still life: a part the sparse points
barely see, which the photos' silhouettes show.

The world frame is deliberately not normalised (z up, the object about 2 units wide, centred at
OBJECT_CENTRE, off the origin) so the normalize stage has real work to do.

Surfaces carry solid textures (value noise over several octaves, hard-edged colour patches and
spots), so the same 3D point looks the same from every view and SIFT has plenty to match; Lambertian
shading from one fixed light makes the geometry read. Colours are supersampled per pixel to keep the
fine texture from aliasing differently in each view; depth and coverage come from the pixel centre.

Written to disk by `write_scene`:
    images/NNNN.png              8-bit RGB (RGBA with alpha=True, object kind only)
    masks/NNNN.png               with masks=True: 8-bit grey, the share of each pixel the object covers
    transforms.json              shared PINHOLE camera + OpenGL camera-to-world per frame, as the poses stage writes it
    ground_truth/mesh.ply        the foreground shapes, triangulated, in the same world frame
    ground_truth/scene.json      kind, object bounds, world up, the shapes, and each view's near/far hit depths
"""
from __future__ import annotations

import colorsys
import functools
import math
import os
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from stages.common.media import write_png
from stages.common.json_files import read_json, write_json
from plenoxels.core.cameras import Intrinsics, look_at, pixel_directions
from plenoxels.core.errors import UserError

KINDS = ("object", "forward", "unbounded", "room", "turntable")
WORLD_UP = (0.0, 0.0, 1.0)
OBJECT_CENTRE = np.array([0.3, -0.2, 0.5])
ENVIRONMENT_RADIUS = 24.0
HORIZONTAL_FOV_DEG = {"object": 55.0, "forward": 60.0, "unbounded": 60.0, "room": 60.0, "turntable": 50.0}
# The turntable rig: the still camera's distance from the object's centre and its elevation (degrees), and the
# radius of the room around them.
TURNTABLE_DISTANCE, TURNTABLE_ELEVATION_DEG, ROOM_RADIUS = 3.2, 28.0, 7.0
# Hits closer than this along a ray are ignored, so a ray never hits the surface it starts on.
MIN_HIT_DISTANCE = 1e-6


@dataclass(frozen=True)
class Texture:
    """A solid (3D) texture: the colour at a point depends only on where the point is in space."""
    seed: int
    frequency: float                      # noise cells per world unit in the coarsest octave
    base: tuple[float, float, float]      # the two colours of the hard-edged patches
    patch: tuple[float, float, float]
    spot: tuple[float, float, float]      # the colour of the small round spots
    # When set, the pattern grows with the square root of the distance from this point beyond
    # zoom_radius, so an endless ground keeps features that are not much smaller than a pixel
    # instead of turning into aliased noise towards the horizon.
    zoom_centre: tuple[float, float, float] | None = None
    zoom_radius: float = 1.0

    def albedo(self, points: np.ndarray) -> np.ndarray:
        """Reflectance [N,3] in [0,1] at world points [N,3]."""
        if self.zoom_centre is not None:
            offset = points - np.asarray(self.zoom_centre)
            distance = np.linalg.norm(offset, axis=1, keepdims=True)
            points = offset * np.sqrt(self.zoom_radius / (self.zoom_radius + distance))
        p = (points * self.frequency).astype(np.float32)
        table = _noise_table(self.seed)
        # Octaves 2.1x apart (not 2x) and each turned its own way, so their periods never line up, the sum
        # does not repeat, and the noise lattice leaves no axis-aligned grain.
        octaves = [_value_noise(_rotate(p, rotation) * np.float32(2.1 ** n) + np.float32(17.3 * n), table)
                   for n, rotation in enumerate(_octave_rotations(self.seed))]
        patches = _smoothstep(0.46, 0.54, octaves[0][:, 3:])
        colour = (1 - patches) * np.asarray(self.base, np.float32) + patches * np.asarray(self.patch, np.float32)
        for noise, weight in zip(octaves, (0.45, 0.35, 0.28, 0.22)):
            colour += np.float32(weight) * (noise[:, :3] - np.float32(0.5))
        # Grey detail in the finer octaves: SIFT sees only brightness, which colour noise barely changes.
        for noise in octaves[1::2]:
            colour += np.float32(0.7) * (noise[:, 3:] - np.float32(0.5))
        spots = _smoothstep(0.7, 0.76, octaves[2][:, 3:])
        colour = (1 - spots) * colour + spots * np.asarray(self.spot, np.float32)
        return np.clip(colour, 0.03, 0.97).astype(np.float64)


@dataclass(frozen=True)
class Sphere:
    centre: tuple[float, float, float]
    radius: float
    texture: Texture
    foreground: bool = True
    inward: bool = False                  # seen from inside: the unbounded scene's environment
    shaded: bool = True

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Ray parameter t of the first hit (inf for a miss) for rays origin + t * dirs."""
        oc = origin - np.asarray(self.centre)
        a = _dot(dirs, dirs)
        b = _dot(dirs, oc)
        c = oc @ oc - self.radius ** 2
        disc = b * b - a * c
        root = np.sqrt(np.maximum(disc, 0.0))
        near, far = (-b - root) / a, (-b + root) / a
        t = far if self.inward else np.where(near > MIN_HIT_DISTANCE, near, far)
        return np.where((disc >= 0) & (t > MIN_HIT_DISTANCE), t, np.inf)

    def normals(self, points: np.ndarray) -> np.ndarray:
        n = (points - np.asarray(self.centre)) / self.radius
        return -n if self.inward else n

    def mesh(self) -> trimesh.Trimesh:
        return trimesh.creation.icosphere(subdivisions=4, radius=self.radius).apply_translation(self.centre)


@dataclass(frozen=True)
class Box:
    centre: tuple[float, float, float]
    half_extents: tuple[float, float, float]
    yaw: float                            # rotation about the world z axis, radians
    texture: Texture
    foreground: bool = True
    shaded: bool = True

    def rotation(self) -> np.ndarray:
        """World-from-box rotation."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        rot, h = self.rotation(), np.asarray(self.half_extents)
        t = np.full(len(dirs), np.inf)
        # Only rays that pass through the bounding sphere can hit; a box covers few pixels.
        candidates = np.flatnonzero(np.isfinite(Sphere(self.centre, float(np.linalg.norm(h)), self.texture)
                                                .intersect(origin, dirs)))
        o = rot.T @ (origin - np.asarray(self.centre))
        d = _rotate(dirs[candidates], rot.T)
        t_enter = np.full(len(candidates), -np.inf)
        t_exit = np.full(len(candidates), np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            for axis in range(3):
                t1, t2 = (-h[axis] - o[axis]) / d[:, axis], (h[axis] - o[axis]) / d[:, axis]
                t_enter = np.maximum(t_enter, np.minimum(t1, t2))
                t_exit = np.minimum(t_exit, np.maximum(t1, t2))
        t_hit = np.where(t_enter > MIN_HIT_DISTANCE, t_enter, t_exit)
        t[candidates] = np.where((t_exit >= t_enter) & (t_hit > MIN_HIT_DISTANCE), t_hit, np.inf)
        return t

    def normals(self, points: np.ndarray) -> np.ndarray:
        rot, h = self.rotation(), np.asarray(self.half_extents)
        local = _rotate(points - np.asarray(self.centre), rot.T)
        axis = np.argmax(np.abs(local) / h, axis=1)
        n_local = np.zeros_like(local)
        rows = np.arange(len(local))
        n_local[rows, axis] = np.sign(local[rows, axis])
        return _rotate(n_local, rot)

    def mesh(self) -> trimesh.Trimesh:
        transform = np.eye(4)
        transform[:3, :3], transform[:3, 3] = self.rotation(), self.centre
        return trimesh.creation.box(extents=2 * np.asarray(self.half_extents), transform=transform)


@dataclass(frozen=True)
class Plane:
    """An endless plane; `normal` is the side the cameras see, and the side that is lit."""
    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    texture: Texture
    foreground: bool = False
    shaded: bool = True

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        n = np.asarray(self.normal)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((np.asarray(self.point) - origin) @ n) / _dot(dirs, n)
        return np.where(t > MIN_HIT_DISTANCE, t, np.inf)

    def normals(self, points: np.ndarray) -> np.ndarray:
        return np.broadcast_to(np.asarray(self.normal, dtype=np.float64), points.shape)


@dataclass(frozen=True)
class TurnedTexture:
    """A texture turned with its shape: the colour at a point is the inner texture's at the point turned back."""
    texture: Texture
    angle: float
    pivot: tuple[float, float, float]

    def albedo(self, points: np.ndarray) -> np.ndarray:
        return self.texture.albedo(_turn(points, -self.angle, self.pivot))


@dataclass(frozen=True)
class Turned:
    """A shape turned by `angle` (radians) about the vertical axis through `pivot`, its texture with it."""
    shape: Sphere | Box | Plane
    angle: float
    pivot: tuple[float, float, float]

    @property
    def foreground(self) -> bool:
        return self.shape.foreground

    @property
    def shaded(self) -> bool:
        return self.shape.shaded

    @property
    def texture(self) -> TurnedTexture:
        return TurnedTexture(self.shape.texture, self.angle, self.pivot)

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        back = _z_rotation(-self.angle)
        return self.shape.intersect(_turn(origin[None], -self.angle, self.pivot)[0], _rotate(dirs, back))

    def normals(self, points: np.ndarray) -> np.ndarray:
        return _rotate(self.shape.normals(_turn(points, -self.angle, self.pivot)), _z_rotation(self.angle))

    def mesh(self) -> trimesh.Trimesh:
        transform = np.eye(4)
        transform[:3, :3] = _z_rotation(self.angle)
        transform[:3, 3] = np.asarray(self.pivot) - transform[:3, :3] @ np.asarray(self.pivot)
        return self.shape.mesh().apply_transform(transform)


def _z_rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _turn(points: np.ndarray, angle: float, pivot) -> np.ndarray:
    """Points [N,3] turned by `angle` about the vertical axis through `pivot`."""
    pivot = np.asarray(pivot, dtype=np.float64)
    return _rotate(points - pivot, _z_rotation(angle)) + pivot


Shape = Sphere | Box | Plane | Turned


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
    lambert = np.clip(_dot(shape.normals(points), np.asarray(scene.light)), 0.0, None)
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


def render_view(scene: SceneSpec, c2w: np.ndarray, intrinsics: Intrinsics,
                supersample: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Renders one view.

    Returns rgb [h,w,3] uint8 (background colour where nothing is hit), depth [h,w] float64 along the
    camera's viewing axis (-z in camera space) at the pixel centre, inf where nothing is hit, and
    alpha [h,w] float64 in [0,1]: the share of the pixel covered by foreground shapes.
    """
    rgb, depth, alpha = _render_float(scene, c2w, intrinsics, supersample)
    return _to_uint8(rgb), depth, alpha


def surface_points(scene: SceneSpec, c2w: np.ndarray, k: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel centre's ray first meets a shape: world points [h*w,3] (inf for a miss) and the index into
    scene.shapes [h*w] (-1 for a miss)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    dirs = _rotate(_camera_directions(k), c2w[:3, :3])
    t, index = trace(scene, c2w[:3, 3], dirs)
    return c2w[:3, 3] + t[:, None] * dirs, index


def _render_float(scene: SceneSpec, c2w: np.ndarray, k: Intrinsics, supersample: int):
    c2w = np.asarray(c2w, dtype=np.float64)
    origin, rot = c2w[:3, 3], c2w[:3, :3]
    # Camera-space directions have z = -1, so the ray parameter t is the depth along the viewing axis.
    centre = _camera_directions(k)
    depth, _ = trace(scene, origin, _rotate(centre, rot))

    # Sub-pixel offsets (dx, dy) in pixels shift the camera-space direction by (dx / fl_x, -dy / fl_y, 0).
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    shifts = np.array([(dx / k.fl_x, -dy / k.fl_y, 0.0) for dy in offsets for dx in offsets])
    dirs = _rotate((centre[None] + shifts[:, None]).reshape(-1, 3), rot)
    t, index = trace(scene, origin, dirs)
    colour = np.broadcast_to(np.asarray(scene.background), dirs.shape).copy()
    for s, shape in enumerate(scene.shapes):
        hit = index == s
        if hit.any():
            colour[hit] = surface_colour(scene, shape, origin + t[hit, None] * dirs[hit])
    # The trailing False is what a miss (index -1) picks.
    foreground = np.array([s.foreground for s in scene.shapes] + [False])
    rgb = colour.reshape(len(shifts), k.h, k.w, 3).mean(axis=0)
    alpha = foreground[index].reshape(len(shifts), k.h, k.w).mean(axis=0)
    return rgb, depth.reshape(k.h, k.w), alpha


# Products with a 3-vector or 3x3 matrix over many rows, written out: BLAS spends far longer
# starting and syncing its threads than on the arithmetic, badly so when the cores are busy.
def _dot(vectors: np.ndarray, v: np.ndarray) -> np.ndarray:
    """[N,3] . [3] or row by row with another [N,3] -> [N]."""
    return vectors[:, 0] * v[..., 0] + vectors[:, 1] * v[..., 1] + vectors[:, 2] * v[..., 2]


def _rotate(vectors: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """rotation @ v for every row v of vectors [N,3]."""
    return vectors[:, :1] * rotation[:, 0] + vectors[:, 1:2] * rotation[:, 1] + vectors[:, 2:3] * rotation[:, 2]


@functools.lru_cache(maxsize=8)
def _camera_directions(k: Intrinsics) -> np.ndarray:
    """[h*w,3] camera-space directions through the pixel centres, z = -1."""
    return pixel_directions(k, torch.float64).numpy().reshape(-1, 3)


def _to_uint8(values: np.ndarray) -> np.ndarray:
    return np.round(np.clip(values, 0.0, 1.0) * 255).astype(np.uint8)


# ----------------------------------------------------------------------------------------------
# Scene layouts


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


# ----------------------------------------------------------------------------------------------
# Cameras


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
            c2w[:3, :3] = _z_rotation(-angle) @ still[:3, :3]
            c2w[:3, 3] = _turn(still[None, :3, 3], -angle, centre)[0]
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


# ----------------------------------------------------------------------------------------------
# Writing a scene


def _silently(items, total=None, desc=""):
    return items


def write_scene(kind: str, out_dir: Path | str, n_views: int = 40, width: int = 320, height: int = 240,
                seed: int = 0, alpha: bool = False, supersample: int = 2, masks: bool = False, mast: bool = False,
                track=None) -> Path:
    """Renders a synthetic scene into out_dir (replacing an earlier synthetic scene there) and returns out_dir.
    `masks` writes a mask per photo into masks/ (the object's coverage of each pixel); `mast` adds a thin mast;
    `track(items, total, desc)` wraps the views rendered, for progress (a Reporter's `track`).

    The scene is assembled in a sibling folder and renamed into place, so out_dir is either the old
    scene or the complete new one. Same arguments, same bytes.
    """
    scene = build_scene(kind, seed, mast=mast)
    _check_arguments(kind, n_views, width, height, alpha, supersample)
    out_dir = Path(out_dir)
    _check_replaceable(out_dir)

    tmp = out_dir.with_name(f".{out_dir.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "images").mkdir(parents=True)
    (tmp / "ground_truth").mkdir()
    if masks:
        (tmp / "masks").mkdir()
    k = intrinsics_for(kind, width, height)
    poses = camera_poses(scene, n_views)
    angles = turn_angles(n_views) if scene.room else np.zeros(n_views)
    frames, views = [], []
    for n, (c2w, angle) in enumerate((track or _silently)(list(zip(poses, angles)), total=n_views,
                                                  desc=f"rendering {kind} scene")):
        rgb, depth, coverage = _render_float(view_scene(scene, angle), c2w, k, supersample)
        name = f"images/{n:04d}.png"
        if masks:
            write_png(tmp / "masks" / f"{n:04d}.png", _to_uint8(coverage))
        if alpha:
            # Unpremultiplied colour: compositing the PNG over the background gives the RGB render back.
            with np.errstate(divide="ignore", invalid="ignore"):
                fg = (rgb - (1 - coverage[..., None]) * np.asarray(scene.background)) / coverage[..., None]
            fg = np.where(coverage[..., None] > 0, fg, 0.0)
            write_png(tmp / name, np.concatenate([_to_uint8(fg), _to_uint8(coverage)[..., None]], axis=-1))
        else:
            write_png(tmp / name, _to_uint8(rgb))
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
        view = {"file_path": name, **_depth_range(depth, k)}
        if scene.room:
            view["turn_deg"] = math.degrees(angle)
        views.append(view)

    write_json(tmp / "transforms.json", {
        "camera_model": "PINHOLE",
        "fl_x": k.fl_x, "fl_y": k.fl_y, "cx": k.cx, "cy": k.cy, "w": k.w, "h": k.h,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "frames": frames,
        "synthetic": {"kind": kind, "seed": seed, "n_views": n_views, "alpha": alpha, "supersample": supersample,
                      "masks": masks, "mast": mast},
    })
    scene.mesh().export(tmp / "ground_truth" / "mesh.ply")
    bounds = scene.object_bounds()
    write_json(tmp / "ground_truth" / "scene.json", {
        "kind": kind,
        "seed": seed,
        "world_up": list(WORLD_UP),
        "object_bounds": {"min": bounds[0].tolist(), "max": bounds[1].tolist()},
        "object_centre": list(scene.look_at),
        "environment_radius": ENVIRONMENT_RADIUS if kind == "unbounded" else None,
        "depth_convention": "depth = distance along the camera's viewing axis; distance = along the ray",
        "views": views,
        "scene": scene.to_json(),
    })
    if out_dir.exists():
        shutil.rmtree(out_dir)
    os.replace(tmp, out_dir)
    return out_dir


def _depth_range(depth: np.ndarray, k: Intrinsics) -> dict:
    """Nearest and farthest surface hit in a view, as depth along the viewing axis and as distance along the ray."""
    hit = np.isfinite(depth)
    if not hit.any():
        return {"near_depth": None, "far_depth": None, "near_distance": None, "far_distance": None}
    ray_length = np.linalg.norm(_camera_directions(k), axis=-1).reshape(depth.shape)
    distance = depth[hit] * ray_length[hit]
    return {"near_depth": float(depth[hit].min()), "far_depth": float(depth[hit].max()),
            "near_distance": float(distance.min()), "far_distance": float(distance.max())}


def _check_arguments(kind: str, n_views: int, width: int, height: int, alpha: bool, supersample: int) -> None:
    if n_views < 1:
        raise UserError(f"the number of views must be at least 1 (got {n_views})")
    if width < 8 or height < 8:
        raise UserError(f"images must be at least 8x8 pixels (got {width}x{height})")
    if supersample < 1:
        raise UserError(f"supersample must be at least 1 (got {supersample})")
    if alpha and kind != "object":
        raise UserError(f"alpha only applies to the object kind (the {kind} scene has no empty background)")


def _check_replaceable(out_dir: Path) -> None:
    """Only an empty folder or an earlier synthetic scene may be replaced: never a user's photos."""
    if not out_dir.exists():
        return
    if not out_dir.is_dir():
        raise UserError(f"{out_dir} is a file; give a folder path for the synthetic scene")
    transforms = out_dir / "transforms.json"
    earlier_scene = transforms.is_file() and "synthetic" in read_json(transforms)
    if any(out_dir.iterdir()) and not earlier_scene:
        raise UserError(f"{out_dir} already holds files that are not a synthetic scene; choose an empty or new folder")


# ----------------------------------------------------------------------------------------------
# Value noise


def _smoothstep(lo: float, hi: float, x: np.ndarray) -> np.ndarray:
    x = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return x * x * (3 - 2 * x)


NOISE_PERIOD = 64   # lattice cells per axis of a noise table (a power of two, for the wrap-around mask)


@functools.lru_cache(maxsize=64)
def _noise_table(seed: int) -> np.ndarray:
    """Random bytes at the lattice points of a NOISE_PERIOD^3 cube, four channels each, flattened."""
    return np.random.default_rng(seed).integers(0, 256, (NOISE_PERIOD ** 3, 4), dtype=np.uint8)


@functools.lru_cache(maxsize=64)
def _octave_rotations(seed: int) -> np.ndarray:
    """Four random float32 rotations, one per noise octave."""
    q, r = np.linalg.qr(np.random.default_rng(seed + 1).normal(size=(4, 3, 3)))
    q *= np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    return q.astype(np.float32)


def _value_noise(p: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Four channels [N,4] in [0,1] of smooth value noise at float32 points [N,3], one cell per unit."""
    cell = np.floor(p)
    f = p - cell
    w = f * f * (3 - 2 * f)
    ic = cell.astype(np.int64)
    wrap = NOISE_PERIOD - 1
    xs = [((ic[:, 0] + d) & wrap) * NOISE_PERIOD ** 2 for d in (0, 1)]
    ys = [((ic[:, 1] + d) & wrap) * NOISE_PERIOD for d in (0, 1)]
    zs = [(ic[:, 2] + d) & wrap for d in (0, 1)]

    def corner(dx: int, dy: int, dz: int) -> np.ndarray:
        return np.take(table, xs[dx] + ys[dy] + zs[dz], axis=0).astype(np.float32)

    def lerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
        return a + (b - a) * t

    wx, wy, wz = w[:, 0:1], w[:, 1:2], w[:, 2:3]
    near = lerp(lerp(corner(0, 0, 0), corner(1, 0, 0), wx), lerp(corner(0, 1, 0), corner(1, 1, 0), wx), wy)
    far = lerp(lerp(corner(0, 0, 1), corner(1, 0, 1), wx), lerp(corner(0, 1, 1), corner(1, 1, 1), wx), wy)
    return lerp(near, far, wz) * np.float32(1 / 255)
