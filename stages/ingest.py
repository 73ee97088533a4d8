"""Ingest: a folder of photos (or a video) -> 8-bit RGB PNGs, upright, downscaled, scored for sharpness.

Writes ingest/images/<name>.png, ingest/masks/<name>.png (only for images with alpha) and
ingest/images.json listing every kept image with its original size, scale and sharpness.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, ImageOps

from pipeline.config import require
from plenoxels.errors import UserError
from pipeline.io import write_json, write_png

NAME = "ingest"
DEPENDS: tuple[str, ...] = ()
VERSION = 1

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".webp", ".heic", ".heif"}
VIDEO_SUFFIXES = {".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v"}
SHARPNESS_SIDE = 512  # score every image at the same size so scores compare across resolutions

try:  # HEIC support comes from pillow-heif when it is installed
    from pillow_heif import register_heif_opener

    register_heif_opener()
except ImportError:
    IMAGE_SUFFIXES -= {".heic", ".heif"}


@dataclass
class Settings:
    max_side: int = 960                # downscale so the longest side is at most this; 0 keeps full size
    drop_blurry_fraction: float = 0.0  # drop this share of the blurriest images (0 keeps all)
    video_fps: float = 2.0             # frames kept per second of video: the sharpest in each window
    min_images: int = 3

    def check(self) -> None:
        require(self.max_side == 0 or self.max_side >= 32, "ingest.max_side must be 0 (full size) or at least 32")
        require(0.0 <= self.drop_blurry_fraction < 1.0, "ingest.drop_blurry_fraction must be in [0, 1)")
        require(self.video_fps > 0, "ingest.video_fps must be positive")
        require(self.min_images >= 3, "ingest.min_images must be at least 3 (fewer cannot be posed)")


def fingerprint(scene: Path) -> list:
    files = [scene] if scene.is_file() else sorted(p for p in scene.iterdir() if p.is_file())
    return [[p.name, p.stat().st_size, p.stat().st_mtime_ns] for p in files]


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image at a fixed size: higher is sharper."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    scale = SHARPNESS_SIDE / max(grey.shape)
    if scale < 1:
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def _to_uint8(array: np.ndarray) -> np.ndarray:
    if array.dtype == np.uint8:
        return array
    if array.dtype == np.uint16:
        return (array.astype(np.uint32) * 255 // 65535).astype(np.uint8)
    if np.issubdtype(array.dtype, np.floating):
        return (np.clip(array, 0, 1) * 255 + 0.5).astype(np.uint8)
    return np.clip(array, 0, 255).astype(np.uint8)


def _orient(array: np.ndarray, exif_orientation: int) -> np.ndarray:
    """Applies an EXIF orientation tag (1-8) to a pixel array, as a camera's viewer would."""
    ops = {2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
           5: lambda a: np.swapaxes(a, 0, 1), 6: lambda a: np.rot90(a, -1),
           7: lambda a: np.rot90(a, 1)[::-1], 8: lambda a: np.rot90(a, 1)}
    return np.ascontiguousarray(ops[exif_orientation](array)) if exif_orientation in ops else array


