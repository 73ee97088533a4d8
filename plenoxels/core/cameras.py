"""The project's one camera convention, and the conversions at its edges.

Inside the project every camera is a pinhole with a 4x4 camera-to-world matrix in the OpenGL/NeRF
convention: camera x points right, y up, and the camera looks down -z. Intrinsics are fl_x, fl_y,
cx, cy in pixels, and pixel (column i, row j) has its centre at (i + 0.5, j + 0.5).

Other conventions are converted here, where data enters or leaves, and nowhere else:
- COLMAP / OpenCV: world-to-camera, camera x right, y down, looks down +z.
- LLFF poses_bounds.npy: camera-to-world 3x4 with columns [down, right, back], plus H, W, focal.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

# Flips y and z: maps OpenCV camera axes to OpenGL camera axes and back (it is its own inverse).
OPENCV_TO_OPENGL_AXES = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Intrinsics:
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    w: int
    h: int

    @classmethod
    def from_frame(cls, frame: dict) -> "Intrinsics":
        """From a frame record's (or a transforms.json's shared) fl_x, fl_y, cx, cy, w, h."""
        return cls(float(frame["fl_x"]), float(frame["fl_y"]), float(frame["cx"]), float(frame["cy"]),
                   int(frame["w"]), int(frame["h"]))

    def matrix(self) -> np.ndarray:
        return np.array([[self.fl_x, 0, self.cx], [0, self.fl_y, self.cy], [0, 0, 1]], dtype=np.float64)

    def scaled(self, factor: float) -> "Intrinsics":
        """The same camera for an image resized by `factor` (pixel-centre convention kept exact)."""
        w, h = max(1, round(self.w * factor)), max(1, round(self.h * factor))
        sx, sy = w / self.w, h / self.h
        return Intrinsics(self.fl_x * sx, self.fl_y * sy, self.cx * sx, self.cy * sy, w, h)


def opengl_c2w_from_colmap_w2c(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """COLMAP's world-to-camera (R, t) -> our 4x4 camera-to-world."""
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = rotation, translation
    return np.linalg.inv(w2c) @ OPENCV_TO_OPENGL_AXES


def colmap_w2c_from_opengl_c2w(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Our 4x4 camera-to-world -> COLMAP's world-to-camera (R, t)."""
    w2c = np.linalg.inv(c2w @ OPENCV_TO_OPENGL_AXES)
    return w2c[:3, :3], w2c[:3, 3]


def opengl_c2w_from_projection(projection: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A 3x4 projection P = K [R | t] (OpenCV's camera axes, any scale or sign) -> (K 3x3 with K[2, 2] = 1, our 4x4
    camera-to-world). K comes out of an RQ decomposition of P's left 3x3 with a positive diagonal."""
    projection = np.asarray(projection, dtype=np.float64)[:3, :4]
    flip = np.flipud(np.eye(3))
    q, r = np.linalg.qr((flip @ projection[:, :3]).T)
    k, rotation = flip @ r.T @ flip, flip @ q.T
    signs = np.diag(np.sign(np.diag(k)))
    k, rotation = k @ signs, signs @ rotation
    if np.linalg.det(rotation) < 0:  # P's overall sign was negative
        k, rotation = -k, -rotation
    centre = -np.linalg.solve(projection[:, :3], projection[:, 3])
    return k / k[2, 2], opengl_c2w_from_colmap_w2c(rotation, -rotation @ centre)


def opengl_c2w_from_llff(pose_3x4: np.ndarray) -> np.ndarray:
    """LLFF's camera-to-world with columns [down, right, back] -> ours ([right, up, back])."""
    down, right, back, centre = pose_3x4[:, 0], pose_3x4[:, 1], pose_3x4[:, 2], pose_3x4[:, 3]
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, -down, back, centre
    return c2w


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world for a camera at `eye` looking at `target`, with image-up towards `up`."""
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(right, forward), -forward, eye
    return c2w


def project(points_world: np.ndarray, c2w: np.ndarray, k: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """World points [N,3] -> pixel coordinates [N,2] (continuous, pixel centres at +0.5) and depth [N]
    along the viewing axis (positive in front of the camera)."""
    w2c = np.linalg.inv(c2w)
    p_cam = points_world @ w2c[:3, :3].T + w2c[:3, 3]
    depth = -p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = k.fl_x * p_cam[:, 0] / depth + k.cx
        v = -k.fl_y * p_cam[:, 1] / depth + k.cy
    return np.stack([u, v], axis=-1), depth


def pixel_directions(k: Intrinsics, dtype=torch.float32) -> torch.Tensor:
    """Unnormalised camera-space ray directions [h, w, 3] through every pixel centre."""
    j, i = torch.meshgrid(torch.arange(k.h, dtype=torch.float64), torch.arange(k.w, dtype=torch.float64), indexing="ij")
    d = torch.stack([(i + 0.5 - k.cx) / k.fl_x, -(j + 0.5 - k.cy) / k.fl_y, -torch.ones_like(i)], dim=-1)
    return d.to(dtype)


def rays_from_camera(c2w, k: Intrinsics, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Origins and unit directions [h, w, 3] of the rays through every pixel centre, in the world frame."""
    c2w = torch.as_tensor(np.asarray(c2w), dtype=torch.float64)
    d = pixel_directions(k, torch.float64) @ c2w[:3, :3].T
    d = d / d.norm(dim=-1, keepdim=True)
    o = c2w[:3, 3].expand_as(d)
    return o.to(dtype).contiguous(), d.to(dtype).contiguous()
