"""Which way is up and where the cameras point: the up axis from the cameras, the point their axes meet, the spread
of their viewing directions, and the rotation that makes the frame z up."""
from __future__ import annotations

import numpy as np

from stages.framing.sightings import Cameras


# Up from the camera x axes needs them to spread: the middle eigenvalue (per camera) must exceed this.
RIGHT_AXES_MIN_SPREAD = 0.01
# Below this length the mean of the cameras' unit up axes says they turn every way round the way they look.
UPS_AGREE_MIN = 0.3



def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)



def _trimmed(vectors: np.ndarray, residual) -> np.ndarray:
    """Drops the vectors whose residual is far above the typical one (a few tilted or rotated shots)."""
    r = residual(vectors)
    keep = r <= max(3.0 * np.median(r), 0.05)
    return vectors[keep] if keep.sum() >= 2 else vectors



def camera_up(c2w: np.ndarray, inward: bool) -> tuple[np.ndarray, str]:
    """World up from the cameras, and which rule found it.

    People keep the horizon level far more than they keep the pitch fixed, so for inward captures up is
    the direction most nearly perpendicular to every camera's x (right) axis; that needs the right axes
    to spread, which an orbit gives. Forward captures (and narrow arcs) use the mean camera up axis.
    Either way the sign follows the mean camera up axis. Where the cameras' up axes turn every way round the way they
    look (a survey flown back and forth, a table shot from above: a camera held over what it looks down at, which a
    level camera never is), up is against that way, and the sign follows it.
    """
    rights = _unit(c2w[:, :3, 0])
    ups = _unit(c2w[:, :3, 1])
    looking_down = np.linalg.norm(ups.mean(axis=0)) < UPS_AGREE_MIN
    mean_up = _unit(c2w[:, :3, 2].mean(axis=0) if looking_down else ups.mean(axis=0))
    if inward:
        def smallest_axis(v):
            values, vectors = np.linalg.eigh(v.T @ v / len(v))
            return values, vectors[:, 0]
        values, axis = smallest_axis(rights)
        if values[1] > RIGHT_AXES_MIN_SPREAD:
            kept = _trimmed(rights, lambda v: np.abs(v @ axis))
            axis = smallest_axis(kept)[1]
            return (axis if axis @ mean_up >= 0 else -axis), "perpendicular to the cameras' right axes"
    if looking_down:
        return mean_up, "against the way the cameras look (their up axes turn every way round it: looking down)"
    kept = _trimmed(ups, lambda v: 1.0 - v @ mean_up)
    return _unit(kept.mean(axis=0)), "mean of the cameras' up axes"



def closest_point_of_axes(origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, float]:
    """The point nearest to all optical axes (least squares, down-weighting axes that pass far from it,
    so a few shots aimed elsewhere do not pull it), and how well the axes pin it down: the smallest
    eigenvalue of the normal matrix per camera (0 when the axes are parallel)."""
    weights = np.ones(len(origins))
    point = origins.mean(axis=0)
    conditioning = 0.0
    for _ in range(5):
        projectors = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]
        a = np.einsum("n,nij->ij", weights, projectors)
        b = np.einsum("n,nij,nj->i", weights, projectors, origins)
        conditioning = float(np.linalg.eigvalsh(a / weights.sum())[0])
        if conditioning < 1e-6:
            break
        point = np.linalg.solve(a, b)
        offsets = point - origins
        miss = np.linalg.norm(offsets - (offsets * dirs).sum(1, keepdims=True) * dirs, axis=1)
        weights = 1.0 / np.maximum(miss, np.median(miss) + 1e-12)
    return point, conditioning



def view_cone_deg(dirs: np.ndarray) -> float:
    """90th percentile of the angles between the viewing directions and their mean direction."""
    mean = dirs.mean(axis=0)
    if np.linalg.norm(mean) < 1e-9:
        return 180.0
    cos = np.clip(dirs @ _unit(mean), -1.0, 1.0)
    return float(np.degrees(np.percentile(np.arccos(cos), 90)))



def rotation_to_z_up(up: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """Rotation (rows = new axes in input coordinates) taking `up` to +z and `heading`'s horizontal part to +y."""
    z = _unit(up)
    y = heading - (heading @ z) * z
    if np.linalg.norm(y) < 1e-6:  # heading straight up or down: any horizontal direction will do
        y = np.cross(z, [1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.cross(z, [0.0, 1.0, 0.0])
    y = _unit(y)
    return np.stack([np.cross(y, z), y, z])



def horizontal_heading(dirs: np.ndarray, up: np.ndarray, first: int) -> np.ndarray:
    """The mean viewing direction's horizontal part when the cameras agree on one; otherwise (a full orbit,
    where the mean is near zero and noisy) camera `first`'s, so the frame stays well defined."""
    flat = dirs - (dirs @ up)[:, None] * up
    mean = flat.mean(axis=0)
    if np.linalg.norm(mean) >= 0.5 * np.linalg.norm(flat, axis=1).mean():
        return mean
    return flat[first] if np.linalg.norm(flat[first]) > 1e-6 else dirs[first]



def reference_camera(cams: Cameras, dirs: np.ndarray, up: np.ndarray) -> np.ndarray:
    """The average pose: at the mean camera centre, looking along the mean viewing direction, level with `up`."""
    forward = _unit(dirs.mean(axis=0))
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-6:  # looking straight along up (a survey looking down): level with the first camera
        right = np.cross(forward, cams.c2w[0, :3, 1])
    right = _unit(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(right, forward), -forward, cams.origins.mean(axis=0)
    return c2w