def load_photo(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Any supported photo -> (8-bit RGB [h,w,3], 8-bit alpha [h,w] or None), upright per its EXIF."""
    with Image.open(path) as im:
        orientation = im.getexif().get(0x0112, 1)
        mode = im.mode
        if mode in ("I;16", "I;16B", "I;16L", "I", "F"):
            grey = _to_uint8(np.asarray(im)) if mode != "I" else _to_uint8(np.asarray(im).astype(np.uint16))
            rgb, alpha = np.repeat(_orient(grey, orientation)[..., None], 3, axis=-1), None
            return rgb, alpha
        if mode not in ("RGB", "RGBA", "L", "LA", "P", "CMYK", "YCbCr", "I;16"):
            raise ValueError(f"unsupported pixel mode {mode}")
        wide = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.suffix.lower() in {".png", ".tif", ".tiff"} else None
        if wide is not None and wide.dtype == np.uint16 and wide.ndim == 3:
            # Pillow reads 16-bit colour as 8-bit by truncation; OpenCV keeps the full range.
            wide = cv2.cvtColor(wide, cv2.COLOR_BGRA2RGBA if wide.shape[2] == 4 else cv2.COLOR_BGR2RGB)
            pixels = _orient(_to_uint8(wide), orientation)
        else:
            im = ImageOps.exif_transpose(im)
            has_alpha = im.mode in ("RGBA", "LA") or (im.mode == "P" and "transparency" in im.info)
            pixels = np.asarray(im.convert("RGBA" if has_alpha else "RGB"))
    if pixels.shape[2] == 4:
        return np.ascontiguousarray(pixels[..., :3]), np.ascontiguousarray(pixels[..., 3])
    return np.ascontiguousarray(pixels), None


def _resize(image: np.ndarray, max_side: int) -> np.ndarray:
    scale = max_side / max(image.shape[:2]) if max_side else 1.0
    if scale >= 1.0:
        return image
    size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def _video_frames(path: Path, settings: Settings, report) -> list[tuple[str, np.ndarray]]:
    """Keeps the sharpest frame of each 1/video_fps-second window."""
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise UserError(f"cannot read video {path.name}; convert it to MP4 (H.264) or extract photos")
    fps = capture.get(cv2.CAP_PROP_FPS) or 30.0
    total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) or None
    window = max(1, round(fps / settings.video_fps))
    kept, best, index = [], None, 0
    with report.bar(total=total, desc=f"reading {path.name}") as bar:
        while True:
            ok, bgr = capture.read()
            if not ok:
                break
            rgb = _resize(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), settings.max_side)
            score = sharpness(rgb)
            if best is None or score > best[0]:
                best = (score, index, rgb)
            index += 1
            bar.update()
            if index % window == 0:
                kept.append((f"frame_{best[1]:06d}", best[2]))
                best = None
    if best is not None:
        kept.append((f"frame_{best[1]:06d}", best[2]))
    capture.release()
    return kept


def run(ctx) -> dict:
    s: Settings = ctx.settings
    images_dir = ctx.work / "images"
    masks_dir = ctx.work / "masks"
    images_dir.mkdir()
    records, unreadable = [], []

    def keep(name: str, source: str, rgb: np.ndarray, alpha: np.ndarray | None, original: tuple[int, int]) -> None:
        rgb = _resize(rgb, s.max_side)
        record = {"name": name, "file": f"images/{name}.png", "source": source, "width": rgb.shape[1],
                  "height": rgb.shape[0], "original_width": original[0], "original_height": original[1],
                  "scale": rgb.shape[1] / original[0], "sharpness": round(sharpness(rgb), 3), "mask": None}
        write_png(images_dir / f"{name}.png", rgb)
        if alpha is not None:
            masks_dir.mkdir(exist_ok=True)
            write_png(masks_dir / f"{name}.png", _resize(alpha, s.max_side))
            record["mask"] = f"masks/{name}.png"
        records.append(record)

    if ctx.scene.is_file():
        if ctx.scene.suffix.lower() not in VIDEO_SUFFIXES:
            raise UserError(f"{ctx.scene.name} is neither a folder of photos nor a video ({', '.join(sorted(VIDEO_SUFFIXES))})")
        for name, rgb in _video_frames(ctx.scene, s, ctx.report):
            keep(name, ctx.scene.name, rgb, None, (rgb.shape[1], rgb.shape[0]))
    else:
        candidates = sorted(p for p in ctx.scene.iterdir() if p.is_file() and not p.name.startswith("."))
        photos = [p for p in candidates if p.suffix.lower() in IMAGE_SUFFIXES]
        unreadable += [f"{p.name} (not a supported image type)" for p in candidates
                       if p.suffix.lower() not in IMAGE_SUFFIXES | {".json", ".npy", ".txt", ".md"}]
        stems = [p.stem for p in photos]
        for path in ctx.report.track(photos, desc="reading photos"):
            try:
                rgb, alpha = load_photo(path)
            except Exception as e:  # any decoder failure means the same thing to the user: this file is skipped
                unreadable.append(f"{path.name} ({str(e).splitlines()[0][:60] or type(e).__name__})")
                continue
            name = path.stem if stems.count(path.stem) == 1 else path.name.replace(".", "_")
            keep(name, path.name, rgb, alpha, (rgb.shape[1], rgb.shape[0]))
    if unreadable:
        ctx.report.warn(f"skipped {len(unreadable)} file(s) that are not readable photos: {'; '.join(unreadable)}")

    dropped = []
    if s.drop_blurry_fraction > 0 and records:
        n_drop = int(len(records) * s.drop_blurry_fraction)
        for record in sorted(records, key=lambda r: r["sharpness"])[:n_drop]:
            dropped.append(record["name"])
            (ctx.work / record["file"]).unlink()
            if record["mask"]:
                (ctx.work / record["mask"]).unlink()
        records = [r for r in records if r["name"] not in dropped]

    if len(records) < s.min_images:
        raise UserError(f"only {len(records)} usable image(s) in {ctx.scene}; at least {s.min_images} overlapping photos are needed")
    write_json(ctx.work / "images.json", {"images": records, "skipped": unreadable, "dropped_blurry": dropped})
    w, h = records[0]["width"], records[0]["height"]
    line = f"{len(records)} images at {w}x{h}"
    if dropped:
        line += f", dropped {len(dropped)} blurriest"
    if unreadable:
        line += f", skipped {len(unreadable)} unreadable"
    return {"line": line, "images": len(records), "skipped": len(unreadable), "dropped_blurry": len(dropped)}
