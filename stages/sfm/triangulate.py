"""Sparse points for imported poses: what the cameras look at and how far it lies.

Poses imported from a transforms.json or LLFF's poses_bounds.npy come without points, yet the normalize stage
needs them: the foreground box, the scene type and each image's near/far come from where the scene's content
lies, and without points it could only guess from the cameras (the region they surround, which in a room takes
in the room). With the poses known, points cost little: SIFT features in each photo (OpenCV), matched only with
the photos taken from nearby and facing the same way, kept only where the match agrees with the known epipolar
geometry, and triangulated from the two known cameras. There is no bundle adjustment and no track building; a
point is one matched pair, with its two observations, which is all that the depth statistics downstream read.
"""
from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from plenoxels.core.cameras import Intrinsics, colmap_w2c_from_opengl_c2w, project

# Photos are searched for features at most this many pixels on their longer side.
FEATURE_MAX_SIDE = 800
FEATURES = 2000
# Each photo is matched with this many others: those whose viewing directions are within PAIR_MAX_ANGLE_DEG of
# its own and whose centres lie closest.
NEIGHBOURS = 5
PAIR_MAX_ANGLE_DEG = 60.0
# Lowe's ratio test, then the epipolar line of the known poses, in pixels at the feature scale.
RATIO = 0.8
EPIPOLAR_PX = 1.5
# A triangulated point must reproject within this many pixels in both photos, and its two rays must meet at
# this angle at least (smaller angles put the depth anywhere along the ray).
REPROJECTION_PX = 2.0
MIN_ANGLE_DEG = 1.0
MAX_POINTS = 50_000


@dataclass
class TriangulatedPoints:
    xyz: np.ndarray          # [P, 3] world (the poses' frame)
    rgb: np.ndarray          # [P, 3] uint8
    error: np.ndarray        # [P] mean reprojection error, pixels at the photos' size
    obs_frame: np.ndarray    # [2P] frame index of each observation
    obs_point: np.ndarray    # [2P] point index of each observation
    pairs: int               # image pairs matched
    # [Q, 4] for each pair matched: its two frames, its matches that pass the ratio test, and how many of them agree
    # with the poses' epipolar geometry (on their epipolar lines, and not meeting behind a camera)
    agreement: np.ndarray

    def arrays(self) -> dict[str, np.ndarray]:
        """The layout of poses/points.npz."""
        return {"xyz": self.xyz, "rgb": self.rgb, "error": self.error,
                "track_length": np.full(len(self.xyz), 2, dtype=np.int32),
                "obs_frame": self.obs_frame.astype(np.int32), "obs_point": self.obs_point.astype(np.int32)}


def neighbour_pairs(c2w: np.ndarray, neighbours: int = NEIGHBOURS, max_angle_deg: float = PAIR_MAX_ANGLE_DEG) -> list[tuple[int, int]]:
    """Pairs (i < j) of cameras that face within max_angle_deg of each other, each camera with its `neighbours`
    nearest such cameras by centre distance."""
    centres = c2w[:, :3, 3]
    views = -c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
    facing = views @ views.T >= math.cos(math.radians(max_angle_deg))
    distance = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    distance[~facing] = np.inf
    np.fill_diagonal(distance, np.inf)
    pairs = set()
    for i in range(len(c2w)):
        for j in np.argsort(distance[i])[:neighbours]:
            if np.isfinite(distance[i, j]):
                pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def _projection(c2w: np.ndarray, k: Intrinsics) -> np.ndarray:
    """3x4 OpenCV projection matrix whose pixel coordinates follow the project's convention (centres at +0.5)."""
    rotation, translation = colmap_w2c_from_opengl_c2w(c2w)
    return k.matrix() @ np.hstack([rotation, translation[:, None]])


def _fundamental(p1: np.ndarray, p2: np.ndarray, c1: np.ndarray) -> np.ndarray:
    """F with x2^T F x1 = 0, from the two projection matrices and the first camera's centre."""
    e2 = p2 @ np.append(c1, 1.0)
    skew = np.array([[0, -e2[2], e2[1]], [e2[2], 0, -e2[0]], [-e2[1], e2[0], 0]])
    return skew @ p2 @ np.linalg.pinv(p1)


