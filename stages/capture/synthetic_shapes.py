"""The synthetic scenes' analytic shapes (spheres, boxes, planes, and shapes turned about a pivot) with their ray
intersections and normals, and the solid textures they carry (value noise over several octaves, colour patches,
spots), so the same 3D point looks the same from every view."""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import trimesh


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
        octaves = [_value_noise(rotate_rows(p, rotation) * np.float32(2.1 ** n) + np.float32(17.3 * n), table)
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
        a = dot_rows(dirs, dirs)
        b = dot_rows(dirs, oc)
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
        d = rotate_rows(dirs[candidates], rot.T)
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
        local = rotate_rows(points - np.asarray(self.centre), rot.T)
        axis = np.argmax(np.abs(local) / h, axis=1)
        n_local = np.zeros_like(local)
        rows = np.arange(len(local))
        n_local[rows, axis] = np.sign(local[rows, axis])
        return rotate_rows(n_local, rot)

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
            t = ((np.asarray(self.point) - origin) @ n) / dot_rows(dirs, n)
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
        return self.texture.albedo(turn_about(points, -self.angle, self.pivot))



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
        back = z_rotation(-self.angle)
        return self.shape.intersect(turn_about(origin[None], -self.angle, self.pivot)[0], rotate_rows(dirs, back))

    def normals(self, points: np.ndarray) -> np.ndarray:
        return rotate_rows(self.shape.normals(turn_about(points, -self.angle, self.pivot)), z_rotation(self.angle))

    def mesh(self) -> trimesh.Trimesh:
        transform = np.eye(4)
        transform[:3, :3] = z_rotation(self.angle)
        transform[:3, 3] = np.asarray(self.pivot) - transform[:3, :3] @ np.asarray(self.pivot)
        return self.shape.mesh().apply_transform(transform)



def z_rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])



def turn_about(points: np.ndarray, angle: float, pivot) -> np.ndarray:
    """Points [N,3] turned by `angle` about the vertical axis through `pivot`."""
    pivot = np.asarray(pivot, dtype=np.float64)
    return rotate_rows(points - pivot, z_rotation(angle)) + pivot



Shape = Sphere | Box | Plane | Turned



# Products with a 3-vector or 3x3 matrix over many rows, written out: BLAS spends far longer
# starting and syncing its threads than on the arithmetic, badly so when the cores are busy.
def dot_rows(vectors: np.ndarray, v: np.ndarray) -> np.ndarray:
    """[N,3] . [3] or row by row with another [N,3] -> [N]."""
    return vectors[:, 0] * v[..., 0] + vectors[:, 1] * v[..., 1] + vectors[:, 2] * v[..., 2]



def rotate_rows(vectors: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """rotation @ v for every row v of vectors [N,3]."""
    return vectors[:, :1] * rotation[:, 0] + vectors[:, 1:2] * rotation[:, 1] + vectors[:, 2:3] * rotation[:, 2]



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
