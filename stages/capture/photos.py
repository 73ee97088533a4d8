"""Reading the user's photos and videos: supported file types, decoding to upright 8-bit RGB (plus alpha),
downscaling, sharpness scoring and picking the sharpest video frames."""
from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path

import cv2
import numpy as np
import PIL.features
from PIL import Image, ImageOps

from plenoxels.core.errors import UserError
from stages.common.text import text_name

# .jfif and .jpe are JPEGs as some browsers save them; AVIF where this Pillow decodes it (11.2 and later).
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".jfif", ".jpe", ".png", ".tif", ".tiff", ".webp", ".bmp", ".heic", ".heif"}
if PIL.features.check("avif"):
    IMAGE_SUFFIXES.add(".avif")
VIDEO_SUFFIXES = {".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v"}
SHARPNESS_SIDE = 512  # score every image at the same size so scores compare across resolutions
# Video frames are tracked at this size; a stretch ends when fewer than this share of its corners are still followed,
# and its frames past this share of the motion wanted are candidates to keep.
TRACKING_SIDE = 480
TRACKS_KEPT_SHARE = 0.5
CANDIDATE_SHARE = 0.6
# A clip that gives too few frames at the motion set is read again at most VIDEO_RETRIES times, with frames at least
# MIN_MOTION_SHARE of that motion apart (closer, neighbours differ by less than SfM can triangulate from).
VIDEO_RETRIES = 3
MIN_MOTION_SHARE = 0.25
# A folder of more photos than ingest.video_max_frames is looked at for a video's frames saved one by one at this
# many places through it (two photos each): neighbours closer than this share of ingest.video_motion are such frames.
# A walk around ball filmed at 30 frames a second moves 1.2% of the view's diagonal a frame (its 16 s clip, 5.8
# diagonals in all); measured neighbours of photos taken one by one: 4.1% (fox), 14% (cup); ball's frames at 8 a
# second 4.9%.
SEQUENCE_PAIRS = 10
SEQUENCE_MOTION_SHARE = 0.5
EXIF_ORIENTATION = 0x0112
# A photo whose pixels nearly all sit within COLOURLESS_SPREAD of grey (the 99th percentile, over its pixels neither
# near black nor near white, of each pixel's largest difference between two channels, of 255), in a capture whose
# typical photo spreads at least COLOUR_SPREAD, is a greyscale print or filter among colour photos: SfM poses it from
# its grey like any other, but fitted, its grey would pull the scene's colours toward grey. Colour photos spread 53-199
# (fox, ball, lego, fern, a DTU scan), their greyest 64-pixel patches (cup's white table) 2-3; grey photos 0, or 1
# where a decoder rounds.
COLOURLESS_SPREAD = 1
COLOUR_SPREAD = 16
# Two photos whose grey thumbnails (THUMBNAIL_SIDE square) differ by at most DUPLICATE_RMS (of 255, root mean square)
# are one shot twice: a file copied, or saved as both HEIC and JPEG. A copy re-encoded or halved differs by 0.2-0.7;
# the closest distinct photos of cup, fox, ball, lego and fern by 3.0-15.
THUMBNAIL_SIDE = 32
DUPLICATE_RMS = 1.0
# A video's rows or columns at its frame's edge that are dark and flat (grey mean at most BAR_MEAN, spread at most
# BAR_SPREAD, of 255) in each of BAR_SAMPLES frames spread over the clip are black bars (a portrait clip exported in a
# landscape frame, a film's letterbox), not scene: cropped from every frame where they are at least BAR_MIN_SHARE of
# the frame across and leave at least BAR_MIN_PICTURE of it. Bars decode to 0-4 with 18 at most where the codec rings
# beside the picture; the darkest edge lines of ball, fox, cup, fern and apple have means of 23-140.
BAR_SAMPLES = 24
BAR_MEAN = 12.0
BAR_SPREAD = 6.0
BAR_MIN_SHARE = 0.01
BAR_MIN_PICTURE = 0.2

try:  # HEIC support comes from pillow-heif when it is installed
    from pillow_heif import register_heif_opener

    register_heif_opener()
except ImportError:
    IMAGE_SUFFIXES -= {".heic", ".heif"}
