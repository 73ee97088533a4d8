"""What the poses stage hands over, as the framing reads it: the cameras (poses, intrinsics, image names) and the
sparse points with the images that see them."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plenoxels.core.cameras import Intrinsics, project
from plenoxels.core.errors import UserError


# At least this many sparse points before they are trusted to describe the scene or one image's depths.
MIN_POINTS = 30
MIN_POINTS_PER_IMAGE = 10



@dataclass
class Cameras:
    names: list[str]
    frames: list[dict]                  # the poses stage's frame records, in the same order
    c2w: np.ndarray                     # [N,4,4] input frame
    intrinsics: list[Intrinsics]
    bounds: np.ndarray | None           # [N,2] LLFF near/far depths (input units) when every frame has them

    @property
    def origins(self) -> np.ndarray:
        return self.c2w[:, :3, 3]

    @property
    def view_dirs(self) -> np.ndarray:
        return -self.c2w[:, :3, 2] / np.linalg.norm(self.c2w[:, :3, 2], axis=1, keepdims=True)



@dataclass
class Points:
    xyz: np.ndarray                     # [P,3]
    obs_frame: np.ndarray               # [V] index into the frames of transforms.json
    obs_point: np.ndarray               # [V]

    @staticmethod
    def empty() -> "Points":
        return Points(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))



def read_cameras(transforms: dict) -> Cameras:
    frames = transforms.get("frames") or []
    if len(frames) < 2:
        raise UserError(f"the poses hold {len(frames)} camera(s); at least 2 posed images are needed to normalise a scene")
    names, c2w, intrinsics = [], [], []
    for frame in frames:
        names.append(frame.get("name") or Path(frame["file_path"]).stem)
        c2w.append(np.asarray(frame["transform_matrix"], dtype=np.float64))
        intrinsics.append(Intrinsics.from_frame({**transforms, **frame}))  # per-frame values override shared ones
    bounds = None
    if all("near" in f and "far" in f for f in frames):
        bounds = np.array([[f["near"], f["far"]] for f in frames], dtype=np.float64)
    return Cameras(names, frames, np.stack(c2w), intrinsics, bounds)



def read_points(path: Path) -> Points:
    if not path.is_file():
        return Points.empty()
    with np.load(path) as data:
        xyz = np.asarray(data["xyz"], dtype=np.float64).reshape(-1, 3)
        obs_frame = np.asarray(data["obs_frame"], dtype=np.int64) if "obs_frame" in data else np.zeros(0, np.int64)
        obs_point = np.asarray(data["obs_point"], dtype=np.int64) if "obs_point" in data else np.zeros(0, np.int64)
    return Points(xyz, obs_frame, obs_point)



def points_seen_by_frame(points: Points, cams: Cameras) -> list[np.ndarray]:
    """Indices of the points each frame sees: its SfM observations, or (without any) the points inside its image."""
    if len(points.obs_frame):
        order = np.argsort(points.obs_frame, kind="stable")
        splits = np.searchsorted(points.obs_frame[order], np.arange(len(cams.names) + 1))
        return [points.obs_point[order[splits[i]:splits[i + 1]]] for i in range(len(cams.names))]
    seen = []
    for c2w, k in zip(cams.c2w, cams.intrinsics):
        uv, depth = project(points.xyz, c2w, k)
        inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= k.w) & (uv[:, 1] >= 0) & (uv[:, 1] <= k.h)
        seen.append(np.flatnonzero(inside))
    return seen
