"""Reading the user's photos: supported file types, where a scene's photos are, decoding to upright 8-bit RGB (plus
alpha), downscaling, and what ingest measures of each (sharpness, colour, repeats); videos are read in
stages/capture/video.py."""
from __future__ import annotations

import json
import os
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import PIL.features
from PIL import Image, ImageOps

from plenoxels.core.errors import UserError
from stages.capture.picture import BAR_SAMPLES, picture_box

# .jfif and .jpe are JPEGs as some browsers save them; AVIF where this Pillow decodes it (11.2 and later).
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".jfif", ".jpe", ".png", ".tif", ".tiff", ".webp", ".bmp", ".heic", ".heif"}
if PIL.features.check("avif"):
    IMAGE_SUFFIXES.add(".avif")
VIDEO_SUFFIXES = {".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v"}
# A 360 camera's unstitched recordings: Insta360's video and photos, GoPro MAX's.
RAW_360_SUFFIXES = {".insv", ".insp", ".360"}
# Files beside the photos that are no photos and are passed over without a word: pose files and notes.
SIDECAR_SUFFIXES = {".json", ".npy", ".npz", ".xml", ".txt", ".md", ".xmp", ".csv"}
SHARPNESS_SIDE = 512  # score every image at the same size so scores compare across resolutions
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
# Files a tool writes beside each photo from the photo itself (`twins`): BlendedMVS's `<stem>_masked.jpg` (the photo
# blacked out where its reconstruction saw nothing), and an object's mask kept beside its photo (`<stem>_mask.png`,
# read as its mask where no masks/ folder is: masks.py).
DERIVED_TAILS = {"_masked": "masked", "_mask": "mask", "-mask": "mask"}
TWIN_WORDS = {"raw": "RAW files left for the developed photos of their names",
              "masked": "masked copies left for the photos of their names",
              "mask": "masks kept beside the photos of their names (read as their masks where no masks/ folder is)"}


def is_video(scene: Path) -> bool:
    """True when the scene is a single video file rather than a folder of photos."""
    return scene.is_file() and scene.suffix.lower() in VIDEO_SUFFIXES


# The splits a published dataset folder may define: NeRF synthetic's (Blender's) <split>/ beside
# transforms_<split>.json; NeRF++'s <split>/rgb/ beside <split>/pose/ (its val split named validation/); NSVF's rgb/
# photos named 0_ (train), 1_ (val) and 2_ (test) beside pose/ (svox2's Tanks and Temples).
DATASET_SPLITS = ("train", "val", "test")
NERFPP_SPLIT_FOLDERS = {"train": ("train",), "val": ("validation", "val"), "test": ("test",)}
NSVF_PREFIXES = {"0_": "train", "1_": "val", "2_": "test"}
# The folders NSVF and NeRF++ keep a photo's camera-to-world pose in (extrinsic/: NSVF's world-to-camera ones).
POSE_FOLDERS = ("pose", "poses", "extrinsic")
# Polycam's raw export (keyframes/): a folder of its photos -> the folder of their cameras beside it; the undistorted
# photos first.
POLYCAM_CAMERAS = {"corrected_images": "corrected_cameras", "images": "cameras"}


def _has_photos(folder: Path) -> bool:
    return folder.is_dir() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in folder.iterdir() if p.is_file())


def _posed_folder(folder: Path) -> bool:
    """Whether a photo folder has NSVF's or NeRF++'s pose folder beside it."""
    return any((folder.parent / name).is_dir() for name in POSE_FOLDERS)


def split_folder(scene: Path, split: str) -> Path | None:
    """The photo folder of a split dataset's `split` (the first of NeRF++'s names for it that holds photos)."""
    if split_layout(scene) == "blender":
        return scene / split
    held = [scene / name / "rgb" for name in NERFPP_SPLIT_FOLDERS[split]]
    return next((folder for folder in held if _has_photos(folder)), None)