# A camera's RAW files, developed by LibRaw (rawpy): a RAW beside a JPEG or HEIC of its name is the same shot, which the
# camera developed already, so the developed one is read (`raw_twins`).
RAW_SUFFIXES = {".dng", ".cr2", ".cr3", ".nef", ".nrw", ".arw", ".raf", ".orf", ".rw2", ".pef", ".srw"}
try:
    import rawpy
except ImportError:
    RAW_SUFFIXES = set()
IMAGE_SUFFIXES |= RAW_SUFFIXES


def is_video(scene: Path) -> bool:
    """True when the scene is a single video file rather than a folder of photos."""
    return scene.is_file() and scene.suffix.lower() in VIDEO_SUFFIXES


# The splits a NeRF synthetic (Blender) dataset folder has: <split>/ beside transforms_<split>.json.
DATASET_SPLITS = ("train", "val", "test")


def _has_photos(folder: Path) -> bool:
    return folder.is_dir() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in folder.iterdir() if p.is_file())


def is_split_dataset(folder: Path) -> bool:
    """A NeRF synthetic layout: train/ (and val/, test/) photo folders, each beside its transforms_<split>.json."""
    return folder.is_dir() and (folder / "transforms_train.json").is_file() and _has_photos(folder / "train")


def lexical_path(path: Path) -> Path:
    """`path` made absolute and normalised (`.` and `..` folded) without following symbolic links: how a pose file's
    frame and a photo are compared, the same way on both sides (a split folder of links to the photos must not
    turn one split's frame into another's)."""
    return Path(os.path.normpath(os.path.abspath(path)))


def frame_photo(base: Path, file_path: str) -> Path | None:
    """The photo a pose file's `file_path` names, relative to the pose file's folder `base`: the file as written, or
    with a photo suffix added (NeRF synthetic frames name `./train/r_0` for `train/r_0.png`); None when absent."""
    named = base / file_path.replace("\\", "/")
    if named.suffix.lower() in IMAGE_SUFFIXES and named.is_file():
        return named
    return next((named.with_name(named.name + suffix) for suffix in sorted(IMAGE_SUFFIXES)
                 if named.with_name(named.name + suffix).is_file()), None)


def split_photos(scene: Path, split: str) -> list[Path]:
    """The photos of a split dataset's `split`: the frames its transforms_<split>.json lists, nothing else (the
    published test/ folders also hold depth and normal renders beside each photo); every photo of the folder where
    the split has no such file."""
    listing = scene / f"transforms_{split}.json"
    folder = scene / split
    if not listing.is_file():
        return sorted(f for f in folder.iterdir() if f.is_file() and not f.name.startswith(".")) if folder.is_dir() else []
    try:
        frames = json.loads(listing.read_text())["frames"]
        names = [str(frame["file_path"]) for frame in frames]
    except (json.JSONDecodeError, KeyError, TypeError):
        raise UserError(f"{listing} is not a transforms file with a 'frames' list, each with a file_path; fix it or "
                        f"move it away from the photos") from None
    photos, absent = [], []
    for name in names:
        photo = frame_photo(scene, name)
        if photo is not None and not lexical_path(photo).is_relative_to(lexical_path(scene)):
            raise UserError(f"{listing.name} names {name}, outside the dataset folder {scene}; a split dataset's "
                            f"frames live in its own split folders")
        (photos if photo is not None else absent).append(photo or name)
    if absent:
        raise UserError(f"{listing.name} lists {len(absent)} frame(s) with no photo in {scene} ({', '.join(absent[:3])}"
                        f"{', ...' if len(absent) > 3 else ''}); restore them or remove those frames from the file")
    return sorted(set(photos))


def photo_folder(scene: Path) -> Path:
    """The folder the scene's photo paths are relative to: for a video, the folder it sits in; for a dataset
    folder, its images/ (a COLMAP project or a nerfstudio folder) or its largest images_N/ (LLFF), or the dataset
    itself when its photos sit in split folders (NeRF synthetic); else the folder named."""
    if scene.is_file():
        return scene.parent
    if _has_photos(scene) or is_split_dataset(scene):
        return scene
    for name in ("images", "image"):  # image/: the NeuS/IDR layout (beside mask/ and cameras_sphere.npz)
        if _has_photos(scene / name):
            return scene / name
    downscaled = [d for d in scene.glob("images_*") if d.name[7:].isdigit() and _has_photos(d)]
    return min(downscaled, key=lambda d: int(d.name[7:])) if downscaled else scene


