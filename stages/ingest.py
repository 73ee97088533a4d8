"""Ingest: a folder of photos (or a video) -> 8-bit RGB PNGs, upright, downscaled, scored for sharpness, with the
object's mask where the photos carry one (an alpha channel, or a masks/ or mask/ folder beside them: stages/capture/masks.py).

Writes ingest/images/<name>.png, ingest/masks/<name>.png (only for images with a mask, at the image's size) and
ingest/images.json listing every kept image with its original size, scale, sharpness and mask.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.common.media import write_png
from stages.common.json_files import write_json
from stages.capture.masks import mask_folder, match_masks, read_mask
from stages.capture.photos import (IMAGE_SUFFIXES, SIDECAR_SUFFIXES, VIDEO_SUFFIXES, colour_spread,
                                   colourless_among_colour, fit_max_side, is_split_dataset, load_photo, not_a_scene,
                                   not_read_why, photo_folder, photos_picture, repeated, scene_photos, sharpness,
                                   stored_orientation, thumbnail, twin_words, twins)
from stages.capture.panorama import (FRAME_SHARE, PANORAMA_VIEWS, POLE_WORDS, frame_side, is_two_to_one,
                                     looks_equirect, photos_equirect, says_equirect, split_frame, view_focal, view_name,
                                     view_side)
from stages.capture.flight_log import locate_frames
from stages.capture.video import clip_samples, sequence_step, video_frames
from stages.sfm import pose_files
from stages.common.text import short_list, size_words, text_name
from plenoxels.core.errors import UserError
from plenoxels.core.photo_colour import capture_key
from stages.settings.ingest import Settings
from stages.common.layout import IMAGES_JSON


def run(ctx) -> dict:
    s: Settings = ctx.settings
    images_dir = ctx.work / "images"
    masks_dir = ctx.work / "masks"
    images_dir.mkdir()
    records, unreadable, thumbnails = [], [], []
    clip = bars = sequence = None
    left: dict[Path, str] = {}  # files beside a photo of their name, not read
    clips: list[str] = []
    panoramas: list[tuple[int, int]] = []  # the 360 frames split, their sizes

    def keep_views(name: str, source: str, rgb: np.ndarray) -> None:
        """A 360 frame as its pinhole views, each named for its frame and yaw (or pole), with its known focal length."""
        panoramas.append((rgb.shape[1], rgb.shape[0]))
        for turn, view in split_frame(rgb, view_side(rgb.shape[1], s.max_side), s.equirect_poles):
            keep(view_name(name, turn), source, view, None, (view.shape[1], view.shape[0]),
                 panorama={"frame": name, **turn})

    def keep(name: str, source: str, rgb: np.ndarray, alpha: np.ndarray | None, original: tuple[int, int],
             split: str | None = None, mask_file: Path | None = None, photo_orientation: int = 1,
             picture: tuple[slice, slice] | None = None, panorama: dict | None = None) -> None:
        cutout = alpha is not None
        mask_from = "alpha" if cutout else None
        if mask_file is not None:
            given = read_mask(mask_file, original, s.mask_threshold, photo_orientation)
            alpha = given if alpha is None else np.minimum(alpha, given)
            mask_from = mask_file.relative_to(mask_file.parent.parent).as_posix()
        within, frame = None, original
        if picture is not None:  # within black bars: the photo is what the picture shows
            rgb = np.ascontiguousarray(rgb[picture])
            alpha = np.ascontiguousarray(alpha[picture]) if alpha is not None else None
            within = [picture[1].start, picture[0].start, rgb.shape[1], rgb.shape[0]]  # x, y, width, height
            original = (rgb.shape[1], rgb.shape[0])
        rgb = fit_max_side(rgb, s.max_side)
        record = {"name": name, "file": f"images/{name}.png", "source": source, "width": rgb.shape[1],
                  "height": rgb.shape[0], "original_width": original[0], "original_height": original[1],
                  "scale": rgb.shape[1] / original[0], "sharpness": round(sharpness(rgb), 3),
                  "colour_spread": colour_spread(rgb), "mask": None}
        if split:
            record["split"] = split
        if photo_orientation != 1:  # its pixels as stored are turned (EXIF): a pose file may describe them so
            record["orientation"] = photo_orientation
        if within:  # a pose file given elsewhere describes the whole frame
            record["bars_cropped"], record["frame_size"] = within, list(frame)
        if panorama:  # a 360 frame's view: a pinhole of known focal length, posed with the frame's other views
            record["panorama"], record["focal"] = panorama, view_focal(rgb.shape[1])
        write_png(images_dir / f"{name}.png", rgb)
        if alpha is not None:
            masks_dir.mkdir(exist_ok=True)
            write_png(masks_dir / f"{name}.png", fit_max_side(alpha, s.max_side))
            record["mask"], record["mask_from"] = f"masks/{name}.png", mask_from
            if cutout:  # what lies outside its mask is whatever the cut left there, not a backdrop
                record["cutout"] = True
        records.append(record)
        thumbnails.append(thumbnail(rgb))

    if ctx.scene.is_file():
        if ctx.scene.suffix.lower() not in VIDEO_SUFFIXES:
            raise UserError(not_a_scene(ctx.scene))
        samples = clip_samples(ctx.scene)
        panorama = s.equirect == "yes" or s.equirect == "auto" and bool(samples) and (
            is_two_to_one(*samples[0].shape[::-1]) and says_equirect(ctx.scene) or looks_equirect(samples))
        if panorama and samples and not is_two_to_one(*samples[0].shape[::-1]):
            height, width = samples[0].shape
            raise UserError(f"ingest.equirect=yes, but {ctx.scene.name}'s frames are {width}x{height}, not the 2:1 of "
                            "an equirectangular 360 video; set ingest.equirect=auto or no")
        if panorama:  # each frame gives PANORAMA_VIEWS views: fewer frames, read large enough for the views
            frames, clip = video_frames(ctx.scene, frame_side(s.max_side), s.video_motion, s.video_fps, ctx.report,
                                        s.video_frames // FRAME_SHARE, False, s.video_max_frames // FRAME_SHARE,
                                        s.paint_overlays, samples)
            clip["panorama"], clip["poles"] = PANORAMA_VIEWS, s.equirect_poles
        else:
            frames, clip = video_frames(ctx.scene, s.max_side, s.video_motion, s.video_fps, ctx.report,
                                        s.video_frames, s.crop_bars, s.video_max_frames, s.paint_overlays, samples)
        for name, rgb in frames:
            if panorama:
                keep_views(name, ctx.scene.name, rgb)
            else:
                keep(name, ctx.scene.name, rgb, None, (rgb.shape[1], rgb.shape[0]))
        if not panorama and (flight := locate_frames(records, ctx.scene, clip["fps"])) is not None:
            clip["flight_log"] = flight  # where a drone was as it filmed, for SfM to hold its frames near
    else:
        folder = photo_folder(ctx.scene)
        candidates = scene_photos(ctx.scene, s.holdout_split)
        left = twins([p for p, _ in candidates])
        photos = [(p.relative_to(folder), split) for p, split in candidates
                  if p.suffix.lower() in IMAGE_SUFFIXES and p not in left]
        unreadable += [f"{p.name} ({not_read_why(p)})" for p, _ in candidates
                       if p.suffix.lower() not in IMAGE_SUFFIXES | VIDEO_SUFFIXES | SIDECAR_SUFFIXES]
        clips = [p.name for p, _ in candidates if p.suffix.lower() in VIDEO_SUFFIXES]
        if clips:
            ctx.report.warn(f"{len(clips)} video(s) beside the photos are not read: {short_list(clips)} (a phone's "
                            "Live Photo clips; a walk-around video is read where it is given alone, as the scene)")
        own_poses = is_split_dataset(ctx.scene) or any(pose_files.candidates(ctx.scene).values())
        if s.video_max_frames and len(photos) > s.video_max_frames and (
                not own_poses or pose_files.numbered_frames(ctx.scene)):
            ordered = sorted(photos, key=lambda photo: capture_key(photo[0].as_posix()))  # 9.jpg before 10.jpg
            step, apart = sequence_step([folder / p for p, _ in ordered], s.video_motion, s.video_max_frames,
                                        s.video_frames)
            if step > 1:  # a video's frames saved one by one: read as the video would be
                sequence = (len(photos), step, apart)
                photos = ordered[::step]
                ctx.report.warn(f"the {sequence[0]} photos are a video's frames saved one by one (neighbours "
                                f"{apart:.1%} of the view's diagonal apart): one in {step} is read, as the video would "
                                f"be (ingest.video_motion, ingest.video_max_frames)")
        # Split folders repeat file names (train/r_0.png, val/r_0.png): then every name carries its folder, and
        # its suffix too where only that tells two photos apart (p.jpg, p.png).
        names = [p.stem for p, _ in photos]
        for naming in (lambda p: p.with_suffix("").as_posix().replace("/", "_"),
                       lambda p: p.as_posix().replace("/", "_").replace(".", "_")):
            if len(set(names)) == len(names):
                break
            names = [naming(p) for p, _ in photos]
        name_of = {p: text_name(name) for (p, _), name in zip(photos, names)}
        beside = [p for p, kind in left.items() if kind == "mask"]  # masks kept beside their photos, where no folder
        masks_given = (mask_folder(folder) or (folder if beside else None)) if s.masks else None
        mask_of = match_masks([folder / p for p, _ in photos], masks_given, beside if masks_given == folder else None) \
            if masks_given is not None else {}
        if masks_given is not None and not mask_of:
            ctx.report.warn(f"{masks_given} holds no mask named like any photo, so it is not used")
        elif masks_given is not None:
            unmasked = [name_of[p] for p, _ in photos if folder / p not in mask_of]
            if unmasked:
                ctx.report.warn(f"{len(unmasked)} of {len(photos)} photos have no mask in {masks_given} (by name): "
                                f"{short_list(unmasked)}; they are posed from the whole photo and left out of the fit")
        # Photos with their own poses are read as those poses describe them: 360 frames where the pose file says so.
        panorama = s.equirect == "yes" or s.equirect == "auto" and (
            pose_files.poses_equirect(ctx.scene) if own_poses else photos_equirect([folder / p for p, _ in photos]))
        if s.crop_bars and not own_poses and not panorama:
            bars = photos_picture([folder / p for p, _ in photos])
        for relative, split in ctx.report.track(photos, desc="reading photos"):
            try:
                rgb, alpha = load_photo(folder / relative)
            except Exception as e:  # any decoder failure means the same thing to the user: this file is skipped
                unreadable.append(f"{relative.as_posix()} ({str(e).splitlines()[0][:60] or type(e).__name__})")
                continue
            size = (rgb.shape[1], rgb.shape[0])
            if panorama and is_two_to_one(*size):
                keep_views(name_of[relative], relative.as_posix(), rgb)
                continue
            mask_file = mask_of.get(folder / relative)
            picture = bars[1] if bars is not None and size == bars[0] else None
            keep(name_of[relative], relative.as_posix(), rgb, alpha, size, split, mask_file,
                 stored_orientation(folder / relative), picture)
    if unreadable:
        ctx.report.warn(f"skipped {len(unreadable)} file(s) that are not readable photos: {'; '.join(unreadable)}")

    def drop(record: dict) -> None:
        (ctx.work / record["file"]).unlink()
        if record["mask"]:
            (ctx.work / record["mask"]).unlink()

    # A published data set's own splits keep its protocol, copies or not.
    loose = [i for i, r in enumerate(records) if not r.get("split")]
    stems = [Path(records[i]["source"]).stem for i in loose]
    repeats = {records[loose[i]]["name"]: records[loose[kept]]["name"]
               for i, kept in repeated([thumbnails[i] for i in loose], stems).items()}
    if repeats:
        for record in records:
            if record["name"] in repeats:
                drop(record)
        records = [r for r in records if r["name"] not in repeats]
        ctx.report.warn(f"{len(repeats)} photo(s) repeat another's pixels (a file copied, saved as both HEIC and "
                        "JPEG, or a video's frame saved twice), so each shot is kept once: "
                        f"{short_list([f'{name} (= {repeats[name]})' for name in sorted(repeats, key=capture_key)])}")

    dropped = []
    if s.drop_blurry_fraction > 0 and records:
        n_drop = int(len(records) * s.drop_blurry_fraction)
        for record in sorted(records, key=lambda r: r["sharpness"])[:n_drop]:
            dropped.append(record["name"])
            drop(record)
        records = [r for r in records if r["name"] not in dropped]

    colourless = [records[i]["name"] for i in colourless_among_colour([r["colour_spread"] for r in records])]
    for record in records:
        if record["name"] in colourless:
            record["colourless"] = True
    if colourless:
        ctx.report.warn(f"{len(colourless)} of {len(records)} photos have no colour where the others do (greyscale): "
                        f"{short_list(sorted(colourless, key=capture_key))}; they are posed with the others, and left "
                        "out of the fit and scores")

    if len(records) < s.min_images:
        raise UserError(f"only {len(records)} usable image(s) in {ctx.scene}; at least {s.min_images} overlapping photos are needed")
    write_json(ctx.work / IMAGES_JSON, {"images": records, "skipped": unreadable, "repeated": repeats,
                                        "dropped_blurry": dropped, **({"video": clip} if clip is not None else {})})
    line = f"{len(records)} images at {size_words(records)}"
    if clip is not None:
        line += video_words(clip, s)
        kept = len(panoramas) or len(records)
        if kept < min_frames(clip, s):
            short = too_short(clip, kept, s)
            ctx.report.warn(short)
            line += f"; {short}"
    cropped = sum("bars_cropped" in r for r in records)
    if cropped:
        (width, height), (rows, columns) = bars
        line += (f", black bars cropped from {cropped} (the picture {columns.stop - columns.start}x"
                 f"{rows.stop - rows.start} of their {width}x{height})")
    if panoramas:
        views = sum("panorama" in r for r in records)
        sizes = size_words([dict(zip(("width", "height"), p)) for p in panoramas])
        line += (f", {len(panoramas)} equirectangular 360-degree frames ({sizes}) cut into {views} pinhole views of "
                 f"90 degrees around the horizon{POLE_WORDS[s.equirect_poles]}")
    masked = sum(r["mask"] is not None for r in records)
    if masked:
        given = sum(r.get("mask_from") not in (None, "alpha") for r in records)
        line += f", {masked} with masks ({f'{given} from mask files' if given else 'their alpha'})"
    if colourless:
        line += f", {len(colourless)} without colour (posed only)"
    if repeats:
        line += f", dropped {len(repeats)} repeated"
    if dropped:
        line += f", dropped {len(dropped)} blurriest"
    if sequence:
        line += f", one in {sequence[1]} of {sequence[0]} frames saved from a video"
    if left:
        line += f", {twin_words(left)}"
    if clips:
        line += f", {len(clips)} video(s) beside them not read"
    if unreadable:
        line += f", skipped {len(unreadable)} unreadable"
    return {"line": line, "images": len(records), "skipped": len(unreadable), "repeated": len(repeats),
            "dropped_blurry": len(dropped), "masked": masked, "colourless": len(colourless), "cropped": cropped,
            "raw_twins": sum(kind == "raw" for kind in left.values()), "panorama_frames": len(panoramas),
            **({"sequence": {"photos": sequence[0], "step": sequence[1], "apart": round(sequence[2], 4)}}
               if sequence else {}),
            **({"video": clip} if clip is not None else {})}


def video_words(clip: dict, s: Settings) -> str:
    """The summary's words on a video: its length and the spacing its frames were kept at."""
    words = f" from a {clip['seconds']:.1f} s video, a frame each {clip['motion']:.1%} of the view's diagonal"
    if clip["motion"] < s.video_motion:
        words += (f" (closer than ingest.video_motion's {s.video_motion:.0%}: at that spacing the clip gave fewer than"
                  f" ingest.video_frames's {s.video_frames}{share_words(clip)})")
    if clip.get("every", 1) > 1:
        words += (f", one in {clip['every']} of the {clip['due']} that spacing gave (at most "
                  f"ingest.video_max_frames={s.video_max_frames}{share_words(clip)})")
    if "overlay" in clip:
        what = "what moves with the camera: its holder, a logo" if clip.get("panorama") else "a watermark or caption"
        words += f", a still overlay painted over ({clip['overlay']:.1%} of the picture: {what})"
    if flight := clip.get("flight_log"):
        words += (f", {flight['why']}, so its frames are posed without it" if "why" in flight else
                  f", where the drone was for {flight['frames']} of them from its flight log {flight['file']}")
    if "bars" in clip:
        (width, height), kept = clip["bars"]["frame"], clip["bars"]["kept"]
        words += f", black bars cropped (the picture {kept[2]}x{kept[3]} of its {width}x{height} frame)"
    return words


def min_frames(clip: dict, s: Settings) -> int:
    """The fewest frames a clip should give: ingest.video_min_frames, a FRAME_SHARE-th of it of 360 frames."""
    return s.video_min_frames // FRAME_SHARE if clip.get("panorama") else s.video_min_frames


def share_words(clip: dict) -> str:
    return f" (a {FRAME_SHARE}th of it for 360 frames)" if clip.get("panorama") else ""


def too_short(clip: dict, frames: int, s: Settings) -> str:
    """Why a clip's frames are too few for a good fit, and what to do."""
    limit = (f"at most ingest.video_fps={s.video_fps:g} a second" if frames >= 0.9 * clip["most_frames"]
             else f"the view moved {clip['total_motion']:.2f} of its diagonal in all")
    return (f"the clip is too short for a good fit: {frames} frames where ingest.video_min_frames asks "
            f"{s.video_min_frames}{share_words(clip)} ({limit}); film longer and further around the object, or add "
            "photos")
