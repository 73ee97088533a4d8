"""Normalized device coordinates (NDC) for forward-facing scenes, in the LLFF convention.

A forward-facing capture looks at a world that reaches from a near plane to infinity. A cubic grid in
the world would spend almost all of its voxels on empty far depth; the projective map of the
reference camera squeezes [near, infinity) into z in [-1, 1] and the reference image into x, y in
[-1, 1], so a grid on [-1, 1]^3 spends its voxels where the pixels are.

In the reference camera's frame (OpenGL: x right, y up, looking down -z), a point (x, y, z) with z < 0
maps to
    x_ndc = ax * x / -z + bx,    ax = 2 fl_x / w,   bx = 2 cx / w - 1
    y_ndc = ay * y / -z + by,    ay = 2 fl_y / h,   by = 1 - 2 cy / h
    z_ndc = 1 + 2 near / z
so x_ndc, y_ndc are the reference image's pixel coordinates scaled to [-1, 1] (y up), the near plane
z = -near goes to z_ndc = -1 and infinity to z_ndc = 1. With the principal point at the image centre
(bx = by = 0) this is LLFF's `ndc_rays`.

The map is projective, so a world ray maps to a straight NDC ray. As in LLFF, each ray's origin is
first moved along the ray to the near plane; the NDC ray then starts at z_ndc = -1 (t = 0) and reaches
the image of the ray's point at infinity at t = 1. The fit integrates density over NDC distance.

Rays that do not move into the scene (direction z >= -PARALLEL_EPS * |d| in the reference frame,
including rays parallel to the image plane) have no point at infinity in front of the camera; their
direction's z is set to -PARALLEL_EPS * |d| before mapping. The result is finite, and for origins
behind the near plane (every camera of a forward capture) the NDC ray lies far outside the grid box
in x or y, so it sees no grid, only what is behind it.

The grid box is the reference image in x and y only for the reference camera. Every other camera is
shifted and turned a little, so near its image's edges it sees what lies outside the reference
image: on fern, 3-10% of a training view's pixels at mid depth. A box of [-1, 1]^3 leaves those rays
nothing to fit but the constant colour behind the grid. The box therefore reaches, in x and y, as far
as the training cameras' views do between the near plane and infinity (Plenoxels' LLFF grid is
likewise about 1.5x the reference image); z stays [-1, 1]. The cells keep their size in the reference
image's pixels, so the wider box adds cells rather than coarsening them (bench/README.md, "Scene models").
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from plenoxels.core.cameras import Intrinsics, pixel_directions
from plenoxels.core.errors import UserError

# Smallest |d_z| / |d| a ray keeps in the reference frame; below it the ray counts as parallel.
PARALLEL_EPS = 1e-5
# Largest NDC depth mapped back to the world: z_ndc = 1 is infinitely far.
MAX_Z_NDC = 1.0 - 1e-5
# Plenoxels' LLFF grids keep 128 depth cells at every level (256x256x128 up to 1408x1156x128): depth
# needs half the cells across at coarse levels, and no more than 128 at fine ones: more depth cells than half
# gain little for their time (bench/README.md, "Scene models").
DEPTH_FRACTION = 0.5
MAX_DEPTH_CELLS = 128
# The grid box reaches at most this far in x and y (NDC units; the reference image is [-1, 1]), so it
# holds at most 4x the cells of the reference view's frustum: further out only the outermost cameras see.
MAX_BOX_REACH = 2.0
# Grown by this share of its size on each side, so the outermost training rays do not graze its faces.
BOX_MARGIN = 0.02


@dataclass(frozen=True)
class NDCMapping:
    """The projective map of one reference camera: world <-> NDC."""
    reference_c2w: tuple[tuple[float, ...], ...]   # 4x4, OpenGL camera-to-world in the normalised world
    near: float
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    w: int
    h: int
    # The grid box in x and y (NDC units): the reference image, [-1, 1], unless from_scene widened it to
    # what the training cameras see.
    box_min: tuple[float, float] = (-1.0, -1.0)
    box_max: tuple[float, float] = (1.0, 1.0)

    def __post_init__(self):
        c2w = np.asarray(self.reference_c2w, dtype=np.float64)
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            raise UserError("the forward block's reference_c2w must be a finite 4x4 matrix; re-run the normalize stage")
        # Stored as nested tuples so mappings compare, hash and serialise the same however they were built.
        object.__setattr__(self, "reference_c2w", _as_tuple(c2w))
        if not (self.near > 0 and math.isfinite(self.near)):
            raise UserError(f"NDC needs a positive near plane, got {self.near}; re-run the normalize stage "
                            "or set fit.ndc=off")
        if not (self.fl_x > 0 and self.fl_y > 0 and self.w > 0 and self.h > 0):
            raise UserError("NDC needs positive focal lengths and image size in scene.json's frames")
        object.__setattr__(self, "box_min", tuple(float(v) for v in self.box_min))
        object.__setattr__(self, "box_max", tuple(float(v) for v in self.box_max))
        if not (len(self.box_min) == len(self.box_max) == 2
                and all(-MAX_BOX_REACH <= lo < hi <= MAX_BOX_REACH for lo, hi in zip(self.box_min, self.box_max))):
            raise UserError(f"the NDC grid box {self.box_min}..{self.box_max} must be increasing and within "
                            f"+-{MAX_BOX_REACH:g}; fit again")

    # ---- construction -------------------------------------------------------------------------
    @classmethod
    def from_scene(cls, scene: dict[str, Any]) -> "NDCMapping":
        """From normalize/scene.json: its `forward` block (reference camera, near), the intrinsics of
        the training frames (the median, so one odd frame does not decide the NDC map) and the grid box
        that the training frames' views cover (see covering_box)."""
        block = scene.get("forward")
        if not isinstance(block, dict) or "reference_c2w" not in block or "near" not in block:
            raise UserError("scene.json has no forward block (reference_c2w, near); NDC needs a forward scene: "
                            "re-run normalize or set fit.ndc=off")
        frames = [f for f in scene.get("frames", []) if f.get("split", "train") == "train"] or scene.get("frames", [])
        if not frames:
            raise UserError("scene.json lists no frames; re-run the normalize stage")

        def median(key: str) -> float:
            if key in block:
                return float(block[key])
            return float(np.median([float(f[key]) for f in frames]))

        mapping = cls(reference_c2w=block["reference_c2w"], near=float(block["near"]),
                      fl_x=median("fl_x"), fl_y=median("fl_y"), cx=median("cx"), cy=median("cy"),
                      w=int(round(median("w"))), h=int(round(median("h"))))
        views = [f for f in frames if "transform_matrix" in f]
        if not views:
            return mapping
        box_min, box_max = mapping.covering_box(views)
        return replace(mapping, box_min=box_min, box_max=box_max)

    def covering_box(self, frames: list[dict[str, Any]]) -> tuple[tuple[float, float], tuple[float, float]]:
        """(x, y) minimum and maximum of the NDC box that holds what these frames (scene.json records)
        see from the near plane to infinity, grown by BOX_MARGIN, at least the reference image and at
        most MAX_BOX_REACH. A camera's view there is the image of its frustum; the map is projective, so
        the extremes lie on the rays through the image corners, at the near plane or at infinity."""
        lo, hi = np.array([-1.0, -1.0]), np.array([1.0, 1.0])
        for frame in frames:
            c2w = torch.tensor(np.asarray(frame["transform_matrix"], dtype=np.float64)[:3])
            k = Intrinsics.from_frame(frame)
            # Directions through the pixel corners: pixel_directions gives centres, shifted by half a pixel.
            centres = pixel_directions(Intrinsics(k.fl_x, k.fl_y, k.cx + 0.5, k.cy + 0.5, k.w + 1, k.h + 1),
                                       torch.float64)
            corners = centres[[0, 0, -1, -1], [0, -1, 0, -1]] @ c2w[:, :3].T
            o_ndc, d_ndc = self.rays(c2w[:, 3].expand_as(corners), corners)
            ends = torch.cat([o_ndc[:, :2], (o_ndc + d_ndc)[:, :2]]).numpy()
            lo, hi = np.minimum(lo, ends.min(axis=0)), np.maximum(hi, ends.max(axis=0))
        grow = (hi - lo) * BOX_MARGIN
        lo, hi = np.maximum(lo - grow, -MAX_BOX_REACH), np.minimum(hi + grow, MAX_BOX_REACH)
        return (float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1]))

    def to_dict(self) -> dict[str, Any]:
        return {"reference_c2w": [list(r) for r in self.reference_c2w], "near": self.near, "fl_x": self.fl_x,
                "fl_y": self.fl_y, "cx": self.cx, "cy": self.cy, "w": self.w, "h": self.h,
                "box_min": list(self.box_min), "box_max": list(self.box_max)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "NDCMapping":
        return cls(reference_c2w=d["reference_c2w"], near=float(d["near"]), fl_x=float(d["fl_x"]),
                   fl_y=float(d["fl_y"]), cx=float(d["cx"]), cy=float(d["cy"]), w=int(d["w"]), h=int(d["h"]),
                   # Fits saved before the box was recorded used the reference image alone.
                   box_min=tuple(d.get("box_min", (-1.0, -1.0))), box_max=tuple(d.get("box_max", (1.0, 1.0))))

    # ---- the grid in NDC ----------------------------------------------------------------------
    def grid_box(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """bbox_min, bbox_max of the grid in NDC: what the training cameras see, from the near plane
        (z = -1) to infinity (z = 1)."""
        return (*self.box_min, -1.0), (*self.box_max, 1.0)

    def grid_resolution(self, max_side: int, min_depth: int = 16) -> tuple[int, int, int]:
        """Anisotropic (Rx, Ry, Rz): `max_side` cells along the reference image's longer side, so cells are
        square in its pixels, and as many more as the box reaches beyond the image; depth as Plenoxels'
        LLFF grids have it: half the cells across the image, at most 128 (at least `min_depth`)."""
        if max_side < 2:
            raise UserError(f"the NDC grid needs at least 2 cells across, got {max_side}")
        longer = max(self.w, self.h)
        across_x = (self.box_max[0] - self.box_min[0]) / 2 * self.w
        across_y = (self.box_max[1] - self.box_min[1]) / 2 * self.h
        rx = max(2, round(max_side * across_x / longer))
        ry = max(2, round(max_side * across_y / longer))
        rz = max(min_depth, min(MAX_DEPTH_CELLS, round(max_side * DEPTH_FRACTION)))
        return rx, ry, rz

    # ---- the map ------------------------------------------------------------------------------
    def _frame(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        c2w = torch.tensor(self.reference_c2w, dtype=torch.float64, device=like.device)
        return c2w[:3, :3], c2w[:3, 3]

    def _scales(self) -> tuple[float, float, float, float]:
        return (2 * self.fl_x / self.w, 2 * self.cx / self.w - 1, 2 * self.fl_y / self.h, 1 - 2 * self.cy / self.h)

    def points_to_ndc(self, p_world: torch.Tensor) -> torch.Tensor:
        """World points [..., 3] in front of the near plane -> NDC points [..., 3]."""
        rot, centre = self._frame(p_world)
        p = (p_world.to(torch.float64) - centre) @ rot
        ax, bx, ay, by = self._scales()
        z = p[..., 2]
        out = torch.stack([ax * p[..., 0] / -z + bx, ay * p[..., 1] / -z + by, 1 + 2 * self.near / z], dim=-1)
        return out.to(p_world.dtype)

    def points_to_world(self, p_ndc: torch.Tensor) -> torch.Tensor:
        """NDC points [..., 3] -> world points [..., 3]. z_ndc is clamped to [-1, MAX_Z_NDC]: z_ndc = 1 is
        infinitely far, and the clamp keeps far points finite (2e5 near planes away)."""
        rot, centre = self._frame(p_ndc)
        q = p_ndc.to(torch.float64)
        ax, bx, ay, by = self._scales()
        z = 2 * self.near / (q[..., 2].clamp(-1.0, MAX_Z_NDC) - 1)
        p = torch.stack([(q[..., 0] - bx) * -z / ax, (q[..., 1] - by) * -z / ay, z], dim=-1)
        return (p @ rot.T + centre).to(p_ndc.dtype)

    def rays(self, o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World rays (origins, directions [..., 3]; any length) -> NDC rays (o_ndc, d_ndc), LLFF convention:
        o_ndc is where the ray crosses the near plane (z_ndc = -1) and o_ndc + d_ndc the image of its point at
        infinity (z_ndc = 1), so d_ndc is not unit length. Computed in float64, returned in o's dtype."""
        rot, centre = self._frame(o)
        oc = (o.to(torch.float64) - centre) @ rot
        dc = d.to(torch.float64) @ rot
        # Bend rays that do not move into the scene (see the module docstring) so the map stays finite.
        limit = -PARALLEL_EPS * dc.norm(dim=-1).clamp_min(1e-30)
        dz = torch.minimum(dc[..., 2], limit)
        ax, bx, ay, by = self._scales()
        # Closed forms of LLFF's shift-then-project, rearranged so no large terms cancel near d_z = 0.
        rx, ry = dc[..., 0] / dz, dc[..., 1] / dz
        shift = (self.near + oc[..., 2]) / self.near
        o_ndc = torch.stack([ax * (oc[..., 0] / self.near - shift * rx) + bx,
                             ay * (oc[..., 1] / self.near - shift * ry) + by,
                             torch.full_like(rx, -1.0)], dim=-1)
        d_ndc = torch.stack([ax * (oc[..., 2] * rx - oc[..., 0]) / self.near,
                             ay * (oc[..., 2] * ry - oc[..., 1]) / self.near,
                             torch.full_like(rx, 2.0)], dim=-1)
        return o_ndc.to(o.dtype), d_ndc.to(o.dtype)

    def world_distance(self, o: torch.Tensor, d: torch.Tensor, p_ndc: torch.Tensor) -> torch.Tensor:
        """Distance along each world ray (o, d) [..., 3] from o to the world point of an NDC point on it
        (a rendered NDC depth point, for example): for depth maps in world units."""
        p = self.points_to_world(p_ndc).to(torch.float64)
        unit = d.to(torch.float64) / d.to(torch.float64).norm(dim=-1, keepdim=True)
        return ((p - o.to(torch.float64)) * unit).sum(-1).to(o.dtype)


def _as_tuple(m) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(v) for v in row) for row in np.asarray(m, dtype=np.float64).reshape(4, 4))