def scene_source(scene: Path) -> Path:
    """What the scene's photos come from: the folder or video named; or, for a folder that holds no photos but one
    video, that video. A folder of several videos and no photos stops with their names."""
    if not scene.is_dir() or is_split_dataset(scene) or _has_photos(photo_folder(scene)):
        return scene
    videos = sorted(f for f in scene.iterdir() if f.is_file() and f.suffix.lower() in VIDEO_SUFFIXES
                    and not f.name.startswith("."))
    if len(videos) > 1:
        raise UserError(f"{scene} holds {len(videos)} videos and no photos: give one of them ("
                        f"{', '.join(v.name for v in videos[:4])}{', ...' if len(videos) > 4 else ''})")
    return videos[0] if videos else scene


ARCHIVE_SUFFIXES = {".zip", ".tar", ".gz", ".tgz", ".bz2", ".xz", ".7z", ".rar"}


def not_a_scene(path: Path) -> str:
    """Why a file given as the scene is not one, and what to give instead."""
    suffix = path.suffix.lower()
    if suffix in IMAGE_SUFFIXES:
        return f"{path.name} is one photo; give the folder that holds the scene's photos ({path.parent})"
    if suffix in ARCHIVE_SUFFIXES:
        return f"{path.name} is an archive; unpack it and give the folder of photos it holds"
    return f"{path.name} is neither a folder of photos nor a video ({', '.join(sorted(VIDEO_SUFFIXES))})"


def scene_photos(scene: Path, holdout_split: str) -> list[tuple[Path, str | None]]:
    """The photo files of a folder scene, each with its split when the dataset defines one: a NeRF synthetic folder
    gives train/ as "train" and the `holdout_split` folder ("val" or "test"; "none": none) as "test"."""
    folder = photo_folder(scene)
    if is_split_dataset(scene):
        holding_out = holdout_split in DATASET_SPLITS[1:]
        splits = [("train", "train" if holding_out else None)] + ([(holdout_split, "test")] if holding_out else [])
        if len(splits) > 1 and not _has_photos(scene / holdout_split):
            raise UserError(f"{scene} has no {holdout_split}/ photos to hold out; set ingest.holdout_split to one it "
                            f"has ({', '.join(d for d in DATASET_SPLITS[1:] if _has_photos(scene / d)) or 'none'})")
        return [(p, split) for name, split in splits for p in split_photos(scene, name)]
    photos = [(p, None) for p in sorted(f for f in folder.iterdir() if f.is_file() and not f.name.startswith("."))]
    if not any(p.suffix.lower() in IMAGE_SUFFIXES for p, _ in photos):
        # Two levels down at most: a folder as wide as a home folder is named, not walked.
        holding = [(d, sum(1 for pattern in ("*", "*/*") for f in d.glob(pattern)
                           if f.suffix.lower() in IMAGE_SUFFIXES and f.is_file()))
                   for d in sorted(folder.iterdir()) if d.is_dir() and not d.name.startswith(".")]
        holding = [f"{d.name}/ ({count} photo{'s' if count != 1 else ''})" for d, count in holding if count]
        if holding:
            raise UserError(f"no photos in {folder} itself, but its folders {', '.join(holding[:4])} hold some: give "
                            "the folder that holds the scene's photos (one capture's photos together in one folder)")
    return photos


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image at a fixed size: higher is sharper."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    scale = SHARPNESS_SIDE / max(grey.shape)
    if scale < 1:
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def colour_spread(rgb: np.ndarray) -> float:
    """How far a photo's colours reach from grey: the 99th percentile over its pixels (every other row and column)
    neither near black nor near white, whose channels clip alike in any photo, of the largest difference between two
    of a pixel's channels, 0-255; 0 for a greyscale photo, 255 for one all but black or white."""
    pixels = rgb[::2, ::2].reshape(-1, 3).astype(np.int16)
    pixels = pixels[np.abs(pixels.mean(axis=1) - 128) < 104]
    if len(pixels) == 0:
        return 255.0
    spread = np.abs(pixels - np.roll(pixels, 1, axis=-1)).max(axis=-1)
    return float(np.percentile(spread, 99))


