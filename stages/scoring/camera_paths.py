"""Novel-view camera paths in the normalised world: an orbit around the foreground, an LLFF-style spiral, an
arc through the training cameras, and the choice among them that suits a capture (default_path)."""
from __future__ import annotations

import math

import numpy as np

from plenoxels.core.cameras import Intrinsics, look_at

# Spiral path for forward scenes: LLFF's focus weighting and its margins on the depth bounds.
SPIRAL_FOCUS_WEIGHT = 0.75
SPIRAL_TURNS = 2


def median_intrinsics(frames: list[dict], side: int) -> Intrinsics:
    """The median-focal training camera, scaled so its longest side is `side` pixels."""
    k = Intrinsics.from_frame(sorted(frames, key=lambda f: f["fl_x"])[len(frames) // 2])
    return k.scaled(side / max(k.w, k.h))


def orbit_path(scene: dict, frames: list[dict], n: int) -> list[np.ndarray]:
    """Cameras on a circle around the foreground centre (z up) at the training cameras' median distance
    and elevation, looking at the centre."""
    lo, hi = np.asarray(scene["foreground"]["min"]), np.asarray(scene["foreground"]["max"])
    centre = (lo + hi) / 2
    offsets = np.array([np.asarray(f["transform_matrix"])[:3, 3] for f in frames]) - centre
    radius = float(np.median(np.linalg.norm(offsets, axis=1)))
    elevation = float(np.median(np.arcsin(np.clip(offsets[:, 2] / np.linalg.norm(offsets, axis=1), -1, 1))))
    start = math.atan2(offsets[0, 1], offsets[0, 0])
    path = []
    for i in range(n):
        azimuth = start + 2 * math.pi * i / n
        eye = centre + radius * np.array([math.cos(elevation) * math.cos(azimuth),
                                          math.cos(elevation) * math.sin(azimuth), math.sin(elevation)])
        path.append(look_at(eye, centre))
    return path


def spiral_path(scene: dict, frames: list[dict], n: int) -> list[np.ndarray]:
    """LLFF-style spiral: around the reference (average) camera, within the spread of the training
    cameras, every view looking at a focus point in front of the reference camera."""
    forward_block = scene.get("forward") or {}
    poses = np.array([np.asarray(f["transform_matrix"], dtype=np.float64) for f in frames])
    if "reference_c2w" in forward_block:
        reference = np.asarray(forward_block["reference_c2w"], dtype=np.float64)
    else:
        reference = poses[0].copy()
        reference[:3, 3] = poses[:, :3, 3].mean(axis=0)
    right, up, back, centre = reference[:3, 0], reference[:3, 1], reference[:3, 2], reference[:3, 3]
    local = (poses[:, :3, 3] - centre) @ np.stack([right, up, back], axis=1)
    spread = np.percentile(np.abs(local), 90, axis=0)
    near = min(f["near"] for f in frames) * 0.9
    far = max(f["far"] for f in frames) * 5.0
    focus = 1.0 / ((1 - SPIRAL_FOCUS_WEIGHT) / near + SPIRAL_FOCUS_WEIGHT / far)
    target = centre - back * focus
    path = []
    for i in range(n):
        theta = 2 * math.pi * SPIRAL_TURNS * i / n
        offset = spread * np.array([math.cos(theta), -math.sin(theta), -math.sin(theta / SPIRAL_TURNS)])
        eye = centre + offset @ np.stack([right, up, back])
        path.append(look_at(eye, target, up=tuple(up)))
    return path


# ------------------------------------------------------------------------------------------------
# The path that suits the capture

# Cameras orbit the scene when no gap between their azimuths around the foreground (z up) is wider than this.
ORBIT_MAX_GAP_DEG = 90.0
# An arc path smooths the cameras' positions, in order along the arc, with a Gaussian of this share of their count.
ARC_SMOOTHING = 0.15


def _centre(scene: dict) -> np.ndarray:
    fg = scene.get("foreground") or {}
    return (np.asarray(fg.get("min", (-1.0, -1.0, -1.0))) + np.asarray(fg.get("max", (1.0, 1.0, 1.0)))) / 2


def _azimuths(scene: dict, frames: list[dict]) -> np.ndarray:
    centres = np.array([np.asarray(f["transform_matrix"], dtype=np.float64)[:3, 3] for f in frames])
    offsets = centres - _centre(scene)
    return np.arctan2(offsets[:, 1], offsets[:, 0])


def largest_azimuth_gap_deg(scene: dict, frames: list[dict]) -> float:
    """The widest empty sector, in degrees, between the cameras' azimuths around the foreground centre."""
    az = np.sort(_azimuths(scene, frames))
    gaps = np.diff(np.append(az, az[0] + 2 * math.pi))
    return float(np.degrees(gaps.max()))


def arc_path(scene: dict, frames: list[dict], n: int) -> list[np.ndarray]:
    """Through and near the training cameras: their centres in order of azimuth around the foreground
    (starting after the widest empty sector), smoothed, then travelled out and back with eased ends so the
    video loops; every view looks at the foreground centre."""
    centre = _centre(scene)
    positions = np.array([np.asarray(f["transform_matrix"], dtype=np.float64)[:3, 3] for f in frames])
    az = _azimuths(scene, frames)
    order = np.argsort(az)
    gaps = np.diff(np.append(az[order], az[order][0] + 2 * math.pi))
    order = np.roll(order, -(int(np.argmax(gaps)) + 1))
    along = positions[order]
    sigma = max(1.0, ARC_SMOOTHING * len(along))
    offsets = np.arange(-math.ceil(3 * sigma), math.ceil(3 * sigma) + 1)
    kernel = np.exp(-0.5 * (offsets / sigma) ** 2)
    padded = np.concatenate([np.repeat(along[:1], len(offsets) // 2, axis=0), along,
                             np.repeat(along[-1:], len(offsets) // 2, axis=0)])
    smooth = np.stack([np.convolve(padded[:, a], kernel / kernel.sum(), mode="valid") for a in range(3)], axis=1)
    arc_length = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(smooth, axis=0), axis=1))])
    total = arc_length[-1] if arc_length[-1] > 0 else 1.0
    path = []
    for i in range(n):
        s = (1 - math.cos(2 * math.pi * i / n)) / 2 * total
        eye = np.array([np.interp(s, arc_length, smooth[:, a]) for a in range(3)])
        path.append(look_at(eye, centre))
    return path


def default_path(scene: dict, frames: list[dict], n: int, ndc: bool = False) -> tuple[str, list[np.ndarray]]:
    """(kind, cameras) of the path that suits the capture: a spiral for forward scenes (or an NDC fit), an
    orbit where the training cameras surround the foreground, else an arc through and near them (a facade
    shot from in front gets no views from behind the wall)."""
    if ndc or scene.get("type") == "forward":
        return "spiral", spiral_path(scene, frames, n)
    if largest_azimuth_gap_deg(scene, frames) <= ORBIT_MAX_GAP_DEG:
        return "orbit", orbit_path(scene, frames, n)
    return "arc", arc_path(scene, frames, n)