def split_layout(folder: Path) -> str | None:
    """"blender": NeRF synthetic's train/ (and val/, test/) photo folders, each beside its transforms_<split>.json;
    "nerfpp": NeRF++'s train/rgb/ (and validation/, test/) beside train/pose/; else None."""
    if not folder.is_dir():
        return None
    if (folder / "transforms_train.json").is_file() and _has_photos(folder / "train"):
        return "blender"
    return "nerfpp" if _has_photos(folder / "train" / "rgb") and _posed_folder(folder / "train" / "rgb") else None


def is_split_dataset(folder: Path) -> bool:
    return split_layout(folder) is not None


def nsvf_splits(folder: Path, names: list[str]) -> dict[str, str]:
    """NSVF's splits of the photos named `names` in `folder` (0_ train, 1_ val, 2_ test), where every photo carries
    one of those prefixes and a pose folder is beside them; else none."""
    prefixed = {name: NSVF_PREFIXES.get(name[:2]) for name in names}
    if not names or not all(prefixed.values()) or "train" not in prefixed.values() or not _posed_folder(folder):
        return {}
    return prefixed


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
    folder = split_folder(scene, split)
    if split_layout(scene) != "blender" or not listing.is_file():
        return sorted(f for f in folder.iterdir() if f.is_file() and not f.name.startswith(".")) \
            if folder is not None and folder.is_dir() else []
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
    folder, its images/ (a COLMAP project or a nerfstudio folder), image/ (NeuS), rgb/ (NSVF), blended_images/
    (BlendedMVS), Polycam's keyframes/corrected_images/ (or images/), or its largest images_N/ (LLFF), or the dataset
    itself when its photos sit in split folders (NeRF synthetic, NeRF++); else the folder named."""
    if scene.is_file():
        return scene.parent
    if _has_photos(scene) or is_split_dataset(scene):
        return scene
    if any(_has_photos(scene / "keyframes" / name) for name in POLYCAM_CAMERAS):  # Polycam's raw export
        scene = scene / "keyframes"
    if _has_photos(scene / "corrected_images") and (scene / POLYCAM_CAMERAS["corrected_images"]).is_dir():
        return scene / "corrected_images"
    # image/: the NeuS/IDR layout (beside mask/ and cameras_sphere.npz); rgb/: NSVF's (beside pose/);
    # blended_images/: BlendedMVS's (beside MVSNet's cams/)
    for name in ("images", "image", "rgb", "blended_images"):
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
    if suffix in RAW_360_SUFFIXES:
        return (f"{path.name} is a 360 camera's own file (its lenses' pictures, not yet stitched); export it from the "
                "camera's app as an equirectangular MP4 and give that")
    return f"{path.name} is neither a folder of photos nor a video ({', '.join(sorted(VIDEO_SUFFIXES))})"


def not_read_why(path: Path) -> str:
    """Why a file beside the photos is not read, in words for the list of files skipped."""
    if path.suffix.lower() in RAW_360_SUFFIXES:
        return "a 360 camera's unstitched file: export it from the camera's app as an equirectangular MP4"
    return "not a supported image type"


def scene_photos(scene: Path, holdout_split: str) -> list[tuple[Path, str | None]]:
    """The photo files of a folder scene, each with its split when the dataset defines one: a NeRF synthetic folder
    gives train/ as "train" and the `holdout_split` folder ("val" or "test"; "none": none) as "test"."""
    folder = photo_folder(scene)
    holding_out = holdout_split in DATASET_SPLITS[1:]
    if is_split_dataset(scene):
        splits = [("train", "train" if holding_out else None)] + ([(holdout_split, "test")] if holding_out else [])
        if len(splits) > 1 and not split_photos(scene, holdout_split):
            raise UserError(f"{scene} has no {holdout_split} photos to hold out; set ingest.holdout_split to one it "
                            f"has ({', '.join(d for d in DATASET_SPLITS[1:] if split_photos(scene, d)) or 'none'})")
        return [(p, split) for name, split in splits for p in split_photos(scene, name)]
    photos = [(p, None) for p in sorted(f for f in folder.iterdir() if f.is_file() and not f.name.startswith("."))]
    prefixed = nsvf_splits(folder, [p.name for p, _ in photos if p.suffix.lower() in IMAGE_SUFFIXES])
    if prefixed:
        if holding_out and holdout_split not in prefixed.values():
            raise UserError(f"{folder} has no {holdout_split} photos to hold out (NSVF's "
                            f"{next(k for k, v in NSVF_PREFIXES.items() if v == holdout_split)} names); set "
                            f"ingest.holdout_split to one it has "
                            f"({', '.join(sorted(set(prefixed.values()) - {'train'})) or 'none'})")
        kept = ("train", holdout_split) if holding_out else ("train",)
        return [(p, {"train": "train" if holding_out else None, holdout_split: "test"}[prefixed[p.name]])
                for p, _ in photos if prefixed.get(p.name) in kept]
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


def repeated(thumbnails: list[np.ndarray], stems: list[str]) -> dict[int, int]:
    """Each photo (by index) that repeats another (DUPLICATE_RMS), and the one of them kept: the shortest file stem
    (a copy's name adds to its original's: `3(1)`, `photo copy`; a pose file names the original), else the first."""
    if len(thumbnails) < 2:
        return {}
    stacked = np.stack(thumbnails).astype(np.float64)
    squares = (stacked ** 2).sum(axis=1)
    distance = (squares[:, None] + squares[None] - 2 * stacked @ stacked.T) / stacked.shape[1]
    close = np.tril(distance <= DUPLICATE_RMS ** 2, k=-1)
    groups: dict[int, list[int]] = {}
    for i in np.flatnonzero(close.any(axis=1)):
        groups.setdefault(int(np.argmax(close[i])), []).append(int(i))
    kept = {first: min([first, *copies], key=lambda i: (len(stems[i]), i)) for first, copies in groups.items()}
    return {i: kept[first] for first, copies in groups.items() for i in [first, *copies] if i != kept[first]}


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
        folders = [split_folder(scene, split) for split in DATASET_SPLITS]
        return [p for folder in folders if folder is not None and folder.is_dir()
                for p in sorted(f for f in folder.iterdir() if f.is_file() and not f.name.startswith("."))]
    photos, folder = [p for p, _ in scene_photos(scene, "none")], photo_folder(scene)
    if photos and nsvf_splits(folder, [p.name for p in photos]):  # every split's photos, whichever is held out
        return sorted(f for f in folder.iterdir() if f.is_file() and not f.name.startswith("."))
    return photos


def twins(photos: list[Path]) -> dict[Path, str]:
    """The files among `photos` that stand beside another photo of their name in the same folder and are not read,
    each with what it is (a key of TWIN_WORDS): a RAW file beside the photo the camera developed from it (a RAW of
    its stem beside a JPEG or HEIC); a photo's masked copy or mask (its stem with a tail of DERIVED_TAILS)."""
    developed = {(p.parent, p.stem.lower()) for p in photos
                 if p.suffix.lower() in IMAGE_SUFFIXES and p.suffix.lower() not in RAW_SUFFIXES}
    found = {p: "raw" for p in photos if p.suffix.lower() in RAW_SUFFIXES and (p.parent, p.stem.lower()) in developed}
    for p in photos:
        tail = next((t for t in DERIVED_TAILS if p.stem.lower().endswith(t)), None)
        if tail and p.suffix.lower() in IMAGE_SUFFIXES and (p.parent, p.stem.lower()[:-len(tail)]) in developed:
            found[p] = DERIVED_TAILS[tail]
    return found


def twin_words(found: dict[Path, str]) -> str:
    """What `twins` left out, in words for ingest's summary ("" where nothing)."""
    counts = Counter(found.values())
    return ", ".join(f"{counts[kind]} {words}" for kind, words in TWIN_WORDS.items() if counts[kind])


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
        # Decoded from its bytes: OpenCV takes a path as UTF-8, and crashes on one that is not (a name from another
        # system's encoding).
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
