"""360-degree captures: equirectangular frames (a 360 camera's video, or its photos) told apart from ordinary ones and
split into pinhole views around the horizon, which SfM poses and the fit trains on as any photos.

An equirectangular frame maps longitude to its columns (-180 to 180 degrees, the camera's forward at the middle) and
latitude to its rows (+90 at the top). SfM's cameras are pinholes: trained as it is, a 360 frame is a photo whose
straight lines curve, and no focal length poses it. Each frame is cut into PANORAMA_VIEWS square views of
VIEW_FOV_DEG, at yaws evenly spaced around the horizon, neighbours overlapping by half, and a view straight up (the
ceiling or sky) and, where asked, one straight down (the floor or ground: ingest.equirect_poles), which with them
cover the whole sphere; one view's pixel is sampled from the frame's by bilinear interpolation across the seam. SfM
poses the views around the horizon (a ceiling's or the sky's plain view would find few matches) and those at the
poles take their frame's pose (stages/sfm/pole_views.py).

A frame is read as equirectangular where the file says so (a 360 camera's XMP `ProjectionType`, a video's spherical
metadata) and its sides are 2:1, or, without that, where the pixels show it: sides 2:1, the left and right edges
continuous (one meridian seen twice), and a pole row that varies no more along its length than a few pixels do
(each pole is one point drawn across the whole width), the edges not plain.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import cv2
import numpy as np

from stages.capture.photos import load_photo, upright_size

PANORAMA_VIEWS = 8
# The pitches of the views at the poles, and the names they end in.
POLES = {-90.0: "down", 90.0: "up"}
# What ingest's summary adds for each choice of views at the poles (ingest.equirect_poles).
POLE_WORDS = {"up": " and straight up", "both": " and straight down and up", "none": ""}
# A 360 frame's views stand in for this many of a video's frames: ingest.video_frames, video_max_frames and
# video_min_frames ask this many times fewer 360 frames.
FRAME_SHARE = 4
VIEW_FOV_DEG = 90.0
# Sides within this share of 2:1.
ASPECT_TOLERANCE = 0.01
# The seam: the mean difference across it at most this many times the median difference between neighbouring
# columns; the ends of a photo 2:1 wide differ by 5-40 times as much. A pole row's change along its length: at most
# this share of the median change along the middle rows.
SEAM_RATIO = 3.0
POLE_RATIO = 0.35
# The edge columns' change along their length, at least this share of the median change between columns.
EDGE_TEXTURE = 0.5
# Bytes read from each end of a file for its metadata (a video's moov box, a photo's XMP packet).
METADATA_BYTES = 4 << 20
METADATA_MARKS = (b"equirectangular", b"GSpherical:Spherical>true")
# Photos of a folder looked at for 360 pixels.
DETECTION_SAMPLES = 8


def is_two_to_one(width: int, height: int) -> bool:
    return height > 0 and abs(width / height - 2.0) <= 2.0 * ASPECT_TOLERANCE


def says_equirect(path: Path) -> bool:
    """Whether the file's metadata marks it as a 360 picture: XMP's GPano ProjectionType equirectangular (photos),
    Google's spherical video metadata (XMP in a uuid box, or the sv3d box of Spherical Video V2 with its equi
    projection box: four bytes alone would turn up by chance in one file of a few hundred)."""
    try:
        with open(path, "rb") as f:
            head = f.read(METADATA_BYTES)
            f.seek(0, 2)
            f.seek(max(len(head), f.tell() - METADATA_BYTES))
            tail = f.read()
    except OSError:  # a file that cannot be read is named where it is loaded
        return False
    return any(mark in head or mark in tail for mark in METADATA_MARKS) or any(
        re.search(rb"sv3d.{0,200}equi", block, re.DOTALL) for block in (head, tail))


def looks_equirect(greys: list[np.ndarray]) -> bool:
    """Whether grey frames of one capture are equirectangular by their pixels: 2:1, their left and right edges
    continuous, and a pole row smooth along its length, in most of them."""
    votes = []
    for grey in greys:
        h, w = grey.shape[:2]
        if not is_two_to_one(w, h) or h < 16:
            return False
        g = grey.astype(np.float32)
        neighbours = np.abs(np.diff(g, axis=1)).mean(axis=0)
        typical = float(np.median(neighbours))
        if typical < 0.5:  # a flat frame (dark, a wall) shows nothing either way
            continue
        seam = float(np.abs(g[:, 0] - g[:, -1]).mean())
        # Edges that meet say so only where they hold something to meet: a plain backdrop on both sides would too.
        textured = min(float(np.abs(np.diff(g[:, side])).mean()) for side in (0, -1)) >= EDGE_TEXTURE * typical
        along = [float(np.abs(np.diff(g[row])).mean()) for row in (0, h - 1)]
        middle = float(np.median(np.abs(np.diff(g[h // 4: 3 * h // 4], axis=1))))
        pole = min(along) <= POLE_RATIO * max(middle, typical)
        votes.append(seam <= SEAM_RATIO * typical and textured and pole)
    return bool(votes) and sum(votes) > len(votes) / 2


def frame_directions(width: int, du: float = 0.5, dv: float = 0.5) -> np.ndarray:
    """[width/2, width, 3] unit directions, in the camera's axes (the project's convention), of an equirectangular
    frame's pixels sampled at (du, dv) within each pixel: the inverse of `view_maps`' longitude and latitude."""
    height = width // 2
    longitude = ((np.arange(width) + du) / width - 0.5) * 2 * math.pi
    latitude = (0.5 - (np.arange(height) + dv) / height) * math.pi
    lon, lat = np.meshgrid(longitude, latitude)
    return np.stack([np.sin(lon) * np.cos(lat), np.sin(lat), -np.cos(lon) * np.cos(lat)], -1)


def view_yaws(views: int = PANORAMA_VIEWS) -> list[float]:
    """The views' yaws in degrees, counter-clockwise seen from above, 0 the frame's middle (its forward)."""
    return [360.0 * k / views for k in range(views)]


def view_side(frame_width: int, max_side: int) -> int:
    """A view's side in pixels: the frame's own resolution at the view's centre (its width over pi for a 90-degree
    view), at most `max_side` (0: no limit)."""
    native = round(2 * math.tan(math.radians(VIEW_FOV_DEG) / 2) * frame_width / (2 * math.pi))
    return max(16, min(native, max_side) if max_side else native)


def view_focal(side: int) -> float:
    """The pinhole focal length in pixels of a square view of VIEW_FOV_DEG."""
    return side / 2 / math.tan(math.radians(VIEW_FOV_DEG) / 2)


def view_maps(frame_shape: tuple[int, int], side: int, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap's maps from a view (square, `side` pixels, turned by `rotation` from the frame's forward view:
    `view_rotation`) into an equirectangular frame of (height, width) pixels. The view is a pinhole in the project's
    convention (x right, y up, looking down -z)."""
    h, w = frame_shape
    f = view_focal(side)
    centre = (np.arange(side) + 0.5 - side / 2) / f
    x, y = np.meshgrid(centre, -centre)
    tx, ty, tz = np.einsum("ij,jhw->ihw", rotation, np.stack([x, y, -np.ones_like(x)]))
    longitude = np.arctan2(tx, -tz)
    latitude = np.arctan2(ty, np.hypot(tx, tz))
    u = (longitude / (2 * math.pi) + 0.5) * w - 0.5
    v = (0.5 - latitude / math.pi) * h - 0.5
    return u.astype(np.float32), v.astype(np.float32)


