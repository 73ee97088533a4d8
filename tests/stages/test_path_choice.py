"""The default camera path suits the capture (stages/scoring/camera_paths.py default_path): an orbit where the
cameras ring the scene, a path through and near them where they do not (a facade shot from an arc must not
get views from behind its wall), a spiral for forward scenes."""
from __future__ import annotations

import math

import numpy as np
import pytest

from stages.scoring.camera_paths import default_path, largest_azimuth_gap_deg, orbit_path
from plenoxels.core.cameras import look_at

# A wall across x in the plane y = 0 (the foreground box is a thin slab), cameras in front of it (y < 0).
WALL = {"type": "object", "foreground": {"min": [-1.0, -0.1, -0.5], "max": [1.0, 0.1, 0.5]}}


def _frames(eyes, target=(0.0, 0.0, 0.0)) -> list[dict]:
    return [{"transform_matrix": look_at(eye, target).tolist()} for eye in eyes]


def _arc(n: int, radius: float, from_deg: float, to_deg: float, height: float = 0.3) -> list[tuple]:
    rng = np.random.default_rng(0)
    angles = np.radians(np.linspace(from_deg, to_deg, n))
    rng.shuffle(angles)  # the order of the frames must not matter
    return [(radius * math.cos(a), radius * math.sin(a), height + 0.05 * rng.normal()) for a in angles]


def test_a_full_ring_gets_an_orbit():
    scene = {"type": "object", "foreground": {"min": [-1] * 3, "max": [1] * 3}}
    frames = _frames(_arc(24, 3.0, 0, 345))
    assert largest_azimuth_gap_deg(scene, frames) == pytest.approx(15, abs=0.1)
    kind, path = default_path(scene, frames, 10)
    assert kind == "orbit" and len(path) == 10


def test_an_arc_in_front_of_a_wall_gets_a_path_near_its_cameras():
    eyes = _arc(15, 3.0, -150, -30)  # 120 degrees of arc, all at y < 0
    frames = _frames(eyes)
    kind, path = default_path(WALL, frames, 40)
    assert kind == "arc" and len(path) == 40
    cameras = np.array(eyes)
    spacing = 3.0 * math.radians(120 / 14)
    for c2w in path:
        eye = c2w[:3, 3]
        assert eye[1] < -1.0  # in front of the wall, never behind it
        assert np.min(np.linalg.norm(cameras - eye, axis=1)) < spacing  # near a training camera
        assert -c2w[:3, 2] @ (np.zeros(3) - eye) > 0  # looking at the wall
    # Smooth: consecutive views move by similar, small steps, and the path loops back to its start.
    steps = np.array([np.linalg.norm(b[:3, 3] - a[:3, 3]) for a, b in zip(path, path[1:] + path[:1])])
    assert steps.max() < 4 * np.median(steps) and steps.max() < 0.1 * 3.0 * math.radians(120) * 2
    # The plain orbit flies behind the wall: what the default avoids.
    assert max(c2w[1, 3] for c2w in orbit_path(WALL, frames, 40)) > 1.0


def test_forward_scenes_get_a_spiral():
    eyes = [(x, -3.0, z) for x in (-0.3, 0.0, 0.3) for z in (-0.2, 0.2)]
    frames = [{**f, "near": 1.0, "far": 6.0} for f in _frames(eyes, target=(0.0, 0.0, 0.0))]
    assert default_path({**WALL, "type": "forward"}, frames, 8)[0] == "spiral"
    assert default_path(WALL, frames, 8, ndc=True)[0] == "spiral"