def _epipolar_distance(f: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Symmetric point-to-epipolar-line distance (pixels) of matches x1 [M, 2] <-> x2 [M, 2]."""
    h1, h2 = np.hstack([x1, np.ones((len(x1), 1))]), np.hstack([x2, np.ones((len(x2), 1))])
    lines2, lines1 = h1 @ f.T, h2 @ f
    d2 = np.abs((lines2 * h2).sum(1)) / np.maximum(np.linalg.norm(lines2[:, :2], axis=1), 1e-12)
    d1 = np.abs((lines1 * h1).sum(1)) / np.maximum(np.linalg.norm(lines1[:, :2], axis=1), 1e-12)
    return np.maximum(d1, d2)


def _colours(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """uint8 colours [M, 3] of `image` at continuous pixel coordinates xy [M, 2] (centres at +0.5)."""
    col = np.clip(xy[:, 0].astype(np.int64), 0, image.shape[1] - 1)
    row = np.clip(xy[:, 1].astype(np.int64), 0, image.shape[0] - 1)
    return image[row, col].astype(np.uint8)


def triangulate(images: Iterable[np.ndarray], c2w: np.ndarray, intrinsics: list[Intrinsics],
                seed: int = 0) -> TriangulatedPoints:
    """Points seen by pairs of the posed photos `images` (uint8 RGB [h, w, 3], at the size `intrinsics` describe),
    read one at a time: each photo's features keep their colours, so no photo is needed twice."""
    sift = cv2.SIFT_create(nfeatures=FEATURES)
    features, scales = [], []
    for image in images:
        scale = min(1.0, FEATURE_MAX_SIDE / max(image.shape[:2]))
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        if scale < 1.0:
            gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        keypoints, descriptors = sift.detectAndCompute(gray, None)
        # Pixel centres at +0.5, at the photo's full size.
        xy = (np.array([kp.pt for kp in keypoints], dtype=np.float64).reshape(-1, 2) + 0.5) / scale
        features.append((xy, descriptors, _colours(image, xy)))
        scales.append(scale)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    pairs = neighbour_pairs(c2w)
    xyz_all, err_all, rgb_all, obs_all, agreement = [], [], [], [], []
    for i, j in pairs:
        (xy_i, desc_i, rgb_i), (xy_j, desc_j, _) = features[i], features[j]
        if desc_i is None or desc_j is None or len(desc_i) < 2 or len(desc_j) < 2:
            continue
        knn = matcher.knnMatch(desc_i, desc_j, k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < RATIO * m[1].distance]
        if len(good) < 8:
            continue
        a = np.array([m.queryIdx for m in good])
        b = np.array([m.trainIdx for m in good])
        x1, x2 = xy_i[a], xy_j[b]
        p1, p2 = _projection(c2w[i], intrinsics[i]), _projection(c2w[j], intrinsics[j])
        tolerance = EPIPOLAR_PX / min(scales[i], scales[j])
        keep = _epipolar_distance(_fundamental(p1, p2, c2w[i][:3, 3]), x1, x2) < tolerance
        if keep.sum() < 8:
            agreement.append((i, j, len(good), int(keep.sum())))
            continue
        x1, x2, a, b = x1[keep], x2[keep], a[keep], b[keep]
        homogeneous = cv2.triangulatePoints(p1, p2, x1.T, x2.T)
        xyz = (homogeneous[:3] / homogeneous[3]).T
        uv1, depth1 = project(xyz, c2w[i], intrinsics[i])
        uv2, depth2 = project(xyz, c2w[j], intrinsics[j])
        error = 0.5 * (np.linalg.norm(uv1 - x1, axis=1) + np.linalg.norm(uv2 - x2, axis=1))
        ray1, ray2 = xyz - c2w[i][:3, 3], xyz - c2w[j][:3, 3]
        cos = (ray1 * ray2).sum(1) / np.maximum(np.linalg.norm(ray1, axis=1) * np.linalg.norm(ray2, axis=1), 1e-12)
        meets = (cos < math.cos(math.radians(MIN_ANGLE_DEG))) & np.isfinite(xyz).all(1)
        # A match on its epipolar line whose rays meet behind a camera contradicts the poses all the same: cameras
        # that slide along one line keep each other's epipolar lines wherever the file puts them, not the side.
        agreement.append((i, j, len(good), int(keep.sum() - (meets & ((depth1 <= 0) | (depth2 <= 0))).sum())))
        good_point = ((depth1 > 0) & (depth2 > 0) & (error < REPROJECTION_PX / min(scales[i], scales[j])) & meets)
        start = sum(len(x) for x in xyz_all)
        count = int(good_point.sum())
        xyz_all.append(xyz[good_point])
        err_all.append(error[good_point])
        rgb_all.append(rgb_i[a][good_point])
        index = np.arange(start, start + count)
        obs_all.append((np.repeat([i, j], count), np.concatenate([index, index])))
    if not xyz_all or sum(len(x) for x in xyz_all) == 0:
        empty = np.zeros(0, dtype=np.int64)
        return TriangulatedPoints(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), empty, empty, len(pairs),
                                  np.array(agreement, dtype=np.int64).reshape(-1, 4))
    xyz = np.concatenate(xyz_all)
    error = np.concatenate(err_all)
    obs_frame = np.concatenate([o[0] for o in obs_all])
    obs_point = np.concatenate([o[1] for o in obs_all])
    # Each point's colour where the first photo of its pair saw it.
    rgb = np.concatenate(rgb_all)
    if len(xyz) > MAX_POINTS:
        chosen = np.sort(np.random.default_rng(seed).choice(len(xyz), MAX_POINTS, replace=False))
        remap = np.full(len(xyz), -1)
        remap[chosen] = np.arange(MAX_POINTS)
        kept = remap[obs_point] >= 0
        obs_frame, obs_point = obs_frame[kept], remap[obs_point[kept]]
        xyz, error, rgb = xyz[chosen], error[chosen], rgb[chosen]
    return TriangulatedPoints(xyz, rgb, error, obs_frame, obs_point, len(pairs),
                              np.array(agreement, dtype=np.int64).reshape(-1, 4))