def frame_views(poles: str = "up") -> list[dict[str, float]]:
    """The views cut from each frame, as {"yaw", "pitch"} in degrees: PANORAMA_VIEWS around the horizon, then (with
    `poles`: up, both or none) straight down and straight up."""
    around = [{"yaw": yaw, "pitch": 0.0} for yaw in view_yaws()]
    pitches = {"up": (90.0,), "both": (-90.0, 90.0), "none": ()}[poles]
    return around + [{"yaw": 0.0, "pitch": pitch} for pitch in pitches]


def view_name(frame: str, view: dict[str, float]) -> str:
    """A view's image name: its frame's and its yaw in degrees, or the pole it looks at."""
    pitch = view.get("pitch", 0.0)
    return f"{frame}_{POLES[pitch]}" if pitch else f"{frame}_{view['yaw']:03.0f}"


def at_pole(record: dict) -> bool:
    """Whether an ingested image is a 360 frame's view straight up or down."""
    return bool(record.get("panorama", {}).get("pitch", 0.0))


def split_frame(rgb: np.ndarray, side: int, poles: str = "up") -> list[tuple[dict[str, float], np.ndarray]]:
    """An equirectangular frame's pinhole views (`frame_views`): (the view's yaw and pitch, RGB of side x side)."""
    out = []
    for view in frame_views(poles):
        u, v = view_maps(rgb.shape[:2], side, view_rotation(view["yaw"], view["pitch"]))
        out.append((view, cv2.remap(rgb, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)))
    return out


def view_rotation(yaw_deg: float, pitch_deg: float = 0.0) -> np.ndarray:
    """3x3 rotation of a view at `yaw_deg` and `pitch_deg` relative to the frame's forward view (camera axes, the
    project's convention): turned counter-clockwise about +y seen from above (towards -x, the left), then tipped up
    about its own x (a pitch of -90 looks straight down, its up the frame's way ahead)."""
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    c, s = math.cos(yaw), math.sin(yaw)
    turned = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    c, s = math.cos(pitch), math.sin(pitch)
    return turned @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def frame_side(max_side: int) -> int:
    """The width to read equirectangular frames at for views of at most `max_side` (0: full size): the views then
    sample the frame at their own resolution (`view_side`)."""
    return 2 * math.ceil(max_side * math.pi / math.tan(math.radians(VIEW_FOV_DEG) / 2) / 2) if max_side else 0


def photos_equirect(paths: list[Path]) -> bool:
    """Whether a folder's 2:1 photos are equirectangular (a 360 camera's): marked so in their metadata, or by the
    pixels of up to DETECTION_SAMPLES of them spread over the capture."""
    sizes = {path: size for path in paths if (size := upright_size(path)) is not None}
    wide = [p for p, size in sizes.items() if is_two_to_one(*size)]
    if not wide:
        return False
    sampled = [wide[i] for i in np.unique(np.linspace(0, len(wide) - 1, DETECTION_SAMPLES).round().astype(int))]
    if any(says_equirect(p) for p in sampled):
        return True
    greys = []
    for path in sampled:
        try:
            greys.append(cv2.cvtColor(load_photo(path)[0], cv2.COLOR_RGB2GRAY))
        except Exception:  # an unreadable photo is named where it is loaded
            continue
    return looks_equirect(greys)