def colourless_among_colour(spreads: list[float]) -> list[int]:
    """The photos (by index) without colour in a capture whose typical photo has it (COLOURLESS_SPREAD,
    COLOUR_SPREAD); none in a capture that is grey throughout."""
    if not spreads or np.median(spreads) < COLOUR_SPREAD:
        return []
    return [i for i, spread in enumerate(spreads) if spread <= COLOURLESS_SPREAD]


def thumbnail(rgb: np.ndarray) -> np.ndarray:
    """A photo's grey thumbnail, THUMBNAIL_SIDE square whatever its shape, as floats: what `repeated` compares."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    return cv2.resize(grey, (THUMBNAIL_SIDE, THUMBNAIL_SIDE), interpolation=cv2.INTER_AREA).astype(np.float32).ravel()


def repeated(thumbnails: list[np.ndarray]) -> dict[int, int]:
    """Each photo (by index) that repeats an earlier one (DUPLICATE_RMS), and the first photo it repeats."""
    if len(thumbnails) < 2:
        return {}
    stacked = np.stack(thumbnails).astype(np.float64)
    squares = (stacked ** 2).sum(axis=1)
    distance = (squares[:, None] + squares[None] - 2 * stacked @ stacked.T) / stacked.shape[1]
    close = np.tril(distance <= DUPLICATE_RMS ** 2, k=-1)
    return {i: int(np.argmax(close[i])) for i in np.flatnonzero(close.any(axis=1))}


def _to_uint8(array: np.ndarray) -> np.ndarray:
    if array.dtype == np.uint8:
        return array
    if array.dtype == np.uint16:
        return (array.astype(np.uint32) * 255 // 65535).astype(np.uint8)
    if np.issubdtype(array.dtype, np.floating):
        return (np.clip(array, 0, 1) * 255 + 0.5).astype(np.uint8)
    return np.clip(array, 0, 255).astype(np.uint8)


def orient(array: np.ndarray, exif_orientation: int) -> np.ndarray:
    """Applies an EXIF orientation tag (1-8) to a pixel array, as a camera's viewer would."""
    ops = {2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
           5: lambda a: np.swapaxes(a, 0, 1), 6: lambda a: np.rot90(a, -1),
           7: lambda a: np.rot90(a, 1)[::-1], 8: lambda a: np.rot90(a, 1)}
    return np.ascontiguousarray(ops[exif_orientation](array)) if exif_orientation in ops else array


def stored_orientation(path: Path) -> int:
    """The EXIF orientation (1-8) a photo's pixels are stored in; 1 (upright) where it has none or cannot be read."""
    try:
        with Image.open(path) as im:
            return int(im.getexif().get(EXIF_ORIENTATION, 1))
    except Exception:  # an unreadable photo is skipped where it is loaded; its orientation does not matter
        return 1


def scene_files(scene: Path) -> list[Path]:
    """Every file `scene_photos` may return for this scene, whatever split is held out (for a cache key)."""
    if scene.is_file():
        return [scene]
    if is_split_dataset(scene):
        return [p for split in DATASET_SPLITS if (scene / split).is_dir()
                for p in sorted(f for f in (scene / split).iterdir() if f.is_file() and not f.name.startswith("."))]
    return [p for p, _ in scene_photos(scene, "none")]


def raw_twins(photos: list[Path]) -> list[Path]:
    """The RAW files among `photos` that have a developed photo (not RAW) of the same name in the same folder."""
    developed = {(p.parent, p.stem.lower()) for p in photos
                 if p.suffix.lower() in IMAGE_SUFFIXES and p.suffix.lower() not in RAW_SUFFIXES}
    return [p for p in photos if p.suffix.lower() in RAW_SUFFIXES and (p.parent, p.stem.lower()) in developed]


