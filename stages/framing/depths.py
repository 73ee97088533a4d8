"""Near and far per image: from the depths of the sparse points each camera sees, else from the box; and a forward
capture's depth range."""
from __future__ import annotations

import numpy as np

from plenoxels.core.cameras import Intrinsics, project
from stages.framing.sightings import Cameras, MIN_POINTS, MIN_POINTS_PER_IMAGE


# Near/far per image: these percentiles of the depths of the points seen there, widened by NEAR_FAR_MARGIN.
NEAR_FAR_PERCENTILES = (1.0, 99.0)
NEAR_FAR_MARGIN = 0.1



def near_far_from_points(xyz: np.ndarray, c2w: np.ndarray, k: Intrinsics) -> tuple[float, float] | None:
    """Near from depths along the viewing axis, far from distances along the rays, so [near, far] brackets
    the points whichever of the two a sampler measures (depth <= distance)."""
    _, depth = project(xyz, c2w, k)
    in_front = depth > 0
    if in_front.sum() < MIN_POINTS_PER_IMAGE:
        return None
    distance = np.linalg.norm(xyz[in_front] - c2w[:3, 3], axis=1)
    near = np.percentile(depth[in_front], NEAR_FAR_PERCENTILES[0]) * (1 - NEAR_FAR_MARGIN)
    far = np.percentile(distance, NEAR_FAR_PERCENTILES[1]) * (1 + NEAR_FAR_MARGIN)
    return float(near), float(far)



def near_far_from_box(c2w: np.ndarray, box: np.ndarray) -> tuple[float, float]:
    """Near: the camera's distance to the box (a small value when it is inside); far: its farthest corner."""
    origin = c2w[:3, 3]
    outside = np.maximum(np.maximum(box[0] - origin, origin - box[1]), 0.0)
    corners = np.array([[box[i][0], box[j][1], box[l][2]] for i in (0, 1) for j in (0, 1) for l in (0, 1)])
    far = np.linalg.norm(corners - origin, axis=1).max()
    near = max(float(np.linalg.norm(outside)), 0.01 * far)
    return near, float(far)



def forward_depth_guess(cams: Cameras) -> tuple[float, float, str]:
    """Depth range of a forward capture without points: LLFF bounds when the frames carry them, otherwise
    a guess from the spread of the cameras (scenes are usually several baselines away)."""
    if cams.bounds is not None:
        return float(cams.bounds[:, 0].min()), float(np.percentile(cams.bounds[:, 1], 90)), "llff bounds"
    baseline = float(np.linalg.norm(np.ptp(cams.origins, axis=0))) or 1.0
    return 2.0 * baseline, 20.0 * baseline, "guess: 2 to 20 camera baselines in front of the cameras"



def forward_depths(xyz_world: np.ndarray | None, reference: np.ndarray, cams: Cameras, scale: float,
                    box: np.ndarray) -> dict:
    """NDC's near plane and the far depth, along the reference camera's axis (normalised units). All points
    count, not only the foreground: the floor just in front of the cameras, seen by few of them, is what
    sets the near plane."""
    if xyz_world is not None:
        depth = -((xyz_world - reference[:3, 3]) @ reference[:3, 2])
        depth = depth[depth > 0]
        if len(depth) >= MIN_POINTS:
            return {"near": float(np.percentile(depth, NEAR_FAR_PERCENTILES[0]) * (1 - NEAR_FAR_MARGIN)),
                    "far": float(np.percentile(depth, NEAR_FAR_PERCENTILES[1]) * (1 + NEAR_FAR_MARGIN)),
                    "from": "sparse points"}
    if cams.bounds is not None:
        return {"near": float(cams.bounds[:, 0].min() * scale * (1 - NEAR_FAR_MARGIN)),
                "far": float(cams.bounds[:, 1].max() * scale * (1 + NEAR_FAR_MARGIN)), "from": "llff bounds"}
    near, far = near_far_from_box(reference, box)
    return {"near": near, "far": far, "from": "foreground box"}
