"""Evaluate: the fitted model on the held-out views, and a novel-view video.

Writes evaluate/metrics.json (PSNR and SSIM per held-out view and their means), evaluate/renders/,
evaluate/gt/ and evaluate/depth/ (PNG per held-out view; depth colour-mapped between its 2nd and 98th
percentile over the pixels the model covers, black where it covers nothing), evaluate/video.mp4 (an
orbit around the foreground for inward scenes, a spiral around the average camera for forward ones)
and evaluate/contact_sheet.png (ground truth | render | error, one row per held-out view).

Ground truth is the held-out photo resized to the evaluation scale, its mask (if any) composited onto
the fit's background colour exactly as the fit saw its training photos. SSIM is scikit-image's
structural_similarity (Gaussian-weighted, as in Wang et al. 2004) on RGB in [0, 1].
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import imageio.v2 as imageio
import numpy as np
import torch
from matplotlib import colormaps
from skimage.metrics import structural_similarity

from plenoxels.cameras import Intrinsics, look_at
from pipeline.config import require
from pipeline.io import read_json, write_json, write_png
from plenoxels.scene_model import SceneModel, psnr
from stages.fit import load_frame

NAME = "evaluate"
DEPENDS: tuple[str, ...] = ("normalize", "fit")
VERSION = 1
CODE = ("plenoxels",)

# Error images show |render - truth| (mean over channels) times this, so small errors are visible.
ERROR_GAIN = 4.0
DEPTH_PERCENTILES = (2.0, 98.0)
# Pixels at least this opaque count as covered in the depth maps.
DEPTH_MIN_OPACITY = 0.5
# Spiral path for forward scenes: LLFF's focus weighting and its margins on the depth bounds.
SPIRAL_FOCUS_WEIGHT = 0.75
SPIRAL_TURNS = 2


@dataclass
class Settings:
    scale: float | Literal["fit"] = "fit"   # held-out views are rendered at this share of their size; fit: the fit's image_scale
    max_views: int = 0                      # evaluate at most this many held-out views, spread evenly (0: all)
    video_frames: int = 60                  # 0: no video
    video_side: int = 240                   # longest side of the video frames, pixels
    video_fps: int = 24
    sheet_rows: int = 8                     # held-out views on the contact sheet (spread evenly)
    sheet_side: int = 200                   # longest side of each contact-sheet tile, pixels

    def check(self) -> None:
        require(self.scale == "fit" or 0 < float(self.scale) <= 1, "evaluate.scale must be 'fit' or a number in (0, 1]")
        require(self.max_views >= 0, "evaluate.max_views must be >= 0 (0: all held-out views)")
        require(self.video_frames >= 0 and self.video_fps >= 1, "evaluate.video_frames must be >= 0, video_fps >= 1")
        require(self.video_side >= 16, "evaluate.video_side must be at least 16 pixels")
        require(self.sheet_rows >= 1 and self.sheet_side >= 16, "evaluate.sheet_rows must be >= 1, sheet_side >= 16")


# ------------------------------------------------------------------------------------------------
# Metrics and pictures


def image_psnr(render: np.ndarray, truth: np.ndarray) -> float:
    """PSNR in dB between float RGB images in [0, 1]."""
    return psnr(float(np.mean((render.astype(np.float64) - truth.astype(np.float64)) ** 2)))


def image_ssim(render: np.ndarray, truth: np.ndarray) -> float:
    return float(structural_similarity(truth, render, channel_axis=-1, data_range=1.0, gaussian_weights=True,
                                       sigma=1.5, use_sample_covariance=False))


def to_uint8(image: np.ndarray) -> np.ndarray:
    return (np.clip(image, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)


def colour_depth(depth: np.ndarray, opacity: np.ndarray) -> np.ndarray:
    """uint8 RGB [h,w,3]: depth through the turbo colour map (near blue, far red), stretched
    between its percentiles over the covered pixels; uncovered pixels black."""
    covered = opacity >= DEPTH_MIN_OPACITY
    out = np.zeros(depth.shape + (3,), dtype=np.uint8)
    if not covered.any():
        return out
    lo, hi = np.percentile(depth[covered], DEPTH_PERCENTILES)
    scaled = np.clip((depth - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    rgb = colormaps["turbo"](scaled)[..., :3]
    out[covered] = to_uint8(rgb[covered])
    return out


def error_image(render: np.ndarray, truth: np.ndarray) -> np.ndarray:
    error = np.clip(np.abs(render - truth).mean(axis=-1) * ERROR_GAIN, 0.0, 1.0)
    return to_uint8(colormaps["magma"](error)[..., :3])


def _fit_to(image: np.ndarray, side: int) -> np.ndarray:
    import cv2

    scale = side / max(image.shape[:2])
    size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST)


def contact_sheet(rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]], side: int) -> np.ndarray:
    """uint8 image: one row per view of (ground truth | render | error) tiles, 4 px white gaps."""
    gap = 4
    tiles = [[_fit_to(t, side) for t in row] for row in rows]
    h = max(t.shape[0] for row in tiles for t in row)
    w = max(t.shape[1] for row in tiles for t in row)
    sheet = np.full((len(tiles) * (h + gap) + gap, 3 * (w + gap) + gap, 3), 255, dtype=np.uint8)
    for r, row in enumerate(tiles):
        for c, tile in enumerate(row):
            y, x = gap + r * (h + gap), gap + c * (w + gap)
            sheet[y:y + tile.shape[0], x:x + tile.shape[1]] = tile
    return sheet


# ------------------------------------------------------------------------------------------------
# Camera paths


def _median_intrinsics(frames: list[dict], side: int) -> Intrinsics:
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


def _spread(items: list, limit: int) -> list:
    if limit <= 0 or len(items) <= limit:
        return items
    return [items[i] for i in np.linspace(0, len(items) - 1, limit).round().astype(int)]


def run(ctx) -> dict:
    s: Settings = ctx.settings
    scene = read_json(ctx.upstream["normalize"] / "scene.json")
    model = SceneModel.load(ctx.upstream["fit"])
    fit_record = read_json(ctx.upstream["fit"] / "model.json")
    scale = float(fit_record.get("fit_settings", {}).get("image_scale", 1.0)) if s.scale == "fit" else float(s.scale)
    frames = scene.get("frames") or []
    held_out = _spread([f for f in frames if f.get("split") == "test"], s.max_views)
    train = [f for f in frames if f.get("split", "train") == "train"] or frames

    for folder in ("renders", "gt", "depth"):
        (ctx.work / folder).mkdir()
    views, sheet_rows = [], []
    sheet_names = {f["name"] for f in _spread(held_out, s.sheet_rows)}
    started = time.time()
    for frame in ctx.report.track(held_out, desc="rendering held-out views"):
        truth, k = load_frame(ctx.out, frame, scale, model.background_color)
        with torch.no_grad():
            out = model.render_camera(np.asarray(frame["transform_matrix"], dtype=np.float64), k)
        render = out["rgb"].cpu().numpy().astype(np.float32)
        views.append({"name": frame["name"], "width": k.w, "height": k.h,
                      "psnr": round(image_psnr(render, truth), 4), "ssim": round(image_ssim(render, truth), 5)})
        write_png(ctx.work / "renders" / f"{frame['name']}.png", to_uint8(render))
        write_png(ctx.work / "gt" / f"{frame['name']}.png", to_uint8(truth))
        write_png(ctx.work / "depth" / f"{frame['name']}.png",
                  colour_depth(out["depth"].cpu().numpy(), out["opacity"].cpu().numpy()))
        if frame["name"] in sheet_names:
            sheet_rows.append((to_uint8(truth), to_uint8(render), error_image(render, truth)))
    render_seconds = time.time() - started
    if sheet_rows:
        write_png(ctx.work / "contact_sheet.png", contact_sheet(sheet_rows, s.sheet_side))

    video = None
    if s.video_frames:
        path_kind = "spiral" if model.ndc is not None or scene.get("type") == "forward" else "orbit"
        path = (spiral_path if path_kind == "spiral" else orbit_path)(scene, train, s.video_frames)
        k = _median_intrinsics(train, s.video_side)
        # Even sizes: H.264 in yuv420p needs them.
        k = Intrinsics(k.fl_x, k.fl_y, k.cx - (k.w % 2) / 2, k.cy - (k.h % 2) / 2, k.w - k.w % 2, k.h - k.h % 2)
        with imageio.get_writer(ctx.work / "video.mp4", fps=s.video_fps, codec="libx264", quality=7,
                                macro_block_size=1) as writer:
            for c2w in ctx.report.track(path, desc=f"rendering the {path_kind} video"):
                with torch.no_grad():
                    writer.append_data(to_uint8(model.render_camera(c2w, k)["rgb"].cpu().numpy()))
        video = {"file": "video.mp4", "path": path_kind, "frames": s.video_frames, "width": k.w, "height": k.h,
                 "fps": s.video_fps}

    mean = ({"psnr": round(float(np.mean([v["psnr"] for v in views])), 4),
             "ssim": round(float(np.mean([v["ssim"] for v in views])), 5)} if views else None)
    write_json(ctx.work / "metrics.json", {"views": views, "mean": mean, "scale": scale, "count": len(views),
                                           "render_seconds": round(render_seconds, 2), "video": video,
                                           "ssim": "skimage.metrics.structural_similarity, gaussian, data_range 1"})
    if mean:
        line = (f"PSNR {mean['psnr']:.2f} dB, SSIM {mean['ssim']:.3f} on {len(views)} held-out views "
                f"at {views[0]['width']}x{views[0]['height']}")
    else:
        line = "no held-out views to score (normalize.holdout_every=0)"
    if video:
        line += f"; {video['path']} video of {video['frames']} frames"
    return {"line": line, "views": len(views), "psnr": mean["psnr"] if mean else None,
            "ssim": mean["ssim"] if mean else None}
