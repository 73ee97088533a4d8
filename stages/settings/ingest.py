"""The ingest stage as the pipeline plans it: its name, the stages it reads, its version, its settings and the
fingerprint of the photos it reads (its work: stages/ingest.py)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from plenoxels.core.errors import require
from stages.capture.flight_log import flight_log
from stages.capture.masks import mask_folder
from stages.capture.photos import photo_folder, scene_files
from stages.sfm.pose_files import candidates

NAME = "ingest"
DEPENDS: tuple[str, ...] = ()
VERSION = 1


@dataclass
class Settings:
    max_side: int = 960
    """Downscale so the longest side is at most this many pixels; 0 keeps the full size."""
    drop_blurry_fraction: float = 0.0
    """Share of the blurriest images to drop, in [0, 1); 0 keeps all."""
    video_motion: float = 0.05
    """From a video, keep a frame each time the view has moved this share of the frame's diagonal (the sharpest of
    the frames near that point), so neighbouring frames overlap."""
    video_fps: float = 10.0
    """From a video, keep at most this many frames per second."""
    video_frames: int = 120
    """From a video, aim for about this many frames: a clip whose motion gives fewer at video_motion is read again
    with frames closer together (down to a quarter of video_motion, at most video_fps a second). More views of each
    point make new views sharper: ball's 16 s video, on the same held-out views, 26.83 dB from 109 training frames,
    25.01 from 55 (bench/README.md, "Real captures"). 0: keep video_motion whatever the clip gives."""
    video_max_frames: int = 300
    """From a video, keep at most this many frames: a longer clip keeps every second (third, ...) frame of those its
    motion gives, so they span the whole clip; memory holds no more, and SfM's time grows with each frame
    (0: no limit). A folder of more photos than this that are a video's frames saved one by one (neighbours closer
    than half of video_motion) is read as the video would be."""
    video_min_frames: int = 30
    """From a video, fewer frames than this, read as close together as video_frames allows, are too few for a good
    fit, which the summary says (0: never say so)."""
    min_images: int = 3
    """Fail when fewer usable images than this remain (at least 3)."""
    holdout_split: str = "val"
    """A dataset folder that names its splits (NeRF synthetic's train/, val/, test/; NeRF++'s train/, validation/,
    test/; NSVF's photos named 0_, 1_, 2_): the split held out for scoring (val, test or none)."""
    masks: bool = True
    """Read the object's masks from a masks/ (or mask/) folder beside the photos, one per photo by name: poses come
    from features inside them and the fit models the object alone. Off: ignore the folder (alpha channels still count)."""
    mask_threshold: int | Literal["auto"] = "auto"
    """A mask's value above this (0-254) marks the object; auto: above 0, or above 127 in JPEG and WebP masks."""
    paint_overlays: bool = True
    """Paint over a still overlay on a video's picture (a watermark, a caption, a timestamp an app burned in: crisp
    pixels that stay put while the view moves) in every frame kept, from around it: trained as it is, it is a thing
    fixed in front of every camera that SfM takes for a still background behind a turning object."""
    equirect: Literal["auto", "yes", "no"] = "auto"
    """A 360 camera's equirectangular video or photos (2:1, the whole sphere) are cut into 8 pinhole views around the
    horizon, which SfM poses as one camera of known focal length (and the views at the poles equirect_poles names,
    which take their frame's pose); auto: where the file's metadata or the pixels say a 2:1 picture is one (its left
    and right edges meet, its top or bottom row is one point drawn wide), or, for photos with their poses, where a
    transforms.json says camera_model EQUIRECTANGULAR (each view takes its frame's pose)."""
    equirect_poles: Literal["up", "both", "none"] = "up"
    """Which of each 360 frame's views straight up and straight down are cut beside those around the horizon, so the
    fit learns more of the sphere than 45 degrees either side of it: up (the ceiling or sky, which the views around
    see least), both (the floor or ground too: for a camera on a tripod, whose still legs are painted over, or a
    drone's), or none. The view down of a camera held on a stick shows the hand and the person who hold it, which
    move with the camera and would be fitted as a thing under every place it went."""
    crop_bars: bool = True
    """Crop black bars along the frame's edges (a portrait clip in a landscape frame, a letterbox), dark in every
    frame of a video, or in every photo of the common size where no pose file is beside the photos (those keep the
    whole frames their cameras describe; a pose file poses.path names elsewhere has its cameras moved with the crop):
    trained, they are a black wall in front of every camera."""

    def check(self) -> None:
        require(self.max_side == 0 or self.max_side >= 32, "ingest.max_side must be 0 (full size) or at least 32")
        require(0.0 <= self.drop_blurry_fraction < 1.0, "ingest.drop_blurry_fraction must be in [0, 1)")
        require(self.video_fps > 0, "ingest.video_fps must be positive")
        require(0 < self.video_motion < 1, "ingest.video_motion must be in (0, 1): a share of the frame's diagonal")
        require(self.video_frames >= 0, "ingest.video_frames must be >= 0 (0: keep ingest.video_motion)")
        require(self.video_min_frames >= 0, "ingest.video_min_frames must be >= 0 (0: off)")
        require(self.video_max_frames == 0 or self.video_max_frames >= max(3, self.video_min_frames),
                "ingest.video_max_frames must be 0 (no limit) or at least ingest.video_min_frames (and 3)")
        require(self.min_images >= 3, "ingest.min_images must be at least 3 (fewer cannot be posed)")
        require(self.holdout_split in ("val", "test", "none"), "ingest.holdout_split must be val, test or none")
        require(self.mask_threshold == "auto" or 0 <= int(self.mask_threshold) <= 254,
                "ingest.mask_threshold must be auto or a value from 0 to 254")


def fingerprint(scene: Path) -> list:
    folder = photo_folder(scene)
    log = flight_log(scene) if scene.is_file() else None  # where a drone was as it filmed the clip
    listed = [[str(p.relative_to(folder)), p.stat().st_size, p.stat().st_mtime_ns]
              for p in scene_files(scene) + ([log] if log else [])]
    masks = mask_folder(folder) if not scene.is_file() else None
    if masks is not None:
        listed += [[str(p.relative_to(masks.parent)), p.stat().st_size, p.stat().st_mtime_ns]
                   for p in sorted(masks.iterdir()) if p.is_file()]
    # Photos are cropped of black bars only where no pose file describes their whole frames.
    return listed + sorted(kind for kind, files in candidates(scene).items() if files)
