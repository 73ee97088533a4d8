"""A video whose frames SfM refuses, read again: frames twice as close and at full size, to pose; and the model of
those full-size frames scaled to the size ingest keeps (stages/poses.py)."""
from __future__ import annotations

from pathlib import Path

import pycolmap

from stages.common.media import write_png
from stages.capture.flight_log import locate_frames
from stages.capture.panorama import split_frame, view_focal, view_name, view_side
from stages.capture.photos import fit_max_side
from stages.capture.video import video_frames


def denser_frames(scene: Path, clip: dict, records: list[dict], scratch: Path,
                  report) -> tuple[Path, list[dict], Path, list[dict], dict]:
    """The clip read again with frames twice as close (and up to twice as many a second) and at full size, where a clip
    whose frames do not hold together often does: neighbours overlap more, and a downscaled frame's finer texture is
    back for SfM. Two folders laid out as ingest's: the frames at full size (to pose) and at the ingested size (the
    output), with their records (each frame's place where the clip's flight log gives it); a 360 clip's frames cut
    into their views."""
    side = max(records[0]["width"], records[0]["height"])
    frames, denser = video_frames(scene, 0, clip["motion"] / 2, 2 * clip["max_per_second"], report,
                                  crop_bars=clip.get("crop_bars", True), max_frames=2 * clip.get("max_frames", 0),
                                  paint_overlays=clip.get("paint_overlays", True))
    if clip.get("panorama"):  # a 360 clip's frames, cut into their views at the frames' own resolution
        frames = [(view_name(name, turn), view, {"panorama": {"frame": name, **turn}}) for name, rgb in frames
                  for turn, view in split_frame(rgb, view_side(rgb.shape[1], 0), clip.get("poles", "none"))]
    else:
        frames = [(name, rgb, {}) for name, rgb in frames]
    full, ingested = scratch / "denser_full", scratch / "denser"
    full_records, ingested_records = [], []
    for name, rgb, view in frames:
        for folder, image, kept in ((full, rgb, full_records), (ingested, fit_max_side(rgb, side), ingested_records)):
            (folder / "images").mkdir(parents=True, exist_ok=True)
            write_png(folder / "images" / f"{name}.png", image)
            kept.append({"name": name, "file": f"images/{name}.png", "source": scene.name,
                         "width": image.shape[1], "height": image.shape[0], "mask": None,
                         **({**view, "focal": view_focal(image.shape[1])} if view else {})})
    if not clip.get("panorama"):  # where the drone was for each, where a flight log beside the clip says
        for kept in (full_records, ingested_records):
            locate_frames(kept, scene, denser["fps"])
    return full, full_records, ingested, ingested_records, denser


def rescale_model(reconstruction: pycolmap.Reconstruction, width: int, height: int) -> None:
    """A model of full-size frames made the model of the same frames at width x height: its cameras and every
    observation scaled (COLMAP's pixel coordinates start at the image's corner, so a scale keeps pixel centres)."""
    for camera in reconstruction.cameras.values():
        sx, sy = width / camera.width, height / camera.height
        camera.rescale(new_width=width, new_height=height)
        for image in reconstruction.images.values():
            if image.camera_id == camera.camera_id:
                for point in image.points2D:
                    point.xy = point.xy * (sx, sy)
    reconstruction.update_point_3d_errors()
