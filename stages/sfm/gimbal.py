"""Which way is up in an SfM model of a drone's photos. DJI's photos carry their gimbal's pitch in XMP
(drone-dji:GimbalPitchDegree: 0 level, -90 straight down; the gimbal keeps the horizon level), which puts the
world's up in each camera's axes (OpenCV's: x right, y down, z forward) at (0, -cos pitch, sin pitch); the model's
rotations carry it into the model's frame. A survey's cameras all look down along gravity, where the cameras alone
cannot tell up (stages/framing/orientation.py), so this is the up normalize takes where the photos agree on it."""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pycolmap

PITCH = re.compile(rb'GimbalPitchDegree\s*(?:=\s*"|>)\s*([+-]?\d+(?:\.\d*)?)')
# Bytes of a photo read for its XMP packet, which cameras write near the start.
HEAD_BYTES = 1 << 17
# The share of the model's photos that must carry a pitch, and how far (median, degrees) their ups may stray from
# their mean: past either, the cameras decide.
MIN_SHARE = 0.5
MAX_SPREAD_DEG = 5.0


def pitch(photo: Path) -> float | None:
    """A photo's gimbal pitch in degrees, from its XMP; None without one."""
    try:
        with open(photo, "rb") as f:
            found = PITCH.search(f.read(HEAD_BYTES))
    except OSError:
        return None
    value = float(found.group(1)) if found else math.nan
    return value if -90.5 <= value <= 90.5 else None


def gravity(reconstruction: pycolmap.Reconstruction, pitches: dict[str, float]) -> tuple[np.ndarray | None, dict]:
    """The world's up in the model's frame from the pitches of its images (by image name), and what was found."""
    ups = []
    for image in reconstruction.images.values():
        if image.has_pose and image.name in pitches:
            angle = math.radians(pitches[image.name])
            ups.append(image.cam_from_world().rotation.matrix().T @ [0.0, -math.cos(angle), math.sin(angle)])
    posed = sum(image.has_pose for image in reconstruction.images.values())
    found = {"photos": len(ups), "of": posed}
    if not ups or len(ups) < MIN_SHARE * posed:
        return None, found
    mean = np.mean(ups, axis=0)
    mean /= np.linalg.norm(mean)
    spread = float(np.degrees(np.median(np.arccos(np.clip(np.asarray(ups) @ mean, -1.0, 1.0)))))
    found["spread_deg"] = round(spread, 2)
    return (mean if spread <= MAX_SPREAD_DEG else None), found