def upright_size(path: Path) -> tuple[int, int] | None:
    """A photo's (width, height) as it is shown (EXIF orientation applied; a RAW file's as developed), from its
    header; None where it cannot be read."""
    try:
        if path.suffix.lower() in RAW_SUFFIXES:
            with open(path, "rb") as file, rawpy.imread(file) as raw:
                size, turned = (raw.sizes.width, raw.sizes.height), raw.sizes.flip in (5, 6)
        else:
            with Image.open(path) as im:
                size, turned = im.size, im.getexif().get(EXIF_ORIENTATION, 1) in (5, 6, 7, 8)
    except Exception:  # an unreadable photo is skipped where it is loaded
        return None
    return (size[1], size[0]) if turned else size


def load_raw(path: Path) -> np.ndarray:
    """A RAW photo developed to 8-bit sRGB, upright: the camera's white balance, and no brightening of its own (each
    photo brightened by its own histogram would differ in exposure from the next)."""
    with open(path, "rb") as file, rawpy.imread(file) as raw:
        return np.ascontiguousarray(raw.postprocess(use_camera_wb=True, no_auto_bright=True, output_bps=8))


def load_photo(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Any supported photo -> (8-bit RGB [h,w,3], 8-bit alpha [h,w] or None), upright per its EXIF; a RAW photo
    developed (`load_raw`)."""
    if path.suffix.lower() in RAW_SUFFIXES:
        return load_raw(path), None
    with Image.open(path) as im:
        orientation = im.getexif().get(EXIF_ORIENTATION, 1)
        mode = im.mode
        if mode in ("I;16", "I;16B", "I;16L", "I", "F"):
            grey = _to_uint8(np.asarray(im)) if mode != "I" else _to_uint8(np.asarray(im).astype(np.uint16))
            rgb, alpha = np.repeat(orient(grey, orientation)[..., None], 3, axis=-1), None
            return rgb, alpha
        if mode not in ("RGB", "RGBA", "L", "LA", "P", "CMYK", "YCbCr", "I;16"):
            raise ValueError(f"unsupported pixel mode {mode}")
        # Decoded from its bytes: OpenCV takes a path as UTF-8 and crashes on one that is not (a name from another system).
        wide = (cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_UNCHANGED)
                if path.suffix.lower() in {".png", ".tif", ".tiff"} else None)
        if wide is not None and wide.dtype == np.uint16 and wide.ndim == 3:
            # Pillow reads 16-bit colour as 8-bit by truncation; OpenCV keeps the full range.
            wide = cv2.cvtColor(wide, cv2.COLOR_BGRA2RGBA if wide.shape[2] == 4 else cv2.COLOR_BGR2RGB)
            pixels = orient(_to_uint8(wide), orientation)
        else:
            im = ImageOps.exif_transpose(im)
            has_alpha = im.mode in ("RGBA", "LA") or (im.mode == "P" and "transparency" in im.info)
            pixels = np.asarray(im.convert("RGBA" if has_alpha else "RGB"))
    if pixels.shape[2] == 4:
        return np.ascontiguousarray(pixels[..., :3]), np.ascontiguousarray(pixels[..., 3])
    return np.ascontiguousarray(pixels), None


def fit_max_side(image: np.ndarray, max_side: int) -> np.ndarray:
    """The image downscaled (area filter) so its longest side is at most `max_side`; 0 or a larger side keeps it."""
    scale = max_side / max(image.shape[:2]) if max_side else 1.0
    if scale >= 1.0:
        return image
    size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def _view_motion(first: np.ndarray, second: np.ndarray) -> float:
    """How far the view moved between two grey frames, as a share of their diagonal: the median motion of the first's
    corners followed into the second by optical flow; 1 where fewer than TRACKS_KEPT_SHARE of them can be followed."""
    corners = _corners(first)
    if corners is None or first.shape != second.shape:
        return 1.0
    followed, status, _ = cv2.calcOpticalFlowPyrLK(first, second, corners, None)
    alive = status.ravel() == 1
    if alive.sum() < TRACKS_KEPT_SHARE * len(corners):
        return 1.0
    return float(np.median(np.linalg.norm((followed[alive] - corners[alive]).reshape(-1, 2), axis=1))) / np.hypot(
        *first.shape)


def sequence_step(paths: list[Path], motion: float, max_frames: int, target_frames: int) -> tuple[int, float]:
    """Of a folder's photos in name order: whether they are a video's frames saved one by one (neighbours, at
    SEQUENCE_PAIRS places through the folder, closer than SEQUENCE_MOTION_SHARE of `motion`), and if so, every how many
    to read, as a video is read: frames about `motion` apart, at most `max_frames`, but not fewer than `target_frames`
    for that spacing; 1 for separate photos. Also the neighbours' median motion."""
    moves = []
    for i in np.linspace(0, len(paths) - 2, SEQUENCE_PAIRS).round().astype(int):
        try:
            first, second = (_tracking_grey(cv2.cvtColor(load_photo(paths[j])[0], cv2.COLOR_RGB2BGR)) for j in (i, i + 1))
        except Exception:  # an unreadable photo is skipped where it is loaded
            continue
        moves.append(_view_motion(first, second))
    apart = float(np.median(moves)) if moves else 1.0
    if apart >= SEQUENCE_MOTION_SHARE * motion:
        return 1, apart
    spaced = min(round(motion / max(apart, 1e-4)), len(paths) // max(target_frames, 1))
    return max(1, math.ceil(len(paths) / max_frames) if max_frames else 1, spaced), apart


def open_video(path: Path) -> cv2.VideoCapture:
    """A video opened for reading, upright (its rotation metadata applied), or one line that says it cannot be. A path
    that is not UTF-8 (a name from another system), which OpenCV cannot take, is opened through a link of a plain name,
    gone once the file is open."""
    try:
        str(path).encode("utf-8")
        capture = cv2.VideoCapture(str(path))
    except UnicodeEncodeError:
        with tempfile.TemporaryDirectory() as folder:
            link = Path(folder) / "video"
            link.symlink_to(path.resolve())
            capture = cv2.VideoCapture(str(link))
    if not capture.isOpened():
        raise UserError(f"cannot read video {text_name(path.name)}; convert it to MP4 (H.264) or extract photos")
    capture.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)
    return capture


def _tracking_grey(bgr: np.ndarray) -> np.ndarray:
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    scale = TRACKING_SIDE / max(grey.shape)
    return cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else grey


def _corners(grey: np.ndarray) -> np.ndarray | None:
    return cv2.goodFeaturesToTrack(grey, maxCorners=400, qualityLevel=0.01, minDistance=max(4, max(grey.shape) // 60))


def _dark_lines(grey: np.ndarray, axis: int) -> np.ndarray:
    """Which rows (axis 1) or columns (axis 0) of a grey frame are dark and flat."""
    return (grey.mean(axis=axis) <= BAR_MEAN) & (grey.std(axis=axis) <= BAR_SPREAD)


def _edge_run(dark: np.ndarray) -> tuple[int, int]:
    """How many lines from each end of `dark` are dark without a break."""
    lit = np.flatnonzero(~dark)
    return (int(lit[0]), int(len(dark) - 1 - lit[-1])) if len(lit) else (len(dark), 0)


def picture_box(greys: list[np.ndarray]) -> tuple[slice, slice] | None:
    """The (rows, columns) of a video's frames that hold its picture, within the black bars along their edges
    (BAR_MEAN, BAR_SPREAD) in every one of `greys`; None where there are no bars worth cropping or no picture
    would be left (a clip dark throughout)."""
    if not greys:
        return None
    dark_rows = np.logical_and.reduce([_dark_lines(g, 1) for g in greys])
    dark_columns = np.logical_and.reduce([_dark_lines(g, 0) for g in greys])
    (top, bottom), (left, right) = _edge_run(dark_rows), _edge_run(dark_columns)
    height, width = greys[0].shape
    top, bottom = (v if v >= BAR_MIN_SHARE * height else 0 for v in (top, bottom))
    left, right = (v if v >= BAR_MIN_SHARE * width else 0 for v in (left, right))
    if not (top or bottom or left or right):
        return None
    if height - top - bottom < BAR_MIN_PICTURE * height or width - left - right < BAR_MIN_PICTURE * width:
        return None
    return slice(top, height - bottom), slice(left, width - right)


def photos_picture(paths: list[Path]) -> tuple[tuple[int, int], tuple[slice, slice]] | None:
    """For a capture's photos: the upright (width, height) most of them share and the picture within the black
    bars that all of those have (`picture_box` over BAR_SAMPLES of them, spread over the capture: frames a tool
    saved from a padded video); None where they have none, or carry their own alpha."""
    sizes = {path: size for path in paths if (size := upright_size(path)) is not None}
    if not sizes:
        return None
    common = max(set(sizes.values()), key=list(sizes.values()).count)
    # A camera's RAW file holds the whole sensor, never bars; developing one to look costs most of a second.
    alike = [path for path, size in sizes.items() if size == common and path.suffix.lower() not in RAW_SUFFIXES]
    if not alike:
        return None
    greys = []
    for index in np.unique(np.linspace(0, len(alike) - 1, BAR_SAMPLES).round().astype(int)):
        try:
            rgb, alpha = load_photo(alike[index])
        except Exception:
            continue
        if alpha is not None:
            return None
        greys.append(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    picture = picture_box(greys)
    return (common, picture) if picture is not None else None


def video_picture(path: Path) -> tuple[slice, slice] | None:
    """The picture within a video's black bars (`picture_box` over BAR_SAMPLES frames spread over the clip), or
    None where it has none."""
    capture = open_video(path)
    total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    # Read on, not seeked: a seek decodes from the last key frame, which cost ball's 127-frame clip 2.2 s for 24
    # samples against 0.5 s to decode it all. A clip of unknown length gives its first samples, 10 frames apart.
    step = max(1, total // BAR_SAMPLES) if total > 0 else 10
    greys, index = [], 0
    while len(greys) < BAR_SAMPLES and capture.grab():
        if index % step == 0:
            ok, bgr = capture.retrieve()
            if ok:
                greys.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
        index += 1
    capture.release()
    return picture_box(greys)


def video_frames(path: Path, max_side: int, motion: float, max_per_second: float, report,
                 target_frames: int = 0, crop_bars: bool = True,
                 max_frames: int = 0) -> tuple[list[tuple[str, np.ndarray]], dict]:
    """(name, RGB) of the frames to pose from a video (see frames_by_motion), and what the clip gave: its `seconds`,
    the `motion` the frames were kept at and `total_motion` (diagonals the view moved in all). A clip whose motion
    gives fewer than `target_frames` at `motion` (a short clip, or a camera that moved little) is read again with
    frames closer together, as close as the motion allows for `target_frames` but never below MIN_MOTION_SHARE of
    `motion`, nor more than `max_per_second` a second. A clip that gives more than `max_frames` (0: no limit; a
    long one) is read again keeping every `every`-th frame due, so the frames span the whole clip and memory holds
    no more than that many. With `crop_bars`, black bars along the frame's edges (`video_picture`) are cropped from
    every frame before anything else, and the clip's `bars` say what was kept: [x, y, width, height] of the frame's
    [width, height]."""
    picture = video_picture(path) if crop_bars else None

    def read(at: float, every: int = 1) -> tuple[list[tuple[str, np.ndarray]], dict]:
        return frames_by_motion(path, max_side, at, max_per_second, report, picture, max_frames if every == 1 else 0,
                                every)

    kept, clip = read(motion)
    used = motion
    for _ in range(VIDEO_RETRIES):
        if not target_frames or clip["due"] >= target_frames or clip["due"] >= clip["most_frames"]:
            break
        denser = max(motion * MIN_MOTION_SHARE, min(used * 0.7, clip["total_motion"] / target_frames))
        if denser >= used:
            break
        used = denser
        kept, clip = read(used)
    every = 1
    if max_frames and clip["due"] > max_frames:
        every = math.ceil(clip["due"] / max_frames)
        kept, clip = read(used, every)
        if len(kept) > max_frames:  # the second reading's stretches fell a little differently
            kept = [kept[i] for i in np.linspace(0, len(kept) - 1, max_frames).round().astype(int)]
    return kept, {**clip, "motion": used, "every": every, "max_per_second": max_per_second}


def frames_by_motion(path: Path, max_side: int, motion: float, max_per_second: float, report,
                     picture: tuple[slice, slice] | None = None, max_frames: int = 0,
                     keep_every: int = 1) -> tuple[list[tuple[str, np.ndarray]], dict]:
    """(name, RGB) of the frames to pose from a video, upright (its rotation metadata applied), cropped to
    `picture` (rows, columns) where given, downscaled to
    `max_side`, and the clip's `seconds`, `total_motion` and `most_frames` (what `max_per_second` allows). A frame is
    due each time the view has moved by `motion` of the frame's diagonal since the last kept
    frame (the median motion of corners tracked from it by optical flow), or when fewer than half of those corners
    can still be followed, so neighbours keep overlapping however fast or slowly the camera moved; of the frames
    in the last stretch before that point, the sharpest is kept. At most `max_per_second` frames per second of video.
    Of the frames due, every `keep_every`-th is kept (the first included). Past `max_frames` (0: no limit) the frames
    due are only counted, their pixels let go, and none are returned: the clip's `due` says how many there were."""
    capture = open_video(path)
    fps = capture.get(cv2.CAP_PROP_FPS) or 30.0
    total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) or None
    min_gap = max(1, round(fps / max_per_second))
    kept: list[tuple[str, np.ndarray]] = []
    # The sharpest candidate since the stretch began, (sharpness, index, rgb): one frame held, however long the stretch.
    best: tuple[float, int, np.ndarray] | None = None
    previous = points = start = None
    index, last_kept, tracked, due = 0, -min_gap, 0, 0
    total_motion, counted = 0.0, 0.0  # diagonals moved in all: the stretches ended, and the current one so far
    counting = False  # past max_frames: the frames due are counted, and none held

    def keeping() -> bool:
        """Whether the next frame due is kept, so its stretch's candidates need their pixels."""
        return due % keep_every == 0 and not counting

    def keep(frame: tuple[float, int, np.ndarray | None]) -> None:
        nonlocal last_kept, due, counting
        if frame[2] is not None:
            kept.append((f"frame_{frame[1]:06d}", frame[2]))
            if max_frames and len(kept) > max_frames:
                kept.clear()
                counting = True
        last_kept, due = frame[1], due + 1

    with report.bar(total=total, desc=f"reading {path.name}") as bar:
        while True:
            ok, bgr = capture.read()
            if not ok:
                break
            if picture is not None:
                frame_shape = bgr.shape[:2]
                bgr = np.ascontiguousarray(bgr[picture])
            grey = _tracking_grey(bgr)
            moved, lost = 0.0, False
            if previous is not None and points is not None and len(points):
                followed, status, _ = cv2.calcOpticalFlowPyrLK(previous, grey, points, None)
                alive = status.ravel() == 1
                points, start = followed[alive], start[alive]
                lost = len(points) < TRACKS_KEPT_SHARE * tracked
                if len(points):
                    moved = float(np.median(np.linalg.norm((points - start).reshape(-1, 2), axis=1))) / np.hypot(*grey.shape)
                    counted = max(counted, moved)
            if previous is None or points is None or not len(points):
                total_motion, counted = total_motion + counted, 0.0
                points = _corners(grey)
                start, tracked = points, len(points) if points is not None else 0
                if not due:  # the first frame anchors the sequence
                    rgb = fit_max_side(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), max_side)
                    keep((sharpness(rgb), index, rgb))
            elif (moved >= CANDIDATE_SHARE * motion or lost) and not keeping():
                best = best or (0.0, index, None)
            elif moved >= CANDIDATE_SHARE * motion or lost:
                rgb = fit_max_side(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), max_side)
                score = sharpness(rgb)
                if best is None or score > best[0]:
                    best = (score, index, rgb)
            if (moved >= motion or lost) and best is not None and index - last_kept >= min_gap:
                keep(best)
                best = None
                # Track again from this frame: the next stretch is measured from (about) the frame just kept.
                total_motion, counted = total_motion + counted, 0.0
                points = _corners(grey)
                start, tracked = points, len(points) if points is not None else 0
            previous = grey
            index += 1
            bar.update()
    if best is not None and best[1] - last_kept >= min_gap:
        keep(best)
    capture.release()
    bars = {}
    if picture is not None and index:
        rows, columns = picture
        bars = {"bars": {"frame": [frame_shape[1], frame_shape[0]],
                         "kept": [columns.start, rows.start, columns.stop - columns.start, rows.stop - rows.start]}}
    return kept, {"seconds": round(index / fps, 2), "total_motion": round(total_motion + counted, 4),
                  "most_frames": index // min_gap + 1, "due": due, **bars}
